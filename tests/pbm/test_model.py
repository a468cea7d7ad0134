"""Fill rule for missing samples, feed distribution, CQA statistics, geometry studies."""

import numpy as np
import pytest
from scipy.stats import gamma

from coupling.errors import ConfigError, TableError
from coupling.tables import make_table
from pbm import PbmConfig, fill_missing_velocities, regrid, scale_blender, simulate
from pbm.model import default_feed_weights, feed_distribution


def table_with_samples(n_samples, values=None, t=None, min_samples=5):
    k, nx, ny = n_samples.shape
    values = np.arange(k * nx * ny, dtype=float).reshape(k, nx, ny) + 1.0 if values is None else values
    return make_table(
        t=np.arange(k) * 5.0 if t is None else t,
        x_edges=np.linspace(0, 0.3, nx + 1),
        y_edges=np.linspace(-0.05, 0.05, ny + 1),
        vx_pos=values,
        vx_neg=2 * values,
        vy_pos=3 * values,
        vy_neg=4 * values,
        n_samples=n_samples,
        min_samples=min_samples,
    )


def test_fill_rule_nearest_window_of_same_compartment_earlier_on_tie():
    ns = np.full((4, 2, 2), 10)
    ns[1, 0, 0] = 0  # windows 0 and 2 equally near: the earlier one
    ns[0:2, 1, 1] = 3  # below min_samples in windows 0, 1: nearest valid is window 2
    table = table_with_samples(ns)
    filled, mask = fill_missing_velocities(table)
    v = table.vx_pos
    assert filled.vx_pos[1, 0, 0] == v[0, 0, 0]
    assert filled.vy_neg[1, 0, 0] == table.vy_neg[0, 0, 0]
    assert filled.vx_pos[0, 1, 1] == v[2, 1, 1] and filled.vx_pos[1, 1, 1] == v[2, 1, 1]
    assert mask.sum() == 3 and mask[1, 0, 0] and mask[0, 1, 1]
    # Valid entries are untouched; n_samples keeps its provenance.
    np.testing.assert_array_equal(filled.vx_pos[~mask], v[~mask])
    np.testing.assert_array_equal(filled.n_samples, table.n_samples)


def test_fill_rule_uneven_window_spacing_picks_nearest_in_time():
    ns = np.full((3, 1, 2), 10)
    ns[1, 0, 0] = 0
    table = table_with_samples(ns, t=[0.0, 10.0, 12.0])
    filled, _ = fill_missing_velocities(table)
    assert filled.vx_pos[1, 0, 0] == table.vx_pos[2, 0, 0]


def test_fill_rule_never_valid_compartment_takes_slice_then_nearest_slice_then_table_mean():
    ns = np.full((2, 3, 3), 10)
    ns[:, 0, 0] = 0  # never valid; its slice has valid neighbours -> slice mean per window
    ns[:, 2, :] = 0  # a whole slice never valid -> nearest valid slice (1)
    table = table_with_samples(ns)
    filled, _ = fill_missing_velocities(table)
    v = table.vx_pos
    for k in range(2):
        assert filled.vx_pos[k, 0, 0] == pytest.approx(v[k, 0, 1:].mean())
        assert filled.vx_pos[k, 2, 1] == pytest.approx(v[k, 1, :].mean())
        assert filled.vy_pos[k, 2, 2] == pytest.approx(table.vy_pos[k, 1, :].mean())
    # Equidistant valid slices on both sides are averaged.
    ns2 = np.full((1, 3, 2), 10)
    ns2[:, 1, :] = 0
    t2 = table_with_samples(ns2)
    f2, _ = fill_missing_velocities(t2)
    assert f2.vx_pos[0, 1, 0] == pytest.approx(0.5 * (t2.vx_pos[0, 0].mean() + t2.vx_pos[0, 2].mean()))
    # A window without any valid compartment: table-wide mean of valid values.
    ns3 = np.full((2, 2, 2), 10)
    ns3[1] = 0
    ns3[:, 0, 0] = 0
    t3 = table_with_samples(ns3)
    f3, _ = fill_missing_velocities(t3)
    assert f3.vx_pos[1, 0, 0] == pytest.approx(t3.vx_pos[t3.valid].mean())
    assert f3.vx_pos[1, 1, 1] == t3.vx_pos[0, 1, 1]  # rule 1 still applies to the others


def test_fill_rule_refuses_a_table_without_any_sample():
    with pytest.raises(TableError, match="no compartment-window"):
        fill_missing_velocities(table_with_samples(np.zeros((2, 2, 2), int)))


def test_missing_outlet_velocity_is_not_read_as_zero():
    # The outlet slice never had samples (stored velocity 0): a literal reading would
    # trap every particle; the fill rule gives it the neighbouring slice's velocity.
    nx, ny = 4, 2
    ns = np.full((1, nx, ny), 50)
    ns[:, -1, :] = 0
    vx = np.full((1, nx, ny), 0.03)
    vx[:, -1, :] = 0.0
    table = make_table(
        t=[0.0],
        x_edges=np.linspace(0, 0.33, nx + 1),
        y_edges=np.linspace(-0.05, 0.05, ny + 1),
        vx_pos=vx,
        vx_neg=0.0,
        vy_pos=0.1,
        vy_neg=0.1,
        n_samples=ns,
        min_samples=10,
    )
    result = simulate(table, PbmConfig(duration_s=120.0))
    assert result.summary.filled_compartment_windows == ny
    assert result.summary.steady_outflow_per_s == pytest.approx(1990.0, rel=1e-3)


def test_default_feed_weights_split_the_diameter():
    np.testing.assert_allclose(default_feed_weights(np.linspace(-1, 1, 5), +1), [0, 0, 0.5, 0.5])
    np.testing.assert_allclose(default_feed_weights(np.linspace(-1, 1, 5), -1), [0.5, 0.5, 0, 0])
    np.testing.assert_allclose(default_feed_weights(np.linspace(-1.5, 1.5, 4), +1), [0, 1 / 3, 2 / 3])
    with pytest.raises(ConfigError, match="y > 0"):
        default_feed_weights(np.array([-2.0, -1.0]), +1)


def test_feed_distribution_custom_weights_and_length_check():
    table = make_table(
        t=[0.0], x_edges=[0, 0.1, 0.2], y_edges=[-0.05, 0, 0.05], vx_pos=0.01, vx_neg=0, vy_pos=0, vy_neg=0
    )
    feed = feed_distribution(table, [1.0, 3.0], None)
    np.testing.assert_allclose(feed[:, 0], [0.25, 0.75, 0, 0])
    np.testing.assert_allclose(feed[:, 1], [1.0, 0, 0, 0])
    with pytest.raises(ConfigError, match="feed_weights_a has 3 entries; .* NY = 2"):
        feed_distribution(table, [1.0, 1.0, 1.0], None)


def test_scale_blender_length_doubles_plug_residence_time():
    nx, v = 4, 0.03
    table = make_table(
        t=[0.0], x_edges=np.linspace(0, 0.33, nx + 1), y_edges=[-0.05, 0.05], vx_pos=v, vx_neg=0, vy_pos=0, vy_neg=0
    )
    long = scale_blender(table, length_factor=2.0)
    np.testing.assert_allclose(long.x_edges, 2 * table.x_edges)
    base = simulate(table, PbmConfig(duration_s=200.0), rtd_pulse_s=0.0).summary.mean_residence_time_s
    doubled = simulate(long, PbmConfig(duration_s=200.0), rtd_pulse_s=0.0).summary.mean_residence_time_s
    k = v / (0.33 / nx)
    assert base == pytest.approx(
        nx / k * gamma.cdf(200, nx + 1, scale=1 / k) / gamma.cdf(200, nx, scale=1 / k), rel=1e-9
    )
    assert doubled == pytest.approx(2 * base, rel=1e-6)
    wide = scale_blender(table, diameter_factor=1.5)
    np.testing.assert_allclose(wide.y_edges, 1.5 * table.y_edges)
    with pytest.raises(ConfigError, match="length_factor must be a finite number > 0, got -1"):
        scale_blender(table, length_factor=-1)


def test_regrid_is_conservative_and_particle_weighted():
    table = make_table(
        t=[0.0],
        x_edges=[0.0, 0.1, 0.2],
        y_edges=[-0.05, 0.05],
        vx_pos=np.array([[[1.0], [2.0]]]),
        vx_neg=0.0,
        vy_pos=0.0,
        vy_neg=0.0,
        count_A=np.array([[[1.0], [2.0]]]),
        count_B=np.array([[[0.0], [1.0]]]),
        n_samples=np.array([[[10], [30]]]),
    )
    coarse = regrid(table, nx=1)
    assert coarse.vx_pos[0, 0, 0] == pytest.approx((1 * 1.0 + 3 * 2.0) / 4)  # ratio of sums
    assert coarse.count_A.sum() == pytest.approx(3.0) and coarse.n_samples[0, 0, 0] == 40
    fine = regrid(table, nx=4, ny=2)
    assert fine.count_A.sum() + fine.count_B.sum() == pytest.approx(4.0)
    np.testing.assert_allclose(fine.vx_pos[0, :, 0], [1, 1, 2, 2])
    # Uniform velocities stay uniform on any grid; the same grid is the identity.
    uniform = make_table(
        t=[0.0, 5.0],
        x_edges=np.linspace(0, 0.33, 11),
        y_edges=np.linspace(-0.05, 0.05, 11),
        vx_pos=0.03,
        vx_neg=0.01,
        vy_pos=0.2,
        vy_neg=0.1,
    )
    for nx, ny in ((5, 5), (20, 7), (10, 10)):
        g = regrid(uniform, nx=nx, ny=ny)
        assert g.nx == nx and g.ny == ny
        np.testing.assert_allclose(g.vy_pos, 0.2)
    same = regrid(uniform)
    np.testing.assert_allclose(same.vx_pos, uniform.vx_pos)
    with pytest.raises(ConfigError, match="nx must be an integer >= 1, got 0"):
        regrid(uniform, nx=0)
    with pytest.raises(ConfigError, match="must span the table's extent"):
        regrid(uniform, x_edges=[0.0, 0.1, 0.2])


def test_regridded_table_feeds_the_solver_and_conserves():
    from pbm import synthetic_table

    table = regrid(synthetic_table(n_windows=6, seed=5), nx=15, ny=6)
    result = simulate(table, PbmConfig(duration_s=30.0), rtd_pulse_s=1.0)
    fed = result.fed_A + result.fed_B
    held = result.holdup_A + result.holdup_B + result.discharged_A + result.discharged_B
    assert np.max(np.abs(fed - held)) <= 1e-9 * fed[-1]
    assert result.rsd_by_slice_final.shape == (15,)
