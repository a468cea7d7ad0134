"""The LIGGGHTS solver as a process: its version, its command line, running it under
supervision.

- :func:`liggghts_version`, :func:`solver_command` (checks that the programs exist) and
  :func:`launch_command` (the same argv, pure: for a job script run elsewhere);
- :func:`run_solver` runs a command in a directory, streams its output to a file line by
  line, collects ``ERROR`` lines, stops every MPI rank on Ctrl-C, on a timeout or when the
  solver hangs after an error, and returns a :class:`SolverResult`.

Reading what the solver prints is :mod:`dem.liggghts_log`.

Errors: :class:`~coupling.errors.SolverNotFoundError` (a program is missing; the message
carries the install command), :class:`~coupling.errors.SolverRunError` (a timeout).
"""

from __future__ import annotations

import os
import queue
import re
import resource
import shlex
import shutil
import signal
import subprocess
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

from coupling.errors import SolverNotFoundError, SolverRunError
from dem.deck import MAIN_DECK

__all__ = [
    "INSTALL_HINT",
    "SolverResult",
    "launch_command",
    "liggghts_version",
    "run_solver",
    "solver_command",
    "text_tail",
]

INSTALL_HINT = "install it with `apt-get install liggghts openmpi-bin` (or `make setup`)"


def check_tmpdir(environ=None) -> None:
    """Open MPI (which Debian's LIGGGHTS is linked against, even on one rank) creates its
    session directory under ``$TMPDIR`` and aborts before LIGGGHTS prints anything when it
    cannot: refuse a TMPDIR that is not an existing, writable directory, naming it.
    Raises SolverRunError."""
    environ = os.environ if environ is None else environ
    tmpdir = environ.get("TMPDIR")
    if not tmpdir:
        return
    probe = tmpdir
    while not os.path.lexists(probe):  # Open MPI creates a missing TMPDIR (mkdir -p) if it can
        parent = os.path.dirname(os.path.abspath(probe))
        if parent == probe:
            break
        probe = parent
    if not os.path.isdir(probe):
        why = f"is not a directory ({probe} is a file)" if probe != tmpdir else "is not a directory"
        raise SolverRunError(
            f"TMPDIR={tmpdir} {why}: Open MPI creates its session directory there and LIGGGHTS "
            "cannot start; set TMPDIR to a writable directory (or unset it for /tmp)"
        )
    if not os.access(probe, os.W_OK | os.X_OK):
        raise SolverRunError(
            f"TMPDIR={tmpdir} is not writable: Open MPI creates its session directory there and "
            "LIGGGHTS cannot start; set TMPDIR to a writable directory (or unset it for /tmp)"
        )


def _mpi_session_failure(output: str) -> str | None:
    """The directory named by Open MPI's "unable to create the desired directory" message,
    or None when the output is not that failure."""
    if "session_dir" not in output and "unable to create the desired directory" not in output:
        return None
    match = re.search(r"Directory:\s*(\S+)", output)
    error = re.search(r"Error:\s*(.+)", output)
    where = match.group(1) if match else "its session directory"
    return f"{where}" + (f" ({error.group(1).strip()})" if error else "")


# ----------------------------------------------------------------------------- the command
def liggghts_version(liggghts: str = "liggghts") -> str:
    """The banner of ``liggghts -h`` (e.g. 'LIGGGHTS-PUBLIC 3.8.0, compiled ...').

    Raises SolverNotFoundError when the executable is missing. The banner is asked once
    per executable file (its path and modification time) in a process: a run's key needs
    it, and starting LIGGGHTS takes seconds on a busy machine."""
    exe = shlex.split(liggghts)
    found = shutil.which(exe[0]) if exe else None
    if found is None:
        raise SolverNotFoundError(f"LIGGGHTS executable {liggghts!r} not found on PATH; {INSTALL_HINT}")
    check_tmpdir()
    return _version((found, *exe[1:]), os.stat(found).st_mtime_ns, liggghts)


@lru_cache(maxsize=16)
def _version(exe: tuple[str, ...], _mtime_ns: int, liggghts: str) -> str:
    try:
        # -log none: otherwise `liggghts -h` leaves a log.liggghts in the caller's directory
        out = subprocess.run(
            [*exe, "-log", "none", "-h"],
            capture_output=True,
            text=True,
            errors="replace",
            timeout=60,
            stdin=subprocess.DEVNULL,
        )
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise SolverNotFoundError(f"cannot run {liggghts!r} -h: {exc}; {INSTALL_HINT}") from exc
    match = re.search(r"LIGGGHTS \(Version ([^)]*)\)", out.stdout + out.stderr)
    session = None if match else _mpi_session_failure(out.stdout + out.stderr)
    if session is not None:
        raise SolverRunError(
            f"LIGGGHTS is installed but could not start: Open MPI could not create {session}; "
            "set TMPDIR to a writable directory"
        )
    if not match:
        raise SolverNotFoundError(f"{liggghts!r} -h did not print a LIGGGHTS version banner; {INSTALL_HINT}")
    return match.group(1).strip()


def _launcher(run_config, np: int | None) -> list[str]:
    nprocs = int(np if np is not None else run_config.np)
    if nprocs < 1:
        raise SolverRunError(f"number of MPI ranks must be >= 1, got {nprocs}")
    launcher = run_config.launcher.strip()
    if not launcher or (nprocs == 1 and "{np}" in launcher):
        return []
    return shlex.split(launcher.format(np=nprocs))


def launch_command(run_config, np: int | None = None, main_input: str = MAIN_DECK) -> list[str]:
    """argv ``[<launcher formatted with np>] <liggghts> -in <main_input>`` (``run_config``:
    a :class:`~dem.config.RunConfig`; ``np`` defaults to its ``np``). Pure.

    The launcher is skipped for np == 1 when it is an ``{np}`` template (plain mpirun);
    a launcher without ``{np}`` (``srun``) is always used."""
    return [*_launcher(run_config, np), *shlex.split(run_config.liggghts), "-in", main_input]


def solver_command(run_config, np: int | None = None, main_input: str = MAIN_DECK) -> list[str]:
    """:func:`launch_command` for this machine, with ``stdbuf -oL`` before the solver.

    Raises SolverNotFoundError naming the missing executable."""
    prefix = _launcher(run_config, np)
    check_tmpdir()
    if prefix and shutil.which(prefix[0]) is None:
        raise SolverNotFoundError(f"MPI launcher {prefix[0]!r} not found on PATH; {INSTALL_HINT}")
    exe = shlex.split(run_config.liggghts)
    if not exe or shutil.which(exe[0]) is None:
        raise SolverNotFoundError(f"LIGGGHTS executable {run_config.liggghts!r} not found on PATH; {INSTALL_HINT}")
    # Line-buffer the solver's stdout so an ERROR line is not lost in a pipe buffer when it
    # aborts (measured on LIGGGHTS 3.8.0). stdbuf goes after the launcher so it applies to
    # the solver itself, on every rank.
    stdbuf = ["stdbuf", "-oL"] if shutil.which("stdbuf") else []
    return [*prefix, *stdbuf, *exe, "-in", main_input]


# ----------------------------------------------------------------------------- running it
@dataclass(frozen=True)
class SolverResult:
    """A finished solver process. ``cpu_s``: user + system time of every process it started
    (all ranks); on a shared machine the wall time also measures the other jobs."""

    command: list[str]
    returncode: int
    error_lines: list[str]
    wall_s: float
    cpu_s: float
    output_file: Path

    @property
    def output(self) -> str:
        return self.output_file.read_text(errors="replace")

    @property
    def failure(self) -> str | None:
        """What went wrong (the first ERROR line or the exit status), None for a clean exit."""
        if self.error_lines:
            return f"LIGGGHTS reported an error: {self.error_lines[0]}"
        if self.returncode != 0:
            return f"LIGGGHTS exited with status {self.returncode}"
        return None


def run_solver(
    command: Sequence[str],
    cwd: str | os.PathLike,
    output_file: str | os.PathLike,
    *,
    append: bool = False,
    on_start: Callable[[int], None] | None = None,
    on_line: Callable[[str], None] | None = None,
    timeout_s: float | None = None,
    error_grace_s: float = 30.0,
) -> SolverResult:
    """Run ``command`` in ``cwd`` in a session of its own, copying its stdout + stderr line
    by line to ``output_file`` (``cwd``-relative unless absolute; ``append`` keeps what is
    there). ``on_start(pid)`` is called once the process exists, ``on_line(line)`` with
    every output line.

    The process group and every process of the session (each MPI rank) are terminated when
    anything interrupts the run (Ctrl-C, an exception from ``on_line``: re-raised), after
    ``timeout_s`` (SolverRunError), and ``error_grace_s`` after an ERROR line if the solver
    is still running then (an MPI rank waiting for the others would hang forever)."""
    cwd = Path(cwd)
    output_file = cwd / output_file
    errors: list[str] = []
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.monotonic()
    proc = None
    try:
        with open(output_file, "a" if append else "w", buffering=1) as out:
            proc = subprocess.Popen(
                list(command),
                cwd=cwd,
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
                text=True,
                errors="replace",
                bufsize=1,
                start_new_session=True,
            )
            if on_start is not None:
                on_start(proc.pid)
            returncode = _stream(proc, out, on_line, errors, t0, timeout_s, error_grace_s)
    except BaseException:
        if proc is not None:
            _terminate_session(proc)
        raise
    finally:
        if proc is not None and proc.stdout is not None:
            proc.stdout.close()
    if returncode is None:
        raise SolverRunError(
            f"LIGGGHTS ran longer than the {timeout_s:.0f} s allowed: stopped",
            run_dir=cwd,
            log_tail=text_tail(output_file),
        )
    wall = time.monotonic() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return SolverResult(list(command), returncode, errors, wall, cpu, output_file)


def _stream(proc, out, on_line, errors, t0, timeout_s, error_grace_s) -> int | None:
    """Copy the output until the process ends; its exit status, None after a timeout.

    A reader thread feeds a queue so that this thread stays responsive to Ctrl-C and can
    stop a solver that hangs."""
    lines: queue.Queue = queue.Queue()

    def reader() -> None:
        for line in proc.stdout:
            lines.put(line)
        lines.put(None)

    thread = threading.Thread(target=reader, name="liggghts-output", daemon=True)
    thread.start()
    error_since = None
    try:
        while True:
            try:
                line = lines.get(timeout=1.0)
            except queue.Empty:
                line = ""
            if line is None:
                return proc.wait()
            if line:
                out.write(line)
                if on_line is not None:
                    on_line(line)
                if line.lstrip().startswith("ERROR"):
                    errors.append(line.strip())
                    error_since = error_since or time.monotonic()
            now = time.monotonic()
            if timeout_s is not None and now - t0 > timeout_s:
                _terminate_session(proc)
                return None
            if error_since is not None and now - error_since > error_grace_s and proc.poll() is None:
                _terminate_session(proc)
    except BaseException:
        _terminate_session(proc)
        raise
    finally:
        # the pipe ends once no process of the session is left: let the reader see its end
        # before the caller closes it
        thread.join(timeout=10.0)


def _session_members(sid: int) -> list[int]:
    """PIDs of the processes in session ``sid`` (Linux /proc; empty elsewhere). mpirun puts
    each rank in a process group of its own, but they stay in the session we created."""
    members = []
    try:
        entries = os.listdir("/proc")
    except OSError:
        return members
    for entry in entries:
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as handle:
                fields = handle.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[3]) == sid and fields[0] != "Z":  # after the command: state ppid pgrp session
            members.append(int(entry))
    return members


def _terminate_session(proc: subprocess.Popen, grace_s: float = 10.0) -> None:
    """SIGTERM the solver's process group and every process of its session (every MPI
    rank), SIGKILL whatever is left after ``grace_s``."""
    sid = proc.pid  # start_new_session: the launcher leads its own session and group
    for sig, wait in ((signal.SIGTERM, grace_s), (signal.SIGKILL, 5.0)):
        try:
            os.killpg(sid, sig)
        except (ProcessLookupError, PermissionError):
            pass
        for pid in _session_members(sid):
            try:
                os.kill(pid, sig)
            except (ProcessLookupError, PermissionError):
                pass
        try:
            proc.wait(timeout=wait)
        except subprocess.TimeoutExpired:
            continue
        deadline = time.monotonic() + wait
        while _session_members(sid) and time.monotonic() < deadline:
            time.sleep(0.1)
        if not _session_members(sid):
            return


def text_tail(path: str | os.PathLike, lines: int = 25) -> str:
    """The last ``lines`` lines of a text file ('' if it cannot be read)."""
    try:
        text = Path(path).read_text(errors="replace")
    except OSError:
        return ""
    return "\n".join(text.rstrip().splitlines()[-lines:])
