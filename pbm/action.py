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

from dataclasses import dataclass

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
    from pbm import kernels  # compiled: see pbm.kernels for why it is imported here

    return kernels.action_march(
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
