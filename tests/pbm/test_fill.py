"""The fill law (pbm.fill): identity at the reference fill, the bulk against scipy's BDF on
the full nonlinear system, conservation, fits that recover known exponents, and refusals."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.linalg import expm

from coupling.errors import ConfigError, TableError
from coupling.tables import read_table
from pbm.config import PbmConfig
from pbm.fill import (
    FillLaw,
    FillSamples,
    config_schedule,
    fill_reference,
    fill_samples,
    fit_fill_law,
    linearised,
)
from pbm.frequency import sinusoid_response, stationary_system, system_response
from pbm.model import feed_distribution
from pbm.simulate import feed_factors, simulate
from workflows.shipped import REDUCED_RUN

FEED = 600.0


@pytest.fixture(scope="module")
def shipped():
    return read_table(REDUCED_RUN)


def _config(table, rates="measured", **kw) -> PbmConfig:
    settings = {"feed_rate_a_per_s": FEED, "feed_rate_b_per_s": FEED, "duration_s": 120.0, **kw}
    return PbmConfig(rates=rates, rate_law="fill", **settings)


@pytest.mark.parametrize("rates", ["velocity", "measured", "phases"])
def test_law_is_the_identity_at_the_reference_fill(shipped, rates):
    ref = fill_reference(shipped, rates)
    values = ref.values(np.ones((1, shipped.nx, 2)))
    np.testing.assert_allclose(values[0], ref.schedule.vals[0], rtol=1e-12, atol=1e-12)
    # and a factor moves only the axial moves of its slice, keeping the columns' balance
    factors = np.ones((1, shipped.nx, 2))
    factors[0, 3, 0] = 2.0
    g = ref.schedule.dense(0)
    g2 = type(ref.schedule)(ref.schedule.t, ref.schedule.rows, ref.schedule.cols, ref.values(factors), ref.schedule.m)
    changed = np.argwhere(~np.isclose(g2.dense(0), g))
    n = ref.n_populations
    assert changed.size > 0
    assert np.all(ref.slice_of[changed[:, 1]] == 3)
    np.testing.assert_allclose(g2.dense(0)[: n + 1, :n].sum(axis=0), 0.0, atol=1e-9)


def test_bulk_and_composition_against_bdf_on_the_nonlinear_system(shipped):
    """A and B marched on the law's schedule against scipy's BDF on the full nonlinear
    system (each species moved by rates that follow the total), from empty to steady."""
    law = FillLaw(np.tile([1.5, 0.5], (shipped.nx, 1)), "given", {})
    config = _config(shipped, fill_exponents=law.beta.tolist(), output_interval_s=5.0)
    result = simulate(shipped, config)
    ref = fill_reference(shipped, "measured")
    feed = feed_distribution(shipped, config.feed_weights_a, config.feed_weights_b, "measured")
    n = ref.n_populations

    def rhs(_t, y):
        z = y.reshape(2, n)
        fill = np.bincount(ref.slice_of, z.sum(axis=0), shipped.nx)
        g = type(ref.schedule)(
            ref.schedule.t,
            ref.schedule.rows,
            ref.schedule.cols,
            ref.values(law.factors(fill, ref.fill)[None]),
            ref.schedule.m,
        ).dense(0)[:n, :n]
        return (g @ z.T + feed * FEED).T.ravel()

    sol = solve_ivp(rhs, (0.0, 120.0), np.zeros(2 * n), method="BDF", t_eval=result.times, rtol=1e-9, atol=1e-9)
    assert sol.success
    held = sol.y.reshape(2, n, -1).sum(axis=1)  # (2, T)
    np.testing.assert_allclose(result.holdup_A, held[0], rtol=2e-3, atol=0.5)
    np.testing.assert_allclose(result.holdup_B, held[1], rtol=2e-3, atol=0.5)
    # conservation: what came in is held or gone, to rounding
    balance = (
        result.fed_A + result.fed_B - result.discharged_A - result.discharged_B - result.holdup_A - result.holdup_B
    )
    assert np.abs(balance).max() <= 1e-9 * (result.fed_A[-1] + result.fed_B[-1])
    assert result.summary.rate_law == "fill" and result.summary.fill_law_form == "given"


def test_more_feed_holds_less_than_proportionally_more(shipped):
    """With forward exponents > 0 doubling the feed raises the hold-up by less than 2x;
    with none (the linear PBM under its steady rates) by 2x."""
    held = {}
    for beta in (0.0, 1.5):
        exps = np.tile([beta, 0.0], (shipped.nx, 1)).tolist()
        for f in (1.0, 2.0):
            cfg = _config(shipped, fill_exponents=exps, duration_s=min(250.0, shipped.t_end)).model_copy(
                update={"feed_rate_a_per_s": FEED * f, "feed_rate_b_per_s": FEED * f}
            )
            held[beta, f] = simulate(shipped, cfg).summary.holdup_final
    assert held[0.0, 2.0] / held[0.0, 1.0] == pytest.approx(2.0, rel=1e-3)
    assert 1.05 < held[1.5, 2.0] / held[1.5, 1.0] < 1.6


def _synthetic_samples(beta, fills, intercept, windows=40, seed=0, noise=0.0):
    """Runs whose slice rates follow exp(intercept) * fill^beta exactly (plus log noise)."""
    rng = np.random.default_rng(seed)
    out = []
    for level in fills:
        ramp = np.minimum(1.0, (np.arange(windows) + 1) / 10.0)[:, None] * level
        fill = np.broadcast_to(ramp, (windows, beta.shape[0])).copy()
        rates = np.exp(intercept[None] + beta[None] * np.log(fill)[..., None])
        rates *= np.exp(noise * rng.standard_normal(rates.shape))
        out.append(
            FillSamples(fill, rates, fill[..., None] * rates, fill[..., None] + 0 * rates, np.arange(windows) >= 12)
        )
    return out


def test_fits_recover_known_exponents():
    nx = 4
    beta = np.array([[1.0, 0.2], [1.5, 0.0], [2.0, 0.5], [4.0, 1.0]])
    intercept = np.zeros((nx, 2))
    # several runs: the steady points
    law = fit_fill_law(_synthetic_samples(beta, [100.0, 150.0, 200.0], intercept))
    np.testing.assert_allclose(law.beta, beta, atol=1e-9)
    assert law.form == "per-slice" and set(law.scores) == {"per-slice", "per-direction", "none"}
    # one run: its filling transient, the forward rates only (the backward stay fixed)
    law = fit_fill_law(_synthetic_samples(beta, [150.0], intercept))
    np.testing.assert_allclose(law.beta[:, 0], beta[:, 0], atol=1e-9)
    assert np.all(law.beta[:, 1] == 0)
    # slices that differ, through noise: the held-out error keeps an exponent per slice
    for seed in range(5):
        law = fit_fill_law(_synthetic_samples(beta, [100.0, 130.0, 160.0, 200.0], intercept, seed=seed, noise=0.05))
        assert law.form == "per-slice"
        assert law.scores["per-slice"] < law.scores["per-direction"] < law.scores["none"]
        np.testing.assert_allclose(law.beta, beta, atol=0.15)


def test_refusals(shipped):
    with pytest.raises(ValueError, match="finite and >= 0"):
        PbmConfig(fill_exponents=[[1.0, -1.0]])
    with pytest.raises(ValueError, match="forward, backward"):
        PbmConfig(fill_exponents=[[1.0]])
    cfg = _config(shipped, fill_exponents=[[1.0, 0.0]] * 3)
    with pytest.raises(ConfigError, match="NX = 10"):
        simulate(shipped, cfg)
    filling = shipped.replace(
        t=shipped.t[:4],
        **{
            name: getattr(shipped, name)[:4]
            for name in ("vx_pos", "vx_neg", "vy_pos", "vy_neg", "count_A", "count_B", "n_samples")
        },
        **{name: getattr(shipped, name)[:4] for name in ("rate_x_pos", "rate_x_neg", "rate_y_pos", "rate_y_neg")},
    )
    with pytest.raises(TableError, match="never becomes steady"):
        fill_samples(filling, "measured")
    table_law = PbmConfig(rates="measured")
    assert config_schedule(shipped, table_law, None, np.ones((1, 2)), 10.0) == (None, None)


def test_linearised_response_matches_the_nonlinear_run_under_small_noise(shipped):
    """The frequency domain's linearisation against the nonlinear PBM itself: from the
    law's steady state, 1 % feeder noise each second; the outlet C_A's deviation per
    second from the nonlinear run and from the linearised system driven by the same noise."""
    beta = np.tile([1.5, 0.3], (shipped.nx, 1)).tolist()
    cfg = _config(shipped, fill_exponents=beta, duration_s=40.0, noise_sigma=0.01, output_interval_s=1.0)
    feed = feed_distribution(shipped, None, None, "measured")
    rates = np.array([FEED, FEED])
    lin = linearised(fill_reference(shipped, "measured"), FillLaw(np.array(beta), "given", {}), feed, rates)
    counts = lin.species.reshape(2, shipped.nx, shipped.ny)
    run = simulate(shipped, cfg, initial_counts=counts)
    # the deviation system with the dq integrals as two more states, stepped 1 s at a time
    n2 = lin.generator.shape[0]
    m = np.zeros((n2 + 4, n2 + 4))
    m[:n2, :n2] = lin.generator
    m[:n2, n2 : n2 + 2] = lin.feed
    m[n2 + 2 :, :n2] = lin.outlet
    step = expm(m)
    factors = feed_factors(cfg, 40)[:, 0]
    x = np.zeros(n2 + 4)
    dq = []
    for k in range(40):
        x[n2 : n2 + 2] = rates * (factors[k] - 1.0)
        x[n2 + 2 :] = 0.0
        x = step @ x
        dq.append(x[n2 + 2 :].copy())
    dq = np.array(dq)
    q0 = rates  # at steady state all that is fed leaves
    linear_ca = (q0[0] + dq[:, 0]) / (q0.sum() + dq.sum(axis=1)) - 0.5
    nonlinear_ca = run.C_A - 0.5
    assert np.abs(nonlinear_ca).max() > 1e-4  # the noise does move the outlet
    np.testing.assert_allclose(nonlinear_ca, linear_ca, atol=0.03 * np.abs(nonlinear_ca).max())


def test_frequency_response_under_the_fill_law(shipped):
    """H(0) = 1 for either feeder (what a feeder adds leaves, and the other species'
    outflow returns to its feed); the filter still damps fast noise; sinusoids in the
    time domain agree with the transfer function of the linearised system."""
    beta = np.tile([1.5, 0.3], (shipped.nx, 1)).tolist()
    cfg = _config(shipped, fill_exponents=beta)
    system = stationary_system(shipped, cfg)
    assert system.generator.shape[0] == 2 * shipped.nx * shipped.ny
    for feeder in ("A", "B"):
        h = system_response(system, np.array([0.0, 0.01, 0.2]), feeder)
        assert h[0] == pytest.approx(1.0, abs=1e-8)
        assert abs(h[2]) < 0.5
    np.testing.assert_allclose(
        sinusoid_response(system, np.array([0.05]), "A"), system_response(system, np.array([0.05]), "A"), atol=1e-6
    )
    with pytest.raises(ConfigError, match="both feed rates > 0"):
        stationary_system(shipped, cfg.model_copy(update={"feed_rate_b_per_s": 0.0}))


@pytest.mark.parametrize("rates", ["measured", "phases"])
def test_bulk_jacobian_is_the_derivative_of_the_flows(shipped, rates):
    """The analytic Jacobian (the rates' change with each slice's fill included) against
    central differences, at a fill away from the reference's; the flows in numpy and
    compiled are the same, a slice emptied below the floor included."""
    from pbm.fill import _bulk_rhs_and_jacobian

    ref = fill_reference(shipped, rates)
    law = FillLaw(np.tile([1.5, 0.7], (shipped.nx, 1)), "given", {})
    rhs, jac = _bulk_rhs_and_jacobian(ref, law, compiled=False)
    compiled, _ = _bulk_rhs_and_jacobian(ref, law, compiled=True)
    y = np.random.default_rng(3).uniform(0.5, 30.0, ref.n_populations)
    h = 1e-5
    numeric = np.stack([(rhs(y + h * e) - rhs(y - h * e)) / (2 * h) for e in np.eye(y.size)], axis=1)
    np.testing.assert_allclose(jac(y), numeric, rtol=1e-5, atol=1e-7)
    emptied = np.where(ref.slice_of == 0, 0.0, y)
    for state in (y, emptied):
        np.testing.assert_allclose(compiled(state), rhs(state), rtol=1e-12, atol=1e-12 * np.abs(rhs(state)).max())


def test_pooled_rtd_takes_the_runs_own_schedule(shipped):
    """The pooled RTD on the schedule simulate marched on is the one it builds itself (the
    bulk solved once, not twice), and under table rates there is none to hand over."""
    from pbm.rtd import pooled_rtd

    cfg = _config(shipped, fill_exponents=np.tile([1.0, 0.0], (shipped.nx, 1)).tolist())
    result = simulate(shipped, cfg)
    assert result.schedule is not None and result.schedule.n_windows > 1
    window, horizon = (40.0, 50.0), 60.0
    handed = pooled_rtd(shipped, cfg, window, horizon, schedule=result.schedule)
    built = pooled_rtd(shipped, cfg, window, horizon)
    assert handed.mean_s == built.mean_s and handed.variance_s2 == built.variance_s2
    assert simulate(shipped, cfg.model_copy(update={"rate_law": "table"})).schedule is None


@pytest.mark.parametrize("rates", ["velocity", "measured", "phases"])
def test_bulk_jacobian_lies_in_the_band_lsoda_is_told(shipped, rates):
    """LSODA factorises only the band: every entry of the Jacobian must lie in it, and the
    packed storage must put each where LSODA reads it."""
    from pbm.fill import _bulk_rhs_and_jacobian, _packed, bulk_bandwidth

    rng = np.random.default_rng(3)
    ref = fill_reference(shipped, rates)
    law = FillLaw(rng.uniform(0.0, 3.0, (shipped.nx, 2)), "given", {})
    _, jac = _bulk_rhs_and_jacobian(ref, law, compiled=False)
    j = jac(rng.uniform(1.0, 50.0, ref.n_populations))
    band = bulk_bandwidth(ref)
    rows, cols = np.nonzero(j)
    assert np.abs(rows - cols).max() <= band < ref.n_populations - 1
    packed = _packed(j, band)
    inside = np.abs(rows - cols) <= band
    np.testing.assert_array_equal(packed[band + rows[inside] - cols[inside], cols[inside]], j[rows, cols])
