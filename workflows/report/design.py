"""The design tool's figure: the feasible region over impeller speed and blender length."""

from __future__ import annotations

import math
from pathlib import Path

from matplotlib.figure import Figure

from pbm.design import DesignResult


def plot_feasible(result: DesignResult, path: str | Path) -> Path:
    """The feasible lengths against the impeller speed, the best design and the library's runs."""
    fig = Figure(figsize=(7, 4.5), layout="constrained")
    ax = fig.subplots()
    length = result.length_m
    rows = result.rows
    rpm = [r.rpm for r in rows]
    lo = [r.length_factor_lo * length if r.feasible else math.nan for r in rows]
    hi = [r.length_factor_hi * length if r.feasible else math.nan for r in rows]
    spec = result.spec
    ax.axhspan(
        spec.length_factor_min * length,
        spec.length_factor_max * length,
        color="#f0f0f0",
        zorder=0,
        label="lengths searched",
    )
    ax.fill_between(rpm, lo, hi, color="#74c476", alpha=0.7, label="meets the spec")
    ax.plot(rpm, lo, "g-", lw=1)
    bad = [r.rpm for r in rows if not r.feasible]
    if bad:
        ax.plot(bad, [spec.length_factor_min * length] * len(bad), "rx", label="no length meets it")
    if result.best is not None:
        best = result.best
        ax.plot(
            best.rpm,
            best.length_factor * length,
            "k*",
            ms=12,
            label=f"smallest: {best.length_factor * length * 1000:.0f} mm at {best.rpm:g} rpm",
        )
    for k, (a, b) in enumerate(result.rpm_ranges):
        ax.hlines(length, a, b, colors="#08519c", lw=3, label="this blender meets it" if k == 0 else None)
    ax.axhline(length, color="#08519c", lw=0.8, ls="--")
    for v in result.library_rpm:
        ax.axvline(v, color="#636363", lw=0.8, ls="--")
    ax.set(
        xlabel="impeller speed [rpm] (dashed: the library's DEM runs and blender)",
        ylabel="blender length [m]",
        title="Design space: where the PBM meets the spec",
    )
    ax.legend(fontsize=8, loc="best")
    out = Path(path)
    fig.savefig(out, dpi=120)
    return out
