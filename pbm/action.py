"""The exact step's action on the state, by uniformization over the generator's diagonals.

The dense path (:mod:`pbm.solver`) forms every window's step operator, a matrix
exponential of the whole state: its cost grows as the cube of the states, once per window.
A march needs that operator applied to a few columns only (A, B, tracer), and the
generator has a handful of non-zero diagonals (the neighbours in x and y, the phase
switches), so the action costs non-zeros x columns x terms instead:

    exp(G h) v = sum_k Poisson(k; lam h) B^k v,     B = I + G / lam,

with lam >= every leaving rate, so that B >= 0 entry-wise (uniformization; Stewart,
"Introduction to the numerical solution of Markov chains", 1994, ch. 8). Every term is a sum
of non-negative numbers -- no cancellation -- and the series is cut where the Poisson tail
falls below :data:`TAIL`, so the result agrees with the dense path to ~1e-13 of its norm.
The feed enters as the augmented state's constant rows (``B`` maps them to F r / lam), the
accumulators as three more rows (``pbm.model``). The kernel walks each diagonal as one
contiguous loop, which the compiler vectorises: on the benchmark machine 3-4
multiply-adds per ns against 20 for the dense products, which the dense path needs ~10x
more of on a 10 x 10 grid, and ever more as the grid or the phases grow.

:func:`diagonals` reads a generator's diagonals (None when it has another form: the dense
path serves it), :func:`march_action` runs a whole march in compiled code.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from pbm.model import N_ACCUMULATORS

# Poisson mass left out of each series: the result's error relative to its norm.
TAIL = 1e-14
# Largest lam h of one series: exp(-MAX_MEAN) must stay far above underflow (1e-308).
# Consecutive steps under one window and feed share a series up to it (each step's end
# weights the same powers of B by its own Poisson probabilities), and a longer step is cut
# into equal sub-steps.
MAX_MEAN = 600.0
# Smallest uniformization rate [1/s]: a generator that moves nothing still needs a
# positive rate for its feed and accumulator terms (any rate is exact; small is cheap).
MIN_RATE = 1.0


@dataclass(frozen=True)
class Diagonals:
    """The uniformized generators of every window, population block by diagonals.

    ``offsets`` (d,): column - row of each stored diagonal, 0 first. ``values`` (W, d, n):
    ``B[i, i + offsets[j]]`` of window w at ``values[w, j, i]`` (0 where i + offset leaves
    the populations), B = I + G / ``rate[w]``. ``outflow`` (W, n): the discharge row of G
    over the populations, divided by the rate. ``rate`` (W,) [1/s]: the uniformization
    rate lam of each window. ``pad``: the largest |offset|.
    """

    offsets: np.ndarray
    values: np.ndarray
    outflow: np.ndarray
    rate: np.ndarray

    @property
    def n(self) -> int:
        return self.values.shape[2]

    @property
    def pad(self) -> int:
        return int(np.abs(self.offsets).max())

    @property
    def nonzeros(self) -> int:
        """Multiply-adds of one product B v of one column (diagonals and accumulators)."""
        return self.offsets.size * self.n + 2 * self.n


def diagonals(rows: np.ndarray, cols: np.ndarray, vals: np.ndarray, m: int) -> Diagonals | None:
    """The :class:`Diagonals` of the generators given as triplets (``vals`` (W, nnz), the
    form of ``pbm.model``'s builder), or None when they are not populations followed by
    the three accumulators OUT, INT1 and INT2 of ``pbm.model``."""
    n = m - N_ACCUMULATORS
    vals = np.atleast_2d(vals)
    pop = (rows < n) & (cols < n)
    out = rows == n
    int1 = rows == n + 1
    int2 = rows == n + 2
    if not np.all(pop | out | int1 | int2) or np.any(cols[out | int1] >= n):
        return None
    if not (np.array_equal(np.sort(cols[int1]), np.arange(n)) and np.all(vals[:, int1] == 1.0)):
        return None
    if not (np.array_equal(cols[int2], [n + 1]) and np.all(vals[:, int2] == 1.0)):
        return None
    windows = vals.shape[0]
    diag = np.zeros((windows, n))
    on_diag = pop & (rows == cols)
    diag[:, rows[on_diag]] = vals[:, on_diag]
    rate = np.maximum(-diag.min(axis=1), MIN_RATE)
    off = pop & (rows != cols)
    offset_of = cols[off] - rows[off]
    offsets = np.concatenate([[0], np.unique(offset_of)])
    values = np.zeros((windows, offsets.size, n))
    values[:, 0, :] = 1.0 + diag / rate[:, None]
    values[:, np.searchsorted(offsets[1:], offset_of) + 1, rows[off]] = vals[:, off] / rate[:, None]
    outflow = np.zeros((windows, n))
    outflow[:, cols[out]] = vals[:, out] / rate[:, None]
    return Diagonals(offsets.astype(np.int64), values, outflow, rate)


def series_terms(mean: np.ndarray) -> np.ndarray:
    """About the products B v a series of Poisson mean ``mean`` takes (cut into series of
    at most :data:`MAX_MEAN`): the mean plus the 8 standard deviations of the tail
    :data:`TAIL` leaves, per series."""
    count = np.maximum(1, np.ceil(np.asarray(mean) / MAX_MEAN))
    sub = np.asarray(mean) / count
    return count * np.floor(sub + 8.0 * np.sqrt(sub) + 10.0)


def march_action(
    diag: Diagonals,
    feed: np.ndarray,
    windows: np.ndarray,
    steps: np.ndarray,
    feed_rates: np.ndarray,
    feed_key: np.ndarray,
    z0: np.ndarray,
    injections: dict[int, np.ndarray],
) -> np.ndarray:
    """The state (m, c) at every breakpoint, (S + 1, m, c), of the march that
    :func:`pbm.solver.march` describes: step s lasts ``steps[s]`` under window
    ``windows[s]`` and feed rates ``feed_rates[feed_key[s]]`` (2, c); ``feed`` (n, 2) is
    the inlet distribution; ``injections[b]`` (m, c) is added at breakpoint b."""
    n_steps = steps.size
    m, c = z0.shape
    inject_at = np.full(n_steps + 1, -1, dtype=np.int64)
    inject = np.zeros((max(1, len(injections)), m, c))
    for j, (b, value) in enumerate(sorted(injections.items())):
        inject_at[b] = j
        inject[j] = value
    return _march(
        diag.offsets,
        diag.values,
        diag.outflow,
        diag.rate,
        diag.pad,
        np.ascontiguousarray(feed, dtype=float),
        np.ascontiguousarray(windows, dtype=np.int64),
        np.ascontiguousarray(steps, dtype=float),
        np.ascontiguousarray(feed_rates, dtype=float),
        np.ascontiguousarray(feed_key, dtype=np.int64),
        np.ascontiguousarray(z0, dtype=float),
        inject_at,
        inject,
        TAIL,
        MAX_MEAN,
    )


@numba.njit(cache=True, nogil=True)
def _product(offsets, values_w, outflow_w, rate, v, t, source, pad, n):
    """t = B v on the padded buffers (populations at [pad, pad + n), then OUT, INT1, INT2)."""
    tv = t[pad : pad + n]
    for i in range(n):
        tv[i] = source[i]
    for d in range(offsets.size):
        dv = values_w[d]
        sv = v[pad + offsets[d] : pad + offsets[d] + n]
        for i in range(n):
            tv[i] += dv[i] * sv[i]
    pop = v[pad : pad + n]
    out = 0.0
    total = 0.0
    for i in range(n):
        out += outflow_w[i] * pop[i]
        total += pop[i]
    a = pad + n + pad
    t[a] = v[a] + out
    t[a + 1] = v[a + 1] + total / rate
    t[a + 2] = v[a + 2] + v[a + 1] / rate


@numba.njit(cache=True, nogil=True)
def _series(offsets, values_w, outflow_w, rate, means, v, t, results, source, pad, n, tail):
    """results[j] = exp(G tau_j) applied to the padded state v, for lam tau_j = ``means[j]``
    (increasing): one series serves every output, each weighting the same powers B^k v
    by its own Poisson probabilities. v and t are work buffers (v is overwritten)."""
    g = means.size
    size = v.size
    weights = np.empty(g)
    left = np.empty(g)
    used = np.empty(g)
    for j in range(g):
        weights[j] = math.exp(-means[j])
        left[j] = 1.0 - weights[j]
        used[j] = weights[j]
        for i in range(size):
            results[j, i] = weights[j] * v[i]
    k = 0
    while left[g - 1] > tail and k < 1000000:
        k += 1
        _product(offsets, values_w, outflow_w, rate, v, t, source, pad, n)
        v, t = t, v
        for j in range(g):
            if left[j] <= tail:
                continue
            weights[j] *= means[j] / k
            left[j] -= weights[j]
            w = weights[j]
            if w > 1e-300:
                used[j] += w
                for i in range(size):
                    results[j, i] += w * v[i]
    # Divided by the weight summed, as if the tail left out were spread like the terms
    # kept: the error stays below TAIL, and the populations plus the discharge keep their
    # total to rounding (B conserves it), so a still blender loses no tracer to the cut.
    for j in range(g):
        for i in range(size):
            results[j, i] /= used[j]


@numba.njit(cache=True, nogil=True)
def _march(
    offsets,
    values,
    outflow,
    rates,
    pad,
    feed,
    windows,
    steps,
    feed_rates,
    feed_key,
    z0,
    inject_at,
    inject,
    tail,
    max_mean,
):
    m, c = z0.shape
    n = m - 3
    size = pad + n + pad + 3
    a = pad + n + pad
    n_steps = steps.size
    out = np.empty((n_steps + 1, m, c))
    z = z0.copy()
    if inject_at[0] >= 0:
        z += inject[inject_at[0]]
    out[0] = z
    v = np.zeros(size)
    t = np.zeros(size)
    start = np.zeros(size)
    source = np.zeros(n)
    s = 0
    while s < n_steps:
        # a group: the steps that share the window and the feed, with no pulse between
        # them, up to a Poisson mean of max_mean: one series gives all their ends
        w = windows[s]
        rate = rates[w]
        e = s + 1
        total = rate * steps[s]
        while (
            e < n_steps
            and windows[e] == w
            and feed_key[e] == feed_key[s]
            and inject_at[e] < 0
            and total + rate * steps[e] <= max_mean
        ):
            total += rate * steps[e]
            e += 1
        g = e - s
        count = 1
        if g == 1:
            count = max(1, int(math.ceil(total / max_mean)))
        means = np.empty(g)
        acc = 0.0
        for j in range(g):
            acc += rate * steps[s + j]
            means[j] = acc / count
        results = np.zeros((g, size))
        for q in range(c):
            r_a = feed_rates[feed_key[s], 0, q]
            r_b = feed_rates[feed_key[s], 1, q]
            for i in range(n):
                source[i] = (feed[i, 0] * r_a + feed[i, 1] * r_b) / rate
            for i in range(n):
                start[pad + i] = z[i, q]
            for j in range(3):
                start[a + j] = z[n + j, q]
            for _sub in range(count):
                for i in range(size):
                    v[i] = start[i]
                _series(offsets, values[w], outflow[w], rate, means, v, t, results, source, pad, n, tail)
                for i in range(size):
                    start[i] = results[g - 1, i]
            for j in range(g):
                for i in range(n):
                    out[s + 1 + j, i, q] = results[j, pad + i]
                for i in range(3):
                    out[s + 1 + j, n + i, q] = results[j, a + i]
        for j in range(g):
            if inject_at[s + 1 + j] >= 0:
                for i in range(m):
                    for q in range(c):
                        out[s + 1 + j, i, q] += inject[inject_at[s + 1 + j], i, q]
        for i in range(m):
            for q in range(c):
                z[i, q] = out[e, i, q]
        s = e
    return out
