"""The phase fit as an estimator: ``PhaseEstimator(settings).fit(data).fetch_model()``
returns a :class:`PhaseFit`, the fitted chain with its diagnostics.

``data`` is one run (:class:`dem.phases.PhaseData`) or several on the same grid and
observation interval: a joint fit of one chain to all of them. The EM is then the EM of
the pooled data: the E-step runs over every run's particles, the M-step sums their
expected transitions (and so the expected jumps and dwell times); the feeders' entry
phases are shared, while each run's particles already inside when its window opens keep
initial phases of their own (the runs' windows open on different states). A joint fit of
one run is that run's fit, to the last bit.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import expm

from coupling import phases as phase_model
from coupling.blas import single_threaded_blas
from coupling.errors import ConfigError
from coupling.phases import PhaseTransport
from dem import rates as rate_fit
from dem.phases import diagnostics
from dem.phases.chain import initial_distribution, refinement, steady_occupancy
from dem.phases.data import PhaseData, as_runs, first_compartments
from dem.phases.diagnostics import CkTest
from dem.phases.kernels import forward_backward
from dem.phases.settings import PhaseSettings

#: L-BFGS iterations of the one-phase start (:func:`one_phase`)
ONE_PHASE_ITERATIONS = 2000


@dataclass(frozen=True)
class PhaseFit:
    """A fitted hidden-phase chain and how the fit went.

    ``transport``: the model (:class:`coupling.phases.PhaseTransport`, phases slowest
    first); ``log_likelihood`` [nats] of the training data; ``n_particles``, ``n_steps``
    (particle-steps) of the training data; ``iterations`` (EM) and ``converged`` of the
    best start; ``start_log_likelihoods``: the final log-likelihood of every start (their
    spread says how multimodal the likelihood is); ``wall_time_s`` of the whole fit;
    ``occupancy`` (K, NX, NY): the expected time the data spent in each phase and
    compartment [particle-intervals]; ``n_runs``: the runs fitted jointly; ``settings``:
    those of the fit (None for a model made otherwise).
    """

    transport: PhaseTransport
    log_likelihood: float
    n_particles: int
    n_steps: int
    iterations: int
    converged: bool
    start_log_likelihoods: tuple[float, ...] = ()
    wall_time_s: float = float("nan")
    occupancy: np.ndarray = field(default_factory=lambda: np.zeros(0))
    n_runs: int = 1
    settings: PhaseSettings | None = None

    @property
    def n_phases(self) -> int:
        return self.transport.n_phases

    @property
    def interval_s(self) -> float:
        return self.transport.interval_s

    def generator(self) -> np.ndarray:
        """Q (S*K+1, S*K+1) [1/s], row = from; last state discharged."""
        return self.transport.generator()

    def entry_distribution(self) -> np.ndarray:
        """(2, K): probability of entering in each phase, feed A and feed B."""
        return self.transport.entry

    def initial_distribution(self, data: PhaseData) -> np.ndarray:
        """(2 + S, K): :func:`initial_distribution` of this model for ``data``."""
        return initial_distribution(self.transport, data)

    def n_parameters(self) -> int:
        """Free parameters: every allowed move's rate and K-1 entry probabilities per feeder."""
        moves = phase_model.transitions(self.transport.nx, self.transport.ny, self.n_phases)
        return int(sum(src.size for src, _dst, _c in moves.values()) + 2 * (self.n_phases - 1))

    def score(self, data: PhaseData | Sequence[PhaseData]) -> float:
        """Log-likelihood [nats] of ``data`` (one run or several, e.g. held out) under this model."""
        return diagnostics.log_likelihood(self.transport, data)

    def implied_timescales(self, count: int = 5) -> np.ndarray:
        """:func:`dem.phases.diagnostics.implied_timescales` of the chain [s], longest first."""
        return diagnostics.implied_timescales(self.transport, count)

    def steady_occupancy(self, data: PhaseData) -> np.ndarray:
        """(S, K): expected particles in each (compartment, phase) at steady state for a
        feed of one particle per second entering where ``data``'s particles were first seen,
        in the entry phases [particles per (particle/s)]."""
        return steady_occupancy(self.transport, first_compartments(data))

    def chapman_kolmogorov(
        self, data: PhaseData | Sequence[PhaseData], lags: tuple[int, ...] = (10, 20, 50, 100), z_limit: float = 4.0
    ) -> CkTest:
        """:class:`dem.phases.CkTest` at ``lags`` (in dumps) on the particle-dumps of ``data``
        (one run or several)."""
        return diagnostics.chapman_kolmogorov(self.transport, data, lags, z_limit)


def _move_rates(model: PhaseTransport) -> dict[str, np.ndarray]:
    """The rate of every move of :func:`coupling.phases.transitions`, read off ``model``."""
    q = model.generator()
    return {
        name: q[src, dst]
        for name, (src, dst, _c) in phase_model.transitions(model.nx, model.ny, model.n_phases).items()
    }


def _initial(
    base: PhaseTransport,
    k: int,
    rng: np.random.Generator | None,
    max_rate_x_interval: float,
) -> PhaseTransport:
    """A K-phase start from the one-phase fit ``base`` (:mod:`dem.phases`, "Starts")."""
    nx, ny = base.nx, base.ny
    if rng is None:
        factors = np.geomspace(0.3, 3.0, k) if k > 1 else np.ones(1)
        switch = np.full((k, k), 0.2)
        entry = np.full(k, 1.0 / k)
    else:
        factors = np.sort(np.exp(rng.normal(0.0, 0.8, k)))
        switch = np.exp(rng.uniform(np.log(0.02), np.log(1.0), (k, k)))
        entry = rng.dirichlet(np.ones(k))
    rates = np.stack([base.rates[0] * f for f in factors])
    if rng is not None:
        rates = rates * np.exp(rng.normal(0.0, 0.1, rates.shape))
    switching = np.broadcast_to(switch[:, :, None, None], (k, k, nx, ny)).copy()
    switching[np.arange(k), np.arange(k)] = 0.0
    cap = max_rate_x_interval / base.interval_s
    return PhaseTransport(np.minimum(rates, cap), switching, np.stack([entry, entry]), base.interval_s)


def _stagnant_projection(moves: dict, exit_max: float):
    """The constraints of a stagnant phase 0 on the rates of ``moves`` (their order): it
    makes no move, and leaves each compartment at ``exit_max`` [1/s] at most in all. The
    update of each rate is the maximiser of jumps log r - r dwell, separately, so under
    a bound on their sum the rates leaving one compartment are scaled down together."""
    names = list(moves)
    bounds = np.cumsum([0] + [moves[name][0].size for name in names])
    span = {name: slice(int(a), int(b)) for name, a, b in zip(names, bounds[:-1], bounds[1:])}
    still = [span[n] for n in names if not n.startswith("switch/") and n.endswith("/0")]
    leave = [span[n] for n in names if n.startswith("switch/0/")]

    def project(rates: np.ndarray) -> np.ndarray:
        rates = rates.copy()
        for part in still:
            rates[part] = 0.0
        if leave:
            total = np.sum([rates[part] for part in leave], axis=0)
            scale = np.minimum(1.0, exit_max / np.maximum(total, 1e-300))
            for part in leave:
                rates[part] *= scale
        return rates

    return project


def _with_stagnant(mobile: PhaseTransport, exit_max: float) -> PhaseTransport:
    """A start with a stagnant phase 0 before the phases of ``mobile``: no moves, entered
    from every other phase at 1e-3 /s, left at half of ``exit_max`` in all, never entered
    from the feed."""
    k = mobile.n_phases + 1
    rates = np.concatenate([np.zeros((1,) + mobile.rates.shape[1:]), mobile.rates])
    switching = np.zeros((k, k, mobile.nx, mobile.ny))
    switching[1:, 1:] = mobile.switching
    switching[1:, 0] = 1e-3
    switching[0, 1:] = 0.5 * exit_max / (k - 1)
    entry = np.concatenate([np.zeros((2, 1)), mobile.entry], axis=1)
    return PhaseTransport(rates, switching, entry, mobile.interval_s)


def refined(model: PhaseTransport, refine: int) -> PhaseTransport:
    """``model`` on ``refine`` slices per slice (NY = 1): each slice's moves at ``refine``
    times its rates, so that a particle crosses a slice as fast as before, and no backward
    move out of the first sub-slice; switching and entry as they were. A start for
    :attr:`PhaseSettings.refine`, not a model of its own: the EM refits every rate."""
    if model.ny != 1 or refine < 1:
        raise ValueError(f"refine {refine!r} of a {model.nx}x{model.ny} model: expected NY = 1 and refine >= 1")
    rates = np.repeat(model.rates, refine, axis=2) * refine
    rates[:, 1, 0] = 0.0
    switching = np.repeat(model.switching, refine, axis=2)
    return PhaseTransport(rates, switching, model.entry, model.interval_s)


def _ordered(model: PhaseTransport, occupancy: np.ndarray) -> tuple[PhaseTransport, np.ndarray]:
    """``model`` with its phases sorted by :func:`coupling.phases.mobility`, slowest first,
    and ``occupancy`` (K, NX, NY) sorted alike."""
    order = np.argsort(phase_model.mobility(model.rates, occupancy), kind="stable")
    return (
        PhaseTransport(
            model.rates[order], model.switching[order][:, order], model.entry[:, order], model.interval_s, model.attrs
        ),
        occupancy[order],
    )


def _ctmc_em_steps(
    counts: np.ndarray,
    moves: dict,
    start: dict[str, np.ndarray],
    interval_s: float,
    steps: int,
    max_rate_x_interval: float,
    project=None,
) -> np.ndarray:
    """``steps`` EM updates of the rates of a chain observed at ``counts`` (expected
    transitions per interval): each move's rate becomes its expected number of jumps over
    the expected time spent in its source state, both read off the gradient of
    :func:`dem.rates.log_likelihood` (for a move i -> j, rate * dL/dQ_ij is the expected
    number of jumps and dL/dQ_ii the expected time in i, given the endpoints of every
    interval). One Frechet derivative per update, against tens of evaluations for L-BFGS;
    every update increases the likelihood. Capped at ``max_rate_x_interval`` / interval;
    ``project`` (rates -> rates, the moves' order) imposes constraints after each update
    (:func:`_stagnant_projection`)."""
    src = np.concatenate([t[0] for t in moves.values()])
    dst = np.concatenate([t[1] for t in moves.values()])
    rates = np.concatenate([np.asarray(start[key], dtype=float) for key in moves])
    # EM never moves a rate off 0: start every move slightly off it
    rates = np.maximum(rates, 1e-4 / interval_s)
    cap = max_rate_x_interval / interval_s
    n = counts.shape[0]
    for _ in range(steps):
        q = np.zeros((n, n))
        q[src, dst] = rates
        q[np.arange(n), np.arange(n)] = -q.sum(axis=1)
        _value, d_q = rate_fit.log_likelihood(q, counts, interval_s)
        dwell = d_q[src, src]
        jumps = rates * d_q[src, dst]
        rates = np.where(dwell > 0, np.minimum(jumps / np.maximum(dwell, 1e-300), cap), rates)
        if project is not None:
            rates = project(rates)
    return rates


@dataclass(frozen=True)
class _StartResult:
    """One EM start run to its end: the model, its log-likelihood [nats], the iterations,
    whether it converged and the expected time per (compartment, phase) of the model's grid
    [particle-intervals]."""

    model: PhaseTransport
    log_likelihood: float
    iterations: int
    converged: bool
    dwell: np.ndarray


def _e_step(
    p: np.ndarray, initial: list[np.ndarray], runs: tuple[PhaseData, ...], hidden: int
) -> tuple[float, np.ndarray, list[np.ndarray]]:
    """The E-step over every run's particles: (log-likelihood [nats] and expected
    transitions, both summed over the runs; each run's summed posterior initial phases)."""
    expected = [forward_backward(p, start, run, hidden) for start, run in zip(initial, runs)]
    counts = np.sum([e.counts for e in expected], axis=0)
    return float(sum(e.log_likelihood for e in expected)), counts, [e.entry for e in expected]


def _updated_initial(initial: list[np.ndarray], entries: list[np.ndarray]) -> list[np.ndarray]:
    """Every run's initial phases after an E-step: the feeders' rows (0, 1) from the
    posterior entry phases pooled over the runs (the model's, shared), the rows of the
    particles already inside from the run's own; a row without particles keeps its value."""
    feed = np.sum([entry[:2] for entry in entries], axis=0)
    out = []
    for start, entry in zip(initial, entries):
        sums = np.vstack([feed, entry[2:]])
        updated = sums / np.maximum(sums.sum(axis=1, keepdims=True), 1e-300)
        missing = sums.sum(axis=1) <= 0
        out.append(np.where(missing[:, None], start, updated))
    return out


def _m_step(
    model: PhaseTransport, counts: np.ndarray, entry: np.ndarray, interval_s: float, settings: PhaseSettings, project
) -> PhaseTransport:
    """The chain whose rates raise the expected log-likelihood of ``counts`` (expected
    transitions per interval, from the state after the discharged one zeroed) from
    ``model``'s, entered in ``entry`` (2, K)."""
    nx, ny, k = model.nx, model.ny, model.n_phases
    moves = phase_model.transitions(nx, ny, k)
    if settings.m_step == "lbfgs":
        values, _fit = rate_fit.fit_pattern(counts, moves, _move_rates(model), interval_s, settings.m_step_iterations)
    else:
        values = _ctmc_em_steps(
            counts,
            moves,
            _move_rates(model),
            interval_s,
            settings.m_step_iterations,
            settings.max_rate_x_interval,
            project,
        )
    split = np.cumsum([src.size for src, _d, _c in moves.values()])[:-1]
    per_move = dict(zip(moves, np.split(values, split)))
    return phase_model.from_move_rates(per_move, nx, ny, k, entry, interval_s, model.attrs)


def _em(model: PhaseTransport, runs: tuple[PhaseData, ...], settings: PhaseSettings) -> _StartResult:
    """EM from ``model`` (:mod:`dem.phases`) on the pooled ``runs``, until an iteration
    gains less than ``settings.tol`` per particle-step or after ``settings.max_iterations``.
    The model's grid may refine the data's slices (:attr:`PhaseSettings.refine`)."""
    nx, ny, k, interval = model.nx, model.ny, model.n_phases, runs[0].interval_s
    hidden = refinement(model, runs[0]) * k  # hidden states per observed compartment
    stagnant = settings.stagnant_exit_max_per_s
    project = None if stagnant is None else _stagnant_projection(phase_model.transitions(nx, ny, k), stagnant)
    n_steps = max(sum(run.n_steps for run in runs), 1)
    previous, log_likelihood, converged, iteration = -math.inf, -math.inf, False, 0
    dwell = np.zeros(nx * ny * k)
    initial = [initial_distribution(model, run) for run in runs]
    for iteration in range(1, settings.max_iterations + 1):  # noqa: B007 -- the count is reported after the loop
        p = expm(model.generator() * interval)
        log_likelihood, counts, entries = _e_step(p, initial, runs, hidden)
        # the likelihood is that of the model before this M-step
        if (log_likelihood - previous) / n_steps < settings.tol:
            converged = True
            break
        previous = log_likelihood
        initial = _updated_initial(initial, entries)
        entry = initial[0][:2].reshape(2, -1, k).sum(axis=1)  # over the sub-slices it entered
        counts[-1] = 0.0
        model = _m_step(model, counts, entry, interval, settings, project)
        dwell = counts[:-1].sum(axis=1)
    return _StartResult(model, log_likelihood if converged else previous, iteration, converged, dwell)


def _base(runs: tuple[PhaseData, ...], settings: PhaseSettings, base: PhaseTransport | None) -> PhaseTransport:
    """The one-phase chain the starts split into phases: ``base``, or fitted to the runs
    (:func:`one_phase`), refined to :attr:`PhaseSettings.refine` slices per observed one.
    Raises ConfigError when the data or ``base`` do not fit the settings' grid."""
    data, refine = runs[0], settings.refine
    if refine > 1 and data.ny != 1:
        raise ConfigError(
            f"PhaseSettings.refine = {refine} on {data.nx}x{data.ny} data: expected refine 1, or axial data (NY = 1)"
        )
    if base is None:
        base = one_phase(runs)
    if refine > 1 and base.nx == data.nx:
        base = refined(base, refine)
    if (base.nx, base.ny) != (data.nx * refine, data.ny):
        raise ConfigError(
            f"base grid {base.nx}x{base.ny} is not refine = {refine} times the data's {data.nx}x{data.ny} along x"
        )
    return base


def _starting_models(base: PhaseTransport, settings: PhaseSettings) -> list[PhaseTransport]:
    """The EM's starts (:mod:`dem.phases`, "Starts"), the random ones drawn in order from
    one generator seeded with ``settings.seed``; one start for K = 1."""
    rng = np.random.default_rng(settings.seed)
    stagnant = settings.stagnant_exit_max_per_s
    out = []
    for start in range(settings.starts if settings.n_phases > 1 else 1):
        first = _initial(base, settings.moving_phases, None if start == 0 else rng, settings.max_rate_x_interval)
        out.append(first if stagnant is None else _with_stagnant(first, stagnant))
    return out


def _fitted(
    results: list[_StartResult], runs: tuple[PhaseData, ...], settings: PhaseSettings, wall_time_s: float
) -> PhaseFit:
    """The best start as a :class:`PhaseFit`, its phases ordered slowest first."""
    best = max(results, key=lambda r: r.log_likelihood)
    model = best.model
    occupancy = best.dwell.reshape(model.nx, model.ny, settings.n_phases).transpose(2, 0, 1)
    model, occupancy = _ordered(model, occupancy)
    n_particles = sum(run.n_particles for run in runs)
    n_steps = sum(run.n_steps for run in runs)
    stagnant = settings.stagnant_exit_max_per_s
    attrs = {
        "method": "EM (forward-backward on the phases, dem.rates M-step)",
        "n_particles": n_particles,
        "n_steps": n_steps,
        "log_likelihood": best.log_likelihood,
        "grid": [model.nx, model.ny],
        "observed_grid": [runs[0].nx, runs[0].ny],
        **({} if len(runs) == 1 else {"n_runs": len(runs)}),
        **({} if stagnant is None else {"stagnant_exit_max_per_s": float(stagnant)}),
    }
    return PhaseFit(
        PhaseTransport(model.rates, model.switching, model.entry, model.interval_s, attrs),
        best.log_likelihood,
        n_particles,
        n_steps,
        best.iterations,
        best.converged,
        tuple(float(r.log_likelihood) for r in results),
        wall_time_s,
        occupancy,
        len(runs),
        settings,
    )


@single_threaded_blas()
def _fit(runs: tuple[PhaseData, ...], settings: PhaseSettings, base: PhaseTransport | None) -> PhaseFit:
    wall0 = time.perf_counter()
    first = _base(runs, settings, base)
    results = [_em(start, runs, settings) for start in _starting_models(first, settings)]
    return _fitted(results, runs, settings, time.perf_counter() - wall0)


class PhaseEstimator:
    """Fits the K = ``settings.n_phases`` hidden-phase chain by EM (:mod:`dem.phases`):
    ``PhaseEstimator(settings).fit(data).fetch_model()`` is the :class:`PhaseFit`.

    ``data``: one run's :class:`dem.phases.PhaseData`, or a list of runs on one grid and
    observation interval, fitted jointly (:mod:`dem.phases.estimator`). ``base``: the
    one-phase chain to start from (default: fitted to the data, :func:`one_phase`).

    ``settings.refine`` = r > 1 (axial data, NY = 1): the chain has r slices in each
    observed one, and the sub-slice a particle is in is hidden beside its phase (r K hidden
    states per observed slice, the same forward-backward). Such a chain is fitted to
    observations coarse enough to be Markov in the phases and is itself on a finer grid
    (``pbmdem study phases --observed-nx``): the observations time the crossing of an
    observed slice but do not say where in it the particles are, so the split of the
    hold-up between its sub-slices is not identified.

    ``settings.stagnant_exit_max_per_s``: phase 0 of the K is stagnant, a dead zone: it
    makes no move (nor leaves over the weir), is never entered from the feed, and is left
    at this rate at most in each compartment; the other K - 1 phases start as a
    (K - 1)-phase fit does. Without the bound, maximum likelihood spends an immobile phase
    on the short pauses of the slow bed; with it (e.g. one over the mean residence time)
    the phase holds what the DEM's longest stays are, particles parked for tens of seconds
    in the corners at the inlet wall and under the weir (``pbmdem study phases
    --stagnant``).

    Raises ConfigError for settings that are not :class:`PhaseSettings`, data that are not
    one fit's (:func:`dem.phases.as_runs`) or do not fit the settings' grid."""

    def __init__(self, settings: PhaseSettings | None = None) -> None:
        if settings is not None and not isinstance(settings, PhaseSettings):
            raise ConfigError(f"settings {settings!r}: expected a dem.phases.PhaseSettings")
        self.settings = PhaseSettings() if settings is None else settings
        self._model: PhaseFit | None = None

    def fit(self, data: PhaseData | Sequence[PhaseData], base: PhaseTransport | None = None) -> PhaseEstimator:
        """Fit to ``data`` (one run or several); returns the estimator, whose
        :meth:`fetch_model` is then the fit."""
        self._model = _fit(as_runs(data), self.settings, base)
        return self

    def fetch_model(self) -> PhaseFit:
        """The last :meth:`fit`'s :class:`PhaseFit`; ConfigError before any fit."""
        if self._model is None:
            raise ConfigError("PhaseEstimator.fetch_model() before fit(data): there is no model yet")
        return self._model


@single_threaded_blas()
def one_phase(data: PhaseData | Sequence[PhaseData], max_iterations: int = ONE_PHASE_ITERATIONS) -> PhaseTransport:
    """The K = 1 chain: the measured rates of :mod:`dem.rates` (maximum likelihood of the
    observed moves, pooled over ``data``, one run or several), entry phase trivially 0."""
    runs = as_runs(data)
    counts = np.sum([run.counts() for run in runs], axis=0).astype(float)
    counts[-1] = 0.0
    nx, ny, interval = runs[0].nx, runs[0].ny, runs[0].interval_s
    moves = phase_model.transitions(nx, ny, 1)
    start = rate_fit.naive_rates(counts, nx, ny, interval)
    start_moves = {f"{key}/0": start[key].ravel()[moves[f"{key}/0"][2]] for key in rate_fit.RATE_KEYS}
    values, _fit = rate_fit.fit_pattern(counts, moves, start_moves, interval, max_iterations)
    split = np.cumsum([src.size for src, _d, _c in moves.values()])[:-1]
    return phase_model.from_move_rates(dict(zip(moves, np.split(values, split))), nx, ny, 1, np.ones(1), interval)
