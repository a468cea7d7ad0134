"""Does a deck change leave the physics alone? Its effect against the seed-to-seed scatter.

``python -m workflows.bench.scatter --change dem.geometry.inlet_margin_m=0.005 [--preset smoke]
[--seeds 3]`` runs the preset with ``--seeds`` different random seeds (the insertion and
size draws differ, the physics does not) and once with the change, each a real LIGGGHTS
run through :func:`workflows.pipeline.stages.dem_stage` (cached by input hash under
``results/bench/scatter-runs``, so a rerun costs nothing), and compares the velocity tables
and the DEM's quantities:

* per table field (vx_pos, vx_neg, vy_pos, vy_neg, particles per compartment): the RMS
  over the compartment-windows valid in both tables of the difference, relative to the
  RMS of the field (windows after the first 20 % of the run, when the blender has filled);
* hold-up at the end, discharged particles, C_A of the discharged.

The seed scatter of a metric is its largest difference over every pair of seed runs; the
change "stays within the seed scatter" when its difference from every seed run is at most
that. Prints a table and writes ``results/bench/scatter.json``.

A change that only moves where the ranks split the domain (``inlet_margin_m``) changes
the order of floating-point sums and nothing else, which is chaotic in a granular flow
exactly as a new seed is: the test is whether its difference is of the seeds' size.
"""

from __future__ import annotations

import argparse
import itertools
import math
import os
from pathlib import Path

import numpy as np

from coupling.errors import ConfigError
from coupling.jsonable import write_json
from coupling.tables import VelocityTable
from workflows.config import load_preset, override
from workflows.pipeline.stages import DemSide, dem_stage

OUT = Path("results/bench/scatter.json")
RUNS = Path("results/bench/scatter-runs")
FIELDS = ("vx_pos", "vx_neg", "vy_pos", "vy_neg", "particles")


def largest(values) -> float:
    """The largest of ``values``, NaN if any is NaN (Python's ``max`` ignores a NaN unless
    it comes first, so its answer would depend on the order of the runs)."""
    values = [float(v) for v in values]
    return float("nan") if any(math.isnan(v) for v in values) else max(values)


def next_prime(n: int) -> int:
    """The smallest prime >= n (LIGGGHTS' random seeds must be primes > 10000)."""
    n = max(int(n), 10007)
    while any(n % k == 0 for k in range(2, math.isqrt(n) + 1)):
        n += 1
    return n


def _field(table: VelocityTable, name: str) -> np.ndarray:
    return table.count_A + table.count_B if name == "particles" else getattr(table, name)


def table_difference(a: VelocityTable, b: VelocityTable) -> dict[str, float]:
    """Relative RMS difference per field over the compartment-windows valid in both,
    after the first 20 % of the windows."""
    k = min(a.n_windows, b.n_windows)
    start = int(0.2 * k)
    valid = a.valid[start:k] & b.valid[start:k]
    out = {}
    for name in FIELDS:
        fa, fb = _field(a, name)[start:k][valid], _field(b, name)[start:k][valid]
        scale = np.sqrt(np.mean(0.5 * (fa**2 + fb**2))) if fa.size else np.nan
        out[name] = float(np.sqrt(np.mean((fa - fb) ** 2)) / scale) if scale > 0 else float("nan")
    return out


def quantities(dem: DemSide) -> dict[str, float]:
    s = dem.results.summary
    ts = dem.results.timeseries
    out_a, out_b = ts["outflow_A_per_s"].sum(), ts["outflow_B_per_s"].sum()
    return {
        "holdup_final": float(s.holdup_final),
        "discharged": float(s.accounting["discharged"]),
        "C_A_discharged": float(out_a / (out_a + out_b)) if out_a + out_b > 0 else float("nan"),
    }


def difference(a: DemSide, b: DemSide) -> dict[str, float]:
    out = table_difference(a.table, b.table)
    qa, qb = quantities(a), quantities(b)
    out.update({k: abs(qb[k] - qa[k]) / abs(qa[k]) if qa[k] else float("nan") for k in qa})
    return out


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The command line's options of this benchmark."""
    parser.add_argument("--preset", default="smoke")
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="PATH=VALUE",
        help="change one value of the preset for every run, seeds and change alike, e.g. "
        "dem.operation.duration_s=3 (with dem.tables.window_s=1 and steady_state.window_s=1) for a short "
        "check (repeatable)",
    )
    parser.add_argument(
        "--change",
        default="dem.geometry.inlet_margin_m=0.005",
        help="config path=value of the change to judge (default: the inlet margin of the "
        "configs before the 2-rank cut was moved)",
    )
    parser.add_argument("--seeds", type=int, default=3, help="seed runs for the scatter (>= 2)")
    parser.add_argument("--runs-dir", default=str(RUNS))
    parser.add_argument("--out-file", default=str(OUT))


def run(args: argparse.Namespace) -> int:
    if args.seeds < 2:
        raise ConfigError(f"--seeds {args.seeds}: the scatter needs at least 2 seed runs")
    base = load_preset(args.preset)
    if args.set:
        base = override(base, *args.set)
    changed = override(base, args.change)
    seed0 = base.dem.numerics.seed
    runs: dict[str, DemSide] = {}
    load = [os.getloadavg()[0]]
    for n in range(args.seeds):
        seed = seed0 if n == 0 else next_prime(seed0 + 1000 * n)
        print(f"  seed {seed} ...", flush=True)
        runs[f"seed {seed}"] = dem_stage(override(base, f"dem.numerics.seed={seed}"), args.runs_dir, progress=False)
    print(f"  change {args.change} ...", flush=True)
    runs["change"] = dem_stage(changed, args.runs_dir, progress=False)
    load.append(os.getloadavg()[0])
    seeds = [name for name in runs if name != "change"]
    pairs = {f"{a} vs {b}": difference(runs[a], runs[b]) for a, b in itertools.combinations(seeds, 2)}
    against = {f"change vs {a}": difference(runs[a], runs["change"]) for a in seeds}
    metrics = list(next(iter(pairs.values())))
    scatter = {m: largest(p[m] for p in pairs.values()) for m in metrics}
    effect = {m: largest(p[m] for p in against.values()) for m in metrics}
    # a metric undefined in some run (C_A of a run that discharged nothing) has no verdict
    within = {m: None if math.isnan(effect[m] + scatter[m]) else bool(effect[m] <= scatter[m]) for m in metrics}
    record = {
        "preset": args.preset,
        "set": args.set,
        "change": args.change,
        "seeds": seeds,
        "seed_pairs": pairs,
        "change_vs_seeds": against,
        "seed_scatter": scatter,
        "change_effect": effect,
        "within_scatter": within,
        "all_within": all(v is not False for v in within.values()),
        "load_average": load,
        "runs": {name: str(dem.cache_file) for name, dem in runs.items()},
    }
    print(f"\n{'metric':<16} {'seed scatter':>13} {'change':>10}  verdict")
    for m in metrics:
        verdict = "undefined" if within[m] is None else "within" if within[m] else "OUTSIDE"
        print(f"{m:<16} {scatter[m]:>13.3g} {effect[m]:>10.3g}  {verdict}")
    out = write_json(args.out_file, record)
    print(f"wrote {out}")
    return 0
