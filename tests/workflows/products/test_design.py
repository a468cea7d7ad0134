"""``pbmdem design`` end to end on the shipped library model: the files, the answer's lines,
the exit codes of a spec met nowhere and of a space outside the domain."""

import json

from workflows.cli.main import main

EXAMPLE = ["design", "--ca-within", "0.04", "--noise-sigma", "0.1", "--noise-tau", "5", "--mrt-max", "25"]


def test_the_readme_example_writes_its_files(tmp_path, capsys):
    assert main([*EXAMPLE, "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "shortest blender:" in out and "P(spec met)" in out and "mean delay" in out
    record = json.loads((tmp_path / "design.json").read_text())
    assert record["shortest"]["probability"] >= 0.95
    assert record["dynamics"]["shortest"]["vrr"]["low"] <= record["dynamics"]["shortest"]["vrr"]["high"]
    page = (tmp_path / "report.html").read_text()
    assert 'alt="Left: P(spec met) over impeller speed' in page and "feasible.png" in page
    assert (tmp_path / "feasible.png").stat().st_size > 10_000
    assert not list(tmp_path.glob(".feasible-*"))


def test_a_spec_met_nowhere_exits_1(tmp_path, capsys):
    assert main(["design", "--mrt-max", "1", "--out", str(tmp_path)]) == 1
    assert "no point searched meets the spec" in capsys.readouterr().out


def test_outside_the_domain_is_one_line_and_writes_nothing(tmp_path, capsys):
    out = tmp_path / "design"
    assert main(["design", "--mrt-max", "25", "--rpm-max", "500", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "the domain is 150-350 rpm" in err and "--extrapolate" in err
    assert not out.exists()
