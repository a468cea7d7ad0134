"""``pbmdem study vrr``: feeder-noise filtering of both PBM rate modes against the DEM's,
with the DEM's interval, on one DEM results file (default: the shipped reduced run).
Writes ``vrr.json`` and ``vrr.png`` and prints a short table."""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

from coupling.errors import ConfigError
from coupling.jsonable import write_json
from workflows.analysis.vrr import vrr_comparison
from workflows.pipeline.results import load_results, pbm_config_for
from workflows.report.vrr import plot_vrr, print_table
from workflows.shipped import REDUCED_RUN

HELP = "feeder-noise filtering (VRR) of the PBM rate modes against a DEM run's, with its interval"
OUT = Path("results/vrr")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--reference", default=str(REDUCED_RUN), help="DEM results file (default: %(default)s)")
    parser.add_argument("--out", default=str(OUT), help="output folder (default: %(default)s)")


def run(args: argparse.Namespace) -> int:
    started = time.perf_counter()
    results, config = load_results(args.reference)
    steady = results.summary.steady_state_time_s
    if steady is None or not math.isfinite(steady):
        raise ConfigError(
            f"{args.reference}: the DEM run reached no steady state (steady_state_time_s = "
            f"{steady!r}); there is no stationary blender to compare"
        )
    pbm_config = pbm_config_for(config, results.table, rtd_pulse_s=None)
    comparison = vrr_comparison(results.table, pbm_config, float(steady), results.summary, results.particles)
    elapsed_s = time.perf_counter() - started
    out = Path(args.out)
    # the study's own provenance beside the comparison's record, at the file edge
    write_json(out / "vrr.json", {**comparison.record(), "reference": str(args.reference), "elapsed_s": elapsed_s})
    plot_vrr(comparison, out / "vrr.png")
    print_table(comparison)
    print(f"wrote {out / 'vrr.json'} and {out / 'vrr.png'} in {elapsed_s:.0f} s")
    return 0
