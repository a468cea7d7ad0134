"""``pbmdem study feeders``: do the DEM's two feeders leave with different RTDs, and does
the phase model say so too?

Feeder A enters on +y and B on -y, and the VRR targets judge feeder A alone. The phase
model lumps each axial slice's transverse compartments, so it tells the feeders apart only
by their entry phases and size-class shares. Whether that can be enough depends on whether
the DEM's difference between its feeders is a property of the blender or the sampling
noise of one run. Here, per run (by default the shipped reduced run and the validation
campaign): each feeder's pooled RTD mean and variance, the tracers that entered during the
run's entry window and left within its horizon (:func:`coupling.metrics.rtd_pooled`, the
comparison's definition); their A - B differences, with 95 % intervals from one block
bootstrap over entry time for both feeders (the blocks of :func:`dem.steady.pooled_rtd`:
the table's window, the expanded percentile interval), so the difference's interval keeps
whatever the two feeders share within a block; and the phase model's pooled RTD of each
feeder alone (:func:`pbm.rtd.pooled_rtd` with the other feeder's rate set to 0).

Over the runs it counts the signs of the DEM's differences and the runs whose interval
excludes 0, and pools the differences by inverse variance (each run's standard error from
its interval's half-width): a difference that is the blender's would keep its sign and
survive the pooling. Writes ``feeders.json`` and ``feeders.png`` and prints a table.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.special import ndtri

from coupling.errors import ConfigError
from coupling.files import writable_directory
from coupling.intervals import LEVEL, N_BOOT, Interval, block_bootstrap, inside, time_blocks
from coupling.jsonable import write_json
from pbm.rtd import pooled_rtd
from workflows.analysis.vrr import COMPONENT_CODES
from workflows.pipeline.results import load_results, pbm_config_for
from workflows.studies import add_runs_arguments, distinct_runs

HELP = "each feeder's pooled RTD in the DEM (A - B with its interval) and in the phase model, run by run"
OUT = Path("results/feeders")
#: the statistics of one bootstrap, in this order
_STATS = ("mean_A", "variance_A", "mean_B", "variance_B", "mean_difference", "variance_difference")


@dataclass(frozen=True)
class FeederRtds:
    """One run: the DEM's pooled RTD mean [s] and variance [s^2] per feeder and their A - B
    differences, each an :class:`Interval`; the tracers recovered per feeder; the phase
    model's mean and variance of each feeder alone; the DEM's pooled variance of both
    feeders together (the comparison's, the scale of the figure)."""

    results: str
    name: str
    dem_pooled_variance: float
    n_recovered: dict[str, int]
    dem: dict[str, Interval]
    pbm_mean: dict[str, float]
    pbm_variance: dict[str, float]

    @property
    def pbm_variance_difference(self) -> float:
        return self.pbm_variance["A"] - self.pbm_variance["B"]

    @property
    def difference_excludes_zero(self) -> bool:
        """Whether the DEM's variance difference is distinguishable from none."""
        d = self.dem["variance_difference"]
        return not bool(inside(0.0, d.low, d.high))

    def pbm_inside(self, feeder: str) -> bool:
        """Whether the phase model's variance of ``feeder`` lies in the DEM's interval."""
        d = self.dem[f"variance_{feeder}"]
        return bool(inside(self.pbm_variance[feeder], d.low, d.high))

    def record(self) -> dict:
        return {
            "results": self.results,
            "name": self.name,
            "n_recovered": self.n_recovered,
            "dem": {
                k: {"value": float(v.estimate), "low": float(v.low), "high": float(v.high)} for k, v in self.dem.items()
            },
            "pbm_mean_s": self.pbm_mean,
            "pbm_variance_s2": self.pbm_variance,
            "pbm_variance_difference_s2": self.pbm_variance_difference,
            "dem_difference_excludes_zero": self.difference_excludes_zero,
            "pbm_variance_inside": {f: self.pbm_inside(f) for f in COMPONENT_CODES},
        }


def dem_feeder_intervals(
    component: np.ndarray,
    entry_t_s: np.ndarray,
    exit_t_s: np.ndarray,
    entry_window: tuple[float, float],
    horizon_s: float,
    block_s: float,
    n_boot: int = N_BOOT,
    level: float = LEVEL,
) -> tuple[dict[str, Interval], dict[str, int]]:
    """Per feeder (``component`` codes of :data:`workflows.analysis.vrr.COMPONENT_CODES`)
    the pooled RTD's mean and variance, and their A - B differences, as :class:`Interval`
    from one block bootstrap over entry time (``block_s`` blocks from the window's start);
    with the recovered tracers per feeder. Raises ConfigError when a feeder has no
    recovered tracer or the window holds fewer than two blocks."""
    component = np.asarray(component)
    entry, exit_ = np.asarray(entry_t_s, float), np.asarray(exit_t_s, float)
    t0, t1 = entry_window
    entered = (entry > t0) & (entry <= t1)
    tau = exit_[entered] - entry[entered]
    got = tau <= horizon_s  # NaN: still inside at the end, so not recovered
    feeder = {name: (component[entered] == code) & got for name, code in COMPONENT_CODES.items()}
    counts = {name: int(mask.sum()) for name, mask in feeder.items()}
    if min(counts.values()) == 0:
        raise ConfigError(f"a feeder has no tracer recovered within {horizon_s:g} s: {counts}")
    blocks = time_blocks(entry[entered], block_s, origin=t0)
    if np.unique(blocks).size < 2:
        raise ConfigError(f"the entry window ({t0:g}, {t1:g}] s holds fewer than two {block_s:g}-s blocks")

    def statistic(idx: np.ndarray) -> np.ndarray:
        moments = []
        for mask in feeder.values():
            r = tau[idx][mask[idx]]
            moments += [r.mean(), r.var()] if r.size else [math.nan, math.nan]
        mean_a, var_a, mean_b, var_b = moments
        return np.array([mean_a, var_a, mean_b, var_b, mean_a - mean_b, var_a - var_b])

    est, low, high = block_bootstrap(statistic, blocks, n_boot=n_boot, level=level)
    return {k: Interval(float(e), float(lo), float(hi)) for k, e, lo, hi in zip(_STATS, est, low, high)}, counts


def feeder_rtds(path: str | Path) -> FeederRtds:
    """:class:`FeederRtds` of the results file ``path``. Raises ConfigError naming the file
    when it has no phase model or no pooled RTD; CacheError for a missing or corrupt file."""
    results, config = load_results(path)
    summary = results.summary
    if not results.table.has_phases:
        raise ConfigError(f"{path}: the results carry no phase model")
    if not summary.has_pooled_rtd:
        raise ConfigError(f"{path}: the DEM run has no pooled RTD (no entry window after its steady state)")
    spec = summary.pooled_rtd
    window = tuple(float(v) for v in spec.entry_window_s)
    particles = results.particles
    try:
        dem, counts = dem_feeder_intervals(
            particles["component"].to_numpy(),
            particles["entry_t_s"].to_numpy(float),
            particles["exit_t_s"].to_numpy(float),
            window,
            float(spec.horizon_s),
            float(results.table.window_s),
        )
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None
    pbm_config = pbm_config_for(config, results.table, None).model_copy(update={"rates": "phases"})
    alone = {"A": {"feed_rate_b_per_s": 0.0}, "B": {"feed_rate_a_per_s": 0.0}}
    pooled = {
        f: pooled_rtd(
            results.table, pbm_config.model_copy(update=off), entry_window=window, horizon_s=float(spec.horizon_s)
        )
        for f, off in alone.items()
    }
    return FeederRtds(
        results=str(path),
        name=config.name,
        dem_pooled_variance=float(spec.rtd_variance_s2.value),
        n_recovered=counts,
        dem=dem,
        pbm_mean={f: p.mean_s for f, p in pooled.items()},
        pbm_variance={f: p.variance_s2 for f, p in pooled.items()},
    )


@dataclass(frozen=True)
class Pooled:
    """The DEM's A - B variance differences over the runs: how many are positive, how many
    intervals exclude 0, and their inverse-variance mean with its interval at the runs'
    :data:`coupling.intervals.LEVEL` (each run's standard error from its interval's
    half-width over the normal quantile of that level)."""

    runs: int
    positive: int
    excluding_zero: int
    mean_s2: float
    low_s2: float
    high_s2: float

    def record(self) -> dict:
        return dataclasses.asdict(self)


def pooled_difference(rows: list[FeederRtds]) -> Pooled:
    d = [r.dem["variance_difference"] for r in rows]
    z = float(ndtri((1 + LEVEL) / 2))
    se = np.array([(v.high - v.low) / (2 * z) for v in d])
    w = 1.0 / se**2
    mean = float(np.sum(w * np.array([v.estimate for v in d])) / w.sum())
    half = z / math.sqrt(w.sum())
    return Pooled(
        runs=len(rows),
        positive=sum(v.estimate > 0 for v in d),
        excluding_zero=sum(r.difference_excludes_zero for r in rows),
        mean_s2=mean,
        low_s2=mean - half,
        high_s2=mean + half,
    )


def markdown(rows: list[FeederRtds], pooled: Pooled) -> str:
    """One line per run: each feeder's RTD variance in the DEM (interval) and the phase
    model (✓ inside, ✗ not), and the two A - B differences; then the pooling over runs."""

    def iv(v: Interval) -> str:
        return f"{v.estimate:.0f} [{v.low:.0f}, {v.high:.0f}]"

    lines = [
        "| run | tracers A / B | DEM var A [s²] | PBM var A | DEM var B [s²] | PBM var B "
        "| DEM A − B [s²] | PBM A − B |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        mark = {f: "✓" if r.pbm_inside(f) else "✗" for f in COMPONENT_CODES}
        lines.append(
            f"| {r.name} | {r.n_recovered['A']} / {r.n_recovered['B']} | {iv(r.dem['variance_A'])} "
            f"| {r.pbm_variance['A']:.0f} {mark['A']} | {iv(r.dem['variance_B'])} | {r.pbm_variance['B']:.0f} {mark['B']} "
            f"| {iv(r.dem['variance_difference'])}{' *' if r.difference_excludes_zero else ''} "
            f"| {r.pbm_variance_difference:+.0f} |"
        )
    lines += [
        "",
        f"DEM A − B: positive on {pooled.positive} of {pooled.runs} runs, interval excluding 0 (*) on "
        f"{pooled.excluding_zero}; pooled by inverse variance {pooled.mean_s2:+.1f} s² "
        f"[{pooled.low_s2:+.1f}, {pooled.high_s2:+.1f}]",
    ]
    return "\n".join(lines)


def plot_feeders(rows: list[FeederRtds], pooled: Pooled, path: Path) -> Path:
    """Left: each run's RTD variance per feeder relative to the DEM's of both feeders, the
    DEM's with its interval and the phase model's as a marker. Right: the A - B
    differences, the DEM's with its interval, the model's, and the pooled DEM difference
    as a band."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11, 0.45 * len(rows) + 1.6), layout="constrained")
    left, right = fig.subplots(1, 2, sharey=True)
    y = np.arange(len(rows))[::-1]
    scale = np.array([r.dem_pooled_variance for r in rows])
    for offset, f, colour in ((0.15, "A", "#b2182b"), (-0.15, "B", "#2166ac")):
        d = [r.dem[f"variance_{f}"] for r in rows]
        est = np.array([v.estimate for v in d]) / scale
        err = np.array([[v.estimate - v.low for v in d], [v.high - v.estimate for v in d]]) / scale
        left.errorbar(est, y + offset, xerr=err, fmt="o", ms=4, color=colour, label=f"DEM, feeder {f}")
        pbm = np.array([r.pbm_variance[f] for r in rows]) / scale
        left.plot(pbm, y + offset, "x", ms=7, color=colour, label=f"PBM, feeder {f}")
    d = [r.dem["variance_difference"] for r in rows]
    est = np.array([v.estimate for v in d])
    err = np.array([[v.estimate - v.low for v in d], [v.high - v.estimate for v in d]])
    right.axvspan(pooled.low_s2, pooled.high_s2, color="#bdbdbd", alpha=0.6, lw=0, label="DEM, pooled over runs")
    right.axvline(0.0, color="k", lw=0.6)
    right.errorbar(est, y, xerr=err, fmt="o", ms=4, color="#4d4d4d", label="DEM")
    right.plot([r.pbm_variance_difference for r in rows], y, "x", ms=7, color="#1b7837", label="PBM, phases")
    left.set(yticks=y, yticklabels=[r.name for r in rows], xlabel="feeder's RTD variance / DEM's of both feeders")
    right.set(xlabel="variance, feeder A − feeder B [s²]")
    for ax in (left, right):
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="best")
    fig.savefig(path, dpi=110)
    return path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_runs_arguments(parser, "a phase model and a pooled RTD", str(OUT))


def run(args: argparse.Namespace) -> int:
    rows = [feeder_rtds(path) for path in distinct_runs(args.results)]
    out = writable_directory(args.out, "--out")  # after the inputs are read: a bad one leaves nothing
    pooled = pooled_difference(rows)
    print(markdown(rows, pooled))
    written = write_json(out / "feeders.json", {"pooled": pooled.record(), "runs": [r.record() for r in rows]})
    print(f"wrote {written} and {plot_feeders(rows, pooled, out / 'feeders.png')}")
    return 0
