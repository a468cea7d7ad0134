"""``pbmdem dem ...``: the DEM stage's commands.

    pbmdem dem deck  --preset NAME|--config FILE.toml --out DIR [--resume-from R] [--png] [--view-stl]
    pbmdem dem run   --preset NAME|--config FILE.toml [--np N] [--resume] [--fresh]
                     [--runs-dir DIR] [--cache-dir DIR] [--no-progress]
                     [--stop-when-converged [--check-every S]]
    pbmdem dem post  --preset NAME|--config FILE.toml --dumps 'GLOB' --out-file RESULTS.h5 [--massflow-dir DIR]
    pbmdem dem refit-phases RESULTS.h5 [...]
    pbmdem dem recompute-steady RESULTS.h5 [...]
    pbmdem dem slurm --preset NAME|--config FILE.toml --out DIR [--np N] [--partition P]
                     [--holdup N] [--throughput R]

``run`` reuses a valid cache file or a completed run of the same inputs; ``post`` needs only
the dumps and the configuration they were made with; ``refit-phases`` and
``recompute-steady`` bring a results file made by an earlier version up to this one's
phase fit and steady intervals from what the file stores; ``slurm`` writes the run
directory and a batch script instead of running.
"""

from __future__ import annotations

import argparse
import functools
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from coupling.errors import CacheError, ConfigError
from coupling.files import locked, refuse_output_over_inputs, regular_file
from workflows.pipeline.log import stderr_log

if TYPE_CHECKING:
    from dem.summary import DemSummary

SUMMARY_KEYS = (
    "t_end_s",
    "steady_state_time_s",
    "steady_outflow_per_s",
    "steady_C_A",
    "mean_residence_time_s",
    "rtd_variance_s2",
    "rtd_recovered_fraction",
    "final_rsd_outlet",
    "final_rsd_outlet_floor",
    "final_rsd_blender",
    "final_rsd_blender_floor",
    "holdup_final",
    "inserted",
    "held",
    "discharged",
    "lost",
    "accounting_mismatch",
    "massflow_discharged",
    "discharge_crosscheck_diff",
)


HELP = "DEM stage: write decks, run LIGGGHTS, post-process dumps"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from workflows.config import add_config_arguments

    dem_sub = parser.add_subparsers(dest="dem_command", required=True, metavar="DEM_COMMAND")

    deck = dem_sub.add_parser("deck", help="write a LIGGGHTS deck, meshes and the resolved config into a directory")
    add_config_arguments(deck)
    deck.add_argument("--out", required=True, help="run directory to create (or refresh)")
    deck.add_argument(
        "--resume-from",
        default=None,
        help="also write in.resume, continuing from this restart file (path relative to --out)",
    )
    deck.add_argument("--png", action="store_true", help="also render the assembled geometry to geometry.png")
    deck.add_argument(
        "--view-stl",
        action="store_true",
        help="also write meshes/view_barrel.stl and meshes/view_inlet_wall.stl (viewing only; the deck "
        "uses LIGGGHTS primitives for these)",
    )
    deck.set_defaults(func=deck_command)

    run = dem_sub.add_parser("run", help="run LIGGGHTS on the deck, post-process, cache the velocity table and results")
    add_config_arguments(run)
    run.add_argument("--np", type=int, default=None, help="MPI ranks (default: the config's dem.run.np)")
    run.add_argument("--resume", action="store_true", help="continue an interrupted run from its last restart file")
    run.add_argument("--fresh", action="store_true", help="discard a previous run and cache of the same inputs")
    run.add_argument("--runs-dir", default="runs", help="root of the run directories (default: ./runs)")
    run.add_argument("--cache-dir", default=None, help="where dem-<hash>.h5 goes (default: <runs-dir>/cache)")
    run.add_argument("--no-progress", action="store_true", help="no progress bar")
    run.add_argument(
        "--stop-when-converged",
        action="store_true",
        help="stop the run once more DEM would not move the PBM by more than the DEM resolves "
        "(checked every --check-every simulated seconds; --resume continues a stopped run)",
    )
    run.add_argument(
        "--check-every",
        type=float,
        default=None,
        metavar="S",
        help="simulated seconds between convergence checks (default 20)",
    )
    run.set_defaults(func=run_command)

    post = dem_sub.add_parser("post", help="post-process existing dumps into a velocity table + DEM results file")
    add_config_arguments(post)
    post.add_argument("--dumps", required=True, help="glob of the dump files, quoted: 'run/dumps/dump.*.txt'")
    post.add_argument(
        "--out-file", required=True, metavar="RESULTS.h5", help="the HDF5 file to write (velocity table + DEM results)"
    )
    post.add_argument(
        "--massflow-dir", default=None, help="directory of the discharge files (default: beside the dumps)"
    )
    post.set_defaults(func=post_command)

    refit = dem_sub.add_parser(
        "refit-phases",
        help="fit the hidden-phase model of DEM results files again to their own compartment sequences "
        "(after the fit changed; no dumps needed), rewriting each file in place",
    )
    refit.add_argument("results", nargs="+", help="DEM results files (dem-*.h5) with compartment sequences")
    refit.set_defaults(func=refit_command)

    recompute = dem_sub.add_parser(
        "recompute-steady",
        help="compute the steady quantities, their intervals and the pooled RTD of DEM results files again "
        "from their stored compartment counts or sequences (after the method changed; no dumps needed), "
        "rewriting each file in place",
    )
    recompute.add_argument("results", nargs="+", help="DEM results files (dem-*.h5)")
    recompute.set_defaults(func=recompute_steady_command)

    slurm = dem_sub.add_parser(
        "slurm", help="write the deck and a Slurm batch script with a cost estimate, without running"
    )
    add_config_arguments(slurm)
    slurm.add_argument("--out", required=True, help="run directory to create (deck + job.slurm)")
    slurm.add_argument("--np", type=int, default=None, help="MPI tasks (default: the config's dem.run.np)")
    slurm.add_argument("--partition", default=None, help="Slurm partition")
    slurm.add_argument(
        "--holdup",
        type=float,
        default=None,
        help="steady hold-up [particles]; default: scaled from the shipped reduced run",
    )
    slurm.add_argument(
        "--throughput",
        type=float,
        default=None,
        help="particle-steps per second per core; default: the shipped paper-scale measurement "
        "for the paper's particles, else 3.9e6 (`pbmdem bench dem-deck` measures this machine's)",
    )
    slurm.set_defaults(func=slurm_command)


def refuse_config_overwrite(out: str, config_file: str | None, written: tuple[str, ...]) -> None:
    """A run directory's files must not replace the configuration file they are made from
    (``--out`` holding ``--config`` as ``config.toml``, say): refused before writing."""
    for name in written:
        refuse_output_over_inputs(Path(out) / name, [config_file], "--out", ConfigError)


RUN_DIRECTORY_FILES = ("config.toml", "deck.json", "in.blender")


def deck_command(args: argparse.Namespace) -> int:
    from workflows.config import resolve_config
    from workflows.pipeline.stages import write_run_directory

    refuse_config_overwrite(args.out, args.config, RUN_DIRECTORY_FILES)
    out, digest = write_run_directory(
        resolve_config(args.preset, args.config), args.out, args.resume_from, view_stl=args.view_stl, png=args.png
    )
    print(f"wrote {out / 'in.blender'} (deck hash {digest}); run: cd {out} && liggghts -in in.blender")
    return 0


def run_command(args: argparse.Namespace) -> int:
    from workflows.config import resolve_config
    from workflows.pipeline.stages import dem_stage

    config = resolve_config(args.preset, args.config)
    watch = None
    if args.stop_when_converged:
        from workflows.analysis.convergence import CHECK_EVERY_S, ConvergenceWatch

        every = CHECK_EVERY_S if args.check_every is None else args.check_every
        if not (math.isfinite(every) and every > 0):
            raise ConfigError(f"--check-every must be a number of seconds > 0, got {every}")

        watch = functools.partial(ConvergenceWatch, config, every_s=every, log=stderr_log)
    elif args.check_every is not None:
        raise ConfigError("--check-every needs --stop-when-converged")
    dem = dem_stage(
        config,
        runs_root=args.runs_dir,
        cache_root=args.cache_dir,
        np=args.np,
        resume=args.resume,
        fresh=args.fresh,
        progress=not args.no_progress,
        log=stderr_log,
        watch=watch,
    )
    if dem.source != "run":
        stderr_log(f"DEM results reused from the {dem.source} (LIGGGHTS not started)")
    print_summary(dem.results.summary)
    print(f"DEM results and velocity table: {dem.cache_file}")
    print(f"run directory: {dem.provenance.get('run_dir')}")
    if dem.provenance.get("run_state") == "stopped":
        print(f"stopped early: {dem.provenance.get('stop_reason')}; continue it to the end with --resume")
    return 0


def post_command(args: argparse.Namespace) -> int:
    from workflows.config import resolve_config
    from workflows.pipeline.stages import postprocess_dumps

    results = postprocess_dumps(
        resolve_config(args.preset, args.config), args.dumps, args.out_file, args.massflow_dir, inputs=(args.config,)
    )
    print_summary(results.summary)
    print(f"velocity table and DEM results: {args.out_file} ({results.summary.n_snapshots} snapshots)")
    return 0


def _rewrite(paths, derive, describe, note=None) -> None:
    """Each results file read whole (a corrupt or foreign one refused before anything is
    written), ``derive``d again and rewritten atomically, so a failure leaves it as it was.
    The file's lock is held from the read to the rename: a second command rewriting the
    same file waits and then reads this one's result, rather than overwriting it with a
    result derived from the file as it was. ``note(results)``, if given, may return a line
    printed before the derivation (why it will be slow)."""
    from coupling.cache import load_entry, save_entry
    from dem.post import DemResults

    for path in paths:
        # a missing file is named as such, not as a lock file that cannot be made beside it
        with locked(regular_file(path, "results file", CacheError), "results file"):
            entry = load_entry(path)
            try:
                results = DemResults.from_cache_entry(entry)
                line = note(results) if note is not None else None
                if line:
                    print(f"pbmdem: note: {path}: {line}", file=sys.stderr)
                results = derive(results)
            except ValueError as exc:
                raise ConfigError(f"{path}: {exc}") from None
            save_entry(path, results.to_cache_entry(entry.provenance))
        print(f"{path}: {describe(results.summary)}")


def _phase_fit_line(summary: DemSummary) -> str:
    fit = summary.record().get("phase_fit") or {}
    return (
        f"phase model K = {fit.get('n_phases')} on {fit.get('grid')} (observed on "
        f"{fit.get('observed_grid', fit.get('grid'))}), {fit.get('iterations')} EM iterations, "
        f"{fit.get('wall_time_s', float('nan')):.0f} s"
    )


def _steady_line(summary: DemSummary) -> str:
    steady = summary.steady
    if not steady:
        return "no steady quantities (no steady state, or too short a steady period for an interval)"
    holdup = steady["holdup"]
    return (
        f"steady hold-up {holdup['value']:.0f} [{holdup['low']:.0f}, {holdup['high']:.0f}] from batches of "
        f"{steady['batch_s']:g} s ({steady['degrees_of_freedom']:.1f} degrees of freedom)"
    )


def refit_command(args: argparse.Namespace) -> int:
    from dem.post import refit_phases, slow_refit_note

    _rewrite(args.results, refit_phases, _phase_fit_line, slow_refit_note)
    return 0


def recompute_steady_command(args: argparse.Namespace) -> int:
    from dem.post import recompute_steady

    _rewrite(args.results, recompute_steady, _steady_line)
    return 0


def slurm_command(args: argparse.Namespace) -> int:
    from workflows.config import resolve_config
    from workflows.pipeline.cluster import plan_cluster_run

    refuse_config_overwrite(args.out, args.config, (*RUN_DIRECTORY_FILES, "job.slurm"))
    config = resolve_config(args.preset, args.config)
    np_ranks = config.dem.run.np if args.np is None else args.np
    plan = plan_cluster_run(
        config,
        args.out,
        np_ranks,
        args.partition,
        holdup=args.holdup,
        throughput=args.throughput,
    )
    est = plan.estimate
    print(
        f"wrote {plan.run_dir}/in.blender and {plan.run_dir}/job.slurm; submit with: cd {plan.run_dir} && sbatch job.slurm"
    )
    print(f"or run with MPI: cd {plan.run_dir} && {' '.join(plan.mpi_command)}")
    print(
        f"hold-up {plan.holdup:.0f} particles ({plan.holdup_source}); throughput {plan.throughput:.3g} "
        f"particle-steps/s/core ({plan.throughput_source}); {est.steps} steps"
    )
    print(
        f"estimate on {np_ranks} cores at {est.parallel_efficiency:.0%} parallel efficiency: {est.wall_hours:.1f} h wall, "
        f"{est.core_hours:.0f} core-hours (the paper: 6.5 days on 8 workers = about 1250 core-hours)"
    )
    return 0


def print_summary(summary: DemSummary) -> None:
    record = summary.record()
    for key in SUMMARY_KEYS:
        value = record.get(key)
        if value is None:
            continue
        if isinstance(value, float):
            value = "nan" if math.isnan(value) else f"{value:.4g}"
        print(f"  {key:28s} {value}")
    for message in summary.warnings:
        print(f"pbmdem: warning: {message}", file=sys.stderr)
