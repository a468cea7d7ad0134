"""study law: the joint phase law on shipped runs, end to end through the command line."""

import json
from pathlib import Path

import numpy as np

from workflows.cli.main import main
from workflows.shipped import VALIDATION_DIR

BASELINE = VALIDATION_DIR / "dem-aa093a229dfd2ce4.h5"
FAST = VALIDATION_DIR / "dem-5c3093abd07ae686.h5"  # 350 rpm
SLOW = VALIDATION_DIR / "dem-57ed37b232c5816c.h5"  # 150 rpm


def test_a_law_of_speed_fitted_to_three_runs_predicts_the_one_left_out(tmp_path):
    relative = BASELINE.relative_to(Path.cwd()) if BASELINE.is_relative_to(Path.cwd()) else BASELINE
    argv = ["study", "law", "--results", str(BASELINE), str(FAST), str(SLOW), "--held-out", str(relative)]
    argv += ["--covariates", "speed", "--phases", "2", "--max-iterations", "5", "--out", str(tmp_path)]
    assert main(argv) == 0
    record = json.loads((tmp_path / "law.json").read_text())
    assert record["covariates"] == ["speed"] and record["n_phases"] == 2
    assert record["n_parameters"] == 2 * (2 * 2 + 2) + 2  # (1, speed) for 2 axial moves a phase, 2 switches, entry
    assert [row["fitted_with"] for row in record["self"]] == [True] * 3
    (left,) = record["held_out"]
    assert not left["fitted_with"] and "250 rpm" in left["run"]
    # even five EM iterations put every run's hold-up within a quarter of the DEM's, and a
    # faster impeller holds less
    for row in record["self"] + record["held_out"]:
        assert abs(row["holdup_error"]) < 0.25, row
    by_speed = {row["run"].split("(")[1].split()[0]: row["holdup"] for row in record["self"]}
    assert by_speed["150"] > by_speed["250"] > by_speed["350"]
    assert np.isfinite(record["held_out_log_likelihood_per_step"]).all()


def test_an_unknown_covariate_or_a_missing_file_is_one_line(tmp_path, capsys):
    assert main(["study", "law", "--covariates", "speed,colour", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert (
        len(err) == 1
        and "colour" in err[0]
        and "valid: speed, length, position, feed, speed2, position2, weir" in err[0]
    )
    missing = tmp_path / "nothing.h5"
    assert main(["study", "law", "--results", str(missing), str(BASELINE), "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nothing.h5" in err[0]
    argv = ["study", "law", "--results", str(BASELINE), str(FAST), "--held-out", str(SLOW), "--out", str(tmp_path)]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and SLOW.name in err[0] and "not among the runs fitted" in err[0]
