"""The design tool's figure and page: the feasible region over impeller speed and blender
length, coloured by P(spec met) with its band, and the answer's step response.

Drawn from the design's record (:meth:`workflows.prediction.design.DesignResult.record`,
what ``design.json`` holds), so that ``design.json`` alone redraws it, and the process that
draws it imports matplotlib and nothing of the prediction (:mod:`workflows.products.design`).
"""

from __future__ import annotations

import html
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

#: the band drawn: where P(spec met) crosses these
CONTOURS = (0.05, 0.5, 0.95)


def alt_text(record: Mapping[str, Any]) -> str:
    region = record["region"]
    p = np.asarray(region["probability"], dtype=float)
    text = (
        f"Left: P(spec met) over impeller speed {region['rpm'][0]:.0f}-{region['rpm'][-1]:.0f} rpm and blender "
        f"length {region['length_m'][0]:.3f}-{region['length_m'][-1]:.3f} m at a total feed of "
        f"{region['feed_per_s']:.1f} particles/s, with contours at P = 0.05, 0.5 and 0.95; "
        f"{np.mean(p >= record['spec']['confidence']):.0%} of the points shown meet the spec with the required "
        "confidence."
    )
    best = record["shortest"]
    if best is not None:
        text += (
            f" A star marks the shortest blender, {best['length_m'] * 1000:.0f} mm at {best['rpm']:.0f} rpm and "
            f"{best['feed_per_s']:.1f} particles/s (P = {best['probability']:.3f})."
        )
        moves = record["dynamics"].get("shortest")
        if moves:
            d = moves["mean_delay_s"]
            text += (
                f" Right: its outlet C_A after feeder A's rate steps x{moves['step_factor_a']:g}, rising from "
                f"{moves['ca_before_after'][0]:.3f} to {moves['ca_before_after'][1]:.3f} with a mean delay of "
                f"{d['value']:.1f} s (95 % interval {d['low']:.1f}-{d['high']:.1f} s), the band shaded."
            )
    return text


def plot_design(record: Mapping[str, Any], path: str | Path) -> str:
    """Draw ``feasible.png`` at ``path`` from a design's record and return the page
    (``report.html``) that shows it."""
    region = record["region"]
    rpm = np.asarray(region["rpm"], dtype=float)
    length = np.asarray(region["length_m"], dtype=float)
    p = np.asarray(region["probability"], dtype=float)
    feed = region["feed_per_s"]
    fig = Figure(figsize=(11, 4.5), layout="constrained")
    ax, ax2 = fig.subplots(1, 2, width_ratios=(1.2, 1))
    mesh = ax.pcolormesh(rpm, length * 1000, p.T, shading="nearest", cmap="RdYlGn", vmin=0, vmax=1)
    fig.colorbar(mesh, ax=ax, label="P(spec met)")
    if rpm.size > 1 and length.size > 1:
        lines = ax.contour(
            rpm, length * 1000, p.T, levels=CONTOURS, colors=["k", "k", "k"], linestyles=[":", "--", "-"]
        )
        ax.clabel(lines, fmt="%.2f", fontsize=8)
    for r, length_m, f in record["library_points"]:
        if math.isclose(f, feed, rel_tol=0.05):
            ax.plot(r, length_m * 1000, "o", mfc="none", mec="#08519c", ms=8)
    ax.plot([], [], "o", mfc="none", mec="#08519c", label="library's DEM runs at this feed")
    best = record["shortest"]
    if best is not None and math.isclose(best["feed_per_s"], feed, rel_tol=1e-9):
        ax.plot(best["rpm"], best["length_m"] * 1000, "k*", ms=14, label="shortest blender")
    ax.set(
        xlabel="impeller speed [rpm]",
        ylabel="blender length [mm]",
        title=f"P(spec met) at {feed:.1f} particles/s (contours 0.05, 0.5, 0.95)",
    )
    ax.legend(fontsize=8, loc="upper right")
    moves = record["dynamics"].get("shortest")
    if moves:
        t = np.asarray(moves["step_times_s"])
        step = moves["step_ca"]
        ax2.fill_between(t, step["low"], step["high"], color="#9ecae1", label="95 % band (mean residence time's)")
        ax2.plot(t, step["value"], "k-", lw=1.2, label="predicted")
        ax2.set(
            xlabel="time after the step [s]",
            ylabel="outlet C_A",
            title=f"Feeder A's rate x{moves['step_factor_a']:g}: the shortest blender's answer",
        )
        ax2.legend(fontsize=8, loc="lower right")
    else:
        ax2.set_axis_off()
    out = Path(path)
    fig.savefig(out, dpi=110)
    return design_html(record, "feasible.png")


def design_html(record: Mapping[str, Any], figure: str) -> str:
    """``report.html``: the answers, their margins with intervals and P, and the figure
    with its alt text."""
    rows = []
    for title, key in (("Shortest blender", "shortest"), ("Largest feed", "largest_feed")):
        point = record[key]
        if point is None:
            continue
        m, h = point["mean_residence_time_s"], point["holdup"]
        cells = [
            title,
            f"{point['rpm']:.0f}",
            f"{point['length_m'] * 1000:.1f}",
            f"{point['feed_per_s']:.1f}",
            f"{m['value']:.1f} [{m['low']:.1f}, {m['high']:.1f}]",
            f"{h['value']:.0f} [{h['low']:.0f}, {h['high']:.0f}]",
            "-"
            if point["vrr"] is None
            else f"{point['vrr']['value']:.2f} [{point['vrr']['low']:.2f}, {point['vrr']['high']:.2f}]",
            "; ".join(
                f"{x['name']} {x['value']:+.3g} [{x['low']:+.3g}, {x['high']:+.3g}], P {x['probability']:.3f}"
                for x in point["margins"]
            ),
            f"{point['probability']:.3f}",
        ]
        rows.append("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in cells) + "</tr>")
    head = [
        "",
        "rpm",
        "length [mm]",
        "feed [1/s]",
        "mean residence time [s]",
        "hold-up",
        "VRR",
        "margins (95 % intervals)",
        "P(spec met)",
    ]
    notes = "".join(f"<li>{html.escape(n)}</li>" for n in record["notes"])
    spec = ", ".join(f"{k} = {v}" for k, v in record["spec"].items() if v is not None)
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>pbmdem design</title></head>
<body>
<h1>Design on the library's law</h1>
<p>Spec: {html.escape(spec)}. Library: {html.escape(str(record.get("library", "")))}; domain
{html.escape(record["domain"])}. Intervals: 95 % prediction intervals of the law corrected by the
library's lines; P(spec met): {html.escape(record["dependence"])}.</p>
<table border="1" cellspacing="0" cellpadding="4">
<tr>{"".join(f"<th>{html.escape(c)}</th>" for c in head)}</tr>
{"".join(rows) or '<tr><td colspan="9">no point meets the spec with the required confidence</td></tr>'}
</table>
<ul>{notes}</ul>
<img src="{html.escape(figure)}" alt="{html.escape(alt_text(record))}" width="100%">
</body></html>
"""
