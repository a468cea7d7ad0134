"""The hidden-phase estimator and its diagnostics (dem/phases/) against known answers: a
synthetic hidden-phase chain recovered, from one run or jointly from two, K = 1 equal to
the measured rates, the Chapman-Kolmogorov test telling Markovian from non-Markovian data,
and the settings refused by field. The data are tested in test_phases_data.py, the table
and the PBM in test_phases_tables.py.

Tolerances: the synthetic chain has 6000 particles and ~5e5 particle-steps, so a
compartment's rate carries ~3-10 % sampling noise, a rate averaged over the compartments
(weighted by the time spent there) ~1-2 %: the recovery is judged on those averages (5 %)
and on the RTD variance (2 %), which is what the PBM uses the model for.
"""

import dataclasses
import math

import numpy as np
import pytest
from scipy.linalg import expm

from coupling.errors import ConfigError
from coupling.phases import PhaseTransport, mobility
from dem import phases
from dem import rates as rate_fit
from dem.phases import PhaseEstimator, PhaseSettings
from tests.dem.phase_chains import (
    INTERVAL,
    NX,
    TEST_SETTINGS,
    dead_zone_model,
    exact_rtd_moments,
    fit_chain,
    inlet,
    joined,
    two_phase_model,
)

#: what other tests import from here
__all__ = ["NX", "dead_zone_model", "exact_rtd_moments", "inlet"]


def test_compiled_forward_backward_equals_numpy(synthetic_two_phase):
    model, _seq, data, _fit = synthetic_two_phase
    p = expm(model.generator() * INTERVAL)
    fast = phases.forward_backward(p, model.entry, data, 2, compiled=True)
    slow = phases.forward_backward(p, model.entry, data, 2, compiled=False)
    assert fast.log_likelihood == pytest.approx(slow.log_likelihood, rel=1e-12)
    np.testing.assert_allclose(fast.counts, slow.counts, atol=1e-8)
    np.testing.assert_allclose(fast.entry, slow.entry, atol=1e-9)
    # the expected transitions are the particle-steps
    assert fast.counts.sum() == pytest.approx(data.n_steps, rel=1e-12)


def test_two_phase_chain_is_recovered(synthetic_two_phase):
    truth, _seq, data, fit = synthetic_two_phase
    assert fit.converged
    got = fit.transport
    weights = fit.occupancy  # (K, NX, NY): time each phase spends in each compartment
    for h in range(2):
        w = weights[h] / weights[h].sum()
        for d in (0, 1):
            inside = w.copy()
            if d == 1:
                inside[0] = 0.0  # no backward move through the inlet wall
            inside /= inside.sum()
            assert (got.rates[h, d] * inside).sum() == pytest.approx((truth.rates[h, d] * inside).sum(), rel=0.05)
        g = 1 - h
        assert (got.switching[h, g] * w).sum() == pytest.approx(truth.switching[h, g, 0, 0], rel=0.05), h
    np.testing.assert_allclose(got.entry, truth.entry, atol=0.03)
    # ordered slowest first
    assert np.all(np.diff(mobility(got.rates, weights)) > 0)
    mean_t, var_t = exact_rtd_moments(truth, inlet())
    mean_f, var_f = exact_rtd_moments(got, inlet())
    assert mean_f == pytest.approx(mean_t, rel=0.02)
    assert var_f == pytest.approx(var_t, rel=0.02)
    # the truth's likelihood is no better than the fit's (EM found the maximum)
    assert fit.log_likelihood >= fit.score(data) - 1e-6 * data.n_steps
    assert phases.PhaseFit(truth, 0, 0, 0, 0, True).score(data) <= fit.log_likelihood + 1e-6 * data.n_steps


def test_a_stagnant_phase_is_recovered_where_the_particles_park():
    """A dead zone in the first and last slices: the stream (forward 3 /s, back 1 /s)
    parks there at 0.08 /s and leaves the zone at 0.05 /s, nowhere else. Fitted with a
    stagnant phase bounded at 0.2 /s: it makes no move, is entered where the truth parks
    (and hardly elsewhere), left at the truth's rate, and the RTD's mean and variance,
    which the long stays dominate, are the truth's."""
    truth = dead_zone_model()
    # 20 000 particles over 1200 s: ~1500 parking episodes, so the leaving rate carries
    # ~3 % sampling noise and the variance, as its inverse square, ~6 %
    sequences = phases.simulate_sequences(truth, inlet(), 20000, 3000, np.random.default_rng(11))
    fit = fit_chain(phases.prepare(sequences), 2, starts=1, tol=1e-7, stagnant_exit_max_per_s=0.2)
    got = fit.transport
    assert np.all(got.rates[0] == 0.0) and np.all(got.switching[0, 1] <= 0.2 + 1e-12)
    np.testing.assert_allclose(got.entry[:, 0], 0.0)
    parks = got.switching[1, 0, :, 0]
    assert parks[[0, NX - 1]] == pytest.approx([0.08, 0.08], rel=0.1)
    assert np.all(parks[1:-1] < 0.005)
    occupancy = fit.occupancy[0, :, 0]
    leaves = (got.switching[0, 1, :, 0] * occupancy).sum() / occupancy.sum()
    assert leaves == pytest.approx(0.05, rel=0.1)
    mean_t, var_t = exact_rtd_moments(truth, inlet())
    mean_f, var_f = exact_rtd_moments(got, inlet())
    assert mean_f == pytest.approx(mean_t, rel=0.03)
    assert var_f == pytest.approx(var_t, rel=0.15)
    with pytest.raises(ValueError, match="stagnant_exit_max"):
        fit_chain(phases.prepare(sequences), 1, stagnant_exit_max_per_s=0.2)


def test_one_phase_is_the_measured_chain(synthetic_two_phase):
    """K = 1 is dem.rates' maximum likelihood on the pooled moves."""
    _truth, _seq, data, _fit = synthetic_two_phase
    one = fit_chain(data, 1)
    measured = rate_fit.fit_rates(data.counts(), NX, 1, INTERVAL, min_observations=1)
    for d, key in enumerate(rate_fit.RATE_KEYS[:2]):
        got = one.transport.rates[0, d]
        want = np.nan_to_num(measured.rates()[key])
        np.testing.assert_allclose(got, want, rtol=2e-3, atol=1e-4)
    assert one.log_likelihood == pytest.approx(measured.log_likelihood, rel=1e-6)


def test_held_out_likelihood_prefers_the_true_number_of_phases(synthetic_two_phase):
    _truth, sequences, _data, _fit = synthetic_two_phase
    t_mid = sequences.snapshot_t[sequences.start].max() / 2
    train = phases.prepare(sequences, (-1.0, t_mid))
    test = phases.prepare(sequences, (t_mid, np.inf))
    one, two = fit_chain(train, 1), fit_chain(train, 2, starts=1)
    assert two.score(test) > one.score(test) + 100.0


def test_a_grid_whose_memory_three_phases_hold_keeps_three(synthetic_two_phase):
    # the truth has two phases: two more than three add nothing the held-out half can see
    _truth, sequences, _data, _fit = synthetic_two_phase
    k, gain = phases.choose_phases(sequences, 0.0)
    assert k == phases.PHASES and abs(gain) < phases.PHASE_GAIN_MIN / 4


def test_chapman_kolmogorov_tells_markovian_from_hidden_phases(synthetic_two_phase):
    truth, _seq, data, fit_two = synthetic_two_phase
    one_on_two = fit_chain(data, 1)
    assert not one_on_two.chapman_kolmogorov(data).passed
    assert fit_two.chapman_kolmogorov(data).passed
    # a chain that is Markovian on the compartments: its own K = 1 fit passes
    markov = PhaseTransport(
        truth.rates[:1] * 0 + np.array([2.0, 1.2, 0, 0])[None, :, None, None],
        np.zeros((1, 1, NX, 1)),
        np.ones((2, 1)),
        INTERVAL,
    )
    markov_data = phases.prepare(phases.simulate_sequences(markov, inlet(), 6000, 2400, np.random.default_rng(3)))
    test = fit_chain(markov_data, 1).chapman_kolmogorov(markov_data)
    assert test.passed and test.max_abs_error() < 0.02


def _ck_tallies_by_hand(data: phases.PhaseData, lag: int):
    """The Chapman-Kolmogorov test's observed fractions, cluster standard errors, starts
    and particles per start slice, counted start point by start point."""
    nx, s = data.nx, data.n_cells
    hits = np.zeros((data.n_particles, nx, nx + 1))
    for p in range(data.n_particles):
        seq = data.flat[data.offsets[p] : data.offsets[p + 1]]
        for t, c in enumerate(seq):
            if c >= s or data.start[p] + t + lag > data.last_dump:
                continue
            if t + lag < seq.size:
                end = seq[t + lag] // data.ny if seq[t + lag] < s else nx
            elif seq[-1] == s:
                end = nx
            else:  # lost before t + lag
                continue
            hits[p, c // data.ny, end] += 1
    n_p = hits.sum(axis=2)
    starts = n_p.sum(axis=0)
    fraction = hits.sum(axis=0) / np.maximum(starts, 1)[:, None]
    residual = hits - n_p[:, :, None] * fraction[None]
    error = np.sqrt((residual**2).sum(axis=0)) / np.maximum(starts, 1)[:, None]
    return fraction, error, starts, (n_p > 0).sum(axis=0)


def test_chapman_kolmogorov_tallies_equal_a_count_by_hand(synthetic_two_phase):
    """The compiled one-pass tallies against a count start point by start point, on
    particles lost before the end, discharged ones, and a run end that censors."""

    model, _seq, data, _fit = synthetic_two_phase
    rows = np.arange(0, data.n_particles, 12)
    pieces = [data.flat[data.offsets[p] : data.offsets[p + 1]] for p in rows]
    pieces = [seq[: max(1, seq.size - 9)] if i % 3 == 0 else seq for i, seq in enumerate(pieces)]  # lost
    lengths = np.array([seq.size for seq in pieces])
    obs = np.full((rows.size, lengths.max()), -1, np.int16)
    for i, seq in enumerate(pieces):
        obs[i, : seq.size] = seq
    subset = dataclasses.replace(
        data,
        obs=obs,
        lengths=lengths,
        group=data.group[rows],
        start=data.start[rows],
        last_dump=int(np.median(data.start[rows] + lengths)),  # many sequences outlast the run
        flat=np.concatenate(pieces).astype(np.int64),
        offsets=np.concatenate([[0], np.cumsum(lengths)]),
    )
    lags = (1, 7, 40)
    test = phases.chapman_kolmogorov(model, subset, lags)
    for n, lag in enumerate(lags):
        fraction, error, starts, particles = _ck_tallies_by_hand(subset, lag)
        assert starts.sum() > 1000
        np.testing.assert_array_equal(test.starts[n], starts)
        np.testing.assert_array_equal(test.particles[n], particles)
        np.testing.assert_allclose(test.observed[n], fraction, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(test.standard_error[n], error, rtol=1e-9, atol=1e-12)


def test_implied_timescales_and_generator_shape(synthetic_two_phase):
    _truth, _seq, _data, fit = synthetic_two_phase
    q = fit.generator()
    assert q.shape == (NX * 2 + 1, NX * 2 + 1)
    np.testing.assert_allclose(q.sum(axis=1), 0.0, atol=1e-12)
    times = fit.implied_timescales(3)
    assert times.size == 3 and np.all(np.diff(times) <= 0) and times[0] > 1.0


def test_the_bound_on_rate_x_interval_holds_and_is_checked(synthetic_two_phase):
    """The fast phase moves 7 /s x 0.1 s = 0.7 per interval: a bound of 0.3 holds every rate
    at 3 /s, and the true rates are recovered under the product's bound; a bound that is
    not > 0 is refused by name."""
    _model, _sequences, data, fit = synthetic_two_phase
    held = fit_chain(data, 2, starts=1, max_iterations=30, max_rate_x_interval=0.3)
    assert held.transport.rates.max() <= 0.3 / INTERVAL * (1 + 1e-9)
    assert fit.transport.rates.max() > 0.3 / INTERVAL  # the fast lane at 7 /s is not held back
    with pytest.raises(ValueError, match="max_rate_x_interval"):
        fit_chain(data, 2, max_rate_x_interval=0.0)


def test_a_finer_chain_fitted_to_coarser_observations_keeps_the_rtd(synthetic_two_phase):
    """The known two-phase chain on 10 slices, observed on 5 (the sub-slice hidden beside
    the phase): the 10-slice chain fitted to those observations has the truth's RTD mean
    and variance, and it is the data's grid it refines that the fit checks."""
    truth, sequences, _data, _fit = synthetic_two_phase
    coarse = phases.prepare(sequences, grid=(NX // 2, 1))
    fit = fit_chain(coarse, 2, starts=1, refine=2)
    assert (fit.transport.nx, fit.transport.ny) == (NX, 1)
    assert fit.transport.attrs["observed_grid"] == [NX // 2, 1]
    mean_t, var_t = exact_rtd_moments(truth, inlet())
    mean_f, var_f = exact_rtd_moments(fit.transport, inlet())
    assert mean_f == pytest.approx(mean_t, rel=0.03)
    assert var_f == pytest.approx(var_t, rel=0.05)
    with pytest.raises(ValueError, match="refine = 0"):
        fit_chain(coarse, 2, refine=0)
    with pytest.raises(ValueError, match="m_step 'lbfgs'"):
        fit_chain(coarse, 2, refine=2, m_step="lbfgs")
    with pytest.raises(ValueError, match="NY = 1"):
        fit_chain(
            phases.prepare(phases.simulate_sequences(two_phase_model(2), inlet(2), 50, 60, np.random.default_rng(1))),
            2,
            refine=2,
        )
    with pytest.raises(ValueError, match="base grid 10x1 is not refine = 1"):
        fit_chain(coarse, 2, base=fit.transport)


# ----------------------------------------------------------------------------- joint fits
def test_a_joint_fit_of_two_runs_is_the_fit_of_their_pooled_particles():
    """Two runs simulated from the known two-phase chain on the same dumps: the joint fit
    recovers the chain (RTD moments within 4 %: 2 x 2500 particles), and it is the fit of
    one record holding both runs' particles (the E-step over all of them, the M-step on
    their summed expectations), to rounding; a joint fit of one run is that run's fit, to
    the last bit."""
    truth = two_phase_model()
    rng = np.random.default_rng(21)
    sequences = [phases.simulate_sequences(truth, inlet(), 2500, 1600, rng) for _ in range(2)]
    runs = [phases.prepare(s) for s in sequences]
    settings = dataclasses.replace(TEST_SETTINGS, n_phases=2, starts=1)
    joint = PhaseEstimator(settings).fit(runs).fetch_model()
    assert joint.converged and joint.n_runs == 2 and joint.transport.attrs["n_runs"] == 2
    assert joint.n_particles == sum(r.n_particles for r in runs) and joint.n_steps == sum(r.n_steps for r in runs)
    mean_t, var_t = exact_rtd_moments(truth, inlet())
    mean_f, var_f = exact_rtd_moments(joint.transport, inlet())
    assert mean_f == pytest.approx(mean_t, rel=0.04) and var_f == pytest.approx(var_t, rel=0.04)
    np.testing.assert_allclose(joint.transport.entry, truth.entry, atol=0.05)
    assert joint.score(runs) == pytest.approx(joint.score(runs[0]) + joint.score(runs[1]), rel=1e-12)
    pooled = PhaseEstimator(settings).fit(phases.prepare(joined(*sequences))).fetch_model()
    assert pooled.iterations == joint.iterations
    assert joint.log_likelihood == pytest.approx(pooled.log_likelihood, rel=1e-10)
    np.testing.assert_allclose(joint.transport.rates, pooled.transport.rates, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(joint.transport.switching, pooled.transport.switching, rtol=1e-6, atol=1e-9)
    alone = PhaseEstimator(settings).fit(runs[0]).fetch_model()
    listed = PhaseEstimator(settings).fit([runs[0]]).fetch_model()
    assert listed.log_likelihood == alone.log_likelihood and listed.iterations == alone.iterations
    for name in ("rates", "switching", "entry"):
        np.testing.assert_array_equal(getattr(listed.transport, name), getattr(alone.transport, name))
    assert listed.transport.attrs == alone.transport.attrs and "n_runs" not in alone.transport.attrs
    # the CK test pools the runs' start points
    ck = joint.chapman_kolmogorov(runs, (10,))
    parts = [joint.chapman_kolmogorov(run, (10,)) for run in runs]
    np.testing.assert_array_equal(ck.starts, parts[0].starts + parts[1].starts)


def test_a_joint_fit_needs_one_grid_and_one_interval():
    sequences = phases.simulate_sequences(two_phase_model(), inlet(), 200, 200, np.random.default_rng(2))
    fine = phases.prepare(sequences)
    estimator = PhaseEstimator(PhaseSettings(n_phases=1))
    with pytest.raises(ConfigError, match=r"run 1 is on 5x1 observed every 0.1 s, run 0 on 10x1"):
        estimator.fit([fine, phases.prepare(sequences, grid=(NX // 2, 1))])
    with pytest.raises(ConfigError, match=r"run 1 is on 10x1 observed every 0.2 s"):
        estimator.fit([fine, phases.prepare(sequences, lag=2)])
    with pytest.raises(ConfigError, match="no run to fit"):
        estimator.fit([])
    with pytest.raises(ConfigError, match="run 0 is a CompartmentSequences"):
        estimator.fit([sequences])
    with pytest.raises(ConfigError, match="before fit"):
        PhaseEstimator().fetch_model()


# ----------------------------------------------------------------------------- settings
@pytest.mark.parametrize(
    "field, value, valid",
    [
        ("n_phases", 0, "a whole number >= 1"),
        ("n_phases", 2.0, "a whole number >= 1"),
        ("starts", 0, "a whole number >= 1"),
        ("max_iterations", -3, "a whole number >= 1"),
        ("tol", 0.0, "finite and > 0"),
        ("tol", -1e-5, "finite and > 0"),
        ("max_rate_x_interval", math.inf, "finite and > 0"),
        ("lag_s", 0, "finite and > 0"),
        ("m_step", "newton", "one of em, lbfgs"),
        ("refine", 0, "a whole number >= 1"),
        ("stagnant_exit_max_per_s", -0.1, "finite and > 0, or None"),
        ("zone_residences", math.nan, "finite and > 0, or None"),
    ],
)
def test_settings_are_refused_by_field_with_the_valid_range(field, value, valid):
    with pytest.raises(ConfigError) as refused:
        PhaseSettings(**{field: value})
    assert f"PhaseSettings.{field} = {value!r}: expected" in str(refused.value) and valid in str(refused.value)
    with pytest.raises(ConfigError, match=f"PhaseSettings.{field}"):  # a variant is checked as well
        dataclasses.replace(PhaseSettings(), **{field: value})


def test_settings_that_only_fail_together_are_refused_and_the_defaults_are_the_products():
    with pytest.raises(ConfigError, match="stagnant_exit_max_per_s = 0.2 with n_phases 1"):
        PhaseSettings(n_phases=1, stagnant_exit_max_per_s=0.2)
    with pytest.raises(ConfigError, match="refine = 2: expected 1 with m_step 'lbfgs'"):
        PhaseSettings(refine=2, m_step="lbfgs")
    with pytest.raises(ConfigError, match="expected a dem.phases.PhaseSettings"):
        PhaseEstimator({"n_phases": 2})
    product = PhaseSettings()
    assert (product.n_phases, product.tol, product.lag_s, product.max_rate_x_interval) == (
        phases.PHASES,
        phases.PHASE_TOL,
        phases.PHASE_LAG_S,
        phases.PHASE_MAX_RATE_X_INTERVAL,
    )
    assert (product.starts, product.zone_residences, product.stagnant_exit_max_per_s) == (2, 1.0, None)
    assert product.lag_dumps(0.1) == 4 and product.lag_dumps(1.0) == 1
    assert PhaseSettings(n_phases=4, stagnant_exit_max_per_s=0.1).moving_phases == 3
