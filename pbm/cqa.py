"""Critical quality attributes, defined exactly as in DESIGN.md ("defined identically for
DEM and PBM"). Pure functions of particle counts; no solver inside.
"""

from __future__ import annotations

import numpy as np


def rsd(counts_a: np.ndarray, counts_b: np.ndarray, axis: int = 0, min_particles: float = 1.0) -> np.ndarray:
    """Relative standard deviation of the A fraction across compartments (paper eq. 6).

    ``c_i = N_A / (N_A + N_B)`` in each compartment along ``axis``; compartments holding
    fewer than ``min_particles`` particles (A + B) are empty and left out. RSD = sample
    standard deviation (ddof = 1) over the mean of the remaining ``c_i``. NaN where fewer
    than two compartments remain or their mean fraction is 0 (no A: undefined).
    """
    a = np.moveaxis(np.asarray(counts_a, dtype=float), axis, 0)
    b = np.moveaxis(np.asarray(counts_b, dtype=float), axis, 0)
    total = a + b
    occupied = total >= max(min_particles, np.finfo(float).tiny)
    frac = np.divide(a, total, out=np.zeros_like(a), where=occupied)
    n = occupied.sum(axis=0)
    mean = np.divide(frac.sum(axis=0), n, out=np.full(n.shape, np.nan), where=n > 0)
    dev2 = np.where(occupied, (frac - mean) ** 2, 0.0).sum(axis=0)
    sd = np.sqrt(np.divide(dev2, n - 1, out=np.full(n.shape, np.nan), where=n > 1))
    ok = (n > 1) & (mean > 0)
    return np.divide(sd, mean, out=np.full(n.shape, np.nan), where=ok)


def outflow_fraction_a(discharged_a: np.ndarray, discharged_b: np.ndarray) -> np.ndarray:
    """C_A over each interval (eq. 5, flux-weighted): dA / (dA + dB); NaN when nothing left."""
    da = np.asarray(discharged_a, dtype=float)
    db = np.asarray(discharged_b, dtype=float)
    total = da + db
    return np.divide(da, total, out=np.full(total.shape, np.nan), where=total > 0)


def holdup_relative_change(times: np.ndarray, holdup: np.ndarray, window_s: float) -> np.ndarray:
    """Relative change of the mean hold-up between two successive trailing windows.

    At output time t (uniform spacing), with W = ``window_s``: ``|m1 - m0| / m1`` where m1 is
    the mean hold-up over (t-W, t] and m0 over (t-2W, t-W]. NaN before 2 W of outputs
    exist or where m1 = 0.
    """
    times = np.asarray(times, dtype=float)
    holdup = np.asarray(holdup, dtype=float)
    change = np.full(times.size, np.nan)
    if times.size < 2:
        return change
    w = max(1, int(round(window_s / (times[1] - times[0]))))
    csum = np.concatenate([[0.0], np.cumsum(holdup)])
    idx = np.arange(2 * w - 1, times.size)
    if idx.size == 0:
        return change
    recent = (csum[idx + 1] - csum[idx + 1 - w]) / w
    before = (csum[idx + 1 - w] - csum[idx + 1 - 2 * w]) / w
    change[idx] = np.divide(np.abs(recent - before), recent, out=np.full(idx.size, np.nan), where=recent > 0)
    return change


def detect_steady_state(times: np.ndarray, holdup: np.ndarray, window_s: float, rel_tol: float) -> float | None:
    """First output time [s] at which the hold-up is steady, or None if it never is.

    Criterion: :func:`holdup_relative_change` <= ``rel_tol``: the mean hold-up over the
    trailing window (t-W, t] differs from the mean over the window before by at most
    ``rel_tol`` of itself. Window means rather than point values make the test robust to
    the window-to-window jitter of DEM velocities, and a quasi-linear filling rise never
    passes it (its relative change over W stays about W / t).
    """
    change = holdup_relative_change(times, holdup, window_s)
    hits = np.nonzero(np.nan_to_num(change, nan=np.inf) <= rel_tol)[0]
    return float(np.asarray(times)[hits[0]]) if hits.size else None


def rtd_moments(amount: float, held: float, int1: float, int2: float, elapsed_s: float) -> dict[str, float]:
    """Mean and variance of the residence time of the recovered tracer, exactly.

    From the tracer's hold-up at the end ``held`` = H(T), and its time integrals since the
    pulse ``int1`` = int_0^T H dtau and ``int2`` = int_0^T int1 dtau, with T = ``elapsed_s``
    since the pulse and the outflow q = -dH/dtau. Integration by parts gives
    int tau q = int1 - T H(T) and int tau^2 q = 2 (T int1 - int2) - T^2 H(T). Moments are
    conditional on recovery by the end, like the DEM's tagged particles that left.
    """
    recovered = amount - held
    m1 = int1 - elapsed_s * held
    m2 = 2.0 * (elapsed_s * int1 - int2) - elapsed_s**2 * held
    if recovered <= 0:
        return {"recovered_fraction": 0.0, "mean_s": float("nan"), "variance_s2": float("nan")}
    mean = m1 / recovered
    return {
        "recovered_fraction": recovered / amount,
        "mean_s": mean,
        "variance_s2": m2 / recovered - mean**2,
    }
