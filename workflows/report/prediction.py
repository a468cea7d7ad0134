"""``pbmdem predict``'s page: the predicted RTD and hold-up profile with their bands, and
every quantity with its 95 % prediction interval."""

from __future__ import annotations

import html
import math
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from workflows.prediction.covariates import AXIAL_SLICES
from workflows.prediction.design import Dynamics, Noise
from workflows.prediction.library import SCALAR_KEYS, slice_key
from workflows.prediction.predict import Prediction

#: the feeder noise whose VRR ``predict`` reports (:func:`workflows.prediction.design.point_dynamics`'s default)
NOISE = Noise()
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


def plot_prediction(prediction: Prediction, dynamics: Dynamics, path: Path) -> Path:
    """Three panels: E(t) of the corrected chain with the band of its mean's interval, each
    slice's hold-up with its prediction interval, and the outlet's answer to a step in
    feeder A with its band."""
    fig = Figure(figsize=(14, 4), layout="constrained")
    left, right, step = fig.subplots(1, 3)
    t = prediction.rtd_times_s
    left.fill_between(
        t, prediction.rtd[1], prediction.rtd[2], color="#9ecae1", label="at the ends of the mean's interval"
    )
    left.plot(t, prediction.rtd[0], color="#08519c", lw=1.5, label="the library's law, corrected")
    mean = prediction.quantity("mean_residence_time_s")
    left.axvspan(mean.low, mean.high, color="#fdae6b", alpha=0.4, label="mean: 95 % prediction interval")
    left.axvline(mean.value, color="#e6550d", lw=1)
    left.set(xlabel="residence time [s]", ylabel="E(t) [1/s]", title="Residence time distribution")
    left.legend(fontsize=8)
    slices = [prediction.quantity(slice_key(i)) for i in range(AXIAL_SLICES)]
    x = np.arange(1, AXIAL_SLICES + 1)
    value = np.array([q.value for q in slices])
    low, high = np.array([q.low for q in slices]), np.array([q.high for q in slices])
    right.fill_between(x, low, high, color="#a1d99b", step="mid", label="95 % prediction interval")
    right.step(x, value, where="mid", color="#006d2c", lw=1.5, label="predicted")
    right.set(xlabel="axial slice (inlet to weir)", ylabel="steady hold-up [particles]", title="Hold-up profile")
    right.set_ylim(bottom=0)
    right.legend(fontsize=8)
    t = dynamics.times_s
    step.fill_between(t, dynamics.step[1], dynamics.step[2], color="#bcbddc", label="95 % band")
    step.plot(t, dynamics.step[0], color="#54278f", lw=1.5, label="predicted")
    step.set(
        xlabel="time after the step [s]",
        ylabel="outlet C_A",
        title=f"Feeder A's rate x{dynamics.step_factor:g} at t = 0",
    )
    step.legend(fontsize=8)
    fig.savefig(path, dpi=110)
    return path


def draw(prediction: Prediction, dynamics: Dynamics, config_name: str, figure: Path, files: dict[str, str]) -> str:
    """The figure written to ``figure`` (:func:`plot_prediction`) and the page that shows
    it (:func:`prediction_html`): what ``predict``'s forked process runs."""
    plot_prediction(prediction, dynamics, figure)
    return prediction_html(prediction, dynamics, config_name, figure.name, files)


def _number(value: float) -> str:
    return "-" if not math.isfinite(value) else f"{value:.4g}"


def prediction_html(
    prediction: Prediction, dynamics: Dynamics, config_name: str, figure: str | None, files: dict[str, str]
) -> str:
    p = prediction.point
    rows = []
    for q in prediction.quantities:
        label, unit = LABELS.get(q.key, (f"hold-up of slice {q.key.rsplit('_', 1)[-1]}", "particles"))
        rows.append(
            f"<tr><td>{html.escape(label)}</td><td><code>{q.key}</code></td><td>{_number(q.value)}</td>"
            f"<td>[{_number(q.low)}, {_number(q.high)}]</td><td>{html.escape(unit)}</td></tr>"
        )
    for label, key, band, unit in (
        (f"VRR of feeder {NOISE.feeder}'s white noise ({NOISE.band_hz:g} Hz band)", "dynamics.vrr", dynamics.vrr, "-"),
        (
            f"mean delay after feeder A's rate x{dynamics.step_factor:g}",
            "dynamics.mean_delay_s",
            dynamics.mean_delay_s,
            "s",
        ),
    ):
        rows.append(
            f"<tr><td>{html.escape(label)}</td><td><code>{key}</code></td><td>{_number(band.value)}</td>"
            f"<td>[{_number(band.low)}, {_number(band.high)}]</td><td>{unit}</td></tr>"
        )
    warning = ""
    if prediction.extrapolated:
        warning = (
            '<p class="warn"><b>Extrapolated:</b> '
            + html.escape("; ".join(prediction.outside))
            + f". The intervals are widened {prediction.quantities[0].widening:.2f}x, at least to a share of the "
            "errors of the library's end runs predicted without them.</p>"
        )
    links = " · ".join(f'<a href="{html.escape(name)}">{html.escape(what)}</a>' for what, name in files.items())
    image = (
        f'<img src="{html.escape(figure)}" alt="Predicted residence-time distribution, steady hold-up per axial '
        'slice and the outlet C_A after a step in feeder A, each with its 95 % band" width="950">'
        if figure
        else ""
    )
    headline = ", ".join(
        f"{LABELS[k][0]} {_number(prediction.quantity(k).value)} {LABELS[k][1]}" for k in SCALAR_KEYS[:4]
    )
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>Prediction: {html.escape(config_name)}</title>
<style>body{{font-family:sans-serif;max-width:960px;margin:2em auto}}td,th{{padding:2px 8px;text-align:left}}
.warn{{background:#fee;padding:6px}}</style></head><body>
<h1>Prediction without DEM: {html.escape(config_name)}</h1>
<p>{p.impeller_rpm:g} rpm, total feed {p.feed_rate_total_per_s:g} particles/s, length {p.length_m:g} m.
From the library's law (no DEM run at this point): {html.escape(headline)}.</p>
{warning}
<p>Library domain: {html.escape(prediction.domain.describe())}.</p>
{image}
<h2>Every quantity with its 95 % prediction interval</h2>
<p>Each value is the library's law corrected by what it misses at the library's runs (a least-squares line
over the operating point). The interval is where a DEM run at this point would put its value, 95 % of the
time: the scatter of the DEM about that line (seeds included) and the line's own uncertainty at this point,
which grows away from the runs; checked on every library run left out (<code>calibration.md</code> beside
the library). The VRR and the step's mean delay are those of the predicted chain, whose time scale alone
is uncertain: their intervals are the chain stretched to the mean residence time's interval ends.</p>
<table><tr><th>quantity</th><th>key</th><th>predicted</th><th>95 % interval</th><th>unit</th></tr>
{"".join(rows)}</table>
<p>Files: {links}</p>
</body></html>
"""
