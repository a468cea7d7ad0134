"""The cluster path: a run directory with its Slurm script and a core-hour estimate, from
the hold-up of a shipped run of the same blender and a measured throughput."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from coupling.errors import ConfigError
from coupling.files import writable_directory
from dem.cluster import estimate_cost, mpi_command, slurm_script
from dem.deck import MAIN_DECK, build_deck, write_deck
from workflows.config import Config, dump_toml
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
