"""How much can two ranks gain on this machine at all? (``python -m workflows.bench_machine``)

Two MPI ranks can at best do what two independent single-rank runs do side by side. This
runs the rotating drum of :func:`dem.deck.build_drum_deck` (the blender deck's fair
reference: same particles, same physics, no communication between runs) on 1 rank alone,
then two copies at once, each on 1 rank, ``--repeats`` times interleaved, and reports

    bound = (particle-steps/s of the two together) / (particle-steps/s of one alone)

from each run's LIGGGHTS ``Loop time``. A bound below 2 is the machine's (shared cores,
memory bandwidth, a virtual machine's scheduling), not the deck's; no decomposition of a
2-rank run can exceed it. Writes ``results/bench/machine.json``.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import tempfile
from pathlib import Path

from coupling.errors import SolverRunError
from dem import deck
from dem.liggghts import solver_command
from dem.liggghts_log import parse_runs
from workflows.bench import write_json
from workflows.config import load_preset

OUT = Path("results/bench/machine.json")


def _start(run_config, run_dir: Path) -> subprocess.Popen:
    command = [*solver_command(run_config, 1, deck.DRUM_DECK), "-log", deck.DRUM_LOG_FILE]
    return subprocess.Popen(command, cwd=run_dir, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def _rate(process: subprocess.Popen, run_dir: Path) -> float:
    output, _ = process.communicate()
    runs = parse_runs(output)
    if process.returncode != 0 or not runs or runs[-1].loop.seconds <= 0:
        raise SolverRunError(f"the drum run failed (exit {process.returncode})", run_dir=run_dir)
    last = runs[-1]
    atoms = last.column("Atoms") or [float(last.loop.atoms)]
    return sum(atoms) / len(atoms) * last.loop.steps / last.loop.seconds


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(prog="python -m workflows.bench_machine", description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="smoke")
    parser.add_argument("--particles", type=int, default=1546, help="drum particles (default: the smoke bed)")
    parser.add_argument("--steps", type=int, default=20000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", default=str(OUT))
    args = parser.parse_args(argv if argv is not None else [])
    config = load_preset(args.preset)
    files = deck.build_drum_deck(config.dem, args.particles, args.steps)
    alone, together = [], []
    load = [os.getloadavg()[0]]
    with tempfile.TemporaryDirectory(prefix="bench_machine_") as tmp:
        dirs = [deck.write_deck(files, Path(tmp) / name) for name in ("a", "b")]
        for repeat in range(args.repeats):
            alone.append(_rate(_start(config.dem.run, dirs[0]), dirs[0]))
            pair = [_start(config.dem.run, d) for d in dirs]
            together.append(sum(_rate(p, d) for p, d in zip(pair, dirs)))
            print(f"  repeat {repeat + 1}: one alone {alone[-1]:.3g} particle-steps/s, two at once {together[-1]:.3g} "
                  f"(x{together[-1] / alone[-1]:.2f})", flush=True)
    load.append(os.getloadavg()[0])
    bound = statistics.median(t / a for t, a in zip(together, alone))
    record = {"preset": args.preset, "particles": args.particles, "steps": args.steps, "alone": alone,
              "together": together, "bound_two_ranks": bound, "load_average": load, "cpus": os.cpu_count()}
    print(f"two single-rank runs at once deliver {bound:.2f}x one alone (median of {args.repeats}; load "
          f"{load[0]:.2f}-{load[1]:.2f}): no 2-rank run can speed up more on this machine")
    print(f"wrote {write_json(args.out, record)}")
    return record


if __name__ == "__main__":
    import sys

    main(sys.argv[1:])
