"""The machine benchmark: its arguments are checked before any solver starts, and (marked
``liggghts``) a tiny real run records a bound and a speed-up per launcher."""

import json

import pytest

from workflows.bench import machine as bench_machine
from workflows.cli.main import main


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--particles", "1546,many"], "comma-separated whole numbers"),
        (["--particles", "0"], ">= 1"),
        (["--launchers", "mpirun -np 2"], "no {np}"),
        (["--repeats", "0"], "--repeats 0: expected a whole number >= 1"),
        (["--steps", "-5"], "--steps -5: expected a whole number >= 1"),
    ],
)
def test_bad_arguments_are_refused_by_name(argv, message, capsys):
    try:
        code = main(["bench", "machine", *argv])
    except SystemExit as exit_:  # argparse refuses a malformed option value itself
        code = exit_.code
    assert code == 2
    assert message in capsys.readouterr().err


def test_launcher_labels():
    assert bench_machine._label("mpirun --allow-run-as-root -np {np}") == "as the runs use it"
    assert bench_machine._label("mpirun --allow-run-as-root --bind-to none -np {np}") == "--bind-to none"


@pytest.mark.liggghts
def test_tiny_run_records_bound_and_speedups(tmp_path):
    out = tmp_path / "machine.json"
    launcher = "mpirun --allow-run-as-root --oversubscribe -np {np}"
    assert (
        main(
            [
                "bench",
                "machine",
                "--particles",
                "60",
                "--steps",
                "200",
                "--repeats",
                "1",
                "--launchers",
                launcher,
                "--out-file",
                str(out),
            ]
        )
        == 0
    )
    record = json.loads(out.read_text())
    (bed,) = record["beds"]
    assert bed["particles"] == 60 and len(bed["alone"]) == len(bed["together"]) == 1
    assert record["bound_two_ranks"] == bed["bound_two_ranks"] > 0
    assert list(bed["two_ranks"]) == [launcher] and bed["two_ranks"][launcher]["speedup"] > 0
