"""The one rewrite path (coupling.files.replace_file, atomic_h5 over it) under failure: an
exception at any point leaves the file byte-identical and no temporary; the lock serialises
or refuses a second writer; a signal during a write is raised only once the write is whole.
The command-line chaos tests (a file-size limit, two commands, signals) are in
tests/workflows/cli/test_chaos.py."""

from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from coupling import files, interrupts
from coupling.cache import load_entry, save_entry
from coupling.errors import CacheError, Interrupted, OutputError
from coupling.files import locked, replace_file
from coupling.tables import atomic_h5
from tests.rewrites import REPO, leftovers, sha, shipped_copy


@pytest.fixture
def original(tmp_path) -> Path:
    return shipped_copy(tmp_path)


@pytest.mark.parametrize(
    ("failure", "raised", "says"),
    [
        (OSError(errno.ENOSPC, "No space left on device"), CacheError, "No space left on device"),
        (OSError(errno.EFBIG, "File too large"), CacheError, "File too large"),
        (RuntimeError("bug"), RuntimeError, "bug"),
        (KeyboardInterrupt(), KeyboardInterrupt, None),
    ],
    ids=["ENOSPC", "EFBIG", "exception", "interrupt"],
)
def test_a_write_failing_before_the_rename_leaves_the_file_and_no_temporary(
    original, monkeypatch, failure, raised, says
):
    before = sha(original)
    entry = load_entry(original)

    def fail(fd):
        assert any(name.endswith(".tmp") for name in leftovers(original.parent))  # there is one to remove
        raise failure

    monkeypatch.setattr(os, "fsync", fail)  # the whole image is in the temporary by then
    with pytest.raises(raised, match=says) as error:
        save_entry(original, entry)
    if raised is CacheError:
        assert str(original) in str(error.value) and "\n" not in str(error.value)
    assert sha(original) == before
    assert leftovers(original.parent) == []


def test_an_exception_while_the_hdf5_file_is_built_writes_nothing(original, monkeypatch):
    before = sha(original)
    entry = load_entry(original)
    import coupling.cache

    def half_then_fail(group, table):
        group.create_dataset("partial", data=np.arange(10))
        raise KeyboardInterrupt

    monkeypatch.setattr(coupling.cache, "table_to_group", half_then_fail)
    with pytest.raises(KeyboardInterrupt):
        save_entry(original, entry)
    assert sha(original) == before
    assert leftovers(original.parent) == []


def test_an_hdf5_write_on_a_new_path_is_whole_and_shareable(tmp_path):
    path = tmp_path / "sub" / "new.h5"
    with atomic_h5(path) as h5:
        h5.create_dataset("x", data=np.arange(1000), compression="gzip")
    import h5py

    with h5py.File(path, "r") as h5:
        assert h5["x"][-1] == 999
    umask = os.umask(0)
    os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask
    assert leftovers(path.parent) == []


def test_no_room_is_refused_before_anything_is_written(tmp_path, monkeypatch):
    path = tmp_path / "report.html"
    path.write_text("old")
    monkeypatch.setattr(files.shutil, "disk_usage", lambda where: SimpleNamespace(free=1000))
    with pytest.raises(
        OutputError, match=r"No space left on device for report .*report\.html: 5000 bytes to write, 1000 bytes free"
    ):
        replace_file(path, b"x" * 5000, "report")
    assert path.read_text() == "old" and leftovers(tmp_path) == []


def test_the_lock_is_reentrant_and_removed_on_release(tmp_path):
    path = tmp_path / "f.json"
    with locked(path) as target:
        assert (tmp_path / "f.json.lock").read_text().strip() == str(os.getpid())
        replace_file(path, "{}\n")  # the writer under a read-modify-write's lock
        assert target == path.resolve() and path.read_text() == "{}\n"
    assert leftovers(tmp_path) == []


HOLD = """
import sys, time
from coupling.files import locked
with locked(sys.argv[1]):
    print("held", flush=True)
    time.sleep(float(sys.argv[2]))
"""


def _holder(path: Path, seconds: float) -> subprocess.Popen:
    child = subprocess.Popen(
        [sys.executable, "-c", HOLD, str(path), str(seconds)], cwd=REPO, stdout=subprocess.PIPE, text=True
    )
    assert child.stdout.readline().strip() == "held"
    return child


def test_a_second_writer_waits_for_the_lock(tmp_path, monkeypatch):
    path = tmp_path / "f.json"
    monkeypatch.setenv("PBMDEM_LOCK_WAIT_S", "20")
    with _holder(path, 1.0):
        started = time.monotonic()
        replace_file(path, "mine\n")
        waited = time.monotonic() - started
    assert waited > 0.5 and path.read_text() == "mine\n"
    assert leftovers(tmp_path) == []


def test_a_second_writer_is_refused_after_the_wait_naming_the_file_and_the_holder(tmp_path, monkeypatch):
    path = tmp_path / "f.json"
    path.write_text("theirs\n")
    monkeypatch.setenv("PBMDEM_LOCK_WAIT_S", "0.3")
    with _holder(path, 3.0) as child:
        with pytest.raises(OutputError) as refused:
            replace_file(path, "mine\n", "JSON file")
        child.kill()
    message = str(refused.value)
    assert "\n" not in message and str(path) in message and f"pid {child.pid}" in message
    assert "PBMDEM_LOCK_WAIT_S" in message
    assert path.read_text() == "theirs\n"


def test_a_signal_during_a_write_is_raised_once_the_file_is_whole(tmp_path, monkeypatch):
    path = tmp_path / "f.json"
    path.write_text("old\n")
    real_fsync = os.fsync

    def signalled(fd):
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(0.05)  # Python runs the handler at the next bytecode: here, inside the write
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", signalled)
    with interrupts.handled(), pytest.raises(Interrupted) as raised:
        replace_file(path, "new\n")
    assert raised.value.exit_code == 128 + signal.SIGTERM
    assert path.read_text() == "new\n" and leftovers(tmp_path) == []
