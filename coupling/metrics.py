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
* :func:`lacey_index` -- Lacey's mixing index across compartments, same empty rule as
  :func:`rsd`: 0 for a fully segregated, about 1 for a random mixture.
* :func:`sampled_rsd`, :func:`sampled_lacey` -- the like-for-like basis for the PBM: the
  RSD (Lacey index) its expected composition would show if it were sampled with integer
  particles the way the DEM is, so that both sides carry the same binomial noise.
* :func:`rtd_pooled`, :func:`rtd_density`, :func:`rtd_overlap` -- the pooled RTD: particles
  entering during a window, each followed for the same horizon H, censored at H on both
  sides; its density on fixed bins over [0, H]; the overlap of two such densities.
* :func:`binomial_interval` -- Wilson score interval of a proportion (e.g. the fraction
  of the tagged particles recovered).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cache
from statistics import NormalDist

import numpy as np

from coupling.errors import ConfigError

#: A compartment with fewer particles than this is empty: left out of every RSD.
EMPTY_BELOW = 1.0

#: Columns of a CQA time series, both sides: time [s] at the end of each sampling interval;
#: outflow of A and B over the interval [1/s]; C_A over the interval; RSD across the last
#: slice and across all compartments at that time; particles of A and B held at that time.
TIMESERIES_COLUMNS = (
    "t_s",
    "outflow_A_per_s",
    "outflow_B_per_s",
    "C_A",
    "rsd_outlet",
    "rsd_blender",
    "holdup_A",
    "holdup_B",
)


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
    a = np.asarray(counts_a, dtype=float)
    b = np.asarray(counts_b, dtype=float)
    if a.shape != b.shape:
        raise ValueError(f"A and B counts must have one shape, got {a.shape} and {b.shape}")
    axis = axis % a.ndim if a.ndim else 0
    kernel = _rsd_kernel()
    if kernel is None or a.ndim == 0:
        return _rsd_reference(a, b, axis)
    # (before, compartments, after): a view of any C-ordered input, so nothing is copied
    shape = (math.prod(a.shape[:axis]), a.shape[axis], math.prod(a.shape[axis + 1 :]))
    a3 = np.ascontiguousarray(a).reshape(shape)
    b3 = np.ascontiguousarray(b).reshape(shape)
    return kernel(a3, b3, EMPTY_BELOW).reshape(a.shape[:axis] + a.shape[axis + 1 :])


def _rsd_reference(counts_a, counts_b, axis: int) -> np.ndarray:
    """:func:`rsd` in numpy, the reference of the compiled kernel (tests hold them equal)."""
    _, occupied, frac = _fractions(counts_a, counts_b, axis)
    n = occupied.sum(axis=0)
    mean = np.divide(frac.sum(axis=0), n, out=np.full(n.shape, np.nan), where=n > 0)
    dev2 = np.where(occupied, (frac - mean) ** 2, 0.0).sum(axis=0)
    sd = np.sqrt(np.divide(dev2, n - 1, out=np.full(n.shape, np.nan), where=n > 1))
    return np.divide(sd, mean, out=np.full(n.shape, np.nan), where=(n > 1) & (mean > 0))


def _rsd_columns(a, b, empty_below):
    """:func:`rsd` over axis 1 of (P, C, Q) counts: each fraction computed once into a
    (C, Q) row buffer, then two passes over it adding in the reference's order (compartment
    after compartment) into (Q,) sums. numpy's version makes ~11 passes over temporaries as
    large as the input, which made the RSD of a 10 000-member ensemble's outlets cost as
    much as their products."""
    p_n, c_n, q_n = a.shape
    out = np.empty((p_n, q_n))
    n = np.empty(q_n)
    total = np.empty(q_n)
    dev2 = np.empty(q_n)
    frac = np.empty((c_n, q_n))
    for p in range(p_n):
        n[:] = 0.0
        total[:] = 0.0
        dev2[:] = 0.0
        for c in range(c_n):
            for q in range(q_n):
                t = a[p, c, q] + b[p, c, q]
                if t >= empty_below:
                    f = a[p, c, q] / t
                    n[q] += 1.0
                    total[q] += f
                else:
                    f = np.nan  # empty: left out of both passes
                frac[c, q] = f
        for q in range(q_n):
            total[q] = total[q] / n[q] if n[q] > 0 else np.nan
        for c in range(c_n):
            for q in range(q_n):
                f = frac[c, q]
                if f == f:
                    d = f - total[q]
                    dev2[q] += d * d
        for q in range(q_n):
            mean = total[q]
            if n[q] > 1 and mean > 0:
                out[p, q] = math.sqrt(dev2[q] / (n[q] - 1.0)) / mean
            else:
                out[p, q] = np.nan
    return out


@cache
def _rsd_kernel():
    """:func:`_rsd_columns` compiled, on first use (numba's import is a third of a second
    that a command without an RSD need not pay); None without numba (a dependency)."""
    try:
        import numba
    except ImportError:  # pragma: no cover
        return None
    return numba.njit(cache=True, nogil=True)(_rsd_columns)


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
    """When a hold-up curve is steady: from the first time the mean hold-up over the trailing
    window differs from the mean over the window before by at most ``rel_tol`` of itself.

    ``window_s`` [s]: length of the two successive windows whose mean hold-ups are
    compared; ``rel_tol``: largest relative difference of the two means that counts as
    steady. A run needs at least two windows of output after filling to be seen steady.
    """

    # metadata: pydantic reads "description" when the rule is a section of the pipeline's
    # configuration; "bounds" states for the config reference what __post_init__ enforces
    # (a test holds the two together), without pydantic enforcing it a second time
    window_s: float = field(
        default=10.0,
        metadata={
            "description": "length of each of the two successive windows whose mean hold-ups are compared",
            "bounds": {"gt": 0},
        },
    )
    rel_tol: float = field(
        default=0.02,
        metadata={
            "description": "largest relative difference of the two window means that counts as steady",
            "bounds": {"gt": 0, "lt": 1},
        },
    )

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
        change[2 * w - 1 :] = np.divide(
            np.abs(recent - before), recent, out=np.full(recent.size, np.nan), where=recent > 0
        )
        return change

    def time(self, times, holdup) -> float | None:
        """First time [s] at which the hold-up is steady, or None if it never is."""
        change = self.relative_change(times, holdup)
        hits = np.nonzero(np.nan_to_num(change, nan=np.inf) <= self.rel_tol)[0]
        return float(np.asarray(times)[hits[0]]) if hits.size else None


def lacey_index(counts_a, counts_b, axis: int = 0) -> np.ndarray:
    """Lacey mixing index of A across the compartments laid along ``axis``.

    Over the non-empty compartments (at least :data:`EMPTY_BELOW` particles, as in
    :func:`rsd`), with m of them:

    * p = sum N_A / sum (N_A + N_B), the pooled A fraction; sigma0^2 = p (1 - p), the
      variance of a fully segregated mixture;
    * n_bar = sum (N_A + N_B) / m, the mean particles per compartment;
      sigmaR^2 = p (1 - p) / n_bar, the variance of a random mixture;
    * s^2 = the population variance (ddof 0, unweighted) of the compartment fractions
      c = N_A / (N_A + N_B) about their own unweighted mean;
    * M = (sigma0^2 - s^2) / (sigma0^2 - sigmaR^2).

    M = 0 for a fully segregated mixture and M is close to 1 for a random one when the
    compartments hold equal numbers (with unequal numbers the binomial variance of the
    fractions is p (1 - p) mean(1/n) > sigmaR^2, so a random mixture scores below 1: the
    classical index, not a corrected one). M may exceed 1 (better than random) or fall
    below 0. NaN where fewer than two compartments remain, where p is 0 or 1, or where
    n_bar = 1 (sigma0^2 = sigmaR^2). Returns an array shaped like the input without
    ``axis``.
    """
    total, occupied, frac = _fractions(counts_a, counts_b, axis)
    a = np.moveaxis(np.asarray(counts_a, dtype=float), axis, 0)
    m = occupied.sum(axis=0)
    pooled_n = np.where(occupied, total, 0.0).sum(axis=0)
    p = np.divide(np.where(occupied, a, 0.0).sum(axis=0), pooled_n, out=np.zeros(m.shape), where=pooled_n > 0)
    n_bar = np.divide(pooled_n, m, out=np.zeros(m.shape), where=m > 0)
    c_bar = np.divide(np.where(occupied, frac, 0.0).sum(axis=0), m, out=np.zeros(m.shape), where=m > 0)
    s2 = np.divide(np.where(occupied, (frac - c_bar) ** 2, 0.0).sum(axis=0), m, out=np.zeros(m.shape), where=m > 0)
    sigma0 = p * (1 - p)
    sigma_r = np.divide(sigma0, n_bar, out=np.zeros(m.shape), where=m > 0)
    denominator = sigma0 - sigma_r
    # n_bar > 1 and 0 < p < 1 make the denominator positive; test it directly so that
    # rounding near p = 0 or 1 cannot divide by a tiny difference of equal numbers
    return np.divide(sigma0 - s2, denominator, out=np.full(m.shape, np.nan), where=(m > 1) & (denominator > 0))


#: Largest number of sampled counts held at once by :func:`sampled_rsd` (memory bound).
_SAMPLE_BATCH = 2_000_000


def _sampled_mean(metric, fraction_a, totals, draws: int, seed) -> np.ndarray:
    """Mean over ``draws`` binomial samplings of ``metric(counts_a, counts_b, axis=-1)``
    (see :func:`sampled_rsd`), over the draws in which the metric is defined."""
    if isinstance(draws, bool) or not isinstance(draws, (int, np.integer)) or draws < 1:
        raise ValueError(f"draws must be a positive integer, got {draws!r}")
    try:
        frac, tot = np.broadcast_arrays(np.asarray(fraction_a, dtype=float), np.asarray(totals, dtype=float))
    except ValueError:
        raise ValueError(
            f"fraction_a (shape {np.shape(fraction_a)}) and totals (shape {np.shape(totals)}) must "
            "broadcast to one shape (..., n_compartments)"
        ) from None
    if frac.ndim == 0:
        raise ValueError("fraction_a and totals must have at least one axis (the compartments), got scalars")
    if not np.all(np.isfinite(tot) & (tot >= 0)):
        raise ValueError("totals must be finite particle numbers >= 0")
    occupied = tot >= EMPTY_BELOW
    if not np.all(~occupied | ((frac >= 0) & (frac <= 1))):
        raise ValueError(
            "fraction_a must lie in [0, 1] in every compartment holding at least "
            f"{EMPTY_BELOW:g} particle (NaN is accepted only in empty ones)"
        )
    # the DEM counts whole particles: a compartment expected to hold n particles is sampled
    # with round(n) of them, and one expected to hold less than EMPTY_BELOW stays empty,
    # exactly as rsd would leave it out
    n = np.where(occupied, np.rint(tot), 0).astype(np.int64)
    p = np.where(occupied, frac, 0.0)
    rng = np.random.default_rng(seed)
    total_sum = np.zeros(frac.shape[:-1])
    defined = np.zeros(frac.shape[:-1], dtype=np.int64)
    batch = max(1, _SAMPLE_BATCH // max(1, frac.size))
    for start in range(0, draws, batch):
        k = min(batch, draws - start)
        sampled_a = rng.binomial(n, p, size=(k,) + n.shape).astype(float)
        values = metric(sampled_a, n - sampled_a, axis=-1)
        ok = np.isfinite(values)
        total_sum += np.where(ok, values, 0.0).sum(axis=0)
        defined += ok.sum(axis=0)
    return np.divide(total_sum, defined, out=np.full(total_sum.shape, np.nan), where=defined > 0)


def sampled_rsd(fraction_a, totals, draws: int = 1000, seed=0) -> np.ndarray:
    """The RSD the PBM's expected composition would show if sampled like the DEM.

    For each compartment, N_A ~ Binomial(round(n), c) and N_B = round(n) - N_A, where n =
    ``totals`` is the expected number of particles and c = ``fraction_a`` the expected A
    fraction; compartments with n < :data:`EMPTY_BELOW` hold no particle (empty, as in
    :func:`rsd`). The result is the mean of :func:`rsd` of the sampled counts over
    ``draws`` independent samplings, taken over the draws in which it is defined (NaN if
    none is). This is the like-for-like basis: the DEM's RSD is that of one such sample
    of its own mixture, so comparing it with the RSD of the PBM's expected counts would
    compare noise with none.

    ``fraction_a`` and ``totals`` broadcast to (..., n_compartments); the RSD is taken over
    the last axis and the result has shape (...). Deterministic for a given ``seed``. The
    mean RSD is not the random-mixture floor of :func:`random_mixture_rsd` (the square
    root of the mean variance, over the true mean): for a uniform mixture it is below the
    floor by the bias of a sample standard deviation, 2-3 % over 10 compartments.
    """
    return _sampled_mean(rsd, fraction_a, totals, draws, seed)


def sampled_lacey(fraction_a, totals, draws: int = 1000, seed=0) -> np.ndarray:
    """The Lacey index (:func:`lacey_index`) the PBM's expected composition would show if
    sampled like the DEM: the same binomial sampling, empty rule, shapes and averaging as
    :func:`sampled_rsd`."""
    return _sampled_mean(lacey_index, fraction_a, totals, draws, seed)


@dataclass(frozen=True)
class PooledRtd:
    """The pooled RTD sample (see :func:`rtd_pooled`).

    ``residence_s`` [s]: residence times of the recovered particles (tau <= horizon);
    ``entry_s`` [s]: their entry times, in the same order (for blocking by entry time);
    ``n_entered``: particles that entered during the window; ``recovered_fraction``:
    recovered / entered (NaN if none entered); ``mean_s`` [s] and ``variance_s2`` [s^2]:
    mean and population variance (ddof 0) of ``residence_s`` (NaN if none recovered);
    ``entry_window`` [s] and ``horizon_s`` [s]: the definition's parameters.
    """

    residence_s: np.ndarray
    entry_s: np.ndarray
    n_entered: int
    recovered_fraction: float
    mean_s: float
    variance_s2: float
    entry_window: tuple[float, float]
    horizon_s: float


def rtd_pooled(entry_t, exit_t, entry_window, horizon_s: float) -> PooledRtd:
    """The pooled RTD: the one definition both sides use.

    The particles that entered in the window (t0, t1] = ``entry_window`` [s] are the
    tracer; each one's residence time is tau = exit - entry [s]. Every one of them is
    followed for at least the horizon H = ``horizon_s`` (the caller sets t1 <= t_end - H),
    and only tau <= H counts as recovered. Censoring at the same H whatever the entry
    time is what makes the pooled sample one distribution: tau truncated to [0, H], which
    the PBM reproduces exactly by truncating its own response at H.

    ``entry_t`` and ``exit_t``: one value per particle [s]; ``exit_t`` is NaN for a
    particle still inside at the end (it was followed for at least H, so tau > H).
    Raises ValueError for mismatched shapes, a non-finite entry time, an exit before
    its entry, an empty window or a horizon that is not a positive number.
    """
    entry = np.asarray(entry_t, dtype=float)
    exit_ = np.asarray(exit_t, dtype=float)
    if entry.ndim != 1 or entry.shape != exit_.shape:
        raise ValueError(
            f"entry_t and exit_t must be 1-D arrays of one value per particle, got shapes "
            f"{entry.shape} and {exit_.shape}"
        )
    if not np.all(np.isfinite(entry)):
        raise ValueError("entry_t must be finite for every particle")
    try:
        t0, t1 = (float(v) for v in entry_window)
    except (TypeError, ValueError):
        raise ValueError(f"entry_window must be a pair (t0, t1) of times in s, got {entry_window!r}") from None
    if not (math.isfinite(t0) and math.isfinite(t1) and t0 < t1):
        raise ValueError(f"entry_window must be finite with t0 < t1, got ({t0}, {t1})")
    horizon = float(horizon_s)
    if not (math.isfinite(horizon) and horizon > 0):
        raise ValueError(f"horizon_s must be a finite number of seconds > 0, got {horizon_s}")
    tau = exit_ - entry
    if np.any(tau < 0):
        raise ValueError(f"exit_t must not precede entry_t; {int(np.sum(tau < 0))} particle(s) leave before they enter")
    entered = (entry > t0) & (entry <= t1)
    # NaN (never left) compares False, so it is never recovered
    recovered = entered & (tau <= horizon)
    n_entered = int(entered.sum())
    residence = tau[recovered]
    return PooledRtd(
        residence_s=residence,
        entry_s=entry[recovered],
        n_entered=n_entered,
        recovered_fraction=residence.size / n_entered if n_entered else math.nan,
        mean_s=float(residence.mean()) if residence.size else math.nan,
        variance_s2=float(residence.var()) if residence.size else math.nan,
        entry_window=(t0, t1),
        horizon_s=horizon,
    )


def rtd_bin_edges(bin_s: float, horizon_s: float) -> np.ndarray:
    """Edges [s] of the RTD bins: 0, bin_s, ..., H. H must be a whole number of bins, so
    that no bin is cut short."""
    bin_s, horizon = float(bin_s), float(horizon_s)
    if not (math.isfinite(bin_s) and bin_s > 0):
        raise ValueError(f"bin_s must be a finite number of seconds > 0, got {bin_s}")
    if not (math.isfinite(horizon) and horizon > 0):
        raise ValueError(f"horizon_s must be a finite number of seconds > 0, got {horizon}")
    n_bins = round(horizon / bin_s)
    if n_bins < 1 or not math.isclose(n_bins * bin_s, horizon, rel_tol=1e-9):
        raise ValueError(f"horizon_s ({horizon} s) must be a whole number of bins of bin_s ({bin_s} s)")
    return np.linspace(0.0, horizon, n_bins + 1)


def rtd_density(residence_times, bin_s: float, horizon_s: float, weights=None) -> tuple[np.ndarray, np.ndarray]:
    """E(t) on the bins of :func:`rtd_bin_edges`: (edges [s], density [1/s]).

    density_k = (weight in bin k) / (total weight * bin_s), bins [e_k, e_k+1) with the
    last one closed at H, so that sum(density) * bin_s = 1 over [0, H]: the RTD of the
    recovered tracer, as censored by :func:`rtd_pooled`. Each residence time weighs 1
    (DEM particles) unless ``weights`` gives one weight per time (the PBM: tracer
    discharged in each of its bins, placed at the bin centre). Times outside [0, H] are
    refused, not dropped, since dropping them would change the normalisation. The
    density is NaN everywhere when the total weight is 0 (nothing recovered).
    """
    edges = rtd_bin_edges(bin_s, horizon_s)
    tau = np.asarray(residence_times, dtype=float).ravel()
    if not np.all((tau >= 0) & (tau <= edges[-1])):
        raise ValueError(
            f"residence_times must lie in [0, horizon_s] = [0, {edges[-1]}] s; censor them with rtd_pooled first"
        )
    if weights is not None:
        w = np.asarray(weights, dtype=float).ravel()
        if w.shape != tau.shape or not np.all(np.isfinite(w) & (w >= 0)):
            raise ValueError(
                f"weights must be {tau.size} finite values >= 0, one per residence time, got shape {w.shape}"
            )
    else:
        w = None
    mass, _ = np.histogram(tau, bins=edges, weights=w)
    total = mass.sum()
    if total <= 0:
        return edges, np.full(mass.shape, np.nan)
    return edges, mass / (total * float(bin_s))


def rtd_overlap(density_1, density_2, bin_s: float) -> float:
    """Overlap of two RTD densities on the same bins: sum_k min(E1_k, E2_k) * bin_s.

    1 for identical densities, 0 for disjoint ones. For densities that each integrate
    to 1 it equals 1 - 1/2 sum |E1 - E2| bin_s. NaN if either density is NaN anywhere
    (nothing recovered on that side).
    """
    e1 = np.asarray(density_1, dtype=float)
    e2 = np.asarray(density_2, dtype=float)
    if e1.ndim != 1 or e1.shape != e2.shape:
        raise ValueError(f"density_1 and density_2 must be 1-D on the same bins, got shapes {e1.shape} and {e2.shape}")
    if not (math.isfinite(bin_s) and bin_s > 0):
        raise ValueError(f"bin_s must be a finite number of seconds > 0, got {bin_s}")
    if np.any(e1 < 0) or np.any(e2 < 0):
        raise ValueError("densities must be >= 0 in every bin")
    return float(np.sum(np.minimum(e1, e2)) * bin_s)


def binomial_interval(k, n, level: float = 0.95) -> tuple:
    """Wilson score interval (low, high) of a proportion k / n at confidence ``level``.

    With z the two-sided normal quantile, low/high = (k + z^2/2 -+ z sqrt(k (n - k) / n +
    z^2 / 4)) / (n + z^2). Unlike the Wald interval it stays inside [0, 1] and keeps its
    width at k = 0 or k = n (e.g. all tagged particles recovered). n = 0 gives (0, 1).
    ``k`` and ``n`` broadcast; floats for scalar input, arrays otherwise.
    """
    if not (isinstance(level, (int, float)) and 0 < level < 1):
        raise ValueError(f"level must lie in (0, 1), got {level!r}")
    k = np.asarray(k, dtype=float)
    n = np.asarray(n, dtype=float)
    if not np.all(np.isfinite(k) & np.isfinite(n) & (n >= 0) & (k >= 0) & (k <= n)):
        raise ValueError("binomial_interval needs counts 0 <= k <= n, both finite")
    z = NormalDist().inv_cdf(0.5 + level / 2)
    spread = np.divide(k * (n - k), n, out=np.zeros(np.broadcast(k, n).shape), where=n > 0)
    centre = k + z * z / 2
    half = z * np.sqrt(spread + z * z / 4)
    # the interval lies in [0, 1] exactly; the clip only absorbs rounding at k = 0 or n
    low = np.clip((centre - half) / (n + z * z), 0.0, 1.0)
    high = np.clip((centre + half) / (n + z * z), 0.0, 1.0)
    return low[()], high[()]


#: Below this fraction of the tracer recovered, the moments of the recovered part are
#: differences of numbers that agree to round-off (the recovered amount is itself
#: amount - held, ~1e-16 x amount when nothing left): not reported.
MIN_RECOVERED_FRACTION = 1e-9


def residence_moments(amount: float, recovered: float, m1: float, m2: float) -> dict[str, float]:
    """Mean [s] and variance [s^2] of the residence time from the raw moments of the
    recovered tracer (``recovered`` = int q, ``m1`` = int tau q, ``m2`` = int tau^2 q), with
    the guard every CQA shares: a time or a variance below zero is never reported. NaN when
    under :data:`MIN_RECOVERED_FRACTION` of ``amount`` was recovered (the moments are then
    round-off), and NaN for a mean below zero; a variance below zero by round-off (>= -1e-9
    mean^2) is 0, any other negative one NaN. Returns recovered_fraction, mean_s, variance_s2."""
    fraction = float(recovered / amount) if amount > 0 else 0.0
    nan = float("nan")
    if not (math.isfinite(fraction) and fraction > MIN_RECOVERED_FRACTION):
        return {
            "recovered_fraction": max(fraction, 0.0) if math.isfinite(fraction) else nan,
            "mean_s": nan,
            "variance_s2": nan,
        }
    mean = float(m1 / recovered)
    variance = float(m2 / recovered - mean**2)
    if not (math.isfinite(mean) and mean >= 0):
        return {"recovered_fraction": fraction, "mean_s": nan, "variance_s2": nan}
    if variance < 0:
        variance = 0.0 if variance >= -1e-9 * max(mean**2, 1e-300) else nan
    return {"recovered_fraction": fraction, "mean_s": mean, "variance_s2": variance if math.isfinite(variance) else nan}
