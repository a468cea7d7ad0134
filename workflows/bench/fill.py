"""What the fill law costs: ``pbmdem bench fill``.

One PBM run (:func:`pbm.simulate.simulate`) per case, each at its DEM run's own feed: with
the table's rates, and under the fill law with the bulk integrated by LSODA (the default,
:data:`pbm.fill.BULK_METHOD`) and by BDF, with the largest hold-up difference between the
two. Cases: the validation baseline (10 x 10, steady feed) and the reduced reference
binned at 20 x 10 with 5 % feeder noise redrawn every second (the bulk restarts at every
feed change), in the measured and phase modes (``--cases`` and ``--modes`` choose among
them). The phase model's fill law under noise is the one that takes minutes: the shipped
20-slice twin carries 18 phases, 3600 bulk populations, where the 4.1 s of
workflows/reference/validation/VALIDATION.md is for 3 phases (600); 470 s on this 2-core
machine at load 5-8.
Medians of ``--repeats``; prints a table and writes ``results/bench/fill-cost.json``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

import pbm.fill as fill_module
from coupling.errors import ConfigError
from coupling.jsonable import json_ready, write_json
from pbm.simulate import simulate
from workflows.pipeline.results import load_results, pbm_config_for
from workflows.shipped import REFERENCE_DIR, VALIDATION_DIR

#: name -> (label, results file, feeder noise)
CASES = {
    "baseline": ("validation baseline, 10 x 10", VALIDATION_DIR / "dem-aa093a229dfd2ce4.h5", 0.0),
    "reduced-noise": ("reduced, 20 x 10, 1-s noise 5 %", REFERENCE_DIR / "dem-ac547c3f930c80c8.h5", 0.05),
}
MODES = ("measured", "phases")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--repeats", type=int, default=3, help="runs per timing (median)")
    parser.add_argument(
        "--cases", default=",".join(CASES), help=f"comma-separated, of {', '.join(CASES)} (default all)"
    )
    parser.add_argument(
        "--modes", default=",".join(MODES), help=f"rate modes, comma-separated, of {', '.join(MODES)} (default all)"
    )
    parser.add_argument("--out-file", default="results/bench/fill-cost.json")


def _chosen(option: str, text: str, known) -> list[str]:
    """The comma-separated names of ``text`` in the order given; ConfigError naming the
    unknown ones and the valid choices."""
    names = [name.strip() for name in text.split(",") if name.strip()]
    unknown = [name for name in names if name not in known]
    if unknown or not names:
        raise ConfigError(f"{option} {text!r}: unknown {unknown or 'empty'}; choose from {', '.join(known)}")
    return names


def _timed(table, config, repeats: int):
    times, result = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        result = simulate(table, config)
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), result


def run(args: argparse.Namespace) -> int:
    cases = _chosen("--cases", args.cases, CASES)
    modes = _chosen("--modes", args.modes, MODES)
    if args.repeats < 1:
        raise ConfigError(f"--repeats {args.repeats}: expected a whole number >= 1")
    rows = []
    default = fill_module.BULK_METHOD
    for label, path, noise in (CASES[name] for name in cases):
        results, config = load_results(path)
        table = results.table
        base = pbm_config_for(config, table, None).model_copy(update={"noise_sigma": noise})
        for mode in modes:
            table_cfg = base.model_copy(update={"rates": mode})
            fill_cfg = table_cfg.model_copy(update={"rate_law": "fill"})
            simulate(table, table_cfg)  # warm-up (compiled kernels, caches)
            row = {"case": label, "mode": mode, "table_s": _timed(table, table_cfg, args.repeats)[0]}
            held = {}
            try:
                for method in ("LSODA", "BDF"):
                    fill_module.BULK_METHOD = method
                    row[f"fill_{method}_s"], res = _timed(table, fill_cfg, args.repeats)
                    held[method] = res.holdup_A + res.holdup_B
            finally:
                fill_module.BULK_METHOD = default
            row["max_holdup_difference"] = float(np.abs(held["LSODA"] - held["BDF"]).max())
            rows.append(row)
            print(
                f"{label:34s} {mode:9s} table {row['table_s']:6.2f} s  fill: LSODA {row['fill_LSODA_s']:6.2f} s"
                f"  BDF {row['fill_BDF_s']:6.2f} s  (hold-ups within {row['max_holdup_difference']:.2g})",
                flush=True,
            )
    out = write_json(args.out_file, json_ready({"repeats": args.repeats, "rows": rows}))
    print(f"wrote {out}")
    return 0
