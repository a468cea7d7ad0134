"""A dynamic check: the outlet's answer to a step in feeder A's rate, DEM against PBM.

One real LIGGGHTS run of the ``validation`` preset in which a second feeder of A starts
after the steady state (:data:`STEP_OVERRIDES`: A's rate doubles at 80 s, so the feed's
A share goes from 1/2 to 2/3), run and cached like any other (:func:`run_step`); its
results ship in ``workflows/reference/step``.

The PBM is fed the same step (``PbmConfig.feed_step_s``, on the PBM's 1-s feed grid; the
DEM's second feeder starts half an insertion batch, 0.025 s, later) and predicts the
outlet C_A per sampling interval. Two PBMs are judged, each in both rate modes:

* ``self``: the step run's own tables (what the hybrid does when the DEM saw the change);
* ``baseline``: the steady baseline's tables, velocities unchanged by the step (what the
  hybrid predicts from a steady DEM run alone -- the use of a PBM for control).

The DEM's outlet C_A per interval is a binomial sample of n particles. Two numbers judge
each PBM (:func:`judge_step`, a statistical test with its own rule, not the project's
value-against-reference judge):

* the share of the intervals after the step whose DEM count of A lies in the PBM's central
  95 % binomial range (Binomial(n, C_PBM)); about 0.95 if the PBM were the DEM's truth;
* the response's mean delay, sum over the intervals after the step of
  (C_after - C(t)) dt / (C_after - C_before), with the levels the feed's A share before
  and after the step. For a linear blender it is the mean residence time of A (less the
  part of the response after the run's end, cut the same way on both sides). The DEM's carries a 95 %
  interval from a parametric bootstrap of its binomial counts; the PBM's, by the same rule
  on its own series, must fall inside it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd
from scipy.stats import chi2

from coupling.errors import ConfigError
from coupling.intervals import N_BOOT, SEED, Interval
from pbm.model import supported_modes
from pbm.simulate import simulate
from workflows.config import Config
from workflows.pipeline.results import pbm_config_for
from workflows.pipeline.stages import DemSide

#: The deviance's p-value below which the PBM's response is rejected as a whole.
P_MIN = 0.05
#: Range searched for the time-scale factor, and the 95 % chi-square quantile (1 dof).
ALPHA_RANGE = (0.25, 4.0)
CHI2_95_ONE_DOF = 3.841458820694124


def dem_counts(timeseries: pd.DataFrame, interval_s: float) -> pd.DataFrame:
    """Particles of A and B discharged per sampling interval (t_s: the interval's end)."""
    n_a = np.rint(timeseries["outflow_A_per_s"].to_numpy() * interval_s)
    n_b = np.rint(timeseries["outflow_B_per_s"].to_numpy() * interval_s)
    return pd.DataFrame({"t_s": timeseries["t_s"].to_numpy(), "n_A": n_a, "n_B": n_b})


def pbm_response(
    table, config: Config, rates: str, step_s: float, t_end: float, fill_exponents: list[list[float]] | None = None
) -> pd.DataFrame:
    """The PBM's outlet C_A per sampling interval for ``table`` under the config's step;
    with ``fill_exponents``, its rates follow the fill by that law (:mod:`pbm.fill`)."""
    op = config.dem.operation
    interval = float(config.dem.tables.sample_interval_s)
    pbm_config = pbm_config_for(config, table, None).model_copy(
        update={
            "rates": rates,
            "feed_step_s": step_s,
            "feed_step_factor_a": op.step_factor_a,
            "output_interval_s": interval,
            "noise_interval_s": interval,
            "duration_s": min(t_end, table.t_end),
            "rate_law": "table" if fill_exponents is None else "fill",
            "fill_exponents": fill_exponents,
        }
    )
    result = simulate(table, pbm_config)
    return pd.DataFrame({"t_s": result.times, "C_A": result.C_A})


def feed_levels(config: Config) -> tuple[float, float]:
    """The feed's A share before and after the step: where the outlet's C_A starts and,
    for a blender that loses no particle, where it ends."""
    op = config.dem.operation
    a, b = op.feed_rate_a_per_s, op.feed_rate_b_per_s
    return a / (a + b), op.step_factor_a * a / (op.step_factor_a * a + b)


def mean_delay(
    t_s: np.ndarray, c_a: np.ndarray, step_s: float, interval_s: float, levels: tuple[float, float]
) -> float:
    """sum over the intervals after the step of (C_after - C(t)) dt / (C_after - C_before),
    with the levels the feed's (:func:`feed_levels`): measuring them from the outlet would
    add their sampling noise to every interval of the sum."""
    c0, c1 = levels
    if not abs(c1 - c0) > 0:
        raise ConfigError(f"the feed's A share does not change across the step ({c0} -> {c1}): no response to time")
    response = (t_s > step_s) & np.isfinite(c_a)
    return float(np.sum(c1 - c_a[response]) * interval_s / (c1 - c0))


def binomial_deviance(k: np.ndarray, n: np.ndarray, p: np.ndarray) -> float:
    """2 sum [k ln(k / n p) + (n - k) ln((n - k) / n (1 - p))]: the likelihood-ratio
    statistic of counts k of n against probabilities p (chi-square with one degree of
    freedom per interval when p is the truth)."""
    p = np.clip(p, 1e-12, 1 - 1e-12)
    with np.errstate(divide="ignore", invalid="ignore"):
        a = np.where(k > 0, k * np.log(k / (n * p)), 0.0)
        b = np.where(n - k > 0, (n - k) * np.log((n - k) / (n * (1 - p))), 0.0)
    return float(2 * np.sum(a + b))


@dataclass(frozen=True)
class TimeScale:
    """The factor by which the DEM's response runs faster than the PBM's (:func:`time_scale`),
    with its 95 % profile-likelihood interval [low, high]; ``at_bound``: the interval reaches
    the searched range's end (:data:`ALPHA_RANGE`), so the true bound may lie beyond."""

    value: float
    low: float
    high: float
    at_bound: bool

    @property
    def holds_one(self) -> bool:
        """The interval holds 1: the DEM's response runs at the PBM's speed."""
        return self.low <= 1.0 <= self.high

    def record(self) -> dict[str, Any]:
        return {"value": self.value, "low": self.low, "high": self.high, "at_bound": self.at_bound}


def time_scale(
    t_s: np.ndarray, k: np.ndarray, n: np.ndarray, pbm_t: np.ndarray, pbm_c: np.ndarray, step_s: float
) -> TimeScale:
    """The factor alpha by which the DEM's response runs faster than the PBM's (the DEM at
    step + dt matches the PBM at step + alpha dt), by binomial maximum likelihood over a
    log-spaced grid, with its 95 % profile-likelihood interval (deviance within 3.84 of
    its minimum). ``at_bound`` says the interval reaches the grid's end (0.25 or 4)."""
    alphas = np.geomspace(ALPHA_RANGE[0], ALPHA_RANGE[1], 1201)
    ok = np.isfinite(pbm_c)
    deviances = np.array(
        [binomial_deviance(k, n, np.interp(step_s + (t_s - step_s) * a, pbm_t[ok], pbm_c[ok])) for a in alphas]
    )
    best = int(np.argmin(deviances))
    inside = alphas[deviances <= deviances[best] + CHI2_95_ONE_DOF]
    return TimeScale(
        value=float(alphas[best]),
        low=float(inside.min()),
        high=float(inside.max()),
        at_bound=bool(inside.min() <= alphas[0] or inside.max() >= alphas[-1]),
    )


@dataclass(frozen=True)
class StepJudgement:
    """One PBM's step response against the DEM's (:func:`judge_step`).

    ``intervals_after_step``: the sampling intervals judged; ``deviance`` and ``deviance_p``:
    the DEM's counts of A against the PBM's C_A (chi-square, one dof per interval);
    ``time_scale``: how much faster the DEM responds; ``dem_delay_s``: the DEM's mean delay
    [s] with its 95 % bootstrap interval; ``pbm_delay_s``: the PBM's [s], by the same rule.
    The verdicts (:attr:`time_scale_inside`, :attr:`delay_inside`, :attr:`predicted`)
    follow from these numbers."""

    intervals_after_step: int
    deviance: float
    deviance_p: float
    time_scale: TimeScale
    dem_delay_s: Interval
    pbm_delay_s: float

    @property
    def time_scale_inside(self) -> bool:
        return self.time_scale.holds_one

    @property
    def delay_inside(self) -> bool:
        return bool(self.dem_delay_s.low <= self.pbm_delay_s <= self.dem_delay_s.high)

    @property
    def predicted(self) -> bool:
        """The PBM predicts the step: the DEM runs at its speed and its counts are
        consistent with it (p >= :data:`P_MIN`). The mean delay is reported, not judged."""
        return bool(self.time_scale_inside and self.deviance_p >= P_MIN)

    def record(self) -> dict[str, Any]:
        delay = self.dem_delay_s
        return {
            "intervals_after_step": self.intervals_after_step,
            "deviance": self.deviance,
            "deviance_p": self.deviance_p,
            "time_scale": self.time_scale.record(),
            "time_scale_inside": self.time_scale_inside,
            "dem_delay_s": {"value": delay.estimate, "low": delay.low, "high": delay.high},
            "pbm_delay_s": self.pbm_delay_s,
            "delay_inside": self.delay_inside,
            "predicted": self.predicted,
        }


def judge_step(
    dem: pd.DataFrame,
    pbm: pd.DataFrame,
    step_s: float,
    interval_s: float,
    levels: tuple[float, float],
    n_boot: int = N_BOOT,
    seed: int = SEED,
) -> StepJudgement:
    """One PBM's step response against the DEM's (module docstring): the response's time
    scale and the counts' deviance decide; the mean delay is reported with its interval.
    ``dem``: counts per interval (:func:`dem_counts`); ``pbm``: t_s and C_A
    (:func:`pbm_response`); ``step_s``, ``interval_s`` [s]; ``levels``: :func:`feed_levels`.
    Only intervals after the step where the DEM discharged something and the PBM is defined."""
    merged = dem.merge(pbm, on="t_s", how="inner")
    n = (merged["n_A"] + merged["n_B"]).to_numpy()
    t = merged["t_s"].to_numpy()
    c_pbm = merged["C_A"].to_numpy()
    post = (t > step_s) & (n > 0) & np.isfinite(c_pbm)
    t, n, c_pbm, k = t[post], n[post], c_pbm[post], merged["n_A"].to_numpy()[post]
    if t.size == 0:
        raise ConfigError(f"no interval after the step at {step_s} s with particles discharged: nothing to judge")
    deviance = binomial_deviance(k, n, c_pbm)
    p_value = float(chi2.sf(deviance, t.size))
    scale = time_scale(t, k, n, pbm["t_s"].to_numpy(), pbm["C_A"].to_numpy(), step_s)
    dem_delay = mean_delay(t, k / n, step_s, interval_s, levels)
    rng = np.random.default_rng(seed)
    draws = rng.binomial(n.astype(np.int64), k / n, size=(n_boot, n.size))
    boot = [mean_delay(t, d / n, step_s, interval_s, levels) for d in draws]
    low, high = (float(q) for q in np.percentile(boot, [2.5, 97.5]))
    pbm_delay = mean_delay(t, c_pbm, step_s, interval_s, levels)
    return StepJudgement(
        intervals_after_step=int(t.size),
        deviance=deviance,
        deviance_p=p_value,
        time_scale=scale,
        dem_delay_s=Interval(dem_delay, low, high),
        pbm_delay_s=pbm_delay,
    )


@dataclass(frozen=True)
class StepRow:
    """One PBM of the comparison: its tables (``source``: "self" or "baseline"), its rate
    ``mode`` and its :class:`StepJudgement`."""

    source: str
    mode: str
    judgement: StepJudgement

    def record(self) -> dict[str, Any]:
        return {"source": self.source, "mode": self.mode, **self.judgement.record()}


# eq=False: the series are DataFrames, whose == is elementwise and has no truth value
@dataclass(frozen=True, eq=False)
class StepComparison:
    """:func:`step_comparison`'s answer: the PBM's step time ``step_s`` [s] (on its feed
    grid), feeder A's factor, the sampling interval [s], one :class:`StepRow` per PBM, and
    the series for a figure: ``dem`` (t_s, n_A, n_B per interval, :func:`dem_counts`) and
    ``series`` (per (source, mode), the PBM's t_s and C_A, in the rows' order)."""

    step_s: float
    factor_a: float
    interval_s: float
    rows: tuple[StepRow, ...]
    dem: pd.DataFrame
    series: dict[tuple[str, str], pd.DataFrame]

    def record(self) -> dict[str, Any]:
        """The JSON-ready part (no series): ``summary.json``'s ``step_response``."""
        return {
            "step_s": self.step_s,
            "factor_a": self.factor_a,
            "interval_s": self.interval_s,
            "rows": [row.record() for row in self.rows],
        }


def step_comparison(
    step: DemSide,
    baseline: DemSide | None,
    config: Config,
    fill_law: dict[str, list[list[float]]] | None = None,
) -> StepComparison:
    """Every PBM (own tables / the baseline's, each rate mode the table carries) judged
    against the step run's DEM; with the series for the figure. ``fill_law``: per rate
    mode, the exponents of a fill law (e.g. the baseline's own): the baseline's tables are then
    also judged with rates that follow the fill ("baseline + fill law")."""
    op = config.dem.operation
    interval = float(config.dem.tables.sample_interval_s)
    # the PBM's feed changes on its interval grid; the DEM's second feeder starts 0.025 s later
    step_s = math.floor(op.step_time_s / interval + 1e-9) * interval
    t_end = float(step.results.timeseries["t_s"].max())
    dem = dem_counts(step.results.timeseries, interval)
    sources = {"self": (step.table, {})}
    if baseline is not None:
        sources["baseline"] = (baseline.table, {})
        if fill_law:
            sources["baseline + fill law"] = (baseline.table, fill_law)
    rows, series = [], {}
    for source, (table, law) in sources.items():
        for mode in supported_modes(table):
            if source == "baseline + fill law" and mode not in law:
                continue
            pbm = pbm_response(table, config, mode, step_s, t_end, law.get(mode))
            series[(source, mode)] = pbm
            rows.append(StepRow(source, mode, judge_step(dem, pbm, step_s, interval, feed_levels(config))))
    return StepComparison(
        step_s=step_s, factor_a=op.step_factor_a, interval_s=interval, rows=tuple(rows), dem=dem, series=series
    )
