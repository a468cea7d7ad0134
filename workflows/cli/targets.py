"""``pbmdem targets``: the measured-rates targets, checked on comparisons' ``summary.json``
(:func:`workflows.analysis.targets.check`); exit 1 if any fails."""

from __future__ import annotations

import argparse
import glob
from pathlib import Path

from coupling.errors import ConfigError

HELP = "check the measured-rates targets on comparisons' summary.json (exit 1 if any fails)"
DEFAULT = "results/reduced-*/summary.json"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "summaries", nargs="*", default=[DEFAULT], help="summary.json files or globs (default: %(default)s)"
    )


def run(args: argparse.Namespace) -> int:
    from workflows.analysis.targets import checked, read_summary

    paths = [Path(p) for pattern in args.summaries for p in sorted(glob.glob(pattern))]
    if not paths:
        raise ConfigError(f"no summary.json at {' '.join(args.summaries)}: run `make full-comparison` first")
    failed = False
    for path in paths:
        lines = checked(read_summary(path), path)
        print(path)
        for target, numbers, passed in lines:
            flag = "info" if passed is None else ("PASS" if passed else "FAIL")
            failed |= passed is False
            print(f"  {flag:4}  {target}: {numbers}")
    return 1 if failed else 0
