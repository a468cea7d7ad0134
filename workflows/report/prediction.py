"""``pbmdem predict``'s page, made from its record (``prediction.json``): the predicted RTD
and hold-up profile with their bands, the outlet's answer to a step in feeder A, and every
quantity with its 95 % prediction interval. The process that draws it imports matplotlib
and nothing of the prediction (:mod:`workflows.products.predict` forks it when it starts)."""

from __future__ import annotations

import html
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

LABELS = {
    "mean_residence_time_s": ("mean residence time (RTD)", "s"),
    "rtd_variance_s2": ("RTD variance", "s²"),
    "little_mean_residence_time_s": ("mean residence time (hold-up / outflow)", "s"),
    "holdup": ("steady hold-up", "particles"),
    "outflow_per_s": ("steady outflow", "particles/s"),
    "C_A": ("steady C_A", "-"),
    "rsd_outlet": ("outlet RSD", "-"),
    "lacey_outlet": ("outlet Lacey index", "-"),
}
#: the quantities the page's first line names
HEADLINE = ("mean_residence_time_s", "rtd_variance_s2", "little_mean_residence_time_s", "holdup")
SLICE = "holdup_slice_"


def _floats(values) -> np.ndarray:
    """``values`` as floats, a null (NaN written to JSON) as NaN."""
    return np.array([math.nan if v is None else v for v in values], dtype=float)


def _slices(record: Mapping[str, Any]) -> list[Mapping[str, Any]]:
    rows = [q for q in record["quantities"] if q["key"].startswith(SLICE)]
    return sorted(rows, key=lambda q: int(q["key"][len(SLICE) :]))


def plot_prediction(record: Mapping[str, Any], path: str | Path) -> Path:
    """Three panels of a prediction's record: E(t) of the corrected chain with the band of
    its mean's interval, each slice's hold-up with its prediction interval, and the outlet's
    answer to a step in feeder A with its band."""
    fig = Figure(figsize=(14, 4))
    # fixed margins: the constrained layout took 40 % of the drawing's time
    fig.subplots_adjust(left=0.05, right=0.99, bottom=0.13, top=0.92, wspace=0.22)
    left, right, step = fig.subplots(1, 3)
    rtd = record["rtd"]
    t, e = _floats(rtd["times_s"]), rtd["density_per_s"]
    left.fill_between(
        t, _floats(e["low"]), _floats(e["high"]), color="#9ecae1", label="at the ends of the mean's interval"
    )
    left.plot(t, _floats(e["value"]), color="#08519c", lw=1.5, label="the library's law, corrected")
    mean = _floats(
        next(
            ([q["value"], q["low"], q["high"]] for q in record["quantities"] if q["key"] == "mean_residence_time_s"), []
        )
    )
    if mean.size and np.all(np.isfinite(mean)):
        left.axvspan(mean[1], mean[2], color="#fdae6b", alpha=0.4, label="mean: 95 % prediction interval")
        left.axvline(mean[0], color="#e6550d", lw=1)
    left.set(xlabel="residence time [s]", ylabel="E(t) [1/s]", title="Residence time distribution")
    left.legend(fontsize=8, loc="upper right")
    slices = _slices(record)
    x = np.arange(1, len(slices) + 1)
    value = _floats(q["value"] for q in slices)
    low, high = _floats(q["low"] for q in slices), _floats(q["high"] for q in slices)
    right.fill_between(x, low, high, color="#a1d99b", step="mid", label="95 % prediction interval")
    right.step(x, value, where="mid", color="#006d2c", lw=1.5, label="predicted")
    right.set(xlabel="axial slice (inlet to weir)", ylabel="steady hold-up [particles]", title="Hold-up profile")
    right.set_ylim(bottom=0)
    right.legend(fontsize=8, loc="lower right")
    dynamics = record["dynamics"]
    t, ca = _floats(dynamics["step_times_s"]), dynamics["step_ca"]
    step.fill_between(t, _floats(ca["low"]), _floats(ca["high"]), color="#bcbddc", label="95 % band")
    step.plot(t, _floats(ca["value"]), color="#54278f", lw=1.5, label="predicted")
    step.set(
        xlabel="time after the step [s]",
        ylabel="outlet C_A",
        title=f"Feeder A's rate x{dynamics['step_factor_a']:g} at t = 0",
    )
    step.legend(fontsize=8, loc="lower right")
    fig.savefig(path, dpi=110)
    return Path(path)


def draw(record: Mapping[str, Any], figure: str | Path, files: dict[str, str]) -> str:
    """The figure of ``record`` written to ``figure`` (:func:`plot_prediction`) and the
    page that shows it (:func:`prediction_html`): what ``predict``'s forked process runs."""
    plot_prediction(record, figure)
    return prediction_html(record, Path(figure).name, files)


def _number(value: float) -> str:
    return "-" if value is None or not math.isfinite(value) else f"{value:.4g}"


def prediction_html(record: Mapping[str, Any], figure: str | None, files: dict[str, str]) -> str:
    """The page of a prediction's record, showing ``figure`` and linking ``files``."""
    p = record["point"]
    feed = p["feed_rate_a_per_s"] + p["feed_rate_b_per_s"]
    config_name = str(record["config"])
    quantities = {q["key"]: q for q in record["quantities"]}
    rows = []
    for q in record["quantities"]:
        label, unit = LABELS.get(q["key"], (f"hold-up of slice {q['key'][len(SLICE) :]}", "particles"))
        rows.append(
            f"<tr><td>{html.escape(label)}</td><td><code>{q['key']}</code></td><td>{_number(q['value'])}</td>"
            f"<td>[{_number(q['low'])}, {_number(q['high'])}]</td><td>{html.escape(unit)}</td></tr>"
        )
    dynamics, noise = record["dynamics"], record["noise"]
    for label, key, unit in (
        (f"VRR of feeder {noise['feeder']}'s white noise ({noise['band_hz']:g} Hz band)", "vrr", "-"),
        (f"mean delay after feeder A's rate x{dynamics['step_factor_a']:g}", "mean_delay_s", "s"),
    ):
        band = dynamics[key]
        rows.append(
            f"<tr><td>{html.escape(label)}</td><td><code>dynamics.{key}</code></td><td>{_number(band['value'])}</td>"
            f"<td>[{_number(band['low'])}, {_number(band['high'])}]</td><td>{unit}</td></tr>"
        )
    warning = ""
    if record["extrapolated"]:
        widening = next((part.get("widening") for part in record["interval_parts"].values()), None)
        widened = f"widened {widening:.2f}x" if isinstance(widening, (int, float)) else "widened"
        warning = (
            '<p class="warn"><b>Extrapolated:</b> '
            + html.escape("; ".join(record["outside_domain"]))
            + f". The intervals are {widened}, at least to a share of the "
            "errors of the library's end runs predicted without them.</p>"
        )
    if record.get("new_layout"):
        warning += (
            '<p class="warn"><b>A blade layout no library run has</b> (this length puts its stations and its gap '
            "to the weir where no run had them): each interval is at least the error of the library's runs that "
            "were alone at their layouts, each predicted without it. A DEM run of this layout narrows them.</p>"
        )
    links = " · ".join(f'<a href="{html.escape(name)}">{html.escape(what)}</a>' for what, name in files.items())
    image = (
        f'<img src="{html.escape(figure)}" alt="Predicted residence-time distribution, steady hold-up per axial '
        'slice and the outlet C_A after a step in feeder A, each with its 95 % band" width="950">'
        if figure
        else ""
    )
    headline = ", ".join(
        f"{LABELS[k][0]} {_number(quantities[k]['value'])} {LABELS[k][1]}" for k in HEADLINE if k in quantities
    )
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>Prediction: {html.escape(config_name)}</title>
<style>body{{font-family:sans-serif;max-width:960px;margin:2em auto}}td,th{{padding:2px 8px;text-align:left}}
.warn{{background:#fee;padding:6px}}</style></head><body>
<h1>Prediction without DEM: {html.escape(config_name)}</h1>
<p>{p["impeller_rpm"]:g} rpm, total feed {feed:g} particles/s, length {p["length_m"]:g} m.
From the library's law (no DEM run at this point): {html.escape(headline)}.</p>
{warning}
<p>Library domain: {html.escape(record["domain"])}.</p>
{image}
<h2>Every quantity with its 95 % prediction interval</h2>
<p>Each value is the library's law corrected by what it misses at the library's runs (a least-squares line
over the operating point; each slice's hold-up from the zone law of the bed where the library has one),
the slices scaled so that they hold the predicted hold-up. The interval is where a DEM run at this point
would put its value, 95 % of the time: the scatter of the DEM about that line (seeds included) and the
line's own uncertainty at this point, which grows away from the runs; checked on every library run left out (<code>calibration.md</code> beside
the library). The VRR and the step's mean delay are those of the predicted chain, whose time scale alone
is uncertain: their intervals are the chain stretched to the mean residence time's interval ends.</p>
<table><tr><th>quantity</th><th>key</th><th>predicted</th><th>95 % interval</th><th>unit</th></tr>
{"".join(rows)}</table>
<p>Files: {links}</p>
</body></html>
"""
