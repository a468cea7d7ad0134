"""The validation campaign's page: parity and hold-up-profile figures, verdict lines and the
HTML report (the numbers come from :mod:`workflows.analysis.validation`)."""

from __future__ import annotations

import html
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from workflows.analysis.agreement import MODES
from workflows.analysis.budget import BudgetStudy
from workflows.analysis.validation import LawVerdict, Prediction, PredictionVerdict
from workflows.report.comparison import MODE_STYLES, fmt

SOURCE_COLOURS = {
    "self": "#636363",
    "baseline": "#e6550d",
    "library": "#31a354",
    "baseline + fill law": "#fdae6b",
    "library + fill law": "#3182bd",
}


MODE_MARKERS = {"velocity": "o", "measured": "s", "phases": "^"}


PARITY = (
    ("mean_residence_time_s", "mean residence time [s]"),
    ("rtd_variance_s2", "RTD variance [s²]"),
    ("little_mean_residence_time_s", "hold-up / outflow [s]"),
    ("holdup", "steady hold-up [particles]"),
    ("outflow_per_s", "steady outflow [1/s]"),
    ("C_A", "steady C_A [-]"),
    ("rsd_outlet", "outlet RSD [-]"),
    ("lacey_outlet", "outlet Lacey index [-]"),
)


#: the alt text of the verdict figures
FIGURE_ALT = {
    "parity": "Parity plots, one per quantity: each run's PBM prediction against its DEM value with the DEM's "
    "95 % interval, by source of the prediction and rate mode; on the diagonal a prediction is exact",
    "profiles": "Steady hold-up per axial slice for each run: the DEM with its 95 % band against the PBM "
    "from each source and rate mode",
}


def plot_parity(preds: list[Prediction], path: Path) -> None:
    """Predicted against DEM, one panel per quantity, the DEM's 95 % interval as error bars."""
    fig = Figure(figsize=(13, 6.5), layout="constrained")
    axes = fig.subplots(2, 4).ravel()
    for ax, (key, label) in zip(axes, PARITY):
        lo_all, hi_all = [], []
        for p in preds:
            row = next((r for r in p.rows if r.key == key), None)
            if row is None or not np.isfinite(row.dem):
                continue
            for mode in MODES:
                value = row.value(mode)
                if value is None or not np.isfinite(value):
                    continue
                err = [[max(row.dem - row.dem_ci_low, 0)], [max(row.dem_ci_high - row.dem, 0)]]
                ax.errorbar(
                    [row.dem],
                    [value],
                    xerr=err,
                    fmt=MODE_MARKERS[mode],
                    ms=5,
                    color=SOURCE_COLOURS[p.source],
                    mfc="none" if mode == "velocity" else None,
                    lw=0.8,
                )
                lo_all += [row.dem_ci_low, value]
                hi_all += [row.dem_ci_high, value]
        if lo_all:  # one range for both axes: the diagonal is the 45-degree line of a perfect prediction
            lo, hi = min(lo_all), max(hi_all)
            pad = 0.05 * (hi - lo or abs(hi) or 1)
            ax.plot([lo - pad, hi + pad], [lo - pad, hi + pad], color="k", lw=0.6, ls="--")
            ax.set_xlim(lo - pad, hi + pad)
            ax.set_ylim(lo - pad, hi + pad)
        ax.set_title(label, fontsize=9)
        ax.set_xlabel("DEM", fontsize=8)
        ax.set_ylabel("PBM", fontsize=8)
        ax.tick_params(labelsize=7)
    handles = [axes[0].plot([], [], "o", color=c, label=s)[0] for s, c in SOURCE_COLOURS.items()]
    handles += [
        axes[0].plot([], [], m, color="k", mfc="none" if mode == "velocity" else None, label=f"{mode} rates")[0]
        for mode, m in MODE_MARKERS.items()
    ]
    fig.legend(handles=handles, loc="outside lower center", ncol=5, fontsize=8)
    fig.savefig(path, dpi=110)


def plot_profiles(preds: list[Prediction], runs: list[str], path: Path) -> None:
    """The steady hold-up per axial slice of every run: DEM with its interval, each source's PBM."""
    fig = Figure(figsize=(3.2 * len(runs), 3.8), layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, len(runs), sharey=True))
    for ax, run in zip(axes, runs):
        mine = [p for p in preds if p.run == run and p.rows]
        if mine:
            rows = sorted(
                (r for r in mine[0].rows if r.key.startswith("holdup_slice_")),
                key=lambda r: int(r.key.rsplit("_", 1)[1]),
            )
            if rows:
                slices = np.arange(1, len(rows) + 1)
                ax.fill_between(
                    slices, [r.dem_ci_low for r in rows], [r.dem_ci_high for r in rows], color="#b2182b", alpha=0.25
                )
                ax.plot(slices, [r.dem for r in rows], color="#b2182b", lw=2)
            for p in mine:
                prow = sorted(
                    (r for r in p.rows if r.key.startswith("holdup_slice_")), key=lambda r: int(r.key.rsplit("_", 1)[1])
                )
                for mode in MODES:
                    ax.plot(
                        np.arange(1, len(prow) + 1),
                        [r.value(mode) for r in prow],
                        color=SOURCE_COLOURS[p.source],
                        ls="--" if mode == "velocity" else "-",
                        lw=1,
                    )
        ax.set_title(run, fontsize=9)
        ax.set_xlabel("axial slice (inlet → outlet)", fontsize=8)
        ax.tick_params(labelsize=7)
    axes[0].set_ylabel("particles", fontsize=8)
    handles = [axes[0].plot([], [], color="#b2182b", lw=2, label="DEM (band: 95 %)")[0]]
    handles += [axes[0].plot([], [], color=c, label=f"PBM from {s}")[0] for s, c in SOURCE_COLOURS.items()]
    handles += [
        axes[0].plot([], [], color="k", ls=ls, lw=1, label=f"{mode} rates")[0]
        for mode, (ls, _label) in MODE_STYLES.items()
    ]
    fig.legend(handles=handles, loc="outside lower center", ncol=6, fontsize=8)
    fig.savefig(path, dpi=110)


def render_report(
    campaign: list[dict[str, Any]],
    judged: list[PredictionVerdict],
    figures: dict[str, str],
    budget: BudgetStudy | None = None,
    span_s: float | None = None,
    step_section: str | None = None,
    law: list[LawVerdict] | None = None,
) -> str:
    """The validation page: the campaign, a verdict per change, the numbers behind each."""
    total = sum(r["dem_wall_time_s"] or 0 for r in campaign)
    parts = [
        "<!doctype html><html><head><meta charset='utf-8'><title>Validation campaign</title>",
        "<style>body{font-family:sans-serif;max-width:1300px;margin:auto}table{border-collapse:collapse;"
        "font-size:13px}td,th{border:1px solid #ccc;padding:2px 6px;text-align:right}"
        "td:first-child,th:first-child{text-align:left}.no{background:#fdd}.yes{background:#dfd}</style>",
        "</head><body><h1>Does the hybrid predict what it was not built from?</h1>",
        "<p>Each run below is a real LIGGGHTS run of the <code>validation</code> preset with one factor "
        "changed. Each is predicted by PBMs built without it: from the baseline DEM alone (length by "
        "rescaled compartments, rpm by velocities scaled with the speed, feed with unchanged velocities), "
        "and from the table library (rpm interpolated between the other runs). A quantity is predicted "
        "when |prediction − DEM| ≤ the hybrid's relative error on the baseline (its PBM against its DEM) "
        "× the new DEM value + half the new DEM's 95 % interval: as good as the hybrid is where it was "
        "built. The self-built PBM (the run's own tables) is shown for reference.</p>",
        "<h2>Campaign</h2><table><tr><th>run</th><th>change</th><th>DEM from</th><th>DEM wall time [s]</th>"
        "<th>steady hold-up</th><th>mean residence time [s]</th><th>tracers</th><th>recovered</th></tr>",
    ]
    for r in campaign:
        parts.append(
            f"<tr><td>{html.escape(r['run'])}</td><td>{html.escape(r['change'])}</td>"
            f"<td>{html.escape(r['source'])}</td><td>{fmt(r['dem_wall_time_s'])}</td>"
            f"<td>{fmt(r['holdup'])}</td><td>{fmt(r['mean_residence_time_s'])}</td>"
            f"<td>{fmt(r['tracers'])}</td><td>{fmt(r['recovered'])}</td></tr>"
        )
    span = (
        ""
        if span_s is None
        else (
            f"; elapsed from the first run's start to the last one's end: "
            f"{span_s / 3600:.2f} h (runs that overlap count once)"
        )
    )
    parts.append(f"</table><p>Sum of the runs' DEM wall times: {total / 3600:.2f} h{span}.</p>")
    parts.append(
        "<h2>Verdicts</h2><table><tr><th>run</th><th>predicted from</th><th>velocity rates</th>"
        "<th>measured rates</th><th>verdict</th></tr>"
    )
    for v in judged:
        cells = []
        for mode in MODES:
            j = (v.judged or {}).get(mode)
            cells.append(
                "<td>–</td>"
                if j is None
                else f"<td class='{'yes' if j.predicts else 'no'}'>{len(j.rows) - len(j.failing)}/{len(j.rows)} ok</td>"
            )
        parts.append(
            f"<tr><td>{html.escape(v.run)}</td><td>{html.escape(v.source)}</td>{''.join(cells)}"
            f"<td>{html.escape(v.verdict)}</td></tr>"
        )
    parts.append("</table>")
    if law:
        parts.extend(_law_section(law))
    for name, alt in FIGURE_ALT.items():
        if name in figures:
            parts.append(
                f'<p><img src="{html.escape(figures[name])}" alt="{html.escape(alt)}" style="max-width:100%"></p>'
            )
    if budget is not None:
        parts.extend(_budget_section(budget, figures))
    if step_section:
        parts.append(step_section)
    parts.extend(_numbers_section(judged))
    links = " · ".join(f'<a href="{html.escape(name)}">{html.escape(name)}</a>' for name in figures.values())
    parts.append(f'<h2>Files</h2><p><a href="summary.json">summary.json</a> (every number of this page) · {links}</p>')
    parts.append("</body></html>")
    return "\n".join(parts)


def _law_section(law: list[LawVerdict]) -> list[str]:
    """Each change predicted by the library's law fitted without that run."""
    parts = [
        "<h2>Predicted by the library's law, the run left out (<code>pbmdem predict</code>)</h2>",
        "<p>One transport law fitted to the DEM library (the campaign and "
        "<code>workflows/reference/library/</code>) less the run judged, at that run's operating point. "
        "Predicted when the mean residence time, RTD variance, Little's-law time and hold-up, and all but "
        "two other quantities, lie inside the DEM's 95 % interval widened by the DEM's scatter between seeds "
        "(<code>pbmdem library fit</code>, <code>workflows/reference/library/law/calibration.md</code>).</p>",
        "<table><tr><th>run</th><th>DEM inside the 95 % prediction interval</th>"
        "<th>prediction inside the widened DEM interval</th><th>verdict</th></tr>",
    ]
    for v in law:
        parts.append(
            f"<tr><td>{html.escape(v.run)}</td><td>{v.covered}/{v.n}</td>"
            f"<td class='{'yes' if v.predicts else 'no'}'>{v.inside_widened}/{v.n}</td>"
            f"<td>{html.escape(v.verdict)}</td></tr>"
        )
    parts.append("</table>")
    return parts


def _budget_section(budget: BudgetStudy, figures: dict[str, str]) -> list[str]:
    """The budget study's table (the smallest DEM span each rate mode needs) and figure."""
    parts: list[str] = []
    parts.append(
        "<h2>How little DEM does the PBM need?</h2><p>PBMs built from the baseline's first T "
        "seconds (the transient as measured, the steady flow seen by T held for the rest), each "
        "quantity against the same PBM built from the whole run, judged by the half width of the "
        "DEM's 95 % interval.</p><table><tr><th>rate mode</th><th>smallest T [s]</th>"
        "<th>fraction of the run</th><th>without the slice hold-ups [s]</th></tr>"
    )
    for mode, (t_s, fraction) in budget.smallest_T.items():
        other = budget.smallest_T_without_slices.get(mode, (None, None))[0]
        parts.append(f"<tr><td>{mode}</td><td>{fmt(t_s)}</td><td>{fmt(fraction, 2)}</td><td>{fmt(other)}</td></tr>")
    parts.append("</table>")
    if "budget" in figures:
        alt = (
            "For each rate mode, the distance of each quantity of the PBM built from the DEM's first T seconds "
            "from the PBM built from the whole run, in half-widths of the DEM's interval, against T"
        )
        parts.append(
            f'<p><img src="{html.escape(figures["budget"])}" alt="{html.escape(alt)}" style="max-width:100%"></p>'
        )
    return parts


def _numbers_section(judged: list[PredictionVerdict]) -> list[str]:
    """One table per judged prediction: each quantity's DEM value and interval beside every
    mode's prediction, self-built value and verdict."""
    parts = ["<h2>The numbers behind each verdict</h2>"]
    for v in judged:
        if not v.judged:
            continue
        parts.append(
            f"<h3>{html.escape(v.run)}, predicted from {html.escape(v.source)}</h3>"
            "<table><tr><th>quantity</th><th>DEM</th><th>95 % interval</th>"
            + "".join(f"<th>{m}: predicted</th><th>{m}: self-built</th><th>{m}: ok</th>" for m in MODES)
            + "</tr>"
        )
        by_mode = {m: {r.key: r for r in v.judged[m].rows} for m in MODES}
        keys = list(dict.fromkeys(k for m in MODES for k in by_mode[m]))
        for key in keys:
            first = next(by_mode[m][key] for m in MODES if key in by_mode[m])
            cells = ""
            for m in MODES:
                r = by_mode[m].get(key)
                cells += (
                    "<td>–</td><td>–</td><td>–</td>"
                    if r is None
                    else f"<td>{fmt(r.judged.value)}</td><td>{fmt(r.self_value)}</td>"
                    f"<td class='{'yes' if r.ok else 'no'}'>{fmt(r.ok)}</td>"
                )
            parts.append(
                f"<tr><td>{html.escape(first.judged.quantity)}</td><td>{fmt(first.judged.reference)}</td>"
                f"<td>{fmt(first.dem_ci_low)} – {fmt(first.dem_ci_high)}</td>{cells}</tr>"
            )
        parts.append("</table>")
    return parts
