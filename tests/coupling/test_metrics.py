"""The CQAs both sides compute through coupling.metrics: RSD and its empty rule, the
random-mixture floor, C_A, the steady-state rule; and the DEM and PBM agreeing on them
when handed the same counts."""

import math

import numpy as np
import pytest

from coupling import metrics
from coupling.errors import ConfigError
from coupling.metrics import (
    EMPTY_BELOW,
    SteadyStateRule,
    binomial_interval,
    lacey_index,
    outflow_fraction_a,
    random_mixture_rsd,
    rsd,
    rtd_bin_edges,
    rtd_density,
    rtd_overlap,
    rtd_pooled,
    sampled_lacey,
    sampled_rsd,
)


def test_rsd_sample_statistic_and_empty_compartments():
    a = np.array([1.0, 3.0, 0.0, 2.0])
    b = np.array([3.0, 1.0, 0.0, 2.0])  # fractions 0.25, 0.75, (empty), 0.5
    assert rsd(a, b) == pytest.approx(np.std([0.25, 0.75, 0.5], ddof=1) / 0.5)
    assert np.isnan(rsd(np.array([1.0, 0.0]), np.array([1.0, 0.0])))  # one occupied compartment
    assert np.isnan(rsd(np.array([0.0, 0.0]), np.array([2.0, 2.0])))  # no A: undefined
    # fewer than EMPTY_BELOW (one) particle expected counts as empty
    assert EMPTY_BELOW == 1.0
    assert rsd(np.array([0.3, 1.0, 3.0]), np.array([0.0, 3.0, 1.0])) == pytest.approx(
        np.std([0.25, 0.75], ddof=1) / 0.5
    )


def test_rsd_along_an_axis_equals_one_call_per_row(rng):
    a = rng.integers(0, 5, size=(7, 10)).astype(float)
    b = rng.integers(0, 5, size=(7, 10)).astype(float)
    along = rsd(a, b, axis=1)
    for k in range(7):
        assert along[k] == pytest.approx(float(rsd(a[k], b[k])), nan_ok=True)
    floors = random_mixture_rsd(a.T, b.T, axis=0)
    for k in range(7):
        assert floors[k] == pytest.approx(float(random_mixture_rsd(a[k], b[k])), nan_ok=True)


@pytest.mark.parametrize(
    ("shape", "axis"), [((10,), 0), ((6, 9), 0), ((6, 9), 1), ((3, 4, 5, 2), 2), ((3, 4, 5), -1), ((0, 4), 1)]
)
def test_compiled_rsd_is_the_numpy_definition(rng, shape, axis):
    # integer and expected counts, empty compartments, compartments below one particle,
    # all-B rows (mean 0) and rows with a single occupied compartment
    a = rng.integers(0, 4, size=shape) * rng.random(shape)
    b = rng.integers(0, 4, size=shape) * rng.random(shape)
    if a.size:
        a.flat[::5] = 0.0
        b.flat[::7] = 0.4
    got = rsd(a, b, axis=axis)
    want = metrics._rsd_reference(a, b, axis % len(shape))
    # the same sums in another order (numpy adds long rows pairwise): equal to rounding
    assert got.shape == want.shape
    np.testing.assert_allclose(got, want, rtol=1e-14, atol=0)
    # a non-contiguous view reads the same
    np.testing.assert_array_equal(rsd(np.asfortranarray(a), b, axis=axis), got)


def test_rsd_refuses_counts_of_two_shapes():
    with pytest.raises(ValueError, match=r"\(3,\) and \(4,\)"):
        rsd(np.ones(3), np.ones(4))


def test_random_mixture_floor_is_the_binomial_sampling_noise():
    # Monte-Carlo check of the analytic floor (seeded): mean sample variance of binomial fractions
    rng = np.random.default_rng(7)
    n = np.array([3, 5, 8, 13, 21])
    p = 0.3
    x = rng.binomial(n, p, size=(200_000, n.size))
    var = np.mean(np.var(x / n, axis=1, ddof=1))
    assert float(random_mixture_rsd(p * n, (1 - p) * n)) == pytest.approx(math.sqrt(var) / p, rel=5e-3)
    assert math.isnan(float(random_mixture_rsd([1, 0], [0, 0])))  # one non-empty compartment


def test_outflow_fraction():
    assert outflow_fraction_a(np.array([1.0, 0.0]), np.array([3.0, 0.0]))[0] == 0.25
    assert np.isnan(outflow_fraction_a(np.array([1.0, 0.0]), np.array([3.0, 0.0]))[1])


def test_steady_state_rule():
    t = np.arange(1.0, 201.0)
    rule = SteadyStateRule(window_s=10.0, rel_tol=0.02)
    assert rule.time(t, 100 * t) is None  # a linear rise never passes
    holdup = 1000 * (1 - np.exp(-t / 20))
    found = rule.time(t, holdup)

    def change(s):  # |m1 - m0| / m1 over the windows (s-10, s] and (s-20, s-10]
        m1 = holdup[(t > s - 10) & (t <= s)].mean()
        m0 = holdup[(t > s - 20) & (t <= s - 10)].mean()
        return abs(m1 - m0) / m1

    assert found is not None and change(found) <= 0.02 < change(found - 1)
    # unknown values (before the first DEM dump) spoil only the windows that hold them
    early_nan = holdup.copy()
    early_nan[:3] = np.nan
    assert rule.time(t, early_nan) == found


@pytest.mark.parametrize("kwargs", [{"window_s": 0.0}, {"window_s": math.inf}, {"rel_tol": 1.0}, {"rel_tol": math.nan}])
def test_steady_state_rule_refuses_bad_values(kwargs):
    with pytest.raises(ConfigError, match="steady_state"):
        SteadyStateRule(**kwargs)


def test_dem_and_pbm_give_the_same_cqas_for_the_same_counts(tmp_path):
    """A DEM snapshot and a PBM state holding the same particles report the same RSDs."""
    from coupling.tables import make_table
    from dem.config import DemConfig, TablesConfig
    from dem.dumps import format_snapshot
    from dem.post import postprocess
    from pbm import PbmConfig, simulate

    cfg = DemConfig(tables=TablesConfig(nx=2, ny=2, window_s=1.0, sample_interval_s=1.0, min_samples=1))
    # slice 1 (x > L/2): 3 A + 1 B at j = 0, 1 A + 1 B at j = 1; slice 0: 2 A at j = 1
    rows = [
        (1, 1, 0.2, -0.02),
        (2, 1, 0.2, -0.02),
        (3, 1, 0.2, -0.02),
        (4, 2, 0.2, -0.02),
        (5, 1, 0.2, 0.02),
        (6, 2, 0.2, 0.02),
        (7, 1, 0.05, 0.02),
        (8, 1, 0.05, 0.02),
    ]
    data = np.array([(i, t, x, y, 0, 0, 0, 0, 0.003) for i, t, x, y in rows], dtype=float)
    step = int(round(1.0 / cfg.timestep_s))
    columns = ("id", "type", "x", "y", "z", "vx", "vy", "vz", "radius")
    (tmp_path / f"dump.{step}.txt").write_bytes(format_snapshot(step, columns, data))
    dem = postprocess(str(tmp_path / "dump.*.txt"), cfg).summary

    counts = np.zeros((2, 2, 2))
    counts[0, 1] = [3, 1]
    counts[1, 1] = [1, 1]
    counts[0, 0, 1] = 2
    table = make_table([0.0], [0, 0.165, 0.33], [-0.05, 0, 0.05], 0, 0, 0, 0)
    pbm = simulate(
        table, PbmConfig(feed_rate_a_per_s=0, feed_rate_b_per_s=0, duration_s=1.0), initial_counts=counts
    ).summary
    assert pbm.final_rsd_outlet == pytest.approx(dem.final_rsd_outlet)
    assert pbm.final_rsd_blender == pytest.approx(dem.final_rsd_blender)


# --- Lacey index, sampled RSD / Lacey -------------------------------------------------------


def test_lacey_index_definition_by_hand():
    a = np.array([2.0, 6.0, 0.0, 4.0])
    b = np.array([6.0, 2.0, 0.5, 4.0])  # fractions 0.25, 0.75, (empty: 0.5 particle), 0.5
    p, n_bar = 12 / 24, 8.0
    s2 = np.var([0.25, 0.75, 0.5])  # population variance
    expected = (p * (1 - p) - s2) / (p * (1 - p) - p * (1 - p) / n_bar)
    assert float(lacey_index(a, b)) == pytest.approx(expected)


def test_lacey_index_is_zero_when_fully_segregated_and_one_for_a_random_mixture():
    assert float(lacey_index([10, 10, 0, 0], [0, 0, 10, 10])) == pytest.approx(0.0)
    rng = np.random.default_rng(11)
    n, p = 20, 0.3
    a = rng.binomial(n, p, size=(20_000, 50)).astype(float)
    m = lacey_index(a, n - a, axis=1)
    assert m.shape == (20_000,)
    assert m.mean() == pytest.approx(1.0, abs=5e-3)


def test_lacey_index_undefined_cases_and_axis():
    assert np.isnan(lacey_index([3, 0], [3, 0]))  # one non-empty compartment
    assert np.isnan(lacey_index([0, 0], [4, 4]))  # no A: p = 0
    assert np.isnan(lacey_index([1, 0], [0, 1]))  # one particle each: sigma0^2 = sigmaR^2
    rng = np.random.default_rng(2)
    a = rng.integers(0, 6, size=(5, 8)).astype(float)
    b = rng.integers(0, 6, size=(5, 8)).astype(float)
    along = lacey_index(a.T, b.T, axis=0)
    for k in range(5):
        assert along[k] == pytest.approx(float(lacey_index(a[k], b[k])), nan_ok=True)


def test_sampled_rsd_of_a_uniform_composition_is_the_random_mixture_floor():
    n, p = 25, 0.4
    floor = float(random_mixture_rsd(np.full(100, p * n), np.full(100, (1 - p) * n)))
    assert float(sampled_rsd(np.full(100, p), n, draws=2000, seed=1)) == pytest.approx(floor, rel=0.01)
    # over 10 compartments the mean RSD sits below the floor by the bias of a sample SD
    ten = float(sampled_rsd(np.full(10, p), n, draws=4000, seed=1))
    assert 0.95 * floor < ten < floor


def test_sampled_rsd_shapes_determinism_and_empty_rule():
    frac = np.array([[0.5] * 10, [0.2] * 5 + [0.8] * 5])
    out = sampled_rsd(frac, np.full(10, 30.0), draws=200, seed=3)
    assert out.shape == (2,)
    assert out[1] > out[0]  # segregation shows above the sampling noise
    assert np.array_equal(out, sampled_rsd(frac, np.full(10, 30.0), draws=200, seed=3))
    # an expected 0.4 particle is an empty compartment, whatever its (undefined) fraction
    with_empty = sampled_rsd([0.5, 0.5, np.nan], [30.0, 30.0, 0.4], draws=300, seed=4)
    assert with_empty == pytest.approx(sampled_rsd([0.5, 0.5], [30.0, 30.0], draws=300, seed=4))
    assert np.isnan(sampled_rsd([0.5, 0.5], [30.0, 0.0], draws=10))  # one compartment: undefined
    assert sampled_lacey(np.full(50, 0.3), 20, draws=2000, seed=5) == pytest.approx(1.0, abs=0.01)
    assert sampled_lacey([1.0, 1.0, 0.0, 0.0], 10, draws=5) == pytest.approx(0.0)


@pytest.mark.parametrize(
    "kwargs, word",
    [
        ({"fraction_a": [0.5, 1.5], "totals": [5, 5]}, "fraction_a"),
        ({"fraction_a": [0.5, np.nan], "totals": [5, 5]}, "fraction_a"),
        ({"fraction_a": [0.5, 0.5], "totals": [5, -1]}, "totals"),
        ({"fraction_a": [0.5, 0.5, 0.5], "totals": [5, 5]}, "broadcast"),
        ({"fraction_a": 0.5, "totals": 5}, "compartments"),
        ({"fraction_a": [0.5, 0.5], "totals": [5, 5], "draws": 0}, "draws"),
    ],
)
def test_sampled_rsd_refuses_bad_arguments(kwargs, word):
    with pytest.raises(ValueError, match=word):
        sampled_rsd(**kwargs)


# --- pooled RTD ------------------------------------------------------------------------


def _exponential_particles(rng, n, mean_s, t_end):
    entry = rng.uniform(0.0, 100.0, n)
    exit_ = entry + rng.exponential(mean_s, n)
    exit_[exit_ > t_end] = np.nan  # still inside at the end
    return entry, exit_


def test_pooled_rtd_of_exponential_residence_times_is_the_truncated_exponential():
    from scipy.stats import truncexpon

    rng = np.random.default_rng(21)
    mean_s, horizon, t_end = 20.0, 30.0, 120.0
    entry, exit_ = _exponential_particles(rng, 400_000, mean_s, t_end)
    window = (40.0, t_end - horizon)
    rtd = rtd_pooled(entry, exit_, window, horizon)
    entered = (entry > 40.0) & (entry <= 90.0)
    assert rtd.n_entered == int(entered.sum())
    assert rtd.residence_s.size == rtd.entry_s.size
    assert np.all((rtd.entry_s > 40.0) & (rtd.entry_s <= 90.0)) and rtd.residence_s.max() <= horizon
    truth = truncexpon(b=horizon / mean_s, scale=mean_s)
    assert rtd.recovered_fraction == pytest.approx(1 - math.exp(-horizon / mean_s), abs=3e-3)
    assert rtd.mean_s == pytest.approx(truth.mean(), rel=5e-3)
    assert rtd.variance_s2 == pytest.approx(truth.var(), rel=1e-2)
    assert rtd.variance_s2 == pytest.approx(np.var(rtd.residence_s))


def test_pooled_rtd_edge_cases():
    empty = rtd_pooled([1.0, 2.0], [3.0, np.nan], (5.0, 6.0), 10.0)
    assert empty.n_entered == 0 and math.isnan(empty.recovered_fraction) and math.isnan(empty.mean_s)
    # the window is (t0, t1]: an entry at t0 is out, at t1 in; tau = H is recovered
    rtd = rtd_pooled([5.0, 6.0, 5.5], [9.0, 16.0, np.nan], (5.0, 6.0), 10.0)
    assert rtd.n_entered == 2 and rtd.recovered_fraction == 0.5
    assert list(rtd.residence_s) == [10.0] and list(rtd.entry_s) == [6.0]


@pytest.mark.parametrize(
    "args, word",
    [
        (([0.0, 1.0], [2.0], (0, 1), 5.0), "entry_t and exit_t"),
        (([np.nan], [2.0], (0, 1), 5.0), "entry_t"),
        (([1.0], [0.5], (0, 1), 5.0), "exit_t"),
        (([1.0], [2.0], (1, 1), 5.0), "entry_window"),
        (([1.0], [2.0], 3.0, 5.0), "entry_window"),
        (([1.0], [2.0], (0, 1), 0.0), "horizon_s"),
    ],
)
def test_pooled_rtd_refuses_bad_arguments(args, word):
    with pytest.raises(ValueError, match=word):
        rtd_pooled(*args)


def test_rtd_density_is_normalised_on_whole_bins():
    edges, e = rtd_density([0.0, 0.5, 1.0, 2.9, 3.0], 1.0, 3.0)
    assert np.allclose(edges, [0, 1, 2, 3])
    assert np.allclose(e, [2 / 5, 1 / 5, 2 / 5])  # last bin closed at H
    assert np.sum(e) * 1.0 == pytest.approx(1.0)
    # the PBM's binned tracer, as weights at its bin centres, lands on the same bins
    _, pbm = rtd_density([0.25, 0.75, 1.25], 0.5, 1.5, weights=[1.0, 3.0, 0.0])
    assert np.allclose(pbm, [0.5, 1.5, 0.0])
    _, nothing = rtd_density([], 1.0, 3.0)
    assert np.all(np.isnan(nothing))
    assert np.allclose(rtd_bin_edges(0.5, 2.0), [0, 0.5, 1, 1.5, 2])


@pytest.mark.parametrize(
    "args, kwargs, word",
    [
        (([1.0], 1.0, 2.5), {}, "whole number of bins"),
        (([1.0], 0.0, 2.0), {}, "bin_s"),
        (([1.0], 1.0, -2.0), {}, "horizon_s"),
        (([3.0], 1.0, 2.0), {}, "residence_times"),
        (([1.0], 1.0, 2.0), {"weights": [1.0, 2.0]}, "weights"),
    ],
)
def test_rtd_density_refuses_bad_arguments(args, kwargs, word):
    with pytest.raises(ValueError, match=word):
        rtd_density(*args, **kwargs)


def test_rtd_overlap_limits():
    _, e = rtd_density(np.random.default_rng(0).exponential(5.0, 500).clip(max=30), 1.0, 30.0)
    assert rtd_overlap(e, e, 1.0) == pytest.approx(1.0)
    left = np.array([0.5, 0.5, 0.0, 0.0])
    right = np.array([0.0, 0.0, 0.5, 0.5])
    assert rtd_overlap(left, right, 1.0) == 0.0
    half = np.array([0.25, 0.25, 0.25, 0.25])
    assert rtd_overlap(left, half, 1.0) == pytest.approx(1 - 0.5 * np.sum(np.abs(left - half)))
    assert math.isnan(rtd_overlap(np.full(4, np.nan), half, 1.0))
    with pytest.raises(ValueError, match="same bins"):
        rtd_overlap(left, half[:3], 1.0)
    with pytest.raises(ValueError, match="bin_s"):
        rtd_overlap(left, half, 0.0)


# --- Wilson interval -------------------------------------------------------------------


@pytest.mark.parametrize(
    "k, n, low, high",
    [
        # Newcombe (1998), Stat. Med. 17:857, Table I, method 3 (Wilson score, no correction)
        (81, 263, 0.2553, 0.3662),
        (15, 148, 0.0624, 0.1605),
        (0, 20, 0.0, 0.1611),
        (1, 29, 0.0061, 0.1718),
        (5, 10, 0.2366, 0.7634),
    ],
)
def test_wilson_interval_known_values(k, n, low, high):
    lo, hi = binomial_interval(k, n)
    assert lo == pytest.approx(low, abs=1e-4) and hi == pytest.approx(high, abs=1e-4)


def test_wilson_interval_properties():
    assert binomial_interval(0, 0) == (0.0, 1.0)
    lo, hi = binomial_interval(np.array([0, 10, 20]), 20)
    assert lo.shape == (3,) and lo[0] == 0.0 and hi[2] == 1.0 and lo[2] > 0.8
    narrow, wide = binomial_interval(50, 100, 0.9), binomial_interval(50, 100, 0.99)
    assert wide[0] < narrow[0] < 0.5 < narrow[1] < wide[1]
    for bad, word in [((5, 4), "k <= n"), ((-1, 4), "k <= n"), ((1, np.nan), "finite")]:
        with pytest.raises(ValueError, match=word):
            binomial_interval(*bad)
    with pytest.raises(ValueError, match="level"):
        binomial_interval(1, 4, level=1.0)
