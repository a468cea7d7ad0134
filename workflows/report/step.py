"""The dynamic check (feed step) as a figure and an HTML section (computed by
:mod:`workflows.analysis.step`)."""

from __future__ import annotations

import html
from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from workflows.analysis.step import P_MIN, StepComparison
from workflows.report.comparison import MODE_STYLES, fmt


def plot_step(comparison: StepComparison, path: str | Path) -> Path:
    """DEM outlet C_A per interval with its 95 % binomial range, and every PBM's."""
    from coupling.metrics import binomial_interval

    dem = comparison.dem
    n = (dem["n_A"] + dem["n_B"]).to_numpy()
    keep = n > 0
    t = dem["t_s"].to_numpy()[keep]
    lo, hi = binomial_interval(dem["n_A"].to_numpy()[keep], n[keep])
    fig = Figure(figsize=(9, 4.5), layout="constrained")
    ax = fig.subplots()
    ax.fill_between(t, lo, hi, step="pre", color="#bdbdbd", label="DEM, 95 % binomial range")
    ax.step(t, dem["n_A"].to_numpy()[keep] / n[keep], "k-", where="pre", lw=0.6, label="DEM")
    # 5-s pooled fractions: the trend the eye looks for under the per-interval noise
    block = np.floor((t - 1e-9) / 5.0)
    pooled = pd.DataFrame({"b": block, "k": dem["n_A"].to_numpy()[keep], "n": n[keep]}).groupby("b").sum()
    ax.plot(5.0 * pooled.index + 2.5, pooled["k"] / pooled["n"], "ko", ms=4, label="DEM, 5-s pooled")
    colours = {"self": "#3182bd", "baseline": "#e6550d", "baseline + fill law": "#756bb1"}
    for (source, mode), pbm in comparison.series.items():
        colour, ls = colours.get(source, "#31a354"), MODE_STYLES.get(mode, ("-", ""))[0]
        ax.plot(pbm["t_s"], pbm["C_A"], color=colour, ls=ls, lw=1.5, label=f"PBM, {source} tables, {mode} rates")
    ax.axvline(comparison.step_s, color="#636363", lw=0.8, ls=":")
    start = max(0.0, comparison.step_s - 40)
    shown = t >= start
    ax.set(
        xlabel="time [s]",
        ylabel="outlet C_A",
        title=f"Feeder A x{comparison.factor_a:g} at {comparison.step_s:g} s: the outlet's response",
        xlim=(start, t.max()),
        ylim=(max(0.0, lo[shown].min() - 0.05), min(1.0, hi[shown].max() + 0.05)),
    )
    ax.legend(fontsize=8, loc="lower right")
    out = Path(path)
    fig.savefig(out, dpi=120)
    return out


def step_html(comparison: StepComparison, figure: str | None) -> str:
    """The report section: one row per PBM, with the DEM's intervals and the verdict."""
    parts = [
        "<h2>A dynamic check: a step in feeder A</h2>",
        f"<p>One LIGGGHTS run of the validation preset in which feeder A's rate is multiplied by "
        f"{comparison.factor_a:g} at {comparison.step_s:g} s, predicted by PBMs on the run's own tables "
        "(<i>self</i>), on the steady baseline's (<i>baseline</i>: the flow unchanged by the step) and on the "
        "baseline's with rates that follow each slice's fill (<i>baseline + fill law</i>: the law of the "
        "baseline's own filling transient, pbm.fill). A PBM predicts "
        "the step when the DEM's response runs at its speed (the fitted time-scale factor's 95 % interval holds 1) "
        f"and the DEM's counts of A per {comparison.interval_s:g}-s interval are consistent with it (binomial "
        f"deviance, p &ge; {P_MIN:g}). The mean delay (for a linear blender the mean residence time of A) is shown "
        "with the DEM's interval.</p>",
        "<table><tr><th>PBM tables</th><th>rates</th><th>DEM faster by [95 %]</th><th>deviance p</th>"
        "<th>mean delay, DEM [95 %]</th><th>mean delay, PBM</th><th>verdict</th></tr>",
    ]
    for row in comparison.rows:
        j = row.judgement
        d, a = j.dem_delay_s, j.time_scale
        verdict = "predicts the step" if j.predicted else "does not"
        parts.append(
            f"<tr class='{'yes' if j.predicted else 'no'}'><td>{html.escape(row.source)}</td>"
            f"<td>{row.mode}</td><td>&times;{a.value:.2f} [{a.low:.2f}, {a.high:.2f}] "
            f"{'&#10003;' if j.time_scale_inside else '&#10007;'}</td><td>{j.deviance_p:.2f}</td>"
            f"<td>{fmt(d.estimate)} [{fmt(d.low)}, {fmt(d.high)}] s</td><td>{fmt(j.pbm_delay_s)} s "
            f"{'&#10003;' if j.delay_inside else '&#10007;'}</td><td>{verdict}</td></tr>"
        )
    parts.append("</table>")
    if figure:
        parts.append(
            f'<p><img src="{html.escape(figure)}" alt="Outlet C_A after the feed step: the DEM per interval '
            'with its 95 % binomial range against every PBM" style="max-width:100%"></p>'
        )
    return "\n".join(parts)
