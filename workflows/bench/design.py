"""What the README's ``pbmdem design`` example costs, and where: ``pbmdem bench design``.

Measures, each in a fresh interpreter as a user would meet it, ``--repeats`` times (median):

* the command itself (:data:`EXAMPLE`), start to exit, written to a temporary directory;
* the imports of the command's own modules (``workflows.products.design``);
* the floor under both: importing only the libraries the command cannot do without
  (:data:`LIBRARIES`: the linear algebra, the root finder and HDF5), with nothing of this
  project. The figure's plotting library is not in it: the command imports it, and draws
  the figure, in a process forked when it starts, on the other core
  (:class:`coupling.forked.Prepared`);

and, in this process after those imports, the stages of :func:`workflows.products.design.run_design`:
reading the library (each results file's tables, checked against its head digest), the
blender inversion (the frequency responses of the candidate lengths and speeds), the
throughput inversion, and drawing ``feasible.png``. Writes ``results/bench/design.json``.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from coupling.jsonable import write_json
from workflows.shipped import VALIDATION_DIR

OUT = Path("results/bench/design.json")
#: the README's example spec
EXAMPLE = ("--ca-within", "0.04", "--noise-sigma", "0.1", "--noise-tau", "5", "--mrt-max", "25")
#: what any implementation of the command imports before it can answer: numpy and scipy's
#: linear algebra and root finding (the inversion), h5py (the results files)
LIBRARIES = "import numpy, scipy.linalg, scipy.optimize, h5py"
TARGET_S = 2.0
#: the stages of the blender's search: as the command runs it, and in one process
SEARCH = "smallest blender (lengths x speeds, {workers} process(es))"
SERIAL = "  the same in one process (its responses counted)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--repeats", type=int, default=3, help="fresh interpreters per measurement")
    parser.add_argument("--out-file", default=str(OUT))


def _fresh(code_or_args: list[str], repeats: int) -> list[float]:
    """Wall times [s] of ``python <args>`` in a fresh interpreter; raises on a failure."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        done = subprocess.run([sys.executable, *code_or_args], capture_output=True, text=True)
        times.append(time.perf_counter() - start)
        if done.returncode not in (0, 1):  # 1: the spec is met nowhere, still an answer
            raise RuntimeError(f"{' '.join(code_or_args)} failed ({done.returncode}): {done.stderr.strip()[-500:]}")
    return times


def _stages() -> tuple[dict[str, float], dict[str, float], int]:
    """Seconds of each stage of run_design, in this process (imports already paid), the
    work of its frequency responses (:func:`_responses_work`, counted in one process; and
    ``search_seconds``, the blender search's share) and the processes the search ran on."""
    from unittest import mock

    import pbm.design
    from pbm.design import design, design_spec, max_feed
    from workflows.products.design import library_runs, load_feed_library, load_library
    from workflows.report.design import plot_feasible

    spec = design_spec(ca_tolerance=0.04, noise_sigma=0.1, noise_tau_s=5.0, mrt_max_s=25.0)
    out: dict[str, float] = {}
    start = time.perf_counter()
    runs = library_runs()
    out["read the library (each file's tables, head digest checked)"] = time.perf_counter() - start
    calls: list[tuple[int, int, float]] = []  # (states, frequencies, seconds) of each response

    def timed(system, freqs, feeder="A", respond=pbm.design.system_response):
        t0 = time.perf_counter()
        h = respond(system, freqs, feeder)
        calls.append((system.generator.shape[0], int(np.size(freqs)), time.perf_counter() - t0))
        return h

    # a first search pays what every first call does (the library's interpolated tables,
    # scipy's first dispatches): not timed, so that the two timed ones compare
    with mock.patch.object(pbm.design, "free_cores", lambda limit=None: 1):
        design(load_library(runs, "measured"), spec)
        # the responses counted in one process: forked workers' calls would not come back
        with mock.patch.object(pbm.design, "system_response", timed):
            start = time.perf_counter()
            design(load_library(runs, "measured"), spec)
            serial = time.perf_counter() - start
    searched = sum(t for _, _, t in calls)  # the blender's responses, the rest are the feed's
    workers = pbm.design.search_processes(len(pbm.design.speed_grid(load_library(runs, "measured"), spec)))
    start = time.perf_counter()
    result = design(load_library(runs, "measured"), spec)
    out[SEARCH.format(workers=workers)] = time.perf_counter() - start
    out[SERIAL] = serial
    with mock.patch.object(pbm.design, "system_response", timed):
        start = time.perf_counter()
        feeds = load_feed_library(runs, "measured")
        if feeds is not None:
            max_feed(feeds, spec)
        out["largest feed (fill law)"] = time.perf_counter() - start
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        plot_feasible(result.to_dict(), Path(tmp) / "feasible.png")
    out["figure (in the command: drawn by its forked process beside the largest feed)"] = time.perf_counter() - start
    return out, {**_responses_work(calls), "search_seconds": searched}, workers


def _responses_work(calls: list[tuple[int, int, float]]) -> dict[str, float]:
    """The flops of the frequency responses: per system of n states, its real Schur form
    (~25 n^3, Golub & Van Loan) and, per frequency, the complex back substitution (n^2 / 2
    complex multiply-adds, 4 n^2 flops); with the seconds they took, the rate achieved."""
    flops = sum(25.0 * n**3 + 4.0 * f * n**2 for n, f, _ in calls)
    seconds = sum(t for _, _, t in calls)
    return {
        "systems": len(calls),
        "states_min": min((n for n, _, _ in calls), default=0),
        "states_max": max((n for n, _, _ in calls), default=0),
        "frequencies": max((f for _, f, _ in calls), default=0),
        "flops": flops,
        "seconds": seconds,
        "flops_per_s": flops / seconds if seconds > 0 else float("nan"),
    }


def _h5_read_s(directory: Path) -> float:
    """Seconds h5py alone takes to read the velocity tables of the library's files: what
    any reader of them pays, before a digest or a table is made."""
    import h5py

    from coupling.tables import GROUP

    def read(_name, obj):
        if isinstance(obj, h5py.Dataset):
            obj[()]

    start = time.perf_counter()
    for path in sorted(directory.glob("dem-*.h5")):
        with h5py.File(path, "r") as h5:
            h5[GROUP].visititems(read)
    return time.perf_counter() - start


def run(args: argparse.Namespace) -> int:
    with tempfile.TemporaryDirectory() as tmp:
        command = _fresh(["-m", "workflows.cli", "design", *EXAMPLE, "--out", tmp], args.repeats)
    own = _fresh(["-c", "import workflows.products.design"], args.repeats)
    floor = _fresh(["-c", LIBRARIES], args.repeats)
    stages, work, workers = _stages()
    h5_read = _h5_read_s(VALIDATION_DIR)
    # the responses at the pace the search's processes gained over one: what the cores
    # deliver together, which is not their number when they share the floating point
    speedup = stages[SERIAL] / stages[SEARCH.format(workers=workers)]
    responses_s = work["search_seconds"] / speedup + (work["seconds"] - work["search_seconds"])
    floor_s = statistics.median(floor) + h5_read + responses_s
    record = {
        "command": ["pbmdem", "design", *EXAMPLE],
        "command_s": command,
        "command_median_s": statistics.median(command),
        "imports_of_the_command_s": own,
        "imports_of_the_libraries_alone_s": floor,
        "stages_s": stages,
        "frequency_responses": work,
        "search_processes": workers,
        "search_speedup": speedup,
        "h5py_read_of_the_library_s": h5_read,
        "floor_s": floor_s,
        "target_s": TARGET_S,
    }
    write_json(Path(args.out_file), record)
    rows = [
        ("the README's `pbmdem design` example, fresh interpreter", statistics.median(command), f"<= {TARGET_S:g} s"),
        ("  its imports (workflows.products.design)", statistics.median(own), ""),
        ("  floor: numpy, scipy.linalg, scipy.optimize, h5py alone", statistics.median(floor), ""),
        *((f"  {name}", seconds, "") for name, seconds in stages.items()),
        (
            f"  of which {work['systems']} frequency responses ({work['states_min']}-{work['states_max']} states, "
            f"{work['frequencies']} "
            f"frequencies): {work['flops'] / 1e9:.1f} Gflop at {work['flops_per_s'] / 1e9:.1f} Gflop/s in one process",
            work["seconds"],
            "",
        ),
        ("  reading the library's tables, h5py alone", h5_read, ""),
        (
            f"floor: the libraries' imports + h5py's read + the responses (search's / {speedup:.2f})",
            floor_s,
            f"{'above' if floor_s > TARGET_S else 'below'} {TARGET_S:g} s",
        ),
    ]
    print(f"{'measurement':64s} {'median':>9s}  target")
    for name, seconds, target in rows:
        print(f"{name:64s} {seconds:8.2f}s  {target}")
    print(f"wrote {args.out_file}")
    return 0
