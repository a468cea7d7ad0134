"""``pbmdem bench same-numbers`` on small synthetic capture trees (tmp_path). The real
capture runs pbmdem for minutes and is never started here: :func:`capture` is only shown
refusing, and the solver guard is tried with a fake ``liggghts``."""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
from pathlib import Path

import pytest

from coupling.errors import ConfigError
from workflows.bench.same_numbers import (
    CAPTURE_FILE,
    GUARD_EXIT,
    PRESETS,
    Difference,
    capture,
    capture_steps,
    compare_trees,
    solver_guard,
)
from workflows.cli import bench as bench_cli
from workflows.cli.main import main

DECK = "# deck\nunits si\ntimestep 5.9e-05\nrun 100000\n"
SUMMARY = {
    "metrics": {
        "mean_residence_time_pbm_s": 18.404478384334823,
        "pbm_wall_time_s": 0.118,
        "speedup_pbm_over_dem": 16201.9,
        "nan_value": math.nan,
    },
    "provenance": {
        "report_made": "2026-12-01T21:26:21+00:00",
        "commit": "9964567",
        "dem_wall_time_s": 1912.187176669,
        "dem_results_made": "2026-11-23T13:01:53+00:00",
    },
    "pbm_modes": {
        "velocity": {"wall_time_s": 0.12, "holdup": [2356.0, 1.5]},
        "measured": {"wall_time_s": 0.17, "holdup": [2292.0, 1.25]},
    },
    "vrr": {"pbm": {"velocity": {"ensemble_check": [{"ensemble_s": 1.1, "sd_time_domain": 0.0062}]}}},
}
REPORT = (
    "<html><table><tr><td>mrt</td><td>18.4</td></tr>"
    "<tr><td>report_made</td><td>2026-12-01T21:26:21+00:00</td></tr></table>\n<p>end</p>\n"
)


def make_tree(root: Path, summary: dict | None = None, deck: str = DECK, report: str = REPORT) -> Path:
    """A miniature capture: a deck, a config, a summary, a report, a log, a PNG."""
    (root / "decks/smoke/meshes").mkdir(parents=True)
    (root / "decks/smoke/dumps").mkdir()
    (root / "decks/smoke/in.blender").write_text(deck)
    (root / "decks/smoke/meshes/weir.stl").write_text("solid\nfacet normal 1.0 0.0 0.0\nendsolid\n")
    (root / "config-smoke.toml").write_text('name = "smoke"\n')
    results = root / "results/reduced-17ea"
    results.mkdir(parents=True)
    (results / "summary.json").write_text(json.dumps(summary if summary is not None else SUMMARY, indent=1))
    (results / "report.html").write_text(report)
    (results / "c_a.png").write_bytes(b"\x89PNG" + root.name.encode())  # differs per tree: skipped
    (root / "stdout").mkdir()
    (root / "stdout/compare.txt").write_text(f"report: {root}/results/reduced-17ea/report.html\n")
    (root / "_logs").mkdir()
    (root / "_logs/compare.stderr").write_text(f"{len(root.name)}.3 s\n")
    (root / CAPTURE_FILE).write_text(json.dumps({"tree_root": str(root), "source_root": f"/src/{root.name}"}))
    return root


def changed_summary(**edits) -> dict:
    """SUMMARY with ``a__b=value`` set (``KeyError`` as the value deletes the key)."""
    data = json.loads(json.dumps(SUMMARY))
    for dotted, value in edits.items():
        *parents, last = dotted.split("__")
        node = data
        for key in parents:
            node = node[key]
        if value is KeyError:
            del node[last]
        else:
            node[last] = value
    return data


@pytest.fixture
def before(tmp_path: Path) -> Path:
    return make_tree(tmp_path / "before")


# ----------------------------------------------------------------------------- compare_trees
def test_identical_trees_differ_in_nothing(before: Path, tmp_path: Path) -> None:
    after = make_tree(tmp_path / "after")  # other root, other PNG bytes, other stderr
    assert compare_trees(before, after) == []


def test_a_changed_number_is_reported(before: Path, tmp_path: Path) -> None:
    after = make_tree(tmp_path / "after", changed_summary(metrics__mean_residence_time_pbm_s=18.404478384334825))
    assert compare_trees(before, after) == [
        Difference(
            "results/reduced-17ea/summary.json",
            "metrics.mean_residence_time_pbm_s",
            18.404478384334823,
            18.404478384334825,
        )
    ]


def test_a_changed_number_in_a_list_is_reported(before: Path, tmp_path: Path) -> None:
    data = changed_summary()
    data["pbm_modes"]["measured"]["holdup"][1] = 1.2500000000000002
    diffs = compare_trees(before, make_tree(tmp_path / "after", data))
    assert [(d.where, d.before, d.after) for d in diffs] == [("pbm_modes.measured.holdup[1]", 1.25, 1.2500000000000002)]


def test_nan_equals_nan_but_not_a_number(before: Path, tmp_path: Path) -> None:
    assert compare_trees(before, make_tree(tmp_path / "same", changed_summary(metrics__nan_value=math.nan))) == []
    diffs = compare_trees(before, make_tree(tmp_path / "after", changed_summary(metrics__nan_value=0.0)))
    assert [d.where for d in diffs] == ["metrics.nan_value"]


def test_an_int_that_became_a_float_is_reported(before: Path, tmp_path: Path) -> None:
    data = changed_summary()
    data["pbm_modes"]["velocity"]["holdup"][0] = 2356  # same value, int instead of float
    assert [d.where for d in compare_trees(before, make_tree(tmp_path / "after", data))] == [
        "pbm_modes.velocity.holdup[0]"
    ]


def test_a_missing_and_an_extra_key_are_reported(before: Path, tmp_path: Path) -> None:
    data = changed_summary(provenance__dem_wall_time_s=KeyError, metrics__new_key=1)
    diffs = compare_trees(before, make_tree(tmp_path / "after", data))
    assert sorted((d.where, d.before, d.after) for d in diffs) == [
        ("metrics.new_key", "<absent>", 1),
        ("provenance.dem_wall_time_s", 1912.187176669, "<absent>"),
    ]


def test_an_extra_file_and_a_missing_file_are_reported(before: Path, tmp_path: Path) -> None:
    after = make_tree(tmp_path / "after")
    (after / "decks/smoke/meshes/new.stl").write_text("solid\nendsolid\n")
    (after / "config-smoke.toml").unlink()
    shutil.rmtree(after / "decks/smoke/dumps")
    assert sorted((d.path, d.before, d.after) for d in compare_trees(before, after)) == [
        ("config-smoke.toml", "file", "<absent>"),
        ("decks/smoke/dumps/", "empty directory", "<absent>"),
        ("decks/smoke/meshes/new.stl", "<absent>", "file"),
    ]


def test_a_changed_deck_line_is_reported_with_its_number(before: Path, tmp_path: Path) -> None:
    after = make_tree(tmp_path / "after", deck=DECK.replace("5.9e-05", "5.8e-05"))
    assert compare_trees(before, after) == [
        Difference("decks/smoke/in.blender", "line 3", "timestep 5.9e-05", "timestep 5.8e-05")
    ]


def test_an_inserted_deck_line_is_one_difference(before: Path, tmp_path: Path) -> None:
    after = make_tree(tmp_path / "after", deck=DECK.replace("units si\n", "units si\nnewton off\n"))
    assert compare_trees(before, after) == [Difference("decks/smoke/in.blender", "line 3", "<absent>", "newton off")]


def test_ignored_timestamps_and_wall_times_are_not_reported(before: Path, tmp_path: Path) -> None:
    data = changed_summary(
        provenance__report_made="2030-01-01T00:00:00+00:00",
        provenance__commit="abcdef0",
        metrics__pbm_wall_time_s=9.9,
        metrics__speedup_pbm_over_dem=1.0,
    )
    data["pbm_modes"]["velocity"]["wall_time_s"] = 3.0
    data["vrr"]["pbm"]["velocity"]["ensemble_check"][0]["ensemble_s"] = 2.0
    report = REPORT.replace("2026-12-01T21:26:21+00:00", "2030-01-01T00:00:00+00:00")
    assert compare_trees(before, make_tree(tmp_path / "after", data, report=report)) == []


def test_an_ignored_key_ignores_only_itself(before: Path, tmp_path: Path) -> None:
    data = changed_summary()
    data["vrr"]["pbm"]["velocity"]["ensemble_check"][0]["sd_time_domain"] = 0.0063
    diffs = compare_trees(before, make_tree(tmp_path / "after", data))
    assert [d.where for d in diffs] == ["vrr.pbm.velocity.ensemble_check[0].sd_time_domain"]


def test_shipped_timestamps_are_not_ignored(before: Path, tmp_path: Path) -> None:
    data = changed_summary(provenance__dem_results_made="2026-11-24T00:00:00+00:00")
    diffs = compare_trees(before, make_tree(tmp_path / "after", data))
    assert [d.where for d in diffs] == ["provenance.dem_results_made"]


def test_vtk_array_addresses_are_masked_but_its_data_compared(before: Path, tmp_path: Path) -> None:
    vtr = '<DataArray type="Float64" Name="Array {}" format="binary">\n  {}\n</DataArray>\n'
    after = make_tree(tmp_path / "after")
    (before / "grid.vtr").write_text(vtr.format("0x561644959920", "AQAAAAeF5jYIAB"))
    (after / "grid.vtr").write_text(vtr.format("0x556af2cf6de0", "AQAAAAeF5jYIAB"))
    assert compare_trees(before, after) == []
    (after / "grid.vtr").write_text(vtr.format("0x556af2cf6de0", "AQAAAAeF5jYIAC"))
    assert [(d.path, d.where) for d in compare_trees(before, after)] == [("grid.vtr", "line 2")]


def test_a_changed_number_in_the_html_is_reported(before: Path, tmp_path: Path) -> None:
    after = make_tree(tmp_path / "after", report=REPORT.replace("<td>18.4</td>", "<td>18.5</td>"))
    diffs = compare_trees(before, after)
    assert [(d.path, d.where) for d in diffs] == [("results/reduced-17ea/report.html", "line 1")]
    assert "18.4" in str(diffs[0]) and "18.5" in str(diffs[0])


def test_a_tree_that_is_not_a_directory_is_refused(before: Path, tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="nowhere"):
        compare_trees(before, tmp_path / "nowhere")


# ----------------------------------------------------------------------------- capture
def test_capture_refuses_a_non_empty_directory_and_writes_nothing(tmp_path: Path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "old.txt").write_text("a previous capture\n")
    with pytest.raises(ConfigError, match="not an empty directory"):
        capture(out, entry=["false"], checkout=Path(__file__).resolve().parents[3])
    assert [p.name for p in out.iterdir()] == ["old.txt"]


def test_the_steps_write_under_the_tree_in_the_layout_compared() -> None:
    out = Path("/captures/x")
    steps = capture_steps(out)
    assert [s.name for s in steps] == [
        *(f"{kind}-{p}" for p in PRESETS for kind in ("config", "deck")),
        "compare",
        "validate",
        "design",
    ]
    assert {s.stdout for s in steps if s.name.startswith("config-")} == {f"config-{p}.toml" for p in PRESETS}
    paths = [a for s in steps for a in s.args if a.startswith("/")]
    assert paths and all(a.startswith("/captures/x/") for a in paths)


def test_the_guard_refuses_the_solver_but_forwards_the_version_banner(tmp_path: Path) -> None:
    real = tmp_path / "bin"
    real.mkdir()
    (real / "liggghts").write_text('#!/bin/sh\necho "LIGGGHTS (fake banner) $*"\n')
    (real / "liggghts").chmod(0o755)
    with solver_guard(f"{real}{os.pathsep}/usr/bin:/bin") as path:
        env = {**os.environ, "PATH": path}

        def sh(command: str) -> subprocess.CompletedProcess:
            return subprocess.run(["/bin/sh", "-c", command], env=env, capture_output=True, text=True, check=False)

        banner = sh("liggghts -log none -h")
        assert banner.returncode == 0 and banner.stdout == "LIGGGHTS (fake banner) -log none -h\n"
        for command in ("liggghts -in in.blender", "mpirun -np 2 liggghts -in in.blender", "mpiexec -n 1 true"):
            refused = sh(command)
            assert refused.returncode == GUARD_EXIT and "refusing" in refused.stderr, command
    assert not Path(path.split(os.pathsep)[0]).exists()


# ----------------------------------------------------------------------------- command line
def test_the_command_line_compares_and_reports_by_exit_code(
    before: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    same = make_tree(tmp_path / "same")
    assert main(["bench", "same-numbers", "compare", str(before), str(same)]) == 0
    assert capsys.readouterr().out.splitlines()[-1] == "6 files compared, 0 differences"

    after = make_tree(
        tmp_path / "after",
        deck=DECK.replace("run 100000", "run 200000"),
        summary=changed_summary(metrics__mean_residence_time_pbm_s=1.0),
    )
    assert main(["bench", "same-numbers", "compare", str(before), str(after), "--list-skipped"]) == 1
    lines = capsys.readouterr().out.splitlines()
    assert lines[-1] == "6 files compared, 2 differences"
    assert any(line.startswith("decks/smoke/in.blender: line 4:") for line in lines)
    assert any(line.startswith("skipped: results/reduced-17ea/c_a.png") for line in lines)

    assert main(["bench", "same-numbers", "capture", str(before)]) == 2  # not empty: one line, exit 2
    assert "refusing to mix two captures" in capsys.readouterr().err


def test_bench_all_does_not_run_it(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    assert "same-numbers" in bench_cli.NOT_IN_ALL
    assert "same-numbers" in {name for name, _, _ in bench_cli.BENCHMARKS}
    monkeypatch.setattr(bench_cli, "BENCHMARKS", tuple(b for b in bench_cli.BENCHMARKS if b[0] in bench_cli.NOT_IN_ALL))
    assert bench_cli.run_all(argparse.Namespace(only=[])) == 0
    assert capsys.readouterr().out == ""
    with pytest.raises(ConfigError, match="same-numbers"):
        bench_cli.run_all(argparse.Namespace(only=["same-numbers"]))
