"""The memory check on the shipped validation baseline: the phase model against the
memoryless chain on the DEM's own particles, and its out-of-sample RTD."""

import math

import pytest

from dem.phases import phases_per_kind
from workflows.analysis.memory import memory_check
from workflows.pipeline.results import load_results, pbm_config_for, rtd_pulse
from workflows.shipped import VALIDATION_DIR


@pytest.fixture(scope="module")
def baseline():
    results, config = load_results(VALIDATION_DIR / "dem-aa093a229dfd2ce4.h5")
    if results.sequences is None:
        pytest.fail("the shipped validation baseline carries no compartment sequences")
    return results, config


def test_the_phase_model_is_nearer_markov_than_the_memoryless_chain(baseline):
    results, config = baseline
    check = memory_check(results, pbm_config_for(config, results.table, rtd_pulse(results.summary)))
    memoryless, model = check.chains
    assert (memoryless.n_phases, model.n_phases) == (1, results.table.phases.n_phases)
    # the same particles and observations judge both: the phases fit them better at every lag
    assert model.log_likelihood_per_step > memoryless.log_likelihood_per_step
    assert model.ck.max_abs_error() < memoryless.ck.max_abs_error() / 5
    assert model.timescales_s[0] > memoryless.timescales_s[0]
    held = check.out_of_sample
    assert held is not None and held.entry_window_s[0] == pytest.approx(held.fit_window_s[1])
    # the refit fits the way the run's own model was fitted: a chain per size class with the
    # same moving phases and its dead zone, not the zone fitted again as a moving phase
    assert held.refit_phases_per_kind == phases_per_kind(results.table.phases)
    assert held.n_entered > 1000 and math.isfinite(held.pbm_variance_s2)
    assert held.variance_inside == (held.dem_variance_s2.low <= held.pbm_variance_s2 <= held.dem_variance_s2.high)
    # the halves together are the whole run's pooled RTD: their means, weighted by the
    # particles that entered (recovered alike), bracket it
    whole = results.summary.pooled_rtd
    first, second = held.dem_fit_half_mean_s.value, held.dem_mean_s.value
    assert min(first, second) <= whole.mean_residence_time_s.value <= max(first, second)
    record = check.record()
    assert (
        record["chains"][1]["ck_passed"] == model.ck.passed and record["out_of_sample"]["n_entered"] == held.n_entered
    )


def test_no_phase_model_no_check(baseline):
    results, config = baseline
    plain = results.table.replace(phases=None)
    import dataclasses

    assert memory_check(dataclasses.replace(results, table=plain), pbm_config_for(config, plain, None)) is None


def test_a_miss_within_the_two_halves_noise_is_told_apart_from_one_beyond_it():
    from dem.summary import Estimate
    from workflows.analysis.memory import OutOfSample

    second, first = Estimate(20.71, 20.38, 20.98), Estimate(21.51, 20.74, 22.46)  # half widths 0.30, 0.86

    def held(pbm_mean, fit_half):
        return OutOfSample((35, 63), (63, 91), 109, 2000, second, second, pbm_mean, 20.7, fit_half, fit_half, 4)

    near, far, alone = held(21.07, first), held(21.70, first), held(21.07, None)
    assert not near.mean_inside and near.mean_within_halves_noise  # 0.36 <= hypot(0.30, 0.86) = 0.91
    assert not far.mean_inside and far.mean_within_halves_noise is False  # 0.99 > 0.91
    assert alone.mean_within_halves_noise is None and alone.record()["mean_within_halves_noise"] is None
    assert held(20.8, first).mean_inside  # inside the second half's interval: the verdict itself
