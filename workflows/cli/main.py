"""The ``pbmdem`` command line: one entry, one list of commands, one error path.

Every command is a module of this package with ``HELP``, ``add_arguments(parser)`` and a
``run(args) -> int`` (or, for a command with subcommands, a ``func`` per subcommand). A
command parses its arguments and calls the library; library code raises, and only
:func:`main` turns a project error into one line on stderr and exit code 2
(``--traceback`` shows the whole trace instead). Bare ``pbmdem`` prints the help; a
misspelt command, at any level, gets one line naming the nearest (:class:`CommandParser`).
Every command shares one signal policy
(:mod:`coupling.interrupts`): SIGINT, SIGTERM and SIGHUP end it in ``pbmdem: interrupted``
and exit 128 + the signal's number (130, 143, 129), after the cleanups on the way out.
"""

from __future__ import annotations

import argparse
import difflib
import importlib
import shutil
import sys
import textwrap
import tomllib
from collections.abc import Sequence
from pathlib import Path

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
#: commands the help lists apart, under their own heading, after the product's own
STUDIES_AND_BENCHMARKS = ("study", "bench")


def version() -> str:
    """The installed package's version; from ``pyproject.toml`` when run from a source tree
    that is not installed."""
    from importlib import metadata

    try:
        return metadata.version("pbmdem")
    except metadata.PackageNotFoundError:
        pyproject = Path(__file__).resolve().parents[2] / "pyproject.toml"
        return tomllib.loads(pyproject.read_text())["project"]["version"]


class CommandParser(argparse.ArgumentParser):
    """argparse's parser, but a misspelt subcommand gets one line naming the nearest one
    (``pbmdem: error: unknown command 'dem rnu'; did you mean 'dem run'?``) and exit 2
    instead of the usage and the whole list. Subparsers are made of their parent's class,
    so this holds at every level (``pbmdem library ...``, ``pbmdem study ...``). A name
    near none keeps argparse's own message, which lists the choices.

    Flags are spelled whole (no abbreviations): ``--out`` always names a directory, and
    argparse would otherwise take it for ``--out-file`` where that is the only flag it
    begins."""

    def __init__(self, *args, **kwargs) -> None:
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)

    def _check_value(self, action: argparse.Action, value) -> None:
        # argparse checks a subcommand's name here, before the subparsers action runs; no
        # public hook sees the action and the value together (error() only gets the text)
        if isinstance(action, argparse._SubParsersAction) and value not in action.choices:
            nearest = difflib.get_close_matches(str(value), list(action.choices), n=1)
            if nearest:
                # the parser's prog names the path to this level: "pbmdem", "pbmdem dem"
                path = self.prog.split()[1:]
                typed, meant = " ".join([*path, str(value)]), " ".join([*path, nearest[0]])
                self.exit(2, f"pbmdem: error: unknown command {typed!r}; did you mean {meant!r}?\n")
        super()._check_value(action, value)


def build_parser(argv: Sequence[str] | None = None) -> argparse.ArgumentParser:
    """The whole command line; with ``argv``, only the command it names gets its options
    (every command is still listed with its help), so a command does not import the
    libraries of every other (a study or a benchmark imports most of the product)."""
    modules = {name: importlib.import_module(module_name) for name, module_name in COMMANDS}
    parser = CommandParser(
        prog="pbmdem",
        description="Hybrid DEM-PBM pipeline for continuous powder blenders (Sen et al. 2013).",
        epilog=_studies_and_benchmarks({name: modules[name].HELP for name in STUDIES_AND_BENCHMARKS}),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"pbmdem {version()}")
    parser.add_argument("--traceback", action="store_true", help="on an error, show the whole traceback")
    sub = parser.add_subparsers(title="commands", dest="command", required=True, metavar="COMMAND")
    named = {name for name, _ in COMMANDS}
    chosen = None if argv is None else next((a for a in argv if a in named), None)
    for name, module in modules.items():
        # listed apart in the epilog: a subparser added without help is not in the list
        listed = {} if name in STUDIES_AND_BENCHMARKS else {"help": module.HELP}
        command = sub.add_parser(name, description=module.HELP, **listed)
        if hasattr(module, "run"):
            command.set_defaults(func=module.run)
        if argv is None or name == chosen:
            module.add_arguments(command)
    return parser


def _studies_and_benchmarks(helps: dict[str, str]) -> str:
    """The help's last section: the study and bench commands under their own heading, laid
    out like argparse's list of commands above it (names indented by 4, wrapped to the
    terminal as argparse wraps)."""
    column = 4 + max(len(name) for name, _ in COMMANDS) + 3
    width = max(shutil.get_terminal_size().columns - 2, column + 20)
    lines = ["studies and benchmarks (research on the model; not needed to use it):"]
    for name, text in helps.items():
        lines += textwrap.wrap(text, width, initial_indent=f"    {name:<{column - 4}}", subsequent_indent=" " * column)
    return "\n".join([*lines, "", "'pbmdem COMMAND --help' shows a command's options."])


def main(argv: Sequence[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = None
    with interrupts.handled():
        try:
            parser = build_parser(argv)
            if not argv:
                parser.print_help()
                return 0
            try:
                args = parser.parse_args(argv)
            except SystemExit as exc:  # argparse has printed the help, the version or a usage error
                return exc.code if isinstance(exc.code, int) else 0 if exc.code is None else 2
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
