"""The command line builds only the options of the command it is given: every command is
listed, a command's own options parse, and a command does not import the modules of the
others (a study or a benchmark imports most of the product)."""

import subprocess
import sys
from pathlib import Path

from workflows.cli.main import COMMANDS, build_parser

ROOT = Path(__file__).resolve().parents[3]


def test_every_command_is_listed_and_the_chosen_one_parses():
    parser = build_parser(["design", "--ca-within", "0.04"])
    help_text = parser.format_help()
    assert all(name in help_text for name, _ in COMMANDS)
    args = parser.parse_args(["design", "--ca-within", "0.04"])
    assert args.command == "design" and args.ca_within == 0.04
    full = build_parser()  # no argv: every command's options, as for the documentation
    assert full.parse_args(["study", "phases", "--results", "x.h5"]).study == "phases"


def test_a_command_does_not_import_the_studies_or_benchmarks():
    probe = (
        "import sys; from workflows.cli.main import build_parser; build_parser(['design']); "
        "print(sorted(m for m in sys.modules if m.startswith(('workflows.studies.', 'workflows.bench.'))))"
    )
    out = subprocess.run([sys.executable, "-c", probe], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
