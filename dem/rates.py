"""Compartment transfer rates from discretely observed particle transitions.

The DEM post-processing follows every particle by ID through dumps taken every
``interval_s``; for one time window ``counts[a, b]`` is how often a particle was in state
``a`` at one dump and in state ``b`` at the next. States ``0 .. S-1`` are the compartments
(flat index ``c = i * NY + j``) and ``S = NX * NY`` is "discharged" (absorbing, reached only
forward out of the last axial slice). The PBM needs the rates of its nearest-neighbour
generator Q (per particle, 1/s): ``x_pos`` to (i+1, j) (to S from the last slice),
``x_neg`` to (i-1, j), ``y_pos`` to (i, j+1), ``y_neg`` to (i, j-1); no flux through the
inlet wall or the side walls.

Why not count jumps: the naive estimator ``counts[a, b] / (interval * counts[a, :].sum())``
assumes at most one jump per interval. With the DEM's rates (up to ~10 /s) and dumps every
0.1 s a particle often makes several jumps between dumps, so it sees (i+2, j), (i+1, j+1),
... or comes back, and the neighbour counts undercount the rates.

Method: maximum likelihood of the discretely observed chain,
``L(Q) = sum_ab counts[a, b] log P_ab`` with ``P = expm(Q interval)``, over the free rates.
The gradient is exact: with ``G_ab = counts_ab / P_ab``,
``dL/dQ = interval * L_expm(Q^T interval, G)`` (the adjoint of the Frechet derivative of
expm, ``scipy.linalg.expm_frechet``; the transpose convention is checked against finite
differences in ``tests/dem/test_rates.py``), then the chain rule onto each allowed entry Q_ab
and the diagonal ``-sum``. L-BFGS-B with bounds ``0 <= rate <= 2 / interval`` starts from
the naive estimate (or a previous window's fit). A compartment never observed as a start
state has no information of its own: its rates are held fixed (they still shape P for
particles passing through it) and reported as NaN, as are those of every compartment with
fewer than ``min_observations`` observations.

The cap: a rate above ~2 / interval means a particle leaves and the neighbours relax to
their local balance within one dump interval (e^-2 of it left), so the likelihood is flat
in it and the data cannot tell 20 /s from 500 /s. Uncapped, the DEM's transverse rates
between compartments two particle diameters wide ran to the bound at every value tried
(50 / interval and 5 / interval) and the fit crawled along that flat valley for thousands
of iterations. For the PBM a capped rate is as good as infinite: it relaxes in 0.05 s
(at 0.1-s dumps) against a residence time of ~20 s. The fit reports how many rates sit at
the cap (:attr:`RateFit.capped`).

Numbers (``OPENBLAS_NUM_THREADS=1 python -m workflows.bench.rates``; 10 x 10 grid,
forward-biased axial rates and faster transverse rates, 4e6 particles followed for 30
dumps, 0.6-1.1e8 transitions, so sampling noise is ~1 %; worst relative error over every
rate that is not a wall):

    largest rate x interval    MLE      naive    logm (projected)
    0.1                        1.9 %    23 %     2.1 %
    0.3                        1.4 %    53 %     1.4 %
    0.5                        2.1 %    72 %     1.6 %
    1.0                        1.7 %    88 %     4.2 %

The naive estimator is biased even at 0.1: the total exit rate of a compartment (here up
to ~3x the largest single rate), not the largest rate, sets how often a particle jumps
twice. The matrix logarithm of the empirical transition matrix is unbiased only with
this much data: it needs every state observed, ignores the nearest-neighbour structure
(its off-pattern mass is thrown away) and can have no real logarithm at all with noisy
counts, whereas the MLE is a valid generator by construction and uses the structure.
Fit time per window (fit_windows, warm start, 1e5 transitions, largest rate x interval
1.0, single-threaded BLAS on a shared 2-core machine): 0.14 s for 10 x 10 (101 states),
0.86 s for 20 x 10 (201 states); a cold start takes 0.18 s and 1.0 s. The cost is one
expm and one expm_frechet per evaluation. On the DEM's own windows (reduced preset, 10 x 10,
~1.1e5 transitions each) a fit takes 300-500 iterations, 1.5-3 s.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np
from scipy.linalg import expm, expm_frechet
from scipy.optimize import minimize

from coupling.blas import single_threaded_blas

RATE_KEYS = ("x_pos", "x_neg", "y_pos", "y_neg")
MIN_RATE = 0.0
MAX_RATE_X_INTERVAL = 2.0
# P entries of transitions that were observed are floored here before the log: far-away
# entries of expm can round to zero or slightly below while counts say they happened.
_P_FLOOR = 1e-12


@dataclass
class RateFit:
    """Maximum-likelihood rates of one window. Rate arrays are (NX, NY) in 1/s, NaN where
    the compartment had fewer than ``min_observations`` observations, 0 through a wall."""

    x_pos: np.ndarray
    x_neg: np.ndarray
    y_pos: np.ndarray
    y_neg: np.ndarray
    n_observations: np.ndarray
    log_likelihood: float
    iterations: int
    converged: bool
    cap_per_s: float = float("inf")

    def rates(self) -> dict[str, np.ndarray]:
        return {key: getattr(self, key) for key in RATE_KEYS}

    @property
    def capped(self) -> int:
        """Reported rates at the cap (module docstring): faster than the dumps resolve."""
        return int(sum(np.count_nonzero(getattr(self, key) >= 0.999 * self.cap_per_s) for key in RATE_KEYS))


def _check_grid(nx: int, ny: int) -> None:
    for name, value in (("nx", nx), ("ny", ny)):
        if not isinstance(value, (int, np.integer)) or value < 1:
            raise ValueError(f"{name} = {value!r}: expected a positive integer")


def _check_interval(interval_s: float) -> None:
    if not np.isfinite(interval_s) or interval_s <= 0:
        raise ValueError(f"interval_s = {interval_s!r}: expected a positive finite time in seconds")


def _check_counts(counts, nx: int, ny: int, windows: bool = False) -> np.ndarray:
    counts = np.asarray(counts)
    n = nx * ny + 1
    if counts.ndim != (3 if windows else 2) or counts.shape[-2:] != (n, n):
        expected = f"(K, {n}, {n})" if windows else f"({n}, {n})"
        raise ValueError(
            f"counts has shape {counts.shape}; expected {expected} for nx={nx}, ny={ny} "
            f"(S = nx*ny compartments plus the discharged state)"
        )
    counts = counts.astype(float)
    if not np.all(np.isfinite(counts)) or np.any(counts < 0):
        raise ValueError("counts must be finite and non-negative (numbers of observed transitions)")
    return counts


def allowed_transitions(nx: int, ny: int, nz: int = 1) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """For each direction: (source state, target state, flat compartment index) of every
    transition the nearest-neighbour model allows; walls have none.

    With ``nz`` > 1 the compartments are also stacked in height (flat index
    ``(i * ny + j) * nz + l``, layer l from the bottom; ``nz`` = 1 is the tables' grid) and
    "z_pos" / "z_neg" move up and down a layer. Only the layered study uses that."""
    i, j, layer = (a.ravel() for a in np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"))
    c = (i * ny + j) * nz + layer
    s = nx * ny * nz
    out = {"x_pos": (c, np.where(i == nx - 1, s, c + ny * nz), c)}
    steps = [("x_neg", i > 0, -ny * nz), ("y_pos", j < ny - 1, nz), ("y_neg", j > 0, -nz)]
    if nz > 1:
        steps += [("z_pos", layer < nz - 1, 1), ("z_neg", layer > 0, -1)]
    for key, ok, step in steps:
        out[key] = (c[ok], c[ok] + step, c[ok])
    return out


def generator(rates: dict[str, np.ndarray], nx: int, ny: int) -> np.ndarray:
    """Dense generator Q, shape (S+1, S+1) with S = nx*ny: row = from, column = to, rows sum
    to 0, row S (discharged) zero. ``rates`` maps "x_pos", "x_neg", "y_pos", "y_neg" to
    (nx, ny) arrays [1/s]; entries that would point through a wall are not used."""
    _check_grid(nx, ny)
    if set(rates) != set(RATE_KEYS):
        raise ValueError(f"rates has keys {sorted(rates)}; expected exactly {list(RATE_KEYS)}")
    n = nx * ny + 1
    q = np.zeros((n, n))
    for key, (src, dst, comp) in allowed_transitions(nx, ny).items():
        r = np.asarray(rates[key], dtype=float)
        if r.shape != (nx, ny):
            raise ValueError(f"rates[{key!r}] has shape {r.shape}; expected (nx, ny) = ({nx}, {ny})")
        values = r.ravel()[comp]
        if not np.all(np.isfinite(values)) or np.any(values < 0):
            bad = values[~(np.isfinite(values) & (values >= 0))][0]
            raise ValueError(f"rates[{key!r}] contains {bad!r}; expected finite rates >= 0 [1/s]")
        q[src, dst] += values
    q[np.arange(n), np.arange(n)] = -q.sum(axis=1)
    return q


def log_likelihood(q: np.ndarray, counts: np.ndarray, interval_s: float) -> tuple[float, np.ndarray]:
    """``L = sum_ab counts[a, b] log P_ab`` with ``P = expm(q interval)``, and dL/dq for every
    entry of q (treated as independent, no generator constraint)."""
    p = expm(q * interval_s)
    seen = counts > 0
    p_seen = np.maximum(p[seen], _P_FLOOR)
    value = float(np.dot(counts[seen], np.log(p_seen)))
    g = np.zeros_like(p)
    g[seen] = counts[seen] / p_seen
    # <G, L(A, E)> = <L(A^T, G), E>: the adjoint of the Frechet derivative at A is the
    # Frechet derivative at A^T.
    _, frechet = expm_frechet(q.T * interval_s, g, compute_expm=True)
    return value, interval_s * frechet


def naive_rates(counts, nx: int, ny: int, interval_s: float) -> dict[str, np.ndarray]:
    """The one-jump estimator ``counts[a, b] / (interval * sum_b counts[a, b])`` of each
    allowed transition; NaN for compartments never observed, 0 through a wall."""
    _check_grid(nx, ny)
    _check_interval(interval_s)
    counts = _check_counts(counts, nx, ny)
    rows = counts[:-1].sum(axis=1)
    out = {}
    for key, (src, dst, comp) in allowed_transitions(nx, ny).items():
        r = np.zeros(nx * ny)
        with np.errstate(invalid="ignore", divide="ignore"):
            r[comp] = counts[src, dst] / (interval_s * rows[src])
        r[rows == 0] = np.nan
        out[key] = r.reshape(nx, ny)
    return out


class _Objective:
    """-L / n_observations over z = weight * (free rates), with its exact gradient.

    Rates, not log-rates: a rate the data put at 0 then meets its bound and L-BFGS-B fixes
    it there, whereas a log-rate crawls towards minus infinity along a vanishing gradient
    (measured on a reduced-run window: 500 iterations without converging, against ~50).
    The weights are the square roots of each rate's approximate Fisher information
    (n_observations(source) * interval / rate, per observation): without them a rarely
    visited compartment's rates sit in a valley flatter than a busy one's by the ratio of
    their observations, and L-BFGS-B needs several times more iterations.
    """

    def __init__(
        self,
        counts: np.ndarray,
        interval_s: float,
        start: np.ndarray,
        free: np.ndarray,
        src: np.ndarray,
        dst: np.ndarray,
    ):
        self.counts = counts
        self.interval_s = interval_s
        self.n = counts.shape[0]
        self.start = start
        self.free = free
        self.src = src
        self.dst = dst
        # Normalised so that the tolerances mean the same for 1e3 or 1e7 observations.
        self.scale = 1.0 / counts.sum()
        n_src = counts[src[free]].sum(axis=1)
        typical = np.maximum(start[free], 0.1 / interval_s)
        self.weight = np.sqrt(np.maximum(n_src * interval_s / typical, 1.0 / typical) * self.scale)

    def all_rates(self, z: np.ndarray) -> np.ndarray:
        rates = self.start.copy()
        rates[self.free] = z / self.weight
        return rates

    def generator(self, rates: np.ndarray) -> np.ndarray:
        q = np.zeros((self.n, self.n))
        q[self.src, self.dst] = rates
        q[np.arange(self.n), np.arange(self.n)] = -q.sum(axis=1)
        return q

    def rate_gradient(self, z: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        """(L, dL/d rate of the free rates, all rates) at z."""
        rates = self.all_rates(z)
        value, d_q = log_likelihood(self.generator(rates), self.counts, self.interval_s)
        return value, (d_q[self.src, self.dst] - d_q[self.src, self.src])[self.free], rates

    def __call__(self, z: np.ndarray) -> tuple[float, np.ndarray]:
        value, d_rate, rates = self.rate_gradient(z)
        return -value * self.scale, -d_rate * self.scale / self.weight


@dataclass
class PatternFit:
    """How :func:`fit_pattern` ended."""

    log_likelihood: float
    iterations: int
    converged: bool


def fit_pattern(
    counts: np.ndarray,
    transitions: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]],
    start: dict[str, np.ndarray],
    interval_s: float,
    max_iterations: int = 500,
    max_rate_x_interval: float = MAX_RATE_X_INTERVAL,
) -> tuple[np.ndarray, PatternFit]:
    """The maximum-likelihood core of :func:`fit_rates` for any pattern of allowed moves.

    ``counts``: (S+1, S+1) checked counts with row S zeroed; ``transitions``: direction ->
    (source, target, compartment) as :func:`allowed_transitions` gives them; ``start``: direction ->
    a starting rate per move (NaN: unknown). Returns every move's rate, in the order of
    ``transitions`` (directions, then moves), and how the fit ended. Rates of compartments
    never observed as a source stay at their (filled) start; with no observation at all
    nothing is fitted. Rates are bounded by ``max_rate_x_interval`` / ``interval_s``."""
    lo, hi = MIN_RATE, max_rate_x_interval / interval_s
    n_obs = counts[:-1].sum(axis=1)
    src = np.concatenate([t[0] for t in transitions.values()])
    dst = np.concatenate([t[1] for t in transitions.values()])
    first = np.concatenate([np.asarray(start[key], dtype=float) for key in transitions])
    key_of = np.concatenate([np.full(t[0].size, k) for k, t in enumerate(transitions.values())])
    free = n_obs[src] > 0
    # Never-observed compartments: a typical value keeps the particles that pass through
    # them between dumps plausible; it is not reported.
    for k in range(len(transitions)):
        block = key_of == k
        known = block & free & np.isfinite(first)
        fill = float(np.median(first[known])) if known.any() else 1.0 / interval_s
        first[block & ~np.isfinite(first)] = fill
    # A naive 0 is usually a rate the one-jump count missed: start it off the bound.
    first = np.clip(first, max(lo, 1e-3 / interval_s), hi)
    if not free.any():
        return first, PatternFit(0.0, 0, True)
    objective = _Objective(counts, interval_s, first, free, src, dst)
    w = objective.weight
    options = {"maxiter": max_iterations, "ftol": 1e-10, "gtol": 1e-6, "maxcor": 20}
    result = minimize(
        objective, first[free] * w, jac=True, method="L-BFGS-B", bounds=list(zip(lo * w, hi * w)), options=options
    )
    return objective.all_rates(result.x), PatternFit(
        -result.fun / objective.scale, int(result.nit), bool(result.success)
    )


def fit_rates(
    counts,
    nx: int,
    ny: int,
    interval_s: float,
    min_observations: int = 100,
    initial: dict[str, np.ndarray] | None = None,
    max_iterations: int = 500,
    max_rate_x_interval: float = MAX_RATE_X_INTERVAL,
) -> RateFit:
    """Maximum-likelihood nearest-neighbour rates of one window's transition counts.

    ``counts``: (S+1, S+1) numbers of observed dump-to-dump transitions (row S ignored).
    ``initial``: rates to start from (e.g. the previous window's fit; NaN entries fall back
    to the naive estimate). Rates of compartments with fewer than ``min_observations``
    observations (row sums) are NaN in the result. ``max_rate_x_interval``: the cap of
    every rate times the interval (:data:`MAX_RATE_X_INTERVAL`).
    """
    _check_grid(nx, ny)
    _check_interval(interval_s)
    if min_observations < 1:
        raise ValueError(f"min_observations = {min_observations!r}: expected >= 1")
    counts = _check_counts(counts, nx, ny).copy()
    s = nx * ny
    counts[s] = 0.0  # a discharged particle is not followed
    n_obs = counts[:s].sum(axis=1)

    start_dict = naive_rates(counts, nx, ny, interval_s)
    if initial is not None:
        for key in RATE_KEYS:
            if key not in initial or np.shape(initial[key]) != (nx, ny):
                raise ValueError(f"initial[{key!r}] must be an (nx, ny) = ({nx}, {ny}) array of rates")
            warm = np.asarray(initial[key], dtype=float)
            start_dict[key] = np.where(np.isfinite(warm), warm, start_dict[key])

    transitions = allowed_transitions(nx, ny)
    start = {key: start_dict[key].ravel()[comp] for key, (_, _, comp) in transitions.items()}
    report = {key: np.full((nx, ny), np.nan) for key in RATE_KEYS}
    rates, result = fit_pattern(counts, transitions, start, interval_s, max_iterations, max_rate_x_interval)

    reported = n_obs >= min_observations
    offset = 0
    for key, (k_src, _, comp) in transitions.items():
        r = np.zeros(s)
        r[comp] = rates[offset : offset + k_src.size]
        offset += k_src.size
        r[~reported] = np.nan
        report[key] = r.reshape(nx, ny)
    return RateFit(
        **report,
        n_observations=n_obs.reshape(nx, ny),
        log_likelihood=result.log_likelihood,
        iterations=result.iterations,
        converged=result.converged,
        cap_per_s=max_rate_x_interval / interval_s,
    )


@dataclass(frozen=True)
class WindowFits:
    """:func:`fit_windows`' answer: every window's rates, and how the fits ended."""

    #: "rate_x_pos", "rate_x_neg", "rate_y_pos", "rate_y_neg" -> (K, NX, NY) [1/s], NaN
    #: where a compartment-window has too few observations (the table's field names)
    rates: dict[str, np.ndarray]
    #: how many rates sit at the cap, over every window
    capped: int
    #: windows whose fit stopped at ``max_iterations`` (its last iterate is kept: on the
    #: DEM's windows it is within 1 % of the converged rates in the median)
    unconverged: tuple[int, ...]

    @property
    def any_finite(self) -> bool:
        return any(np.isfinite(values).any() for values in self.rates.values())

    @property
    def finite(self) -> int:
        return int(sum(np.isfinite(values).sum() for values in self.rates.values()))


@single_threaded_blas()
def fit_windows(
    counts,
    nx: int,
    ny: int,
    interval_s: float,
    min_observations: int = 100,
    max_iterations: int = 500,
    max_rate_x_interval: float = MAX_RATE_X_INTERVAL,
    memo: dict[bytes, RateFit] | None = None,
) -> WindowFits:
    """:func:`fit_rates` for each window of ``counts`` (K, S+1, S+1), each warm-started from
    the previous window's fit.

    ``memo``: a dict kept by the caller between calls on growing data (a run's windows as
    its dumps arrive): a window whose counts and warm start are those of an earlier call
    takes that call's fit, which is what refitting it would give, without the fit."""
    _check_grid(nx, ny)
    counts = _check_counts(counts, nx, ny, windows=True)
    rates = {f"rate_{key}": np.full((counts.shape[0], nx, ny), np.nan) for key in RATE_KEYS}
    capped, unconverged = 0, []
    previous = None
    settings = (nx, ny, float(interval_s), min_observations, max_iterations, float(max_rate_x_interval))
    for k, window in enumerate(counts):
        key = _fit_key(window, previous, settings) if memo is not None else None
        fit = memo.get(key) if memo is not None else None
        if fit is None:
            fit = fit_rates(
                window,
                nx,
                ny,
                interval_s,
                min_observations=min_observations,
                initial=previous,
                max_iterations=max_iterations,
                max_rate_x_interval=max_rate_x_interval,
            )
            if memo is not None:
                memo[key] = fit
        if not fit.converged:
            unconverged.append(k)
        for key in RATE_KEYS:
            rates[f"rate_{key}"][k] = getattr(fit, key)
        capped += fit.capped
        # Only the reported rates carry over: a start from a poorly observed fit is worse
        # than this window's own naive estimate.
        previous = fit.rates()
    return WindowFits(rates, capped, tuple(unconverged))


def _fit_key(window: np.ndarray, initial: dict[str, np.ndarray] | None, settings: tuple) -> bytes:
    """Everything a window's fit depends on, digested."""
    digest = hashlib.blake2b(repr(settings).encode(), digest_size=20)
    digest.update(np.ascontiguousarray(window, dtype=float).tobytes())
    for key in RATE_KEYS:
        digest.update(b"-" if initial is None else np.ascontiguousarray(initial[key], dtype=float).tobytes())
    return digest.digest()


def simulate_observations(
    q: np.ndarray, start_counts, n_steps: int, interval_s: float, rng: np.random.Generator
) -> np.ndarray:
    """Transition counts (S+1, S+1) of particles following the chain with generator ``q``,
    observed every ``interval_s`` for ``n_steps`` intervals, starting from ``start_counts``
    (integer number of particles per state, length S+1 or S). Exact: each particle's next
    state is drawn from its row of ``expm(q interval)``; particles are exchangeable, so
    only the number in each state is carried. Discharged particles are not counted further."""
    q = np.asarray(q, dtype=float)
    n = q.shape[0]
    if q.ndim != 2 or q.shape != (n, n) or n < 2:
        raise ValueError(f"q has shape {q.shape}; expected a square (S+1, S+1) generator")
    _check_interval(interval_s)
    state = np.asarray(start_counts)
    if state.shape not in ((n,), (n - 1,)):
        raise ValueError(f"start_counts has shape {state.shape}; expected ({n},) or ({n - 1},)")
    if not np.issubdtype(state.dtype, np.integer) or np.any(state < 0):
        raise ValueError("start_counts must be non-negative integers (particles per state)")
    state = np.concatenate([state, [0]]) if state.size == n - 1 else state.copy()
    if n_steps < 0:
        raise ValueError(f"n_steps = {n_steps!r}: expected >= 0")
    p = np.clip(expm(q * interval_s), 0.0, None)
    p /= p.sum(axis=1, keepdims=True)
    counts = np.zeros((n, n), dtype=np.int64)
    live = state[:-1].astype(np.int64)
    for _ in range(n_steps):
        moves = rng.multinomial(live, p[:-1])
        counts[:-1] += moves
        live = moves[:, :-1].sum(axis=0)
    return counts
