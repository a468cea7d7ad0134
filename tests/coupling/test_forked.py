"""A function run in a process forked early: its value and its errors come back, it runs
in another process (or here without fork), and a process given no work exits."""

import os
import time

import pytest

from coupling.forked import Prepared


def test_the_call_runs_in_the_forked_process_and_its_value_comes_back():
    with Prepared("os") as prepared:
        prepared.ready()
        prepared.start("getpid")
        child = prepared.result()
    assert isinstance(child, int) and child != os.getpid()
    with Prepared("os", fork=False) as here:
        here.ready()
        here.start("getpid")
        assert here.result() == os.getpid()


def test_an_error_in_the_call_or_the_import_is_raised_here():
    with Prepared("json") as prepared:
        prepared.start("loads", "{not json")
        with pytest.raises(ValueError, match="Expecting property name"):
            prepared.result()
    with Prepared("no_such_module_here") as prepared:
        prepared.ready()  # the failed import still answers
        prepared.start("anything")
        with pytest.raises(ModuleNotFoundError, match="no_such_module_here"):
            prepared.result()


def test_a_process_given_no_work_exits_when_closed():
    prepared = Prepared("os")
    process = prepared._process
    start = time.monotonic()
    prepared.close()
    assert not process.is_alive() and process.exitcode == 0
    assert time.monotonic() - start < 5  # not the terminate after the join's timeout


def test_one_call_per_process():
    with Prepared("os", fork=False) as prepared:
        with pytest.raises(RuntimeError, match="before start"):
            prepared.result()
        prepared.start("getpid")
        with pytest.raises(RuntimeError, match="already ran a call"):
            prepared.start("getpid")


def test_the_call_still_runs_when_the_process_dies_or_cannot_take_it():
    """A process killed before it answers, or arguments it cannot be sent: the call runs
    here instead, rather than being lost."""
    import signal

    with Prepared("os") as prepared:
        prepared.ready()
        os.kill(prepared._process.pid, signal.SIGKILL)
        prepared._process.join()
        prepared.start("getpid")
        assert prepared.result() == os.getpid()
    with Prepared("builtins") as prepared:
        prepared.start("callable", lambda: 0)  # a lambda cannot be pickled
        assert prepared.result() is True


def test_an_error_that_cannot_travel_comes_back_in_words(tmp_path, monkeypatch):
    (tmp_path / "odd_errors.py").write_text(
        "class Odd(Exception):\n"
        "    def __init__(self, a, b):\n"
        "        super().__init__(f'{a} and {b}')\n"
        "def boom():\n"
        "    raise Odd(1, 2)\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    with Prepared("odd_errors") as prepared:
        prepared.start("boom")
        with pytest.raises(RuntimeError, match=r"odd_errors.boom: Odd: 1 and 2"):
            prepared.result()


def test_a_parent_that_gives_up_on_the_call_leaves_no_trace(capfd):
    """The parent closes the pipe while the call runs (it failed, or Ctrl-C): the process
    ends quietly, without a traceback on stderr."""
    prepared = Prepared("time")
    prepared.start("sleep", 0.3)
    process = prepared._process
    prepared.close()
    assert process.exitcode == 0
    assert capfd.readouterr().err == ""
