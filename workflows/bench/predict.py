"""What ``pbmdem predict`` costs from the shell: ``pbmdem bench predict``.

Measures, each in a fresh interpreter as a user would meet it, ``--repeats`` times
(median), the README's example point (:data:`EXAMPLE`) predicted from the shipped library
into a temporary directory: with its figure and page (drawn by a process the command forks
when it starts, :class:`coupling.forked.Prepared`, which imports matplotlib while the
command imports and predicts), without them (``--no-figures``), and the imports of the
command's own modules alone. The project's modules are compiled to bytecode first, as an
installed package or any second run has them (a shell that sets PYTHONDONTWRITEBYTECODE
would otherwise compile every edited module on every run: 0.2 s here). Writes
``results/bench/predict.json``.
"""

from __future__ import annotations

import argparse
import compileall
import os
import statistics
import tempfile
from pathlib import Path

from coupling.jsonable import write_json
from workflows.bench.design import fresh

OUT = Path("results/bench/predict.json")
#: the README's example point
EXAMPLE = "workflows/reference/unseen/275rpm-x1.3125.toml"
TARGET_S = 2.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--repeats", type=int, default=5, help="fresh interpreters per measurement")
    parser.add_argument("--config", default=EXAMPLE, help=f"the point predicted (default: {EXAMPLE})")
    parser.add_argument("--out-file", default=str(OUT))


#: the project's packages, compiled before the command is timed
PACKAGES = ("coupling", "dem", "pbm", "workflows")


def run(args: argparse.Namespace) -> int:
    root = Path(__file__).resolve().parents[2]
    for package in PACKAGES:
        compileall.compile_dir(root / package, quiet=1)
    measured = {}
    with tempfile.TemporaryDirectory() as tmp:
        command = ["-m", "workflows.cli", "predict", "--config", args.config, "--out", tmp]
        measured["with its figure and page"] = fresh(command, args.repeats)
        measured["without them (--no-figures)"] = fresh([*command, "--no-figures"], args.repeats)
    measured["its imports (workflows.products.predict)"] = fresh(
        ["-c", "import workflows.products.predict"], args.repeats
    )
    record = {
        "command": ["pbmdem", "predict", "--config", args.config],
        **{name: {"wall_s": walls, "cpu_s": cpus} for name, (walls, cpus) in measured.items()},
        "load_average_1min": os.getloadavg()[0],
        "cores": os.cpu_count(),
        "target_s": TARGET_S,
    }
    write_json(Path(args.out_file), record)
    print(f"{'pbmdem predict --config ' + args.config:72s} {'wall':>8s} {'CPU':>8s}  target")
    for name, (walls, cpus) in measured.items():
        target = f"<= {TARGET_S:g} s" if name == "with its figure and page" else ""
        print(f"  {name:70s} {statistics.median(walls):7.2f}s {statistics.median(cpus):7.2f}s  {target}")
    print(
        f"(median of {args.repeats} fresh interpreters, range "
        f"{min(measured['with its figure and page'][0]):.2f}-{max(measured['with its figure and page'][0]):.2f} s "
        f"with the figure; load average {record['load_average_1min']:.1f} on {record['cores']} cores)"
    )
    print(f"wrote {args.out_file}")
    return 0
