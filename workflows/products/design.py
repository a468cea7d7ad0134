"""``pbmdem design``: the operating points that meet a spec, from the library's law
(:mod:`workflows.prediction.design`), no DEM or PBM run.

Reads a library model (default the shipped one) and writes, into the output folder:
``design.json`` (the spec, the grid searched with P(spec met) and the predicted mean
residence time and hold-up with their intervals at every point, the two answers with every
margin, and their feeder-noise VRR and step response with intervals), ``feasible.png`` (the
feasible region over speed and length at the answer's feed, coloured by P, with its
0.05 / 0.5 / 0.95 contours; the step response with its band) and ``report.html``.
"""

from __future__ import annotations

import contextlib
import os
import time
from dataclasses import dataclass
from pathlib import Path

from coupling.errors import OutputError, os_reason
from coupling.files import writable_directory
from coupling.forked import Prepared
from coupling.jsonable import json_ready, write_json
from workflows.prediction.design import DesignResult, DesignSpec, PointDesign, design, surrogate
from workflows.prediction.library import load_model
from workflows.report import DESIGN_FIGURES
from workflows.shipped import LIBRARY_MODEL


@dataclass(frozen=True)
class DesignOutput:
    result: DesignResult
    files: dict[str, Path]
    wall_time_s: float


def run_design(
    spec: DesignSpec,
    out_dir: str | Path = "results/design",
    library: str | Path | None = None,
    extrapolate: bool = False,
    figures: Prepared | None = None,
) -> DesignOutput:
    """``pbmdem design`` on the library model ``library`` (default the shipped one): the
    answer and the files of the module docstring. ``figures``: a process of
    :data:`workflows.report.DESIGN_FIGURES` forked by the caller before its own imports,
    which draws the figure and writes the page; else they are made in this process. The
    files are replaced only when all are made."""
    started = time.perf_counter()
    library_path = Path(library) if library is not None else LIBRARY_MODEL
    model = load_model(library_path)
    # the search first: a box it refuses leaves no output folder behind
    result = design(surrogate(model, extrapolate), spec)
    out_dir = writable_directory(out_dir, "design output directory")
    record = {**result.record(), "library": str(library_path)}
    figures = figures or Prepared(DESIGN_FIGURES, fork=False)
    drawn = out_dir / f".feasible-{os.getpid()}.png"
    figures.start("plot_design", json_ready(record), drawn)
    files = {"design": out_dir / "design.json", "figure": out_dir / "feasible.png", "report": out_dir / "report.html"}
    try:
        write_json(files["design"], json_ready(record))
        page = figures.result()
        os.replace(drawn, files["figure"])
        files["report"].write_text(page)
    except OSError as exc:
        raise OutputError(f"cannot write the design results in {out_dir}: {os_reason(exc)}") from exc
    finally:
        if figures.pending:  # failed before collecting it: the drawing ends before its file goes
            with contextlib.suppress(Exception):
                figures.result()
        drawn.unlink(missing_ok=True)
    return DesignOutput(result, files, time.perf_counter() - started)


def _point_lines(title: str, p: PointDesign) -> list[str]:
    m, h = p.mrt, p.holdup
    lines = [
        f"{title}: {p.length_m * 1000:.1f} mm ({len(p.point.blade_x_m)} blade stations) at "
        f"{p.point.impeller_rpm:.0f} rpm, {p.feed_per_s:.1f} particles/s: P(spec met) = {p.probability:.3f}",
        f"  mean residence time {m.value:.1f} s [{m.low:.1f}, {m.high:.1f}], hold-up {h.value:.0f} "
        f"[{h.low:.0f}, {h.high:.0f}] particles",
    ]
    if p.ca_sd is not None:
        lines.append(
            f"  outlet C_A SD {p.ca_sd.value:.4f} [{p.ca_sd.low:.4f}, {p.ca_sd.high:.4f}], VRR {p.vrr.value:.2f} "
            f"[{p.vrr.low:.2f}, {p.vrr.high:.2f}]"
        )
    lines.append(
        "  margins: "
        + ", ".join(
            f"{x.name} {x.margin.value:+.4g} [{x.margin.low:+.4g}, {x.margin.high:+.4g}] (P {x.probability:.3f})"
            for x in p.margins
        )
    )
    if p.outside:
        lines.append("  EXTRAPOLATED: " + "; ".join(p.outside))
    return lines


def answer_lines(result: DesignResult) -> list[str]:
    """The answer in words: each point with its intervals (95 %), margins and P."""
    lines: list[str] = []
    for title, point in (("shortest blender", result.shortest), ("largest feed", result.largest_feed)):
        if point is not None:
            lines += _point_lines(title, point)
    for key, title in (("shortest", "shortest blender"), ("largest_feed", "largest feed")):
        moves = result.dynamics.get(key)
        if moves is not None:
            d = moves.mean_delay_s
            lines.append(
                f"{title}, feeder A's rate x{moves.step_factor:g}: outlet C_A {moves.levels[0]:.3f} -> "
                f"{moves.levels[1]:.3f}, mean delay {d.value:.1f} s [{d.low:.1f}, {d.high:.1f}]"
            )
    lines += [f"note: {n}" for n in result.notes]
    return lines
