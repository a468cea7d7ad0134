"""Propagation of the piecewise-constant linear system dz/dt = G_k z + F r(t).

Between two consecutive *breakpoints* (output times, table-window switches, feed-noise
redraws, the tracer pulse, RTD bin edges) the generator ``G_k`` and the feed rates ``r``
are constant, so the exact solution over a step of length h is

    z(t + h) = P z(t) + Q r,     P = expm(G h),   Q = int_0^h expm(G s) ds F,

and both blocks come from one matrix exponential of the augmented matrix
``[[G, F], [0, 0]] h`` (Van Loan's trick). ``P`` and ``Q`` depend only on the window and
on h, so they are computed once per (window, h) and reused by every step, every species
and every ensemble member: a step is then one small dense matrix product.

That dense path costs the cube of the states per window. :mod:`pbm.action` applies the
same exact steps to the state's few columns by uniformization over the generator's
diagonals instead, at a cost of non-zeros x columns x (leaving rate x step); a march takes
whichever of the two :func:`kernel_costs` finds cheaper (results agree to ~1e-12, tested).

``method="bdf"`` integrates the same system with scipy's ``solve_ivp`` (BDF, sparse
analytic Jacobian) instead; it is the independent cross-check of the exact path.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from functools import cache, cached_property

import numpy as np
import scipy.sparse as sp

from coupling.blas import free_cores
from coupling.errors import ConfigError, PbmDemError
from coupling.tables import VelocityTable
from pbm.action import Diagonals, diagonals, march_action, series_terms
from pbm.model import N_ACCUMULATORS, dense_generator, generator_triplets

# Times closer than this are the same breakpoint [s]: it absorbs the rounding of k * dt.
TIME_TOLERANCE_S = 1e-9

# Bader, Blanes & Casas (2019), "Computing the matrix exponential with an optimized Taylor
# polynomial approximation", Mathematics 7, 1174: the degree-18 Taylor polynomial in 5
# matrix products. Row i holds the coefficients of B_i over (I, X, X^2, X^3, X^6).
_T18 = np.array(
    [
        [0.0, -1.00365581030144618291e-01, -8.02924648241156932449e-03, -8.92138498045729985177e-04, 0.0],
        [
            0.0,
            3.97849749499645077844e-01,
            1.36783778460411720168e00,
            4.98289622525382669416e-01,
            -6.37898194594723280150e-04,
        ],
        [
            -1.09676396052962061844e01,
            1.68015813878906206114e00,
            5.71779846478865511061e-02,
            -6.98210122488052056106e-03,
            3.34975017086070470649e-05,
        ],
        [
            -9.04316832390810593223e-02,
            -6.76404519071381882256e-02,
            6.75961301770459654925e-02,
            2.95552570429315521194e-02,
            -1.39180257516060693404e-05,
        ],
        [0.0, 0.0, -9.23364619367118555360e-02, -1.69364939002081722752e-02, -1.40086798182036094347e-05],
    ]
)
# 1-norm below which T18 has a backward error below double-precision unit roundoff.
_THETA18 = 1.090863719290036
# Windows whose dense generators are built in one vectorised call (bounds the memory).
_GENERATOR_CHUNK = 16
# Largest diagonal shift used: exp(300) ~ 1e130 leaves ample room below overflow (1e308).
_MAX_SHIFT = 300.0
# Threads computing step operators concurrently (capped: the matrices are small).
MAX_THREADS = 4
# How a march applies the exact steps: "auto" takes the cheaper of the two by
# kernel_costs; "dense" and "action" force one (tests, benchmarks).
KERNELS = ("auto", "dense", "action")
# Multiply-adds per ns of the two kernels, from `pbmdem bench pbm` (its "kernels" rows) on
# the 2-core benchmark machine: dense products of ~100-600 states (BLAS), the dense
# operator applied to a few columns, and the uniformization's diagonal loops. Only their
# ratios matter, and only for which kernel runs: both give the same numbers.
DENSE_PRODUCT_RATE = 20.0
DENSE_APPLY_RATE = 5.0
ACTION_RATE = 3.0
# The action kernel keeps every breakpoint's state: above this many bytes the dense path
# runs instead (it streams).
ACTION_MAX_BYTES = 2**28


class SolverError(PbmDemError):
    """The BDF cross-check failed to integrate a step (its message is scipy's)."""


def expm_taylor18(a: np.ndarray) -> np.ndarray:
    """Matrix exponential by scaling and squaring of an optimised degree-18 Taylor polynomial.

    Bader, Blanes & Casas (2019) evaluate T18 in 5 matrix products and, for a 1-norm
    below ``_THETA18``, keep the backward error below double-precision roundoff (the
    choice of torch.linalg.matrix_exp). Unlike a Pade approximant it needs no linear solve,
    which for ~100 x 100 matrices costs as much as four products here. A diagonal shift,
    ``expm(A) = exp(-mu) expm(A + mu I)``, with mu the largest leaving rate of the
    population generator roughly halves its 1-norm and saves one squaring.
    Accurate to ~1e-14 relative to the norm of the result (tested against scipy).
    """
    n = a.shape[0]
    diagonal = np.arange(n) * (n + 1)
    mu = max(0.0, -float(a.flat[diagonal].min()))
    norm_plain = np.abs(a).sum(axis=0).max()
    x = a.copy()
    x.flat[diagonal] += mu
    norm = np.abs(x).sum(axis=0).max()
    # Keep the shift only when it helps (it must never increase the norm) and while
    # expm(A + mu I), which grows like exp(mu), stays far from overflow.
    if norm >= norm_plain or mu > _MAX_SHIFT:
        x, mu, norm = a.copy(), 0.0, norm_plain
    s = max(0, int(np.ceil(np.log2(norm / _THETA18)))) if norm > 0 else 0
    x *= 0.5**s
    x2 = x @ x
    x3 = x2 @ x
    x6 = x3 @ x3

    # The five combinations B_i of (X, X^2, X^3, X^6) as one small product, then + c_i0 I.
    powers = np.stack([x, x2, x3, x6]).reshape(4, n * n)
    b1, b2, b3, b4, b5 = (_T18[:, 1:] @ powers).reshape(5, n, n)
    for b_i, c0 in zip((b1, b2, b3, b4, b5), _T18[:, 0]):
        if c0:
            b_i.flat[diagonal] += c0
    x9 = b1 @ b5
    x9 += b4
    b3 += x9
    r = b3 @ x9
    r += b2
    for _ in range(s):
        r = r @ r
    if mu:
        r *= np.exp(-mu)
    return r


def breakpoints(t_start: float, t_end: float, *time_sets: np.ndarray) -> np.ndarray:
    """Sorted, de-duplicated times in [t_start, t_end], both ends included [s]."""
    times = np.concatenate([np.atleast_1d(np.asarray(ts, dtype=float)) for ts in time_sets] + [[t_start, t_end]])
    times = np.sort(times[(times >= t_start - TIME_TOLERANCE_S) & (times <= t_end + TIME_TOLERANCE_S)])
    keep = np.concatenate([[True], np.diff(times) > TIME_TOLERANCE_S])
    times = times[keep]
    times[0], times[-1] = t_start, t_end
    return times


def multiples(step: float, t_start: float, t_end: float) -> np.ndarray:
    """Multiples of ``step`` inside [t_start, t_end] (computed as k * step, no drift)."""
    k0 = int(np.ceil(t_start / step - 1e-9))
    k1 = int(np.floor(t_end / step + 1e-9))
    return step * np.arange(k0, k1 + 1, dtype=float)


@dataclass(frozen=True)
class Schedule:
    """Piecewise-constant generators: entry ``w`` is in force from ``t[w]`` to ``t[w + 1]``
    (the first from the start of time, the last for ever after). ``vals[w]`` holds its
    entries at ``rows``, ``cols`` (the same pattern in every entry), ``m`` states.

    A table's windows are one schedule (:func:`table_schedule`); a fill law's rates that
    follow the hold-up are another (:mod:`pbm.fill`), on a grid of its own.
    """

    t: np.ndarray
    rows: np.ndarray
    cols: np.ndarray
    vals: np.ndarray
    m: int

    @property
    def n_windows(self) -> int:
        return self.t.size

    def dense(self, w) -> np.ndarray:
        """The (m, m) generator of entry ``w``, or the stack for an index array."""
        return dense_generator(self.rows, self.cols, self.vals[w], self.m)

    def sparse(self, w: int) -> sp.csr_matrix:
        return sp.csr_matrix((self.vals[w], (self.rows, self.cols)), shape=(self.m, self.m))

    def windows(self, times: np.ndarray) -> np.ndarray:
        """The entry in force during each step between the breakpoints ``times``, read at
        its midpoint, so entry switches must be breakpoints."""
        return step_windows(self.t, times)


def table_schedule(table: VelocityTable, rates: str) -> Schedule:
    """The generators of ``table``'s windows in mode ``rates``; the phase model is the same
    in every window, so it is one entry."""
    windows = np.arange(1 if rates == "phases" else table.n_windows)
    rows, cols, vals, m = generator_triplets(table, windows, rates)
    return Schedule(np.asarray(table.t[windows], dtype=float), rows, cols, vals, m)


@dataclass
class Propagators:
    """Exact step operators of one generator schedule and one feed distribution, cached.

    ``feed`` is (n, 2): the inlet distribution of one particle/s of A and of B. ``rates``
    is the rate mode of the generators (:data:`pbm.model.RATE_MODES`); ``schedule``
    defaults to the (filled) table's windows. :meth:`step` returns ``(P, Q)`` with
    P (m, m) and Q (m, 2), m = n + 3.
    """

    table: VelocityTable
    feed: np.ndarray
    rates: str = "velocity"
    kernel: str = "auto"
    schedule: Schedule | None = None
    _cache: dict = field(default_factory=dict, repr=False)
    _generators: dict = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        if self.kernel not in KERNELS:
            raise ConfigError(f"unknown propagation kernel {self.kernel!r}; valid: {', '.join(KERNELS)}")
        if self.schedule is None:
            self.schedule = table_schedule(self.table, self.rates)

    @property
    def n_states(self) -> int:
        return self.feed.shape[0] + N_ACCUMULATORS

    @cached_property
    def diagonals(self) -> Diagonals | None:
        """Every schedule entry's uniformized generator by diagonals (:mod:`pbm.action`);
        None when the generator has a form the action kernel does not know."""
        s = self.schedule
        return diagonals(s.rows, s.cols, s.vals, s.m)

    def generator(self, k: int) -> np.ndarray:
        if k not in self._generators:
            self._generators[k] = self.schedule.dense(k)
        return self._generators[k]

    def step(self, k: int, h: float) -> tuple[np.ndarray, np.ndarray]:
        key = (k, round(h / TIME_TOLERANCE_S))
        if key not in self._cache:
            self._cache[key] = self._compute(k, h)
        return self._cache[key]

    def prepare(self, windows: np.ndarray, steps: np.ndarray) -> None:
        """Compute the operators of every (window, step length) pair ahead, in parallel.

        Each matrix exponential is independent and numpy releases the GIL inside BLAS and
        LAPACK, so a thread per free core overlaps them (BLAS itself is single-threaded
        here: see coupling.blas). Results are identical to computing them one by one.
        """
        todo = {}
        for k, h in zip(windows.tolist(), steps.tolist()):
            key = (k, round(h / TIME_TOLERANCE_S))
            if key not in self._cache and key not in todo:
                todo[key] = (k, h)
        if not todo:
            return
        missing = sorted({k for k, _h in todo.values()} - self._generators.keys())
        for start in range(0, len(missing), _GENERATOR_CHUNK):
            chunk = missing[start : start + _GENERATOR_CHUNK]
            for k, g in zip(chunk, self.schedule.dense(np.array(chunk))):
                self._generators[k] = g
        workers = free_cores(min(len(todo), MAX_THREADS))
        if workers <= 1:
            for key, (k, h) in todo.items():
                self._cache[key] = self._compute(k, h)
            return
        with ThreadPoolExecutor(max_workers=workers) as pool:
            results = pool.map(lambda kh: self._compute(*kh), todo.values())
            for key, value in zip(todo, results):
                self._cache[key] = value

    def _compute(self, k: int, h: float) -> tuple[np.ndarray, np.ndarray]:
        m = self.n_states
        aug = np.zeros((m + 2, m + 2))
        aug[:m, :m] = self.generator(k)
        aug[: self.feed.shape[0], m:] = self.feed
        e = expm_taylor18(aug * h)
        return np.ascontiguousarray(e[:m, :m]), np.ascontiguousarray(e[:m, m:])


@dataclass(frozen=True)
class KernelWork:
    """What a march asks of each kernel, in multiply-adds (:func:`kernel_work`).

    ``products``: the dense path's products of the augmented state (its operators not yet
    cached); ``dense_products`` their multiply-adds and ``dense_apply`` those of applying
    the operators to the columns; ``action`` the uniformization's (None where it cannot run).
    """

    products: int
    dense_products: float
    dense_apply: float
    action: float | None

    def seconds(self) -> dict[str, float]:
        """Estimated seconds of each kernel at the measured rates (``inf`` where it cannot run)."""
        dense = self.dense_products / DENSE_PRODUCT_RATE + self.dense_apply / DENSE_APPLY_RATE
        action = math.inf if self.action is None else self.action / ACTION_RATE
        return {"dense": dense * 1e-9, "action": action * 1e-9}


def kernel_work(props: Propagators, windows: np.ndarray, steps: np.ndarray, columns: int) -> KernelWork:
    """The work of a march of ``steps`` under ``windows`` for ``columns`` state columns.

    Dense: the operators not yet cached, each 5 products plus one squaring per halving of
    its norm (lam h with the shift, as :func:`expm_taylor18`), then one operator-state
    product per step and column. Action: a Poisson series per run of steps under one window
    (they share it, :mod:`pbm.action`), each term a pass over the diagonals of every column.
    """
    m = props.n_states + 2
    diag = props.diagonals
    if diag is None:
        rate = np.array([-np.diag(props.generator(k)).min() for k in range(windows.max() + 1)])
    else:
        rate = diag.rate
    ticks = np.round(steps / TIME_TOLERANCE_S).astype(np.int64)
    ops = {
        (k, hk): h for k, hk, h in zip(windows.tolist(), ticks.tolist(), steps.tolist()) if (k, hk) not in props._cache
    }
    norms = np.array([rate[k] * h for (k, _hk), h in ops.items()])
    products = int(5 * norms.size + np.ceil(np.log2(np.maximum(norms, _THETA18) / _THETA18)).sum())
    action = None
    if diag is not None and (steps.size + 1) * props.n_states * columns * 8 <= ACTION_MAX_BYTES:
        runs = np.flatnonzero(np.diff(windows, prepend=-1, append=-1))[:-1]
        means = np.add.reduceat(rate[windows] * steps, runs)
        action = float(series_terms(means).sum() * diag.nonzeros * columns)
    return KernelWork(products, float(products) * m**3, float(steps.size * columns) * m * m, action)


def kernel_costs(props: Propagators, windows: np.ndarray, steps: np.ndarray, columns: int) -> dict[str, float]:
    """Estimated seconds of a march by each kernel (:func:`kernel_work` at the measured rates)."""
    return kernel_work(props, windows, steps, columns).seconds()


def choose_kernel(props: Propagators, windows: np.ndarray, steps: np.ndarray, columns: int) -> str:
    """The kernel a march runs: ``props.kernel`` unless "auto", then the cheaper one."""
    if props.kernel == "action" and props.diagonals is None:
        raise ConfigError("the action kernel needs a generator of populations and accumulators; use 'dense'")
    if props.kernel != "auto":
        return props.kernel
    costs = kernel_costs(props, windows, steps, columns)
    return min(costs, key=costs.get)


def step_windows(starts: np.ndarray, times: np.ndarray) -> np.ndarray:
    """The window (of those starting at ``starts``) in force during each step between the
    breakpoints ``times``, read at its midpoint (the last one beyond the end), as
    VelocityTable.window_index."""
    mids = 0.5 * (times[:-1] + times[1:])
    return np.clip(np.searchsorted(starts, mids, side="right") - 1, 0, starts.size - 1)


def march(
    props: Propagators,
    times: np.ndarray,
    z0: np.ndarray,
    feed_rates: Callable[[int], np.ndarray],
    feed_key: np.ndarray,
    injections: dict[int, np.ndarray] | None = None,
    method: str = "expm",
    rtol: float = 1e-6,
    atol: float = 1e-9,
    live: np.ndarray | None = None,
) -> Iterator[tuple[int, np.ndarray]]:
    """Propagate the state matrix ``z0`` (m, c) through the breakpoints ``times``.

    Yields ``(b, z)`` after each breakpoint b = 1..len(times)-1 (z is the live state: copy
    it to keep it). ``feed_key[s]`` (int per step) labels the feed in force during step s
    (times[s] to times[s+1]); ``feed_rates(key)`` returns the (2, c) feed-rate matrix
    [particles/s]: row 0 feed A and row 1 feed B into each column. ``injections[b]`` is
    added to the state at breakpoint b before stepping on (a Dirac pulse). The window in
    force is read at each step's midpoint, so window switches must be breakpoints.
    ``live[s]``, if given, is how many leading columns may be non-zero during step s (the
    others are zero and fed nothing then, so they stay zero): the dense kernel propagates
    only those.
    """
    injections = injections or {}
    z = np.array(z0, dtype=float, copy=True)
    if 0 in injections:
        z += injections[0]
    windows = props.schedule.windows(times)
    if method == "expm":
        steps = np.diff(times)
        if choose_kernel(props, windows, steps, z.shape[1]) == "action":
            keys, index = np.unique(feed_key, return_inverse=True)
            rates = np.stack([feed_rates(int(key)) for key in keys])
            states = _march_columns(props, windows, steps, rates, index, np.asarray(z0, dtype=float), injections)
            for b in range(1, times.size):
                yield b, states[b]
            return
        props.prepare(windows, steps)
        feed_cache: dict[int, np.ndarray] = {}
        for s in range(times.size - 1):
            p, q = props.step(int(windows[s]), float(steps[s]))
            key = int(feed_key[s])
            if key not in feed_cache:
                feed_cache = {key: feed_rates(key)}  # keys arrive in order: keep only the current
            c = z.shape[1] if live is None else int(live[s])
            if c == z.shape[1]:
                z = p @ z
                z += q @ feed_cache[key]
            else:
                z[:, :c] = p @ z[:, :c] + q @ feed_cache[key][:, :c]
            if s + 1 in injections:
                z += injections[s + 1]
            yield s + 1, z
        return
    if method != "bdf":
        raise ConfigError(f"unknown solver method {method!r}; valid: 'expm', 'bdf'")
    yield from _march_bdf(props, times, z, windows, feed_rates, feed_key, injections, rtol, atol)


def _march_columns(props, windows, steps, rates, feed_key, z, injections) -> np.ndarray:
    """:func:`pbm.action.march_action` with the columns, which never mix, split over the
    free cores (the kernel releases the GIL); the same numbers on any thread count."""
    groups = np.array_split(np.arange(z.shape[1]), free_cores(min(MAX_THREADS, z.shape[1])))
    diag = props.diagonals

    def run(cols: np.ndarray) -> np.ndarray:
        own = {b: v[:, cols] for b, v in injections.items()}
        return march_action(diag, props.feed, windows, steps, rates[:, :, cols], feed_key, z[:, cols], own)

    if len(groups) == 1:
        return run(groups[0])
    # the first group on the calling thread, the others on the shared pool's: no thread is
    # started per march (a start costs as much as a tenth of a 20-ms run)
    others = [shared_pool().submit(run, cols) for cols in groups[1:]]
    first = run(groups[0])
    return np.concatenate([first, *(f.result() for f in others)], axis=2)


@cache
def shared_pool() -> ThreadPoolExecutor:
    """The worker threads the marches share, started on first use; how many a march uses is
    sized to the free cores at the time."""
    return ThreadPoolExecutor(max_workers=MAX_THREADS, thread_name_prefix="pbm-march")


# A forked process (`coupling.forked`'s, a study's workers) inherits the pool but not its threads, and work
# it queued there would wait forever: it starts a pool of its own.
if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=shared_pool.cache_clear)


def _march_bdf(props, times, z, windows, feed_rates, feed_key, injections, rtol, atol):
    # imported here: scipy.integrate costs a fifth of a second that only this reference pays
    from scipy.integrate import solve_ivp

    n = props.feed.shape[0]
    m, c = z.shape
    feed = np.zeros((m, 2))
    feed[:n] = props.feed
    s = 0
    n_steps = times.size - 1
    while s < n_steps:
        # A piece: the longest run of steps with one window, one feed and no pulse inside.
        e = s + 1
        while e < n_steps and windows[e] == windows[s] and feed_key[e] == feed_key[s] and e not in injections:
            e += 1
        gen = props.schedule.sparse(int(windows[s]))
        jac = sp.kron(sp.identity(c, format="csr"), gen, format="csr")
        source = (feed @ feed_rates(int(feed_key[s]))).T.ravel()

        def rhs(_t, y, gen=gen, source=source):
            return _rhs(y, gen, source, c, m)

        # Accumulators restart from 0 on each piece so that their size, which grows all
        # run long, does not loosen the relative tolerance on the per-interval increments.
        start = z.copy()
        local = z.copy()
        local[n:] = 0.0
        t0 = times[s]
        sol = solve_ivp(
            rhs,
            (t0, times[e]),
            local.T.ravel(),
            method="BDF",
            t_eval=times[s + 1 : e + 1],
            jac=jac,
            rtol=rtol,
            atol=atol,
        )
        if not sol.success:
            raise SolverError(f"BDF failed between t = {t0:.6g} s and {times[e]:.6g} s: {sol.message}")
        for col, b in enumerate(range(s + 1, e + 1)):
            z = sol.y[:, col].reshape(c, m).T.copy()
            dt = times[b] - t0
            z[n] += start[n]
            z[n + 2] += start[n + 2] + start[n + 1] * dt
            z[n + 1] += start[n + 1]
            if b in injections:
                z += injections[b]
            yield b, z
        s = e


def _rhs(y: np.ndarray, gen: sp.csr_matrix, source: np.ndarray, c: int, m: int) -> np.ndarray:
    # y holds the columns of z one after the other, so y.reshape(c, m) is z transposed.
    return (gen @ y.reshape(c, m).T).T.ravel() + source
