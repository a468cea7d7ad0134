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


def test_the_responses_flops_are_schur_plus_the_back_substitutions():
    """25 n^3 per system and 4 n^2 per frequency, over the seconds they took."""
    from workflows.bench.design import _responses_work

    work = _responses_work([(100, 201, 0.5), (200, 201, 1.5)])
    flops = 25 * (100**3 + 200**3) + 4 * 201 * (100**2 + 200**2)
    assert work["flops"] == flops and work["flops_per_s"] == pytest.approx(flops / 2.0)
    assert (work["systems"], work["states_min"], work["states_max"]) == (2, 100, 200)
    assert _responses_work([])["systems"] == 0
