"""The cluster path: cost estimate from measured throughput, MPI command, Slurm batch and
job-array scripts.

The ``paper`` preset is a day on 2 cores; on a cluster the user wants the command, a batch
script and an honest estimate of the core-hours before submitting.
"""

from __future__ import annotations

import math
import shlex
from dataclasses import dataclass

from coupling.errors import ConfigError
from dem.config import DemConfig
from dem.deck import MAIN_DECK
from dem.liggghts import launch_command


@dataclass(frozen=True)
class CostEstimate:
    """Core-hours of a DEM run from a measured throughput.

    ``particle_steps_per_core_s`` is measured (``make bench``) and ``particles_held`` is the
    mean number of particles in the domain over the run (below the steady hold-up, since the
    blender fills first; the steady value gives a safe upper bound).
    """

    steps: int
    particles_held: float
    particle_steps_per_core_s: float
    cores: int
    parallel_efficiency: float

    @property
    def particle_steps(self) -> float:
        return self.steps * self.particles_held

    @property
    def wall_hours(self) -> float:
        rate = self.particle_steps_per_core_s * self.cores * self.parallel_efficiency
        return self.particle_steps / rate / 3600.0

    @property
    def core_hours(self) -> float:
        return self.wall_hours * self.cores


def estimate_cost(
    config: DemConfig,
    particles_held: float,
    particle_steps_per_core_s: float,
    cores: int,
    parallel_efficiency: float = 0.85,
) -> CostEstimate:
    """Estimate the cost of running ``config`` on ``cores`` cores."""
    check_positive_finite(particles_held, "particles_held (the hold-up, --holdup)", "particles")
    check_positive_finite(
        particle_steps_per_core_s,
        "particle_steps_per_core_s (the throughput, --throughput)",
        "particle-steps per second per core",
    )
    if isinstance(cores, bool) or int(cores) != cores or cores < 1:
        raise ConfigError(f"the number of cores (--np) must be an integer >= 1, got {cores!r}")
    if not (math.isfinite(parallel_efficiency) and 0 < parallel_efficiency <= 1):
        raise ConfigError(f"parallel_efficiency must lie in (0, 1], got {parallel_efficiency}")
    steps = math.ceil(config.operation.duration_s / config.timestep_s)
    return CostEstimate(steps, particles_held, particle_steps_per_core_s, cores, parallel_efficiency)


#: Largest value accepted for a hold-up or a throughput: beyond it a product with the
#: number of steps overflows nothing but means nothing either (1e15 particles, 1e15
#: particle-steps per core-second are both ~1e6x anything LIGGGHTS does).
MAX_PLAUSIBLE = 1e15


def check_positive_finite(value, what: str, unit: str) -> float:
    """``value`` as a float if it is a finite number in (0, 1e15]; else ConfigError naming
    ``what`` and the value (``--throughput nan``, ``--holdup inf``, a boolean)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f"{what} must be a number of {unit} > 0, got {value!r}")
    value = float(value)
    if not (math.isfinite(value) and 0 < value <= MAX_PLAUSIBLE):
        raise ConfigError(f"{what} must be a finite number of {unit} in (0, {MAX_PLAUSIBLE:g}], got {value:g}")
    return value


def mpi_command(config: DemConfig, np: int, deck: str = MAIN_DECK) -> list[str]:
    """The solver command line for ``np`` ranks with the configured launcher, as
    :func:`dem.liggghts.launch_command` (the programs need not exist on this machine)."""
    return launch_command(config.run, np, deck)


#: How LIGGGHTS is started inside a Slurm job: ``srun`` starts the ranks on the job's
#: allocation (its task count: no ``{np}``) and hands them their MPI wiring through PMIx, the
#: interface Open MPI >= 2 reads; Debian's Open MPI has no Slurm PMI-1/2 support, so plain
#: ``srun`` fails ("OMPI was not built with SLURM's PMI support"), and Slurm's PMIx plugin
#: loads ``libpmix.so``, which only Debian's ``libpmix-dev`` installs (measured on a one-node
#: Slurm 22.05 cluster, Open MPI 4.1.4: `srun --mpi=pmix` starts 1 and 2 ranks).
SRUN_LAUNCHER = "srun --mpi=pmix"


def under_srun(config: DemConfig) -> DemConfig:
    """``config`` with LIGGGHTS started by :data:`SRUN_LAUNCHER`, unless its launcher is
    already an ``srun`` (a site's own options kept). The launcher is not part of a run's key
    (:func:`dem.run.run_key`), so a run made in a job is found by a local request too."""
    if config.run.launcher.split()[:1] == ["srun"]:
        return config
    return config.model_copy(update={"run": config.run.model_copy(update={"launcher": SRUN_LAUNCHER})})


def slurm_script(
    config: DemConfig,
    run_dir: str,
    np: int,
    wall_hours: float,
    job_name: str = "pbmdem",
    partition: str | None = None,
) -> str:
    """A Slurm batch script that runs the deck in ``run_dir`` on ``np`` tasks, the ranks
    started by ``srun`` (:func:`under_srun`)."""
    check_tasks(np)
    return batch_script(
        launch_command(under_srun(config).run, np, MAIN_DECK),
        run_dir,
        np,
        wall_hours,
        job_name,
        partition,
        f"# LIGGGHTS reads its input while it runs: do not edit {MAIN_DECK} during the job.",
    )


def check_tasks(np) -> None:
    if isinstance(np, bool) or int(np) != np or np < 1:
        raise ConfigError(f"np must be >= 1, got {np!r} (an integer number of MPI tasks)")


def batch_script(
    command: list[str],
    work_dir: str,
    np: int,
    wall_hours: float,
    job_name: str = "pbmdem",
    partition: str | None = None,
    comment: str | None = None,
    output: str | None = None,
) -> str:
    """A Slurm batch script that runs ``command`` in ``work_dir`` on an allocation of
    ``np`` tasks, its output in ``output`` (default ``<job_name>-<job id>.out`` where it is
    submitted). The wall-time request carries a 30 % margin and is at least 10 minutes,
    so that start-up on a busy node does not kill a short job."""
    lines = _directives(job_name, np, wall_hours, output or f"{job_name}-%j.out", partition)
    lines += ["set -euo pipefail", f"cd {shlex.quote(work_dir)}"]
    if comment:
        lines.append(comment)
    lines += [shlex.join(command), ""]
    return "\n".join(lines)


def array_script(
    commands: dict[int, list[str]],
    work_dir: str,
    np: int,
    wall_hours: float | None,
    record_dir: str,
    job_name: str = "pbmdem",
    partition: str | None = None,
) -> str:
    """A Slurm job array: task ``i`` runs ``commands[i]`` in ``work_dir`` on ``np`` tasks,
    its output in ``<record_dir>/<array job id>_<i>.out``. Each task first writes its own
    job id to ``<record_dir>/<array job id>_<i>.jobid``: without slurmdbd, ``sacct
    --completion`` lists an array's tasks by that id alone. ``wall_hours`` as
    :func:`batch_script`; None asks for no time (the partition's default limit)."""
    if not commands:
        raise ConfigError("a job array needs at least one task")
    record = shlex.quote(record_dir.rstrip("/"))
    lines = _directives(job_name, np, wall_hours, f"{record_dir.rstrip('/')}/%A_%a.out", partition)
    lines.insert(2, f"#SBATCH --array={array_spec(commands)}")
    lines += [
        "set -euo pipefail",
        f"cd {shlex.quote(work_dir)}",
        f'echo "$SLURM_JOB_ID" > {record}/"${{SLURM_ARRAY_JOB_ID}}_${{SLURM_ARRAY_TASK_ID}}.jobid"',
        'case "$SLURM_ARRAY_TASK_ID" in',
        *(f"    {i}) {shlex.join(commands[i])} ;;" for i in sorted(commands)),
        '    *) echo "pbmdem: no task $SLURM_ARRAY_TASK_ID in this array" >&2; exit 2 ;;',
        "esac",
        "",
    ]
    return "\n".join(lines)


def array_spec(indices) -> str:
    """Slurm's ``--array`` value for these task indices: runs of consecutive ones as
    ranges (``0-2,5,7-8``)."""
    ordered = sorted(set(indices))
    if not ordered or ordered[0] < 0 or any(isinstance(i, bool) or int(i) != i for i in ordered):
        raise ConfigError(f"array task indices must be integers >= 0, got {sorted(indices)!r}")
    runs: list[list[int]] = []
    for i in ordered:
        if runs and i == runs[-1][1] + 1:
            runs[-1][1] = i
        else:
            runs.append([i, i])
    return ",".join(str(a) if a == b else f"{a}-{b}" for a, b in runs)


def _directives(job_name: str, np: int, wall_hours: float | None, output: str, partition: str | None) -> list[str]:
    check_tasks(np)
    lines = ["#!/bin/bash", f"#SBATCH --job-name={job_name}", f"#SBATCH --ntasks={np}", "#SBATCH --cpus-per-task=1"]
    if wall_hours is not None:
        check_positive_finite(wall_hours, "the wall time", "hours")
        minutes = max(10, math.ceil(wall_hours * 1.3 * 60))
        lines.append(f"#SBATCH --time={minutes // 60:02d}:{minutes % 60:02d}:00")
    lines.append(f"#SBATCH --output={output}")
    if partition:
        lines.append(f"#SBATCH --partition={partition}")
    return lines
