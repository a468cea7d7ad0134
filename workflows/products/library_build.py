"""``pbmdem library build`` and ``pbmdem library status``: the DEM runs of a library made
from configuration files, on a Slurm cluster as one job array or here one after the other,
and their results added to the library folder.

A library folder holds, like ``workflows/reference/library/``, its results files
``dem-<key>.h5`` (the cache's own names: a hard link to the cache entry, a copy across
file systems), beside the build's ``manifest.json``, ``configs/`` and ``slurm/`` (the job
scripts, the tasks' output). A run's results are added as soon as its task is seen
completed, so ``pbmdem library fit --results DIR/dem-*.h5`` fits what has finished.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
from pathlib import Path

from coupling.errors import ConfigError
from coupling.files import distinct_inputs
from dem.cluster import check_tasks
from dem.run import can_resume, prepare_run
from workflows.config import Config, load_config
from workflows.pipeline.log import Log, quiet
from workflows.pipeline.slurm import (
    Manifest,
    TaskStatus,
    array_status,
    prepare_tasks,
    refuse_live_build,
    resubmit,
    submit_array,
    task_config,
    write_manifest,
)
from workflows.pipeline.stages import dem_stage

SCHEDULERS = ("slurm", "local")


def library_configs(config_files: list[str | Path]) -> dict[str, Config]:
    """Each configuration file, validated, by its file name without ``.toml`` (the task's
    name); two files of one name are refused."""
    paths = distinct_inputs(config_files, "configuration file")
    configs: dict[str, Config] = {}
    for path in paths:
        if path.stem in configs:
            raise ConfigError(f"two configuration files are named {path.name}; a build names its runs by file name")
        configs[path.stem] = load_config(path)
    return configs


def build_library(
    config_files: list[str | Path],
    library_dir: str | Path,
    scheduler: str = "slurm",
    runs_root: str | Path = "runs",
    np: int | None = None,
    partition: str | None = None,
    env: dict[str, str] | None = None,
    log: Log = quiet,
) -> tuple[TaskStatus, ...]:
    """The runs of ``config_files`` into the library ``library_dir`` through the cached DEM
    stage under ``runs_root``. ``slurm``: one job array (:func:`workflows.pipeline.slurm.submit_array`),
    returning at once with the tasks' states; ``local``: each run here in turn (an
    interrupted one resumed), its results added. Every file is validated first."""
    if scheduler not in SCHEDULERS:
        raise ConfigError(f"scheduler {scheduler!r} is not one of {', '.join(SCHEDULERS)}")
    if np is not None:  # before the local path claims a run directory for a command that cannot start
        check_tasks(np)
    configs = library_configs(config_files)
    if scheduler == "slurm":
        submit_array(configs, library_dir, runs_root, np, partition, env, log, reference_dir=())
        return library_status(library_dir, env)
    refuse_live_build(library_dir, env)
    folder, tasks = prepare_tasks(configs, library_dir, srun=False)
    write_manifest(folder, Manifest(str(Path(runs_root).resolve()), np, None, (), tasks))
    for task in tasks:
        config = task_config(folder, task)
        log(f"library: {task.name}: starting, resuming or reusing")
        resume = can_resume(prepare_run(config.dem), runs_root)
        dem_stage(config, runs_root, np=np, resume=resume, progress=False, log=log, reference_dir=())
    return library_status(folder, env)


def library_status(
    library_dir: str | Path, env: dict[str, str] | None = None, resubmit_failed: bool = False, log: Log = quiet
) -> tuple[TaskStatus, ...]:
    """Every task of the build in ``library_dir`` (:func:`workflows.pipeline.slurm.array_status`),
    a completed one's results added to the folder and named there; with
    ``resubmit_failed``, the failed tasks submitted again as one array (resuming from their
    restart files) and their new states."""
    states = add_to_library(library_dir, array_status(library_dir, env))
    failed = [s.task for s in states if s.state == "failed" and s.task.job is not None]
    here = [s.task.name for s in states if s.state == "failed" and s.task.job is None]
    if resubmit_failed and here:
        raise ConfigError(
            f"{', '.join(here)} failed in a build run here, not as Slurm jobs: nothing to resubmit; "
            "build the same configurations again with --scheduler local, which resumes them from their restart files"
        )
    if resubmit_failed and failed:
        resubmit(library_dir, failed, env, log)
        states = add_to_library(library_dir, array_status(library_dir, env))
    return states


def add_to_library(library_dir: str | Path, states: tuple[TaskStatus, ...]) -> tuple[TaskStatus, ...]:
    """Each completed task's results file linked into ``library_dir`` under its own name
    (copied where a hard link cannot be made, whole or not at all); the states with those
    paths."""
    out = []
    for state in states:
        if state.results is not None:
            target = Path(library_dir) / state.results.name
            if not target.exists():
                try:
                    os.link(state.results, target)
                except OSError:  # another file system: a copy, renamed into place whole, since an
                    # existing name is never copied again
                    part = target.with_name(f".{target.name}.{os.getpid()}.part")
                    try:
                        shutil.copy2(state.results, part)
                        os.replace(part, target)
                    finally:
                        part.unlink(missing_ok=True)
            state = dataclasses.replace(state, results=target)
        out.append(state)
    return tuple(out)


def status_table(states: tuple[TaskStatus, ...]) -> str:
    """One row per configuration: index, name, state (Slurm's word beside it), job id,
    elapsed time, and the results file or, when failed, the reason."""
    rows = [("#", "run", "state", "job", "elapsed", "results")]
    for s in states:
        state = s.state if not s.slurm_state or s.slurm_state.lower() == s.state else f"{s.state} ({s.slurm_state})"
        rows.append(
            (
                str(s.task.index),
                s.task.name,
                state,
                s.task.job_id or "-",
                s.elapsed or "-",
                str(s.results) if s.results is not None else s.reason or "-",
            )
        )
    widths = [max(len(r[i]) for r in rows) for i in range(5)]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r[:5], widths)) + "  " + r[5] for r in rows]
    counts = {k: sum(s.state == k for s in states) for k in ("completed", "running", "pending", "failed")}
    lines.append(", ".join(f"{n} {k}" for k, n in counts.items()))
    return "\n".join(line.rstrip() for line in lines)
