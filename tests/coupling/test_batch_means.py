"""Batch means (coupling.intervals.batch_means_error) on series whose correlation is known."""

import math

import numpy as np
import pytest

from coupling.intervals import batch_means_error


def test_batch_means_error_grows_with_the_block_until_it_outlasts_the_correlation():
    """An iid series: the same error at every batch length (sigma / sqrt(n)); an AR(1)
    series with a 20-step correlation: short batches understate it, long ones approach
    the true sqrt(sum of autocorrelations) factor, sqrt((1 + phi) / (1 - phi))."""
    rng = np.random.default_rng(3)
    iid = rng.normal(size=40_000)
    for per in (1, 10, 100):
        assert batch_means_error(iid, per) == pytest.approx(1 / math.sqrt(iid.size), rel=0.15)
    phi = math.exp(-1 / 20)
    ar = np.empty(200_000)
    ar[0] = 0.0
    noise = rng.normal(size=ar.size) * math.sqrt(1 - phi**2)
    for i in range(1, ar.size):
        ar[i] = phi * ar[i - 1] + noise[i]
    true = math.sqrt((1 + phi) / (1 - phi)) / math.sqrt(ar.size)
    assert batch_means_error(ar, 2) < 0.5 * true
    assert batch_means_error(ar, 1000) == pytest.approx(true, rel=0.2)
    assert math.isnan(batch_means_error(ar[:10], 5))
