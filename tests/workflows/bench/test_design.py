"""The design benchmark's fresh-interpreter timer: a failing command is reported with its
exit code and error, not timed as if it had answered; and one repeat of the whole
benchmark on the shipped library."""

import json

import pytest

from workflows.bench.design import fresh
from workflows.cli.main import main


def test_a_fresh_interpreter_is_timed_and_a_failure_named():
    times, cpus = fresh(["-c", "pass"], 2)
    assert len(times) == len(cpus) == 2 and all(t > 0 for t in times) and all(c > 0 for c in cpus)
    # exit code 1 is the design command's "met nowhere": an answer, still timed
    assert len(fresh(["-c", "raise SystemExit(1)"], 1)[0]) == 1
    with pytest.raises(RuntimeError, match=r"failed \(3\): .*no such spec"):
        fresh(["-c", "import sys; sys.stderr.write('no such spec'); raise SystemExit(3)"], 1)


def test_one_repeat_end_to_end(tmp_path):
    """``pbmdem bench design --repeats 1`` on the shipped library: every measurement is
    made once, the command costs more than the libraries' imports alone, and every stage
    is timed."""
    out = tmp_path / "design.json"
    assert main(["bench", "design", "--repeats", "1", "--out-file", str(out)]) == 0
    record = json.loads(out.read_text())
    assert record["command"][:2] == ["pbmdem", "design"]
    for key in (
        "command_s",
        "command_cpu_s",
        "command_process_cpu_s",
        "figure_process_cpu_s",
        "imports_of_the_command_s",
        "imports_of_the_libraries_alone_s",
    ):
        assert len(record[key]) == 1 and record[key][0] > 0, key
    assert record["command_median_s"] > record["imports_of_the_libraries_alone_s"][0]
    assert len(record["stages_s"]) == 4 and all(t > 0 for t in record["stages_s"].values())
    assert record["points_evaluated"] > 100
