"""Cluster path: cost arithmetic and the batch script."""

import pytest

from coupling.errors import ConfigError
from dem.cluster import estimate_cost, mpi_command, slurm_script
from workflows.config import load_preset


def test_cost_is_steps_times_particles_over_throughput():
    dem = load_preset("paper").dem
    est = estimate_cost(dem, particles_held=10_000, particle_steps_per_core_s=1e6, cores=4, parallel_efficiency=1.0)
    steps = dem.operation.duration_s / dem.timestep_s
    assert est.steps == pytest.approx(steps, abs=1)
    assert est.core_hours == pytest.approx(steps * 10_000 / 1e6 / 3600, rel=1e-6)
    assert est.wall_hours == pytest.approx(est.core_hours / 4)


def test_mpi_command_and_slurm_script():
    dem = load_preset("paper").dem
    assert mpi_command(dem, 1) == ["liggghts", "-in", "in.blender"]
    assert mpi_command(dem, 8)[:4] == ["mpirun", "--allow-run-as-root", "-np", "8"]
    # a launcher without {np} takes the task count from its allocation: used on one rank too
    srun = dem.model_copy(update={"run": dem.run.model_copy(update={"launcher": "srun"})})
    assert mpi_command(srun, 1) == ["srun", "liggghts", "-in", "in.blender"]
    script = slurm_script(dem, "/scratch/run 1", np=16, wall_hours=10, partition="compute")
    assert "#SBATCH --ntasks=16" in script and "#SBATCH --time=13:00:00" in script
    assert "cd '/scratch/run 1'" in script
    assert "mpirun --allow-run-as-root -np 16 liggghts -in in.blender" in script
    assert "#SBATCH --time=00:10:00" in slurm_script(dem, "/x", np=1, wall_hours=0.001)  # at least 10 minutes
    with pytest.raises(ConfigError, match="np must be >= 1, got 0"):
        slurm_script(dem, "/x", np=0, wall_hours=1)
    with pytest.raises(ConfigError, match="particles_held"):
        estimate_cost(dem, 0, 1e6, 2)


def test_cli_slurm_writes_deck_and_script(tmp_path, capsys):
    from workflows.cli.main import main

    out = tmp_path / "job"
    assert (
        main(
            [
                "dem",
                "slurm",
                "--preset",
                "paper",
                "--np",
                "16",
                "--holdup",
                "40000",
                "--throughput",
                "4e6",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    text = capsys.readouterr().out
    assert (out / "in.blender").is_file() and (out / "meshes" / "impeller.stl").is_file()
    script = (out / "job.slurm").read_text()
    assert f"cd {out.resolve()}" in script and "#SBATCH --ntasks=16" in script
    assert "core-hours" in text and "sbatch job.slurm" in text


# ----------------------------------------------------------------------------- a real cluster
def _free_port() -> int:
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@pytest.fixture(scope="module")
def slurm_cluster(tmp_path_factory):
    """A one-node Slurm cluster of this machine (munged, slurmctld, slurmd; `make setup`
    installs them). Yields the environment that points Slurm's commands at it."""
    import os
    import shutil
    import socket
    import subprocess
    import time

    missing = [
        p for p in ("munge", "munged", "slurmctld", "slurmd", "sbatch", "squeue", "scontrol") if shutil.which(p) is None
    ]
    if missing:
        pytest.fail(f"not installed: {', '.join(missing)} (make setup installs slurm-wlm and munge)")
    if os.geteuid() != 0:
        pytest.skip("starting slurmd needs root (CI runs as root)")
    root = tmp_path_factory.mktemp("slurm")
    for sub in ("state", "spool", "log"):
        (root / sub).mkdir()
    host = socket.gethostname()
    conf = root / "slurm.conf"
    conf.write_text(
        "\n".join(
            [
                "ClusterName=pbmdemtest",
                f"SlurmctldHost={host}",
                "AuthType=auth/munge",
                "CredType=cred/munge",
                "ProctrackType=proctrack/linuxproc",
                "TaskPlugin=task/none",
                "ReturnToService=2",
                "SlurmUser=root",
                "SlurmdUser=root",
                "SchedulerType=sched/backfill",
                "SelectType=select/cons_tres",
                "SelectTypeParameters=CR_Core",
                "JobAcctGatherType=jobacct_gather/none",
                "AccountingStorageType=accounting_storage/none",
                "MpiDefault=none",
                f"SlurmctldPort={_free_port()}",
                f"SlurmdPort={_free_port()}",
                f"SlurmctldPidFile={root}/slurmctld.pid",
                f"SlurmdPidFile={root}/slurmd.pid",
                f"SlurmdSpoolDir={root}/spool",
                f"StateSaveLocation={root}/state",
                f"SlurmctldLogFile={root}/log/slurmctld.log",
                f"SlurmdLogFile={root}/log/slurmd.log",
                f"NodeName={host} CPUs={os.cpu_count()} State=UNKNOWN",
                "PartitionName=test Nodes=ALL Default=YES MaxTime=INFINITE State=UP",
                "",
            ]
        )
    )
    env = {**os.environ, "SLURM_CONF": str(conf)}
    if subprocess.run(["munge", "-n"], capture_output=True).returncode != 0:
        os.makedirs("/run/munge", exist_ok=True)
        shutil.chown("/run/munge", "munge", "munge")
        subprocess.run(["su", "-s", "/bin/sh", "munge", "-c", "munged"], check=True, capture_output=True)
    for daemon in ("slurmctld", "slurmd"):
        subprocess.run([daemon], env=env, check=True, capture_output=True)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        state = subprocess.run(["sinfo", "-h", "-o", "%t"], env=env, capture_output=True, text=True).stdout.strip()
        if state == "idle":
            break
        time.sleep(0.5)
    else:
        pytest.fail(f"the one-node cluster did not come up (node state {state!r}); logs in {root / 'log'}")
    yield env
    for name in ("slurmd", "slurmctld"):
        pid_file = root / f"{name}.pid"
        if pid_file.is_file():
            subprocess.run(["kill", pid_file.read_text().strip()], capture_output=True)


@pytest.mark.liggghts
@pytest.mark.slow
def test_the_batch_script_runs_under_slurm(slurm_cluster, tmp_path, capsys):
    """`pbmdem dem slurm` writes a script that sbatch runs to completion on 2 tasks, and its
    dumps post-process cleanly."""
    import subprocess
    import time

    from coupling.cache import load_entry
    from workflows.cli.main import main
    from workflows.config import config_from_dict, dump_toml

    data = load_preset("smoke").to_dict()
    data["name"] = "slurmcheck"
    data["dem"]["operation"]["duration_s"] = 2.0
    data["dem"]["tables"]["window_s"] = 1.0  # velocity windows inside the 2-s run
    config_file = tmp_path / "tiny.toml"
    config_file.write_text(dump_toml(config_from_dict(data)))
    run = tmp_path / "run"
    assert (
        main(
            [
                "dem",
                "slurm",
                "--config",
                str(config_file),
                "--np",
                "2",
                "--out",
                str(run),
                "--holdup",
                "500",
                "--throughput",
                "3e6",
            ]
        )
        == 0
    )
    job = (
        subprocess.run(
            ["sbatch", "--parsable", "job.slurm"],
            cwd=run,
            env=slurm_cluster,
            capture_output=True,
            text=True,
            check=True,
        )
        .stdout.strip()
        .split(";")[0]
    )
    deadline = time.monotonic() + 600
    while time.monotonic() < deadline:
        queued = subprocess.run(["squeue", "-h", "-j", job], env=slurm_cluster, capture_output=True, text=True).stdout
        if not queued.strip():
            break
        time.sleep(1)
    shown = subprocess.run(["scontrol", "show", "job", job], env=slurm_cluster, capture_output=True, text=True).stdout
    output = "\n".join(p.read_text(errors="replace")[-2000:] for p in run.glob("pbmdem-slurmcheck-*.out"))
    assert "JobState=COMPLETED" in shown and "ExitCode=0:0" in shown, shown + output
    assert "Loop time of" in output and "on 2 procs" in output
    capsys.readouterr()
    assert (
        main(
            [
                "dem",
                "post",
                "--config",
                str(config_file),
                "--dumps",
                str(run / "dumps" / "dump.*.txt"),
                "--out-file",
                str(tmp_path / "r.h5"),
            ]
        )
        == 0
    )
    summary = load_entry(tmp_path / "r.h5").summary
    assert summary["t_end_s"] == pytest.approx(2.0, abs=0.1) and summary["lost"] == 0
    assert summary["inserted"] > 50


def _tiny(name: str, feed: float, duration: float = 6.0):
    from workflows.config import config_from_dict

    data = load_preset("smoke").to_dict()
    data["name"] = name
    data["dem"]["operation"]["duration_s"] = duration
    data["dem"]["operation"]["feed_rate_total_per_s"] = feed
    data["dem"]["tables"]["window_s"] = 1.0
    data["dem"]["numerics"]["restart_interval_s"] = 0.5
    return config_from_dict(data)


@pytest.mark.liggghts
@pytest.mark.slow
def test_a_campaign_runs_on_slurm_and_a_killed_run_is_resumed(slurm_cluster, tmp_path, monkeypatch):
    """Two runs as Slurm jobs; one is cancelled once it has a restart file, and the follower
    resubmits it with --resume; both end completed and cached, as a local run would."""
    import subprocess

    from dem.run import prepare_run, read_status
    from workflows.pipeline.cluster import run_campaign_on_slurm
    from workflows.pipeline.stages import dem_stage

    monkeypatch.chdir(tmp_path)
    configs = {"slow": _tiny("slurm-slow", 73.7), "fast": _tiny("slurm-fast", 110.0)}
    runs = tmp_path / "runs"
    key = prepare_run(configs["slow"].dem).key
    cancelled = []

    def watch(jobs):
        job = jobs["slow"]
        if not cancelled and job.state == "queued" and list((runs / key / "restart").glob("restart.*.bin")):
            subprocess.run(["scancel", job.job_id], env=slurm_cluster, check=True)
            cancelled.append(job.job_id)

    lines = []
    jobs = run_campaign_on_slurm(
        configs, runs, 1, lines.append, env=slurm_cluster, poll_s=0.5, reference_dir=(), watch=watch
    )
    assert cancelled, "the slow run finished before a restart file was seen: nothing was cancelled"
    assert {j.state for j in jobs.values()} == {"completed"}, lines
    assert jobs["slow"].attempts == 2 and jobs["fast"].attempts == 1
    assert any("resuming" in line for line in lines)
    assert read_status(runs / key)["resumed_from"], "the second job did not continue from the restart file"
    for config in configs.values():
        assert dem_stage(config, runs, solver=False, reference_dir=()).source == "cache"
    # a second call finds everything done: no job
    again = run_campaign_on_slurm(configs, runs, 1, lines.append, env=slurm_cluster, poll_s=0.5, reference_dir=())
    assert {j.state for j in again.values()} == {"ready"}
