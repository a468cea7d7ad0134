"""Measured-rate mode of the PBM, and the pooled RTD that matches the DEM's definition.

Tolerances: the exact propagation is accurate to ~1e-13 relative, so analytic checks use
1e-9 (1e-8 for variances, which subtract two close numbers).
"""

import math

import numpy as np
import pytest
from scipy.stats import gamma

from coupling.errors import ConfigError, TableError
from coupling.tables import RATE_NAMES, make_table
from pbm import PbmConfig, simulate, synthetic_table
from pbm.model import fill_missing_rates, fill_missing_velocities, generator_matrix, transfer_rates
from pbm.rtd import pooled_rtd


def with_rates_from_velocities(table, **overrides):
    """The table with measured rates equal to v/dx and v/dy (what eq. 4 would use)."""
    dx, dy = table.dx[:, None], table.dy[None, :]
    rates = dict(
        rate_x_pos=table.vx_pos / dx,
        rate_x_neg=table.vx_neg / dx,
        rate_y_pos=table.vy_pos / dy,
        rate_y_neg=table.vy_neg / dy,
    )
    rates.update({name: np.full(table.vx_pos.shape, value) for name, value in overrides.items()})
    return table.replace(**rates)


def chain(nx, rate, windows=1, window_s=5.0):
    """NX compartments in a row, forward moves only, at ``rate`` [1/s] measured; the
    velocities say nothing moves, so only the measured mode can see the flow."""
    return make_table(
        t=window_s * np.arange(windows),
        x_edges=np.linspace(0, 0.33, nx + 1),
        y_edges=[-0.05, 0.05],
        vx_pos=0.0,
        vx_neg=0.0,
        vy_pos=0.0,
        vy_neg=0.0,
        window_s=window_s,
        rate_x_pos=rate,
        rate_x_neg=0.0,
        rate_y_pos=0.0,
        rate_y_neg=0.0,
    )


def test_measured_rates_equal_to_v_over_dx_give_the_velocity_results_exactly():
    # The synthetic table has unsampled compartment-windows: the rates are made from the
    # filled velocities, so that both modes see the same numbers everywhere.
    table = synthetic_table(nx=6, ny=5, n_windows=8, window_s=5.0, seed=3)
    table = with_rates_from_velocities(fill_missing_velocities(table)[0])
    by_velocity = simulate(table, PbmConfig(), rtd_pulse_s=10.0)
    by_rates = simulate(table, PbmConfig(rates="measured"), rtd_pulse_s=10.0)
    for name in ("outflow_A", "outflow_B", "counts", "rtd_E", "rsd_outlet"):
        np.testing.assert_array_equal(getattr(by_rates, name), getattr(by_velocity, name), err_msg=name)
    for key in ("mean_residence_time_s", "rtd_variance_s2", "steady_outflow_per_s"):
        assert getattr(by_rates.summary, key) == getattr(by_velocity.summary, key), key


def test_measured_mode_reads_the_rates_closes_the_walls_and_leaves_the_table_alone():
    table = with_rates_from_velocities(
        synthetic_table(nx=4, ny=3, n_windows=2, seed=5), rate_y_pos=0.7, rate_x_neg=0.2, rate_y_neg=0.3
    )
    r = transfer_rates(table, 0, "measured")
    np.testing.assert_array_equal(r["up"][:, :-1], 0.7)
    assert not r["up"][:, -1].any() and not r["down"][:, 0].any() and not r["backward"][0].any()
    np.testing.assert_array_equal(r["forward"], table.rate_x_pos[0])  # the last slice's is the outflow
    assert np.all(table.rate_y_pos == 0.7) and np.all(table.rate_x_neg == 0.2)
    g = generator_matrix(table, 0, "measured")
    assert g[1, 0] == 0.7  # (0, 0) -> (0, 1)
    with pytest.raises(ConfigError, match="unknown rate mode rates = 'dem'"):
        transfer_rates(table, 0, "dem")
    with pytest.raises(TableError, match="fill them first"):
        transfer_rates(table.replace(rate_x_pos=np.full_like(table.rate_x_pos, np.nan)), 0, "measured")


def test_tanks_in_series_from_measured_rates_have_the_erlang_moments():
    nx, k = 4, 0.5
    duration, pulse = 150.0, 2.0
    result = simulate(chain(nx, k), PbmConfig(duration_s=duration, rates="measured"), rtd_pulse_s=pulse)
    s = result.summary
    tau = duration - pulse
    assert s.rtd_recovered_fraction == pytest.approx(gamma.cdf(tau, nx, scale=1 / k), rel=1e-9)
    assert s.mean_residence_time_s == pytest.approx(nx / k, rel=1e-9)
    assert s.rtd_variance_s2 == pytest.approx(nx / k**2, rel=1e-8)
    # The velocity mode on the same table sees still powder: nothing leaves.
    assert (
        simulate(chain(nx, k), PbmConfig(duration_s=duration), rtd_pulse_s=pulse).summary.rtd_recovered_fraction == 0.0
    )


def test_unmeasured_rates_are_filled_by_the_velocity_rule():
    rng = np.random.default_rng(7)
    shape = (4, 3, 2)
    rates = {name: rng.uniform(0.1, 1.0, shape) for name in RATE_NAMES}
    rates["rate_x_pos"][1, 0, 0] = np.nan  # windows 0 and 2 equally near: the earlier one
    rates["rate_y_neg"][:, 2, 1] = np.nan  # never measured: mean of its slice's measured
    table = make_table(
        t=5.0 * np.arange(4),
        x_edges=[0, 0.1, 0.2, 0.3],
        y_edges=[-0.05, 0, 0.05],
        vx_pos=0.01,
        vx_neg=0,
        vy_pos=0,
        vy_neg=0,
        **rates,
    )
    filled, mask = fill_missing_rates(table)
    assert filled.rate_x_pos[1, 0, 0] == table.rate_x_pos[0, 0, 0]
    np.testing.assert_array_equal(filled.rate_y_neg[:, 2, 1], table.rate_y_neg[:, 2, 0])
    assert mask.sum() == 1 + 4 and mask[1, 0, 0] and mask[:, 2, 1].all()
    for name in RATE_NAMES:
        values = getattr(table, name)
        np.testing.assert_array_equal(getattr(filled, name)[~np.isnan(values)], values[~np.isnan(values)])
    summary = simulate(table, PbmConfig(rates="measured", duration_s=20.0), rtd_pulse_s=1.0).summary
    assert summary.filled_compartment_windows == 5
    with pytest.raises(TableError, match="'rate_x_neg' is NaN"):
        fill_missing_rates(table.replace(rate_x_neg=np.full(shape, np.nan)))


def test_measured_mode_without_rates_is_a_config_error_naming_the_mode():
    table = synthetic_table(nx=3, ny=2, n_windows=2)
    with pytest.raises(ConfigError) as info:
        simulate(table, PbmConfig(rates="measured"))
    message = str(info.value)
    assert "rates = 'measured'" in message and "no measured rates" in message and "schema-2" in message
    with pytest.raises(ConfigError, match="no measured rates"):
        pooled_rtd(table, PbmConfig(rates="measured"), entry_window=(0.0, 1.0), horizon_s=5.0)


def test_pooled_rtd_of_a_stationary_table_is_the_single_pulse_rtd_truncated_at_the_horizon():
    table = synthetic_table(nx=5, ny=4, n_windows=1, window_s=100.0, seed=11)
    horizon = 40.0
    pooled = pooled_rtd(table, PbmConfig(duration_s=100.0), entry_window=(10.0, 20.0), horizon_s=horizon)
    single = simulate(table, PbmConfig(duration_s=30.0 + horizon), rtd_pulse_s=30.0)
    assert pooled.n_pulses == 10
    np.testing.assert_allclose(pooled.entry_times_s, 10.5 + np.arange(10))
    np.testing.assert_allclose(pooled.bin_edges, np.arange(41.0))
    np.testing.assert_allclose(pooled.density_per_s, single.rtd_E, rtol=1e-9, atol=1e-13)
    s = single.summary
    assert pooled.recovered_fraction == pytest.approx(s.rtd_recovered_fraction, rel=1e-9)
    assert pooled.mean_s == pytest.approx(s.mean_residence_time_s, rel=1e-9)
    assert pooled.variance_s2 == pytest.approx(s.rtd_variance_s2, rel=1e-8)
    assert np.sum(pooled.density_per_s * np.diff(pooled.bin_edges)) == pytest.approx(
        pooled.recovered_fraction, rel=1e-12
    )


@pytest.mark.parametrize("rates", ["velocity", "measured"])
def test_pooled_rtd_of_one_compartment_has_the_truncated_exponential_moments(rates):
    k, horizon = 0.2, 12.5
    table = chain(1, k).replace(vx_pos=np.full((1, 1, 1), k * 0.33))
    pooled = pooled_rtd(table, PbmConfig(duration_s=30.0, rates=rates), entry_window=(0.0, 3.0), horizon_s=horizon)
    tail = math.exp(-k * horizon)
    recovered = 1 - tail
    mean = (1 / k - tail * (horizon + 1 / k)) / recovered
    second = (2 / k**2 - tail * (horizon**2 + 2 * horizon / k + 2 / k**2)) / recovered
    assert pooled.recovered_fraction == pytest.approx(recovered, rel=1e-9)
    assert pooled.mean_s == pytest.approx(mean, rel=1e-9)
    assert pooled.variance_s2 == pytest.approx(second - mean**2, rel=1e-8)
    # H = 12.5 s with 1-s bins: twelve whole bins and a last half bin.
    assert pooled.bin_edges[-1] == horizon and np.diff(pooled.bin_edges)[-1] == 0.5
    edges = pooled.bin_edges
    np.testing.assert_allclose(pooled.density_per_s, np.diff(-np.exp(-k * edges)) / np.diff(edges), rtol=1e-9)


def test_pooled_rtd_of_a_time_varying_table_averages_the_pulse_responses_at_their_own_times():
    table = synthetic_table(nx=4, ny=3, n_windows=12, window_s=5.0, seed=13)
    horizon = 30.0
    config = PbmConfig(feed_rate_a_per_s=300.0, feed_rate_b_per_s=100.0)
    pooled = pooled_rtd(table, config, entry_window=(12.0, 15.0), horizon_s=horizon, pulse_interval_s=1.5)
    assert pooled.n_pulses == 2
    singles = [
        simulate(table, config.model_copy(update={"duration_s": s + horizon}), rtd_pulse_s=s) for s in (12.75, 14.25)
    ]
    np.testing.assert_allclose(pooled.density_per_s, np.mean([r.rtd_E for r in singles], axis=0), rtol=1e-9, atol=1e-13)
    weights = np.array([r.summary.rtd_recovered_fraction for r in singles])
    means = np.array([r.summary.mean_residence_time_s for r in singles])
    assert pooled.recovered_fraction == pytest.approx(weights.mean(), rel=1e-9)
    assert pooled.mean_s == pytest.approx(np.sum(weights * means) / weights.sum(), rel=1e-9)


def test_pooled_rtd_of_identical_windows_equals_the_one_window_model_propagated_once():
    """Twelve windows of one table propagate the whole comb of pulses; the same table as
    one window propagates a single pulse for all: both must give the same pooled RTD."""
    one = synthetic_table(nx=4, ny=3, n_windows=1, window_s=60.0, seed=17)
    per_window = {
        name: np.repeat(value, 12, axis=0)
        for name, value in vars(one).items()
        if isinstance(value, np.ndarray) and value.shape == (1, one.nx, one.ny)
    }
    repeated = one.replace(t=5.0 * np.arange(12), window_s=5.0, **per_window)
    config = PbmConfig(duration_s=60.0, feed_rate_a_per_s=300.0, feed_rate_b_per_s=100.0)
    comb, single = (pooled_rtd(t, config, entry_window=(8.0, 20.0), horizon_s=35.0) for t in (repeated, one))
    assert comb.n_pulses == single.n_pulses == 12
    np.testing.assert_allclose(comb.density_per_s, single.density_per_s, rtol=1e-9, atol=1e-13)
    assert comb.mean_s == pytest.approx(single.mean_s, rel=1e-10)
    assert comb.variance_s2 == pytest.approx(single.variance_s2, rel=1e-9)
    assert comb.recovered_fraction == pytest.approx(single.recovered_fraction, rel=1e-10)


def test_pooled_rtd_in_groups_of_pulses_equals_the_whole_comb(monkeypatch):
    """A comb too large for the action kernel's memory bound is propagated in groups of
    pulses, each over its own span: the same RTD as the whole comb in one march."""
    import pbm.rtd

    table = synthetic_table(nx=4, ny=3, n_windows=12, window_s=5.0, seed=13)
    config = PbmConfig(duration_s=60.0, feed_rate_a_per_s=300.0, feed_rate_b_per_s=100.0, kernel="action")
    whole = pooled_rtd(table, config, entry_window=(8.0, 20.0), horizon_s=35.0)
    # room for about three columns' states over the comb's breakpoints: groups of 3
    monkeypatch.setattr(pbm.rtd, "ACTION_MAX_BYTES", 3 * 60 * (table.nx * table.ny + 3) * 8)
    grouped = pooled_rtd(table, config, entry_window=(8.0, 20.0), horizon_s=35.0)
    assert grouped.n_pulses == whole.n_pulses == 12
    np.testing.assert_allclose(grouped.density_per_s, whole.density_per_s, rtol=1e-10, atol=1e-14)
    assert grouped.mean_s == pytest.approx(whole.mean_s, rel=1e-12)
    assert grouped.variance_s2 == pytest.approx(whole.variance_s2, rel=1e-11)


def test_pooled_rtd_pulses_are_one_spacing_apart_in_any_window():
    """A window that is not a whole number of spacings (the DEM's never is) still gets a
    comb exactly one spacing apart, centred in it, so every pulse is read on one time grid."""
    table = synthetic_table(nx=3, ny=2, n_windows=12, window_s=5.0, seed=13)
    for window, count in (((10.0, 22.6), 13), ((10.0, 22.4), 12), ((10.0, 10.3), 1)):
        pooled = pooled_rtd(table, PbmConfig(), entry_window=window, horizon_s=20.0)
        entries = pooled.entry_times_s
        assert pooled.n_pulses == count
        np.testing.assert_allclose(np.diff(entries), 1.0, rtol=0, atol=1e-12)
        assert entries.mean() == pytest.approx(0.5 * sum(window), abs=1e-12)
        assert entries[0] > window[0] and entries[-1] <= window[1]


def test_pooled_rtd_matches_the_bdf_cross_check():
    table = synthetic_table(nx=3, ny=2, n_windows=4, window_s=5.0, seed=17)
    exact = pooled_rtd(table, PbmConfig(), entry_window=(1.0, 4.0), horizon_s=12.0)
    bdf = pooled_rtd(table, PbmConfig(method="bdf"), entry_window=(1.0, 4.0), horizon_s=12.0)
    np.testing.assert_allclose(bdf.density_per_s, exact.density_per_s, rtol=1e-4, atol=1e-6)
    assert bdf.mean_s == pytest.approx(exact.mean_s, rel=1e-4)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (dict(entry_window=(5.0, 5.0)), "entry_window must satisfy 0 <= t0 < t1"),
        (dict(entry_window=(-1.0, 5.0)), "entry_window must satisfy 0 <= t0 < t1"),
        (dict(horizon_s=0.0), "horizon_s must be a finite number > 0 s, got 0.0"),
        (dict(pulse_interval_s=-1.0), "pulse_interval_s must be a finite number > 0 s, got -1.0"),
        (dict(entry_window=(0.0, 10.0), horizon_s=15.0), "beyond the run's end 20.0 s"),
    ],
)
def test_pooled_rtd_refuses_bad_windows_by_name(kwargs, message):
    table = synthetic_table(nx=3, ny=2, n_windows=4, window_s=5.0)
    args = dict(entry_window=(0.0, 1.0), horizon_s=5.0) | kwargs
    with pytest.raises(ConfigError, match=message.replace("(", r"\(").replace(")", r"\)")):
        pooled_rtd(table, PbmConfig(), **args)


def test_pooled_rtd_is_fast_on_the_paper_grid():
    # 130 pulses through a 10x10, 52-window, 260-s table: the size of the reduced preset.
    import time

    table = synthetic_table(nx=10, ny=10, n_windows=52, window_s=5.0)
    start = time.perf_counter()
    pooled = pooled_rtd(table, PbmConfig(), entry_window=(0.0, 130.0), horizon_s=130.0)
    elapsed = time.perf_counter() - start
    assert pooled.n_pulses == 130 and pooled.recovered_fraction > 0.99
    assert elapsed < 5.0, f"pooled RTD took {elapsed:.2f} s"


def test_pooled_rtd_density_is_never_negative_after_the_tracer_has_left():
    # A fast chain followed long after it has emptied: the discharged count is flat to the
    # propagation's rounding, which must not show as negative density (the overlap with
    # the DEM's RTD refuses any). Unclamped, this chain's tail bins are ~ -1e-15.
    pooled = pooled_rtd(
        chain(3, 20.0), PbmConfig(duration_s=100.0, rates="measured"), entry_window=(0.0, 30.0), horizon_s=60.0
    )
    assert np.all(pooled.density_per_s >= 0.0)
    assert pooled.density_per_s[-20:] == pytest.approx(0.0, abs=1e-12)
    assert np.sum(pooled.density_per_s) == pytest.approx(pooled.recovered_fraction, rel=1e-12)
