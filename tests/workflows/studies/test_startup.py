"""The start-up study: the time to fill is read off a curve with a known answer; on the
shipped feed x0.5 run (the campaign's slowest model) the linear PBM's judged hold-up lags
its own steady state, which its curve reaches, and the fill law fills it sooner; a file it
cannot use is refused in one line naming it."""

import dataclasses
import json
import math

import numpy as np
import pytest

from coupling.cache import load_entry, save_entry
from workflows.cli.main import main
from workflows.shipped import VALIDATION_DIR
from workflows.studies.startup import filled_time, linear_holdup

HALF_FEED = VALIDATION_DIR / "dem-dccc770e3c39f48c.h5"


def test_the_time_to_fill_of_a_first_order_approach():
    tau, steady = 20.0, 1500.0
    t = np.arange(0.0, 300.0, 0.01)
    holdup = steady * (1.0 - np.exp(-t / tau))
    assert filled_time(t, holdup, steady, within=0.01) == pytest.approx(tau * math.log(100.0), abs=0.02)
    assert math.isnan(filled_time(t[:1000], holdup[:1000], steady))  # 10 s: never within 1 %


def test_a_linear_blender_holds_the_feed_times_the_mean_of_min_tau_t():
    """Exponential residence times of mean m: F E[min(tau, t)] = F m (1 - exp(-t / m)),
    the first-order tank's fill; a tracer never seen to leave counts t."""
    m, feed = 20.0, 50.0
    tau = -m * np.log1p(-(np.arange(200_000) + 0.5) / 200_000)  # exponential quantiles
    for t in (5.0, 20.0, 60.0):
        assert linear_holdup(tau, feed, t) == pytest.approx(feed * m * (1 - math.exp(-t / m)), rel=1e-3)
    assert linear_holdup(np.array([1.0, np.inf]), 2.0, 10.0) == pytest.approx(11.0)


def test_the_linear_model_is_judged_while_still_filling(tmp_path, capsys):
    assert main(["study", "startup", "--results", str(HALF_FEED), "--out", str(tmp_path)]) == 0
    printed = capsys.readouterr().out
    (run,) = json.loads((tmp_path / "startup.json").read_text())["runs"]
    assert run["name"] == "validation-feed_x0.5" and "| validation-feed_x0.5 |" in printed
    stationary = run["pbm_stationary_holdup"]
    # the judged mean starts while the curve is still rising, so it sits below the model's
    # own steady state; a slowest mode of minutes is what keeps it there
    assert run["pbm_judged_holdup"] < 0.995 * stationary
    assert run["slowest_time_scale_s"] > 60.0
    assert run["pbm_filled_within_1pct_s"] > run["dem_steady_time_s"]
    assert run["fill_law_filled_within_1pct_s"] < run["pbm_filled_within_1pct_s"]
    dem = run["dem_holdup"]
    assert run["pbm_stationary_inside"] == (dem["low"] <= stationary <= dem["high"])
    # the DEM is steady while any linear blender with its own RTD holds three quarters of
    # it, and the phase model holds just that: the fast start-up is not a linear one's
    assert run["dem_rtd_linear_share_at_dem_steady"] < 0.85
    assert run["pbm_share_at_dem_steady"] == pytest.approx(run["dem_rtd_linear_share_at_dem_steady"], abs=0.02)
    assert (tmp_path / "startup.png").stat().st_size > 5_000


def test_a_file_without_a_phase_model_is_refused_by_name(tmp_path, capsys):
    entry = load_entry(HALF_FEED)
    plain = tmp_path / "plain.h5"
    save_entry(plain, dataclasses.replace(entry, table=entry.table.replace(phases=None)))
    assert main(["study", "startup", "--results", str(plain), "--out", str(tmp_path)]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(plain) in err[0] and "no phase model" in err[0]
