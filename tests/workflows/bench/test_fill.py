"""``pbmdem bench fill`` end to end on the shipped runs (measured rates: the phase model's
fill law under noise takes minutes): LSODA and BDF integrate the same bulk, so their
hold-ups agree; the option lists are refused by name."""

import json

import pytest

from workflows.cli.main import main


def test_measured_mode_on_both_cases(tmp_path):
    out = tmp_path / "fill.json"
    assert main(["bench", "fill", "--repeats", "1", "--modes", "measured", "--out-file", str(out)]) == 0
    record = json.loads(out.read_text())
    rows = record["rows"]
    assert record["repeats"] == 1
    assert [(row["case"].split(",")[0], row["mode"]) for row in rows] == [
        ("validation baseline", "measured"),
        ("reduced", "measured"),
    ]
    for row in rows:
        assert row["table_s"] > 0 and row["fill_LSODA_s"] > 0 and row["fill_BDF_s"] > 0
        # two integrators of one ODE at rtol 1e-6 on ~1500 particles (measured 2e-4 and 4e-4)
        assert row["max_holdup_difference"] < 1e-2


@pytest.mark.parametrize(
    "argv, message",
    [
        (
            ["--cases", "baseline,nope"],
            "--cases 'baseline,nope': unknown ['nope']; choose from baseline, reduced-noise",
        ),
        (["--modes", "velocity"], "choose from measured, phases"),
        (["--repeats", "0"], "--repeats 0: expected a whole number >= 1"),
    ],
)
def test_bad_options_are_one_line(argv, message, tmp_path, capsys):
    assert main(["bench", "fill", *argv, "--out-file", str(tmp_path / "fill.json")]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "fill.json").exists()
