"""``pbmdem study blocks``: the coverage check runs the product's interval and the old
bootstrap on series with a known mean, and tells them apart."""

from workflows.studies.blocks import coverage_row, rtd_coverage_row


def test_the_coverage_check_separates_the_results_interval_from_short_block_bootstraps():
    """A hold-up whose slow part relaxes in 10 s, residence time 27 s, 160 s steady: the
    results' batch means hold the true mean near the nominal 95 %, a bootstrap over 5-s
    blocks well below it (the study's 1000-series figures: 0.935 and 0.664)."""
    row = coverage_row(27.0, 160.0, 10.0, series=150, seed=3)
    assert row.batch_means >= 0.87
    assert row.bootstrap_5s <= 0.8
    assert row.batch_means - row.bootstrap_5s >= 0.15


def test_the_pooled_rtd_coverage_check_separates_expanded_from_plain_percentile_ends():
    """Pooled RTDs of three entry blocks with a known mean and variance: the expanded ends
    the results carry hold both near the nominal 95 %, the plain percentile ends about
    three times in four (the study's 1000-sample figures: 0.948 / 0.946 and 0.748 / 0.742)."""
    row = rtd_coverage_row(3, series=200, seed=1)
    assert row.mean_expanded >= 0.89 and row.variance_expanded >= 0.89
    assert row.mean_plain <= 0.84 and row.variance_plain <= 0.84
