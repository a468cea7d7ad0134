"""The design benchmark's fresh-interpreter timer: a failing command is reported with its
exit code and error, not timed as if it had answered."""

import pytest

from workflows.bench.design import _fresh


def test_a_fresh_interpreter_is_timed_and_a_failure_named():
    times = _fresh(["-c", "pass"], 2)
    assert len(times) == 2 and all(t > 0 for t in times)
    # exit code 1 is the design command's "met nowhere": an answer, still timed
    assert len(_fresh(["-c", "raise SystemExit(1)"], 1)) == 1
    with pytest.raises(RuntimeError, match=r"failed \(3\): .*no such spec"):
        _fresh(["-c", "import sys; sys.stderr.write('no such spec'); raise SystemExit(3)"], 1)
