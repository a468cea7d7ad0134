"""``pbmdem validate``: the validation campaign's report."""

from __future__ import annotations

import argparse

from coupling.errors import ConfigError
from workflows.pipeline.log import stderr_log

HELP = "the validation campaign: DEM runs with one factor changed, predicted by PBMs built without them"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", default="results/validation", help="where report.html goes")
    parser.add_argument("--runs-dir", default="runs/validation", help="the campaign's DEM runs and their cache")
    parser.add_argument("--np", type=int, default=None, help="MPI ranks per run (default: the preset's)")
    parser.add_argument("--fresh", action="store_true", help="ignore cached and shipped results: rerun every DEM run")
    parser.add_argument(
        "--scheduler",
        choices=("local", "slurm"),
        default="local",
        help="local: missing runs one after the other on this machine; slurm: the missing runs one Slurm job "
        "array of --np tasks each (as `library build`, manifest in RUNS_DIR/slurm), followed through sacct until "
        "done, a failed run resubmitted to resume from its restart files, then the report",
    )
    parser.add_argument("--partition", default=None, help="Slurm partition (--scheduler slurm)")
    parser.add_argument(
        "--no-solver",
        action="store_true",
        help="never start LIGGGHTS: the runs neither shipped nor cached are left out of the report",
    )


def run(args: argparse.Namespace) -> int:
    from workflows.products.validate import validation_report

    if args.scheduler == "slurm":
        if args.no_solver or args.fresh:
            raise ConfigError("--scheduler slurm runs the missing runs: it goes with neither --no-solver nor --fresh")
        from workflows.pipeline.slurm import run_campaign_on_slurm
        from workflows.products.validate import campaign_configs, step_config

        states = run_campaign_on_slurm(
            {**campaign_configs(), "step": step_config()}, args.runs_dir, args.np, stderr_log, partition=args.partition
        )
        for name, state in states.items():
            if state.state == "failed":
                stderr_log(f"{name}: {state.reason}")
    page = validation_report(
        args.out,
        args.runs_dir,
        fresh=args.fresh,
        nprocs=args.np,
        log=stderr_log,
        solver=not args.no_solver and args.scheduler == "local",
    )
    print(f"report: {page}")
    return 0
