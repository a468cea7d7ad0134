"""``pbmdem bench convergence`` end to end: a directory that is not the configuration's
completed run is refused in one line, and (marked ``liggghts``) the checks replayed on the
session's smoke run read every dump once, and a stop's results equal one pass's."""

import json

import pytest

from dem.deck import DUMP_GLOB, dump_step
from dem.run import prepare_run
from workflows.cli.main import main
from workflows.config import load_preset


def test_a_directory_that_is_no_completed_run_is_refused(tmp_path, capsys):
    argv = ["--preset", "smoke", "--run-dir", str(tmp_path), "--out-file", str(tmp_path / "c.json")]
    assert main(["bench", "convergence", *argv]) == 2
    err = capsys.readouterr().err
    assert f"{tmp_path}: not a completed run directory" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "c.json").exists()


@pytest.mark.liggghts
def test_checks_replayed_on_the_smoke_run(smoke_runs_root, tmp_path):
    out = tmp_path / "convergence.json"
    argv = ["--preset", "smoke", "--runs-dir", str(smoke_runs_root), "--every", "10", "--out-file", str(out)]
    assert main(["bench", "convergence", *argv]) == 0
    record = json.loads(out.read_text())
    key = prepare_run(load_preset("smoke").dem).key
    assert record["run"] == key and record["every_s"] == 10
    checks = record["checks"]
    dumps = sorted((smoke_runs_root / key).glob(DUMP_GLOB))
    t_last = max(dump_step(p) for p in dumps) * load_preset("smoke").dem.timestep_s
    # checks every 10 s from 2 x 10 s on, until the first converged one or the last dump
    assert [c["t_s"] for c in checks] == [20.0 + 10.0 * k for k in range(len(checks))]
    assert all(not c["converged"] for c in checks[:-1]) and checks[-1]["t_s"] <= t_last
    assert sum(c["dumps_read"] for c in checks) <= len(dumps)  # each dump read once
    assert sum(c["dem_wall_since_last_check_s"] for c in checks) <= record["dem_wall_s"] * (1 + 1e-9)
    assert record["complete_run_wall_s"] == pytest.approx(record["dem_wall_s"] + record["post_all_dumps_s"])
    if checks[-1]["converged"]:
        assert record["differs_from_one_pass"] == []
        assert record["stopped_run_wall_s"] < record["complete_run_wall_s"] * 1.5
    else:
        assert "stop_t_s" not in record and checks[-1]["t_s"] + 10.0 > t_last
