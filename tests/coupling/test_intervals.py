"""Resampling intervals (coupling.intervals): the block bootstrap keeps time correlation
(wider than the iid bootstrap, near-nominal coverage on an AR(1) series), the RTD overlap
noise band, and the argument checks."""

import math

import numpy as np
import pytest

from coupling.intervals import (
    Interval,
    NoiseBand,
    batch_means_interval,
    block_bootstrap,
    block_draw_counts,
    expanded_interval,
    expansion_factor,
    inside,
    overlap_noise_band,
    percentile_interval,
    time_blocks,
)
from coupling.metrics import rtd_density, rtd_overlap


def _ar1(rng, n, phi):
    """A stationary AR(1) series with zero mean and unit marginal variance."""
    noise = rng.normal(0.0, math.sqrt(1 - phi * phi), n)
    x = np.empty(n)
    x[0] = rng.normal()
    for i in range(1, n):
        x[i] = phi * x[i - 1] + noise[i]
    return x


def test_block_bootstrap_of_an_ar1_mean_is_wider_than_iid_and_covers_nominally():
    rng = np.random.default_rng(2013)
    n, phi, reps = 1000, 0.8, 200
    blocks = time_blocks(np.arange(n), 50.0)  # 20 blocks of 50 steps, >> the correlation time
    iid = np.arange(n)
    covered = {"block": 0, "iid": 0}
    widths = {"block": [], "iid": []}
    for r in range(reps):
        x = _ar1(rng, n, phi)

        def mean(idx, x=x):
            return x[idx].mean()

        for name, labels in (("block", blocks), ("iid", iid)):
            est, low, high = block_bootstrap(mean, labels, n_boot=400, seed=r)
            assert est == pytest.approx(x.mean())
            covered[name] += bool(inside(0.0, low, high))
            widths[name].append(high - low)
    # the true variance of the mean is (1 + phi) / (1 - phi) = 9 times the iid one
    assert np.mean(widths["block"]) > 2 * np.mean(widths["iid"])
    assert 0.85 <= covered["block"] / reps <= 0.99
    assert covered["iid"] / reps < 0.75


def test_block_bootstrap_indices_resample_whole_blocks():
    labels = np.array([3, 1, 3, 2, 1, 3])  # blocks of sizes 2 (label 1), 1 (2), 3 (3), interleaved
    seen = []

    def record(idx):
        seen.append(np.sort(labels[idx]))
        return float(len(idx))

    est, low, high = block_bootstrap(record, labels, n_boot=50, seed=1)
    assert est == 6.0 and list(seen[0]) == list(np.sort(labels))
    for drawn in seen[1:]:
        values, counts = np.unique(drawn, return_counts=True)
        size = {1: 2, 2: 1, 3: 3}
        assert all(c % size[v] == 0 for v, c in zip(values, counts))  # blocks come whole
        assert sum(c // size[v] for v, c in zip(values, counts)) == 3  # three blocks each time
    # the replicates count 3 to 9 items; the ends are theirs moved out by the expansion
    f = expansion_factor(3)
    assert 6.0 - 3.0 * f <= low <= 6.0 <= high <= 6.0 + 3.0 * f


def test_block_bootstrap_vector_statistic_and_determinism():
    rng = np.random.default_rng(4)
    tau = rng.exponential(10.0, 600)
    labels = time_blocks(rng.uniform(0, 60, 600), 5.0)

    def moments(idx):
        return np.array([tau[idx].mean(), tau[idx].var()])

    result = block_bootstrap(moments, labels, n_boot=300, seed=9)
    assert isinstance(result, Interval) and result.estimate.shape == (2,)
    assert np.all(result.low < result.estimate) and np.all(result.estimate < result.high)
    again = block_bootstrap(moments, labels, n_boot=300, seed=9)
    assert np.array_equal(result.low, again.low) and np.array_equal(result.high, again.high)
    wider = block_bootstrap(moments, labels, n_boot=300, level=0.99, seed=9)
    assert np.all(wider.high - wider.low > result.high - result.low)


def test_block_draw_counts_are_the_block_bootstraps_replicates():
    """A mean over items, as a ratio of per-block sums under the draw counts, gives the
    block bootstrap's interval (same seed): the same replicates, without a call each."""
    rng = np.random.default_rng(5)
    tau = rng.exponential(10.0, 700)
    blocks = time_blocks(rng.uniform(0, 80, 700), 5.0)
    _, block_of = np.unique(blocks, return_inverse=True)
    n_blocks = block_of.max() + 1
    sums, counts = np.bincount(block_of, weights=tau), np.bincount(block_of).astype(float)
    direct = block_bootstrap(lambda idx: tau[idx].mean(), blocks, n_boot=400, seed=11)
    draws = block_draw_counts(n_blocks, n_boot=400, seed=11)
    assert draws.shape == (400, n_blocks) and np.all(draws.sum(axis=1) == n_blocks)
    by_counts = expanded_interval(percentile_interval(tau.mean(), draws @ sums / (draws @ counts)), n_blocks)
    np.testing.assert_allclose(by_counts, direct, rtol=1e-12)
    with pytest.raises(ValueError, match="n_blocks"):
        block_draw_counts(1)


@pytest.mark.parametrize(
    "kwargs, word",
    [
        ({"data_blocks": np.zeros(5)}, "two distinct blocks"),
        ({"data_blocks": np.zeros((2, 2))}, "data_blocks"),
        ({"data_blocks": []}, "data_blocks"),
        ({"data_blocks": [0, 1], "n_boot": 0}, "n_boot"),
        ({"data_blocks": [0, 1], "level": 95}, "level"),
    ],
)
def test_block_bootstrap_refuses_bad_arguments(kwargs, word):
    with pytest.raises(ValueError, match=word):
        block_bootstrap(lambda idx: 0.0, **kwargs)


def test_batch_means_interval_of_one_block_batches_is_the_t_interval_of_the_mean():
    """Batches of one block: the jackknife of a mean is the mean's standard error, and
    the interval is Student's with n - 1 degrees of freedom (t = 2.0096 at 49)."""
    x = np.random.default_rng(3).normal(size=50)
    (est, low, high), df = batch_means_interval(lambda idx: x[idx].mean(), 50, 1)
    assert df == 49 and est == pytest.approx(x.mean())
    assert high - est == pytest.approx(est - low)
    assert (high - est) == pytest.approx(2.009575 * x.std(ddof=1) / math.sqrt(50), rel=1e-5)


def test_batch_means_interval_of_a_ratio_is_its_delta_method_interval():
    """A ratio of block sums (hold-up / outflow): the pseudo-values linearise it, so its
    standard error is the delta method's, sum((y - r x)^2) / sum(x)^2 scaled by n / (n - 1)."""
    rng = np.random.default_rng(6)
    y, x = rng.normal(100, 5, 40), rng.normal(10, 1, 40)
    r = y.sum() / x.sum()
    (est, low, high), df = batch_means_interval(lambda idx: y[idx].sum() / x[idx].sum(), 40, 1)
    delta = math.sqrt(40 / 39 * ((y - r * x) ** 2).sum()) / x.sum()
    assert est == pytest.approx(r)
    assert (high - low) / 2 == pytest.approx(2.022691 * delta, rel=0.02)


def test_batch_means_interval_covers_a_slowly_relaxing_series_where_short_blocks_do_not():
    """Blocks of a series relaxing over 2.5 blocks: batches of ten blocks (four times the
    relaxation, as the steady quantities' batches of two residence times are to the
    hold-up's slow part) hold the true mean at close to the nominal rate; one-block
    batches, which treat neighbouring blocks as independent, do not."""
    rng = np.random.default_rng(2013)
    n, phi, reps = 60, math.exp(-1 / 2.5), 300
    covered = {10: 0, 1: 0}
    for _ in range(reps):
        x = _ar1(rng, n, phi)
        for m in covered:
            (_, low, high), _ = batch_means_interval(lambda idx, x=x: x[idx].mean(), n, m)
            covered[m] += bool(inside(0.0, low, high))
    assert covered[10] / reps >= 0.9
    assert covered[1] / reps < 0.75


def test_batch_means_interval_vector_statistic_and_refusals():
    x = np.random.default_rng(1).normal(size=(30, 2))
    (est, low, high), df = batch_means_interval(lambda idx: x[idx].mean(axis=0), 30, 5)
    assert est.shape == low.shape == high.shape == (2,) and np.all(low < est) and np.all(est < high)
    assert df == pytest.approx(1.5 * (30 / 5 - 1))
    with pytest.raises(ValueError, match="at most half of n_blocks"):
        batch_means_interval(lambda idx: 0.0, 30, 16)
    with pytest.raises(ValueError, match="n_blocks"):
        batch_means_interval(lambda idx: 0.0, 1, 1)
    with pytest.raises(ValueError, match="batch_blocks"):
        batch_means_interval(lambda idx: 0.0, 30, 0)
    with pytest.raises(ValueError, match="level"):
        batch_means_interval(lambda idx: 0.0, 30, 1, level=1.5)


def test_time_blocks():
    assert list(time_blocks([0.0, 4.9, 5.0, 12.0], 5.0)) == [0, 0, 1, 2]
    assert list(time_blocks([39.5, 44.0, 44.5], 5.0, origin=39.5)) == [0, 0, 1]
    with pytest.raises(ValueError, match="block_s"):
        time_blocks([1.0], 0.0)
    with pytest.raises(ValueError, match="times"):
        time_blocks([np.nan], 5.0)


def _exponential_density(mean_s=15.0, horizon=60.0, bin_s=1.0):
    edges = np.arange(0.0, horizon + bin_s, bin_s)
    mass = np.diff(-np.exp(-edges / mean_s))
    return mass / (mass.sum() * bin_s)


def test_overlap_noise_band_tends_to_one_and_matches_a_direct_sample():
    e = _exponential_density()
    bands = [overlap_noise_band(e, 1.0, n, draws=400, seed=2) for n in (30, 300, 3000, 300_000)]
    assert all(isinstance(b, NoiseBand) and b.low <= b.median <= 1.0 for b in bands)
    medians = [b.median for b in bands]
    assert medians == sorted(medians) and medians[-1] > 0.99 and medians[0] < 0.85
    # a real sample of that size from the same distribution scores inside the band
    rng = np.random.default_rng(8)
    inside_count = 0
    band = bands[1]
    for _ in range(200):
        tau = rng.exponential(15.0, 2000)
        tau = tau[tau <= 60.0][:300]
        _, sample = rtd_density(tau, 1.0, 60.0)
        inside_count += bool(inside(rtd_overlap(sample, e, 1.0), band.low, 1.0))
    assert inside_count / 200 == pytest.approx(0.95, abs=0.04)


def test_overlap_noise_band_is_deterministic_and_checks_arguments():
    e = _exponential_density()
    assert overlap_noise_band(e, 1.0, 100, seed=5) == overlap_noise_band(e, 1.0, 100, seed=5)
    for kwargs, word in [
        ({"n_particles": 0}, "n_particles"),
        ({"draws": 0}, "draws"),
        ({"level": 0.0}, "level"),
        ({"bin_s": -1.0}, "bin_s"),
    ]:
        args = {"density": e, "bin_s": 1.0, "n_particles": 100, **kwargs}
        with pytest.raises(ValueError, match=word):
            overlap_noise_band(**args)
    with pytest.raises(ValueError, match="density"):
        overlap_noise_band(np.zeros(5), 1.0, 100)


def test_inside():
    assert inside(0.5, 0.0, 1.0) and inside(1.0, 0.0, 1.0) and not inside(1.5, 0.0, 1.0)
    assert not inside(math.nan, 0.0, 1.0)
    assert list(inside(np.array([0.2, 2.0]), np.array([0.0, 0.0]), 1.0)) == [True, False]


def test_the_expansion_is_students_t_over_the_plug_in_normal():
    # n = 2: sqrt(2) t_1(0.975) / z(0.975) = sqrt(2) 12.706 / 1.960
    assert expansion_factor(2) == pytest.approx(math.sqrt(2) * 12.7062 / 1.95996, rel=1e-4)
    assert expansion_factor(10_000) == pytest.approx(1.0, abs=1e-3)
    assert expansion_factor(3, 0.99) > expansion_factor(3) > expansion_factor(6) > 1
    est, low, high = expanded_interval(Interval(1.0, 0.5, 3.0), 4)
    f = expansion_factor(4)
    assert (est, low, high) == pytest.approx((1.0, 1.0 - 0.5 * f, 1.0 + 2.0 * f))  # asymmetry kept
    with pytest.raises(ValueError, match="n_blocks"):
        expansion_factor(1)


def test_with_few_blocks_the_expanded_ends_cover_and_the_plain_ones_do_not():
    """Four blocks of 50 exponential residence times (mean 20 s) with a block-level drift:
    the percentile ends of the pooled mean cover the truth ~80 % of the time, the expanded
    ones ~95 % (the nominal level)."""
    rng = np.random.default_rng(7)
    n_blocks, size, trials = 4, 50, 400
    draws = block_draw_counts(n_blocks, n_boot=1000, seed=3)
    plain = expanded = 0
    for _ in range(trials):
        x = rng.exponential(20.0, (n_blocks, size)) + rng.normal(0.0, 1.5, n_blocks)[:, None]
        sums = x.sum(axis=1)
        ends = percentile_interval(sums.sum() / x.size, draws @ sums / (size * draws.sum(axis=1)))
        plain += bool(inside(20.0, ends.low, ends.high))
        wide = expanded_interval(ends, n_blocks)
        expanded += bool(inside(20.0, wide.low, wide.high))
    assert plain / trials < 0.87
    assert 0.91 <= expanded / trials <= 0.99
