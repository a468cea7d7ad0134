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
    """The scalars of ``summary.json``'s ``metrics`` (the page shows the wall times): the
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
    ax.set(title="Tagged RTD (paper Fig. 7)", xlabel="t - t_pulse [s]", ylabel="E(t) [1/s]")


def _draw_rsd_axial(ax, dem: SideResults, pbm: SideResults) -> None:
    for side, colour in ((dem, DEM_COLOUR), (pbm, PBM_COLOUR)):
        n = len(side.rsd_by_slice)
        ax.plot(np.arange(1, n + 1), side.rsd_by_slice, "o-", color=colour, label=side.label)
    if dem.rsd_by_slice_floor is not None:
        n = len(dem.rsd_by_slice_floor)
        ax.plot(np.arange(1, n + 1), dem.rsd_by_slice_floor, ":", color=DEM_COLOUR, label="DEM random-mixture floor")
    ax.set(
        title="Raw RSD along the blender at the end (Fig. 8a)", xlabel="axial compartment (inlet = 1)", ylabel="raw RSD"
    )


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
    ax.set(title="Raw RSD at the outlet (Fig. 8b)", xlabel="t [s]", ylabel="raw RSD across the last slice")


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

    body = "".join(
        f"<tr><td>{html.escape(r.quantity)}</td><td>{html.escape(r.unit)}</td><td>{fmt(r.dem)}</td>"
        f"<td>{fmt(r.dem_ci_low)} – {fmt(r.dem_ci_high)}</td>"
        + "".join(f"<td>{fmt(r.value(m))}</td><td>{_verdict(r.inside(m))}</td>" for m in MODE_STYLES)
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


# --- the recommendation --------------------------------------------------------------------

#: the agreement table's rows the report's first screen shows, in this order
HEADLINE = ("mean_residence_time_s", "rtd_variance_s2", "holdup", "outflow_per_s", "C_A", "rsd_outlet", "lacey_outlet")


@dataclass(frozen=True)
class ModeScore:
    """One rate mode on the agreement table: its rows inside the DEM's 95 % interval, its
    rows judged at all, and its mean |PBM − DEM| in half-widths of the DEM's interval
    (:meth:`~workflows.analysis.agreement.AgreementRow.half_width`) over the rows judged."""

    mode: str
    inside: int
    judged: int
    deviation: float


@dataclass(frozen=True)
class Recommendation:
    """The rate mode to trust: the most agreement-table rows inside the DEM's intervals. A
    tie on that count goes to the smaller mean deviation (:class:`ModeScore`), then to the
    mode with fewer fitted parameters (the order of :data:`MODE_STYLES`). ``scores``: every
    mode that ran, best first; ``tied``: the other modes with as many rows inside."""

    mode: str
    scores: tuple[ModeScore, ...]
    tied: tuple[str, ...] = ()

    @property
    def score(self) -> ModeScore:
        return self.scores[0]

    def record(self) -> dict[str, Any]:
        """The recommendation as ``summary.json`` holds it."""
        return {
            "mode": self.mode,
            "tied": list(self.tied),
            "scores": {s.mode: {"inside": s.inside, "judged": s.judged, "deviation": s.deviation} for s in self.scores},
        }


def half_widths_off(row: AgreementRow, mode: str) -> float:
    """|PBM - DEM| of ``row`` in ``mode``, in half-widths of the DEM's interval; NaN when
    the half-width is not known or is zero (a point interval gives no scale)."""
    width = row.half_width(mode)
    return abs(row.value(mode) - row.dem) / width if width > 0 else math.nan


def recommend(rows: list[AgreementRow]) -> Recommendation | None:
    """The :class:`Recommendation` of the agreement table ``rows``; None when no mode was
    judged on any row (no steady DEM state to average over)."""
    order = list(MODE_STYLES)
    scores = []
    for mode in order:
        judged = [r for r in rows if r.inside(mode) is not None]
        if not judged:
            continue
        off = [v for v in (half_widths_off(r, mode) for r in judged) if math.isfinite(v)]
        deviation = float(np.mean(off)) if off else math.nan
        scores.append(ModeScore(mode, sum(bool(r.inside(mode)) for r in judged), len(judged), deviation))
    if not scores:
        return None
    ranked = sorted(
        scores,
        key=lambda s: (-s.inside, s.deviation if math.isfinite(s.deviation) else math.inf, order.index(s.mode)),
    )
    best = ranked[0]
    return Recommendation(best.mode, tuple(ranked), tuple(s.mode for s in ranked[1:] if s.inside == best.inside))


def _listed(labels: list[str], shown: int = 3) -> str:
    """``labels`` as prose, the first ``shown``: "a, b, c and 4 more", "a and b", "a"."""
    if len(labels) > shown:
        return ", ".join(labels[:shown]) + f" and {len(labels) - shown} more"
    return " and ".join(filter(None, [", ".join(labels[:-1]), *labels[-1:]]))


def why(rec: Recommendation, rows: list[AgreementRow]) -> str:
    """One sentence on why ``rec.mode`` is the mode to trust, read off the table ``rows``."""
    best = rec.score
    if len(rec.scores) == 1:
        return f"It is the only rate mode the DEM's table supports; it lies inside on {best.inside} of {best.judged}."
    runner = rec.scores[1]
    if rec.tied:
        if best.deviation < runner.deviation or (math.isfinite(best.deviation) and not math.isfinite(runner.deviation)):
            return (
                f"It ties with the {runner.mode} rates on the count and lies nearer the DEM: on average "
                f"{fmt(best.deviation, 2)} half-widths of the DEM's interval from it, against "
                f"{fmt(runner.deviation, 2)}."
            )
        return (
            f"It ties with the {runner.mode} rates on the count and on the distance from the DEM "
            f"({fmt(best.deviation, 2)} half-widths of the DEM's interval) and has fewer fitted parameters."
        )
    gained = [r.quantity for r in rows if r.inside(best.mode) and r.inside(runner.mode) is False]
    missed = [r for r in rows if r.inside(best.mode) is False]
    misses = (
        "it misses nothing"
        if not missed
        else "its "
        + ("one miss is " if len(missed) == 1 else "misses are ")
        + _listed([f"{r.quantity} ({fmt(half_widths_off(r, best.mode), 2)} half-widths off)" for r in missed])
    )
    where = f"on {_listed(gained)} where" if gained else "on more rows than"
    return (
        f"It lies inside the DEM's interval {where} the runner-up, the {runner.mode} rates "
        f"({runner.inside} of {runner.judged} inside){', lies outside' if gained else ''}; {misses}."
    )


def _cell_interval(row: AgreementRow) -> str:
    return f"{fmt(row.dem)} [{fmt(row.dem_ci_low)}, {fmt(row.dem_ci_high)}]"


def _verdict(flag: bool | None) -> str:
    return "–" if flag is None else ("inside" if flag else "<b>outside</b>")


def bottom_line_html(rec: Recommendation | None, rows: list[AgreementRow], configured: str) -> str:
    """The report's first screen: the rate mode to trust with its score on the agreement
    table and why, then the headline quantities (:data:`HEADLINE`): the DEM's value with
    its 95 % interval, that mode's PBM value and the verdict. ``configured``: the mode the
    configuration asks for (a line says how to switch when it is another)."""
    if rec is None:
        return (
            '<section id="bottom-line"><h2>Bottom line</h2><p><b>No rate mode can be recommended:</b> '
            "the DEM run has no steady state to average over, so no PBM value was judged.</p></section>"
        )
    best = rec.score
    others = "; ".join(f"{s.mode} rates {s.inside} of {s.judged}" for s in rec.scores[1:])
    tie = (
        f" Tied on the count with {', '.join(rec.tied)}: broken by the smaller mean distance from the DEM in "
        "half-widths of its interval, then by the fewer fitted parameters (velocity, measured, phases)."
        if rec.tied
        else ""
    )
    switch = (
        ""
        if configured == rec.mode
        else f'<p>The configuration asks for <code>rates = "{html.escape(configured)}"</code>; set '
        f'<code>rates = "{html.escape(rec.mode)}"</code> in its <code>[pbm]</code> section to run this mode.</p>'
    )
    by_key = {r.key: r for r in rows}
    body = "".join(
        f"<tr><td>{html.escape(r.quantity)}</td><td>{html.escape(r.unit)}</td><td>{_cell_interval(r)}</td>"
        f"<td>{fmt(r.value(rec.mode))}</td><td>{_verdict(r.inside(rec.mode))}</td></tr>"
        for r in (by_key[k] for k in HEADLINE if k in by_key)
    )
    return (
        '<section id="bottom-line"><h2>Bottom line</h2>'
        f'<p class="verdict">Recommended rate mode: <b>{html.escape(MODE_STYLES[rec.mode][1])}</b> '
        f'(<code>rates = "{html.escape(rec.mode)}"</code>), <b>{best.inside} of {best.judged}</b> '
        f"agreement-table rows inside the DEM's 95 % intervals ({html.escape(others) or 'the only mode run'}).</p>"
        f"<p>{html.escape(why(rec, rows))}{html.escape(tie)}</p>{switch}"
        f'<table id="headline"><tr><th>quantity</th><th>unit</th><th>DEM [95 % interval]</th>'
        f"<th>PBM, {html.escape(rec.mode)} rates</th><th>verdict</th></tr>{body}</table>"
        '<p class="small">Each quantity as <code>coupling/DEFINITIONS.md</code> defines it, the same rows as in '
        "the agreement table below; <i>inside</i>: the PBM's value lies in the DEM's 95 % interval. The curves "
        f"further down show the PBM with the {html.escape(rec.mode)} rates.</p></section>"
    )


# --- warnings ------------------------------------------------------------------------------

#: how the DEM post-processing's bookkeeping checks of the solver's output read
#: (:func:`dem.post.accounting`, the dump spacing): diagnostics of the DEM run, for the end
#: of the page; its notes on the steady state and the RTD concern the comparison itself
SOLVER_DIAGNOSTICS = (
    "accounting:",
    "discharge cross-check:",
    "solver thermo counters",
    "the last dump lists",
    "particle-snapshots lie outside the vessel",
    "particles are still in the dumps",
    "pairs of consecutive dumps",
    "atom types",
    "particle-snapshots reappeared",
)


def split_warnings(warnings: tuple[str, ...] | list[str]) -> tuple[list[str], list[str]]:
    """The DEM's warnings as (about the comparison's validity: the top of the page; solver
    diagnostics: its end). A warning not known as a diagnostic stays at the top."""
    diagnostics = [w for w in warnings if any(marker in w for marker in SOLVER_DIAGNOSTICS)]
    return [w for w in warnings if w not in diagnostics], diagnostics


# --- the page ------------------------------------------------------------------------------


@dataclass(frozen=True)
class ReportFile:
    """A file the run wrote, linked from the page: ``href`` relative to the page."""

    href: str
    what: str


def _img(src: str, alt: str, caption: str = "", wide: bool = False) -> str:
    cls = ' class="wide"' if wide else ""
    cap = f"<figcaption>{html.escape(caption)}</figcaption>" if caption else ""
    return f'<figure{cls}><img src="{html.escape(src)}" alt="{html.escape(alt)}">{cap}</figure>'


def files_html(files: list[ReportFile]) -> str:
    """The "Files" section: one link per file the run wrote."""
    body = "".join(
        f'<tr><td><a href="{html.escape(f.href)}">{html.escape(f.href)}</a></td><td>{html.escape(f.what)}</td></tr>'
        for f in files
    )
    return f'<h2 id="files">Files</h2><table><tr><th>file</th><th>what it holds</th></tr>{body}</table>'


def render_html(
    title: str,
    *,
    bottom_line: str,
    agreement: str,
    figures: dict[str, str],
    shown_mode: str,
    metrics: dict[str, Any],
    studies_mode: str = "velocity",
    provenance: dict[str, Any],
    studies: list[Study],
    notes: list[str] = (),
    sections: list[str] = (),
    files: list[ReportFile] = (),
    diagnostics: list[str] = (),
) -> str:
    """The report page: ``notes`` on the comparison's validity, the ``bottom_line``
    (:func:`bottom_line_html`), then the details: ``agreement`` (:func:`agreement_html`),
    the curves of the DEM and of the PBM in ``shown_mode`` (``figures``: keys to PNG names
    beside the page), further ``sections`` (HTML), the studies (run in ``studies_mode``), the cost (``metrics``'
    wall times), the ``files``, the provenance and last the solver ``diagnostics``."""
    mode_label = f"PBM, {shown_mode} rates"
    panels = {
        "rtd": f"Tagged RTD E(t) (paper Fig. 7), DEM and {mode_label}",
        "rsd_axial": f"Raw RSD per axial slice at the end (Fig. 8a), DEM with its random-mixture floor and {mode_label}",
        "rsd_time": f"Raw RSD across the outlet slice over time (Fig. 8b), DEM with its floor and {mode_label}",
        "c_a": f"Fraction of A in the outflow, C_A, over time (Fig. 9), DEM and {mode_label}",
        "outflow": f"Outflow rate over the weir over time (Fig. 10), DEM and {mode_label}",
        "holdup": f"Hold-up in the blender over time, total and of A, DEM and {mode_label}",
    }

    def img(key: str, alt: str, caption: str = "", wide: bool = False) -> str:
        return _img(figures[key], alt, caption, wide) if key in figures else ""

    singles = " · ".join(
        f'<a href="{html.escape(figures[k])}">{html.escape(figures[k])}</a>' for k in panels if k in figures
    )
    curves = (
        img(
            "overview",
            f"Six panels, DEM against {mode_label}: " + "; ".join(panels.values()),
            "",
            wide=True,
        )
        + (f"<p>Each panel alone: {singles}.</p>" if singles else "")
        + "<p><b>Raw RSD</b> (the figures' RSD): eq. 6 on each side's counts as they are. The PBM's expected "
        "counts carry no sampling noise, so its raw RSD falls towards 0 while the DEM's stays at its "
        "random-mixture floor (dotted); the like-for-like comparison is the outlet RSD of the table above, the "
        "PBM sampled at the DEM's counts (<code>coupling/DEFINITIONS.md</code>). <b>Tagged RTD</b> (Fig. 7): the "
        "paper's 1-s tag window, a second and noisier estimate; the table's RTD is the pooled one.</p>"
    )
    study_html = ""
    for study in studies:
        header = "".join(f"<th>{html.escape(k)}</th>" for k in study.rows[0]) if study.rows else ""
        body = "".join("<tr>" + "".join(f"<td>{fmt(v)}</td>" for v in row.values()) + "</tr>" for row in study.rows)
        study_html += (
            f"<h3>{html.escape(study.title)}</h3><p>{html.escape(study.trend)}</p>"
            f"<table><tr>{header}</tr>{body}</table>"
            + _img(study.figure, f"{study.title} study with the PBM on the DEM's tables: {study.trend}")
        )
    dem_s, pbm_s = metrics.get("dem_wall_time_s"), metrics.get("pbm_wall_time_s")
    cost = (
        f"<h2>Cost</h2><p>Wall time: DEM {fmt(dem_s)} s, {html.escape(mode_label)} {fmt(pbm_s)} s"
        + (f" (the PBM {fmt(metrics.get('speedup_pbm_over_dem'))} times faster)" if dem_s and pbm_s else "")
        + f"; feed {fmt(metrics.get('feed_rate_per_s'))} particles/s.</p>"
    )
    prov_rows = "".join(
        f"<tr><td>{html.escape(k)}</td><td>{fmt(v) if not isinstance(v, dict) else '<pre>' + html.escape(json.dumps(v, indent=1)) + '</pre>'}</td></tr>"
        for k, v in provenance.items()
        if k != "config_toml"
    )
    config_block = f"<details><summary>Resolved configuration</summary><pre>{html.escape(provenance.get('config_toml', ''))}</pre></details>"
    pointer = (
        [
            f'The DEM run\'s bookkeeping raised {len(diagnostics)} <a href="#diagnostics">solver diagnostics</a>, '
            "listed at the end."
        ]
        if diagnostics
        else []
    )
    items = [html.escape(n) for n in notes] + pointer
    note_html = f'<ul class="notes">{"".join(f"<li>{n}</li>" for n in items)}</ul>' if items else ""
    diagnostics_html = (
        "<h2 id=\"diagnostics\">Solver diagnostics</h2><p>The DEM post-processing's checks of the solver's "
        "bookkeeping: particle accounting, thermo counters, dump spacing (<code>dem/post.py</code>).</p><ul>"
        + "".join(f"<li>{html.escape(d)}</li>" for d in diagnostics)
        + "</ul>"
        if diagnostics
        else ""
    )
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title>
<style>
body {{ font-family: sans-serif; max-width: 1100px; margin: 2em auto; color: #222; }}
table {{ border-collapse: collapse; margin: 1em 0; }}
td, th {{ border: 1px solid #ccc; padding: 0.3em 0.7em; text-align: left; }}
figure {{ display: inline-block; margin: 0.5em; width: 47%; vertical-align: top; }}
figure.wide {{ display: block; width: 100%; margin: 0.5em 0; }}
figure img {{ width: 100%; }}
figcaption {{ font-size: 0.9em; color: #555; }}
.notes li {{ color: #8a4b00; }}
.verdict {{ font-size: 1.15em; }}
.small {{ font-size: 0.9em; color: #555; }}
</style></head><body>
<h1>{html.escape(title)}</h1>
{note_html}
{bottom_line}
<h2 id="details">Agreement: each PBM rate mode against the DEM's 95 % intervals</h2>
{agreement}
{img("rtd_pooled", "Pooled RTD: the DEM's histogram against each PBM rate mode's density on the same bins", "Pooled RTD: DEM and every PBM rate mode")}
{img("holdup_profile", "Steady hold-up per axial slice: the DEM's means with 95 % intervals against each PBM rate mode", "Steady hold-up along the blender")}
<h2>DEM and {html.escape(mode_label)} over time (paper Figs 7-10)</h2>
{curves}
{img("geometry", "The blender: barrel, impeller blades and weir, as the DEM deck builds them", "Blender geometry (impeller, weir)")}
{"".join(sections)}
<h2>Studies with the PBM on the DEM's tables, {html.escape(studies_mode)} rates as configured (paper Figs 3-6)</h2>
{study_html}
{cost}
{files_html(list(files)) if files else ""}
<h2>Provenance</h2>
<table>{prov_rows}</table>
{config_block}
{diagnostics_html}
</body></html>
"""
