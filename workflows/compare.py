"""``pbmdem compare`` / ``make full-comparison``: DEM -> velocity tables -> PBM -> report.

The pipeline, one step per function so that each can be followed on its own:

1. :func:`dem_side` -- the DEM's velocity table and CQAs for the configuration: from the
   cache (seeded by the reference data shipped in ``workflows/reference/``), else from a
   LIGGGHTS run (``dem.run``) post-processed by ``dem.post``.
2. :func:`pbm_config_for` -- the PBM configuration that matches the DEM run: the DEM's feed
   rates, and its feed zones mapped onto the inlet compartments by overlap in y.
3. :func:`pbm.simulate.simulate` on the DEM's own table, with the tracer pulse at the DEM's
   RTD tagging time.
4. :func:`run_studies` -- the paper's blender-length, diameter and feed-noise studies on
   the same table.
5. :func:`workflows.report` -- metrics, figures, HTML, ``summary.json``; ParaView files.
"""

from __future__ import annotations

import datetime as _dt
import json
import shutil
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import pandas as pd

from coupling.cache import cache_path, try_load_dem_results
from coupling.tables import VelocityTable
from pbm.config import PbmConfig
from pbm.ensemble import PAPER_SIGMAS, noise_study
from pbm.geometry import geometry_study
from pbm.simulate import PbmResult, json_ready, simulate
from workflows.config import Config, dump_toml
from workflows.report import SideResults, Study, comparison_metrics, plot_comparison, render_html

REFERENCE_DIR = Path(__file__).parent / "reference"
LENGTH_FACTORS = (0.5, 0.75, 1.0, 1.25, 1.5)
DIAMETER_FACTORS = (0.75, 1.0, 1.25, 1.5)
NOISE_MEMBERS = 200

Log = Callable[[str], None]


@dataclass
class DemSide:
    table: VelocityTable
    results: Any  # dem.post.DemResults
    provenance: dict[str, Any]
    cache_file: Path
    source: str  # "reference", "cache" or "run"


# --- 1. DEM -------------------------------------------------------------------------------


def seed_cache_from_reference(key: str, cache_root: Path, reference_dir: Path = REFERENCE_DIR) -> bool:
    """Copy the shipped DEM results for input hash ``key`` into the cache, if there are any
    and the cache lacks a valid file. Returns True when the cache was seeded."""
    shipped = cache_path(reference_dir, key)
    target = cache_path(cache_root, key)
    if not shipped.is_file():
        return False
    if try_load_dem_results(target, key)[0] is not None:
        return False
    if try_load_dem_results(shipped, key)[0] is None:
        return False
    cache_root.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(shipped, target)
    return True


def dem_side(
    config: Config,
    runs_root: Path,
    np_ranks: int | None = None,
    fresh: bool = False,
    resume: bool = False,
    progress: bool = True,
    log: Log = lambda message: None,
) -> DemSide:
    from dem import deck
    from dem.run import liggghts_version, run_key
    from workflows.pipeline import dem_results

    cache_root = runs_root / "cache"
    seeded = False
    if not fresh:
        key = run_key(deck.build_deck(config.dem), liggghts_version(config.dem.run.liggghts))
        seeded = seed_cache_from_reference(key, cache_root)
        if seeded:
            log(f"DEM results for inputs {key} taken from the shipped reference data")
    table, results, provenance, cache_file, source = dem_results(
        config, runs_root=runs_root, cache_root=cache_root, np=np_ranks, resume=resume, fresh=fresh,
        progress=progress, log=log,
    )
    if source == "cache" and (seeded or _same_file(cache_file, cache_path(REFERENCE_DIR, provenance.get("key", "")))):
        source = "reference"
    return DemSide(table, results, provenance, cache_file, source)


def _same_file(a: Path, b: Path) -> bool:
    try:
        return a.is_file() and b.is_file() and a.read_bytes() == b.read_bytes()
    except OSError:
        return False


# --- 2. PBM configuration from the DEM's -----------------------------------------------------


def feed_weights_from_zones(y_edges: np.ndarray, y_min_m: float, y_max_m: float) -> list[float]:
    """Weights over the y compartments: the overlap of each with the feed zone [y_min, y_max].

    The DEM feeder inserts particles uniformly over its zone, and they fall nearly straight
    down onto the bed, so the overlap in y is the share each inlet compartment receives."""
    lo = np.maximum(y_edges[:-1], y_min_m)
    hi = np.minimum(y_edges[1:], y_max_m)
    overlap = np.clip(hi - lo, 0.0, None)
    if overlap.sum() <= 0:
        raise ValueError(f"feed zone y in [{y_min_m}, {y_max_m}] lies outside the compartments {y_edges[[0, -1]]}")
    return [float(w) for w in overlap / overlap.sum()]


def pbm_config_for(config: Config, table: VelocityTable, rtd_pulse_s: float | None) -> PbmConfig:
    """The PBM configuration that describes the same process as the DEM run."""
    from dem.geometry import feed_zones

    zones = feed_zones(config.dem.geometry)
    operation = config.dem.operation
    return config.pbm.model_copy(
        update={
            "feed_rate_a_per_s": operation.feed_rate_a_per_s,
            "feed_rate_b_per_s": operation.feed_rate_b_per_s,
            "feed_weights_a": feed_weights_from_zones(table.y_edges, zones["A"].ymin, zones["A"].ymax),
            "feed_weights_b": feed_weights_from_zones(table.y_edges, zones["B"].ymin, zones["B"].ymax),
            "rtd_pulse_s": rtd_pulse_s,
        }
    )


def pbm_conservation_error(result: PbmResult) -> float:
    """max over outputs of |fed - discharged - held| / fed: the PBM's particle balance."""
    fed = result.fed_A + result.fed_B
    imbalance = fed - result.discharged_A - result.discharged_B - result.holdup_A - result.holdup_B
    return float(np.max(np.abs(imbalance) / np.maximum(fed, 1.0)))


# --- 3. one shape for both sides -------------------------------------------------------------


def pbm_side(result: PbmResult) -> SideResults:
    ts = pd.DataFrame(
        {
            "t_s": result.times,
            "outflow_A_per_s": result.outflow_A,
            "outflow_B_per_s": result.outflow_B,
            "C_A": result.C_A,
            "rsd_outlet": result.rsd_outlet,
            "rsd_blender": result.rsd_blender,
            "holdup_A": result.holdup_A,
            "holdup_B": result.holdup_B,
        }
    )
    rtd = pd.DataFrame({"t_s": result.rtd_t, "E_per_s": result.rtd_E})
    return SideResults("PBM", ts, rtd, np.asarray(result.rsd_by_slice_final), dict(result.summary))


def dem_side_results(results) -> SideResults:
    """The DEM's CQAs in the report's shape; the hold-up is sampled at the CQA intervals."""
    ts = results.timeseries.copy()
    summary = dict(results.summary)
    return SideResults(
        "DEM", ts, results.rtd[["t_s", "E_per_s"]], np.asarray(results.rsd_by_slice), summary,
        rsd_by_slice_floor=np.asarray(results.rsd_by_slice_floor),
    )


# --- 4. studies ------------------------------------------------------------------------------


def _trend(values: list[float]) -> str:
    finite = [v for v in values if np.isfinite(v)]
    if len(finite) < 2:
        return "undetermined"
    diffs = np.diff(finite)
    if np.all(diffs < 0):
        return "decreases monotonically"
    if np.all(diffs > 0):
        return "increases monotonically"
    return "is not monotonic"


def _study_figure(path: Path, title: str, curves: list[tuple[str, PbmResult]]) -> str:
    import matplotlib.pyplot as plt

    fig, (ax_t, ax_x) = plt.subplots(1, 2, figsize=(11, 4), layout="constrained")
    for label, result in curves:
        ax_t.plot(result.times, result.rsd_outlet, label=label)
        ax_x.plot(np.arange(1, result.rsd_by_slice_final.size + 1), result.rsd_by_slice_final, "o-", label=label)
    ax_t.set(title=f"{title}: RSD at the outlet", xlabel="t [s]", ylabel="RSD")
    ax_x.set(title=f"{title}: RSD along the blender at the end", xlabel="axial compartment", ylabel="RSD")
    for ax in (ax_t, ax_x):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path.name


def _late_mean(result: PbmResult, fraction: float = 0.25) -> float:
    """Mean outlet RSD over the last ``fraction`` of the run (the RSD's level, not its noise)."""
    values = result.rsd_outlet[int(len(result.rsd_outlet) * (1 - fraction)) :]
    values = values[np.isfinite(values)]
    return float(values.mean()) if values.size else float("nan")


def geometry_section(parameter: str, results: dict[float, PbmResult], base_size_m: float, out_dir: Path) -> Study:
    """Report section of one geometry study (``pbm.geometry.geometry_study``'s results for
    ``parameter`` "length" or "diameter", keyed by scale factor)."""
    curves, rows = [], []
    for factor, result in results.items():
        size = base_size_m * factor
        curves.append((f"{parameter} {size * 1000:.0f} mm", result))
        rows.append(
            {
                f"{parameter} [mm]": round(size * 1000, 1),
                "late outlet RSD": _late_mean(result),
                "mean blender RSD at end": float(np.nanmean(result.rsd_by_slice_final)),
                "mean residence time [s]": result.summary.get("mean_residence_time_s"),
                "tracer recovered": result.summary.get("rtd_recovered_fraction"),
                "hold-up at end": result.summary.get("holdup_final"),
            }
        )
    figure = _study_figure(out_dir / f"study_{parameter}.png", f"Blender {parameter}", curves)
    late = [r["late outlet RSD"] for r in rows]
    mrt = [r["mean residence time [s]"] for r in rows]
    trend = (
        f"With the blender {parameter} scaled by {', '.join(f'{f:g}' for f in results)}, the late outlet RSD "
        f"{_trend(late)} ({' → '.join(f'{v:.3g}' for v in late)}) and the mean residence time {_trend(mrt)} "
        f"({' → '.join(f'{v:.3g}' for v in mrt)} s). Same velocities, compartments scaled (paper Figs 3-4)."
    )
    return Study(f"Blender {parameter} (paper Fig. {'3' if parameter == 'length' else '4'})", parameter, figure, trend, rows)


def noise_study_section(table: VelocityTable, pbm_config: PbmConfig, out_dir: Path, members: int) -> Study:
    import matplotlib.pyplot as plt

    results = noise_study(table, pbm_config, sigmas=PAPER_SIGMAS, members=members)
    fig, (ax_c, ax_r) = plt.subplots(1, 2, figsize=(11, 4), layout="constrained")
    rows = []
    for sigma, ens in results.items():
        line = ax_c.plot(ens.times, ens.C_A_mean, label=f"σ = {sigma:g}")[0]
        ax_c.fill_between(ens.times, ens.C_A_p05, ens.C_A_p95, color=line.get_color(), alpha=0.15)
        ax_r.plot(ens.times, ens.rsd_outlet_mean, color=line.get_color(), label=f"σ = {sigma:g}")
        ax_r.fill_between(ens.times, ens.rsd_outlet_p05, ens.rsd_outlet_p95, color=line.get_color(), alpha=0.15)
        late = slice(int(ens.times.size * 0.75), None)
        width = ens.C_A_p95[late] - ens.C_A_p05[late]
        rows.append(
            {
                "sigma": sigma,
                "members": ens.members,
                "late C_A mean": float(np.nanmean(ens.C_A_mean[late])),
                "late C_A 5-95 % band width": float(np.nanmean(width)),
                "late outlet RSD mean": float(np.nanmean(ens.rsd_outlet_mean[late])),
            }
        )
    ax_c.set(title="C_A at the outlet, mean and 5-95 % band (Fig. 5)", xlabel="t [s]", ylabel="C_A", ylim=(0, 1))
    ax_r.set(title="RSD at the outlet, mean and 5-95 % band (Fig. 6b)", xlabel="t [s]", ylabel="RSD")
    for ax in (ax_c, ax_r):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.savefig(out_dir / "study_noise.png", dpi=100)
    plt.close(fig)
    widths = [r["late C_A 5-95 % band width"] for r in rows]
    trend = (
        f"Feed noise σ = {', '.join(f'{s:g}' for s in results)} ({members} realisations each): the late 5-95 % band "
        f"of C_A is {' → '.join(f'{w:.3g}' for w in widths)} wide ({_trend(widths)}). Unmixed, the feed's own A "
        f"fraction a/(a+b) would scatter by ±{1.645 * max(results) * np.sqrt(2) / 4:.2g} (5-95 %) at "
        f"σ = {max(results):g}: the blender damps the feed noise by the ratio of the two."
    )
    return Study("Feed noise (paper Figs 5-6)", "sigma", "study_noise.png", trend, rows)


def run_studies(table: VelocityTable, pbm_config: PbmConfig, config: Config, out_dir: Path, members: int) -> list[Study]:
    g = config.dem.geometry
    base = pbm_config.model_copy(update={"rtd_pulse_s": None})
    geometry = geometry_study(table, base, length_factors=LENGTH_FACTORS, diameter_factors=DIAMETER_FACTORS)
    return [
        geometry_section("length", geometry["length"], g.length_m, out_dir),
        geometry_section("diameter", geometry["diameter"], g.diameter_m, out_dir),
        noise_study_section(table, base, out_dir, members),
    ]


# --- 5. the whole comparison ------------------------------------------------------------------


def _git_commit() -> str:
    try:
        out = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=Path(__file__).parent, capture_output=True, text=True, timeout=10
        )
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"], cwd=Path(__file__).parent, capture_output=True, text=True, timeout=10
        )
        return out.stdout.strip() + (" (with uncommitted changes)" if dirty.stdout.strip() else "") if out.returncode == 0 else "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


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
    # absolute, so that the run directory recorded in the cache stays findable from elsewhere
    dem = dem_side(config, Path(runs_root).resolve(), np_ranks=np_ranks, fresh=fresh, resume=resume, progress=progress, log=log)
    key = dem.provenance.get("key", "unknown")
    out_dir = Path(results_root) / f"{config.name}-{key}"
    out_dir.mkdir(parents=True, exist_ok=True)

    tag_time = dem.results.summary.get("rtd_tag_time_s")
    pbm_config = pbm_config_for(config, dem.table, rtd_pulse_s=tag_time if tag_time is not None and np.isfinite(tag_time) else None)
    log("running the PBM on the DEM's velocity tables")
    pbm_result = simulate(dem.table, pbm_config)
    conservation_error = pbm_conservation_error(pbm_result)

    dem_view, pbm_view = dem_side_results(dem.results), pbm_side(pbm_result)
    metrics = comparison_metrics(dem_view, pbm_view, feed_rate_per_s=config.dem.operation.feed_rate_total_per_s)
    figures = plot_comparison(dem_view, pbm_view, out_dir)
    try:
        from dem.render import render_geometry

        render_geometry(config.dem, out_dir / "geometry.png")
        figures["geometry"] = "geometry.png"
    except Exception as exc:  # a picture must not cost the report; say why it is missing
        log(f"geometry picture skipped: {exc}")

    log("running the PBM studies (length, diameter, feed noise)")
    t0 = time.monotonic()
    studies = run_studies(dem.table, pbm_config, config, out_dir, noise_members)
    studies_time = time.monotonic() - t0

    notes = []
    if dem.source == "reference":
        notes.append(
            f"DEM results come from the reference data shipped with the repository (made {dem.provenance.get('created')}); "
            "LIGGGHTS was not run. Use FRESH=1 (pbmdem compare --fresh) to rerun it."
        )
    elif dem.source == "cache":
        notes.append(f"DEM results come from the cache made {dem.provenance.get('created')}; LIGGGHTS was not run now.")
    for warning in dem.results.summary.get("warnings") or []:
        notes.append(f"DEM: {warning}")
    recovered = dem.results.summary.get("rtd_recovered_fraction")
    if recovered is not None and np.isfinite(recovered) and recovered < 0.95:
        notes.append(f"DEM RTD: only {recovered:.1%} of the tagged particles left by the end (the paper requires 95 %).")

    provenance = {
        "preset": config.name,
        "input_hash": key,
        "liggghts_version": dem.provenance.get("liggghts_version"),
        "commit": _git_commit(),
        "dem_source": {"run": "LIGGGHTS ran now", "cache": "cache", "reference": "shipped reference data"}[dem.source],
        "dem_results_made": dem.provenance.get("created"),
        "dem_ranks": dem.provenance.get("np"),
        "dem_cache_file": str(dem.cache_file),
        "rtd_tag_time_s": tag_time,
        "pbm_conservation_max_rel_error": conservation_error,
        "pbm_feed_weights_a": pbm_config.feed_weights_a,
        "pbm_feed_weights_b": pbm_config.feed_weights_b,
        "studies_wall_time_s": round(studies_time, 2),
        "report_made": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "config_toml": dump_toml(config),
    }
    page = render_html(f"DEM vs PBM — preset {config.name} ({key})", metrics, figures, provenance, studies, notes)
    (out_dir / "report.html").write_text(page)
    summary = {
        "metrics": metrics,
        "provenance": {k: v for k, v in provenance.items() if k != "config_toml"},
        "dem_summary": dem.results.summary,
        "pbm_summary": pbm_result.summary,
        "studies": {s.parameter: {"trend": s.trend, "rows": s.rows} for s in studies},
        "notes": notes,
    }
    (out_dir / "summary.json").write_text(json.dumps(json_ready(summary), indent=1, sort_keys=True))
    dem_view.timeseries.to_csv(out_dir / "dem_timeseries.csv", index=False)
    pbm_view.timeseries.to_csv(out_dir / "pbm_timeseries.csv", index=False)
    if paraview:
        write_paraview(config, dem, out_dir / "paraview", log)
    return out_dir / "report.html"


def write_paraview(config: Config, dem: DemSide, out_dir: Path, log: Log, max_snapshots: int = 60) -> None:
    """Compartment fields over time from the table; particle snapshots and the impeller at
    each snapshot's angle when the run directory with its dumps is still here."""
    from workflows.paraview import write_compartment_series, write_particle_series

    write_compartment_series(dem.table, out_dir, height_m=config.dem.geometry.diameter_m)
    run_dir = Path(dem.provenance.get("run_dir") or "")
    if run_dir.is_dir():
        write_particle_series(config.dem, run_dir, out_dir, max_snapshots=max_snapshots)
    else:
        log("particle snapshots not written: the DEM run directory is not on this machine")
