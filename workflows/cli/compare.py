"""``pbmdem compare``: DEM (or its cached or shipped results) -> velocity tables -> PBM ->
the side-by-side report."""

from __future__ import annotations

import argparse
from pathlib import Path

from workflows.pipeline.log import stderr_log

HELP = "DEM (or its cached / shipped results) -> velocity tables -> PBM -> side-by-side report"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from workflows.config import add_config_arguments

    add_config_arguments(parser)
    parser.add_argument("--np", type=int, default=None, help="MPI ranks for LIGGGHTS (default: the config's)")
    parser.add_argument(
        "--fresh", action="store_true", help="ignore cached and shipped DEM results: run LIGGGHTS again"
    )
    parser.add_argument("--resume", action="store_true", help="resume an interrupted DEM run from its restart file")
    parser.add_argument(
        "--out",
        default=None,
        metavar="DIR",
        help="where report.html and its files go (default: results/<preset>-<input hash>)",
    )
    # the flag's earlier name, kept so that scripts written against it still run; unlisted,
    # since --out is the one spelling every command shares
    parser.add_argument("--results-dir", dest="out", default=argparse.SUPPRESS, help=argparse.SUPPRESS)
    parser.add_argument("--runs-dir", default="runs", help="root of the DEM run directories and cache")
    parser.add_argument("--noise-members", type=int, default=200, help="realisations per noise level")
    parser.add_argument("--no-paraview", action="store_true", help="skip the ParaView (VTK) files")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from pbm.resources import check_ensemble_memory
    from workflows.config import resolve_config
    from workflows.products.compare import full_comparison

    config = resolve_config(args.preset, args.config)
    # the studies' ensembles: refused now, not after the DEM and the PBM
    check_ensemble_memory(
        args.noise_members,
        config.dem.operation.duration_s,
        config.pbm.noise_interval_s,
        config.pbm.output_interval_s,
        config.dem.tables.nx,
    )
    report = full_comparison(
        config,
        out_dir=None if args.out is None else Path(args.out),
        runs_root=Path(args.runs_dir),
        np_ranks=args.np,
        fresh=args.fresh,
        resume=args.resume,
        noise_members=args.noise_members,
        paraview=not args.no_paraview,
        progress=not args.no_progress,
        log=stderr_log,
    )
    print(f"report: {report}")
    return 0
