"""``pbmdem compare`` / ``make full-comparison``: DEM -> velocity tables -> PBM -> report.

:func:`full_comparison` chains the stages:

1. :func:`workflows.pipeline.stages.dem_stage` -- the DEM's velocity table and CQAs: cache,
   shipped reference data, or a LIGGGHTS run post-processed by :mod:`dem.post`.
2. :func:`workflows.pipeline.results.pbm_config_for` -- the PBM configuration of the same process.
3. :func:`workflows.analysis.agreement.run_modes` -- the PBM on the DEM's own table in each rate
   mode, tracer pulse at the DEM's RTD tagging time, steady state by the same rule as the
   DEM; the configured mode's run gives the report's metrics and curves.
4. :mod:`workflows.analysis.agreement` -- every PBM rate mode against every DEM quantity's 95 %
   interval, and the grid sensitivity (the DEM binned at twice the NX, when its dumps,
   cache or shipped results allow it without running LIGGGHTS); :mod:`workflows.analysis.vrr` --
   the feeder-noise filtering VRR(f) of every mode against the DEM's pooled RTD;
   :mod:`workflows.analysis.memory` -- the Chapman-Kolmogorov test of the phase model and of
   the memoryless chain on the DEM's particle sequences.
5. :func:`workflows.products.paper_studies.run_studies` -- the paper's length, diameter and noise studies.
6. :mod:`workflows.report.comparison` -- metrics, figures, HTML and ``summary.json``; ParaView files.
"""

from __future__ import annotations

import datetime as _dt
import os
import subprocess
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from coupling.blas import single_threaded_blas
from coupling.errors import OutputError, ResourceLimitError, os_reason
from coupling.files import replace_file, writable_directory
from coupling.jsonable import write_json
from pbm.config import PbmConfig
from pbm.simulate import PbmResult
from workflows.analysis.agreement import (
    AgreementRow,
    PbmMode,
    agreement_rows,
    dem_density,
    nx_sensitivity,
    run_modes,
)
from workflows.analysis.memory import MemoryCheck, memory_check
from workflows.analysis.vrr import VrrComparison, vrr_comparison
from workflows.config import Config, config_from_dict, dump_toml
from workflows.pipeline.results import pbm_config_for, rtd_pulse
from workflows.pipeline.stages import DemSide, dem_stage
from workflows.products.paper_studies import run_studies
from workflows.report.comparison import (
    Recommendation,
    ReportFile,
    SideResults,
    agreement_html,
    bottom_line_html,
    comparison_metrics,
    interval_method,
    plot_agreement,
    plot_comparison,
    recommend,
    render_html,
    split_warnings,
)
from workflows.report.memory import memory_html, plot_ck
from workflows.report.vrr import plot_vrr, vrr_html

NOISE_MEMBERS = 200

Log = Callable[[str], None]


def pbm_conservation_error(result: PbmResult) -> float:
    """max over outputs of |fed - discharged - held| / fed: the PBM's particle balance."""
    fed = result.fed_A + result.fed_B
    imbalance = fed - result.discharged_A - result.discharged_B - result.holdup_A - result.holdup_B
    return float(np.max(np.abs(imbalance) / np.maximum(fed, 1.0)))


def _git_commit() -> str:
    here = Path(__file__).parent
    try:
        out = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=here, capture_output=True, text=True, timeout=10
        )
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=here,
            capture_output=True,
            text=True,
            timeout=10,
        )
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    if out.returncode != 0:
        return "unknown"
    return out.stdout.strip() + (" (with uncommitted changes)" if dirty.stdout.strip() else "")


def _notes(dem: DemSide) -> tuple[list[str], list[str]]:
    """The page's notes: (on the comparison's validity, for its top; the DEM run's solver
    diagnostics, for its end)."""
    notes = []
    made = dem.provenance.get("created")
    if dem.source == "reference":
        notes.append(
            f"DEM results come from the reference data shipped with the repository (made {made}); "
            "LIGGGHTS was not run. Use FRESH=1 (pbmdem compare --fresh) to rerun it."
        )
    elif dem.source == "cache":
        notes.append(f"DEM results come from the cache made {made}; LIGGGHTS was not run now.")
    validity, diagnostics = split_warnings(dem.results.summary.warnings)
    notes += [f"DEM: {warning}" for warning in validity]
    return notes, diagnostics


@dataclass(frozen=True)
class Comparison:
    """The numbers of one comparison: the DEM's side, each PBM rate mode on its tables, the
    agreement table and the mode it recommends (None without one), that mode's curves
    beside the DEM's (the configured mode's without a recommendation), the grid
    sensitivity and the feeder-noise filtering."""

    config: Config
    dem: DemSide
    pbm_config: PbmConfig
    modes: dict[str, PbmMode]
    dem_view: SideResults
    pbm_view: SideResults
    metrics: dict[str, Any]
    rows: list[AgreementRow]
    recommendation: Recommendation | None
    sensitivity: dict[str, Any] | None
    vrr: VrrComparison | None
    memory: MemoryCheck | None

    @property
    def shown_mode(self) -> str:
        """The rate mode of the report's metrics and curves: the recommended one."""
        return self.pbm_config.rates if self.recommendation is None else self.recommendation.mode

    @property
    def pbm_result(self) -> PbmResult:
        """The shown rate mode's run."""
        return self.modes[self.shown_mode].result


def full_comparison(
    config: Config,
    out_dir: Path | None = None,
    runs_root: Path = Path("runs"),
    np_ranks: int | None = None,
    fresh: bool = False,
    resume: bool = False,
    noise_members: int = NOISE_MEMBERS,
    paraview: bool = True,
    progress: bool = True,
    log: Log = lambda message: None,
) -> Path:
    """Run the whole comparison for ``config`` and return the report's path
    (``<out_dir>/report.html``; by default ``results/<name>-<input hash>/report.html``)."""
    # checked before the DEM, which may take an hour
    writable_directory(Path("results") if out_dir is None else out_dir, "--out")
    dem = dem_stage(config, runs_root, np=np_ranks, fresh=fresh, resume=resume, progress=progress, log=log)
    if out_dir is None:
        out_dir = writable_directory(Path("results") / f"{config.name}-{dem.key}", "--out")
    out_dir = Path(out_dir)
    comparison = compare(config, dem, runs_root, log)
    try:  # every file of the report: a full disk or a vanished directory is one line naming it
        write_report(comparison, out_dir, noise_members, paraview, log)
    except OSError as exc:
        raise OutputError(f"cannot write the report in {out_dir}: {os_reason(exc)}") from exc
    return out_dir / "report.html"


def compare(config: Config, dem: DemSide, runs_root: Path, log: Log = lambda message: None) -> Comparison:
    """The comparison's numbers for the DEM's results ``dem``; writes nothing (the grid
    sensitivity reads or post-processes the same run at 2 NX through ``runs_root``)."""
    pbm_config = pbm_config_for(config, dem.table, rtd_pulse_s=rtd_pulse(dem.results.summary))
    # The memory check (a phase refit, mostly compiled code that releases the GIL) needs
    # nothing of what follows, so it runs on the second core meanwhile. OpenBLAS's thread
    # count is one per process: set once around both threads, not by each in turn, whose
    # saves and restores would interleave.
    with single_threaded_blas():
        aside = ThreadPoolExecutor(max_workers=1, thread_name_prefix="memory-check")
        try:
            memory_future = aside.submit(memory_check, dem.results, pbm_config)
            return _compare(config, dem, runs_root, pbm_config, memory_future, log)
        finally:
            aside.shutdown(wait=False, cancel_futures=True)


def _compare(
    config: Config, dem: DemSide, runs_root: Path, pbm_config: PbmConfig, memory_future, log: Log
) -> Comparison:
    log("running the PBM on the DEM's tables, in each rate mode the table supports")
    modes = run_modes(dem.table, pbm_config, config.steady_state, dem.results.summary)
    rows = agreement_rows(dem.results.summary, dem.results.particles, modes, dem.results.steady_outlet_counts())
    recommendation = recommend(rows)
    shown = pbm_config.rates if recommendation is None else recommendation.mode
    pbm_result = modes[shown].result
    dem_view = SideResults(
        "DEM",
        dem.results.timeseries,
        dem.results.rtd[["t_s", "E_per_s"]],
        dem.results.rsd_by_slice,
        dem.results.summary,
        rsd_by_slice_floor=dem.results.rsd_by_slice_floor,
    )
    pbm_view = SideResults(
        f"PBM, {shown} rates",
        pbm_result.timeseries(),
        pbm_result.rtd(),
        pbm_result.rsd_by_slice_final,
        pbm_result.summary,
    )
    metrics = comparison_metrics(dem_view, pbm_view, feed_rate_per_s=config.dem.operation.feed_rate_total_per_s)
    sensitivity = grid_sensitivity(config, dem, pbm_config, modes, runs_root, log)
    vrr = feeder_filtering(dem, pbm_config, log)
    memory = memory_future.result()
    return Comparison(
        config, dem, pbm_config, modes, dem_view, pbm_view, metrics, rows, recommendation, sensitivity, vrr, memory
    )


def write_figures(c: Comparison, out_dir: Path, log: Log) -> dict[str, str]:
    """The report's figures, as file names in ``out_dir`` by their role."""
    figures = plot_comparison(c.dem_view, c.pbm_view, out_dir)
    summary = c.dem.results.summary
    dem_rtd = dem_density(c.dem.results.particles, summary.pooled_rtd)[:2] if summary.has_pooled_rtd else None
    pbm_rtd = {
        mode: (m.pooled.bin_edges, m.pooled.recovered_density_per_s)
        for mode, m in c.modes.items()
        if m.pooled is not None
    }
    figures.update(plot_agreement(c.rows, dem_rtd, pbm_rtd, out_dir))
    if c.vrr is not None:
        figures["vrr"] = plot_vrr(c.vrr, out_dir / "vrr.png").name
    if c.memory is not None:
        figures["ck"] = plot_ck(c.memory, out_dir / "chapman_kolmogorov.png").name
    try:
        from dem.render import render_geometry

        render_geometry(c.config.dem, out_dir / "geometry.png")
        figures["geometry"] = "geometry.png"
    except Exception as exc:  # a picture must not cost the report; say why it is missing
        log(f"geometry picture skipped: {exc}")
    return figures


def provenance_of(c: Comparison, studies_time_s: float) -> dict[str, Any]:
    """Where every number of the report came from."""
    config, dem = c.config, c.dem
    return {
        "preset": config.name,
        "input_hash": dem.key,
        "liggghts_version": dem.provenance.get("liggghts_version"),
        "commit": _git_commit(),
        "dem_source": {"run": "LIGGGHTS ran now", "cache": "cache", "reference": "shipped reference data"}[dem.source],
        "dem_results_made": dem.provenance.get("created"),
        "dem_ranks": dem.provenance.get("np"),
        "dem_wall_time_s": dem.provenance.get("wall_time_s"),
        "dem_postprocess_time_s": dem.provenance.get("postprocess_time_s"),
        "dem_cache_file": str(dem.cache_file),
        "rtd_tag_time_s": rtd_pulse(dem.results.summary),
        "steady_state_rule": (
            f"window {config.steady_state.window_s:g} s, relative tolerance {config.steady_state.rel_tol:g}"
        ),
        "pbm_rates_configured": c.pbm_config.rates,
        "pbm_rates_shown": c.shown_mode,
        "pbm_conservation_max_rel_error": pbm_conservation_error(c.pbm_result),
        "pbm_feed_weights_a": c.pbm_config.feed_weights_a,
        "pbm_feed_weights_b": c.pbm_config.feed_weights_b,
        "studies_wall_time_s": round(studies_time_s, 2),
        "report_made": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "config_toml": dump_toml(config),
    }


def write_report(c: Comparison, out_dir: Path, noise_members: int, paraview: bool, log: Log) -> None:
    """``report.html`` with its figures, the paper's studies, ``summary.json``, both sides'
    time series as CSV, the resolved configuration and (``paraview``) the VTK files, all in
    ``out_dir``; the page last, linking every other file."""
    figures = write_figures(c, out_dir, log)
    vrr_section = "" if c.vrr is None else vrr_html(c.vrr, figures["vrr"])
    memory_section = "" if c.memory is None else memory_html(c.memory, figures.get("ck"))
    log("running the PBM studies (length, diameter, feed noise)")
    t0 = time.monotonic()
    studies = run_studies(c.dem.table, c.pbm_config, c.config.steady_state, out_dir, noise_members)
    provenance = provenance_of(c, time.monotonic() - t0)
    notes, diagnostics = _notes(c.dem)
    summary = {
        "recommendation": None if c.recommendation is None else c.recommendation.record(),
        "metrics": c.metrics,
        "agreement": [r.record() for r in c.rows],
        "nx_sensitivity": c.sensitivity,
        "vrr": None if c.vrr is None else c.vrr.record(),
        "memory": None if c.memory is None else c.memory.record(),
        "pbm_modes": {mode: m.result.summary.record() for mode, m in c.modes.items()},
        "provenance": {k: v for k, v in provenance.items() if k != "config_toml"},
        "dem_summary": c.dem.results.summary.record(),
        "pbm_summary": c.pbm_result.summary.record(),
        "studies": {s.parameter: {"trend": s.trend, "rows": s.rows} for s in studies},
        "notes": notes,
        "solver_diagnostics": diagnostics,
    }
    write_json(out_dir / "summary.json", summary)
    replace_file(out_dir / "dem_timeseries.csv", c.dem_view.timeseries.to_csv(index=False), "DEM time series")
    replace_file(out_dir / "pbm_timeseries.csv", c.pbm_view.timeseries.to_csv(index=False), "PBM time series")
    replace_file(out_dir / "config.toml", provenance["config_toml"], "configuration")
    if paraview:
        write_paraview(c.config, c.dem, out_dir / "paraview", log)
    page = render_html(
        f"DEM vs PBM — preset {c.config.name} ({c.dem.key})",
        bottom_line=bottom_line_html(c.recommendation, c.rows, c.pbm_config.rates),
        agreement=agreement_html(c.rows, c.sensitivity, interval_method(c.dem.results.summary.steady)),
        figures=figures,
        shown_mode=c.shown_mode,
        studies_mode=c.pbm_config.rates,
        metrics=c.metrics,
        provenance=provenance,
        studies=studies,
        notes=notes,
        sections=[vrr_section, memory_section],
        files=report_files(c, out_dir, figures, studies),
        diagnostics=diagnostics,
    )
    replace_file(out_dir / "report.html", page, "report")


#: what each figure of :func:`write_figures` shows, for the page's list of files
FIGURE_FILES = {
    "overview": "the six panels of DEM and PBM over time in one figure",
    "rtd": "tagged RTD (paper Fig. 7)",
    "rsd_axial": "raw RSD per axial slice at the end (Fig. 8a)",
    "rsd_time": "raw RSD at the outlet over time (Fig. 8b)",
    "c_a": "C_A of the outflow over time (Fig. 9)",
    "outflow": "outflow rate over time (Fig. 10)",
    "holdup": "hold-up over time",
    "rtd_pooled": "pooled RTD, DEM and every PBM rate mode",
    "holdup_profile": "steady hold-up per axial slice, DEM with its intervals and every PBM rate mode",
    "vrr": "feeder-noise filtering, VRR(f)",
    "ck": "Chapman-Kolmogorov test of the PBM's chains",
    "geometry": "the blender's geometry",
}

#: the ParaView collections :func:`write_paraview` may write
PARAVIEW_FILES = {
    "compartments": "compartment fields (counts, velocities) per velocity window",
    "particles": "particle snapshots",
    "impeller": "the impeller at each snapshot's angle",
}


def report_files(c: Comparison, out_dir: Path, figures: dict[str, str], studies) -> list[ReportFile]:
    """Every file of the run the page links, relative to ``out_dir``: the data first (the
    DEM's results file where it lies, linked relative to the page too), then the figures;
    only the files that exist."""
    files = [
        ReportFile("summary.json", "every number of the page, the recommendation and the provenance (JSON)"),
        ReportFile("dem_timeseries.csv", "the DEM's time series: hold-up, outflow, C_A, raw RSDs and their floors"),
        ReportFile("pbm_timeseries.csv", f"the PBM's time series with the {c.shown_mode} rates, the same columns"),
        ReportFile("config.toml", "the resolved configuration of this comparison"),
    ]
    files = [f for f in files if (out_dir / f.href).is_file()]
    source = {"run": "LIGGGHTS ran now", "cache": "from the cache", "reference": "shipped with the repository"}
    files.append(
        ReportFile(
            _relative(c.dem.cache_file, out_dir),
            f"the DEM's results (HDF5: velocity tables, time series, per-particle records), {source[c.dem.source]}",
        )
    )
    for stem, what in PARAVIEW_FILES.items():
        pvd = out_dir / "paraview" / f"{stem}.pvd"
        if pvd.is_file():
            steps = len(list(pvd.parent.glob(f"{stem}_*")))
            files.append(ReportFile(f"paraview/{pvd.name}", f"ParaView: {what}, {steps} files"))
    if (out_dir / "paraview" / "weir.vtp").is_file():
        files.append(ReportFile("paraview/weir.vtp", "ParaView: the weir"))
    files += [ReportFile(name, FIGURE_FILES.get(key, key)) for key, name in figures.items()]
    files += [ReportFile(s.figure, f"figure: {s.title}") for s in studies]
    return files


def _relative(path: Path, start: Path) -> str:
    """``path`` as a link from a page in ``start``: relative (both resolved), its file URI
    when none exists (another drive)."""
    try:
        return Path(os.path.relpath(Path(path).resolve(), Path(start).resolve())).as_posix()
    except ValueError:
        return Path(path).resolve().as_uri()


def feeder_filtering(dem: DemSide, pbm_config, log: Log) -> VrrComparison | None:
    """:func:`workflows.analysis.vrr.vrr_comparison` of the DEM's pooled RTD and the PBM's modes, when
    the DEM has a pooled RTD; None (and a line in the log) otherwise."""
    summary = dem.results.summary
    steady = summary.steady_time
    if not summary.has_pooled_rtd or steady is None:
        log("feeder-noise filtering skipped: the DEM has no pooled RTD")
        return None
    log("feeder-noise filtering: VRR(f) of the PBM against the DEM's pooled RTD")
    return vrr_comparison(dem.table, pbm_config, float(steady), summary, dem.results.particles)


def grid_sensitivity(config: Config, dem: DemSide, pbm_config, modes, runs_root: Path, log: Log) -> dict | None:
    """:func:`workflows.analysis.agreement.nx_sensitivity` on the same DEM run binned at twice the
    NX, when that needs no new LIGGGHTS run; None (and a line in the log) otherwise."""
    data = config.to_dict()
    data["dem"]["tables"]["nx"] = 2 * config.dem.tables.nx
    fine = config_from_dict(data, source="the grid-sensitivity configuration")
    try:
        fine_dem = dem_stage(fine, runs_root, solver=False, progress=False, log=log)
    except (LookupError, ResourceLimitError) as exc:  # a finer grid this machine cannot afford is no failure
        log(f"grid sensitivity skipped: {exc}")
        return None
    # the feed zones mapped onto the finer compartments: a zone inside the first of NX slices
    # may span two of 2 NX
    on_fine = pbm_config_for(config, fine_dem.table, pbm_config.rtd_pulse_s)
    fine_config = pbm_config.model_copy(
        update={"feed_weights_a": on_fine.feed_weights_a, "feed_weights_b": on_fine.feed_weights_b}
    )
    return nx_sensitivity(fine_dem.table, fine_config, config.steady_state, dem.results.summary, modes)


def write_paraview(config: Config, dem: DemSide, out_dir: Path, log: Log, max_snapshots: int = 60) -> None:
    """Compartment fields over time from the table; particle snapshots and the impeller at
    each snapshot's angle when the run directory with its dumps is still here."""
    from workflows.report.paraview import write_compartment_series, write_particle_series

    write_compartment_series(dem.table, out_dir, height_m=config.dem.geometry.diameter_m)
    run_dir = Path(dem.provenance.get("run_dir") or "")
    if run_dir.is_dir():
        write_particle_series(config.dem, run_dir, out_dir, max_snapshots=max_snapshots)
    else:
        log("particle snapshots not written: the DEM run directory is not on this machine")
