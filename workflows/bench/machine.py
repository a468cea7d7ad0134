"""How much can two ranks gain on this machine at all? (``python -m workflows.bench.machine``)

Two MPI ranks can at best do what two independent single-rank runs do side by side. This
runs the rotating drum of :func:`dem.deck.build_drum_deck` (the blender deck's fair
reference: same particles, same physics, no communication between runs) on 1 rank alone,
then two copies at once, each on 1 rank, then one copy on 2 ranks under each launcher of
``--launchers``, ``--repeats`` times interleaved, for each bed size of ``--particles``, and
reports from each run's LIGGGHTS ``Loop time``

    bound   = (particle-steps/s of the two together) / (particle-steps/s of one alone)
    speedup = (particle-steps/s on 2 ranks) / (particle-steps/s of one alone)

A bound below 2 is the machine's (shared cores, memory bandwidth, a virtual machine's
scheduling), not the deck's; no decomposition of a 2-rank run can exceed it. A 2-rank
speed-up well below the bound, for every bed size and launcher, is the solver's own
parallel cost: the drum has no meshes, feeders or dumps for a deck change to remove.
Writes ``results/bench/machine.json``.
"""

from __future__ import annotations

import argparse
import os
import shlex
import statistics
import subprocess
import tempfile
from pathlib import Path

from coupling.errors import ConfigError, SolverRunError
from coupling.jsonable import write_json
from dem import deck
from dem.liggghts import solver_command
from dem.liggghts_log import parse_runs
from workflows.config import load_preset

OUT = Path("results/bench/machine.json")
#: mpirun as the runs use it, without binding ranks to cores, and with ranks that yield the
#: core while they wait for a message (Open MPI spins by default)
LAUNCHERS = (
    "mpirun --allow-run-as-root -np {np}",
    "mpirun --allow-run-as-root --bind-to none -np {np}",
    "mpirun --allow-run-as-root --mca mpi_yield_when_idle 1 -np {np}",
)


def _start(run_config, run_dir: Path, np: int = 1) -> subprocess.Popen:
    command = [*solver_command(run_config, np, deck.DRUM_DECK), "-log", deck.DRUM_LOG_FILE]
    return subprocess.Popen(command, cwd=run_dir, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def _rate(process: subprocess.Popen, run_dir: Path) -> float:
    output, _ = process.communicate()
    runs = parse_runs(output)
    if process.returncode != 0 or not runs or runs[-1].loop.seconds <= 0:
        raise SolverRunError(f"the drum run failed (exit {process.returncode})", run_dir=run_dir)
    last = runs[-1]
    atoms = last.column("Atoms") or [float(last.loop.atoms)]
    return sum(atoms) / len(atoms) * last.loop.steps / last.loop.seconds


def _label(launcher: str) -> str:
    """What a launcher adds to plain ``mpirun -np``, for the summary line."""
    extra = [w for w in shlex.split(launcher) if w not in ("mpirun", "--allow-run-as-root", "-np", "{np}")]
    return " ".join(extra) or "as the runs use it"


def _check_launcher(text: str) -> str:
    if "{np}" not in text:
        raise argparse.ArgumentTypeError(f"launcher {text!r} has no {{np}} for the number of ranks")
    return text


def measure(config, particles: int, steps: int, repeats: int, launchers: list[str]) -> dict:
    """One bed size: rates of one alone, two at once and 2 ranks under each launcher."""
    files = deck.build_drum_deck(config.dem, particles, steps)
    alone, together = [], []
    two_ranks: dict[str, list[float]] = {launcher: [] for launcher in launchers}
    with tempfile.TemporaryDirectory(prefix="bench_machine_") as tmp:
        dirs = [deck.write_deck(files, Path(tmp) / name) for name in ("a", "b")]
        for repeat in range(repeats):
            alone.append(_rate(_start(config.dem.run, dirs[0]), dirs[0]))
            pair = [_start(config.dem.run, d) for d in dirs]
            together.append(sum(_rate(p, d) for p, d in zip(pair, dirs)))
            for launcher in launchers:
                run = config.dem.run.model_copy(update={"launcher": launcher})
                two_ranks[launcher].append(_rate(_start(run, dirs[0], 2), dirs[0]))
            print(
                f"  {particles} particles, repeat {repeat + 1}: one alone {alone[-1]:.3g} particle-steps/s, two at "
                f"once x{together[-1] / alone[-1]:.2f}, 2 ranks "
                + ", ".join(f"x{v[-1] / alone[-1]:.2f}" for v in two_ranks.values()),
                flush=True,
            )
    return {
        "particles": particles,
        "alone": alone,
        "together": together,
        "bound_two_ranks": statistics.median(t / a for t, a in zip(together, alone)),
        "two_ranks": {
            launcher: {"rates": values, "speedup": statistics.median(v / a for v, a in zip(values, alone))}
            for launcher, values in two_ranks.items()
        },
    }


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The command line's options of this benchmark."""
    parser.add_argument("--preset", default="smoke")
    parser.add_argument(
        "--particles", default="1546", help="comma-separated drum bed sizes (default: the smoke bed, 1546)"
    )
    parser.add_argument("--steps", type=int, default=20000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument(
        "--launchers",
        type=_check_launcher,
        nargs="*",
        default=list(LAUNCHERS),
        help="MPI launchers for the 2-rank runs, each with {np} (default: %(default)s)",
    )
    parser.add_argument("--out-file", default=str(OUT))


def run(args: argparse.Namespace) -> int:
    try:
        sizes = [int(v) for v in args.particles.split(",")]
    except ValueError:
        raise ConfigError(
            f"--particles {args.particles!r}: expected comma-separated whole numbers, e.g. 1546,6000"
        ) from None
    if any(n < 1 for n in sizes):
        raise ConfigError(f"--particles {args.particles!r}: every bed size must be >= 1")
    for name in ("steps", "repeats"):
        if getattr(args, name) < 1:
            raise ConfigError(f"--{name} {getattr(args, name)}: expected a whole number >= 1")
    config = load_preset(args.preset)
    load = [os.getloadavg()[0]]
    beds = [measure(config, n, args.steps, args.repeats, args.launchers) for n in sizes]
    load.append(os.getloadavg()[0])
    record = {
        "preset": args.preset,
        "steps": args.steps,
        "repeats": args.repeats,
        "beds": beds,
        "bound_two_ranks": min(bed["bound_two_ranks"] for bed in beds),
        "load_average": load,
        "cpus": os.cpu_count(),
    }
    print(f"medians of {args.repeats}, load {load[0]:.2f}-{load[1]:.2f}:")
    for bed in beds:
        print(
            f"  {bed['particles']} particles: two single-rank runs at once x{bed['bound_two_ranks']:.2f}; one run on "
            "2 ranks " + ", ".join(f"x{r['speedup']:.2f} ({_label(k)})" for k, r in bed["two_ranks"].items())
        )
    print(f"wrote {write_json(args.out_file, record)}")
    return 0
