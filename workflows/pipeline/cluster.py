"""The cluster path: a run directory with its Slurm script and a core-hour estimate, from
the hold-up of a shipped run of the same blender and a measured throughput."""

from __future__ import annotations

import shlex
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from coupling.errors import ConfigError, SolverRunError
from coupling.files import writable_directory
from dem.cluster import batch_script, estimate_cost, mpi_command, slurm_script
from dem.deck import MAIN_DECK, build_deck, write_deck
from dem.run import can_resume, completed_run, prepare_run
from workflows.config import Config, dump_toml
from workflows.pipeline.log import Log
from workflows.pipeline.stages import results_available
from workflows.shipped import measured_throughput, reference_holdup

#: Particle-steps per second per core of the blender deck when no benchmark result is
#: found (LIGGGHTS 3.8.0, one core of the development machine).
DEFAULT_THROUGHPUT_PER_CORE = 3.9e6


@dataclass(frozen=True)
class ClusterPlan:
    run_dir: Path
    mpi_command: list[str]
    holdup: float
    holdup_source: str
    throughput: float
    throughput_source: str
    estimate: Any  # dem.cluster.CostEstimate


def cost_estimate(config: Config, np: int, holdup: float | None = None, throughput: float | None = None):
    """(estimate, hold-up, its source, throughput, its source) of a run of ``config`` on
    ``np`` cores: hold-up given or scaled from the shipped reference; throughput given,
    else the shipped paper-scale measurement when the particles are the same
    (:func:`workflows.shipped.measured_throughput`), else the development machine's
    (``pbmdem bench dem-deck`` measures this machine's: pass it as ``throughput``)."""
    if holdup is not None:
        holdup_source = "given with --holdup"
    else:
        try:
            holdup, holdup_source = reference_holdup(config.dem)
        except LookupError as exc:
            raise ConfigError(str(exc)) from None
    measured = None if throughput is not None else measured_throughput(config.dem)
    efficiency = 0.85
    if throughput is not None:
        throughput_source = "given with --throughput"
    elif measured is not None:
        throughput, throughput_source, measured_np = measured
        if np == measured_np:  # measured on these ranks: their parallel efficiency is in the rate
            efficiency = 1.0
    else:
        throughput, throughput_source = DEFAULT_THROUGHPUT_PER_CORE, "measured on the development machine"
    estimate = estimate_cost(config.dem, holdup, throughput, np, efficiency)
    return estimate, holdup, holdup_source, throughput, throughput_source


def plan_cluster_run(
    config: Config,
    out: str | Path,
    np: int,
    partition: str | None = None,
    holdup: float | None = None,
    throughput: float | None = None,
) -> ClusterPlan:
    """Write the run directory (deck, meshes, resolved config) and ``job.slurm`` with a
    core-hour estimate (:func:`cost_estimate`)."""
    estimate, holdup, holdup_source, throughput, throughput_source = cost_estimate(config, np, holdup, throughput)
    files = build_deck(config.dem)
    writable_directory(out, "run directory")
    files["config.toml"] = dump_toml(config)
    files["job.slurm"] = slurm_script(
        config.dem,
        str(Path(out).resolve()),
        np,
        estimate.wall_hours,
        job_name=f"pbmdem-{config.name}",
        partition=partition,
    )
    run_dir = write_deck(files, out)
    return ClusterPlan(
        run_dir, mpi_command(config.dem, np, MAIN_DECK), holdup, holdup_source, throughput, throughput_source, estimate
    )


# --------------------------------------------------------------------------- a campaign on Slurm
#: seconds between looks at the queue
POLL_S = 30.0
#: submissions of one run before it is given up: the first, then resumes from its restart files
MAX_ATTEMPTS = 3


@dataclass
class CampaignJob:
    """One campaign run on Slurm: its ``name``, resolved config file and job ``script``;
    the current ``job_id``, the ``attempts`` made, ``state`` (queued, completed, failed,
    ready: served without a job) and, when failed, the ``reason``."""

    name: str
    config: Config
    config_file: Path
    script: Path
    job_id: str | None = None
    attempts: int = 0
    state: str = "queued"
    reason: str = ""


def campaign_job_command(config_file: Path, runs_root: Path, np: int, resume: bool) -> list[str]:
    """The job's one command: the ordinary ``pbmdem dem run`` (LIGGGHTS on ``np`` ranks,
    the post-processing, the cache), so a run made on Slurm is found like a local one."""
    command = [sys.executable, "-m", "workflows.cli", "dem", "run", "--config", str(config_file)]
    command += ["--runs-dir", str(runs_root), "--np", str(np), "--no-progress"]
    return command + (["--resume"] if resume else [])


def _slurm(args: list[str], env: dict[str, str] | None) -> str:
    try:
        done = subprocess.run(args, env=env, capture_output=True, text=True, timeout=120)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise SolverRunError(f"{args[0]} could not run: {exc}") from None
    if done.returncode != 0:
        raise SolverRunError(f"{shlex.join(args)} failed: {(done.stderr or done.stdout).strip()[-500:]}")
    return done.stdout


def _submit(job: CampaignJob, runs_root: Path, np: int, partition: str | None, env, log: Log) -> None:
    """Write the job's script (resuming when the run left restart files) and submit it."""
    inputs = prepare_run(job.config.dem)
    resume = can_resume(inputs, runs_root)
    estimate, *_ = cost_estimate(job.config, np)
    job.script.write_text(
        batch_script(
            campaign_job_command(job.config_file, runs_root, np, resume),
            str(Path.cwd()),
            np,
            estimate.wall_hours,
            job_name=f"pbmdem-{job.name}",
            partition=partition,
            output=str(job.script.with_suffix("")) + "-%j.out",
        )
    )
    job.job_id = _slurm(["sbatch", "--parsable", str(job.script)], env).strip().split(";")[0]
    job.attempts += 1
    log(f"slurm: {job.name} submitted as job {job.job_id}{' (resuming)' if resume else ''}")


def run_campaign_on_slurm(
    configs: dict[str, Config],
    runs_root: str | Path,
    np: int | None,
    log: Log,
    partition: str | None = None,
    env: dict[str, str] | None = None,
    poll_s: float = POLL_S,
    max_attempts: int = MAX_ATTEMPTS,
    reference_dir: Path | tuple[Path, ...] | None = None,
    watch: Callable[[dict[str, CampaignJob]], None] | None = None,
) -> dict[str, CampaignJob]:
    """Every run of ``configs`` that is neither cached, shipped nor completed under
    ``runs_root``, as a Slurm job of ``np`` tasks (default: each config's ``dem.run.np``); follows them until none is left in the
    queue, resubmitting (``--resume``) a run that ended incomplete with restart files, up to
    ``max_attempts`` submissions. ``env``: the environment of the Slurm commands (e.g.
    SLURM_CONF); ``watch``: called with the jobs after every look at the queue. Returns
    every run's job record; the results are then the cache's, like a local campaign's."""
    runs_root = writable_directory(runs_root, "runs directory").resolve()
    jobs_dir = writable_directory(runs_root / "slurm", "Slurm job directory")
    shipped = {} if reference_dir is None else {"reference_dir": reference_dir}
    jobs: dict[str, CampaignJob] = {}
    for name, config in configs.items():
        job = CampaignJob(name, config, jobs_dir / f"{name}.toml", jobs_dir / f"{name}.slurm")
        jobs[name] = job
        if results_available(config, runs_root, **shipped):
            job.state = "ready"
            log(f"slurm: {name} needs no job (cached, shipped or completed)")
            continue
        job.config_file.write_text(dump_toml(config))
        _submit(job, runs_root, np or config.dem.run.np, partition, env, log)
    while any(j.state == "queued" for j in jobs.values()):
        time.sleep(poll_s)
        ids = [j.job_id for j in jobs.values() if j.state == "queued"]
        listed = set(_slurm(["squeue", "-h", "-o", "%i", "-j", ",".join(ids)], env).split())
        for job in jobs.values():
            if job.state != "queued" or job.job_id in listed:
                continue
            inputs = prepare_run(job.config.dem)
            if completed_run(inputs, runs_root) is not None:
                job.state = "completed"
                log(f"slurm: {job.name} completed (job {job.job_id})")
            elif job.attempts < max_attempts and can_resume(inputs, runs_root):
                log(f"slurm: {job.name} ended incomplete (job {job.job_id}); resuming from its restart files")
                _submit(job, runs_root, np or job.config.dem.run.np, partition, env, log)
            else:
                job.state = "failed"
                job.reason = (
                    f"job {job.job_id} ended without completing the run after {job.attempts} submission(s)"
                    + ("" if can_resume(inputs, runs_root) else " and left no restart file to resume from")
                    + f"; its output: {job.script.with_suffix('')}-{job.job_id}.out"
                )
                log(f"slurm: {job.name} failed: {job.reason}")
        if watch is not None:
            watch(jobs)
    return jobs
