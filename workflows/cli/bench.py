"""``pbmdem bench NAME`` runs one benchmark; ``pbmdem bench all`` (``make bench``) runs
every one with its defaults and writes ``results/bench/*.json``. Timings are measured
here, never asserted in tests: the machines are shared and noisy."""

from __future__ import annotations

import argparse
import importlib

from coupling.errors import ConfigError

HELP = "benchmarks: speed, accuracy and cost of every stage (results/bench/*.json)"

#: (subcommand, module, title), in the order ``all`` runs them.
BENCHMARKS = (
    ("pbm", "workflows.bench.pbm", "PBM solver and ensembles"),
    ("frequency", "workflows.bench.frequency", "Frequency response against the noise ensemble"),
    ("fill", "workflows.bench.fill", "What the fill law costs: table rates, the law with LSODA and BDF"),
    ("design", "workflows.bench.design", "Where the README's pbmdem design example spends its time"),
    ("predict", "workflows.bench.predict", "What the README's pbmdem predict example costs from the shell"),
    ("dem-post", "workflows.bench.dem_post", "DEM dump reader and post-processing"),
    ("rates", "workflows.bench.rates", "Transfer-rate estimators on a known chain"),
    ("dem-deck", "workflows.bench.dem_deck", "DEM deck efficiency and core-hours"),
    ("machine", "workflows.bench.machine", "What two ranks can gain on this machine at all"),
    ("scatter", "workflows.bench.scatter", "A deck change against the seed-to-seed scatter"),
    ("convergence", "workflows.bench.convergence", "What --stop-when-converged costs and saves on a completed run"),
    ("reference", "workflows.bench.reference", "Post-processing vs DEM wall time of the shipped runs"),
    ("same-numbers", "workflows.bench.same_numbers", "Did a refactoring change any number? Two captures compared"),
)
#: benchmarks ``all`` leaves out: they have no defaults to run with (an output directory,
#: two trees, a completed run directory) or take minutes without measuring this checkout's speed or accuracy
NOT_IN_ALL = frozenset({"same-numbers", "convergence"})


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="bench", required=True, metavar="BENCHMARK")
    every = sub.add_parser(
        "all", help="every benchmark below (but same-numbers) with its defaults, one after the other"
    )
    every.add_argument("only", nargs="*", help="run only these benchmarks (names as below)")
    every.set_defaults(func=run_all)
    for name, module_name, title in BENCHMARKS:
        module = importlib.import_module(module_name)
        bench = sub.add_parser(name, help=title, description=title)
        module.add_arguments(bench)
        bench.set_defaults(func=module.run)


def run_all(args: argparse.Namespace) -> int:
    """Every benchmark but :data:`NOT_IN_ALL` with its defaults; one that fails is reported and the others still
    run, so one broken benchmark does not hide the others' numbers."""
    unknown = set(args.only) - {name for name, _, _ in BENCHMARKS if name not in NOT_IN_ALL}
    if unknown:
        raise ConfigError(
            f"pbmdem bench all: unknown {sorted(unknown)}; known: "
            f"{', '.join(name for name, _, _ in BENCHMARKS if name not in NOT_IN_ALL)} "
            f"({', '.join(sorted(NOT_IN_ALL))}: run on its own)"
        )
    failed = []
    for name, module_name, title in BENCHMARKS:
        if name in NOT_IN_ALL or (args.only and name not in args.only):
            continue
        print(f"\n=== {title} (pbmdem bench {name}) ===", flush=True)
        module = importlib.import_module(module_name)
        parser = argparse.ArgumentParser(prog=f"pbmdem bench {name}")
        module.add_arguments(parser)
        try:
            module.run(parser.parse_args([]))
        except Exception as exc:  # noqa: BLE001 -- reported, and the next benchmark runs
            print(f"FAILED: {type(exc).__name__}: {exc}", flush=True)
            failed.append(name)
    return 1 if failed else 0
