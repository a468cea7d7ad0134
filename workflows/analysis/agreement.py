"""The agreement table: every DEM quantity with its 95 % interval, each PBM rate mode's
value, and whether that value lies inside the interval.

One :class:`AgreementRow` per quantity (:func:`agreement_rows`): the DEM's value and
interval and, per PBM rate mode (``velocity``: the paper's eq. 4 rule; ``measured``: rates
fitted to the DEM's particle moves), a :class:`ModeValue`. In ``summary.json`` a row is
written flat (:meth:`AgreementRow.record`): ``pbm_<mode>`` and ``inside_<mode>`` per mode. The DEM values and intervals come from :mod:`dem.steady`; the PBM's are
computed here by the same definitions (:mod:`coupling.metrics`) from the PBM's own output,
each side over the time after its own steady state (one rule, :class:`SteadyStateRule`):

* hold-up, hold-up per axial slice, outflow, C_A, Little's-law mean residence time:
  means over the output times after the PBM's steady-state time;
* outlet RSD and Lacey index on one basis: the PBM's mean steady composition of each
  last-slice compartment sampled binomially at the DEM's particle numbers there, dump by
  steady dump (:func:`coupling.metrics.sampled_rsd`, :func:`~coupling.metrics.sampled_lacey`;
  at their means when the results carry no per-dump counts), against the DEM's own
  (sampled by nature) values;
* the pooled RTD: mean, variance and recovered fraction over the DEM's entry window and
  horizon (:func:`pbm.rtd.pooled_rtd`); the overlap of the two densities is judged against
  the noise band (:func:`coupling.intervals.overlap_noise_band`): what the DEM's number
  of recovered particles drawn from the PBM's own E(t) would score. The row's ``dem`` is 1
  (a perfect model), its interval [noise low of the mode, 1]; ``inside_<mode>`` = overlap
  >= that mode's noise low.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from coupling.intervals import inside, overlap_noise_band
from coupling.metrics import SteadyStateRule, rtd_density, rtd_overlap, rtd_pooled, sampled_lacey, sampled_rsd
from coupling.tables import VelocityTable
from dem.summary import DemSummary, PooledRtdSummary
from pbm.config import PbmConfig
from pbm.model import RATE_MODES, supported_modes
from pbm.rtd import PooledRtd, pooled_rtd
from pbm.simulate import PbmResult, simulate

#: the PBM's rate modes, in the order of every table and figure (:data:`pbm.model.RATE_MODES`)
MODES = RATE_MODES
#: binomial draws of the sampled RSD / Lacey index (their Monte-Carlo error is < 0.5 %);
#: at the DEM's per-dump counts, ten times as many samplings in all, spread over the dumps
SAMPLING_DRAWS = 2000


@dataclass
class PbmMode:
    """One PBM rate mode's run on the DEM's table and its pooled RTD (None without one)."""

    mode: str
    result: PbmResult
    pooled: PooledRtd | None


def run_modes(
    table: VelocityTable,
    config: PbmConfig,
    steady: SteadyStateRule,
    dem_summary: DemSummary,
    mode_updates: dict[str, dict[str, Any]] | None = None,
) -> dict[str, PbmMode]:
    """The PBM in each rate mode the table supports (``measured`` needs its rates,
    ``phases`` its phase model; the mode ``config`` asks for runs in any case, so a table
    without what it needs raises ConfigError), with the pooled RTD over the DEM's entry
    window and horizon when the DEM has one. ``mode_updates``: per mode, further
    PbmConfig fields (a fill law's exponents fitted in that mode's rates)."""
    pooled_spec = dem_summary.pooled_rtd
    available = supported_modes(table)
    modes = {}
    for mode in MODES:
        if mode not in available and config.rates != mode:
            continue
        cfg = config.model_copy(update={"rates": mode, **(mode_updates or {}).get(mode, {})})
        result = simulate(table, cfg, steady=steady)
        pooled = None
        if dem_summary.has_pooled_rtd:
            pooled = pooled_rtd(
                table,
                cfg,
                entry_window=pooled_spec.entry_window_s,
                horizon_s=pooled_spec.horizon_s,
                schedule=result.schedule,
            )
        modes[mode] = PbmMode(mode, result, pooled)
    return modes


def steady_outputs(result: PbmResult) -> np.ndarray:
    """Which of the PBM's outputs are steady: after its own steady-state time (the rule
    the DEM's own curve is judged by), none when it has none."""
    t_ss = result.summary.steady_time
    return result.times > (t_ss if t_ss is not None else result.times[-1])


def pbm_steady(
    result: PbmResult, dem_steady: dict[str, Any], outlet_counts: np.ndarray | None = None
) -> dict[str, Any]:
    """The PBM's values of the :mod:`dem.steady` quantities (module docstring);
    ``outlet_counts`` (steady dumps, 2, NY): the DEM's A and B in each outlet compartment at
    each steady dump (:meth:`dem.post.DemResults.steady_outlet_counts`), whose totals are
    the counts at which the outlet RSD and Lacey index are sampled; None: the DEM's mean
    counts."""
    after = steady_outputs(result)
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
    # a compartment the DEM fills but the PBM leaves empty has no PBM composition of its
    # own: it is sampled at the PBM's composition of the whole outlet slice
    pooled = outlet[0].sum() / totals_pbm.sum() if totals_pbm.sum() > 0 else np.nan
    fraction = np.where(np.isnan(fraction), pooled, fraction)
    if outlet_counts is not None and len(outlet_counts) and np.isfinite(pooled):
        # The DEM's RSD is a mean over dumps of the RSD at that dump's counts, which
        # fluctuate: a compartment holding 0.7 particles on average is left out of the mean
        # counts' RSD but holds 1-3 particles (fractions 0 or 1) at many dumps.
        # One sampling per (repeat, dump), pooled over those in which the metric is
        # defined: the DEM's mean counts each dump in which it is defined once.
        counts = np.asarray(outlet_counts, dtype=float).sum(axis=1)
        repeats = max(1, math.ceil(SAMPLING_DRAWS * 10 / len(counts)))
        every = np.broadcast_to(counts, (repeats, *counts.shape))
        sampled = {
            "rsd_outlet": sampled_rsd(fraction, every, draws=1),
            "lacey_outlet": sampled_lacey(fraction, every, draws=1),
        }
        sampled = {k: float(np.nanmean(v)) if np.isfinite(v).any() else math.nan for k, v in sampled.items()}
    else:
        dem_totals = np.asarray(dem_steady.get("outlet_totals", totals_pbm), dtype=float)
        fraction = np.where(dem_totals >= 1, fraction, np.nan)
        sampled = {
            "rsd_outlet": float(sampled_rsd(fraction, dem_totals, draws=SAMPLING_DRAWS)),
            "lacey_outlet": float(sampled_lacey(fraction, dem_totals, draws=SAMPLING_DRAWS)),
        }
    return {
        "holdup": holdup,
        "holdup_by_slice": slices.tolist(),
        "outflow_per_s": outflow,
        "C_A": float(out_a.sum() / (out_a.sum() + out_b.sum())) if (out_a.sum() + out_b.sum()) > 0 else math.nan,
        "little_mean_residence_time_s": holdup / outflow if outflow > 0 else math.nan,
        **sampled,
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


@dataclass(frozen=True)
class ModeValue:
    """One PBM rate mode's value of a quantity and whether it lies inside the DEM's
    interval (None: the mode has no value). For the RTD overlap, the noise band's median
    and low end for a DEM-sized sample of that mode's RTD."""

    value: float
    inside: bool | None
    noise_median: float | None = None
    noise_low: float | None = None


@dataclass(frozen=True)
class AgreementRow:
    """One quantity of the agreement table: the DEM's value with its 95 % interval, and
    each PBM rate mode's value (:class:`ModeValue`)."""

    key: str
    quantity: str
    unit: str
    dem: float
    dem_ci_low: float
    dem_ci_high: float
    pbm: Mapping[str, ModeValue] = field(default_factory=dict)

    def value(self, mode: str) -> float:
        """The PBM's value in ``mode``; NaN when the mode did not run."""
        m = self.pbm.get(mode)
        return math.nan if m is None else m.value

    def inside(self, mode: str) -> bool | None:
        m = self.pbm.get(mode)
        return None if m is None else m.inside

    def half_width(self, mode: str) -> float:
        """The one half-width rule: half the width of the DEM's 95 % interval, the scale
        below which a PBM value cannot be told from the DEM's; for the RTD overlap, whose
        interval is the noise band [noise low of the mode, 1], the whole band 1 - noise
        low. NaN when it is not known."""
        if self.key == "rtd_overlap":
            m = self.pbm.get(mode)
            return math.nan if m is None or m.noise_low is None else 1.0 - m.noise_low
        return 0.5 * (float(self.dem_ci_high) - float(self.dem_ci_low))

    def record(self) -> dict[str, Any]:
        """The row as ``summary.json`` holds it: flat, ``pbm_<mode>`` and ``inside_<mode>``
        for every mode of :data:`MODES` (NaN / None for a mode that did not run)."""
        out: dict[str, Any] = {
            "key": self.key,
            "quantity": self.quantity,
            "unit": self.unit,
            "dem": self.dem,
            "dem_ci_low": self.dem_ci_low,
            "dem_ci_high": self.dem_ci_high,
        }
        for mode in (*MODES, *(m for m in self.pbm if m not in MODES)):
            m = self.pbm.get(mode)
            out[f"pbm_{mode}"] = math.nan if m is None else m.value
            out[f"inside_{mode}"] = None if m is None else m.inside
            if m is not None and m.noise_low is not None:
                out[f"noise_median_{mode}"], out[f"noise_low_{mode}"] = m.noise_median, m.noise_low
        return out


def _row(key: str, quantity: str, unit: str, dem: dict[str, Any] | None, pbm: dict[str, float]) -> AgreementRow:
    value, low, high = ((dem or {}).get(k, math.nan) for k in ("value", "low", "high"))
    modes = {mode: ModeValue(v, bool(inside(v, low, high))) for mode, v in pbm.items()}
    return AgreementRow(key, quantity, unit, value, low, high, modes)


def dem_density(records: pd.DataFrame, pooled_spec: PooledRtdSummary) -> tuple[np.ndarray, np.ndarray, int]:
    """(bin edges, density, recovered particles) of the DEM's pooled RTD."""
    sample = rtd_pooled(
        records["entry_t_s"].to_numpy(float),
        records["exit_t_s"].to_numpy(float),
        pooled_spec.entry_window_s,
        pooled_spec.horizon_s,
    )
    edges, density = rtd_density(sample.residence_s, pooled_spec.bin_s, pooled_spec.horizon_s)
    return edges, density, int(sample.residence_s.size)


def agreement_rows(
    dem_summary: DemSummary,
    records: pd.DataFrame,
    modes: dict[str, PbmMode],
    outlet_counts: np.ndarray | None = None,
) -> list[AgreementRow]:
    """The agreement table (module docstring); ``outlet_counts``: see :func:`pbm_steady`."""
    steady = dem_summary.steady
    pooled_spec = dem_summary.pooled_rtd if dem_summary.has_pooled_rtd else None
    pbm_values = {mode: pbm_steady(m.result, steady, outlet_counts) for mode, m in modes.items()}
    for mode, m in modes.items():
        if m.pooled is not None:
            pbm_values[mode].update(
                {
                    "mean_residence_time_s": m.pooled.mean_s,
                    "rtd_variance_s2": m.pooled.variance_s2,
                    "rtd_recovered_fraction": m.pooled.recovered_fraction,
                }
            )
    dem_values = dict(steady)
    if pooled_spec is not None:
        dem_values.update(
            {
                "mean_residence_time_s": pooled_spec.mean_residence_time_s.record(),
                "rtd_variance_s2": pooled_spec.rtd_variance_s2.record(),
                "rtd_recovered_fraction": pooled_spec.recovered_fraction.record(),
            }
        )
    rows = []
    for key, label, unit in _SCALARS:
        pbm = {mode: v[key] for mode, v in pbm_values.items() if key in v}
        if dem_values.get(key) is None and not pbm:
            continue
        rows.append(_row(key, label, unit, dem_values.get(key), pbm))
    if pooled_spec is not None and len(records):
        edges, density, n = dem_density(records, pooled_spec)
        bin_s = float(pooled_spec.bin_s)
        overlaps = {}
        for mode in MODES:
            m = modes.get(mode)
            if m is None or m.pooled is None or n == 0:
                continue
            e_pbm = m.pooled.recovered_density_per_s
            overlap = rtd_overlap(density, e_pbm[: density.size], bin_s)
            band = overlap_noise_band(e_pbm, bin_s, n)
            overlaps[mode] = ModeValue(overlap, bool(overlap >= band.low), band.median, band.low)
        low = min((m.noise_low for m in overlaps.values()), default=math.nan)
        rows.append(
            AgreementRow(
                "rtd_overlap", "RTD overlap (pooled; interval: noise band of the mode)", "-", 1.0, low, 1.0, overlaps
            )
        )
    slices = steady.get("holdup_by_slice")
    if slices:
        for i, (value, low, high) in enumerate(zip(slices["value"], slices["low"], slices["high"])):
            pbm = {mode: v["holdup_by_slice"][i] for mode, v in pbm_values.items() if "holdup_by_slice" in v}
            rows.append(
                _row(
                    f"holdup_slice_{i + 1}",
                    f"hold-up of axial slice {i + 1}",
                    "particles",
                    {"value": value, "low": low, "high": high},
                    pbm,
                )
            )
    return rows


def nx_sensitivity(
    fine_table: VelocityTable,
    config: PbmConfig,
    steady: SteadyStateRule,
    dem_summary: DemSummary,
    coarse: dict[str, PbmMode],
) -> dict[str, Any]:
    """Pooled-RTD mean and variance of each mode on a table binned at a finer NX (the
    measured rates re-fitted to the DEM's moves between the finer compartments, not
    regridded), against the same on the coarse table: the relative changes."""
    fine = run_modes(fine_table, config, steady, dem_summary)
    out: dict[str, Any] = {"nx": [int(next(iter(coarse.values())).result.summary.nx), fine_table.nx]}
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


@dataclass(frozen=True)
class Judged:
    """One quantity judged by the project's one rule: ``value`` agrees with ``reference``
    when |value - reference| <= ``tolerance``. A quantity that cannot be judged (a NaN,
    or no positive tolerance) does not agree: what nobody can check has not passed."""

    key: str
    quantity: str
    value: float
    reference: float
    tolerance: float

    @property
    def error(self) -> float:
        return abs(self.value - self.reference)

    @property
    def judgeable(self) -> bool:
        return all(math.isfinite(v) for v in (self.value, self.reference, self.tolerance)) and self.tolerance > 0

    @property
    def deviation(self) -> float:
        """|value - reference| / tolerance: <= 1 agrees; NaN when not judgeable."""
        return self.error / self.tolerance if self.judgeable else math.nan

    @property
    def ok(self) -> bool:
        return self.judgeable and self.error <= self.tolerance
