"""The ``pbmdem`` command line: one entry, one list of commands, one error path.

Every command is a module of this package with ``HELP``, ``add_arguments(parser)`` and a
``run(args) -> int`` (or, for a command with subcommands, a ``func`` per subcommand). A
command parses its arguments and calls the library; library code raises, and only
:func:`main` turns a project error into one line on stderr and exit code 2
(``--traceback`` shows the whole trace instead). Every command shares one signal policy
(:mod:`coupling.interrupts`): SIGINT, SIGTERM and SIGHUP end it in ``pbmdem: interrupted``
and exit 128 + the signal's number (130, 143, 129), after the cleanups on the way out.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from coupling import interrupts
from coupling.errors import PbmDemError, error_line

#: (command, module): the order ``pbmdem --help`` lists them in.
COMMANDS = (
    ("config", "workflows.cli.config"),
    ("compare", "workflows.cli.compare"),
    ("validate", "workflows.cli.validate"),
    ("predict", "workflows.cli.predict"),
    ("design", "workflows.cli.design"),
    ("library", "workflows.cli.library"),
    ("dem", "workflows.cli.dem"),
    ("pbm", "workflows.cli.pbm"),
    ("targets", "workflows.cli.targets"),
    ("study", "workflows.cli.study"),
    ("bench", "workflows.cli.bench"),
)


def build_parser(argv: Sequence[str] | None = None) -> argparse.ArgumentParser:
    """The whole command line; with ``argv``, only the command it names gets its options
    (every command is still listed with its help), so a command does not import the
    libraries of every other (a study or a benchmark imports most of the product)."""
    parser = argparse.ArgumentParser(
        prog="pbmdem", description="Hybrid DEM-PBM pipeline for continuous powder blenders (Sen et al. 2013)."
    )
    parser.add_argument("--traceback", action="store_true", help="on an error, show the whole traceback")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    named = {name for name, _ in COMMANDS}
    chosen = None if argv is None else next((a for a in argv if a in named), None)
    for name, module_name in COMMANDS:
        module = importlib.import_module(module_name)
        command = sub.add_parser(name, help=module.HELP, description=module.HELP)
        if hasattr(module, "run"):
            command.set_defaults(func=module.run)
        if argv is None or name == chosen:
            module.add_arguments(command)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = None
    with interrupts.handled():
        try:
            args = build_parser(argv).parse_args(argv)
            return int(args.func(args) or 0)
        except BaseException as exc:
            # a compiled kernel (numba) reports an interrupt inside it as a SystemError raised
            # from it, and a cleanup that fails while an interrupt unwinds raises from it too
            interrupt = interrupts.interrupt_in(exc)
            if interrupt is not None:
                print("pbmdem: interrupted", file=sys.stderr)
                return getattr(interrupt, "exit_code", 130)
            # OSError: the file system said no (a path, the disk, a permission)
            if not isinstance(exc, (PbmDemError, OSError)) or args is None or args.traceback:
                raise
            print(f"pbmdem: error: {error_line(exc)}", file=sys.stderr)
            return 2
