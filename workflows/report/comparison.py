"""The side-by-side DEM / PBM report: comparison metrics, figures (paper Figs 3-10) and HTML.

Both sides reach this module in one shape, :class:`SideResults`, so every figure and metric
is computed from the same columns for DEM and PBM (:mod:`coupling.metrics`). The HTML page
is self-contained apart from the PNG files written beside it. Figures are drawn with
matplotlib's object API (no pyplot, so no backend is chosen or needed).
"""

from __future__ import annotations

import html
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from coupling.metrics import TIMESERIES_COLUMNS
from coupling.metrics import rtd_overlap as shared_rtd_overlap
from coupling.summary import ProcessSummary
from dem.steady import intervals_are_current
from dem.summary import DemSummary
from pbm.summary import PbmSummary
from workflows.analysis.agreement import AgreementRow

DEM_COLOUR, PBM_COLOUR = "#b2182b", "#2166ac"


@dataclass
class SideResults:
    """One side's CQAs. ``timeseries`` has :data:`TIMESERIES_COLUMNS` (DEM may add
    ``rsd_outlet_floor`` and ``rsd_blender_floor``, the random-mixture RSD); ``rtd`` has
    ``t_s`` and ``E_per_s``; ``rsd_by_slice`` is the RSD of each axial slice at the end
    (inlet to outlet), ``rsd_by_slice_floor`` its random-mixture floor (DEM only);
    ``summary`` the side's scalars (:class:`dem.summary.DemSummary`,
    :class:`pbm.summary.PbmSummary`)."""

    label: str
    timeseries: pd.DataFrame
    rtd: pd.DataFrame
    rsd_by_slice: np.ndarray
    summary: DemSummary | PbmSummary
    rsd_by_slice_floor: np.ndarray | None = None

    def __post_init__(self) -> None:
        missing = [c for c in TIMESERIES_COLUMNS if c not in self.timeseries.columns]
        if missing:
            raise ValueError(f"{self.label} timeseries lacks columns {missing}")
        missing = [c for c in ("t_s", "E_per_s") if c not in self.rtd.columns]
        if missing:
            raise ValueError(f"{self.label} rtd lacks columns {missing}")


@dataclass
class Study:
    """A parametric study for the report: curves keyed by the parameter's value."""

    title: str
    parameter: str
    figure: str
    trend: str
    rows: list[dict[str, Any]] = field(default_factory=list)


def rtd_overlap(dem_rtd: pd.DataFrame, pbm_rtd: pd.DataFrame) -> float:
    """:func:`coupling.metrics.rtd_overlap` of the two E(t) on the DEM's (uniform) bins: the
    PBM's interpolated there (zero outside its range), both renormalised on those bins, so a
    truncated tail does not count as a difference in shape (1 = identical, 0 = disjoint)."""
    t = dem_rtd["t_s"].to_numpy(float)
    if t.size < 2:
        return float("nan")
    e_dem = dem_rtd["E_per_s"].to_numpy(float)
    e_pbm = np.interp(t, pbm_rtd["t_s"].to_numpy(float), pbm_rtd["E_per_s"].to_numpy(float), left=0.0, right=0.0)
    bin_s = float(t[1] - t[0])
    norm_dem, norm_pbm = e_dem.sum() * bin_s, e_pbm.sum() * bin_s
    if norm_dem <= 0 or norm_pbm <= 0:
        return float("nan")
    return shared_rtd_overlap(e_dem / norm_dem, e_pbm / norm_pbm, bin_s)


def comparison_metrics(dem: SideResults, pbm: SideResults, feed_rate_per_s: float) -> dict[str, Any]:
    """Every number of the report's metrics table (also written to summary.json): the
    shared fields (:class:`coupling.summary.ProcessSummary`) side by side, the DEM's
    random-mixture floors beside its RSDs, and the wall times."""
    d, p = dem.summary, pbm.summary

    def rel(a, b):
        return (b - a) / a if a and np.isfinite(a) and np.isfinite(b) else float("nan")

    floors = isinstance(d, DemSummary)
    return {
        "mean_residence_time_dem_s": d.mean_residence_time_s,
        "mean_residence_time_pbm_s": p.mean_residence_time_s,
        "mean_residence_time_rel_diff": rel(d.mean_residence_time_s, p.mean_residence_time_s),
        "rtd_variance_dem_s2": d.rtd_variance_s2,
        "rtd_variance_pbm_s2": p.rtd_variance_s2,
        "rtd_overlap": rtd_overlap(dem.rtd, pbm.rtd),
        "rtd_recovered_fraction_dem": d.rtd_recovered_fraction,
        "rtd_recovered_fraction_pbm": p.rtd_recovered_fraction,
        "feed_rate_per_s": feed_rate_per_s,
        "steady_outflow_dem_per_s": d.steady_outflow_per_s,
        "steady_outflow_pbm_per_s": p.steady_outflow_per_s,
        "steady_C_A_dem": d.steady_C_A,
        "steady_C_A_pbm": p.steady_C_A,
        "final_rsd_outlet_dem": d.final_rsd_outlet,
        "final_rsd_outlet_dem_floor": d.final_rsd_outlet_floor if floors else None,
        "final_rsd_outlet_pbm": p.final_rsd_outlet,
        "final_rsd_blender_dem": d.final_rsd_blender,
        "final_rsd_blender_dem_floor": d.final_rsd_blender_floor if floors else None,
        "final_rsd_blender_pbm": p.final_rsd_blender,
        "holdup_final_dem": d.holdup_final,
        "holdup_final_pbm": p.holdup_final,
        "dem_wall_time_s": _wall_time_s(d),
        "pbm_wall_time_s": _wall_time_s(p),
        "speedup_pbm_over_dem": (_wall_time_s(d) / _wall_time_s(p) if _wall_time_s(d) and _wall_time_s(p) else None),
    }


def _wall_time_s(summary: ProcessSummary) -> float | None:
    """The side's wall time [s]: a field of the PBM's summary; the DEM's as the pipeline
    added it to the record (None for results post-processed outside it)."""
    return summary.wall_time_s if isinstance(summary, PbmSummary) else summary.extra.get("wall_time_s")


# --- figures -------------------------------------------------------------------------------


def _draw_rtd(ax, dem: SideResults, pbm: SideResults) -> None:
    for side, colour in ((dem, DEM_COLOUR), (pbm, PBM_COLOUR)):
        ax.step(side.rtd["t_s"], side.rtd["E_per_s"], where="mid", color=colour, label=side.label)
    ax.set(title="Residence time distribution (paper Fig. 7)", xlabel="t - t_pulse [s]", ylabel="E(t) [1/s]")


def _draw_rsd_axial(ax, dem: SideResults, pbm: SideResults) -> None:
    for side, colour in ((dem, DEM_COLOUR), (pbm, PBM_COLOUR)):
        n = len(side.rsd_by_slice)
        ax.plot(np.arange(1, n + 1), side.rsd_by_slice, "o-", color=colour, label=side.label)
    if dem.rsd_by_slice_floor is not None:
        n = len(dem.rsd_by_slice_floor)
        ax.plot(np.arange(1, n + 1), dem.rsd_by_slice_floor, ":", color=DEM_COLOUR, label="DEM random-mixture floor")
    ax.set(title="RSD along the blender at the end (Fig. 8a)", xlabel="axial compartment (inlet = 1)", ylabel="RSD")


def _draw_rsd_time(ax, dem: SideResults, pbm: SideResults) -> None:
    for side, colour in ((dem, DEM_COLOUR), (pbm, PBM_COLOUR)):
        ax.plot(side.timeseries["t_s"], side.timeseries["rsd_outlet"], color=colour, label=side.label)
    if "rsd_outlet_floor" in dem.timeseries:
        ax.plot(
            dem.timeseries["t_s"],
            dem.timeseries["rsd_outlet_floor"],
            ":",
            color=DEM_COLOUR,
            label="DEM random-mixture floor",
        )
    ax.set(title="RSD at the outlet (Fig. 8b)", xlabel="t [s]", ylabel="RSD across the last slice")


def _draw_c_a(ax, dem: SideResults, pbm: SideResults) -> None:
    for side, colour in ((dem, DEM_COLOUR), (pbm, PBM_COLOUR)):
        ax.plot(side.timeseries["t_s"], side.timeseries["C_A"], color=colour, label=side.label)
    ax.axhline(0.5, color="grey", lw=0.8)
    ax.set(title="Fraction of A in the outflow (Fig. 9)", xlabel="t [s]", ylabel="C_A", ylim=(0, 1))


def _draw_outflow(ax, dem: SideResults, pbm: SideResults) -> None:
    for side, colour in ((dem, DEM_COLOUR), (pbm, PBM_COLOUR)):
        ts = side.timeseries
        ax.plot(ts["t_s"], ts["outflow_A_per_s"] + ts["outflow_B_per_s"], color=colour, label=side.label)
    ax.set(title="Outflow rate over the weir (Fig. 10)", xlabel="t [s]", ylabel="particles / s")


def _draw_holdup(ax, dem: SideResults, pbm: SideResults) -> None:
    for side, colour in ((dem, DEM_COLOUR), (pbm, PBM_COLOUR)):
        ts = side.timeseries
        ax.plot(ts["t_s"], ts["holdup_A"] + ts["holdup_B"], color=colour, label=f"{side.label} A+B")
        ax.plot(ts["t_s"], ts["holdup_A"], "--", color=colour, lw=0.8, label=f"{side.label} A")
    ax.set(title="Hold-up", xlabel="t [s]", ylabel="particles in the blender")


PANELS = {
    "rtd": _draw_rtd,
    "rsd_axial": _draw_rsd_axial,
    "rsd_time": _draw_rsd_time,
    "c_a": _draw_c_a,
    "outflow": _draw_outflow,
    "holdup": _draw_holdup,
}


def plot_comparison(dem: SideResults, pbm: SideResults, out_dir: Path) -> dict[str, str]:
    """The paper's Figs 7-10 plus hold-up, DEM beside PBM, one PNG each, and ``overview.png``
    with all six. Returns figure key -> file name."""
    out_dir = Path(out_dir)
    files: dict[str, str] = {}
    for key, draw in PANELS.items():
        fig = Figure(figsize=(6.4, 4.0), layout="constrained")
        ax = fig.add_subplot()
        draw(ax, dem, pbm)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        fig.savefig(out_dir / f"{key}.png", dpi=110)
        files[key] = f"{key}.png"
    fig = Figure(figsize=(16, 8.5), layout="constrained")
    axes = fig.subplots(2, 3)
    for ax, draw in zip(axes.ravel(), PANELS.values()):
        draw(ax, dem, pbm)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.savefig(out_dir / "overview.png", dpi=80)
    files["overview"] = "overview.png"
    return files


#: line style and label of each PBM rate mode (:data:`workflows.analysis.agreement.MODES`), in every figure
MODE_STYLES = {
    "velocity": ("--", "PBM, velocity rates (paper eq. 4)"),
    "measured": ("-", "PBM, measured rates"),
    "phases": ("-.", "PBM, hidden mobility phases"),
}


def plot_agreement(
    rows: list[AgreementRow],
    dem_rtd: tuple[np.ndarray, np.ndarray] | None,
    pbm_rtd: dict[str, tuple[np.ndarray, np.ndarray]],
    out_dir: Path,
) -> dict[str, str]:
    """The pooled RTD (DEM histogram, each PBM mode's density on the same bins, all
    conditional on recovery within the horizon) and the steady axial hold-up profile (DEM
    means with their 95 % intervals, each PBM mode). Returns figure key -> file name."""
    files: dict[str, str] = {}
    if dem_rtd is not None:
        fig = Figure(figsize=(6.4, 4.0), layout="constrained")
        ax = fig.add_subplot()
        edges, density = dem_rtd
        ax.stairs(density, edges, color=DEM_COLOUR, label="DEM (pooled)")
        for mode, (m_edges, m_density) in pbm_rtd.items():
            style, label = MODE_STYLES[mode]
            ax.plot(0.5 * (m_edges[:-1] + m_edges[1:]), m_density, style, color=PBM_COLOUR, label=label)
        ax.set(title="Pooled RTD, entry window after steady state", xlabel="residence time [s]", ylabel="E [1/s]")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        fig.savefig(out_dir / "rtd_pooled.png", dpi=110)
        files["rtd_pooled"] = "rtd_pooled.png"
    slices = [r for r in rows if r.key.startswith("holdup_slice_")]
    if slices:
        fig = Figure(figsize=(6.4, 4.0), layout="constrained")
        ax = fig.add_subplot()
        i = np.arange(1, len(slices) + 1)
        dem = np.array([r.dem for r in slices], dtype=float)
        err = np.abs(np.array([[r.dem_ci_low, r.dem_ci_high] for r in slices], dtype=float).T - dem)
        ax.errorbar(i, dem, yerr=err, fmt="o", color=DEM_COLOUR, capsize=3, label="DEM (95 % interval)")
        for mode, (style, label) in MODE_STYLES.items():
            values = np.array([r.value(mode) for r in slices], dtype=float)
            if np.isfinite(values).any():
                ax.plot(i, values, style, marker=".", color=PBM_COLOUR, label=label)
        ax.set(title="Steady hold-up per axial slice", xlabel="axial compartment (inlet = 1)", ylabel="particles")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        fig.savefig(out_dir / "holdup_profile.png", dpi=110)
        files["holdup_profile"] = "holdup_profile.png"
    return files


def interval_method(steady: dict[str, Any]) -> str:
    """One sentence on how the DEM's intervals were had (``coupling/DEFINITIONS.md``)."""
    if not steady or not intervals_are_current(steady):
        return ""
    return (
        f"DEM intervals: the steady quantities' from overlapping batch means over {steady['batch_s']:g}-s batches "
        f"with Student's t at {steady['degrees_of_freedom']:.1f} degrees of freedom; "
        f"the pooled RTD's from a bootstrap over {steady['block_s']:g}-s blocks of entry time; C_A's binomial."
    )


def agreement_html(rows: list[AgreementRow], nx_sensitivity: dict[str, Any] | None, method: str = "") -> str:
    """The agreement table (:mod:`workflows.analysis.agreement`), the sentence on how the
    DEM's intervals were had, and the NX sensitivity as HTML."""
    if not rows:
        return "<p>No agreement table: the DEM run has no steady state to average over.</p>"

    def verdict(flag) -> str:
        return "–" if flag is None else ("inside" if flag else "<b>outside</b>")

    body = "".join(
        f"<tr><td>{html.escape(r.quantity)}</td><td>{html.escape(r.unit)}</td><td>{fmt(r.dem)}</td>"
        f"<td>{fmt(r.dem_ci_low)} – {fmt(r.dem_ci_high)}</td>"
        + "".join(f"<td>{fmt(r.value(m))}</td><td>{verdict(r.inside(m))}</td>" for m in MODE_STYLES)
        + "</tr>"
        for r in rows
    )
    head = (
        "<tr><th>quantity</th><th>unit</th><th>DEM</th><th>DEM 95 % interval</th>"
        + "".join(f"<th>{html.escape(label)}</th><th>verdict</th>" for _, label in MODE_STYLES.values())
        + "</tr>"
    )
    out = f"<table>{head}{body}</table>" + (f"<p>{html.escape(method)}</p>" if method else "")
    if nx_sensitivity:
        lines = []
        for mode in MODE_STYLES:
            entry = nx_sensitivity.get(mode)
            if entry:
                lines.append(
                    f"<tr><td>{html.escape(MODE_STYLES[mode][1])}</td><td>{fmt(entry['mean_s'])}</td>"
                    f"<td>{fmt(entry['change_mean'])}</td><td>{fmt(entry['variance_s2'])}</td>"
                    f"<td>{fmt(entry['change_variance'])}</td></tr>"
                )
        if lines:
            nx = ", ".join(str(v) for v in nx_sensitivity.get("nx", []))
            out += (
                f"<h3>Grid sensitivity (NX = {html.escape(nx)})</h3><table><tr><th>mode</th><th>mean [s]</th>"
                "<th>relative change</th><th>variance [s²]</th><th>relative change</th></tr>"
                + "".join(lines)
                + "</table>"
            )
    return out


# --- HTML ----------------------------------------------------------------------------------


def fmt(value: Any, digits: int = 4) -> str:
    """A value for an HTML cell: numbers to ``digits`` significant figures, "–" for a
    missing or non-finite one, yes / no for a flag."""
    if value is None:
        return "–"
    if isinstance(value, (bool, np.bool_)):
        return "yes" if value else "no"
    if isinstance(value, (float, np.floating)):
        if not math.isfinite(value):
            return "–"
        return f"{float(value):.{digits}g}"
    if isinstance(value, (list, tuple)):
        return ", ".join(fmt(v, digits) for v in value)
    return html.escape(str(value))


METRIC_ROWS = (
    ("Mean residence time [s]", "mean_residence_time_dem_s", "mean_residence_time_pbm_s"),
    ("RTD variance [s²]", "rtd_variance_dem_s2", "rtd_variance_pbm_s2"),
    ("RTD recovered fraction", "rtd_recovered_fraction_dem", "rtd_recovered_fraction_pbm"),
    ("Steady outflow [1/s]", "steady_outflow_dem_per_s", "steady_outflow_pbm_per_s"),
    ("Steady C_A", "steady_C_A_dem", "steady_C_A_pbm"),
    ("Final RSD at the outlet", "final_rsd_outlet_dem", "final_rsd_outlet_pbm"),
    ("Final whole-blender RSD", "final_rsd_blender_dem", "final_rsd_blender_pbm"),
    ("Final hold-up [particles]", "holdup_final_dem", "holdup_final_pbm"),
    ("Wall time [s]", "dem_wall_time_s", "pbm_wall_time_s"),
)


def render_html(
    title: str,
    metrics: dict[str, Any],
    figures: dict[str, str],
    provenance: dict[str, Any],
    studies: list[Study],
    notes: list[str],
    agreement: str = "",
) -> str:
    """The report page. ``figures`` maps keys to PNG names beside the page; ``agreement``
    is the HTML of :func:`agreement_html`."""
    rows = "".join(
        f"<tr><td>{label}</td><td>{fmt(metrics.get(d))}</td><td>{fmt(metrics.get(p))}</td></tr>"
        for label, d, p in METRIC_ROWS
    )
    derived = [
        ("Relative difference of mean residence time (PBM − DEM)/DEM", metrics.get("mean_residence_time_rel_diff")),
        ("RTD overlap 1 − ½∫|E_DEM − E_PBM| dt", metrics.get("rtd_overlap")),
        ("Feed rate [1/s]", metrics.get("feed_rate_per_s")),
        ("DEM random-mixture floor of the final outlet RSD", metrics.get("final_rsd_outlet_dem_floor")),
        ("DEM random-mixture floor of the final whole-blender RSD", metrics.get("final_rsd_blender_dem_floor")),
        ("PBM speed-up over DEM (wall time)", metrics.get("speedup_pbm_over_dem")),
    ]
    derived_rows = "".join(f"<tr><td>{label}</td><td colspan=2>{fmt(v)}</td></tr>" for label, v in derived)

    def img(key: str, caption: str) -> str:
        if key not in figures:
            return ""
        return f'<figure><img src="{html.escape(figures[key])}" alt="{html.escape(caption)}"><figcaption>{html.escape(caption)}</figcaption></figure>'

    study_html = ""
    for study in studies:
        header = "".join(f"<th>{html.escape(k)}</th>" for k in study.rows[0]) if study.rows else ""
        body = "".join("<tr>" + "".join(f"<td>{fmt(v)}</td>" for v in row.values()) + "</tr>" for row in study.rows)
        study_html += (
            f"<h3>{html.escape(study.title)}</h3><p>{html.escape(study.trend)}</p>"
            f"<table><tr>{header}</tr>{body}</table>"
            f'<figure><img src="{html.escape(study.figure)}" alt="{html.escape(study.title)}"></figure>'
        )
    prov_rows = "".join(
        f"<tr><td>{html.escape(k)}</td><td>{fmt(v) if not isinstance(v, dict) else '<pre>' + html.escape(json.dumps(v, indent=1)) + '</pre>'}</td></tr>"
        for k, v in provenance.items()
        if k != "config_toml"
    )
    config_block = f"<details><summary>Resolved configuration</summary><pre>{html.escape(provenance.get('config_toml', ''))}</pre></details>"
    note_html = "".join(f"<li>{html.escape(n)}</li>" for n in notes)
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title>
<style>
body {{ font-family: sans-serif; max-width: 1100px; margin: 2em auto; color: #222; }}
table {{ border-collapse: collapse; margin: 1em 0; }}
td, th {{ border: 1px solid #ccc; padding: 0.3em 0.7em; text-align: left; }}
figure {{ display: inline-block; margin: 0.5em; width: 47%; vertical-align: top; }}
figure img {{ width: 100%; }}
figcaption {{ font-size: 0.9em; color: #555; }}
.notes li {{ color: #8a4b00; }}
</style></head><body>
<h1>{html.escape(title)}</h1>
<ul class="notes">{note_html}</ul>
<h2>Agreement: each PBM rate mode against the DEM's 95 % intervals</h2>
{agreement}
{img("rtd_pooled", "Pooled RTD: DEM and both PBM rate modes")}
{img("holdup_profile", "Steady hold-up along the blender")}
<h2>Metrics (PBM with the paper's velocity rates; RTD from the paper's 1-s tag window)</h2>
<table><tr><th>quantity</th><th>DEM</th><th>PBM</th></tr>{rows}{derived_rows}</table>
<h2>DEM and PBM side by side</h2>
{img("geometry", "Blender geometry (impeller, weir)")}
{img("rtd", "RTD E(t) (paper Fig. 7)")}
{img("rsd_axial", "RSD vs axial position at the end (Fig. 8a)")}
{img("rsd_time", "RSD vs time at the outlet (Fig. 8b)")}
{img("c_a", "C_A vs time (Fig. 9)")}
{img("outflow", "Outflow rate vs time (Fig. 10)")}
{img("holdup", "Hold-up vs time")}
<h2>Studies with the PBM on the DEM's tables (paper Figs 3-6)</h2>
{study_html}
<h2>Provenance</h2>
<table>{prov_rows}</table>
{config_block}
</body></html>
"""
