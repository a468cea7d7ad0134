"""The out-of-sample study over runs: on the shipped validation baseline it is the memory
check's out-of-sample record, with the run's own structure refitted; a file it cannot use
is refused in one line naming it."""

import dataclasses
import json

from coupling.cache import load_entry, save_entry
from workflows.cli.main import main
from workflows.shipped import VALIDATION_DIR

BASELINE = VALIDATION_DIR / "dem-aa093a229dfd2ce4.h5"


def test_the_study_reports_each_runs_refit_against_its_second_half(tmp_path, capsys):
    assert main(["study", "holdout", "--results", str(BASELINE), "--out", str(tmp_path)]) == 0
    printed = capsys.readouterr().out
    (run,) = json.loads((tmp_path / "holdout.json").read_text())["runs"]
    assert run["name"] == "validation-baseline" and "| validation-baseline |" in printed
    assert run["refit_phases_per_kind"] == run["run_phases_per_kind"] > 1
    second = run["dem_mean_s"]
    assert run["mean_inside"] == (second["low"] <= run["pbm_mean_s"] <= second["high"])
    inside = int(run["mean_inside"]), int(run["variance_inside"])
    assert f"inside: mean {inside[0]} of 1, variance {inside[1]} of 1" in printed
    assert (tmp_path / "holdout.png").stat().st_size > 5_000


def test_a_file_without_a_phase_model_is_refused_by_name(tmp_path, capsys):
    entry = load_entry(BASELINE)
    plain = tmp_path / "plain.h5"
    save_entry(plain, dataclasses.replace(entry, table=entry.table.replace(phases=None)))
    assert main(["study", "holdout", "--results", str(plain), "--out", str(tmp_path)]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(plain) in err[0] and "no phase model" in err[0]
