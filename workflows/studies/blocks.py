"""``pbmdem study blocks``: are the DEM's 5-s bootstrap blocks longer than its correlations?

Every steady DEM interval is a block bootstrap over blocks of one table window (5 s): it
holds if the blocks are longer than the time over which the quantity stays correlated.
The batch-means standard error of the steady mean hold-up, taken over blocks of growing
length, tells: it grows with the block length until the blocks outlast the correlation,
then levels off. Where it still grows beyond 5 s, the 5-s intervals are too narrow by that
ratio. Prints, per results file, the steady period, the interval half-width the results
carry and the batch-means standard error at each block length; writes ``blocks.json``.
"""

from __future__ import annotations

import argparse
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from coupling.errors import ConfigError
from coupling.intervals import batch_means_error
from coupling.jsonable import write_json
from workflows.pipeline.stages import load_results
from workflows.shipped import REDUCED_RUN

HELP = "the DEM's bootstrap block length against its hold-up's correlation (batch means by block length)"
OUT = Path("results/blocks")
BLOCKS_S = (1.0, 2.5, 5.0, 10.0, 20.0, 40.0)


@dataclass(frozen=True)
class BlockRow:
    """One results file: ``standard_error[i]`` of the steady mean hold-up by batch means
    over blocks of ``blocks_s[i]`` (NaN with fewer than four batches), and
    the half-width of the results' 95 % interval over 1.96 (the bootstrap's own error)."""

    results: str
    steady_s: float
    holdup: float
    interval_error: float
    little_mean_residence_time_s: float
    blocks_s: tuple[float, ...]
    standard_error: tuple[float, ...]


def block_row(path: str | Path) -> BlockRow:
    results, _config = load_results(path)
    summary = results.summary
    holdup = summary.steady.get("holdup")
    if summary.steady_time is None or not holdup:
        raise ConfigError(f"{path}: the DEM run reached no steady state")
    t = results.holdup["t_s"].to_numpy()
    after = t > summary.steady_time
    values = (results.holdup["holdup_A"] + results.holdup["holdup_B"]).to_numpy()[after]
    dt = float(np.median(np.diff(t)))
    errors = tuple(batch_means_error(values, max(1, round(b / dt))) for b in BLOCKS_S)
    return BlockRow(
        str(path),
        float(t[after][-1] - t[after][0]),
        float(values.mean()),
        float((holdup["high"] - holdup["low"]) / 2 / 1.96),
        float(summary.steady["little_mean_residence_time_s"]["value"]),
        BLOCKS_S,
        errors,
    )


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--results", nargs="+", default=[str(REDUCED_RUN)], help="DEM results files (default: %(default)s)"
    )
    parser.add_argument("--out", default=str(OUT), help="output folder (default: %(default)s)")


def run(args: argparse.Namespace) -> int:
    rows = [block_row(path) for path in args.results]
    head = " | ".join(f"{b:g} s" for b in BLOCKS_S)
    print(f"| results | steady [s] | MRT [s] | hold-up | interval's error | batch means: {head} |")
    print("| --- " * (5 + len(BLOCKS_S)) + "|")
    for r in rows:
        errors = " | ".join("-" if np.isnan(e) else f"{e:.2f}" for e in r.standard_error)
        print(
            f"| {Path(r.results).name} | {r.steady_s:.0f} | {r.little_mean_residence_time_s:.1f} | {r.holdup:.0f} | "
            f"{r.interval_error:.2f} | {errors} |"
        )
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    print(f"wrote {write_json(out / 'blocks.json', {'rows': [asdict(r) for r in rows]})}")
    return 0
