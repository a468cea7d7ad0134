"""workflows.analysis.budget: the truncated table, the judging and the budget rule (no
LIGGGHTS, no PBM runs: a synthetic table and transition counts from a known generator)."""

import math

import numpy as np
import pandas as pd
import pytest

from coupling.tables import RATE_NAMES, VELOCITY_NAMES, make_table
from dem.post import DemResults
from dem.rates import RATE_KEYS, generator, simulate_observations
from dem.summary import DemSummary
from workflows.analysis.agreement import AgreementRow, ModeValue
from workflows.analysis.budget import judge, smallest_budget, table_from_first

NX, NY, WINDOW_S, K, INTERVAL_S = 3, 2, 5.0, 8, 0.1
STEADY_S = 10.0  # windows 2.. are steady


def _rates(scale: float) -> dict[str, np.ndarray]:
    """Forward-biased axial rates and faster transverse ones [1/s], zero through walls."""
    rates = {
        "x_pos": np.full((NX, NY), 1.5 * scale),
        "x_neg": np.full((NX, NY), 0.4 * scale),
        "y_pos": np.full((NX, NY), 2.0 * scale),
        "y_neg": np.full((NX, NY), 1.0 * scale),
    }
    rates["x_pos"][1, 1] = 2.5 * scale  # not uniform: the fit must place each rate
    rates["x_neg"][0] = 0.0
    rates["y_pos"][:, -1] = 0.0
    rates["y_neg"][:, 0] = 0.0
    return rates


STEADY_RATES = _rates(1.0)


@pytest.fixture(scope="module")
def results():
    rng = np.random.default_rng(20130101)
    shape = (K, NX, NY)
    # before the steady state another generator moves the particles: the refit must not see it
    transitions = np.stack(
        [
            simulate_observations(
                generator(_rates(0.5 if k < 2 else 1.0), NX, NY),
                np.full(NX * NY, 20000),
                n_steps=50,
                interval_s=INTERVAL_S,
                rng=rng,
            )
            for k in range(K)
        ]
    )
    per_window = {
        f"rate_{key}": np.stack([_rates(0.5 if k < 2 else 1.0)[key] for k in range(K)]) * 1.01 for key in RATE_KEYS
    }
    per_window["rate_x_pos"][3, 2, 0] = np.nan  # an unmeasured rate stays unmeasured
    table = make_table(
        t=np.arange(K) * WINDOW_S,
        x_edges=np.linspace(0, 0.33, NX + 1),
        y_edges=np.linspace(-0.05, 0.05, NY + 1),
        vx_pos=rng.uniform(0.01, 0.1, shape),
        vx_neg=rng.uniform(0.0, 0.02, shape),
        vy_pos=rng.uniform(0.01, 0.05, shape),
        vy_neg=rng.uniform(0.01, 0.05, shape),
        count_A=rng.uniform(5, 50, shape),
        count_B=rng.uniform(5, 50, shape),
        n_samples=rng.integers(10, 1000, shape),
        window_s=WINDOW_S,
        min_samples=5,
        attrs={"rates_interval_s": INTERVAL_S},
        **per_window,
    )
    empty = pd.DataFrame()
    return DemResults(
        table=table,
        timeseries=empty,
        holdup=empty,
        rsd_by_slice=np.zeros(NX),
        rsd_by_slice_floor=np.zeros(NX),
        rtd=empty,
        residence_times_s=np.zeros(0),
        particles=empty,
        transitions=transitions,
        summary=DemSummary(steady_state_time_s=STEADY_S),
    )


def test_transient_kept_steady_period_holds_the_mean_seen_by_t_and_refit_recovers_the_generator(results):
    full = results.table
    cut = table_from_first(results, 25.0, STEADY_S)  # kept: windows 0-1; steady, seen by T: 2-4
    kept, steady = slice(0, 2), slice(2, 5)
    for name in (*VELOCITY_NAMES, "count_A", "count_B", "n_samples", *RATE_NAMES):
        np.testing.assert_array_equal(getattr(cut, name)[kept], getattr(full, name)[kept], err_msg=name)
    n = full.count_A[steady] + full.count_B[steady]
    for name in VELOCITY_NAMES:
        mean = (n * getattr(full, name)[steady]).sum(axis=0) / n.sum(axis=0)
        for k in range(2, K):
            np.testing.assert_allclose(getattr(cut, name)[k], mean, rtol=1e-12, err_msg=name)
    for k in range(2, K):
        np.testing.assert_allclose(cut.count_A[k], full.count_A[steady].mean(axis=0), rtol=1e-12)
        np.testing.assert_allclose(cut.count_B[k], full.count_B[steady].mean(axis=0), rtol=1e-12)
        np.testing.assert_array_equal(cut.n_samples[k], full.n_samples[steady].sum(axis=0))
    # refitted on the pooled moves of the steady windows: the steady generator, not the
    # early one and not the stored per-window values (those are 1 % off on purpose)
    for key in RATE_KEYS:
        fitted = getattr(cut, f"rate_{key}")[2:]
        assert np.all(np.isfinite(fitted))
        assert np.allclose(fitted, fitted[0])
        walls = STEADY_RATES[key] == 0
        assert np.all(np.abs(fitted[0][walls]) < 1e-9), key
        np.testing.assert_allclose(fitted[0][~walls], STEADY_RATES[key][~walls], rtol=0.04, err_msg=key)
    assert cut.attrs["budget_rates_converged"] and cut.attrs["budget_steady_windows"] == 3
    assert cut.attrs["rates_interval_s"] == INTERVAL_S  # provenance survives


def test_missing_velocities_are_filled_from_before_t_only(results):
    full = results.table
    n_samples = full.n_samples.copy()
    n_samples[2:, 0, 0] = 0  # compartment (0, 0) measured only before the steady state ...
    vx = full.vx_pos.copy()
    vx[2:, 0, 0] = 0.0
    vx[6:, 0, 0] = 5.0  # ... and the only later "measurement" lies after T (it must not leak)
    n_samples[6:, 0, 0] = 100
    holed = DemResults(**{**results.__dict__, "table": full.replace(n_samples=n_samples, vx_pos=vx)})
    cut = table_from_first(holed, 25.0, STEADY_S)
    # the nearest valid window before T is window 1: its velocity, whatever the weights
    assert cut.vx_pos[7, 0, 0] == pytest.approx(full.vx_pos[1, 0, 0], rel=1e-12)
    assert cut.n_samples[7, 0, 0] == 0


def test_the_whole_run_holds_the_mean_of_every_steady_window(results):
    full, pooled = results.table, table_from_first(results, K * WINDOW_S, STEADY_S)
    np.testing.assert_array_equal(pooled.vx_pos[:2], full.vx_pos[:2])
    n = full.count_A[2:] + full.count_B[2:]
    mean = (n * full.vy_neg[2:]).sum(axis=0) / n.sum(axis=0)
    np.testing.assert_allclose(pooled.vy_neg[2:], np.broadcast_to(mean, (K - 2, NX, NY)), rtol=1e-12)
    np.testing.assert_array_equal(pooled.n_samples[3], full.n_samples[2:].sum(axis=0))
    np.testing.assert_allclose(
        pooled.rate_y_pos[4][STEADY_RATES["y_pos"] > 0], STEADY_RATES["y_pos"][STEADY_RATES["y_pos"] > 0], rtol=0.04
    )
    with pytest.raises(ValueError, match="the table has none after it"):
        table_from_first(results, K * WINDOW_S, 100.0)


def test_t_beyond_the_end_is_the_whole_run(results):
    beyond, whole = table_from_first(results, 1000.0, STEADY_S), table_from_first(results, K * WINDOW_S, STEADY_S)
    for name in (*VELOCITY_NAMES, "count_A", "n_samples", *RATE_NAMES):
        np.testing.assert_array_equal(getattr(beyond, name), getattr(whole, name), err_msg=name)


@pytest.mark.parametrize(
    "t_use, steady, match",
    [
        (
            10.0,
            STEADY_S,
            r"T = 10 s: no complete 5-s window lies in \[steady time 10 s, T\); the first one ends at 15 s",
        ),
        (12.0, STEADY_S, r"T = 12 s"),
        (25.0, 100.0, r"T = 25 s.*steady time 100 s, T\); the table has none after it"),
        (25.0, math.nan, r"T = 25 s: the steady-state time is nan"),
        (math.inf, STEADY_S, r"T = inf"),
        (-5.0, STEADY_S, r"T = -5.0"),
    ],
)
def test_bad_t_raises(results, t_use, steady, match):
    with pytest.raises(ValueError, match=match):
        table_from_first(results, t_use, steady)


def _row(key, dem_low, dem_high, pbm, noise_low=None):
    mode = ModeValue(pbm, None, None, noise_low)
    return AgreementRow(key, key, "-", math.nan, dem_low, dem_high, {"velocity": mode})


def test_judge_uses_half_the_full_runs_interval_and_the_noise_band_for_the_overlap():
    full = [
        _row("holdup", 90.0, 110.0, 130.0),
        _row("rtd_recovered_fraction", 0.99, 1.0, 0.5),
        _row("rtd_overlap", 0.95, 1.0, 0.9, noise_low=0.96),
        _row("C_A", 0.5, 0.5, 0.5),
    ]
    at_t = [
        _row("holdup", 90.0, 110.0, 139.0),
        _row("rtd_recovered_fraction", 0.99, 1.0, 0.0),
        _row("rtd_overlap", 0.95, 1.0, 0.95, noise_low=0.9),
        _row("C_A", 0.5, 0.5, 0.5),
    ]
    rows = {row.key: row for row in judge(at_t, full, "velocity")}
    assert "rtd_recovered_fraction" not in rows  # not judged
    assert rows["holdup"].tolerance == 10.0 and rows["holdup"].ok  # 9 <= 10, though outside the DEM's
    assert rows["holdup"].deviation == pytest.approx(0.9)
    assert rows["rtd_overlap"].tolerance == pytest.approx(0.04)  # the full run's band, not T's
    assert not rows["rtd_overlap"].ok  # 0.05 > 0.04
    assert not rows["C_A"].ok and math.isnan(rows["C_A"].deviation)  # a zero-width yardstick judges nothing


def test_smallest_budget_needs_every_larger_t_inside():
    assert smallest_budget({30.0: False, 45.0: True, 60.0: False, 90.0: True, 260.0: True}) == 90.0
    assert smallest_budget({45.0: True, 260.0: True}) == 45.0
    assert smallest_budget({45.0: True, 260.0: False}) is None
    assert smallest_budget({}) is None


def test_refit_at_the_end_is_the_post_processings_own_model():
    """At T = the last dump, with the run's own steady time, the refit is skipped: the phase
    model the post-processing fitted is what fitting again gives (the fit is deterministic;
    to rounding, since the shipped file was fitted on another CPU, whose vector units may
    sum in another order), and before the end the model is fitted again."""
    from dem import phases
    from dem.post import sequence_diameters
    from workflows.analysis.budget import refit_phases
    from workflows.pipeline.results import load_results
    from workflows.shipped import VALIDATION_DIR

    results, _config = load_results(VALIDATION_DIR / "dem-aa093a229dfd2ce4.h5")
    steady, end = results.summary.steady_time, float(results.sequences.snapshot_t[-1])
    own = refit_phases(results, end, steady)
    assert own is results.table.phases
    again, _fit = phases.table_with_phases(
        results.table,
        results.sequences.until(end),
        steady,
        phases.moving_phases(results.table.phases),
        diameters=sequence_diameters(results.sequences, results.particles),
    )
    np.testing.assert_allclose(again.phases.rates, own.rates, rtol=1e-9, atol=0)
    np.testing.assert_allclose(again.phases.switching, own.switching, rtol=1e-9, atol=0)
    assert refit_phases(results, end - 20.0, steady) is not results.table.phases
