"""The agreement table: every DEM quantity with its 95 % interval, each PBM rate mode's
value, and whether that value lies inside the interval.

One row per quantity (:func:`agreement_rows`): ``quantity``, ``unit``, ``dem``,
``dem_ci_low``, ``dem_ci_high``, then ``pbm_<mode>`` and ``inside_<mode>`` for each PBM rate
mode (``velocity``: the paper's eq. 4 rule; ``measured``: rates fitted to the DEM's
particle moves). The DEM values and intervals come from :mod:`dem.steady`; the PBM's are
computed here by the same definitions (:mod:`coupling.metrics`) from the PBM's own output,
each side over the time after its own steady state (one rule, :class:`SteadyStateRule`):

* hold-up, hold-up per axial slice, outflow, C_A, Little's-law mean residence time:
  means over the output times after the PBM's steady-state time;
* outlet RSD and Lacey index on one basis: the PBM's mean steady composition of each
  last-slice compartment sampled binomially at the DEM's mean particle numbers there
  (:func:`coupling.metrics.sampled_rsd`, :func:`~coupling.metrics.sampled_lacey`), against
  the DEM's own (sampled by nature) values;
* the pooled RTD: mean, variance and recovered fraction over the DEM's entry window and
  horizon (:func:`pbm.rtd.pooled_rtd`); the overlap of the two densities is judged against
  the noise band (:func:`coupling.intervals.overlap_noise_band`): what the DEM's number
  of recovered particles drawn from the PBM's own E(t) would score. The row's ``dem`` is 1
  (a perfect model), its interval [noise low of the mode, 1]; ``inside_<mode>`` = overlap
  >= that mode's noise low.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from coupling.intervals import inside, overlap_noise_band
from coupling.metrics import SteadyStateRule, rtd_density, rtd_overlap, rtd_pooled, sampled_lacey, sampled_rsd
from coupling.tables import VelocityTable
from pbm.config import PbmConfig
from pbm.rtd import PooledRtd, pooled_rtd
from pbm.simulate import PbmResult, simulate

MODES = ("velocity", "measured")
#: binomial draws of the sampled RSD / Lacey index (their Monte-Carlo error is < 0.5 %)
SAMPLING_DRAWS = 2000


@dataclass
class PbmMode:
    """One PBM rate mode's run on the DEM's table and its pooled RTD (None without one)."""

    mode: str
    result: PbmResult
    pooled: PooledRtd | None


def run_modes(table: VelocityTable, config: PbmConfig, steady: SteadyStateRule,
              dem_summary: dict[str, Any]) -> dict[str, PbmMode]:
    """The PBM in each rate mode the table supports (``measured`` needs its rates; asked
    for by ``config`` on a table without them, it raises ConfigError), with the pooled RTD
    over the DEM's entry window and horizon when the DEM has one."""
    pooled_spec = dem_summary.get("pooled_rtd") or {}
    modes = {}
    for mode in MODES:
        if mode == "measured" and not table.has_rates and config.rates != "measured":
            continue
        cfg = config.model_copy(update={"rates": mode})
        result = simulate(table, cfg, steady=steady)
        pooled = None
        if pooled_spec.get("n_entered"):
            pooled = pooled_rtd(table, cfg, entry_window=tuple(pooled_spec["entry_window_s"]),
                                horizon_s=pooled_spec["horizon_s"])
        modes[mode] = PbmMode(mode, result, pooled)
    return modes


def pbm_steady(result: PbmResult, dem_steady: dict[str, Any]) -> dict[str, Any]:
    """The PBM's values of the :mod:`dem.steady` quantities (module docstring)."""
    t_ss = result.summary.get("steady_state_time_s")
    after = result.times > (t_ss if t_ss is not None and math.isfinite(t_ss) else result.times[-1])
    if not after.any():
        return {}
    counts = result.counts[after]  # (n, 2, NX, NY)
    slices = counts.sum(axis=(1, 3)).mean(axis=0)
    out_a, out_b = result.outflow_A[after], result.outflow_B[after]
    outflow = float((out_a + out_b).mean())
    holdup = float(slices.sum())
    outlet = counts[:, :, -1, :].mean(axis=0)  # (2, NY)
    totals_pbm = outlet.sum(axis=0)
    fraction = np.divide(outlet[0], totals_pbm, out=np.full(totals_pbm.shape, np.nan), where=totals_pbm > 0)
    dem_totals = np.asarray(dem_steady.get("outlet_totals", totals_pbm), dtype=float)
    # a compartment the DEM fills but the PBM leaves empty has no PBM composition of its
    # own: it is sampled at the PBM's composition of the whole outlet slice
    pooled = outlet[0].sum() / totals_pbm.sum() if totals_pbm.sum() > 0 else np.nan
    fraction = np.where(dem_totals >= 1, np.where(np.isnan(fraction), pooled, fraction), np.nan)
    return {
        "holdup": holdup,
        "holdup_by_slice": slices.tolist(),
        "outflow_per_s": outflow,
        "C_A": float(out_a.sum() / (out_a.sum() + out_b.sum())) if (out_a.sum() + out_b.sum()) > 0 else math.nan,
        "little_mean_residence_time_s": holdup / outflow if outflow > 0 else math.nan,
        "rsd_outlet": float(sampled_rsd(fraction, dem_totals, draws=SAMPLING_DRAWS)),
        "lacey_outlet": float(sampled_lacey(fraction, dem_totals, draws=SAMPLING_DRAWS)),
    }


#: (quantity key, label, unit) of the scalar rows, in the table's order
_SCALARS = (
    ("mean_residence_time_s", "mean residence time (pooled RTD)", "s"),
    ("rtd_variance_s2", "RTD variance (pooled)", "s^2"),
    ("rtd_recovered_fraction", "RTD recovered within the horizon", "-"),
    ("little_mean_residence_time_s", "mean residence time (hold-up / outflow)", "s"),
    ("holdup", "steady hold-up", "particles"),
    ("outflow_per_s", "steady outflow", "1/s"),
    ("C_A", "steady C_A", "-"),
    ("rsd_outlet", "outlet RSD (PBM sampled at the DEM's counts)", "-"),
    ("lacey_outlet", "outlet Lacey index (same basis)", "-"),
)


def _row(quantity: str, unit: str, dem: dict[str, Any] | None, pbm: dict[str, float]) -> dict[str, Any]:
    value, low, high = ((dem or {}).get(k, math.nan) for k in ("value", "low", "high"))
    row = {"quantity": quantity, "unit": unit, "dem": value, "dem_ci_low": low, "dem_ci_high": high}
    for mode in MODES:
        v = pbm.get(mode, math.nan)
        row[f"pbm_{mode}"] = v
        row[f"inside_{mode}"] = bool(inside(v, low, high)) if mode in pbm else None
    return row


def half_width(row: dict[str, Any], mode: str) -> float:
    """Half the width of a row's DEM 95 % interval, the scale below which a PBM value cannot
    be told from the DEM's; for the RTD overlap, whose interval is the noise band
    [noise low of the mode, 1], the whole band 1 - noise low. NaN when it is not known."""
    if row["key"] == "rtd_overlap":
        return 1.0 - float(row.get(f"noise_low_{mode}", math.nan))
    low, high = row.get("dem_ci_low"), row.get("dem_ci_high")
    if low is None or high is None:
        return math.nan
    return 0.5 * (float(high) - float(low))


def dem_density(records: pd.DataFrame, pooled_spec: dict[str, Any]) -> tuple[np.ndarray, np.ndarray, int]:
    """(bin edges, density, recovered particles) of the DEM's pooled RTD."""
    sample = rtd_pooled(records["entry_t_s"].to_numpy(float), records["exit_t_s"].to_numpy(float),
                        tuple(pooled_spec["entry_window_s"]), pooled_spec["horizon_s"])
    edges, density = rtd_density(sample.residence_s, pooled_spec["bin_s"], pooled_spec["horizon_s"])
    return edges, density, int(sample.residence_s.size)


def agreement_rows(dem_summary: dict[str, Any], records: pd.DataFrame, modes: dict[str, PbmMode]) -> list[dict]:
    """The agreement table (module docstring)."""
    steady = dem_summary.get("steady") or {}
    pooled_spec = dem_summary.get("pooled_rtd") or {}
    pbm_values = {mode: pbm_steady(m.result, steady) for mode, m in modes.items()}
    for mode, m in modes.items():
        if m.pooled is not None:
            pbm_values[mode].update({"mean_residence_time_s": m.pooled.mean_s, "rtd_variance_s2": m.pooled.variance_s2,
                                     "rtd_recovered_fraction": m.pooled.recovered_fraction})
    dem_values = {**steady, **{k: pooled_spec.get(k) for k in ("mean_residence_time_s", "rtd_variance_s2")},
                  "rtd_recovered_fraction": pooled_spec.get("recovered_fraction")}
    rows = []
    for key, label, unit in _SCALARS:
        pbm = {mode: v[key] for mode, v in pbm_values.items() if key in v}
        if dem_values.get(key) is None and not pbm:
            continue
        rows.append({"key": key, **_row(label, unit, dem_values.get(key), pbm)})
    if pooled_spec.get("n_entered") and len(records):
        edges, density, n = dem_density(records, pooled_spec)
        bin_s = float(pooled_spec["bin_s"])
        row = {"key": "rtd_overlap", "quantity": "RTD overlap (pooled; interval: noise band of the mode)",
               "unit": "-", "dem": 1.0, "dem_ci_low": math.nan, "dem_ci_high": 1.0}
        lows = []
        for mode in MODES:
            m = modes.get(mode)
            if m is None or m.pooled is None or n == 0:
                row[f"pbm_{mode}"], row[f"inside_{mode}"] = math.nan, None
                continue
            e_pbm = m.pooled.recovered_density_per_s
            overlap = rtd_overlap(density, e_pbm[: density.size], bin_s)
            band = overlap_noise_band(e_pbm, bin_s, n)
            lows.append(band.low)
            row[f"pbm_{mode}"], row[f"inside_{mode}"] = overlap, bool(overlap >= band.low)
            row[f"noise_median_{mode}"], row[f"noise_low_{mode}"] = band.median, band.low
        row["dem_ci_low"] = min(lows) if lows else math.nan
        rows.append(row)
    slices = steady.get("holdup_by_slice")
    if slices:
        for i, (value, low, high) in enumerate(zip(slices["value"], slices["low"], slices["high"])):
            pbm = {mode: v["holdup_by_slice"][i] for mode, v in pbm_values.items() if "holdup_by_slice" in v}
            rows.append({"key": f"holdup_slice_{i + 1}",
                         **_row(f"hold-up of axial slice {i + 1}", "particles",
                                {"value": value, "low": low, "high": high}, pbm)})
    return rows


def nx_sensitivity(fine_table: VelocityTable, config: PbmConfig, steady: SteadyStateRule,
                   dem_summary: dict[str, Any], coarse: dict[str, PbmMode]) -> dict[str, Any]:
    """Pooled-RTD mean and variance of each mode on a table binned at a finer NX (the
    measured rates re-fitted to the DEM's moves between the finer compartments, not
    regridded), against the same on the coarse table: the relative changes."""
    fine = run_modes(fine_table, config, steady, dem_summary)
    out: dict[str, Any] = {"nx": [int(next(iter(coarse.values())).result.summary.get("nx", 0)), fine_table.nx]}
    for mode in MODES:
        a, b = coarse.get(mode), fine.get(mode)
        if a is None or b is None or a.pooled is None or b.pooled is None:
            continue
        out[mode] = {
            "mean_s": [a.pooled.mean_s, b.pooled.mean_s],
            "variance_s2": [a.pooled.variance_s2, b.pooled.variance_s2],
            "change_mean": b.pooled.mean_s / a.pooled.mean_s - 1,
            "change_variance": b.pooled.variance_s2 / a.pooled.variance_s2 - 1,
        }
    return out
