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
