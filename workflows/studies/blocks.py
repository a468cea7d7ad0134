"""``pbmdem study blocks``: how long do the DEM's quantities stay correlated, and do its
intervals cover?

Every DEM interval rests on blocks of the steady period being (nearly) independent. The
batch-means standard error of a mean, taken over blocks of growing length, tells whether
they are: it grows with the block length until the blocks outlast the correlation, then
levels off. Printed per results file, for

* the steady mean hold-up (by dump): it keeps growing well past 5 s on the slow runs,
  which is why the steady quantities' intervals use batches of residence times
  (:data:`dem.steady.BATCH_RESIDENCE_TIMES`, :func:`coupling.intervals.batch_means_interval`);
* the pooled RTD's mean and variance (by 5-s blocks of entry time): they do not grow,
  which is why the pooled RTD keeps its block bootstrap over 5-s blocks;

beside the half-widths / 1.96 of the intervals the results carry.

``--coverage N`` adds the check the choice rests on: N synthetic steady periods with a
known mean (a hold-up that is a fast and a slow Ornstein-Uhlenbeck process, the slow one
relaxing in a given fraction of the residence time), each run through
:func:`dem.steady.steady_quantities` (this version's interval) and through a bootstrap
over 5-s blocks (the earlier one); the share of intervals that hold the true mean is the
coverage, 95 % nominal. It also checks the pooled RTD's intervals on N synthetic pooled
RTDs of 3 to 25 entry blocks (:func:`rtd_coverage_row`): the bootstrap's plain percentile
ends against the expanded ones the results carry. Writes ``blocks.json``.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.signal import lfilter

from coupling.errors import ConfigError
from coupling.intervals import (
    LEVEL,
    N_BOOT,
    batch_means_error,
    block_draw_counts,
    expanded_interval,
    percentile_interval,
)
from coupling.jsonable import write_json
from dem.post import DemResults
from dem.steady import steady_quantities
from workflows.pipeline.results import load_results
from workflows.shipped import REDUCED_RUN
from workflows.studies import distinct_runs

HELP = "how long the DEM's quantities stay correlated (batch means by block length), and the intervals' coverage"
OUT = Path("results/blocks")
BLOCKS_S = (1.0, 2.5, 5.0, 10.0, 20.0, 40.0)


@dataclass(frozen=True)
class BlockRow:
    """One results file: the batch-means standard errors by block length ``blocks_s`` (NaN
    with fewer than four batches) of the steady mean hold-up and of the pooled RTD's mean
    and variance, beside the half-widths / 1.96 of the intervals the results carry."""

    results: str
    steady_s: float
    little_mean_residence_time_s: float
    blocks_s: tuple[float, ...]
    holdup: float
    holdup_interval_error: float
    holdup_error: tuple[float, ...]
    rtd_entry_window_s: float
    rtd_mean_interval_error: float
    rtd_mean_error: tuple[float, ...]
    rtd_variance_interval_error: float
    rtd_variance_error: tuple[float, ...]


@dataclass(frozen=True)
class CoverageRow:
    """Coverage of the true steady hold-up by the results' interval (``batch_means``) and
    by a percentile bootstrap over 5-s blocks (``bootstrap_5s``), over ``series``
    synthetic steady periods of ``steady_s`` with a residence time ``residence_time_s``
    and a slow component relaxing in ``slow_s``."""

    residence_time_s: float
    steady_s: float
    slow_s: float
    series: int
    batch_means: float
    bootstrap_5s: float


@dataclass(frozen=True)
class RtdCoverageRow:
    """Coverage of a synthetic pooled RTD's true mean and variance over ``series`` samples
    of ``n_blocks`` entry blocks: by the bootstrap's plain percentile ends and by the
    expanded ones the results carry (:func:`coupling.intervals.expanded_interval`)."""

    n_blocks: int
    series: int
    mean_plain: float
    mean_expanded: float
    variance_plain: float
    variance_expanded: float


def _half(low, high) -> float:
    return float((high - low) / 2 / 1.96)


def _rtd_errors(results: DemResults) -> tuple[float, tuple[float, ...], tuple[float, ...]]:
    """The pooled RTD's entry window [s] and the batch-means errors of its mean and
    variance by entry blocks of each length (ratio estimators, linearised)."""
    pooled = results.summary.pooled_rtd
    if pooled is None or not pooled.has_tracers:
        nan = (math.nan,) * len(BLOCKS_S)
        return math.nan, nan, nan
    start, end = pooled.entry_window_s
    entry = results.particles["entry_t_s"].to_numpy(float)
    tau = results.particles["exit_t_s"].to_numpy(float) - entry
    chosen = (entry > start) & (entry <= end) & (tau <= pooled.horizon_s)
    entry, tau = entry[chosen], tau[chosen]
    mean, var = tau.mean(), tau.var()
    means, variances = [], []
    for b in BLOCKS_S:
        block = np.floor((entry - start) / b).astype(np.int64)
        n = int(block.max()) + 1
        if n < 4:
            means.append(math.nan)
            variances.append(math.nan)
            continue
        scale = math.sqrt(n / (n - 1)) / tau.size
        means.append(scale * math.sqrt((np.bincount(block, tau - mean, n) ** 2).sum()))
        variances.append(scale * math.sqrt((np.bincount(block, (tau - mean) ** 2 - var, n) ** 2).sum()))
    return end - start, tuple(means), tuple(variances)


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
    window, rtd_mean, rtd_var = _rtd_errors(results)
    pooled = summary.pooled_rtd
    return BlockRow(
        str(path),
        float(t[after][-1] - t[after][0]),
        float(summary.steady["little_mean_residence_time_s"]["value"]),
        BLOCKS_S,
        float(values.mean()),
        _half(holdup["low"], holdup["high"]),
        tuple(batch_means_error(values, max(1, round(b / dt))) for b in BLOCKS_S),
        window,
        _half(mean.low, mean.high) if (mean := pooled and pooled.mean_residence_time_s) else math.nan,
        rtd_mean,
        _half(var.low, var.high) if (var := pooled and pooled.rtd_variance_s2) else math.nan,
        rtd_var,
    )


def _ornstein_uhlenbeck(rng: np.random.Generator, n: int, dt: float, tau: float) -> np.ndarray:
    """A unit-variance OU process sampled every ``dt``, started in its stationary state."""
    a = math.exp(-dt / tau)
    noise = rng.standard_normal(n) * math.sqrt(1 - a * a)
    noise[0] = rng.standard_normal()
    return lfilter([1.0], [1.0, -a], noise)


def coverage_row(
    residence_time_s: float, steady_s: float, slow_s: float, series: int, seed: int = 0, block_s: float = 5.0
) -> CoverageRow:
    """:class:`CoverageRow` of a hold-up of 2000 ± 25 particles (half its variance a 2-s
    OU process, half one of ``slow_s``) on dumps every 0.1 s, and a steady outflow of
    2000 / ``residence_time_s`` per s on 1-s intervals, so Little's law gives the residence
    time; one compartment holds all of it."""
    rng = np.random.default_rng(seed)
    dt, mean, spread = 0.1, 2000.0, 25.0
    t = dt * np.arange(1, round(steady_s / dt) + 1)
    t_int = np.arange(1.0, steady_s + 0.5)
    outflow = np.full(t_int.size, mean / residence_time_s)
    timeseries = pd.DataFrame({"t_s": t_int, "outflow_per_s": outflow, "outflow_A_per_s": outflow / 2})
    timeseries["outflow_B_per_s"] = outflow / 2
    per_block = np.floor((t - 1e-9) / block_s).astype(np.int64)
    n_blocks = int(per_block.max()) + 1
    draws = block_draw_counts(n_blocks, N_BOOT, seed)
    held = {"batch_means": 0, "bootstrap_5s": 0}
    for _ in range(series):
        x = (_ornstein_uhlenbeck(rng, t.size, dt, 2.0) + _ornstein_uhlenbeck(rng, t.size, dt, slow_s)) / math.sqrt(2)
        holdup = np.round(mean + spread * x)
        counts = np.zeros((t.size, 2, 1, 1))
        counts[:, 0, 0, 0] = holdup
        hold = steady_quantities(t, counts, timeseries, 0.0, block_s)["holdup"]
        held["batch_means"] += hold["low"] <= mean <= hold["high"]
        sums = np.bincount(per_block, holdup, n_blocks)
        sizes = np.bincount(per_block, None, n_blocks)
        boot = percentile_interval(holdup.mean(), draws @ sums / (draws @ sizes), LEVEL)
        held["bootstrap_5s"] += boot.low <= mean <= boot.high
    return CoverageRow(
        residence_time_s, steady_s, slow_s, series, held["batch_means"] / series, held["bootstrap_5s"] / series
    )


def rtd_coverage_row(n_blocks: int, series: int, seed: int = 0, per_block: int = 150) -> RtdCoverageRow:
    """:class:`RtdCoverageRow` of pooled RTDs whose ``n_blocks`` entry blocks hold
    ``per_block`` residence times each: gamma-distributed (shape 2.5, scale 8 s: mean 20 s,
    variance 160 s²), every block shifted by a drift of standard deviation 1.5 s (a slow
    fluctuation its particles share), so the truth is 20 s and 160 + 1.5² s²."""
    rng = np.random.default_rng(seed)
    true_mean, true_variance = 20.0, 160.0 + 1.5**2
    draws = block_draw_counts(n_blocks, N_BOOT, seed)
    ones = np.ones((1, n_blocks))
    held = np.zeros((2, 2))  # (plain, expanded) x (mean, variance)
    for _ in range(series):
        tau = rng.gamma(2.5, 8.0, (n_blocks, per_block)) + rng.normal(0.0, 1.5, (n_blocks, 1))
        sums, squares, sizes = tau.sum(axis=1), (tau**2).sum(axis=1), np.full(n_blocks, float(per_block))

        def moments(w, sums=sums, squares=squares, sizes=sizes):
            mean = (w @ sums) / (w @ sizes)
            return np.column_stack([mean, (w @ squares) / (w @ sizes) - mean**2])

        plain = percentile_interval(moments(ones)[0], moments(draws), LEVEL)
        for row, ends in enumerate((plain, expanded_interval(plain, n_blocks, LEVEL))):
            held[row] += (ends.low <= (true_mean, true_variance)) & ((true_mean, true_variance) <= ends.high)
    (mean_plain, variance_plain), (mean_expanded, variance_expanded) = (held / series).tolist()
    return RtdCoverageRow(n_blocks, series, mean_plain, mean_expanded, variance_plain, variance_expanded)


#: entry blocks the pooled RTD's coverage is checked at: half a steady period holds 3-13 of
#: the shipped runs' 5-s blocks, a whole one 5-26
RTD_COVERAGE_BLOCKS = (3, 6, 12, 25)

#: (residence time, steady period, slow relaxation) [s]: the campaign's runs hold 6-8
#: residence times of steady period, and their hold-up's slow part relaxes in about a
#: third to a half of a residence time (its integrated autocorrelation time).
COVERAGE_CASES = ((20.0, 165.0, 7.0), (27.0, 160.0, 10.0), (37.0, 277.0, 12.0), (18.0, 215.0, 4.0), (20.0, 165.0, 20.0))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--results", nargs="+", default=[str(REDUCED_RUN)], help="DEM results files (default: %(default)s)"
    )
    parser.add_argument(
        "--coverage",
        type=int,
        default=0,
        metavar="N",
        help="also check the hold-up and pooled-RTD intervals' coverage on N synthetic samples per case (e.g. 400; default: none)",
    )
    parser.add_argument("--out", default=str(OUT), help="output folder (default: %(default)s)")


def _cells(values) -> str:
    return " | ".join("-" if math.isnan(v) else f"{v:.3g}" for v in values)


def run(args: argparse.Namespace) -> int:
    if args.coverage < 0:
        raise ConfigError(f"--coverage must be a number of series >= 0, got {args.coverage}")
    rows = [block_row(path) for path in distinct_runs(args.results)]
    head = " | ".join(f"{b:g} s" for b in BLOCKS_S)
    for title, pick in (
        ("steady hold-up", lambda r: (r.holdup_interval_error, r.holdup_error)),
        ("pooled RTD mean [s]", lambda r: (r.rtd_mean_interval_error, r.rtd_mean_error)),
        ("pooled RTD variance [s^2]", lambda r: (r.rtd_variance_interval_error, r.rtd_variance_error)),
    ):
        print(f"\n{title}: batch-means standard error by block length")
        print(f"| results | steady [s] | RTD entry window [s] | MRT [s] | interval's error | {head} |")
        print("| --- " * (5 + len(BLOCKS_S)) + "|")
        for r in rows:
            interval, errors = pick(r)
            print(
                f"| {Path(r.results).name} | {r.steady_s:.0f} | {r.rtd_entry_window_s:.0f} | "
                f"{r.little_mean_residence_time_s:.1f} | {interval:.3g} | {_cells(errors)} |"
            )
    coverage = (
        [coverage_row(*case, args.coverage, seed=i) for i, case in enumerate(COVERAGE_CASES)] if args.coverage else []
    )
    if coverage:
        print(f"\ncoverage of the true hold-up (nominal {LEVEL:.0%}), {args.coverage} synthetic steady periods each")
        print(
            "| residence time [s] | steady [s] | slow part [s] | batch means (the results') | bootstrap, 5-s blocks |"
        )
        print("| --- | --- | --- | --- | --- |")
        for c in coverage:
            print(
                f"| {c.residence_time_s:g} | {c.steady_s:g} | {c.slow_s:g} | {c.batch_means:.3f} | {c.bootstrap_5s:.3f} |"
            )
    rtd_coverage = [rtd_coverage_row(n, args.coverage, seed=n) for n in RTD_COVERAGE_BLOCKS] if args.coverage else []
    if rtd_coverage:
        print(
            f"\ncoverage of a pooled RTD's true mean and variance (nominal {LEVEL:.0%}), {args.coverage} samples each"
        )
        print(
            "| entry blocks | mean: percentile ends | expanded (the results') | variance: percentile ends | expanded |"
        )
        print("| --- | --- | --- | --- | --- |")
        for c in rtd_coverage:
            print(
                f"| {c.n_blocks} | {c.mean_plain:.3f} | {c.mean_expanded:.3f} | {c.variance_plain:.3f} | "
                f"{c.variance_expanded:.3f} |"
            )
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    record = {
        "rows": [asdict(r) for r in rows],
        "coverage": [asdict(c) for c in coverage],
        "rtd_coverage": [asdict(c) for c in rtd_coverage],
    }
    print(f"wrote {write_json(out / 'blocks.json', record)}")
    return 0
