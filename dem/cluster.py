"""The cluster path: cost estimate from measured throughput, MPI command and Slurm script.

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


def slurm_script(
    config: DemConfig,
    run_dir: str,
    np: int,
    wall_hours: float,
    job_name: str = "pbmdem",
    partition: str | None = None,
) -> str:
    """A Slurm batch script that runs the deck in ``run_dir`` on ``np`` tasks.

    The ranks are started by the configured launcher (:func:`mpi_command`; Open MPI's
    ``mpirun`` takes its hosts from the Slurm allocation), not by ``srun``: ``srun`` can
    start MPI ranks only when the MPI library was built with Slurm's PMI, and Debian's
    Open MPI is not (measured on a one-node Slurm 22.05 cluster: "OMPI was not built with
    SLURM's PMI support"; ``srun --mpi=pmix`` could not load a PMIx library either).
    """
    check_tasks(np)
    return batch_script(
        mpi_command(config, np, MAIN_DECK),
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
    check_tasks(np)
    check_positive_finite(wall_hours, "the wall time", "hours")
    minutes = max(10, math.ceil(wall_hours * 1.3 * 60))
    lines = [
        "#!/bin/bash",
        f"#SBATCH --job-name={job_name}",
        f"#SBATCH --ntasks={np}",
        "#SBATCH --cpus-per-task=1",
        f"#SBATCH --time={minutes // 60:02d}:{minutes % 60:02d}:00",
        f"#SBATCH --output={output or f'{job_name}-%j.out'}",
    ]
    if partition:
        lines.append(f"#SBATCH --partition={partition}")
    lines += ["set -euo pipefail", f"cd {shlex.quote(work_dir)}"]
    if comment:
        lines.append(comment)
    lines += [shlex.join(command), ""]
    return "\n".join(lines)
