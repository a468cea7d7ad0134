"""``pbmdem validate``: the validation campaign's report."""

from __future__ import annotations

import argparse

from workflows.pipeline.stages import stderr_log

HELP = "the validation campaign: DEM runs with one factor changed, predicted by PBMs built without them"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", default="results/validation", help="where report.html goes")
    parser.add_argument("--runs-dir", default="runs/validation", help="the campaign's DEM runs and their cache")
    parser.add_argument("--np", type=int, default=None, help="MPI ranks per run (default: the preset's)")
    parser.add_argument("--fresh", action="store_true", help="ignore cached and shipped results: rerun every DEM run")
    parser.add_argument(
        "--no-solver",
        action="store_true",
        help="never start LIGGGHTS: the runs neither shipped nor cached are left out of the report",
    )


def run(args: argparse.Namespace) -> int:
    from workflows.products.validate import validation_report

    page = validation_report(
        args.out, args.runs_dir, fresh=args.fresh, nprocs=args.np, log=stderr_log, solver=not args.no_solver
    )
    print(f"report: {page}")
    return 0
