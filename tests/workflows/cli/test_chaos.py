"""Chaos tests of the commands that rewrite a results file in place (``dem recompute-steady``,
``dem refit-phases``): a file-size limit (``ulimit -f``) before and during the write, two
commands on one file, SIGINT and SIGTERM mid-work. Each ends in one line and the exit code
the shell expects, with the file as it was (or whole and new) and no temporary left."""

from __future__ import annotations

import os
import resource
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from coupling.cache import load_entry
from coupling.errors import Interrupted
from tests.rewrites import REPO, leftovers, sha, shipped_copy
from workflows.cli.main import main


@pytest.fixture
def results(tmp_path) -> Path:
    return shipped_copy(tmp_path)


def _limited(max_bytes: int):
    return lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (max_bytes, max_bytes))


#: a child that skips the room check, so that the write itself meets the limit (EFBIG)
UNCHECKED = (
    "import sys, coupling.files as f; f._check_room = lambda *a: None; "
    "from workflows.cli.main import main; raise SystemExit(main(sys.argv[1:]))"
)


@pytest.mark.parametrize("checked", [True, False], ids=["refused-before", "failing-write"])
def test_a_rewrite_over_the_file_size_limit_ends_in_one_line(results, checked):
    before = sha(results)
    start = ["-m", "workflows.cli"] if checked else ["-c", UNCHECKED]
    done = subprocess.run(
        [sys.executable, *start, "dem", "recompute-steady", str(results)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
        preexec_fn=_limited(results.stat().st_size // 2),
    )
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 2, done.stderr[-2000:]  # not 139 (HDF5 closing after a failed write)
    assert len(lines) == 1 and lines[0].startswith("pbmdem: error:") and str(results) in lines[0], done.stderr
    assert "File too large" in lines[0]
    assert sha(results) == before and leftovers(results.parent) == []


SLOW_WRITER = """
import dataclasses, sys, time
from coupling.cache import load_entry, save_entry
from coupling.files import locked
path = sys.argv[1]
with locked(path, "results file"):
    entry = load_entry(path)
    print("read", flush=True)
    time.sleep(float(sys.argv[2]))
    summary = {k: v for k, v in entry.summary.items() if k != "steady"}
    save_entry(path, dataclasses.replace(entry, summary=summary, provenance={**entry.provenance, "writer": "first"}))
"""


def _first_writer(path: Path, seconds: float) -> subprocess.Popen:
    child = subprocess.Popen(
        [sys.executable, "-c", SLOW_WRITER, str(path), str(seconds)], cwd=REPO, stdout=subprocess.PIPE, text=True
    )
    assert child.stdout.readline().strip() == "read"
    return child


def test_a_second_command_on_the_file_waits_and_keeps_the_first_result(results, monkeypatch, capsys):
    monkeypatch.setenv("PBMDEM_LOCK_WAIT_S", "60")
    with _first_writer(results, 2.0) as first:
        assert main(["dem", "recompute-steady", str(results)]) == 0
        assert first.wait(timeout=60) == 0
    entry = load_entry(results)
    # the second read the first's file (its mark kept) and wrote its own result into it
    assert entry.provenance["writer"] == "first" and entry.summary["steady"]["holdup"]["value"] > 0
    assert leftovers(results.parent) == []


def test_a_second_command_on_the_file_is_refused_in_one_line_after_the_wait(results, monkeypatch, capsys):
    monkeypatch.setenv("PBMDEM_LOCK_WAIT_S", "0.3")
    with _first_writer(results, 3.0) as first:
        capsys.readouterr()
        assert main(["dem", "recompute-steady", str(results)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert first.wait(timeout=60) == 0
    assert len(err) == 1 and str(results) in err[0] and f"another process (pid {first.pid})" in err[0], err
    assert load_entry(results).provenance["writer"] == "first"  # nothing lost
    assert leftovers(results.parent) == []


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_a_signal_mid_refit_ends_interrupted_with_the_file_untouched(results, sig):
    before = sha(results)
    lock = results.with_name(results.name + ".lock")
    with subprocess.Popen(
        [sys.executable, "-m", "workflows.cli", "dem", "refit-phases", str(results)],
        cwd=REPO,
        stderr=subprocess.PIPE,
        stdout=subprocess.DEVNULL,
        text=True,
    ) as child:
        deadline = time.monotonic() + 60
        while not lock.exists() and child.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert lock.exists(), "the refit never took the file's lock"
        time.sleep(1.5)  # reading done, fitting (a refit of this file takes 20 s or more)
        assert child.poll() is None
        child.send_signal(sig)
        err = child.stderr.read()
        code = child.wait(timeout=60)
    assert code == 128 + sig, err[-2000:]
    assert err.strip() == "pbmdem: interrupted"
    assert sha(results) == before and leftovers(results.parent) == []


@pytest.mark.parametrize(
    ("interrupt", "code"), [(KeyboardInterrupt(), 130), (Interrupted(signal.SIGTERM), 143)], ids=["INT", "TERM"]
)
def test_an_interrupt_inside_a_compiled_kernel_is_an_interrupt(monkeypatch, capsys, interrupt, code):
    """Numba's dispatcher reports a KeyboardInterrupt raised inside it as a SystemError."""
    import workflows.cli.dem

    def kernel(args):
        try:
            raise interrupt
        except KeyboardInterrupt as exc:
            raise SystemError("<numba dispatcher> returned a result with an exception set") from exc

    monkeypatch.setattr(workflows.cli.dem, "recompute_steady_command", kernel)
    capsys.readouterr()
    assert main(["dem", "recompute-steady", "any.h5"]) == code
    assert capsys.readouterr().err == "pbmdem: interrupted\n"


def test_the_signal_handlers_are_given_back_after_a_command(capsys):
    before = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    main(["dem", "recompute-steady", os.devnull])
    assert {sig: signal.getsignal(sig) for sig in before} == before
