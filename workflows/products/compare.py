"""``pbmdem compare`` / ``make full-comparison``: DEM -> velocity tables -> PBM -> report.

:func:`full_comparison` chains the stages:

1. :func:`workflows.pipeline.stages.dem_stage` -- the DEM's velocity table and CQAs: cache,
   shipped reference data, or a LIGGGHTS run post-processed by :mod:`dem.post`.
2. :func:`workflows.pipeline.stages.pbm_config_for` -- the PBM configuration of the same process.
3. :func:`workflows.analysis.agreement.run_modes` -- the PBM on the DEM's own table in each rate
   mode, tracer pulse at the DEM's RTD tagging time, steady state by the same rule as the
   DEM; the configured mode's run gives the report's metrics and curves.
4. :mod:`workflows.analysis.agreement` -- both PBM rate modes against every DEM quantity's 95 %
   interval, and the grid sensitivity (the DEM binned at twice the NX, when its dumps,
   cache or shipped results allow it without running LIGGGHTS); :mod:`workflows.analysis.vrr` --
   the feeder-noise filtering VRR(f) of both modes against the DEM's pooled RTD.
5. :func:`workflows.products.paper_studies.run_studies` -- the paper's length, diameter and noise studies.
6. :mod:`workflows.report.comparison` -- metrics, figures, HTML and ``summary.json``; ParaView files.
"""

from __future__ import annotations

import datetime as _dt
import subprocess
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from coupling.errors import OutputError, os_reason
from coupling.jsonable import write_json
from pbm.simulate import PbmResult
from workflows.analysis.agreement import agreement_rows, dem_density, nx_sensitivity, run_modes
from workflows.analysis.vrr import vrr_comparison
from workflows.report.vrr import plot_vrr, vrr_html
from workflows.config import Config, config_from_dict, dump_toml
from workflows.pipeline.stages import DemSide, dem_stage, pbm_config_for, rtd_pulse, writable_directory
from workflows.report.comparison import (SideResults, agreement_html, comparison_metrics, plot_agreement, plot_comparison,
                              render_html)
from workflows.products.paper_studies import run_studies

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
        out = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=here, capture_output=True, text=True,
                             timeout=10)
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=here,
                               capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    if out.returncode != 0:
        return "unknown"
    return out.stdout.strip() + (" (with uncommitted changes)" if dirty.stdout.strip() else "")


def _notes(dem: DemSide) -> list[str]:
    notes = []
    made = dem.provenance.get("created")
    if dem.source == "reference":
        notes.append(f"DEM results come from the reference data shipped with the repository (made {made}); "
                     "LIGGGHTS was not run. Use FRESH=1 (pbmdem compare --fresh) to rerun it.")
    elif dem.source == "cache":
        notes.append(f"DEM results come from the cache made {made}; LIGGGHTS was not run now.")
    notes += [f"DEM: {warning}" for warning in dem.results.summary.get("warnings") or []]
    return notes


def full_comparison(
    config: Config,
    results_root: Path = Path("results"),
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
    (``<results_root>/<name>-<input hash>/report.html``)."""
    writable_directory(results_root, "results directory")  # before the DEM, which may take an hour
    dem = dem_stage(config, runs_root, np=np_ranks, fresh=fresh, resume=resume, progress=progress, log=log)
    out_dir = writable_directory(Path(results_root) / f"{config.name}-{dem.key}", "results directory")

    tag_time = rtd_pulse(dem.results.summary)
    pbm_config = pbm_config_for(config, dem.table, rtd_pulse_s=tag_time)
    log("running the PBM on the DEM's tables, in each rate mode the table supports")
    modes = run_modes(dem.table, pbm_config, config.steady_state, dem.results.summary)
    pbm_result = modes[pbm_config.rates].result  # the configured mode: the report's metrics and curves

    dem_view = SideResults("DEM", dem.results.timeseries, dem.results.rtd[["t_s", "E_per_s"]],
                           dem.results.rsd_by_slice, dict(dem.results.summary),
                           rsd_by_slice_floor=dem.results.rsd_by_slice_floor)
    pbm_view = SideResults("PBM", pbm_result.timeseries(), pbm_result.rtd(), pbm_result.rsd_by_slice_final,
                           dict(pbm_result.summary))
    metrics = comparison_metrics(dem_view, pbm_view, feed_rate_per_s=config.dem.operation.feed_rate_total_per_s)

    rows = agreement_rows(dem.results.summary, dem.results.particles, modes)
    sensitivity = grid_sensitivity(config, dem, pbm_config, modes, runs_root, log)
    vrr = feeder_filtering(dem, pbm_config, log)
    try:  # every file of the report: a full disk or a vanished directory is one line naming it
        figures = plot_comparison(dem_view, pbm_view, out_dir)
        pooled_spec = dem.results.summary.get("pooled_rtd") or {}
        dem_rtd = dem_density(dem.results.particles, pooled_spec)[:2] if pooled_spec.get("n_entered") else None
        pbm_rtd = {mode: (m.pooled.bin_edges, m.pooled.recovered_density_per_s)
                   for mode, m in modes.items() if m.pooled is not None}
        figures.update(plot_agreement(rows, dem_rtd, pbm_rtd, out_dir))
        vrr_section = ""
        if vrr is not None:
            figures["vrr"] = plot_vrr(vrr, out_dir / "vrr.png").name
            vrr_section = vrr_html(vrr, figures["vrr"])
        try:
            from dem.render import render_geometry

            render_geometry(config.dem, out_dir / "geometry.png")
            figures["geometry"] = "geometry.png"
        except Exception as exc:  # a picture must not cost the report; say why it is missing
            log(f"geometry picture skipped: {exc}")

        log("running the PBM studies (length, diameter, feed noise)")
        t0 = time.monotonic()
        studies = run_studies(dem.table, pbm_config, config.steady_state, out_dir, noise_members)
        studies_time = time.monotonic() - t0

        notes = _notes(dem)
        provenance = {
            "preset": config.name,
            "input_hash": dem.key,
            "liggghts_version": dem.provenance.get("liggghts_version"),
            "commit": _git_commit(),
            "dem_source": {"run": "LIGGGHTS ran now", "cache": "cache",
                           "reference": "shipped reference data"}[dem.source],
            "dem_results_made": dem.provenance.get("created"),
            "dem_ranks": dem.provenance.get("np"),
            "dem_wall_time_s": dem.provenance.get("wall_time_s"),
            "dem_postprocess_time_s": dem.provenance.get("postprocess_time_s"),
            "dem_cache_file": str(dem.cache_file),
            "rtd_tag_time_s": tag_time,
            "steady_state_rule": (f"window {config.steady_state.window_s:g} s, "
                                  f"relative tolerance {config.steady_state.rel_tol:g}"),
            "pbm_conservation_max_rel_error": pbm_conservation_error(pbm_result),
            "pbm_feed_weights_a": pbm_config.feed_weights_a,
            "pbm_feed_weights_b": pbm_config.feed_weights_b,
            "studies_wall_time_s": round(studies_time, 2),
            "report_made": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "config_toml": dump_toml(config),
        }
        page = render_html(f"DEM vs PBM — preset {config.name} ({dem.key})", metrics, figures, provenance, studies,
                           notes, agreement_html(rows, sensitivity) + vrr_section)
        (out_dir / "report.html").write_text(page)
        summary = {
            "metrics": metrics,
            "agreement": [r.record() for r in rows],
            "nx_sensitivity": sensitivity,
            "vrr": vrr,
            "pbm_modes": {mode: m.result.summary for mode, m in modes.items()},
            "provenance": {k: v for k, v in provenance.items() if k != "config_toml"},
            "dem_summary": dem.results.summary,
            "pbm_summary": pbm_result.summary,
            "studies": {s.parameter: {"trend": s.trend, "rows": s.rows} for s in studies},
            "notes": notes,
        }
        write_json(out_dir / "summary.json", summary)
        dem_view.timeseries.to_csv(out_dir / "dem_timeseries.csv", index=False)
        pbm_view.timeseries.to_csv(out_dir / "pbm_timeseries.csv", index=False)
        if paraview:
            write_paraview(config, dem, out_dir / "paraview", log)
    except OSError as exc:
        raise OutputError(f"cannot write the report in {out_dir}: {os_reason(exc)}") from exc
    return out_dir / "report.html"


def feeder_filtering(dem: DemSide, pbm_config, log: Log) -> dict | None:
    """:func:`workflows.analysis.vrr.vrr_comparison` of the DEM's pooled RTD and the PBM's modes, when
    the DEM has a pooled RTD; None (and a line in the log) otherwise."""
    summary = dem.results.summary
    steady = summary.get("steady_state_time_s")
    if not (summary.get("pooled_rtd") or {}).get("n_entered") or steady is None or not np.isfinite(steady):
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
    except LookupError as exc:
        log(f"grid sensitivity skipped: {exc}")
        return None
    return nx_sensitivity(fine_dem.table, pbm_config, config.steady_state, dem.results.summary, modes)


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
