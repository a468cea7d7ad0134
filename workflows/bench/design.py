"""What the README's ``pbmdem design`` example costs, and where: ``pbmdem bench design``.

Measures, each in a fresh interpreter as a user would meet it, ``--repeats`` times (median):

* the command itself (:data:`EXAMPLE`), start to exit, written to a temporary directory:
  its wall time, and its CPU time split between its own process and the figure's process
  it forks (on two free cores the wall time is about the first: on a machine whose cores
  others are using, the wall time says more about them than about the command);
* the imports of the command's own modules (``workflows.products.design``);
* the floor under both: importing only the libraries the command cannot do without
  (:data:`LIBRARIES`: numpy and scipy's linear algebra and special functions), with nothing
  of this project. The figure's plotting library is not in it: the command imports it, and
  draws the figure, in a process forked when it starts, on the other core
  (:class:`coupling.forked.Prepared`);

and, in this process after those imports, the stages of :func:`workflows.products.design.run_design`:
reading the library model, its correction lines, the search (every grid point's chain,
quantities, VRR and P(spec met), then the answers' refinement, noise and step), and drawing
``feasible.png``. Writes ``results/bench/design.json``.
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from coupling.jsonable import write_json

OUT = Path("results/bench/design.json")
#: the README's example spec
EXAMPLE = ("--ca-within", "0.04", "--noise-sigma", "0.1", "--noise-tau", "5", "--mrt-max", "25")
#: what any implementation of the command imports before it can answer
LIBRARIES = "import numpy, scipy.linalg, scipy.special"
TARGET_S = 2.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--repeats", type=int, default=3, help="fresh interpreters per measurement")
    parser.add_argument("--out-file", default=str(OUT))


def fresh(code_or_args: list[str], repeats: int) -> tuple[list[float], list[float]]:
    """(wall times [s], CPU times [s], user + system, of it and every process it forked)
    of ``python <args>`` in a fresh interpreter; raises on a failure. On a machine whose
    cores others are using the wall time grows and the CPU time much less: both are kept."""
    walls, cpus = [], []
    for _ in range(repeats):
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        start = time.perf_counter()
        done = subprocess.run([sys.executable, *code_or_args], capture_output=True, text=True)
        walls.append(time.perf_counter() - start)
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpus.append(after.ru_utime - before.ru_utime + after.ru_stime - before.ru_stime)
        if done.returncode not in (0, 1):  # 1: the spec is met nowhere, still an answer
            raise RuntimeError(f"{' '.join(code_or_args)} failed ({done.returncode}): {done.stderr.strip()[-500:]}")
    return walls, cpus


#: the command run by its own entry point in a fresh interpreter that then prints its CPU
#: time [s] and that of the figure's process it forked (reaped, a child of it)
_SPLIT = """
import contextlib, io, resource, sys
from workflows.cli.main import main
with contextlib.redirect_stdout(io.StringIO()):
    code = main(['design', *sys.argv[1:]])
own, child = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
print(own.ru_utime + own.ru_stime, child.ru_utime + child.ru_stime)
raise SystemExit(code)
"""


def _split_cpu(out: str, repeats: int) -> tuple[list[float], list[float]]:
    """CPU times [s] of the command's own process and of the figure's process it forks,
    which runs beside it on the other core: on two free cores the wall time is about the
    first's."""
    own, figure = [], []
    for _ in range(repeats):
        done = subprocess.run(
            [sys.executable, "-c", _SPLIT, *EXAMPLE, "--out", out], capture_output=True, text=True, check=True
        )
        a, b = (float(v) for v in done.stdout.split()[-2:])
        own.append(a)
        figure.append(b)
    return own, figure


def _stages() -> tuple[dict[str, float], int]:
    """Seconds of each stage of run_design in this process (imports already paid; the
    search run once untimed first, as every first call pays scipy's first dispatches), and
    the grid points the search evaluated."""
    from workflows.prediction.design import design, design_spec, surrogate
    from workflows.prediction.library import load_model
    from workflows.report.design import plot_design
    from workflows.shipped import LIBRARY_MODEL

    spec = design_spec(ca_tolerance=0.04, noise_sigma=0.1, noise_tau_s=5.0, mrt_max_s=25.0)
    out: dict[str, float] = {}
    start = time.perf_counter()
    model = load_model(LIBRARY_MODEL)
    out["read the library model"] = time.perf_counter() - start
    start = time.perf_counter()
    s = surrogate(model)
    out["its correction lines and domain"] = time.perf_counter() - start
    design(s, spec)
    start = time.perf_counter()
    result = design(s, spec)
    out["the search (grid, answers refined, their noise and step)"] = time.perf_counter() - start
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        plot_design(result.record(), Path(tmp) / "feasible.png")
    out["figure and page (in the command: drawn by its forked process)"] = time.perf_counter() - start
    return out, result.evaluated


def run(args: argparse.Namespace) -> int:
    with tempfile.TemporaryDirectory() as tmp:
        command, command_cpu = fresh(["-m", "workflows.cli", "design", *EXAMPLE, "--out", tmp], args.repeats)
        process_cpu, figure_cpu = _split_cpu(tmp, args.repeats)
    own, own_cpu = fresh(["-c", "import workflows.products.design"], args.repeats)
    floor, floor_cpu = fresh(["-c", LIBRARIES], args.repeats)
    stages, points = _stages()
    record = {
        "command": ["pbmdem", "design", *EXAMPLE],
        "command_s": command,
        "command_median_s": statistics.median(command),
        "command_cpu_s": command_cpu,
        "command_process_cpu_s": process_cpu,
        "figure_process_cpu_s": figure_cpu,
        "imports_of_the_command_s": own,
        "imports_of_the_command_cpu_s": own_cpu,
        "imports_of_the_libraries_alone_s": floor,
        "imports_of_the_libraries_alone_cpu_s": floor_cpu,
        "stages_s": stages,
        "points_evaluated": points,
        "load_average_1min": os.getloadavg()[0],
        "cores": os.cpu_count(),
        "target_s": TARGET_S,
    }
    write_json(Path(args.out_file), record)
    rows = [
        (
            "the README's `pbmdem design` example, fresh interpreter",
            statistics.median(command),
            statistics.median(command_cpu),
            f"<= {TARGET_S:g} s",
        ),
        ("  CPU of the command's own process", None, statistics.median(process_cpu), ""),
        ("  CPU of the figure's process it forks (beside it)", None, statistics.median(figure_cpu), ""),
        ("  its imports (workflows.products.design)", statistics.median(own), statistics.median(own_cpu), ""),
        (
            f"  floor: {LIBRARIES.removeprefix('import ')} alone",
            statistics.median(floor),
            statistics.median(floor_cpu),
            "",
        ),
        *((f"  {name}", seconds, None, "") for name, seconds in stages.items()),
    ]
    print(f"{'measurement':64s} {'wall':>8s} {'CPU':>8s}  target")
    for name, seconds, cpu, target in rows:
        wall = "" if seconds is None else f"{seconds:7.2f}s"
        print(f"{name:64s} {wall:>8s} {'' if cpu is None else f'{cpu:7.2f}s':>8s}  {target}")
    print(
        f"({points} operating points evaluated per search; load average {record['load_average_1min']:.1f} on "
        f"{record['cores']} cores: the CPU column counts the command and the process it forks)"
    )
    print(f"wrote {args.out_file}")
    return 0
