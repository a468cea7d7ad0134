"""The feed step: the deck's second feeder, the PBM's step against a single tank's closed
form, and the step judge (:func:`judge_step`) on synthetic DEM counts with known answers."""

import math

import numpy as np
import pandas as pd
import pytest

from coupling.errors import ConfigError
from coupling.tables import make_table
from dem.deck import STEP_FEEDER, build_deck, deck_parameters
from pbm.config import PbmConfig
from pbm.simulate import simulate
from workflows.analysis.step import StepComparison, StepRow, binomial_deviance, judge_step, mean_delay
from workflows.config import load_preset, override
from workflows.products.validate import step_config


def test_step_config_adds_a_second_feeder_that_starts_on_time():
    config = step_config()
    op = config.dem.operation
    info = deck_parameters(config.dem)
    step = info["feed_step"]
    assert step["extra_rate_a_per_s"] == pytest.approx((op.step_factor_a - 1) * op.feed_rate_a_per_s)
    assert 0 < step["start_s"] - op.step_time_s <= 0.05  # half a batch later: never on a batch of the first
    deck = build_deck(config.dem)["in.blender"]
    assert f"fix {STEP_FEEDER} gA insert/rate/region" in deck and f"start {step['start_step']}" in deck
    assert f"variable        insA equal f_insA[1]+f_{STEP_FEEDER}[1]" in deck
    # resumed past the start, the fix restores its state and must not be given a start in the past
    resumed = build_deck(config.dem, resume_from=f"restart/restart.{step['start_step'] + 1}.bin")["in.resume"]
    assert f"fix {STEP_FEEDER}" in resumed and " start " not in resumed
    # a steady run's deck has no trace of it
    assert STEP_FEEDER not in build_deck(load_preset("validation").dem)["in.blender"]


@pytest.mark.parametrize(
    "assignments, message",
    [
        (("dem.operation.step_time_s=80", "dem.operation.step_factor_a=0.5"), "must be > 1"),
        (("dem.operation.step_factor_a=2",), "needs step_time_s"),
        (("dem.operation.step_time_s=300", "dem.operation.step_factor_a=2"), "before the end"),
    ],
)
def test_bad_steps_are_refused(assignments, message):
    with pytest.raises(ConfigError, match=message):
        override(load_preset("validation"), *assignments)


def test_pbm_step_is_off_its_feed_grid_refused():
    with pytest.raises(ValueError, match="multiple of noise_interval_s"):
        PbmConfig(feed_step_s=20.5, feed_step_factor_a=2.0)


def test_pbm_step_matches_a_single_tank():
    k, f_a, f_b, t0, factor = 0.1, 10.0, 10.0, 20.0, 2.0
    v = k * 0.33  # one compartment of length 0.33 m: rate v / dx = k
    table = make_table(
        t=[0.0, 30.0],
        x_edges=[0.0, 0.33],
        y_edges=[-0.05, 0.05],
        vx_pos=v,
        vx_neg=0.0,
        vy_pos=0.0,
        vy_neg=0.0,
        window_s=30.0,
    )
    config = PbmConfig(
        feed_rate_a_per_s=f_a,
        feed_rate_b_per_s=f_b,
        feed_weights_a=[1.0],
        feed_weights_b=[1.0],
        feed_step_s=t0,
        feed_step_factor_a=factor,
        duration_s=60.0,
    )
    result = simulate(table, config)

    def discharged(rate, t, start):  # particles out of an empty tank fed `rate` from `start`
        s = np.clip(t - start, 0, None)
        return rate * (s - (1 - np.exp(-k * s)) / k)

    t = result.times
    out_a = discharged(f_a, t, 0.0) + discharged((factor - 1) * f_a, t, t0)
    out_b = discharged(f_b, t, 0.0)
    da, db = np.diff(out_a, prepend=0.0), np.diff(out_b, prepend=0.0)
    np.testing.assert_allclose(result.C_A, da / (da + db), rtol=1e-9)


def synthetic(step_s=80.0, t_end=170.0, tau=15.0, c0=0.5, c1=2 / 3, n=100):
    t = np.arange(1.0, t_end + 1)
    c = np.where(t > step_s, c1 - (c1 - c0) * np.exp(-(t - step_s) / tau), c0)
    return t, c, np.full(t.size, n)


def test_mean_delay_of_a_first_order_response():
    t, c, _ = synthetic(tau=15.0)
    # sampled at the ends of the 90 1-s intervals after the step: sum_i exp(-i / tau)
    expected = np.sum(np.exp(-np.arange(1, 91) / 15.0))
    assert expected == pytest.approx(15.0 - 0.5, abs=0.05)  # about tau, less half an interval
    assert mean_delay(t, c, 80.0, 1.0, (0.5, 2 / 3)) == pytest.approx(expected, rel=1e-9)
    with pytest.raises(ConfigError, match="does not change"):
        mean_delay(t, c, 80.0, 1.0, (0.5, 0.5))


def synthetic_dem(t, c, n, seed=7):
    n_a = np.random.default_rng(seed).binomial(n, c)
    return pd.DataFrame({"t_s": t, "n_A": n_a, "n_B": n - n_a})


def test_judge_step_accepts_its_own_curve_and_rejects_a_slower_one():
    t, c, n = synthetic(tau=15.0, n=100)
    dem = synthetic_dem(t, c, n)
    levels = (0.5, 2 / 3)
    same = judge_step(dem, pd.DataFrame({"t_s": t, "C_A": c}), 80.0, 1.0, levels)
    assert same.predicted and same.delay_inside and same.time_scale_inside and same.deviance_p > 0.05
    scale = same.time_scale
    assert scale.low < 1 < scale.high and scale.high - scale.low < 0.6 and not scale.at_bound
    lo, hi = same.dem_delay_s.low, same.dem_delay_s.high
    assert lo < same.pbm_delay_s < hi and hi - lo < 12  # 90 intervals of ~100 particles: +-5 s
    # a PBM twice as slow: the DEM runs faster by about 2, and 1 is far outside
    _, slow, _ = synthetic(tau=30.0)
    other = judge_step(dem, pd.DataFrame({"t_s": t, "C_A": slow}), 80.0, 1.0, levels)
    assert not other.predicted and not other.time_scale_inside
    assert other.time_scale.low < 2.0 < other.time_scale.high
    assert math.isclose(other.dem_delay_s.estimate, same.dem_delay_s.estimate)


def test_step_records_keep_the_summary_json_layout():
    """``summary.json``'s ``step_response`` (and report.html) read these records: their keys,
    nesting and plain-Python types are the file's format."""
    t, c, n = synthetic(tau=15.0, n=100)
    pbm = pd.DataFrame({"t_s": t, "C_A": c})
    dem = synthetic_dem(t, c, n)
    judged = judge_step(dem, pbm, 80.0, 1.0, (0.5, 2 / 3), n_boot=200)
    row = StepRow("self", "velocity", judged)
    comparison = StepComparison(
        step_s=80.0, factor_a=2.0, interval_s=1.0, rows=(row,), dem=dem, series={("self", "velocity"): pbm}
    )
    record = comparison.record()
    assert list(record) == ["step_s", "factor_a", "interval_s", "rows"]
    assert (record["step_s"], record["factor_a"], record["interval_s"]) == (80.0, 2.0, 1.0)
    (r,) = record["rows"]
    assert list(r) == [
        "source",
        "mode",
        "intervals_after_step",
        "deviance",
        "deviance_p",
        "time_scale",
        "time_scale_inside",
        "dem_delay_s",
        "pbm_delay_s",
        "delay_inside",
        "predicted",
    ]
    assert (r["source"], r["mode"], r["intervals_after_step"]) == ("self", "velocity", 90)
    assert list(r["time_scale"]) == ["value", "low", "high", "at_bound"]
    assert list(r["dem_delay_s"]) == ["value", "low", "high"]
    scale, delay = judged.time_scale, judged.dem_delay_s
    assert r["time_scale"] == {"value": scale.value, "low": scale.low, "high": scale.high, "at_bound": scale.at_bound}
    assert r["dem_delay_s"] == {"value": delay.estimate, "low": delay.low, "high": delay.high}
    assert (r["deviance"], r["deviance_p"], r["pbm_delay_s"]) == (
        judged.deviance,
        judged.deviance_p,
        judged.pbm_delay_s,
    )
    assert r["time_scale_inside"] == (scale.low <= 1 <= scale.high)
    assert r["delay_inside"] == (delay.low <= judged.pbm_delay_s <= delay.high)
    assert r["predicted"] == (r["time_scale_inside"] and r["deviance_p"] >= 0.05)

    def plain(value):  # what the JSON writer is given: no numpy scalars, no tuples
        if isinstance(value, dict):
            return all(isinstance(k, str) and plain(v) for k, v in value.items())
        if isinstance(value, list):
            return all(plain(v) for v in value)
        return type(value) in (str, int, float, bool)

    assert plain(record) and type(r["intervals_after_step"]) is int and type(r["predicted"]) is bool


def test_deviance_is_zero_at_the_counts_own_fractions():
    k, n = np.array([3.0, 0.0, 10.0]), np.array([10.0, 5.0, 10.0])
    assert binomial_deviance(k, n, k / n) == pytest.approx(0.0, abs=1e-9)
    assert binomial_deviance(k, n, np.full(3, 0.5)) > 10


@pytest.mark.slow
def test_shipped_step_run_is_found_and_judged(tmp_path):
    from workflows.analysis.step import step_comparison
    from workflows.products.validate import campaign_configs, run_campaign, run_step

    side = run_step(runs_root=tmp_path, solver=False, log=lambda message: None)
    assert side.source == "reference"
    base = run_campaign(
        tmp_path, solver=False, log=lambda message: None, configs={"baseline": campaign_configs()["baseline"]}
    )["baseline"]
    comparison = step_comparison(side, base, step_config())
    rows = {(r.source, r.mode): r.judgement for r in comparison.rows}
    # every mode each side's tables carry: both ship with their phase models
    assert {(s, m) for s in ("self", "baseline") for m in ("velocity", "measured", "phases")} == set(rows)
    assert list(comparison.series) == [(r.source, r.mode) for r in comparison.rows]
    for mode in ("velocity", "measured", "phases"):  # on its own tables the PBM follows the step
        own = rows[("self", mode)]
        assert own.predicted and own.delay_inside
    # the steady tables alone respond too slowly: the DEM runs faster than that PBM, by more
    # than on the run's own tables
    assert rows[("baseline", "measured")].time_scale.value > rows[("self", "measured")].time_scale.value + 0.1
