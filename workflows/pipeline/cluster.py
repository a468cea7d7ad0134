"""The cluster path: a run directory with its Slurm script and a core-hour estimate, from
the hold-up of a shipped run of the same blender and a measured throughput."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from coupling.errors import ConfigError
from coupling.files import writable_directory
from dem.cluster import estimate_cost, mpi_command, slurm_script
from dem.deck import MAIN_DECK, build_deck, write_deck
from workflows.config import Config, dump_toml
from workflows.pipeline.log import Log
from workflows.pipeline.slurm import TaskStatus, array_status, resubmit, submit_array
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
#: seconds between looks at the jobs
POLL_S = 30.0
#: submissions of one run before it is given up: the first, then resumes from its restart files
MAX_ATTEMPTS = 3


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
    watch: Callable[[tuple[TaskStatus, ...]], None] | None = None,
) -> dict[str, TaskStatus]:
    """Every run of ``configs`` that is neither cached, shipped nor completed under
    ``runs_root``, a task of one Slurm job array of ``np`` ranks each (default: the largest
    ``dem.run.np`` of the configs) -- :func:`workflows.pipeline.slurm.submit_array`, as
    ``pbmdem library build`` -- with its manifest in ``<runs_root>/slurm``; followed through
    :func:`workflows.pipeline.slurm.array_status` until no task is queued or running, a
    failed task resubmitted (resuming from its restart files) up to ``max_attempts``
    submissions. ``env``: the environment of the Slurm commands (e.g. SLURM_CONF);
    ``watch``: called with the tasks' states after every look. Returns every run's state by
    name; the results are then the cache's, like a local campaign's."""
    runs_root = writable_directory(runs_root, "runs directory").resolve()
    shipped = {} if reference_dir is None else {"reference_dir": reference_dir}
    folder = runs_root / "slurm"
    submit_array(configs, folder, runs_root, np, partition, env, log, **shipped)
    while True:
        states = array_status(folder, env)
        if watch is not None:
            watch(states)
        retry = [s for s in states if s.state == "failed" and s.task.job is not None and s.task.attempts < max_attempts]
        for s in retry:
            log(f"slurm: {s.task.name} failed ({s.reason}); submitting it again")
        if retry:
            resubmit(folder, [s.task for s in retry], env, log)
        elif not any(s.state in ("pending", "running") for s in states):
            return {s.task.name: s for s in states}
        time.sleep(poll_s)
