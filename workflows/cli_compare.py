"""``pbmdem compare``: the full DEM -> tables -> PBM -> report pipeline (``make full-comparison``)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from workflows.cli_dem import add_config_arguments


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser(
        "compare",
        help="DEM (or its cached / shipped results) -> velocity tables -> PBM -> side-by-side report",
    )
    add_config_arguments(parser)
    parser.add_argument("--np", type=int, default=None, help="MPI ranks for LIGGGHTS (default: the config's)")
    parser.add_argument("--fresh", action="store_true", help="ignore cached and shipped DEM results: run LIGGGHTS again")
    parser.add_argument("--resume", action="store_true", help="resume an interrupted DEM run from its restart file")
    parser.add_argument("--results-dir", default="results", help="where <preset>-<hash>/report.html goes")
    parser.add_argument("--runs-dir", default="runs", help="root of the DEM run directories and cache")
    parser.add_argument("--noise-members", type=int, default=200, help="realisations per noise level")
    parser.add_argument("--no-paraview", action="store_true", help="skip the ParaView (VTK) files")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from coupling.errors import ConfigError
    from workflows.compare import full_comparison
    from workflows.config import resolve_config

    if args.noise_members < 1:
        raise ConfigError(f"--noise-members must be >= 1, got {args.noise_members}")
    config = resolve_config(args.preset, args.config)

    def log(message: str) -> None:
        print(f"pbmdem: {message}", file=sys.stderr, flush=True)

    report = full_comparison(
        config,
        results_root=Path(args.results_dir),
        runs_root=Path(args.runs_dir),
        np_ranks=args.np,
        fresh=args.fresh,
        resume=args.resume,
        noise_members=args.noise_members,
        paraview=not args.no_paraview,
        progress=not args.no_progress,
        log=log,
    )
    print(f"report: {report}")
    return 0
