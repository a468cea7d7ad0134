"""`pbmdem library build` / `status`: the job array's script, sacct's text, and three smoke
runs built as one array on the one-node cluster, one of them killed and resubmitted."""

import json
import subprocess
import time
from pathlib import Path

import pytest

from coupling.errors import ConfigError
from dem.cluster import SRUN_LAUNCHER, array_script, array_spec, under_srun
from workflows.config import dump_toml, load_preset
from workflows.pipeline.slurm import ArrayTask, JobRecord, TaskStatus, parse_sacct, task_state
from workflows.products.library_build import status_table


# ----------------------------------------------------------------------------- pure: sacct's text
def test_sacct_array_lines_steps_and_pending_ranges():
    """What sacct prints for an array with accounting: the tasks' own lines, their steps
    (left out), a cancelled task's "by <uid>", pending tasks listed as one range."""
    text = "\n".join(
        [
            "123_0|COMPLETED|0:0|00:00:41",
            "123_0.batch|COMPLETED|0:0|00:00:41",
            "123_0.extern|COMPLETED|0:0|00:00:41",
            "123_0.0|COMPLETED|0:0|00:00:40",
            "123_1|CANCELLED by 0|0:15|00:00:12",
            "123_1.batch|CANCELLED|0:15|00:00:13",
            "123_[2-4,7]|PENDING|0:0|00:00:00",
            "124_[9-13:2%2]|PENDING|0:0|00:00:00",
            "",
            "garbage",
        ]
    )
    jobs = parse_sacct(text)
    assert sorted(jobs) == sorted(["123_0", "123_1", "123_2", "123_3", "123_4", "123_7", "124_9", "124_11", "124_13"])
    assert jobs["123_0"] == JobRecord("123_0", "COMPLETED", "0:0", "00:00:41")
    assert jobs["123_1"].state == "CANCELLED" and jobs["123_1"].exit_code == "0:15"
    assert {jobs[j].task_state for j in ("123_2", "123_7", "124_13")} == {"pending"}


def test_completion_log_and_squeue_lines():
    """sacct --completion lists an array task by its own id; squeue -r -o '%i|%T|0:0|%M'
    lists running and pending tasks (measured on Slurm 22.05)."""
    assert parse_sacct("3|FAILED|3:0|00:00:02\n2|COMPLETED|0:0|00:00:02\n") == {
        "3": JobRecord("3", "FAILED", "3:0", "00:00:02"),
        "2": JobRecord("2", "COMPLETED", "0:0", "00:00:02"),
    }
    queue = parse_sacct("45_1|RUNNING|0:0|0:14\n45_2|PENDING|0:0|0:00\n")
    assert queue["45_1"].task_state == "running" and queue["45_2"].task_state == "pending"


@pytest.mark.parametrize(
    ("slurm", "ours"),
    [
        ("PENDING", "pending"),
        ("REQUEUED", "pending"),
        ("RUNNING", "running"),
        ("COMPLETING", "running"),
        ("COMPLETED", "completed"),
        ("FAILED", "failed"),
        ("CANCELLED by 0", "failed"),
        ("CANCELLED+", "failed"),
        ("TIMEOUT", "failed"),
        ("NODE_FAIL", "failed"),
        ("OUT_OF_MEMORY", "failed"),
        ("", "failed"),
    ],
)
def test_slurm_states_map_onto_four(slurm, ours):
    assert task_state(slurm) == ours


# ----------------------------------------------------------------------------- pure: the script
def test_array_spec_runs_of_indices():
    assert array_spec([0, 1, 2]) == "0-2"
    assert array_spec([5, 0, 2, 3, 7, 8]) == "0,2-3,5,7-8"
    assert array_spec([4]) == "4"
    with pytest.raises(ConfigError, match=r"integers >= 0, got \[-1\]"):
        array_spec([-1])


def test_array_script_golden():
    script = array_script(
        {0: ["python", "-m", "workflows.cli", "dem", "run", "--config", "/lib/configs/a.toml"], 2: ["echo", "b c"]},
        "/code root",
        1,
        0.05,
        "/lib/slurm",
        job_name="pbmdem-lib",
        partition="short",
    )
    assert script == "\n".join(
        [
            "#!/bin/bash",
            "#SBATCH --job-name=pbmdem-lib",
            "#SBATCH --array=0,2",
            "#SBATCH --ntasks=1",
            "#SBATCH --cpus-per-task=1",
            "#SBATCH --time=00:10:00",
            "#SBATCH --output=/lib/slurm/%A_%a.out",
            "#SBATCH --partition=short",
            "set -euo pipefail",
            "cd '/code root'",
            'echo "$SLURM_JOB_ID" > /lib/slurm/"${SLURM_ARRAY_JOB_ID}_${SLURM_ARRAY_TASK_ID}.jobid"',
            'case "$SLURM_ARRAY_TASK_ID" in',
            "    0) python -m workflows.cli dem run --config /lib/configs/a.toml ;;",
            "    2) echo 'b c' ;;",
            '    *) echo "pbmdem: no task $SLURM_ARRAY_TASK_ID in this array" >&2; exit 2 ;;',
            "esac",
            "",
        ]
    )
    # no estimate: no time request (the partition's limit)
    assert "--time" not in array_script({0: ["true"]}, "/", 2, None, "/r")
    with pytest.raises(ConfigError, match="at least one task"):
        array_script({}, "/", 1, 1.0, "/r")


def test_under_srun_keeps_the_run_key_and_a_site_srun():
    from dem.deck import build_deck, deck_hash

    dem = load_preset("smoke").dem
    srun = under_srun(dem)
    assert srun.run.launcher == SRUN_LAUNCHER and deck_hash(build_deck(srun)) == deck_hash(build_deck(dem))
    own = dem.model_copy(update={"run": dem.run.model_copy(update={"launcher": "srun --mpi=pmi2 --cpu-bind=cores"})})
    assert under_srun(own) is own


def test_status_table_rows():
    tasks = [
        ArrayTask(0, "fast", "configs/fast.toml", "k0", "45", 1),
        ArrayTask(1, "slow", "configs/slow.toml", None, "47", 2),
    ]
    table = status_table(
        (
            TaskStatus(tasks[0], "completed", "COMPLETED", "00:01:10", Path("/lib/dem-k0.h5")),
            TaskStatus(tasks[1], "failed", "CANCELLED", "00:00:12", None, "job 47_1 ended CANCELLED"),
        )
    )
    lines = table.splitlines()
    assert lines[0].split() == ["#", "run", "state", "job", "elapsed", "results"]
    assert lines[1].split() == ["0", "fast", "completed", "45_0", "00:01:10", "/lib/dem-k0.h5"]
    assert lines[2].split()[:5] == ["1", "slow", "failed", "(CANCELLED)", "47_1"]
    assert lines[-1] == "1 completed, 0 running, 0 pending, 1 failed"


# ----------------------------------------------------------------------------- the cluster
def _tiny(name: str, feed: float, duration: float = 6.0):
    from workflows.config import config_from_dict

    data = load_preset("smoke").to_dict()
    data["name"] = name
    data["dem"]["operation"]["duration_s"] = duration
    data["dem"]["operation"]["feed_rate_total_per_s"] = feed
    data["dem"]["tables"]["window_s"] = 1.0
    data["dem"]["numerics"]["restart_interval_s"] = 0.5
    return config_from_dict(data)


def _wait(library, env, until, timeout_s=1500, poll_s=0.5, each=None):
    from workflows.pipeline.slurm import array_status

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        states = array_status(library, env)
        if each is not None:
            each(states)
        if until(states):
            return states
        time.sleep(poll_s)
    pytest.fail(f"the array did not get there in {timeout_s} s: {[(s.task.name, s.state) for s in states]}")


@pytest.mark.liggghts
@pytest.mark.slow
def test_library_build_three_runs_as_one_array(slurm_cluster, tmp_path, monkeypatch, capsys):
    """Three smoke runs (feed rates differing) built as one job array of 1-rank tasks; one is
    cancelled once it has a restart file: sacct reports it failed (CANCELLED), `status
    --resubmit-failed` submits it again, it resumes and completes; all three results end up
    in the library folder, readable."""
    from dem.run import prepare_run, read_status
    from workflows.cli.main import main
    from workflows.pipeline.results import load_results

    monkeypatch.setenv("SLURM_CONF", slurm_cluster["SLURM_CONF"])
    feeds = {"feed-a": 73.7, "feed-b": 90.0, "feed-c": 110.0}
    files = []
    for name, feed in feeds.items():
        files.append(tmp_path / f"{name}.toml")
        files[-1].write_text(dump_toml(_tiny(f"lib-{name}", feed)))
    library, runs = tmp_path / "lib", tmp_path / "runs"
    common = ["--library", str(library)]
    assert main(["library", "build", *map(str, files), *common, "--runs-dir", str(runs), "--np", "1"]) == 0
    out = capsys.readouterr().out
    # it returned with the tasks queued or running, not finished
    assert "0 completed" in out and "follow it with: pbmdem library status" in out, out
    manifest = json.loads((library / "manifest.json").read_text())
    assert {t["job"] for t in manifest["tasks"]} == {manifest["tasks"][0]["job"]}, "not one array"
    assert [t["name"] for t in manifest["tasks"]] == list(feeds)
    script = (library / "slurm" / "array-1.sh").read_text()
    assert "#SBATCH --array=0-2" in script and "#SBATCH --ntasks=1" in script
    assert "srun --mpi=pmix" in (library / "configs" / "feed-a.toml").read_text()

    # cancel the slowest-feeding run once it has a restart file
    victim = manifest["tasks"][0]
    run_dir = runs / prepare_run(_tiny("lib-feed-a", 73.7).dem).key
    cancelled = []

    def cancel(states):
        state = next(s for s in states if s.task.name == victim["name"])
        if not cancelled and state.state == "running" and list((run_dir / "restart").glob("restart.*.bin")):
            subprocess.run(["scancel", state.task.job_id], env=slurm_cluster, check=True)
            cancelled.append(state.task.job_id)

    states = _wait(library, slurm_cluster, lambda ss: all(s.state in ("completed", "failed") for s in ss), each=cancel)
    assert cancelled, "the run finished before a restart file was seen: nothing was cancelled"
    by_name = {s.task.name: s for s in states}
    assert by_name["feed-a"].state == "failed" and by_name["feed-a"].slurm_state == "CANCELLED", by_name["feed-a"]
    assert {by_name[n].state for n in ("feed-b", "feed-c")} == {"completed"}
    assert by_name["feed-b"].slurm_state == "COMPLETED" and by_name["feed-b"].elapsed  # read from sacct

    capsys.readouterr()
    assert main(["library", "status", *common]) == 0
    table = capsys.readouterr().out
    rows = {line.split()[1]: line.split()[2:4] for line in table.splitlines()[1:-1]}
    assert rows["feed-a"] == ["failed", "(CANCELLED)"] and rows["feed-b"][0] == rows["feed-c"][0] == "completed"
    assert len(list(library.glob("dem-*.h5"))) == 2  # the completed ones already in the library

    assert main(["library", "status", *common, "--resubmit-failed"]) == 0
    manifest = json.loads((library / "manifest.json").read_text())
    again = manifest["tasks"][0]
    assert again["attempts"] == 2 and again["job"] != victim["job"]
    assert "--resume" in (library / "slurm" / "array-2.sh").read_text()
    states = _wait(library, slurm_cluster, lambda ss: all(s.state in ("completed", "failed") for s in ss), poll_s=2)
    assert {s.state for s in states} == {"completed"}, [(s.task.name, s.reason) for s in states]
    assert read_status(run_dir)["resumed_from"], "the resubmitted task did not continue from the restart file"

    capsys.readouterr()
    assert main(["library", "status", *common]) == 0
    table = capsys.readouterr().out
    assert "3 completed, 0 running, 0 pending, 0 failed" in table
    added = sorted(library.glob("dem-*.h5"))
    assert len(added) == 3 and {s.results.name for s in states} == {p.name for p in added}
    feeds_read = []
    for path in added:
        results, config = load_results(path)
        assert results.summary.t_end_s == pytest.approx(6.0, abs=0.1) and results.summary.accounting["lost"] == 0
        feeds_read.append(config.dem.operation.feed_rate_total_per_s)
    assert sorted(feeds_read) == sorted(feeds.values())

    # the local scheduler on the same runs: the cache serves them, no run starts
    local = tmp_path / "local-lib"
    assert (
        main(
            [
                "library",
                "build",
                *map(str, files),
                "--library",
                str(local),
                "--runs-dir",
                str(runs),
                "--scheduler",
                "local",
            ]
        )
        == 0
    )
    assert "3 completed" in capsys.readouterr().out
    assert sorted(p.name for p in local.glob("dem-*.h5")) == [p.name for p in added]


@pytest.mark.liggghts
@pytest.mark.slow
def test_the_campaign_follower_uses_the_array_path(slurm_cluster, tmp_path):
    """`validate --scheduler slurm`'s follower: the missing run as an array task, cancelled
    once it has a restart file, resubmitted by the follower and resumed; a second call finds
    everything done and submits nothing."""
    from dem.run import prepare_run, read_status
    from workflows.pipeline.slurm import run_campaign_on_slurm
    from workflows.pipeline.stages import dem_stage

    configs = {"slow": _tiny("follow-slow", 80.0)}
    runs = tmp_path / "runs"
    run_dir = runs / prepare_run(configs["slow"].dem).key
    cancelled = []

    def watch(states):
        (state,) = states
        if not cancelled and state.state == "running" and list((run_dir / "restart").glob("restart.*.bin")):
            subprocess.run(["scancel", state.task.job_id], env=slurm_cluster, check=True)
            cancelled.append(state.task.job_id)

    lines = []
    states = run_campaign_on_slurm(
        configs, runs, 1, lines.append, env=slurm_cluster, poll_s=0.5, reference_dir=(), watch=watch
    )
    assert cancelled, "the run finished before a restart file was seen: nothing was cancelled"
    assert states["slow"].state == "completed" and states["slow"].task.attempts == 2, lines
    assert any("resuming from restart files: slow" in line for line in lines), lines
    assert read_status(run_dir)["resumed_from"]
    assert dem_stage(configs["slow"], runs, solver=False, reference_dir=()).source == "cache"
    again = run_campaign_on_slurm(configs, runs, 1, lines.append, env=slurm_cluster, poll_s=0.5, reference_dir=())
    assert again["slow"].state == "completed" and again["slow"].task.job is None


def test_build_refuses_before_anything_runs(tmp_path, capsys):
    """Two files making one DEM run, two files of one name, a folder without a build: one
    line each, exit 2, nothing written."""
    from workflows.cli.main import main

    smoke = load_preset("smoke")
    (tmp_path / "a").mkdir()
    one, same = tmp_path / "one.toml", tmp_path / "same.toml"
    one.write_text(dump_toml(smoke))
    same.write_text(dump_toml(smoke.model_copy(update={"name": "renamed"})))
    lib = tmp_path / "lib"
    args = ["--library", str(lib), "--scheduler", "local", "--runs-dir", str(tmp_path / "runs")]
    assert main(["library", "build", str(one), str(same), *args]) == 2
    assert "one and same make the same DEM run" in capsys.readouterr().err
    twin = tmp_path / "a" / "one.toml"
    twin.write_text(dump_toml(smoke.model_copy(update={"name": "twin"})))
    assert main(["library", "build", str(one), str(twin), *args]) == 2
    assert "two configuration files are named one.toml" in capsys.readouterr().err
    assert not lib.exists()
    assert main(["library", "status", "--library", str(lib)]) == 2
    assert "holds no build (manifest.json not found)" in capsys.readouterr().err
