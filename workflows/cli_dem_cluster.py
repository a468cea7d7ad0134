"""``pbmdem dem slurm``: the cluster path for big presets (``paper``).

Writes the run directory (deck, meshes, resolved config) plus ``job.slurm`` instead of
running, prints the MPI command and an estimate of the core-hours from the measured
throughput and the hold-up scaled from the shipped reduced run.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from workflows.cli_dem import add_config_arguments

# Measured here (dem/deck.py's presets, LIGGGHTS 3.8.0, one core): about 3.9e6 particle-steps
# per second for this blender deck. `make bench` measures it again (results/bench/dem_deck.json).
DEFAULT_THROUGHPUT_PER_CORE = 3.9e6
BENCH_FILE = Path("results/bench/dem_deck.json")


def register(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser("slurm", help="write the deck and a Slurm batch script with a cost estimate, without running")
    add_config_arguments(parser)
    parser.add_argument("--out", required=True, help="run directory to create (deck + job.slurm)")
    parser.add_argument("--np", type=int, default=32, help="MPI tasks (default 32)")
    parser.add_argument("--partition", default=None, help="Slurm partition")
    parser.add_argument("--holdup", type=float, default=None,
                        help="steady hold-up [particles]; default: scaled from the shipped reduced run")
    parser.add_argument("--throughput", type=float, default=None,
                        help="particle-steps per second per core; default: results/bench/dem_deck.json or 3.9e6")
    parser.set_defaults(func=run)


def reference_holdup(dem_config) -> tuple[float, str]:
    """Steady hold-up for ``dem_config`` scaled by solid volume from a shipped DEM run:
    the same blender holds the same powder volume, so N scales with (d_ref / d)^3."""
    from coupling.cache import try_load_dem_results
    from workflows.compare import REFERENCE_DIR
    from workflows.config import config_from_dict

    import tomllib

    for path in sorted(REFERENCE_DIR.glob("dem-*.h5")):
        loaded, _ = try_load_dem_results(path)
        if loaded is None:
            continue
        _, results, provenance = loaded
        ref = config_from_dict(tomllib.loads(provenance["config_toml"])).dem
        if ref.geometry != dem_config.geometry.model_copy(update={"blade_tip_clearance_m": ref.geometry.blade_tip_clearance_m}):
            continue
        held = float(results.summary["holdup_final"])
        scale = (ref.particles.diameter_m / dem_config.particles.diameter_m) ** 3
        return held * scale, f"{held:.0f} particles of {ref.particles.diameter_m * 1000:g} mm in {path.name}, x {scale:.3g}"
    raise LookupError("no shipped reference run of the same blender to scale the hold-up from; pass --holdup")


def run(args: argparse.Namespace) -> int:
    from coupling.errors import ConfigError
    from dem.cluster import estimate_cost, mpi_command, slurm_script
    from dem.deck import build_deck, write_deck
    from workflows.config import dump_toml, resolve_config

    config = resolve_config(args.preset, args.config)
    if args.holdup is not None:
        holdup, holdup_source = args.holdup, "given with --holdup"
    else:
        try:
            holdup, holdup_source = reference_holdup(config.dem)
        except LookupError as exc:
            raise ConfigError(str(exc)) from None
    if args.throughput is not None:
        throughput, throughput_source = args.throughput, "given with --throughput"
    elif BENCH_FILE.is_file():
        throughput = float(json.loads(BENCH_FILE.read_text())["blender_particle_steps_per_s_serial"])
        throughput_source = f"measured by make bench ({BENCH_FILE})"
    else:
        throughput, throughput_source = DEFAULT_THROUGHPUT_PER_CORE, "measured on the development machine"
    estimate = estimate_cost(config.dem, holdup, throughput, args.np)
    files = build_deck(config.dem)
    files["config.toml"] = dump_toml(config)
    files["job.slurm"] = slurm_script(config.dem, str(Path(args.out).resolve()), args.np, estimate.wall_hours, job_name=f"pbmdem-{config.name}",
                                      partition=args.partition)
    out = write_deck(files, args.out)
    print(f"wrote {out}/in.blender and {out}/job.slurm; submit with: cd {out} && sbatch job.slurm")
    print(f"or run with MPI: cd {out} && {' '.join(mpi_command(config.dem, args.np))}")
    print(f"hold-up {holdup:.0f} particles ({holdup_source}); throughput {throughput:.3g} particle-steps/s/core "
          f"({throughput_source}); {estimate.steps} steps")
    print(f"estimate on {args.np} cores at {estimate.parallel_efficiency:.0%} parallel efficiency: "
          f"{estimate.wall_hours:.1f} h wall, {estimate.core_hours:.0f} core-hours "
          f"(the paper: 6.5 days on 8 workers = about 1250 core-hours)")
    return 0
