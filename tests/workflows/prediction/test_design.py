"""Design on the library's law: probabilities with known answers (a spec met everywhere, one
met nowhere, one constraint's t law by hand, the bivariate t against draws), the quantities
the same as ``predict``'s, the fast VRR the same as :mod:`pbm.frequency`'s, the step
response of one tank in closed form, and the domain refused in one line."""

import math
from dataclasses import replace

import numpy as np
import pytest
from scipy.integrate import quad
from scipy.special import stdtr, stdtrit

from coupling.errors import ConfigError
from dem.phases.law import MAX_LAW_RATE
from pbm.frequency import StationarySystem
from workflows.prediction import design as D
from workflows.prediction import predict as P
from workflows.prediction.library import load_model
from workflows.prediction.predict import entering, predict, rtd_moments
from workflows.shipped import LIBRARY_MODEL


@pytest.fixture(scope="module")
def shipped():
    return D.surrogate(load_model(LIBRARY_MODEL))


def _point(s, rpm=250.0, length=0.33, feed=73.7):
    return D.design_point(s.base, s.rule, rpm, length, feed)


def test_the_library_lengths_get_their_own_blade_stations(shipped):
    rule = P.station_rule([r.point for r in shipped.model.runs])
    for run in shipped.model.runs:
        p = run.point
        made = D.design_point(shipped.base, rule, p.impeller_rpm, p.length_m, p.feed_rate_total_per_s)
        assert np.allclose(made.blade_x_m, p.blade_x_m, atol=1e-9), run.file
        assert made.feed_rate_a_per_s == pytest.approx(p.feed_rate_a_per_s)


def test_the_quantities_are_predicts(shipped):
    """The axial chains solved together give predict's hold-up and mean residence time,
    value and interval, at a point the library never ran; the chain's generator is the
    law's, its mean residence time the chain's time to discharge, and the system the
    noise and step are read off holds predict's slices and its mean residence time."""
    point = _point(shipped, 275.0, 0.37, 90.0)
    ours = D.evaluate(shipped, D.design_spec(mrt_max_s=30.0), point)
    theirs = predict(shipped.model, point, shipped.pattern)
    assert theirs.new_layout  # 0.37 m: both keep the layout floor
    reused = predict(shipped.model, point, shipped.pattern, least=shipped.floors)
    assert [q.record() for q in reused.quantities] == [q.record() for q in theirs.quantities]
    for q in (ours.mrt, ours.holdup):
        other = theirs.quantity(q.key)
        assert (q.value, q.low, q.high) == pytest.approx((other.value, other.low, other.high), rel=1e-9)
    law = shipped.model.law
    x = D.covariate_columns(point, D.AXIAL_SLICES, law.covariate_names[1:], shipped.pattern)
    chain = law.chain(x, D.AXIAL_SLICES, 1, shipped.model.interval_s)
    assert np.allclose(D.law_generators(law, x[None])[0], chain.generator(), rtol=1e-12, atol=0)
    chains = D.solved_chains(shipped, [point])
    feed = entering(point, D.AXIAL_SLICES, 1)
    assert rtd_moments(chain, feed)[0] == pytest.approx(chains.held.sum() / chains.totals[0], rel=1e-10)
    system = D.predicted_system(shipped, ours)
    steady = np.linalg.solve(-system.generator, system.feed @ [point.feed_rate_a_per_s, point.feed_rate_b_per_s])
    slices = steady.reshape(D.AXIAL_SLICES, -1).sum(axis=1)
    assert slices.sum() / point.feed_rate_total_per_s == pytest.approx(ours.mrt.value, rel=1e-10)
    written = theirs.values.counts.sum(axis=(0, 2))  # the chain predict writes for the PBM
    assert slices / slices.sum() == pytest.approx(written / written.sum(), rel=1e-9)


def test_a_spec_met_everywhere_or_nowhere(shipped):
    points = [_point(shipped, r, length, f) for r in (150, 350) for length in (0.2475, 0.495) for f in (36.85, 147.4)]
    easy = D.evaluate_many(shipped, D.design_spec(mrt_min_s=1.0, mrt_max_s=1000.0, holdup_max=1e6), points)
    assert all(p.probability > 1 - 1e-6 for p in easy)
    hard = D.evaluate_many(shipped, D.design_spec(mrt_max_s=1.0), points)
    assert all(p.probability < 1e-6 for p in hard)
    # a composition no blender delivers: the outlet SD within a millionth
    hopeless = D.evaluate_many(shipped, D.design_spec(ca_tolerance=1e-6, noise_sigma=0.1), points)
    assert all(p.probability < 1e-6 for p in hopeless)


def test_one_constraint_is_its_t_law_by_hand(shipped):
    point = _point(shipped)
    first = D.evaluate(shipped, D.design_spec(mrt_max_s=1000.0), point)
    q = first.mrt
    bound = q.value * 1.02
    nu = q.correction.dof
    scale = math.log(q.high / q.value) / stdtrit(nu, 0.975)
    by_hand = stdtr(nu, math.log(bound / q.value) / scale)
    got = D.evaluate(shipped, D.design_spec(mrt_max_s=bound), point)
    assert got.probability == pytest.approx(by_hand, abs=1e-12)
    assert got.margins[0].probability == pytest.approx(by_hand, abs=1e-12)
    # at the interval's upper end: 97.5 %
    assert D.evaluate(shipped, D.design_spec(mrt_max_s=q.high), point).probability == pytest.approx(0.975, abs=1e-9)


def test_without_an_interval_the_value_alone_decides_either_bound(shipped):
    # a line that fits its runs exactly: a zero-width interval, P(spec met) 1 or 0 by the value
    point = _point(shipped)
    first = D.evaluate(shipped, D.design_spec(mrt_max_s=1000.0), point)
    mrt = replace(first.mrt, low=first.mrt.value, high=first.mrt.value)
    holdup = replace(first.holdup, low=first.holdup.value, high=first.holdup.value)
    assert D.t_scale(mrt) == 0.0 and D.t_scale(holdup) == 0.0
    v, h = mrt.value, holdup.value
    for bounds, met in (
        ({"mrt_min_s": v / 2}, 1.0),
        ({"mrt_min_s": v * 2}, 0.0),
        ({"mrt_max_s": v * 2}, 1.0),
        ({"mrt_max_s": v / 2}, 0.0),
        ({"holdup_min": h / 2}, 1.0),
        ({"holdup_min": h * 2}, 0.0),
        ({"mrt_min_s": v / 2, "holdup_min": h / 2}, 1.0),
        ({"mrt_min_s": v * 2, "holdup_min": h / 2}, 0.0),
        ({"mrt_min_s": v / 2, "holdup_min": h * 2}, 0.0),
    ):
        spec = D.design_spec(**bounds)
        assert D.joint_probability(spec, mrt, holdup, shipped.correlation) == met, bounds
        margins = [m.probability for m in D._margins(spec, point, mrt, holdup, None, math.nan)]
        assert min(margins) == met and len(margins) == len(bounds)


def test_a_points_dynamics_default_to_feeder_a_white_noise(shipped):
    point = _point(shipped)
    assert (
        D.point_dynamics(shipped, point).record() == D.point_dynamics(shipped, point, D.Noise(0.0, 0.5, "A")).record()
    )


def test_the_bivariate_rectangle():
    """Against seeded draws of the bivariate t (one chi-square shared: uncorrelated is not
    independent), and the whole second axis gives the first's marginal."""
    nu = 10
    assert D.rectangle(nu, 0.6, -1.0, 2.0, -math.inf, math.inf) == pytest.approx(
        stdtr(nu, 2.0) - stdtr(nu, -1.0), abs=1e-10
    )
    rng = np.random.default_rng(5)
    for rho in (0.0, 0.8):
        z = rng.multivariate_normal([0, 0], [[1, rho], [rho, 1]], size=400_000)
        t = z / np.sqrt(rng.chisquare(nu, size=(400_000, 1)) / nu)
        inside = (t[:, 0] > -1) & (t[:, 0] < 2) & (t[:, 1] > -0.5) & (t[:, 1] < 1.5)
        assert D.rectangle(nu, rho, -1.0, 2.0, -0.5, 1.5) == pytest.approx(inside.mean(), abs=0.003)


def test_hold_up_and_residence_time_together_use_their_correlation(shipped):
    point = _point(shipped)
    base = D.evaluate(shipped, D.design_spec(mrt_max_s=1000.0), point)
    spec = D.design_spec(mrt_max_s=base.mrt.value * 1.01, holdup_max=base.holdup.value * 1.01)
    both = D.evaluate(shipped, spec, point)
    alone = [m.probability for m in both.margins]
    assert 0.5 < shipped.correlation < 1.0
    # positively correlated: between the product of the marginals and the least of them
    assert alone[0] * alone[1] < both.probability < min(alone)


def test_the_fast_vrr_is_the_schur_forms(shipped):
    """The VRR read off one interpolated eigen-response equals the direct response of
    :func:`pbm.frequency.system_response` on the chain predict writes, to 1e-3."""
    for tau in (0.0, 5.0):
        spec = D.design_spec(ca_tolerance=0.04, noise_sigma=0.1, noise_tau_s=tau)
        for rpm, length, feed in ((150, 0.2475, 36.85), (350, 0.495, 147.4), (220, 0.4, 100.0)):
            got = D.evaluate(shipped, spec, _point(shipped, rpm, length, feed))
            m = got.mrt
            direct = D.noise_vrr(
                D.predicted_system(shipped, got), spec.noise, np.array([1.0, m.low / m.value, m.high / m.value])
            )
            assert [got.vrr.value, got.vrr.low, got.vrr.high] == pytest.approx(direct, rel=1e-3)
            assert got.vrr.low < got.vrr.value < got.vrr.high  # a longer residence filters more
            sd = got.point.feed_rate_a_per_s / got.point.feed_rate_total_per_s * 0.5 * 0.1 / math.sqrt(got.vrr.value)
            assert got.ca_sd.value == pytest.approx(sd, rel=1e-12)


def test_the_step_response_of_one_tank():
    """One tank of rate k: F(t) = 1 - exp(-k t), C(t) = C g / (C g + 1 - C), g = 1 + (x - 1) F."""
    k = 0.2
    system = StationarySystem(np.array([[-k]]), np.ones((1, 2)), np.full((2, 1), k), np.zeros(1))

    class Mrt:
        value, low, high = 1 / k, 0.9 / k, 1.2 / k

    point = replace(_point(D.surrogate(load_model(LIBRARY_MODEL))), feed_rate_a_per_s=30.0, feed_rate_b_per_s=70.0)
    times, step, levels, delay = D.step_response(system, point, Mrt, factor=3.0)
    c0, x = 0.3, 3.0

    def curve(t, tau=1 / k):
        g = 1 + (x - 1) * (1 - np.exp(-t / tau))
        return c0 * g / (c0 * g + 1 - c0)

    assert levels == pytest.approx((c0, x * c0 / (x * c0 + 1 - c0)))
    assert np.allclose(step[0], curve(times), atol=1e-12)
    assert np.allclose(step[1], np.minimum(curve(times, 0.9 / k), curve(times, 1.2 / k)), atol=2e-3)
    exact = quad(lambda t: levels[1] - curve(t), 0, times[-1])[0] / (levels[1] - c0)
    assert delay.value == pytest.approx(exact, rel=1e-3)
    assert delay.low < delay.value < delay.high


def test_outside_the_domain_refused_in_one_line_unless_extrapolated(shipped):
    spec = D.design_spec(mrt_max_s=25.0, rpm_max=420.0)
    with pytest.raises(ConfigError, match=r"leaves the library's domain \(speed.*the domain is 150-350 rpm") as err:
        D.design(shipped, spec, grid=(2, 2, 2))
    assert "\n" not in str(err.value)
    wide = D.design(D.surrogate(shipped.model, extrapolate=True), spec, grid=(3, 2, 2))
    assert any("EXTRAPOLATED" in n for n in wide.notes)
    outside = [p for p in wide.points if p.outside]
    # beyond 350 rpm: outside the speed range; inside it, a corner of the box (shortest
    # blender, least feed) is beyond the combinations a library of one change at a time spans
    above = [p for p in outside if p.point.impeller_rpm > 350.0]
    assert above and all("speed outside" in p.outside[0] for p in above)
    corners = [p for p in outside if p.point.impeller_rpm <= 350.0]
    assert corners and all(p.outside == (p.outside[0],) and "beyond the combinations" in p.outside[0] for p in corners)
    # labelled and widened, never narrower than the same point's interval inside the hull would be
    assert all(p.mrt.widening > 1.0 for p in outside)


def test_one_bound_beyond_the_domains_other_end_is_refused_not_overridden(shipped):
    # rpm_max 100 under the domain's 150: searching 150 rpm would answer outside what was asked
    wide = D.surrogate(shipped.model, extrapolate=True)
    with pytest.raises(ConfigError, match=r"^rpm_max 100 lies beyond .* 150 rpm is the default rpm_min: give rpm_min"):
        D.box(wide, D.design_spec(mrt_max_s=25.0, rpm_max=100.0))
    with pytest.raises(ConfigError, match=r"^length_min_m 0.6 lies beyond .* 0.495 m is the default length_max_m"):
        D.box(wide, D.design_spec(mrt_max_s=25.0, length_min_m=0.6))
    assert D.box(wide, D.design_spec(mrt_max_s=25.0, rpm_min=80.0, rpm_max=100.0))[0] == (80.0, 100.0)


def test_a_box_reaching_past_the_extrapolations_reach_is_refused_naming_it(shipped):
    wide = replace(shipped, extrapolate=True)
    with pytest.raises(
        ConfigError, match=r"reaches too far beyond .*feed 4.53 widths .*reaches 4.146-1228 particles/s"
    ):
        D.box(wide, D.design_spec(mrt_max_s=20.0, feed_max_per_s=1e6))


def test_no_column_of_the_grid_holds_a_larger_feed_than_the_answer(shipped):
    """Every (speed, length) of the grid walked along the feed finely: none meets the spec at
    a feed beyond the answer's by more than the refinement's step."""
    spec = D.design_spec(mrt_min_s=20.0)
    result = D.design(shipped, spec, grid=(3, 3, 4))
    (_, _), (_, _), (f0, f1) = D.box(shipped, spec)
    trial = np.geomspace(f0, f1, 40)
    points = [
        D.design_point(shipped.base, shipped.rule, r, x, f)
        for r in result.speeds
        for x in result.lengths
        for f in trial
    ]
    met = [p.feed_per_s for p in D.evaluate_many(shipped, spec, points) if p.probability >= spec.confidence]
    step = (f1 / f0) ** (1 / 3 / (D.REFINE_POINTS + 1))
    assert max(met) <= result.largest_feed.feed_per_s * step * (1 + 1e-9)


def test_each_band_of_stations_ends_just_before_the_next_station():
    rule = (0.045, 0.255 / 9, 0.025)
    tops = D.band_tops(rule, 0.2475, 0.495)
    assert tops.size == 9  # 7 to 15 stations end inside the range; 16 reach past 0.495 m
    for top in tops:
        n = P.stations_for(rule, top)
        assert P.stations_for(rule, top + 2e-6) == n + 1
        assert top - (0.045 + (n - 1) * rule[1]) == pytest.approx(0.025 + rule[1], abs=2e-6)


def test_the_search_answers_within_its_box(shipped):
    spec = D.design_spec(ca_tolerance=0.04, noise_sigma=0.1, noise_tau_s=5.0, mrt_max_s=25.0)
    result = D.design(shipped, spec, grid=(3, 4, 3))
    assert result.probability.shape == (3, 4, 3)
    best = result.shortest
    assert best is not None and best.probability >= spec.confidence
    met = [p for p in (*result.points, *result.region.points) if p.probability >= spec.confidence]
    assert best.length_m <= min(p.length_m for p in met) + 1e-12
    assert result.region.feed_per_s == pytest.approx(best.feed_per_s)
    assert result.region.probability.shape == (13, 17)
    assert result.largest_feed.feed_per_s >= max(p.feed_per_s for p in result.points if p.probability >= 0.95)
    assert set(result.dynamics) == {"shortest", "largest_feed"}
    record = result.record()
    assert record["grid"]["shape"] == [3, 4, 3] and record["shortest"]["probability"] == best.probability


def test_the_spec_names_a_bad_value():
    with pytest.raises(ConfigError, match="at least one criterion"):
        D.design_spec(noise_sigma=0.1)
    with pytest.raises(ConfigError, match="noise_sigma > 0"):
        D.design_spec(ca_tolerance=0.04)
    with pytest.raises(ConfigError, match=r"length_min_m \(0.4\) must be <= length_max_m"):
        D.design_spec(mrt_max_s=25.0, length_min_m=0.4, length_max_m=0.3)
    with pytest.raises(ConfigError, match=r"^design spec: confidence = 2.0: Input should be less than 1$"):
        D.design_spec(mrt_max_s=25.0, confidence=2.0)


def test_the_command_line_refuses_a_spec_naming_its_flags(capsys):
    from workflows.cli.main import main

    assert main(["design", "--ca-within", "0.04"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "(--ca-within, --rsd-max) needs the feeder noise: --noise-sigma > 0" in err
    assert main(["design", "--mrt-min", "30", "--mrt-max", "20"]) == 2
    assert "--mrt-min (30.0) must be <= --mrt-max (20.0)" in capsys.readouterr().err


def test_any_predicted_point_has_its_noise_and_step(shipped):
    """A point's noise and step alone are those of the design that found it."""
    spec = D.design_spec(ca_tolerance=0.04, noise_sigma=0.1, noise_tau_s=5.0, mrt_max_s=25.0)
    result = D.design(shipped, spec, grid=(3, 4, 3))
    assert result.shortest is not None, "the spec is met somewhere on the grid"
    alone = D.point_dynamics(shipped, result.shortest.point, spec.noise)
    found = result.dynamics["shortest"]
    assert alone.vrr.value == pytest.approx(found.vrr.value, rel=1e-3)
    assert alone.mean_delay_s == found.mean_delay_s and np.array_equal(alone.step, found.step)


def test_the_composition_is_judged_on_the_residence_times_t_law(shipped):
    """A C_A tolerance met exactly at the predicted mean residence time is met with P 1/2
    (a longer residence filters more); one met exactly at its interval's lower end, with
    P 0.975 (the margin tabulated in t, linear between)."""
    point = _point(shipped, 200.0, 0.3, 60.0)
    first = D.evaluate(shipped, D.design_spec(ca_tolerance=0.5, noise_sigma=0.1, noise_tau_s=5.0), point)
    for tolerance, expected, tol in ((3 * first.ca_sd.value, 0.5, 1e-9), (3 * first.ca_sd.high, 0.975, 3e-3)):
        got = D.evaluate(shipped, D.design_spec(ca_tolerance=tolerance, noise_sigma=0.1, noise_tau_s=5.0), point)
        assert got.probability == pytest.approx(expected, abs=tol)
        assert got.margins[0].probability == pytest.approx(got.probability, abs=1e-12)


def test_designs_generators_hold_a_rate_at_the_laws_bound_as_the_law_does(shipped):
    """A family whose predictor passes the bound at a point (the slowest phase's backward
    moves, steep in position) gives the law's chain there, not an overflowing generator."""
    law = shipped.model.law
    family = "x_neg/0"
    wild = dict(law.coefficients)
    wild[family] = wild[family].copy()
    wild[family][0] += 60.0  # the constant lifted far past log(MAX_RATE_PER_S)
    law = replace(law, coefficients=wild)
    point = _point(shipped, 275.0, 0.37, 90.0)
    x = D.covariate_columns(point, D.AXIAL_SLICES, law.covariate_names[1:], shipped.pattern)
    chain = law.chain(x, D.AXIAL_SLICES, 1, shipped.model.interval_s)
    assert chain.rates[0, 1, 1:].max() == pytest.approx(MAX_LAW_RATE)
    assert np.allclose(D.law_generators(law, x[None])[0], chain.generator(), rtol=1e-12, atol=0)
