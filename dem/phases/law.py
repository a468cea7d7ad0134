"""One phase chain for a library of runs: every rate a log-linear law of the operating point.

A per-run fit (:mod:`dem.phases.estimator`) has a rate per move, phase and compartment,
about 550 numbers a run, and they are not a function of anything: between two speeds the
phases change meaning and a rate-by-rate blend mixes unlike phases. Here one chain is
fitted to every particle of every run of a library at once. Its K phases are the same in
every run, and each rate of a run's chain is a law of the compartment's covariates:

    log q_f(run, c) = x(run, c) . beta_f

for every rate family f: the phase-keeping moves ``"<direction>/<h>"`` and the switches
``"switch/<h>/<g>"`` (the keys of :func:`coupling.phases.transitions`), and x(run, c) the
covariates of compartment c of that run (:class:`LawRun`: a constant first, then any
columns the caller builds, e.g. log impeller speed, position from inlet to weir, the blade
section's orientation, the compartment's fill). The parameters are the K (K + 3) vectors
beta_f and the feeders' entry phases, shared by every run: tens, not hundreds a run. A run
at an operating point the library never ran has its chain from its covariates
(:meth:`PhaseLaw.chain`), on its own grid: runs may differ in length and slice count.

EM (generalised): the E-step is the forward-backward pass of :mod:`dem.phases.kernels`
on each run's chain, which gives the expected (compartment, phase) transitions per dump
interval; from them, the expected number of jumps J and the expected time D in the source
state of every move, given both ends of every interval (one Frechet derivative,
:func:`dem.rates.log_likelihood`, as in :func:`dem.phases.estimator._ctmc_em_steps`).
The M-step maximises sum J (x . beta) - D exp(x . beta) over each family's beta, the
moves of every run pooled: a Poisson regression with offset log D, concave, solved by
damped Newton steps. The feeders' entry phases are the pooled posterior entry phases; the
particles already inside when a run's window opens keep initial phases of their own run.
The fit stops when an iteration gains less than ``tol`` nats per particle-step.

Phases are ordered by mobility, slowest first: by the forward rate of the constant alone
(the law's phase at covariates 0 besides the constant).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.linalg import expm

from coupling import phases as phase_model
from coupling.blas import single_threaded_blas
from coupling.errors import ConfigError
from coupling.phases import PhaseTransport
from dem import rates as rate_fit
from dem.phases import diagnostics
from dem.phases.chain import initial_distribution
from dem.phases.data import PhaseData
from dem.phases.kernels import forward_backward

#: the log of the fastest rate a law's chain holds: beyond :data:`coupling.phases.MAX_RATE_PER_S`
#: a move is instantaneous at any dump interval. A family whose moves are all but never
#: seen (the slowest phase's backward moves) drifts towards rate 0 with coefficients that
#: grow without bound (hundreds), so its predictor is a steep quadratic in position whose
#: peak another run's covariates can lift past the bound; the rate is held there instead
#: of making the chain invalid
LOG_MAX_RATE = math.log(phase_model.MAX_RATE_PER_S) - 1e-9  # exp() of it within the bound
#: that rate [/s]
MAX_LAW_RATE = math.exp(LOG_MAX_RATE)


def law_rates(predictor: np.ndarray) -> np.ndarray:
    """exp(``predictor``), the rates of a family's linear predictor x . beta, held at
    :data:`MAX_LAW_RATE`."""
    return np.exp(np.minimum(predictor, LOG_MAX_RATE))


#: damped Newton steps of one M-step: the regression is concave and starts from the last
#: M-step's answer, so a few steps reach its maximum to far below the EM's tolerance
NEWTON_STEPS = 10
#: the largest change of a coefficient in one Newton step: a family whose moves are never
#: seen drifts towards rate 0 instead of jumping there
MAX_NEWTON_STEP = 2.0
#: ridge on the Newton matrix: keeps it invertible where a family's rates went to 0
NEWTON_RIDGE = 1e-9
#: the starting phases' rates are the one-phase law's times these (slowest first) and
#: every phase switches to every other at this rate [1/s]
START_FACTORS = (0.3, 3.0)
START_SWITCHING_PER_S = 0.2
#: the one-phase law's EM iterations before the phases split from it
ONE_PHASE_ITERATIONS = 30
#: the fit's stopping gain [nats per particle-step]. Far below the per-run fit's
#: (:data:`dem.phases.settings.PHASE_TOL`): the switching coefficients converge slowly,
#: and on a synthetic library of three runs (tests/dem/test_phase_law.py) stopping at 1e-5
#: left the switching's speed exponents at 0 against a true 0.5 and 0.3; at 1e-9 they are
#: recovered within sampling error (139 iterations)
LAW_TOL = 1e-9
LAW_MAX_ITERATIONS = 2000


@dataclass(frozen=True)
class LawRun:
    """One run of a library: its sequences (:class:`dem.phases.PhaseData`, any grid) and
    the law's covariates of each of its compartments, ``covariates`` (S, P): row c for
    compartment c = i * NY + j, column 0 the constant 1."""

    data: PhaseData
    covariates: np.ndarray
    name: str = ""

    def __post_init__(self) -> None:
        x = np.asarray(self.covariates, dtype=float)
        label = self.name or "a run"
        if x.ndim != 2 or x.shape[0] != self.data.n_cells or x.shape[1] < 1:
            raise ConfigError(
                f"covariates of {label} have shape {x.shape}; expected (S, P) = ({self.data.n_cells}, P >= 1), "
                "one row per compartment of its grid"
            )
        if not np.all(np.isfinite(x)):
            raise ConfigError(f"covariates of {label} hold {x[~np.isfinite(x)][0]!r}; expected finite numbers")
        if not np.all(x[:, 0] == 1.0):
            raise ConfigError(f"covariates of {label}: column 0 must be the constant 1 (the law's intercept)")
        object.__setattr__(self, "covariates", x)


@dataclass(frozen=True)
class PhaseLaw:
    """The fitted law (module docstring): ``coefficients`` maps each rate family to its
    (P,) vector; ``entry`` (2, K) the feeders' entry phases; ``covariate_names`` (P,)."""

    n_phases: int
    coefficients: dict[str, np.ndarray]
    entry: np.ndarray
    covariate_names: tuple[str, ...]
    log_likelihood: float
    n_steps: int
    iterations: int
    converged: bool
    wall_time_s: float = 0.0

    @property
    def n_parameters(self) -> int:
        """Free parameters: every coefficient and the entry rows' K - 1 each."""
        return int(sum(b.size for b in self.coefficients.values()) + 2 * (self.n_phases - 1))

    def chain(self, covariates: np.ndarray, nx: int, ny: int, interval_s: float) -> PhaseTransport:
        """The law's chain on an ``nx`` x ``ny`` grid whose compartments have
        ``covariates`` (NX * NY, P): a run of the library, or one it never ran."""
        return law_chain(self.coefficients, self.entry, covariates, nx, ny, self.n_phases, interval_s)

    def run_chain(self, run: LawRun) -> PhaseTransport:
        return self.chain(run.covariates, run.data.nx, run.data.ny, run.data.interval_s)

    def record(self) -> dict:
        """The law as JSON-able numbers (:meth:`from_record` reads it back)."""
        return {
            "n_phases": self.n_phases,
            "covariate_names": list(self.covariate_names),
            "coefficients": {key: value.tolist() for key, value in sorted(self.coefficients.items())},
            "entry": self.entry.tolist(),
            "log_likelihood": self.log_likelihood,
            "n_steps": self.n_steps,
            "iterations": self.iterations,
            "converged": self.converged,
            "wall_time_s": self.wall_time_s,
        }

    @classmethod
    def from_record(cls, record: dict, source: str = "a law record") -> PhaseLaw:
        """The law of :meth:`record`; raises ConfigError naming ``source`` and the first bad field."""
        try:
            k = int(record["n_phases"])
            names = tuple(str(n) for n in record["covariate_names"])
            coefficients = {str(key): np.asarray(v, dtype=float) for key, v in dict(record["coefficients"]).items()}
            entry = np.asarray(record["entry"], dtype=float)
            law = cls(
                k,
                coefficients,
                entry,
                names,
                float(record["log_likelihood"]),
                int(record["n_steps"]),
                int(record["iterations"]),
                bool(record["converged"]),
                float(record.get("wall_time_s", 0.0)),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise ConfigError(f"{source}: not a phase law ({type(exc).__name__}: {exc})") from None
        if k < 1 or entry.shape != (2, k) or not np.all(np.isfinite(entry)) or np.any(entry < 0):
            raise ConfigError(
                f"{source}: entry phases of shape {entry.shape}; expected (2, {max(k, 1)}) of finite values >= 0"
            )
        for key, beta in coefficients.items():
            if beta.shape != (len(names),) or not np.all(np.isfinite(beta)):
                raise ConfigError(
                    f"{source}: coefficients {key!r} have shape {beta.shape} or non-finite values; "
                    f"expected {len(names)} finite numbers, one per covariate {list(names)}"
                )
        return law

    def score(self, runs: LawRun | Sequence[LawRun]) -> float:
        """Log-likelihood [nats] of ``runs`` under the law (a held-out run's, say); the
        particles inside when a run's window opens start in the chain's steady phases."""
        runs = _as_runs(runs, len(self.covariate_names))
        return float(sum(diagnostics.log_likelihood(self.run_chain(run), run.data) for run in runs))


def law_chain(
    coefficients: dict[str, np.ndarray],
    entry: np.ndarray,
    covariates: np.ndarray,
    nx: int,
    ny: int,
    n_phases: int,
    interval_s: float,
) -> PhaseTransport:
    """The chain of the law ``coefficients`` on a grid with ``covariates`` (NX * NY, P)."""
    x = np.asarray(covariates, dtype=float)
    values = {}
    for name, (_src, _dst, comp) in phase_model.transitions(nx, ny, n_phases).items():
        if name in coefficients:
            values[name] = law_rates(x[comp] @ coefficients[name])
        elif comp.size:
            raise ConfigError(
                f"the law has no rate for the moves {name!r} of a {nx}x{ny} grid: it was fitted on runs without "
                f"them; valid grids have moves of {sorted(coefficients)} only"
            )
        else:
            values[name] = np.zeros(0)
    return phase_model.from_move_rates(values, nx, ny, n_phases, entry, interval_s)


def _kinds(runs: tuple[LawRun, ...], k: int) -> list[str]:
    """The rate families with moves on some run's grid: the law's (an axial library has no
    transverse ones)."""
    names = {
        name
        for run in runs
        for name, (src, _dst, _comp) in phase_model.transitions(run.data.nx, run.data.ny, k).items()
        if src.size
    }
    return [name for name in phase_model.transitions(2, 2, k) if name in names]


def _as_runs(runs: LawRun | Sequence[LawRun], n_covariates: int | None = None) -> tuple[LawRun, ...]:
    out = (runs,) if isinstance(runs, LawRun) else tuple(runs)
    if not out:
        raise ConfigError("no run to fit: expected a LawRun or a non-empty list of them")
    for n, run in enumerate(out):
        if not isinstance(run, LawRun):
            raise ConfigError(f"run {n} is a {type(run).__name__}: expected dem.phases.law.LawRun")
    widths = {run.covariates.shape[1] for run in out} | ({n_covariates} if n_covariates else set())
    if len(widths) != 1:
        raise ConfigError(f"the runs' covariates have {sorted(widths)} columns: one law needs the same P for all")
    return out


def _expected_moves(model: PhaseTransport, counts: np.ndarray, interval_s: float) -> dict[str, tuple]:
    """Per rate family, (expected jumps, expected time in the source state) of each move
    over the data's intervals, given both ends of every interval (module docstring)."""
    q = model.generator()
    _value, d_q = rate_fit.log_likelihood(q, counts, interval_s)
    out = {}
    for name, (src, dst, _comp) in phase_model.transitions(model.nx, model.ny, model.n_phases).items():
        out[name] = (np.maximum(q[src, dst] * d_q[src, dst], 0.0), np.maximum(d_q[src, src], 0.0))
    return out


def poisson_regression(beta: np.ndarray, x: np.ndarray, jumps: np.ndarray, dwell: np.ndarray) -> np.ndarray:
    """The beta that maximises sum jumps (x . beta) - dwell exp(x . beta), from ``beta``:
    damped Newton steps (:data:`NEWTON_STEPS`, each coefficient moved by at most
    :data:`MAX_NEWTON_STEP`)."""
    beta = np.array(beta, dtype=float)
    for _ in range(NEWTON_STEPS):
        mu = dwell * law_rates(x @ beta)
        gradient = x.T @ (jumps - mu)
        information = (x * mu[:, None]).T @ x + NEWTON_RIDGE * np.eye(beta.size)
        step = np.linalg.solve(information, gradient)
        biggest = float(np.max(np.abs(step), initial=0.0))
        if biggest > MAX_NEWTON_STEP:
            step *= MAX_NEWTON_STEP / biggest
        beta += step
        if biggest < 1e-10:
            break
    return beta


def _m_step(
    coefficients: dict[str, np.ndarray], runs: tuple[LawRun, ...], models: list[PhaseTransport], counts: list
) -> dict[str, np.ndarray]:
    """Every family's coefficients refitted to the expected moves of all runs pooled."""
    pooled: dict[str, list[tuple]] = {name: [] for name in coefficients}
    for run, model, c in zip(runs, models, counts):
        moves = _expected_moves(model, c, run.data.interval_s)
        families = phase_model.transitions(run.data.nx, run.data.ny, model.n_phases)
        for name, (jumps, dwell) in moves.items():
            if name in pooled:
                pooled[name].append((run.covariates[families[name][2]], jumps, dwell))
    out = {}
    for name, parts in pooled.items():
        if not parts or sum(p[0].shape[0] for p in parts) == 0:
            out[name] = coefficients[name]
            continue
        x, jumps, dwell = (np.concatenate([p[i] for p in parts]) for i in range(3))
        out[name] = poisson_regression(coefficients[name], x, jumps, dwell)
    return out


def _shared_entry(entries: list[np.ndarray], previous: np.ndarray) -> np.ndarray:
    """The feeders' entry phases from the posterior entry phases pooled over the runs; a
    feeder no run fed keeps ``previous``."""
    feed = np.sum([e[:2] for e in entries], axis=0)
    sums = feed.sum(axis=1, keepdims=True)
    return np.where(sums > 0, feed / np.maximum(sums, 1e-300), previous)


def _residents(initial: np.ndarray, entry_rows: np.ndarray) -> np.ndarray:
    """A run's initial phases of the particles inside when its window opened, from their
    posterior (rows without particles keep theirs)."""
    sums = entry_rows.sum(axis=1, keepdims=True)
    return np.where(sums > 0, entry_rows / np.maximum(sums, 1e-300), initial)


def _em(
    coefficients: dict[str, np.ndarray],
    entry: np.ndarray,
    runs: tuple[LawRun, ...],
    k: int,
    max_iterations: int,
    tol: float,
) -> tuple[dict[str, np.ndarray], np.ndarray, float, int, bool]:
    """EM from ``coefficients`` and ``entry`` until an iteration gains less than ``tol``
    nats per particle-step: (coefficients, entry, log-likelihood, iterations, converged)."""
    n_steps = max(sum(run.data.n_steps for run in runs), 1)
    residents = [None] * len(runs)
    previous, log_likelihood, iteration = -math.inf, -math.inf, 0
    for iteration in range(1, max_iterations + 1):  # noqa: B007 -- the count is returned
        models = [
            law_chain(coefficients, entry, r.covariates, r.data.nx, r.data.ny, k, r.data.interval_s) for r in runs
        ]
        # the residents start in the chain's steady phases, then in their own posterior
        starts = [
            initial_distribution(m, r.data) if rows is None else np.vstack([entry, rows])
            for m, r, rows in zip(models, runs, residents)
        ]
        expected = [
            forward_backward(expm(m.generator() * r.data.interval_s), start, r.data, k)
            for m, r, start in zip(models, runs, starts)
        ]
        log_likelihood = float(sum(e.log_likelihood for e in expected))
        if (log_likelihood - previous) / n_steps < tol:
            return coefficients, entry, log_likelihood, iteration, True
        previous = log_likelihood
        entry = _shared_entry([e.entry for e in expected], entry)
        residents = [_residents(start[2:], e.entry[2:]) for start, e in zip(starts, expected)]
        counts = []
        for e in expected:
            c = np.array(e.counts, dtype=float)
            c[-1] = 0.0
            counts.append(c)
        coefficients = _m_step(coefficients, runs, models, counts)
    return coefficients, entry, previous, iteration, False


def _one_phase_start(runs: tuple[LawRun, ...]) -> dict[str, np.ndarray]:
    """Every family of the one-phase law at the log of its pooled one-jump rate (the
    constant alone), the EM's start."""
    width = runs[0].covariates.shape[1]
    hits: dict[str, list[float]] = {}
    for run in runs:
        counts = run.data.counts().astype(float)
        naive = rate_fit.naive_rates(counts, run.data.nx, run.data.ny, run.data.interval_s)
        for key, (_src, _dst, comp) in phase_model.transitions(run.data.nx, run.data.ny, 1).items():
            rates = naive[key.split("/")[0]].ravel()[comp]
            hits.setdefault(key, []).extend(rates[np.isfinite(rates)].tolist())
    out = {}
    for key in _kinds(runs, 1):
        rates = np.asarray(hits.get(key, []), dtype=float)
        level = float(np.mean(rates)) if rates.size else 0.0
        out[key] = np.concatenate([[math.log(max(level, 1e-3))], np.zeros(width - 1)])
    return out


def _split(one: dict[str, np.ndarray], runs: tuple[LawRun, ...], k: int) -> dict[str, np.ndarray]:
    """The one-phase law split into ``k`` phases (module constants :data:`START_FACTORS`,
    :data:`START_SWITCHING_PER_S`)."""
    factors = np.geomspace(*START_FACTORS, k) if k > 1 else np.ones(1)
    width = next(iter(one.values())).size
    out = {}
    for key in _kinds(runs, k):
        parts = key.split("/")
        if parts[0] == "switch":
            out[key] = np.concatenate([[math.log(START_SWITCHING_PER_S)], np.zeros(width - 1)])
        else:
            beta = one[f"{parts[0]}/0"].copy()
            beta[0] += math.log(factors[int(parts[1])])
            out[key] = beta
    return out


def _ordered(coefficients: dict[str, np.ndarray], entry: np.ndarray, k: int) -> tuple[dict, np.ndarray]:
    """The phases relabelled slowest first (by the forward rate of the constant alone)."""
    order = np.argsort([coefficients[f"x_pos/{h}"][0] for h in range(k)], kind="stable")
    new = {int(old): n for n, old in enumerate(order)}
    out = {}
    for key, beta in coefficients.items():
        parts = key.split("/")
        if parts[0] == "switch":
            out[f"switch/{new[int(parts[1])]}/{new[int(parts[2])]}"] = beta
        else:
            out[f"{parts[0]}/{new[int(parts[1])]}"] = beta
    return out, entry[:, order]


@single_threaded_blas()
def fit_law(
    runs: LawRun | Sequence[LawRun],
    n_phases: int,
    covariate_names: Sequence[str] | None = None,
    max_iterations: int = LAW_MAX_ITERATIONS,
    tol: float = LAW_TOL,
    start: PhaseLaw | None = None,
) -> PhaseLaw:
    """The :class:`PhaseLaw` of ``n_phases`` phases fitted to every particle of ``runs``
    (module docstring); from ``start`` when given (a law fitted to a library these runs
    are most of: leaving one run out then takes a fraction of the iterations), else from
    the one-phase law split. Raises ConfigError for no runs, covariates of different
    widths, ``n_phases`` < 1, or a ``start`` of other phases or covariates."""
    wall0 = time.perf_counter()
    runs = _as_runs(runs)
    if isinstance(n_phases, bool) or int(n_phases) != n_phases or n_phases < 1:
        raise ConfigError(f"n_phases must be an integer >= 1, got {n_phases!r}")
    k, width = int(n_phases), runs[0].covariates.shape[1]
    names = tuple(covariate_names) if covariate_names is not None else ("1",) + tuple(f"x{i}" for i in range(1, width))
    if len(names) != width:
        raise ConfigError(f"{len(names)} covariate names for {width} covariates: expected one name per column")
    if start is not None:
        missing = sorted(set(_kinds(runs, k)) - set(start.coefficients))
        if start.n_phases != k or start.covariate_names != names or missing:
            raise ConfigError(
                f"a start law of {start.n_phases} phases on {list(start.covariate_names)} (lacking {missing}) "
                f"cannot start a fit of {k} phases on {list(names)}"
            )
        coefficients, entry = {key: start.coefficients[key].copy() for key in _kinds(runs, k)}, start.entry.copy()
    else:
        one, entry1, _ll, _it, _ok = _em(_one_phase_start(runs), np.ones((2, 1)), runs, 1, ONE_PHASE_ITERATIONS, tol)
        coefficients, entry = _split(one, runs, k), np.full((2, k), 1.0 / k)
        if k == 1:
            coefficients, entry = one, entry1
    coefficients, entry, log_likelihood, iterations, converged = _em(coefficients, entry, runs, k, max_iterations, tol)
    coefficients, entry = _ordered(coefficients, entry, k)
    return PhaseLaw(
        k,
        coefficients,
        entry,
        names,
        log_likelihood,
        sum(run.data.n_steps for run in runs),
        iterations,
        converged,
        time.perf_counter() - wall0,
    )
