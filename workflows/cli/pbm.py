"""``pbmdem pbm ...``: run the PBM on a velocity table, or make a synthetic table to try it.

pbmdem pbm run --tables TABLES.h5 [--config FILE.toml | --preset NAME]
               [--rtd-pulse SECONDS] [--method expm|bdf] [--rates velocity|measured|phases|all] --out DIR
pbmdem pbm synth --out-file TABLES.h5 [--nx 10 --ny 10 --windows 52 --window-s 5 --seed 2013]
"""

from __future__ import annotations

import argparse
import json
import sys

from coupling.errors import ConfigError
from coupling.files import refuse_output_over_inputs

HELP = "PBM stage: simulate CQAs from DEM velocity tables"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from workflows.config import add_config_arguments

    pbm_sub = parser.add_subparsers(dest="pbm_command", required=True, metavar="PBM_COMMAND")

    run = pbm_sub.add_parser("run", help="simulate the blender from a velocity table and write the CQAs")
    run.add_argument("--tables", required=True, help="velocity table (HDF5, see coupling/tables.py)")
    add_config_arguments(run, required=False)
    run.add_argument(
        "--rtd-pulse",
        type=float,
        default=None,
        metavar="SECONDS",
        help="tracer pulse time [s] (default: config, else the detected steady state)",
    )
    run.add_argument(
        "--method",
        choices=("expm", "bdf"),
        default=None,
        help="exact propagation (default) or the solve_ivp BDF cross-check",
    )
    run.add_argument(
        "--rates",
        choices=("velocity", "measured", "phases", "all"),
        default=None,
        help="transfer rates: the paper's v/dx rule, the rates measured from DEM particle moves (schema-2 "
        "tables), the hidden-phase model fitted to the particles' sequences (schema 3), or all the table "
        "supports, each into OUT/<mode> (default: the config's pbm.rates)",
    )
    run.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    run.add_argument("--out", required=True, help="output directory")
    run.set_defaults(func=run_command)

    synth = pbm_sub.add_parser("synth", help="write a seeded synthetic velocity table of DEM-like magnitudes")
    synth.add_argument("--out-file", required=True, metavar="TABLES.h5", help="the HDF5 file to write")
    synth.add_argument("--nx", type=int, default=10)
    synth.add_argument("--ny", type=int, default=10)
    synth.add_argument("--windows", type=int, default=52)
    synth.add_argument("--window-s", type=float, default=5.0)
    synth.add_argument("--seed", type=int, default=2013)
    synth.set_defaults(func=synth_command)


def run_command(args: argparse.Namespace) -> int:
    from workflows.config import Config, resolve_config
    from workflows.pipeline.stages import run_pbm

    config = Config() if args.preset is None and args.config is None else resolve_config(args.preset, args.config)
    refuse_output_over_inputs(args.out, [args.config], "--out", ConfigError)
    runs = run_pbm(
        args.tables,
        config,
        args.out,
        rtd_pulse_s=args.rtd_pulse,
        method=args.method,
        figures=not args.no_figures,
        rates=args.rates,
    )
    for mode, (result, paths) in runs.items():
        for override in result.feed_overrides:
            print(f"warning: {override.message}", file=sys.stderr)
        s = result.summary
        print(
            f"PBM ({mode} rates) {s.nx}x{s.ny}, {s.duration_s:g} s ({s.method}) in "
            f"{s.wall_time_s * 1e3:.1f} ms: steady outflow {s.steady_outflow_per_s:.1f}/s, "
            f"C_A {s.steady_C_A:.4f}, mean residence {s.mean_residence_time_s:.2f} s "
            f"(recovered {s.rtd_recovered_fraction:.3f}), final outlet RSD {s.final_rsd_outlet:.3g}"
        )
        print(json.dumps({k: str(v) for k, v in paths.items()}, indent=2))
    return 0


def synth_command(args: argparse.Namespace) -> int:
    from coupling.tables import write_table
    from pbm.synthetic import synthetic_table

    table = synthetic_table(nx=args.nx, ny=args.ny, n_windows=args.windows, window_s=args.window_s, seed=args.seed)
    path = write_table(args.out_file, table)
    print(f"wrote {path}: {table.n_windows} windows x {table.nx}x{table.ny} compartments")
    return 0
