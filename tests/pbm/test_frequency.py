"""Transfer functions and variance reduction ratios (pbm.frequency) against a chain of n
equal tanks in series, whose transfer function is (k / (s + k))^n exactly."""

import math
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import gamma

from coupling.errors import ConfigError
from coupling.tables import make_table
from pbm.frequency import (
    noise_frequencies,
    noise_spectrum,
    sinusoid_response,
    stationary_system,
    system_response,
    transfer_function,
    transfer_function_from_rtd,
    vrr_noise,
    vrr_sinusoid,
    vrr_spectrum,
)

LENGTH_M = 0.3
FREQS = np.array([0.0, 0.005, 0.02, 0.1, 0.3])


def chain(n_tanks, rates_per_s, ny=1):
    """n tanks in series, one window per entry of ``rates_per_s`` (5 s apart): in "velocity"
    mode the forward rate is vx_pos / dx, so vx_pos = k dx; nothing moves back or across."""
    rates = np.atleast_1d(np.asarray(rates_per_s, dtype=float))
    dx = LENGTH_M / n_tanks
    return make_table(
        t=5.0 * np.arange(rates.size),
        x_edges=np.linspace(0, LENGTH_M, n_tanks + 1),
        y_edges=np.linspace(-0.05, 0.05, ny + 1),
        vx_pos=(rates * dx)[:, None, None],
        vx_neg=0.0,
        vy_pos=0.0,
        vy_neg=0.0,
    )


def tanks(freqs, n, k):
    return (k / (2j * np.pi * np.asarray(freqs) + k)) ** n


def test_chain_transfer_function_magnitude_and_phase_exact():
    for n, k in ((1, 0.5), (5, 1.0), (10, 2.0)):
        h = transfer_function(chain(n, k), None, FREQS)
        exact = tanks(FREQS, n, k)
        np.testing.assert_allclose(np.abs(h), np.abs(exact), rtol=1e-10)
        np.testing.assert_allclose(np.unwrap(np.angle(h)), np.unwrap(np.angle(exact)), atol=1e-10)
        assert h[0] == pytest.approx(1.0, abs=1e-12)


def test_both_feeders_and_transverse_mixing_keep_throughput_one():
    # Faster axial flow on the y > 0 side: with uniform axial rates the axial progress
    # would not depend on y, and A and B would leave alike whatever the transverse flow.
    table = make_table(
        t=[0.0],
        x_edges=np.linspace(0, LENGTH_M, 5),
        y_edges=np.linspace(-0.05, 0.05, 4),
        vx_pos=np.array([0.02, 0.03, 0.05]),
        vx_neg=0.01,
        vy_pos=0.02,
        vy_neg=0.05,
    )
    for feeder in ("A", "B"):
        assert transfer_function(table, None, 0.0, feeder=feeder) == pytest.approx(1.0, abs=1e-12)
    ha, hb = (transfer_function(table, None, [0.05], feeder=f) for f in ("A", "B"))
    assert abs(ha[0] - hb[0]) > 1e-3


def test_mean_generator_of_windows_and_single_window():
    table = chain(4, [1.0, 3.0, 2.0])
    np.testing.assert_allclose(transfer_function(table, None, FREQS), tanks(FREQS, 4, 2.0), rtol=1e-10)
    np.testing.assert_allclose(transfer_function(table, None, FREQS, window=1), tanks(FREQS, 4, 3.0), rtol=1e-10)
    # Windows starting at or after 5 s: rates 3 and 2, mean 2.5.
    np.testing.assert_allclose(transfer_function(table, None, FREQS, t_start_s=5.0), tanks(FREQS, 4, 2.5), rtol=1e-10)


def test_vrr_of_sinusoid_is_inverse_squared_gain():
    h = transfer_function(chain(5, 1.0), None, FREQS)
    np.testing.assert_allclose(vrr_sinusoid(h), (1 + (2 * np.pi * FREQS / 1.0) ** 2) ** 5, rtol=1e-10)
    assert vrr_sinusoid(0.0) == np.inf


@pytest.mark.parametrize("tau", [0.0, 3.0])
def test_vrr_of_band_limited_noise_through_one_tank(tau):
    # |H|^2 = 1 / (1 + b w^2), S = 1 / (1 + a w^2), a = tau^2, b = 1/k^2, df = dw / 2 pi:
    # int S |H|^2 dw = (sqrt(a) atan(sqrt(a) W) - sqrt(b) atan(sqrt(b) W)) / (a - b).
    k, f_max = 0.2, 0.5
    w = 2 * np.pi * f_max
    a, b = tau**2, 1 / k**2
    filtered = (math.sqrt(a) * math.atan(math.sqrt(a) * w) - math.sqrt(b) * math.atan(math.sqrt(b) * w)) / (a - b)
    unfiltered = math.atan(tau * w) / tau if tau > 0 else w
    vrr = vrr_noise(chain(1, k), None, tau, f_max)
    assert vrr == pytest.approx(unfiltered / filtered, rel=1e-4)
    # The default band is the Nyquist frequency of the feeder's noise interval (1 s here).
    assert vrr_noise(chain(1, k), None, tau) == pytest.approx(vrr, rel=1e-12)


def test_rtd_route_on_sampled_erlang_matches_generator_route():
    n, k = 5, 1.0
    h = transfer_function(chain(n, k), None, FREQS)
    t = np.arange(0.005, 200.0, 0.01)  # cell centres of 0.01-s cells over [0, 200] s
    e = gamma.pdf(t, n, scale=1 / k)
    h_rtd = transfer_function_from_rtd(t, e, FREQS)
    assert np.all(np.abs(h_rtd - h) <= 0.01 * np.abs(h))


def test_rtd_route_on_histogram_undoes_the_binning():
    # A 1-s histogram of the Erlang (bin means, as the DEM's pooled RTD is).
    n, k = 5, 0.25
    edges = np.arange(0.0, 301.0, 1.0)
    e = np.diff(gamma.cdf(edges, n, scale=1 / k))
    f = np.array([0.0, 0.005, 0.02, 0.1, 0.3])
    h = transfer_function(chain(n, k), None, f)
    np.testing.assert_allclose(transfer_function_from_rtd(edges, e, f), h, rtol=0.01, atol=1e-6)
    # Read as point samples at the bin centres, the bins would attenuate like the box's sinc.
    centres = edges[:-1] + 0.5
    np.testing.assert_allclose(transfer_function_from_rtd(centres, e, f), h * np.sinc(f), rtol=0.01, atol=1e-6)
    with pytest.raises(ConfigError, match="0.6 Hz.*Nyquist frequency 0.5 Hz"):
        transfer_function_from_rtd(edges, e, [0.6])


def test_vrr_spectrum_from_rtd_matches_generator_vrr():
    n, k = 3, 0.5
    freqs = noise_frequencies(0.5, 801)
    t = np.arange(0.005, 150.0, 0.01)
    h_rtd = transfer_function_from_rtd(t, gamma.pdf(t, n, scale=1 / k), freqs)
    assert vrr_spectrum(freqs, h_rtd, noise_spectrum(freqs, 2.0)) == pytest.approx(
        vrr_noise(chain(n, k), None, 2.0, 0.5, n_frequencies=801), rel=0.01
    )


def test_time_domain_check_matches_transfer_function():
    table = make_table(
        t=[0.0],
        x_edges=np.linspace(0, LENGTH_M, 6),
        y_edges=np.linspace(-0.05, 0.05, 3),
        vx_pos=0.04,
        vx_neg=0.015,
        vy_pos=0.03,
        vy_neg=0.01,
    )
    system = stationary_system(table)
    f = np.array([0.01, 0.05, 0.2])
    for feeder in ("A", "B"):
        h = system_response(system, f, feeder)
        measured = sinusoid_response(system, f, feeder)
        assert np.abs(measured - h).max() / np.abs(h).min() < 0.02
    chain_system = stationary_system(chain(6, 1.5))
    np.testing.assert_allclose(sinusoid_response(chain_system, f), tanks(f, 6, 1.5), rtol=0.02)


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda t: transfer_function(t, None, [0.1, -0.2]), "-0.2"),
        (lambda t: transfer_function(t, None, [np.nan]), "nan"),
        (lambda t: transfer_function(t, None, 0.1, feeder="C"), "'C'.*'A', 'B'"),
        (lambda t: transfer_function(t, None, 0.1, window=3), "0..1.*3"),
        (lambda t: transfer_function(t, None, 0.1, t_start_s=7.0), "7.0 s.*5.0 s"),
        (lambda t: vrr_noise(t, None, -1.0), "-1.0"),
        (lambda t: vrr_noise(t, None, 0.0, f_max_hz=0.0), "0.0"),
        (lambda t: sinusoid_response(stationary_system(t), [0.0, 0.1]), "> 0 Hz"),
        (lambda t: transfer_function_from_rtd([0.0, 1.0, 2.0], [1.0], 0.1), "3 entries.*2 bin edges"),
    ],
)
def test_bad_inputs_raise_config_error_naming_the_value(call, match):
    with pytest.raises(ConfigError, match=match):
        call(chain(3, [1.0, 2.0]))


def test_sampled_ca_spread_matches_the_time_domain_ensemble():
    # three tanks of 0.15 /s fed on both halves of one slice: the ensemble's outlet C_A
    # spread, both feeders redrawn every second, against the frequency domain
    from pbm.config import PbmConfig
    from pbm.ensemble import noise_ensemble
    from pbm.frequency import sampled_ca_sd

    table = chain(3, [0.15] * 40, ny=2)
    config = PbmConfig(feed_rate_a_per_s=30.0, feed_rate_b_per_s=10.0)
    predicted = sampled_ca_sd(stationary_system(table, config), [30.0, 10.0], 0.1, 1.0, 1.0)
    ens = noise_ensemble(table, config, sigma=0.1, members=3000)
    after = ens.times >= 100.0
    measured = np.sqrt(np.mean(np.var(ens.C_A_members[:, after], axis=0, ddof=1)))
    # 3000 members: the SD of an SD estimate is ~1.3 %, less after averaging over time
    assert measured == pytest.approx(predicted, rel=0.03)
    with pytest.raises(ConfigError, match="feed_rates"):
        sampled_ca_sd(stationary_system(table, config), [30.0], 0.1, 1.0, 1.0)


def test_quasi_triangular_solves_equal_a_dense_solve_per_frequency():
    """The back substitution through a real Schur form's 1 x 1 and 2 x 2 blocks
    against numpy's dense solve of (i w I - T) x = rhs at every frequency: a generator
    with rotation (complex pairs, so 2 x 2 blocks) and the shipped reduced table's."""
    from scipy.linalg import schur

    from coupling.tables import read_table
    from pbm.frequency import (
        _quasi_triangular_eigenvalues,
        _responses,
        _responses_reference,
        stationary_system,
    )

    rng = np.random.default_rng(5)
    rotating = rng.normal(size=(40, 40)) - 8.0 * np.eye(40)
    shipped = stationary_system(
        read_table(Path(__file__).resolve().parents[2] / "workflows" / "reference" / "dem-17ea4c9cc143cd3e.h5"),
        None,
        t_start_s=45.0,
    ).generator
    omegas = 2 * np.pi * np.concatenate([[0.0], np.geomspace(1e-4, 0.5, 60)])
    for g in (rotating, shipped):
        t, u = schur(g, output="real")
        rhs, left = u.T @ rng.random(g.shape[0]), rng.random(g.shape[0]) @ u
        got, want = _responses(t, rhs, left, omegas), _responses_reference(t, rhs, left, omegas)
        np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-13 * np.abs(want).max())
        np.testing.assert_allclose(
            np.sort_complex(_quasi_triangular_eigenvalues(t)), np.sort_complex(np.linalg.eigvals(g)), atol=1e-8
        )
    assert np.count_nonzero(np.diag(schur(rotating, output="real")[0], -1)) > 5  # 2 x 2 blocks were met
