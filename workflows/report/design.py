"""The design tool's figure: the feasible region over impeller speed and blender length.

Drawn from the design's record (:meth:`pbm.design.DesignResult.to_dict`, what
``design.json`` holds), so that ``design.json`` alone redraws it, and the process that
draws it imports matplotlib and nothing of the PBM (:mod:`workflows.products.design`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from matplotlib.figure import Figure


def plot_feasible(record: Mapping[str, Any], path: str | Path) -> Path:
    """The feasible lengths against the impeller speed, the best design and the library's
    runs, from a design's record (:meth:`pbm.design.DesignResult.to_dict`)."""
    fig = Figure(figsize=(7, 4.5), layout="constrained")
    ax = fig.subplots()
    length = record["library_length_m"]
    rows = record["speeds"]
    rpm = [r["rpm"] for r in rows]
    lo = [math.nan if r["length_m_lo"] is None else r["length_m_lo"] for r in rows]
    hi = [math.nan if r["length_m_hi"] is None else r["length_m_hi"] for r in rows]
    spec = record["spec"]
    ax.axhspan(
        spec["length_factor_min"] * length,
        spec["length_factor_max"] * length,
        color="#f0f0f0",
        zorder=0,
        label="lengths searched",
    )
    ax.fill_between(rpm, lo, hi, color="#74c476", alpha=0.7, label="meets the spec")
    ax.plot(rpm, lo, "g-", lw=1)
    bad = [r["rpm"] for r in rows if r["length_m_lo"] is None]
    if bad:
        ax.plot(bad, [spec["length_factor_min"] * length] * len(bad), "rx", label="no length meets it")
    best = record["best"]
    if best is not None:
        ax.plot(
            best["rpm"],
            best["length_m"],
            "k*",
            ms=12,
            label=f"smallest: {best['length_m'] * 1000:.0f} mm at {best['rpm']:g} rpm",
        )
    for k, (a, b) in enumerate(record["rpm_ranges_at_library_length"]):
        ax.hlines(length, a, b, colors="#08519c", lw=3, label="this blender meets it" if k == 0 else None)
    ax.axhline(length, color="#08519c", lw=0.8, ls="--")
    for v in record["library_rpm"]:
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
