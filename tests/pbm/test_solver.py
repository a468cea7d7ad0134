"""The PBM against exact limits, conservation and the independent BDF integration.

Tolerances are stated per check: the exact propagation is accurate to ~1e-13 relative,
so analytic checks use 1e-9; the BDF path runs at rtol 1e-6.
"""

import math

import numpy as np
import pytest
from scipy.linalg import expm
from scipy.stats import gamma

from coupling.tables import make_table
from pbm import PbmConfig, simulate, synthetic_table
from pbm.model import generator_matrix, transfer_rates
from pbm.solver import expm_taylor18


def tanks_in_series(nx=5, ny=1, v=0.02, length=0.33, windows=1):
    """Uniform forward flow only: NX ideal tanks in series, rate k = v / dx each."""
    return make_table(
        t=5.0 * np.arange(windows),
        x_edges=np.linspace(0, length, nx + 1),
        y_edges=np.linspace(-0.05, 0.05, ny + 1),
        vx_pos=v,
        vx_neg=0.0,
        vy_pos=0.0,
        vy_neg=0.0,
        window_s=5.0,
    )


def test_expm_matches_scipy_on_a_generator():
    table = synthetic_table(n_windows=3)
    g = generator_matrix(table, 2)
    for h in (0.0, 0.01, 1.0, 7.3, 60.0):
        np.testing.assert_allclose(expm_taylor18(g * h), expm(g * h), rtol=0, atol=1e-12 * np.abs(expm(g * h)).max())


def test_dense_and_sparse_generators_agree():
    # The sparse builder sums duplicate entries, the dense one assigns: equal means none.
    from pbm.model import generator_sparse

    table = synthetic_table(nx=4, ny=3, n_windows=2)
    np.testing.assert_array_equal(generator_matrix(table, 1), generator_sparse(table, 1).toarray())


def test_tanks_in_series_rtd_is_erlang():
    nx, v, length = 5, 0.02, 0.33
    k = v / (length / nx)
    duration, pulse = 60.0, 3.0
    result = simulate(tanks_in_series(nx, v=v, length=length), PbmConfig(duration_s=duration), rtd_pulse_s=pulse)
    edges = np.arange(result.rtd_E.size + 1) * 1.0
    expected = np.diff(gamma.cdf(edges, nx, scale=1 / k))
    np.testing.assert_allclose(result.rtd_E, expected, rtol=1e-9, atol=1e-13)
    tau = duration - pulse
    recovered = gamma.cdf(tau, nx, scale=1 / k)
    mean = nx / k * gamma.cdf(tau, nx + 1, scale=1 / k) / recovered
    second = nx * (nx + 1) / k**2 * gamma.cdf(tau, nx + 2, scale=1 / k) / recovered
    s = result.summary
    assert s.rtd_recovered_fraction == pytest.approx(recovered, rel=1e-9)
    assert s.mean_residence_time_s == pytest.approx(mean, rel=1e-9)
    assert s.rtd_variance_s2 == pytest.approx(second - mean**2, rel=1e-8)
    # Hold-up fed at F from t = 0: F int_0^T survival = F [T (1 - G_N(T)) + N/k G_{N+1}(T)].
    held = 1990.0 * (duration * gamma.sf(duration, nx, scale=1 / k) + nx / k * gamma.cdf(duration, nx + 1, scale=1 / k))
    assert result.holdup_A[-1] + result.holdup_B[-1] == pytest.approx(held, rel=1e-9)


def test_radial_exchange_decays_at_discrete_laplacian_eigenvalues():
    ny, v, dy = 8, 0.1, 0.01
    rate = v / dy
    table = make_table(
        t=[0.0],
        x_edges=[0.0, 0.033],
        y_edges=dy * (np.arange(ny + 1) - ny / 2),
        vx_pos=0.0,
        vx_neg=0.0,
        vy_pos=v,
        vy_neg=v,
        window_s=5.0,
    )
    # The generator restricted to the compartments is the reflecting 1-D Laplacian.
    eig = np.sort(np.linalg.eigvals(generator_matrix(table, 0)[:ny, :ny]).real)
    expected = np.sort(-2 * rate * (1 - np.cos(np.pi * np.arange(ny) / ny)))
    np.testing.assert_allclose(eig, expected, atol=1e-9 * rate)
    # A cosine mode of A (and the complementary one of B) decays at its eigenvalue.
    q = 3
    mode = np.cos(np.pi * q * (np.arange(ny) + 0.5) / ny)
    initial = np.stack([100 + 50 * mode, 100 - 50 * mode])[:, None, :]
    config = PbmConfig(feed_rate_a_per_s=0.0, feed_rate_b_per_s=0.0, duration_s=0.5, output_interval_s=0.05)
    result = simulate(table, config, initial_counts=initial)
    lam = -2 * rate * (1 - np.cos(np.pi * q / ny))
    expected_a = 100 + 50 * np.exp(lam * result.times)[:, None] * mode[None, :]
    np.testing.assert_allclose(result.counts[:, 0, 0, :], expected_a, rtol=1e-10)
    assert np.all(result.outflow_A == 0) and np.all(result.holdup_A == pytest.approx(800.0, rel=1e-12))


def test_generator_reduces_to_paper_eq4_for_uniform_velocities():
    vf, vb, vr = 0.04, 0.01, 0.2
    table = make_table(
        t=[0.0],
        x_edges=np.linspace(0, 0.33, 6),
        y_edges=np.linspace(-0.05, 0.05, 6),
        vx_pos=vf,
        vx_neg=vb,
        vy_pos=vr,
        vy_neg=vr,
    )
    g = generator_matrix(table, 0)
    dx, dy = 0.066, 0.02
    rng = np.random.default_rng(1)
    n_vec = rng.random(25)
    dn = (g[:25, :25] @ n_vec).reshape(5, 5)
    f = n_vec.reshape(5, 5)
    i, j = 2, 2  # an interior compartment: eq. (4) term by term
    eq4 = (
        vf * (f[i - 1, j] - f[i, j]) / dx
        + vb * (f[i + 1, j] - f[i, j]) / dx
        + vr * (f[i, j + 1] + f[i, j - 1] - 2 * f[i, j]) / dy
    )
    assert dn[i, j] == pytest.approx(eq4, rel=1e-12)
    # Walls: no backward flux through the inlet, none through the side walls.
    rates = transfer_rates(table, 0)
    assert np.all(rates["backward"][0] == 0) and np.all(rates["up"][:, -1] == 0) and np.all(rates["down"][:, 0] == 0)
    # Every column of the compartment block sums to minus the outflow rate: conservation.
    col_sums = g[:25, :25].sum(axis=0).reshape(5, 5)
    np.testing.assert_allclose(col_sums[:-1], 0, atol=1e-12)
    np.testing.assert_allclose(col_sums[-1], -vf / dx, rtol=1e-12)


@pytest.mark.parametrize("method", ["expm", "bdf"])
def test_particles_conserved_with_time_varying_tables_and_noise(method):
    table = synthetic_table(nx=6, ny=4, n_windows=8, window_s=3.0, seed=7)
    config = PbmConfig(noise_sigma=0.3, noise_interval_s=0.7, output_interval_s=0.5, duration_s=26.0, method=method)
    result = simulate(table, config, rtd_pulse_s=4.3)
    fed = result.fed_A + result.fed_B
    balance = fed - (result.discharged_A + result.discharged_B) - (result.holdup_A + result.holdup_B)
    tol = 1e-9 if method == "expm" else 1e-6
    assert np.max(np.abs(balance)) <= tol * fed[-1]
    for species in "AB":
        per = (
            getattr(result, f"fed_{species}")
            - getattr(result, f"discharged_{species}")
            - getattr(result, f"holdup_{species}")
        )
        assert np.max(np.abs(per)) <= tol * fed[-1]
    # The noise really varied the feed: factors differ from 1.
    assert not np.allclose(np.diff(result.fed_A), np.diff(result.fed_A)[0])
    # Tracer: everything fed is either discharged or held; E integrates to the recovered part.
    assert np.sum(result.rtd_E) <= result.summary.rtd_recovered_fraction + 1e-9


def test_mirror_symmetric_blender_gives_C_A_one_half_at_all_times(rng):
    nx, ny, k = 4, 6, 5
    vx_pos = rng.uniform(0.02, 0.05, (k, nx, ny))
    vx_pos = 0.5 * (vx_pos + vx_pos[:, :, ::-1])
    vx_neg = rng.uniform(0.0, 0.02, (k, nx, ny))
    vx_neg = 0.5 * (vx_neg + vx_neg[:, :, ::-1])
    vy_pos = rng.uniform(0.05, 0.3, (k, nx, ny))
    vy_neg = vy_pos[:, :, ::-1]  # mirror image: j -> NY-1-j swaps the directions
    table = make_table(
        t=5.0 * np.arange(k),
        x_edges=np.linspace(0, 0.33, nx + 1),
        y_edges=np.linspace(-0.05, 0.05, ny + 1),
        vx_pos=vx_pos,
        vx_neg=vx_neg,
        vy_pos=vy_pos,
        vy_neg=vy_neg,
    )
    result = simulate(table, PbmConfig(duration_s=30.0))
    np.testing.assert_allclose(result.C_A, 0.5, atol=1e-12)


def test_equal_feeds_give_steady_C_A_one_half():
    table = synthetic_table(nx=5, ny=4, n_windows=1, seed=3)  # one window: constant velocities
    result = simulate(table, PbmConfig(duration_s=150.0))
    assert result.C_A[-1] == pytest.approx(0.5, abs=1e-6)
    assert result.summary.steady_C_A == pytest.approx(0.5, abs=1e-3)
    assert result.summary.steady_outflow_per_s == pytest.approx(1990.0, rel=1e-3)
    assert result.summary.steady_state_time_s is not None


def test_exact_and_bdf_agree():
    table = synthetic_table(nx=5, ny=4, n_windows=6, window_s=4.0, seed=11)
    config = PbmConfig(duration_s=24.0)
    exact = simulate(table, config, rtd_pulse_s=6.0)
    bdf = simulate(table, config.model_copy(update={"method": "bdf"}), rtd_pulse_s=6.0)
    for name in ("holdup_A", "holdup_B", "discharged_A", "discharged_B", "outflow_A", "outflow_B", "rtd_E"):
        a, b = getattr(exact, name), getattr(bdf, name)
        assert np.max(np.abs(a - b)) <= 1e-5 * np.max(np.abs(b)), name
    assert exact.summary.mean_residence_time_s == pytest.approx(bdf.summary.mean_residence_time_s, rel=1e-5)


def test_pulse_off_the_output_grid_and_beyond_table_end():
    # Pulse between outputs, duration past the table's end (last window kept).
    nx, v = 4, 0.03
    table = tanks_in_series(nx, v=v, windows=2)
    k = v / (0.33 / nx)
    result = simulate(table, PbmConfig(duration_s=37.0), rtd_pulse_s=2.25)
    edges = np.arange(result.rtd_E.size + 1) * 1.0
    np.testing.assert_allclose(result.rtd_E, np.diff(gamma.cdf(edges, nx, scale=1 / k)), rtol=1e-9, atol=1e-13)
    assert result.rtd_pulse_s == 2.25 and result.summary.rtd_pulse_rule == "given"
    assert math.isclose(result.times[-1], 37.0)
