"""``pbmdem study budget``: how much DEM a PBM needs -- the PBM built from the first T
seconds of a DEM run judged against the whole run, for several T (default: the shipped
reduced run). Writes ``dem_budget.json`` and ``dem_budget.png`` and prints a table."""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

from coupling.errors import ConfigError
from coupling.jsonable import write_json
from workflows.analysis.budget import DEFAULT_T, budget_study
from workflows.pipeline.results import load_results
from workflows.report.budget import plot_budget, print_table
from workflows.shipped import REDUCED_RUN

HELP = "the DEM budget: PBMs from the first T seconds of a DEM run against the whole run"
OUT = Path("results/dem_budget")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--reference", default=str(REDUCED_RUN), help="DEM results file (default: %(default)s)")
    parser.add_argument(
        "--t",
        type=float,
        nargs="+",
        default=list(DEFAULT_T),
        metavar="T",
        help="DEM budgets to study [s] (default: %(default)s)",
    )
    parser.add_argument("--out", default=str(OUT), help="output folder (default: %(default)s)")


def run(args: argparse.Namespace) -> int:
    # A budget of no DEM at all is a typing slip, not a budget that fails to reach steady
    # state: refuse it before the run is loaded.
    bad = [t for t in args.t if not (t > 0)]
    if bad:
        raise ConfigError(f"--t {bad[0]:g}: expected DEM budgets in seconds > 0, e.g. --t 60 90")
    started = time.perf_counter()
    results, config = load_results(args.reference)
    study = budget_study(results, config, args.t, log=lambda message: print(message, flush=True))
    study = dataclasses.replace(study, reference=str(args.reference), elapsed_s=time.perf_counter() - started)
    out = Path(args.out)
    write_json(out / "dem_budget.json", study.record())
    plot_budget(study, out / "dem_budget.png")
    print_table(study)
    print(f"wrote {out / 'dem_budget.json'} and {out / 'dem_budget.png'} in {study.elapsed_s:.0f} s")
    return 0
