"""The noise ensemble's two propagations give the same members: one column pair per member,
and the superposition of unit-feed responses used beyond as many members as noise intervals."""

import numpy as np
import pytest

import pbm.ensemble as ensemble
from pbm.config import PbmConfig
from pbm.synthetic import synthetic_table


@pytest.mark.parametrize(("step", "windows"), [(None, 5), (10.0, 5), (None, 24)])
def test_superposition_equals_one_column_pair_per_member(monkeypatch, step, windows):
    """On 24 windows (120 noise intervals) the outlet's responses are factored to a rank
    well below their columns: the members still agree with their own propagation."""
    table = synthetic_table(n_windows=windows)
    config = PbmConfig(feed_step_s=step, feed_step_factor_a=1.5 if step else 1.0)
    members = 5 * windows + 15  # more than the noise intervals: the superposition path
    fast = ensemble.noise_ensemble(table, config, sigma=0.2, members=members)
    monkeypatch.setattr(ensemble, "_by_superposition", ensemble._by_columns)
    slow = ensemble.noise_ensemble(table, config, sigma=0.2, members=members)
    for name in ("C_A_members", "rsd_outlet_members", "rsd_by_slice_mean", "rsd_by_slice_p95"):
        a, b = getattr(fast, name), getattr(slow, name)
        assert np.array_equal(np.isfinite(a), np.isfinite(b)), name
        np.testing.assert_allclose(a[np.isfinite(a)], b[np.isfinite(b)], rtol=0, atol=1e-11, err_msg=name)
    assert np.nanstd(fast.C_A_members[:, -1]) > 0.005  # the members differ: the noise is there


def test_bands_are_numpys_statistics_row_by_row_whatever_the_nans(monkeypatch):
    """Mean and 5/95 % quantiles of each series over its members: rows without NaN, rows
    with some NaN members (ignored) and all-NaN rows (NaN), the same on one block or several."""
    rng = np.random.default_rng(3)
    rows = rng.normal(size=(9, 500))
    rows[2, ::7] = np.nan
    rows[5] = np.nan
    want_mean = np.array([np.nan if np.isnan(r).all() else np.nanmean(r) for r in rows])
    want = np.array([[np.nan, np.nan] if np.isnan(r).all() else np.nanquantile(r, (0.05, 0.95)) for r in rows])
    for cores in (1, 3):
        monkeypatch.setattr(ensemble, "free_cores", lambda cap, cores=cores: min(cap, cores))
        mean, lo, hi = ensemble._bands(rows)
        np.testing.assert_allclose(mean, want_mean, rtol=1e-12, equal_nan=True)
        np.testing.assert_allclose(lo, want[:, 0], rtol=1e-12, equal_nan=True)
        np.testing.assert_allclose(hi, want[:, 1], rtol=1e-12, equal_nan=True)


def test_noise_factors_are_one_seeded_stream_member_after_member():
    """N(1, sigma) clipped at 0, one generator seeded config.seed drawn member after member
    (member m's factors do not depend on how many follow), (intervals, members, 2)."""
    from pbm.simulate import noise_factors

    config = PbmConfig()
    got = noise_factors(config, 30, 50, 0.6)
    draws = np.random.default_rng(config.seed).standard_normal((50, 30, 2))
    assert got.shape == (30, 50, 2)
    np.testing.assert_array_equal(got, np.clip(1.0 + 0.6 * draws.transpose(1, 0, 2), 0.0, None))
    assert (got == 0).any()  # sigma 0.6 clips some
    np.testing.assert_array_equal(noise_factors(config, 30, 7, 0.6), got[:, :7])
    np.testing.assert_array_equal(noise_factors(config, 30, 5, 0.0), np.ones((30, 5, 2)))


def test_low_rank_factors_reproduce_the_block_with_its_numerical_rank():
    """A rank-5 block plus rounding-level noise: 5 columns (give or take the rounding of
    the product that made it), the block to its rounding level; a full-rank block: exact with every column; a zero block: one zero column."""
    rng = np.random.default_rng(4)
    block = rng.random((160, 5)) @ rng.random((5, 90)) + 1e-18 * rng.random((160, 90))
    q, r = ensemble._low_rank(block)
    assert 5 <= q.shape[1] <= 7 and r.shape == (q.shape[1], 90)
    np.testing.assert_allclose(q @ r, block, rtol=0, atol=1e-13 * np.abs(block).max())
    full = rng.random((40, 30))
    q, r = ensemble._low_rank(full)
    assert q.shape == (40, 30)
    np.testing.assert_allclose(q @ r, full, rtol=0, atol=1e-13)
    q, r = ensemble._low_rank(np.zeros((8, 3)))
    assert q.shape == (8, 1) and not (q @ r).any()
