"""Critical quality attributes: one definition, called by the DEM and the PBM alike.

Both sides hand these functions their own particle counts (the DEM: integers binned from a
dump; the PBM: expected numbers), so a quantity can only differ between them because the
models differ, never because it was computed another way. The written definitions are in
``coupling/DEFINITIONS.md``.

* :func:`rsd` -- paper eq. (6): sample standard deviation over the mean of the A fraction
  across compartments. A compartment holding fewer than :data:`EMPTY_BELOW` (one) particle
  is empty and left out. For DEM counts this is "no particle"; for the PBM's expected
  counts it is "less than one particle expected", where a fraction means nothing.
* :func:`random_mixture_rsd` -- the RSD a perfectly random mixture would show with the
  same counts (binomial sampling noise), with the same empty rule.
* :func:`outflow_fraction_a` -- paper eq. (5): C_A, flux-weighted over an interval.
* :class:`SteadyStateRule` -- one rule, applied to each side's own hold-up curve: steady
  from the first time the mean hold-up over the trailing window differs from the mean
  over the window before by at most ``rel_tol`` of itself. The hold-up alone decides: by
  the particle balance dH/dt = inflow - outflow, a hold-up that stopped changing has an
  outflow equal to the feed, so a separate flow test adds nothing but a second tolerance.
  Window means, not point values: the DEM's hold-up jitters by a few particles from
  dump to dump, and a filling blender's slow rise never passes (its relative change over
  a window stays about window / t).
* :data:`TIMESERIES_COLUMNS` -- the columns every CQA time series carries.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from coupling.errors import ConfigError

#: A compartment with fewer particles than this is empty: left out of every RSD.
EMPTY_BELOW = 1.0

#: Columns of a CQA time series, both sides: time [s] at the end of each sampling interval;
#: outflow of A and B over the interval [1/s]; C_A over the interval; RSD across the last
#: slice and across all compartments at that time; particles of A and B held at that time.
TIMESERIES_COLUMNS = ("t_s", "outflow_A_per_s", "outflow_B_per_s", "C_A", "rsd_outlet", "rsd_blender",
                      "holdup_A", "holdup_B")


def _fractions(counts_a, counts_b, axis: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Counts moved so that compartments lie along axis 0; occupied mask; A fractions."""
    a = np.moveaxis(np.asarray(counts_a, dtype=float), axis, 0)
    total = a + np.moveaxis(np.asarray(counts_b, dtype=float), axis, 0)
    occupied = total >= EMPTY_BELOW
    frac = np.divide(a, total, out=np.zeros_like(a), where=occupied)
    return total, occupied, frac


def rsd(counts_a, counts_b, axis: int = 0) -> np.ndarray:
    """RSD of the A fraction across the compartments laid along ``axis`` (paper eq. 6).

    ``c = N_A / (N_A + N_B)`` per compartment; empty compartments (fewer than
    :data:`EMPTY_BELOW` particles) are left out; RSD = sample SD (ddof 1) / mean of the
    remaining ``c``. NaN where fewer than two compartments remain or their mean is 0.
    Returns an array shaped like the input without ``axis`` (a 0-d array for 1-D input).
    """
    _, occupied, frac = _fractions(counts_a, counts_b, axis)
    n = occupied.sum(axis=0)
    mean = np.divide(frac.sum(axis=0), n, out=np.full(n.shape, np.nan), where=n > 0)
    dev2 = np.where(occupied, (frac - mean) ** 2, 0.0).sum(axis=0)
    sd = np.sqrt(np.divide(dev2, n - 1, out=np.full(n.shape, np.nan), where=n > 1))
    return np.divide(sd, mean, out=np.full(n.shape, np.nan), where=(n > 1) & (mean > 0))


def random_mixture_rsd(counts_a, counts_b, axis: int = 0) -> np.ndarray:
    """RSD floor of a random mixture with the same counts, across the compartments along
    ``axis``: with X_c ~ Binomial(n_c, p) and p the pooled A fraction of the non-empty
    compartments, the expected sample variance of X_c / n_c is exactly mean_c p(1-p)/n_c,
    so the floor is sqrt(mean_c p(1-p)/n_c) / p. Same empty rule and NaN cases as :func:`rsd`.
    """
    total, occupied, _ = _fractions(counts_a, counts_b, axis)
    a = np.moveaxis(np.asarray(counts_a, dtype=float), axis, 0)
    n = occupied.sum(axis=0)
    pooled_n = np.where(occupied, total, 0.0).sum(axis=0)
    p = np.divide(np.where(occupied, a, 0.0).sum(axis=0), pooled_n, out=np.zeros(n.shape), where=pooled_n > 0)
    inv = np.divide(1.0, total, out=np.zeros_like(total), where=occupied).sum(axis=0)
    mean_var = p * (1 - p) * np.divide(inv, n, out=np.zeros(n.shape), where=n > 0)
    return np.divide(np.sqrt(mean_var), p, out=np.full(n.shape, np.nan), where=(n > 1) & (p > 0))


def outflow_fraction_a(discharged_a, discharged_b) -> np.ndarray:
    """C_A over each interval (paper eq. 5, flux-weighted): dA / (dA + dB); NaN when
    nothing left."""
    da = np.asarray(discharged_a, dtype=float)
    total = da + np.asarray(discharged_b, dtype=float)
    return np.divide(da, total, out=np.full(total.shape, np.nan), where=total > 0)


@dataclass(frozen=True)
class SteadyStateRule:
    """When a hold-up curve is steady (see the module docstring).

    ``window_s`` [s]: length of the two successive windows whose mean hold-ups are
    compared; ``rel_tol``: largest relative difference of the two means that counts as
    steady. A run needs at least two windows of output after filling to be seen steady.
    """

    window_s: float = 10.0
    rel_tol: float = 0.02

    def __post_init__(self) -> None:
        if not (math.isfinite(self.window_s) and self.window_s > 0):
            raise ConfigError(f"steady_state.window_s must be a finite number of seconds > 0, got {self.window_s}")
        if not (math.isfinite(self.rel_tol) and 0 < self.rel_tol < 1):
            raise ConfigError(f"steady_state.rel_tol must lie in (0, 1), got {self.rel_tol}")

    def relative_change(self, times, holdup) -> np.ndarray:
        """At each time t of an evenly spaced series: |m1 - m0| / m1, m1 the mean hold-up
        over (t - W, t] and m0 over (t - 2W, t - W]. NaN before two windows exist or where
        m1 = 0."""
        times = np.asarray(times, dtype=float)
        holdup = np.asarray(holdup, dtype=float)
        change = np.full(times.size, np.nan)
        if times.size < 2:
            return change
        w = max(1, int(round(self.window_s / (times[1] - times[0]))))
        if times.size < 2 * w:
            return change
        # window means from a sliding view, so a NaN (no data yet) spoils only its windows
        means = np.lib.stride_tricks.sliding_window_view(holdup, w).mean(axis=1)
        recent, before = means[w:], means[:-w]
        change[2 * w - 1 :] = np.divide(np.abs(recent - before), recent, out=np.full(recent.size, np.nan),
                                        where=recent > 0)
        return change

    def time(self, times, holdup) -> float | None:
        """First time [s] at which the hold-up is steady, or None if it never is."""
        change = self.relative_change(times, holdup)
        hits = np.nonzero(np.nan_to_num(change, nan=np.inf) <= self.rel_tol)[0]
        return float(np.asarray(times)[hits[0]]) if hits.size else None
