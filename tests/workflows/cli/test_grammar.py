"""One command-line grammar: ``--version``, the help when run bare, the nearest command named
for a misspelt one at every level, the studies and benchmarks listed apart from the
product's commands, and a refused rerun told in the command line's flags."""

import argparse
import json
import re
import tomllib
from pathlib import Path

import pytest

from dem import deck
from dem.run import STATUS_FILE, prepare_run
from tests.known_dumps import variant
from workflows.cli.main import COMMANDS, STUDIES_AND_BENCHMARKS, main
from workflows.config import dump_toml, load_preset

ROOT = Path(__file__).resolve().parents[3]


def test_version_prints_the_package_version(capsys):
    assert main(["--version"]) == 0
    out = capsys.readouterr().out
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert out == f"{project['name']} {project['version']}\n"


def test_bare_pbmdem_prints_the_help_and_succeeds(capsys):
    assert main([]) == 0
    captured = capsys.readouterr()
    assert captured.out.startswith("usage: pbmdem") and "commands:" in captured.out
    assert captured.err == ""


@pytest.mark.parametrize(
    "argv, typed, meant",
    [
        (["predcit"], "predcit", "predict"),
        (["libary", "fit"], "libary", "library"),
        (["dem", "rnu"], "dem rnu", "dem run"),
        (["library", "fti", "--results", "x.h5"], "library fti", "library fit"),
        (["study", "phsaes"], "study phsaes", "study phases"),
    ],
)
def test_a_misspelt_command_gets_the_nearest_in_one_line(capsys, argv, typed, meant):
    assert main(argv) == 2
    captured = capsys.readouterr()
    assert captured.err == f"pbmdem: error: unknown command {typed!r}; did you mean {meant!r}?\n"
    assert captured.out == ""


def test_a_command_near_none_keeps_argparse_listing_the_choices(capsys):
    assert main(["xyzzy"]) == 2
    err = capsys.readouterr().err
    assert "did you mean" not in err and "invalid choice: 'xyzzy'" in err and "'predict'" in err


def test_the_help_lists_the_product_first_and_studies_and_benchmarks_apart(capsys):
    assert main(["--help"]) == 0
    help_text = capsys.readouterr().out
    product, _, apart = help_text.partition("studies and benchmarks")
    assert apart, help_text
    for name, _ in COMMANDS:
        listed = re.compile(rf"^    {re.escape(name)}\s", re.MULTILINE)
        assert bool(listed.search(apart)) == (name in STUDIES_AND_BENCHMARKS), name
        assert bool(listed.search(product)) == (name not in STUDIES_AND_BENCHMARKS), name
    # the subcommands are not named in the top-level usage or list: only the two headings hold them
    assert "{" not in help_text.splitlines()[0]


@pytest.fixture
def stopped_run(tmp_path):
    """A config whose LIGGGHTS is a stand-in that only prints a banner, and its run directory
    left interrupted with two dumps and restart files, as a Ctrl-C leaves it."""
    fake = tmp_path / "liggghts"
    fake.write_text('#!/bin/sh\necho "LIGGGHTS (Version LIGGGHTS-PUBLIC 3.8.0, a stand-in)"\n')
    fake.chmod(0o755)
    config = variant(load_preset("smoke"), run={"np": 1, "launcher": "", "liggghts": str(fake)})
    config_file = tmp_path / "config.toml"
    config_file.write_text(dump_toml(config))
    run_dir = tmp_path / "runs" / prepare_run(config.dem).key
    for name in ("dumps/dump.0.txt", "dumps/dump.1000.txt"):
        (run_dir / name).parent.mkdir(parents=True, exist_ok=True)
        (run_dir / name).write_text("ITEM: TIMESTEP\n")
    (run_dir / "restart").mkdir()
    (run_dir / STATUS_FILE).write_text(json.dumps({"state": "interrupted"}))
    return config_file, run_dir


def _rerun(config_file, run_dir, capsys):
    argv = ["dem", "run", "--config", str(config_file), "--runs-dir", str(run_dir.parent), "--no-progress"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("pbmdem: error: run ") and err.endswith(f"\n  run directory: {run_dir}\n"), err
    assert "=True" not in err and "resume=" not in err and "fresh=" not in err
    return err.splitlines()[0]


def test_a_refused_rerun_names_the_restart_file_and_the_flags(stopped_run, capsys):
    config_file, run_dir = stopped_run
    (run_dir / "restart" / "restart.1000.bin").write_bytes(b"\0" * 64)
    # a thermo row at step 1000 in LIGGGHTS' log: the restart of step 1000 is complete
    (run_dir / deck.LOG_FILE).write_text("Step Atoms\n1000 5\n")
    line = _rerun(config_file, run_dir, capsys)
    assert "with 2 dumps and 1 complete restart file;" in line, line
    assert line.endswith(
        "continue it with --resume (from restart/restart.1000.bin), or discard it and start again with --fresh"
    ), line


def test_a_refused_rerun_without_a_complete_restart_offers_only_fresh(stopped_run, capsys):
    config_file, run_dir = stopped_run
    # written, but no log shows its step reached: cut short, --resume cannot use it
    (run_dir / "restart" / "restart.1000.bin").write_bytes(b"\0" * 64)
    line = _rerun(config_file, run_dir, capsys)
    assert "with 2 dumps and 0 complete restart files (and 1 cut short);" in line, line
    assert line.endswith("nothing to resume from: discard it and start again with --fresh"), line
    assert "--resume" not in line


def _options(parser=None, path=()):
    """(command path, action) of every option of the whole command line."""
    import argparse

    from workflows.cli.main import build_parser

    parser = build_parser() if parser is None else parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _options(sub, (*path, name))
        elif action.option_strings:
            yield path, action


def test_out_always_names_a_directory_and_a_file_flag_says_so():
    outs = [(path, a) for path, a in _options() if "--out" in a.option_strings]
    files = {path for path, a in _options() if "--out-file" in a.option_strings}
    assert len(outs) > 15 and {("dem", "post"), ("pbm", "synth"), ("bench", "pbm"), ("study", "lag")} <= files
    for path, action in outs:
        # a default with a suffix (results/x.json) or help naming a file is a file flag under the wrong name
        assert action.default is None or not Path(str(action.default)).suffix, (path, action.default)
        assert not re.search(r"\b(file|HDF5|JSON)\b", action.help or ""), (path, action.help)
    # compare's earlier --results-dir still works, as --out under another name, and is not listed
    earlier = [(path, a) for path, a in _options() if "--results-dir" in a.option_strings]
    assert [(path, a.dest, a.help) for path, a in earlier] == [(("compare",), "out", argparse.SUPPRESS)]


def test_the_ranks_default_to_the_configuration_in_every_product_command():
    ranks = [(path, a.default) for path, a in _options() if "--np" in a.option_strings]
    product = [(path, default) for path, default in ranks if path[0] not in STUDIES_AND_BENCHMARKS]
    assert {("compare",), ("validate",), ("dem", "run"), ("dem", "slurm"), ("library", "build")} <= {
        path for path, _ in product
    }
    assert all(default is None for _, default in product), product


def test_a_flag_is_spelled_whole(tmp_path, capsys):
    # without this, argparse would read --out as the only flag it begins, --out-file
    table = tmp_path / "t.h5"
    assert main(["pbm", "synth", "--out", str(table), "--nx", "2", "--ny", "2", "--windows", "1"]) == 2
    assert "--out-file" in capsys.readouterr().err and not table.exists()
    assert main(["pbm", "synth", "--out-file", str(table), "--nx", "2", "--ny", "2", "--windows", "1"]) == 0
    assert table.stat().st_size > 0


@pytest.mark.parametrize("ranks", [None, 3])
def test_dem_slurm_takes_its_ranks_from_the_configuration(ranks, tmp_path, capsys):
    config = load_preset("paper")
    config = config.model_copy(
        update={"dem": config.dem.model_copy(update={"run": config.dem.run.model_copy(update={"np": 5})})}
    )
    config_file = tmp_path / "paper.toml"
    config_file.write_text(dump_toml(config))
    argv = ["dem", "slurm", "--config", str(config_file), "--out", str(tmp_path / "job")]
    argv += ["--holdup", "1000", "--throughput", "1e6", *([] if ranks is None else ["--np", str(ranks)])]
    assert main(argv) == 0
    expected = 5 if ranks is None else ranks
    assert f"estimate on {expected} cores" in capsys.readouterr().out
    assert f"#SBATCH --ntasks={expected}\n" in (tmp_path / "job" / "job.slurm").read_text()
