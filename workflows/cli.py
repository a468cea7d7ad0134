"""The ``pbmdem`` command line: ``pbmdem pbm ...``, ``pbmdem dem ...``, ``pbmdem compare ...``.

Each stage registers its subcommands from its own module (``workflows/cli_*.py``). Library
code raises; only :func:`main` turns a project error into a message on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from coupling.errors import PbmDemError


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="pbmdem",
        description="Hybrid DEM-PBM pipeline for continuous powder blenders (Sen et al. 2013).",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    from workflows import cli_compare, cli_config, cli_dem, cli_pbm

    for module in (cli_config, cli_pbm, cli_dem, cli_compare):
        module.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except PbmDemError as exc:
        print(f"pbmdem: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("pbmdem: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
