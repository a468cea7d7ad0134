"""``pbmdem study blocks``: the coverage check runs the product's interval and the old
bootstrap on series with a known mean, and tells them apart; the command runs on the
shipped run, and a missing file is one line."""

import json

import pytest

from workflows.cli.main import main
from workflows.pipeline.results import load_results
from workflows.shipped import REDUCED_RUN
from workflows.studies.blocks import COVERAGE_CASES, RTD_COVERAGE_BLOCKS, coverage_row, rtd_coverage_row


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


def test_the_command_reads_the_shipped_run_and_checks_coverage(tmp_path, capsys):
    """On the shipped reduced run the hold-up's batch-means error grows with the block
    length (it stays correlated for longer than a second), and the interval the results
    carry is at least the 5-s blocks' error; with ``--coverage`` the results' batch means
    hold the true mean more often than a bootstrap over 5-s blocks in every case."""
    assert main(["study", "blocks", "--results", str(REDUCED_RUN), "--coverage", "40", "--out", str(tmp_path)]) == 0
    record = json.loads((tmp_path / "blocks.json").read_text())
    (row,) = record["rows"]
    summary = load_results(REDUCED_RUN)[0].summary
    holdup = summary.steady["holdup"]
    assert row["holdup"] == pytest.approx(holdup["value"], rel=0.01)
    errors = dict(zip(row["blocks_s"], row["holdup_error"]))
    assert errors[1.0] < errors[5.0] <= row["holdup_interval_error"]
    assert row["rtd_mean_interval_error"] == pytest.approx(
        (summary.pooled_rtd.mean_residence_time_s.high - summary.pooled_rtd.mean_residence_time_s.low) / (2 * 1.96),
        rel=0.01,
    )
    assert len(record["coverage"]) == len(COVERAGE_CASES) and len(record["rtd_coverage"]) == len(RTD_COVERAGE_BLOCKS)
    for case in record["coverage"]:
        assert case["batch_means"] > case["bootstrap_5s"], case
    assert "| dem-17ea4c9cc143cd3e.h5 |" in capsys.readouterr().out
