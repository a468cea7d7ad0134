"""The design benchmark's fresh-interpreter timer: a failing command is reported with its
exit code and error, not timed as if it had answered; and one repeat of the whole
benchmark on the shipped library."""

import json
import statistics

import pytest

from workflows.bench.design import _fresh
from workflows.cli.main import main


def test_a_fresh_interpreter_is_timed_and_a_failure_named():
    times = _fresh(["-c", "pass"], 2)
    assert len(times) == 2 and all(t > 0 for t in times)
    # exit code 1 is the design command's "met nowhere": an answer, still timed
    assert len(_fresh(["-c", "raise SystemExit(1)"], 1)) == 1
    with pytest.raises(RuntimeError, match=r"failed \(3\): .*no such spec"):
        _fresh(["-c", "import sys; sys.stderr.write('no such spec'); raise SystemExit(3)"], 1)


def test_the_responses_flops_are_schur_plus_the_back_substitutions():
    """25 n^3 per system and 4 n^2 per frequency, over the seconds they took."""
    from workflows.bench.design import _responses_work

    work = _responses_work([(100, 201, 0.5), (200, 201, 1.5)])
    flops = 25 * (100**3 + 200**3) + 4 * 201 * (100**2 + 200**2)
    assert work["flops"] == flops and work["flops_per_s"] == pytest.approx(flops / 2.0)
    assert (work["systems"], work["states_min"], work["states_max"]) == (2, 100, 200)
    assert _responses_work([])["systems"] == 0


def test_one_repeat_end_to_end(tmp_path):
    """``pbmdem bench design --repeats 1`` on the shipped library: every measurement is
    made once, the command's imports cost at least the libraries' alone, and the floor is
    the sum it says it is."""
    out = tmp_path / "design.json"
    assert main(["bench", "design", "--repeats", "1", "--out-file", str(out)]) == 0
    record = json.loads(out.read_text())
    assert record["command"][:2] == ["pbmdem", "design"]
    for key in ("command_s", "imports_of_the_command_s", "imports_of_the_libraries_alone_s"):
        assert len(record[key]) == 1 and record[key][0] > 0, key
    assert record["command_median_s"] > record["imports_of_the_libraries_alone_s"][0]
    work = record["frequency_responses"]
    # the search answers from frequency responses of the library's 10 x 10 and 20 x 10 systems
    assert work["systems"] > 0 and 0 < work["search_seconds"] <= work["seconds"]
    assert work["states_min"] >= 100 and work["states_max"] <= 200
    assert len(record["stages_s"]) == 5 and all(t > 0 for t in record["stages_s"].values())
    responses = work["search_seconds"] / record["search_speedup"] + work["seconds"] - work["search_seconds"]
    floor = statistics.median(record["imports_of_the_libraries_alone_s"]) + record["h5py_read_of_the_library_s"]
    assert record["floor_s"] == pytest.approx(floor + responses)
