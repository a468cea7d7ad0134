"""``pbmdem design``: the design inversion of :mod:`pbm.design` on a table library of DEM runs.

The library is read from a directory of DEM results files (default: the validation
campaign's, shipped in ``workflows/reference/validation``): the largest group of runs whose
configurations differ in the impeller speed alone. Writes ``design.json`` and
``feasible.png`` (the feasible region in the speed-length plane) into the output directory.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Any, NamedTuple

from coupling.errors import ConfigError, OutputError, os_reason
from coupling.files import writable_directory
from coupling.forked import Prepared
from coupling.jsonable import json_ready, write_json
from coupling.operating import OperatingPoint
from coupling.tables import VelocityTable
from dem.summary import DemSummary
from pbm.design import DesignResult, DesignSpec, TableLibrary, ThroughputResult, design, feed_library, max_feed
from workflows.config import Config, same_but_feed, same_but_speed
from workflows.pipeline.log import Log
from workflows.pipeline.results import load_table, pbm_config_for
from workflows.report import DESIGN_FIGURES
from workflows.shipped import VALIDATION_DIR


class LibraryRun(NamedTuple):
    """One DEM results file of a library: what the inversion reads of it."""

    path: Path
    table: VelocityTable
    summary: DemSummary
    config: Config

    @property
    def point(self) -> OperatingPoint:
        """The run's operating point, as its table records it (:func:`load_table`)."""
        if self.table.operating_point is None:
            raise ConfigError(f"table library: {self.path} records no operating point")
        return self.table.operating_point


def library_runs(directory: str | Path = VALIDATION_DIR) -> list[LibraryRun]:
    """Every DEM results file in ``directory``, each read once for both libraries, and only
    its table, summary and configuration (checked against its head digest,
    :func:`workflows.pipeline.results.load_table`). Raises ConfigError when the directory is
    none or holds no results file."""
    directory = Path(directory)
    if not directory.is_dir():
        raise ConfigError(f"table library {directory}: not a directory of DEM results files (dem-*.h5)")
    runs = [LibraryRun(path, *load_table(path)) for path in sorted(directory.glob("dem-*.h5"))]
    if not runs:
        raise ConfigError(f"table library {directory}: no DEM results files (dem-*.h5) in it")
    return runs


def load_library(runs: list[LibraryRun], rates: str = "velocity", log: Log | None = None) -> TableLibrary:
    """The table library among ``runs`` (:func:`library_runs`): grouped by configuration
    less the impeller speed, the largest group (ties: the one with the widest speed range)."""
    directory = runs[0].path.parent
    groups: dict[str, list] = {}
    for run in runs:
        groups.setdefault(repr(same_but_speed(run.config)), []).append((run.point.impeller_rpm, run))
    members = max(groups.values(), key=lambda g: (len(g), max(m[0] for m in g) - min(m[0] for m in g)))
    speeds = [m[0] for m in members]
    if len(set(speeds)) != len(speeds):
        raise ConfigError(f"table library {directory}: two runs at the same speed ({sorted(speeds)} rpm)")
    (log or (lambda _: None))(
        f"table library: {', '.join(f'{m[0]:g} rpm ({m[1].path.name})' for m in sorted(members, key=lambda m: m[0]))}"
    )
    first = members[0][1]
    if any(m[1].summary.steady_time is None for m in members):
        raise ConfigError(
            f"table library {directory}: a run never reached the steady state; its tables describe no "
            "stationary blender"
        )
    pbm_config = pbm_config_for(first.config, first.table, None).model_copy(update={"rates": rates})
    steady = max(m[1].summary.steady_time for m in members)
    return TableLibrary(tuple((m[0], m[1].table) for m in members), pbm_config, float(steady), first.point.length_m)


def load_feed_library(runs: list[LibraryRun], rates: str = "measured", log: Log | None = None):
    """The feed library among ``runs`` (:func:`library_runs`): the largest group whose
    configurations differ only in the feed rate (and the duration), when it holds at least
    two runs with a steady state; else None (the answer then has no throughput)."""
    groups: dict[str, list] = {}
    for run in runs:
        if run.summary.steady_time is None or not run.table.has_rates:
            continue
        groups.setdefault(repr(same_but_feed(run.config)), []).append(run)
    members = max(groups.values(), key=len, default=[])
    if len(members) < 2:
        return None
    members.sort(key=lambda m: m.point.feed_rate_total_per_s)
    (log or (lambda _: None))(
        "feed library: " + ", ".join(f"{m.point.feed_rate_total_per_s:g} /s ({m.path.name})" for m in members)
    )
    first = members[0]
    pbm_config = pbm_config_for(first.config, first.table, None).model_copy(update={"rates": rates})
    tables = [(m.point.feed_rate_total_per_s, m.table) for m in members]
    return feed_library(tables, pbm_config, first.point.impeller_rpm, first.point.length_m)


def run_design(
    spec: DesignSpec,
    out_dir: str | Path = "results/design",
    library_dir: str | Path = VALIDATION_DIR,
    rates: str = "velocity",
    log: Log | None = None,
    figures: Prepared | None = None,
) -> tuple[DesignResult, ThroughputResult | None, Path]:
    """``pbmdem design``: the answer (the smallest blender; the largest feed its own blender
    takes, when the directory holds a feed library), ``design.json`` and ``feasible.png``
    in ``out_dir``. ``figures``: a process of :data:`workflows.report.DESIGN_FIGURES`
    forked by the caller before its own imports, which draws the figure while the feed
    library is searched here; else it is drawn in this process. Both files are replaced
    only when both are made: the figure is drawn to a file of its own first."""
    out_dir = writable_directory(out_dir, "design output directory")
    runs = library_runs(library_dir)
    library = load_library(runs, rates, log)
    figures = figures or Prepared(DESIGN_FIGURES, fork=False)
    figures.ready()  # its imports done, so that the search finds its core free
    result = design(library, spec)
    record = result.to_dict()
    drawn = out_dir / f".feasible-{os.getpid()}.png"
    figures.start("plot_feasible", record, drawn)
    try:
        feeds = load_feed_library(runs, rates, log)
        throughput = None if feeds is None else max_feed(feeds, spec)
        data: dict[str, Any] = {
            **record,
            "throughput": None if throughput is None else throughput.to_dict(),
            "library_dir": str(library_dir),
            "rates": rates,
            "steady_time_s": library.steady_time_s,
        }
        figures.result()
        write_json(out_dir / "design.json", json_ready(data))
        os.replace(drawn, out_dir / "feasible.png")
    except OSError as exc:
        raise OutputError(f"cannot write the design results in {out_dir}: {os_reason(exc)}") from exc
    finally:
        if figures.pending:  # failed before collecting it: the drawing ends before its file goes
            with contextlib.suppress(Exception):
                figures.result()
        drawn.unlink(missing_ok=True)
    return result, throughput, out_dir


def throughput_lines(throughput: ThroughputResult | None) -> list[str]:
    """The throughput answer in words."""
    if throughput is None:
        return ["largest feed: no feed library (two or more steady runs differing only in feed rate) in the directory"]
    lo, hi = throughput.feed_range
    if throughput.best is None:
        return [f"largest feed: none in the feed library's {lo:g}-{hi:g} /s meets the spec"] + [
            f"note: {n}" for n in throughput.notes
        ]
    best = throughput.best
    line = (
        f"largest feed meeting the spec at the library's own blender ({best.rpm:g} rpm, rates following the fill): "
        f"{best.feed_per_s:.1f} particles/s (feed library {lo:g}-{hi:g} /s); mean residence time "
        f"{best.mean_residence_time_s:.1f} s"
    )
    if best.ca_sd is not None:
        line += f", outlet C_A SD {best.ca_sd:.4f}"
    return [line, "  margins: " + ", ".join(f"{k} {v:+.4g}" for k, v in best.margins.items())] + [
        f"note: {n}" for n in throughput.notes
    ]


def answer_lines(result: DesignResult) -> list[str]:
    """The answer in words, with every margin."""
    if result.best is None:
        return ["no design in the library's range meets the spec: " + "; ".join(result.notes)]
    best = result.best
    lines = [
        f"smallest blender: {best.length_factor * result.length_m * 1000:.1f} mm "
        f"({best.length_factor:.3f} x the library's {result.length_m * 1000:.0f} mm) at {best.rpm:g} rpm"
    ]
    ranges = " and ".join(f"{a:.0f}-{b:.0f} rpm" for a, b in result.rpm_ranges) or "no speed searched"
    lines.append(
        f"the library's own {result.length_m * 1000:.0f}-mm blender meets it at {ranges} (searched "
        f"{result.rows[0].rpm:g}-{result.rows[-1].rpm:g} rpm)"
    )
    lines.append(
        f"mean residence time {best.mean_residence_time_s:.1f} s"
        + (
            f"; outlet C_A SD {best.ca_sd:.4f} (RSD {best.ca_rsd:.2%}, VRR {best.vrr:.1f})"
            if best.ca_sd is not None
            else ""
        )
    )
    lines.append("margins: " + ", ".join(f"{k} {v:+.4g}" for k, v in best.margins.items()))
    lines += [f"note: {n}" for n in result.notes]
    return lines
