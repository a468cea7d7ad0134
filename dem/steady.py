"""The DEM's steady-state quantities with their 95 % intervals, and its pooled RTD.

Every number the PBM is judged against carries an interval, and the DEM's numbers are
time series with memory. The steady part of the run is cut into blocks of one velocity
window (5 s by default).

* The steady quantities (hold-ups, outflow, Little's law, outlet composition) relax on the
  scale of a residence time: the hold-up's correlation outlasts a 5-s block by far on the
  slow runs (``pbmdem study blocks``), so a bootstrap over those blocks is too narrow, and
  one over residence-time blocks has too few of them. Their intervals are overlapping batch
  means over batches of :data:`BATCH_RESIDENCE_TIMES` Little's-law residence times, with
  Student's t (:func:`coupling.intervals.batch_means_interval`).
* The pooled RTD's statistics are means over particles, each particle's residence time
  nearly independent of those entering a few seconds before it: the batch-means error of
  its mean and variance does not grow from 1-s to 10-s entry blocks on the runs whose
  entry window is long enough to tell (the same study), so they keep the block bootstrap
  over 5-s blocks of entry time
  (:func:`coupling.intervals.block_bootstrap`).

The definitions of the quantities themselves are those of :mod:`coupling.metrics`, shared
with the PBM.

Quantities (:func:`steady_quantities`, each ``{"value", "low", "high"}``), over the dumps
and sampling intervals after the steady-state time:

* ``holdup`` and ``holdup_by_slice`` [particles]: mean particles in the blender and in each
  axial slice;
* ``outflow_per_s`` [1/s]: mean discharge rate;
* ``little_mean_residence_time_s`` [s]: mean hold-up / mean outflow (Little's law over
  every particle, the sharpest DEM estimate of the mean residence time);
* ``C_A``: A share of the discharged particles, Wilson interval of a binomial proportion
  (each particle a trial);
* ``rsd_outlet`` and ``lacey_outlet``: means over the dumps of the RSD and the Lacey index
  across the last slice's compartments. What the PBM is compared with on this basis is its
  composition sampled at the DEM's particle numbers (:func:`coupling.metrics.sampled_rsd`)
  at every steady dump (:meth:`dem.post.DemResults.steady_outlet_counts`); ``outlet_totals``
  (mean particles per last-slice compartment) is kept for results without them.

The pooled RTD (:func:`pooled_rtd`): every particle that entered during the entry window
(t_ss, t_end - H] is a tracer, censored at the horizon H (:func:`coupling.metrics.rtd_pooled`).
H is :data:`HORIZON_RESIDENCE_TIMES` times the Little's-law mean residence time, rounded up
to whole RTD bins: long enough that nearly every tracer has left (>= 95 % is required), while
leaving most of the steady run as entry window. Intervals by blocks of entry time.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pandas as pd

from coupling.intervals import LEVEL, N_BOOT, batch_means_interval, block_bootstrap
from coupling.metrics import binomial_interval, lacey_index, rsd, rtd_pooled

#: The steady quantities' batch length, in Little's-law mean residence times. On synthetic
#: steady periods of 6-12 residence times (the campaign's) whose hold-up has a slow part
#: relaxing in up to half a residence time (the shipped runs': a third to a half), batches
#: of two cover the true mean 93-95 % of the time at a nominal 95 %, and 88 % when it
#: relaxes in a whole one; a bootstrap over 5-s blocks covers 53-83 %
#: (``pbmdem study blocks --coverage 1000``).
BATCH_RESIDENCE_TIMES = 2.0
#: The pooled RTD's horizon, in Little's-law mean residence times.
HORIZON_RESIDENCE_TIMES = 5.0
RTD_BIN_S = 1.0
RECOVERY_REQUIRED = 0.95


#: What results whose steady intervals could not be brought up to this version say.
STALE_INTERVALS = (
    "the steady intervals are an earlier version's, over 5-s blocks, which the hold-up outlasts: too narrow for "
    "the slow quantities, and the results keep no compartment counts to compute them again"
)


def intervals_are_current(steady: dict[str, Any], pooled: dict[str, Any] | None = None) -> bool:
    """Whether steady quantities were computed this version's way (their batches are
    recorded), and the pooled RTD's intervals too (expanded for their blocks, whose count is
    recorded); empty ones (no steady state, no tracers) are the same either way."""
    pooled_current = not pooled or not pooled.get("n_entered") or "n_blocks" in pooled
    return (not steady or "batch_s" in steady) and pooled_current


def _entry(value, interval) -> dict[str, Any]:
    est, low, high = (np.asarray(v, dtype=float) for v in (value, *interval))
    as_out = (lambda a: a.tolist()) if est.ndim else float
    return {"value": as_out(est), "low": as_out(low), "high": as_out(high)}


def _blocks(times: np.ndarray, start: float, block_s: float) -> np.ndarray:
    return np.floor((times - start) / block_s).astype(np.int64)


def steady_quantities(
    snapshot_t: np.ndarray,
    snapshot_counts: np.ndarray,
    timeseries: pd.DataFrame,
    steady_time_s: float | None,
    block_s: float,
) -> dict[str, Any]:
    """The quantities of the module docstring, or {} when there is no steady state or fewer
    than two blocks of it (no interval can be had). The batches are
    :data:`BATCH_RESIDENCE_TIMES` residence times long in whole blocks, or half the steady
    period when it is shorter than two of them (``batch_s`` records which)."""
    if steady_time_s is None or not math.isfinite(steady_time_s):
        return {}
    after = snapshot_t > steady_time_s
    t_int = timeseries["t_s"].to_numpy()
    late = t_int > steady_time_s
    if after.sum() < 2 or late.sum() < 2:
        return {}
    counts = snapshot_counts[after]  # (n, 2, NX, NY)
    a, b = counts[:, 0], counts[:, 1]
    by_slice = (a + b).sum(axis=2)  # (n, NX)
    outlet_rsd = rsd(a[:, -1, :], b[:, -1, :], axis=1)
    outlet_lacey = lacey_index(a[:, -1, :], b[:, -1, :], axis=1)
    snap_block = _blocks(snapshot_t[after], steady_time_s, block_s)
    int_block = _blocks(t_int[late] - 1e-9, steady_time_s, block_s)
    n_blocks = int(max(snap_block.max(), int_block.max())) + 1
    if n_blocks < 2:
        return {}

    # Per-block sums: one bootstrap item per block, so that statistics mixing dumps and
    # sampling intervals (Little's law) resample the same blocks on both.
    def per_block(values: np.ndarray, blocks: np.ndarray) -> np.ndarray:
        values = np.asarray(values, dtype=float).reshape(len(blocks), -1)
        out = np.zeros((n_blocks, values.shape[1]))
        np.add.at(out, blocks, values)
        return out

    ok_rsd, ok_lacey = np.isfinite(outlet_rsd), np.isfinite(outlet_lacey)
    sums = {
        "snapshots": per_block(np.ones(after.sum()), snap_block)[:, 0],
        "slices": per_block(by_slice, snap_block),
        "rsd": per_block(np.where(ok_rsd, outlet_rsd, 0.0), snap_block)[:, 0],
        "rsd_n": per_block(ok_rsd, snap_block)[:, 0],
        "lacey": per_block(np.where(ok_lacey, outlet_lacey, 0.0), snap_block)[:, 0],
        "lacey_n": per_block(ok_lacey, snap_block)[:, 0],
        "intervals": per_block(np.ones(late.sum()), int_block)[:, 0],
        "outflow": per_block(timeseries["outflow_per_s"].to_numpy()[late], int_block)[:, 0],
    }
    blocks = np.arange(n_blocks)

    def ratio(num, den, idx):
        d = den[idx].sum()
        return num[idx].sum(axis=0) / d if d > 0 else np.full(np.shape(num[0]), np.nan)

    def stat(idx):
        slices = ratio(sums["slices"], sums["snapshots"], idx)
        outflow = ratio(sums["outflow"], sums["intervals"], idx)
        holdup = slices.sum()
        return np.concatenate(
            [
                [
                    holdup,
                    outflow,
                    holdup / outflow if outflow > 0 else np.nan,
                    ratio(sums["rsd"], sums["rsd_n"], idx),
                    ratio(sums["lacey"], sums["lacey_n"], idx),
                ],
                slices,
            ]
        )

    little = float(stat(blocks)[2])
    wanted = math.ceil(BATCH_RESIDENCE_TIMES * little / block_s) if math.isfinite(little) else 1
    batch = max(1, min(wanted, n_blocks // 2))
    (est, low, high), df = batch_means_interval(stat, n_blocks, batch, level=LEVEL)
    out_a = float(timeseries["outflow_A_per_s"].to_numpy()[late].sum())
    out_b = float(timeseries["outflow_B_per_s"].to_numpy()[late].sum())
    interval_s = float(t_int[1] - t_int[0]) if t_int.size > 1 else 1.0
    k, n = out_a * interval_s, (out_a + out_b) * interval_s
    names = ("holdup", "outflow_per_s", "little_mean_residence_time_s", "rsd_outlet", "lacey_outlet")
    out = {name: _entry(est[i], (low[i], high[i])) for i, name in enumerate(names)}
    out["holdup_by_slice"] = _entry(est[len(names) :], (low[len(names) :], high[len(names) :]))
    out["C_A"] = _entry(k / n if n else np.nan, binomial_interval(k, n, LEVEL) if n else (np.nan, np.nan))
    out["outlet_totals"] = (a[:, -1, :] + b[:, -1, :]).mean(axis=0).tolist()
    out["blocks"] = n_blocks
    out["block_s"] = float(block_s)
    out["batch_s"] = float(batch * block_s)
    out["degrees_of_freedom"] = df
    return out


def horizon(little_mean_s: float, bin_s: float = RTD_BIN_S) -> float:
    """The pooled RTD's horizon H [s] for a mean residence time (module docstring)."""
    return math.ceil(HORIZON_RESIDENCE_TIMES * little_mean_s / bin_s) * bin_s


def pooled_rtd(
    records: pd.DataFrame, steady_time_s: float | None, t_end_s: float, little_mean_s: float, block_s: float
) -> dict[str, Any]:
    """The pooled RTD of the per-particle ``records`` (columns entry_t_s, exit_t_s) with
    block-bootstrap intervals of its mean, variance and recovered fraction; {} when the run
    leaves no entry window (too short for its horizon after the steady state)."""
    if steady_time_s is None or not (math.isfinite(steady_time_s) and math.isfinite(little_mean_s)):
        return {}
    h = horizon(little_mean_s)
    window = (float(steady_time_s), float(t_end_s) - h)
    if window[1] - window[0] < 2 * block_s:
        return {
            "horizon_s": h,
            "entry_window_s": list(window),
            "n_entered": 0,
            "note": f"no pooled RTD: the entry window ({window[0]:g}, {window[1]:g}] s after the steady state "
            f"and before t_end - H (H = {h:g} s) is shorter than two {block_s:g}-s blocks",
        }
    entry = records["entry_t_s"].to_numpy(float)
    exit_ = records["exit_t_s"].to_numpy(float)
    pooled = rtd_pooled(entry, exit_, window, h)
    entered = (entry > window[0]) & (entry <= window[1])
    e_in, tau = entry[entered], exit_[entered] - entry[entered]
    got = tau <= h  # NaN: still inside, so not recovered

    def stat(idx):
        r = tau[idx][got[idx]]
        if not r.size:
            return np.array([np.nan, np.nan, 0.0])
        return np.array([r.mean(), r.var(), r.size / idx.size])

    blocks = _blocks(e_in, window[0], block_s)
    est, low, high = block_bootstrap(stat, blocks, n_boot=N_BOOT, level=LEVEL)
    return {
        "horizon_s": h,
        "entry_window_s": list(window),
        "n_entered": pooled.n_entered,
        "n_recovered": int(pooled.residence_s.size),
        "recovered_ok": bool(pooled.recovered_fraction >= RECOVERY_REQUIRED),
        "mean_residence_time_s": _entry(pooled.mean_s, (low[0], high[0])),
        "rtd_variance_s2": _entry(pooled.variance_s2, (low[1], high[1])),
        "recovered_fraction": _entry(pooled.recovered_fraction, (low[2], high[2])),
        "bin_s": RTD_BIN_S,
        "n_blocks": int(np.unique(blocks).size),
    }
