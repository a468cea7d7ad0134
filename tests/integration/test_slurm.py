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
    assert "srun --mpi=pmix liggghts -in in.blender" in script  # srun starts the ranks of the allocation
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


# ----------------------------------------------------------------------------- a real cluster (conftest.py)
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
