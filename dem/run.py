"""Run LIGGGHTS on a deck, in a directory keyed by the hash of the run's inputs.

Entry points::

    inputs = prepare_run(dem_config)   # the deck and its key, built once -> RunInputs
    record = run_dem(inputs, runs_root="runs", np=None, resume=False, fresh=False,
                     progress=True)    # -> RunRecord

Layout of a run directory ``<runs_root>/<key>/`` (key = hash of the deck texts, the meshes
and the LIGGGHTS version; the MPI rank count is *not* part of it -- it changes the
trajectory only within the DEM's own scatter):

    in.blender, meshes...   the deck (dem.deck.write_deck)
    log.liggghts            LIGGGHTS' own log (log.liggghts.attemptN: earlier attempts of
                            a resumed run, which LIGGGHTS would overwrite)
    solver.out              the solver's stdout+stderr as streamed (line-buffered; a resumed
                            attempt is appended after a marker line)
    status.json             state: running | completed | crashed | interrupted, with dates,
                            wall time (summed over attempts), LIGGGHTS version, command, key,
                            deck hash, the solver's final thermo counters and their step
    dumps/, discharge_*.txt[.rank], restart/  (names from dem.deck); before a resume the
                            discharge files are moved to ``<name>.upto<restart step>``,
                            keeping the records up to the restart (LIGGGHTS truncates them)

A ``completed`` run is reused by a second request with the same inputs without starting
LIGGGHTS; anything else is never mistaken for a result. ``fresh=True`` deletes the
directory first; ``resume=True`` continues a crashed or interrupted run from its newest
restart file with the deck's resume variant.

Errors: SolverNotFoundError (liggghts or the launcher missing, with the install command),
SolverRunError (an ERROR line, a non-zero exit or missing output; carries the run
directory and the log's tail). Ctrl-C terminates the solver's process group, marks the run
interrupted and re-raises KeyboardInterrupt. Starting and supervising the solver process
is :mod:`dem.liggghts`.

This module is a little longer than the others: the run directory's states, the status
file, reuse and resume (which rewrites the discharge files) share one layout and are read
together.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import re
import shutil
import signal
import socket
import threading
import time
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

from coupling.errors import Interrupted, OutputError, SolverNotFoundError, SolverRunError
from coupling.files import output_directory_path, replace_file
from dem import deck
from dem.config import DemConfig
from dem.liggghts import SolverResult, liggghts_version, run_solver, solver_command, text_tail
from dem.liggghts_log import ThermoParser

__all__ = [
    "RunInputs",
    "RunRecord",
    "diagnose_stale_status",
    "last_thermo_step",
    "prepare_run",
    "read_status",
    "run_dem",
    "run_key",
    "liggghts_version",
    "solver_command",
    "solver_counters",
]

STATUS_FILE = "status.json"
SOLVER_OUT = "solver.out"
#: The line solver.out gets before a resumed attempt's output.
RESUME_MARKER = "# --- resumed from"


@dataclass(frozen=True)
class RunInputs:
    """What a run is keyed by, computed once (:func:`prepare_run`).

    ``deck_hash``: the deck alone (finds a completed run of the same deck when no solver is
    installed); ``key``: the deck and the LIGGGHTS version, the run directory's name, None
    when LIGGGHTS is not installed (``liggghts_version`` is None then)."""

    config: DemConfig
    files: dict[str, str]
    liggghts_version: str | None
    deck_hash: str
    key: str | None


#: The state of a run its caller stopped before the end (:class:`StopRun`).
STOPPED = "stopped"


class StopRun(Exception):
    """Raised by a run's ``on_line`` callback to stop the solver before the end on purpose
    (e.g. the DEM has converged): :func:`run_dem` stops every rank and returns the run
    marked :data:`STOPPED`, with ``reason`` recorded."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


@dataclass
class RunRecord:
    """What a run produced and where. ``reused`` is True when nothing was started."""

    key: str
    run_dir: Path
    state: str
    reused: bool
    wall_time_s: float | None
    liggghts_version: str
    started: str | None
    finished: str | None
    command: list[str] = field(default_factory=list)
    np: int = 1
    resumed_from: str | None = None
    solver_counters: dict[str, float] = field(default_factory=dict)

    @property
    def dump_glob(self) -> str:
        return str(self.run_dir / deck.DUMP_GLOB)

    @property
    def massflow_dir(self) -> Path:
        return self.run_dir

    def provenance(self) -> dict[str, Any]:
        data = asdict(self)
        data["run_dir"] = str(self.run_dir)
        return data


def run_key(files: dict[str, str | bytes], version: str) -> str:
    """Hash of the run's inputs: every deck file's content (texts and meshes) + the
    LIGGGHTS version; with ``version=""`` the deck alone (:func:`dem.deck.deck_hash`)."""
    return deck.deck_hash(files, version)


def prepare_run(config: DemConfig) -> RunInputs:
    """Build the deck of ``config`` and ask ``liggghts -h`` for the version, once.

    A missing solver is not an error here (``liggghts_version`` and ``key`` are None): a
    completed run of the same deck can still be reused. Raises GeometryError / DeckError
    for a configuration that makes no valid deck."""
    files = deck.build_deck(config)
    try:
        version = liggghts_version(config.run.liggghts)
    except SolverNotFoundError:
        version = None
    key = None if version is None else run_key(files, version)
    return RunInputs(config, files, version, deck.deck_hash(files), key)


def read_status(run_dir: str | os.PathLike) -> dict[str, Any] | None:
    """The run's status.json, or None if absent or unreadable (treated as not completed)."""
    path = Path(run_dir) / STATUS_FILE
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None


def run_dem(
    inputs: RunInputs,
    runs_root: str | os.PathLike = "runs",
    np: int | None = None,
    resume: bool = False,
    fresh: bool = False,
    progress: bool = True,
    on_line: Callable[[str], None] | None = None,
) -> RunRecord:
    """Write the deck, run LIGGGHTS in ``<runs_root>/<key>/`` and return its RunRecord.

    ``inputs``: from :func:`prepare_run`. ``np``: MPI ranks (default
    ``inputs.config.run.np``). ``resume``: continue a crashed or interrupted run from its
    newest restart file. ``fresh``: delete the run directory and start again.
    ``progress``: tqdm bar on stderr. ``on_line``: called with every solver output line;
    raising :class:`StopRun` there stops the run early on purpose (returned as :data:`STOPPED`).

    A completed run with the same inputs is returned as is (``reused=True``) without starting
    a simulation. Without a solver (``inputs.key`` None), a completed run of the same deck
    (same deck hash) under ``runs_root`` is still reused; only a run that must actually
    start raises SolverNotFoundError.

    The steps: reuse (:func:`completed_run`), the run's key, the directory claimed
    (:func:`_claim_run_dir`), its files written (:func:`_write_run_files`), the solver run
    and followed (:func:`_solve`), its outcome judged (:func:`_judge_run`).
    """
    # a symlink loop or a file in the way of the runs directory: one line, before anything
    output_directory_path(runs_root, "runs directory (--runs-dir)", OutputError)
    if not fresh:
        done = completed_run(inputs, runs_root)
        if done is not None:
            return done
    if inputs.key is None:
        # asked again for the message naming what is missing (or the solver appeared since)
        version = liggghts_version(inputs.config.run.liggghts)
        inputs = replace(inputs, liggghts_version=version, key=run_key(inputs.files, version))
    nprocs = int(np if np is not None else inputs.config.run.np)
    run_dir = Path(runs_root) / inputs.key
    status, command = _claim_run_dir(inputs, run_dir, nprocs, resume, fresh)
    resumed_from = _write_run_files(inputs, run_dir, resume)
    base = {
        "key": inputs.key,
        "deck_hash": inputs.deck_hash,
        "liggghts_version": inputs.liggghts_version,
        "command": command,
        "np": nprocs,
        "started": _now(),
        "resumed_from": resumed_from,
        "previous": status if resume else None,
    }
    _write_status(run_dir, {**base, "state": "running", **_process_identity(os.getpid())})
    if resume:
        with open(run_dir / SOLVER_OUT, "a") as out:
            out.write(f"\n{RESUME_MARKER} {resumed_from} at {base['started']} ---\n")
    # wall time accumulates over the attempts of a resumed run
    prior_wall = float(status.get("wall_time_s") or 0.0) if (resume and status) else 0.0
    return _solve(inputs.config, run_dir, base, prior_wall, resume, progress, on_line)


def _claim_run_dir(
    inputs: RunInputs, run_dir: Path, nprocs: int, resume: bool, fresh: bool
) -> tuple[dict[str, Any] | None, list[str]]:
    """``run_dir`` made ready to be written: its earlier status (None after ``fresh``) and
    the solver command. Every argument and program is checked before
    anything in the directory changes: a typo must never cost the outputs of an
    interrupted run. Raises SolverRunError for a run still going, or for outputs that
    neither ``resume`` nor ``fresh`` allows to touch."""
    key = inputs.key
    status = diagnose_stale_status(run_dir, read_status(run_dir), resume=resume)
    command = solver_command(inputs.config.run, nprocs, deck.RESUME_DECK if resume else deck.MAIN_DECK)
    if status and status.get("state") == "running":
        state, why = _liveness(status)
        hint = (
            "; if it is no longer running there, continue it with --resume"
            if state == "unknown"
            else "; wait for it, or stop it first"
        )
        raise SolverRunError(f"run {key} is already running ({why}){hint}", run_dir=run_dir)
    if fresh and run_dir.exists():
        shutil.rmtree(run_dir)
        status = None
    if not resume and run_dir.exists():
        _refuse_to_discard(run_dir, key, status)
    return status, command


def _write_run_files(inputs: RunInputs, run_dir: Path, resume: bool) -> str | None:
    """The deck written into ``run_dir`` (the resume deck from the newest restart file when
    ``resume``; returns that file's name, else None)."""
    if resume:
        resumed_from = _prepare_resume(run_dir, inputs.key, float(inputs.config.timestep_s))
        run_files = deck.build_deck(inputs.config, resume_from=resumed_from)
    else:
        run_dir.mkdir(parents=True, exist_ok=True)
        _clear_outputs(run_dir)
        resumed_from, run_files = None, inputs.files
    # LIGGGHTS reads its input while it runs, so a deck is never edited in place: the run
    # directory is this run's alone and every file is written before the solver starts.
    deck.write_deck(run_files, run_dir)
    return resumed_from


def _solve(
    config: DemConfig,
    run_dir: Path,
    base: dict[str, Any],
    prior_wall: float,
    resume: bool,
    progress: bool,
    on_line: Callable[[str], None] | None,
) -> RunRecord:
    """Run the solver of ``base["command"]`` in ``run_dir``, following its thermo output
    (progress bar, ``on_line``) and keeping ``status.json`` true at every exit: stopped
    early on purpose (:class:`StopRun`), interrupted, crashed, or judged by
    :func:`_judge_run`."""
    dt, duration = float(config.timestep_s), float(config.operation.duration_s)
    parser = ThermoParser(deck.THERMO_DISCHARGED, deck.THERMO_INSERTED, deck.THERMO_COLUMNS)
    resumed_from = base["resumed_from"]
    bar = _Progress(duration, _step_of(Path(resumed_from)) * dt if resumed_from else 0.0, progress)

    def follow(line: str) -> None:
        if on_line is not None:
            on_line(line)
        if parser.feed(line) and parser.step is not None:
            bar.update(parser.step * dt, parser.atoms, parser.discharged)

    def solver_started(pid: int) -> None:
        _write_status(
            run_dir,
            {
                **base,
                "state": "running",
                **_process_identity(os.getpid()),
                "solver_pid": pid,
                "solver_start_ticks": _start_ticks(pid),
            },
        )

    t0 = time.monotonic()
    try:
        with _terminate_as_interrupt():
            result = run_solver(
                base["command"], run_dir, SOLVER_OUT, append=resume, on_start=solver_started, on_line=follow
            )
    except StopRun as stop:
        # asked for by the caller (it has what it needs): the run is kept, marked as stopped
        # early so that it is never taken for a complete one; --resume continues it
        bar.close()
        _write_status(
            run_dir,
            {
                **base,
                "finished": _now(),
                "wall_time_s": prior_wall + time.monotonic() - t0,
                "state": STOPPED,
                "stop_reason": stop.reason,
                "stopped_at_s": None if parser.step is None else parser.step * dt,
                "solver_counters": parser.counters(),
            },
        )
        return _record_from_status(run_dir, read_status(run_dir) or {}, reused=False)
    except BaseException as exc:
        bar.close()
        stopped = {"finished": _now(), "wall_time_s": prior_wall + time.monotonic() - t0}
        if isinstance(exc, KeyboardInterrupt):
            _write_status(run_dir, {**base, **stopped, "state": "interrupted", "solver_counters": parser.counters()})
        else:
            _write_status(run_dir, {**base, **stopped, "state": "crashed"})
        raise
    bar.close()
    final = {
        **base,
        "finished": _now(),
        "wall_time_s": prior_wall + result.wall_s,
        "solver_counters": parser.counters(),
    }
    reached_s = None if parser.step is None else parser.step * dt
    return _judge_run(run_dir, final, result, reached_s, duration, dt)


def _judge_run(
    run_dir: Path, final: dict[str, Any], result: SolverResult, reached_s: float | None, duration: float, dt: float
) -> RunRecord:
    """The finished solver's run marked completed, or crashed (SolverRunError with the
    log's tail) when it failed, wrote no dump or stopped before ``duration`` [s]."""
    problem = result.failure
    if problem is None and not list(run_dir.glob(deck.DUMP_GLOB)):
        problem = "LIGGGHTS finished but wrote no particle dump"
    elif problem is None and (reached_s is None or reached_s < duration - 2 * dt - 1e-9):
        reached = "no thermo output" if reached_s is None else f"t = {reached_s:.3f} s"
        problem = f"LIGGGHTS stopped before the end time {duration} s ({reached})"
    if problem:
        _write_status(run_dir, {**final, "state": "crashed", "error": problem})
        log_path = run_dir / deck.LOG_FILE if (run_dir / deck.LOG_FILE).exists() else run_dir / SOLVER_OUT
        raise SolverRunError(problem, run_dir=run_dir, log_tail=text_tail(log_path))
    _write_status(run_dir, {**final, "state": "completed", "wall_time_this_attempt_s": result.wall_s})
    return _record_from_status(run_dir, read_status(run_dir) or {}, reused=False)


# ----------------------------------------------------------------------------- run directory
@contextmanager
def _terminate_as_interrupt():
    """SIGTERM (a scheduler's or ``timeout``'s stop) and SIGHUP (the terminal or ssh session
    closed) are handled like Ctrl-C while the solver runs: every rank is stopped, the run is
    marked interrupted and can be resumed. Only the main thread can own a signal handler;
    elsewhere the default stays. SIGKILL cannot be caught: :func:`diagnose_stale_status`
    recognises the "running" status it leaves."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum, frame):
        raise Interrupted(signum)

    previous = {sig: signal.signal(sig, interrupt) for sig in (signal.SIGTERM, signal.SIGHUP)}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _refuse_to_discard(run_dir: Path, key: str, status: dict[str, Any] | None) -> None:
    """A run directory holding a stopped run's dumps or restart files is never cleared
    implicitly: the caller says resume or start again. The message counts the restart files
    ``--resume`` can continue from (complete ones, :func:`_restart_files`) and offers
    ``--resume`` only when there is one; it speaks the command line's flags (``run_dem``'s
    ``resume`` and ``fresh`` are the same choices)."""
    dumps = list(run_dir.glob(deck.DUMP_GLOB))
    written = [p for p in run_dir.glob(deck.RESTART_GLOB) if p.is_file()]
    if not (dumps or written):
        return
    complete = _restart_files(run_dir)
    state = (status or {}).get("state", "unknown")
    if (status or {}).get("error"):
        state += f": {status['error']}"
    kept = _count(len(dumps), "dump") + " and " + _count(len(complete), "complete restart file")
    if len(written) > len(complete):
        kept += f" (and {len(written) - len(complete)} cut short)"
    choice = (
        f"continue it with --resume (from {complete[-1].relative_to(run_dir)}), or discard it and start again with --fresh"
        if complete
        else "nothing to resume from: discard it and start again with --fresh"
    )
    # the error's second line names the run directory
    raise SolverRunError(f"run {key} stopped ({state}) with {kept}; {choice}", run_dir=run_dir)


def _count(n: int, noun: str) -> str:
    """``"1 dump"``, ``"3 dumps"``, ``"0 dumps"``."""
    return f"{n} {noun}" if n == 1 else f"{n} {noun}s"


def _now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")


def _write_status(run_dir: Path, data: dict[str, Any]) -> None:
    replace_file(run_dir / STATUS_FILE, json.dumps(data, indent=2, sort_keys=True, default=str) + "\n", "run status")


def _step_of(path: Path) -> int:
    numbers = re.findall(r"\d+", path.name)
    return int(numbers[-1]) if numbers else -1


def _restart_files(run_dir: Path) -> list[Path]:
    """Restart files known to be complete, oldest first.

    A restart file carries no end marker, and a run killed while writing one leaves it
    truncated. LIGGGHTS writes a step's restart before that step's thermo line, so a restart
    at step S is complete once a log written after it shows a thermo row at a step >= S;
    newer ones are ignored (the resume then starts from an older restart: safe, a little
    slower). The logs judged are LIGGGHTS' own (``log.liggghts``, a resume's log and the
    earlier attempts' logs), written by the solver itself, so they survive the death of the
    Python process that copied its output (after SIGHUP or SIGKILL solver.out lacks the rows
    the solver printed after its reader died), and solver.out's current attempt. "Written
    after": a log last modified before the restart file (an earlier attempt's, when a
    resumed attempt rewrote that restart and was killed while doing so) does not vouch for it."""
    files = [p for p in run_dir.glob(deck.RESTART_GLOB) if p.is_file() and p.stat().st_size > 0]
    logs = _thermo_logs(run_dir)

    def complete(path: Path) -> bool:
        written = path.stat().st_mtime_ns
        return any(mtime >= written and step >= _step_of(path) for mtime, step in logs)

    return sorted((p for p in files if complete(p)), key=_step_of)


def _last_step_of_lines(lines) -> int:
    parser, last = ThermoParser(), -1
    for line in lines:
        if parser.feed(line) and parser.step is not None:
            last = max(last, parser.step)
    return last


def _thermo_logs(run_dir: Path) -> list[tuple[int, int]]:
    """(modification time [ns], newest thermo step) of each log of the run that shows one:
    LIGGGHTS' logs, and solver.out from its last resume marker on (it is appended across
    attempts, so its earlier rows are an earlier attempt's)."""
    out = []
    for path in (run_dir / deck.LOG_FILE, run_dir / deck.RESUME_LOG_FILE, *run_dir.glob(deck.LOG_FILE + ".attempt*")):
        try:
            with open(path, errors="replace") as handle:
                step = _last_step_of_lines(handle)
            mtime = path.stat().st_mtime_ns
        except OSError:
            continue
        if step >= 0:
            out.append((mtime, step))
    try:
        text = (run_dir / SOLVER_OUT).read_text(errors="replace")
        mtime = (run_dir / SOLVER_OUT).stat().st_mtime_ns
    except OSError:
        return out
    step = _last_step_of_lines(text[text.rfind(RESUME_MARKER) + 1 if RESUME_MARKER in text else 0 :].splitlines())
    if step >= 0:
        out.append((mtime, step))
    return out


def last_thermo_step(run_dir: str | os.PathLike) -> int:
    """The newest step of a thermo row in the run's logs (``log.liggghts``, a resume's log,
    the earlier attempts' logs and solver.out's current attempt); -1 when none shows one."""
    return max((step for _, step in _thermo_logs(Path(run_dir))), default=-1)


def solver_counters(run_dir: str | os.PathLike) -> dict[str, float]:
    """The solver's own final counters of a run directory (discharged, inserted, atoms, step):
    from status.json when the run recorded them, else from the last thermo row of
    ``log.liggghts``. Empty when neither is there (dumps from elsewhere). For the
    post-processing's accounting (:func:`dem.post.postprocess` ``solver_counters``)."""
    run_dir = Path(run_dir)
    status = read_status(run_dir) or {}
    counters = status.get("solver_counters")
    if isinstance(counters, dict) and counters:
        return {name: float(value) for name, value in counters.items() if isinstance(value, (int, float))}
    parser = ThermoParser(deck.THERMO_DISCHARGED, deck.THERMO_INSERTED, deck.THERMO_COLUMNS)
    try:
        with open(run_dir / deck.LOG_FILE, errors="replace") as handle:
            for line in handle:
                parser.feed(line)
    except OSError:
        return {}
    return {name: float(value) for name, value in parser.counters().items()}


def _prepare_resume(run_dir: Path, key: str, dt: float) -> str:
    """Set the run directory up for a resume from its newest complete restart file; that
    file's path relative to the run directory."""
    restarts = _restart_files(run_dir) if run_dir.exists() else []
    if not restarts:
        raise SolverRunError(
            f"cannot resume run {key}: no complete restart file in {run_dir} (start it without --resume)",
            run_dir=run_dir,
        )
    restart = restarts[-1]
    _set_aside_massflow(run_dir, _step_of(restart), dt)
    # LIGGGHTS overwrites its log: keep the interrupted attempt's log beside it
    if (run_dir / deck.LOG_FILE).exists():
        attempt = 1 + len(list(run_dir.glob(deck.LOG_FILE + ".attempt*")))
        os.replace(run_dir / deck.LOG_FILE, run_dir / f"{deck.LOG_FILE}.attempt{attempt}")
    return str(restart.relative_to(run_dir))


def _clear_outputs(run_dir: Path) -> None:
    """Remove a previous attempt's outputs so they can never mix with a new run's."""
    for name in (deck.LOG_FILE, SOLVER_OUT, STATUS_FILE):
        (run_dir / name).unlink(missing_ok=True)
    for pattern in (deck.DUMP_GLOB, deck.RESTART_GLOB, *deck.MASSFLOW_GLOBS.values()):
        for path in run_dir.glob(pattern):
            if path.is_file():
                path.unlink()


def _set_aside_massflow(run_dir: Path, restart_step: int, dt: float) -> None:
    """Before a resume: LIGGGHTS reopens the discharge files for writing (``file``
    truncates them), so the records written before the crash are moved to
    ``<name>.upto<step>``, keeping only the particles discharged up to the restart step
    (the resumed run discharges the later ones again)."""
    limit = restart_step * dt + 0.5 * dt
    for comp, name in deck.MASSFLOW_FILES.items():
        for path in sorted(run_dir.glob(deck.MASSFLOW_GLOBS[comp])):
            suffix = path.name[len(name) :]
            if suffix and not (suffix[:1] == "." and suffix[1:].isdigit()):
                continue  # not the solver's own file nor a rank's: set aside by an earlier resume
            kept = []
            for line in path.read_text(errors="replace").splitlines():
                fields = line.split()
                if line.startswith("#") or len(fields) < 2:
                    kept.append(line)
                    continue
                try:
                    if float(fields[1]) <= limit:
                        kept.append(line)
                except ValueError:
                    continue  # a line cut by the crash
            path.with_name(f"{path.name}.upto{restart_step}").write_text("\n".join(kept) + "\n")
            path.unlink()


def _record_from_status(run_dir: Path, status: dict[str, Any], reused: bool) -> RunRecord:
    return RunRecord(
        key=status.get("key", run_dir.name),
        run_dir=run_dir,
        state=status.get("state", "unknown"),
        reused=reused,
        wall_time_s=status.get("wall_time_s"),
        liggghts_version=status.get("liggghts_version", ""),
        started=status.get("started"),
        finished=status.get("finished"),
        command=list(status.get("command", [])),
        np=int(status.get("np", 1)),
        resumed_from=status.get("resumed_from"),
        solver_counters=dict(status.get("solver_counters") or {}),
    )


def can_resume(inputs: RunInputs, runs_root: str | os.PathLike = "runs") -> bool:
    """An interrupted run of these inputs under ``runs_root`` has a complete restart file
    to continue from (what ``run_dem(resume=True)`` needs)."""
    if inputs.key is None:
        return False
    run_dir = Path(runs_root) / inputs.key
    status = read_status(run_dir)
    if status and status.get("state") == "completed":
        return False
    if status and status.get("state") == "running" and _alive(status):
        return False
    return run_dir.is_dir() and bool(_restart_files(run_dir))


def completed_run(inputs: RunInputs, runs_root: str | os.PathLike = "runs") -> RunRecord | None:
    """The completed run of these inputs under ``runs_root`` (``reused=True``), or None.
    Without a solver (``inputs.key`` None) the newest completed run of the same deck."""
    if inputs.key is None:
        done = _completed_for_deck(Path(runs_root), inputs.deck_hash)
        return _record_from_status(done, read_status(done) or {}, reused=True) if done is not None else None
    run_dir = Path(runs_root) / inputs.key
    status = read_status(run_dir)
    if status and status.get("state") == "completed":
        return _record_from_status(run_dir, status, reused=True)
    return None


def _completed_for_deck(runs_root: Path, deck_digest: str) -> Path | None:
    """Newest completed run directory under ``runs_root`` made from the same deck."""
    best = None
    for status_path in runs_root.glob(f"*/{STATUS_FILE}"):
        status = read_status(status_path.parent)
        if status and status.get("state") == "completed" and status.get("deck_hash") == deck_digest:
            if best is None or str(status.get("finished")) > str(best[0]):
                best = (status.get("finished"), status_path.parent)
    return best[1] if best else None


def _start_ticks(pid: int) -> int | None:
    """The start time of process ``pid`` in clock ticks since boot (/proc/<pid>/stat field
    22): with the pid it identifies a process, so a pid reused after a reboot or by another
    program is not taken for the run's."""
    try:
        with open(f"/proc/{int(pid)}/stat") as handle:
            fields = handle.read().rsplit(")", 1)[1].split()
    except (OSError, ValueError):
        return None
    if fields[0] == "Z":  # a zombie has ended
        return None
    return int(fields[19])


def _process_identity(pid: int) -> dict[str, Any]:
    return {"pid": pid, "pid_start_ticks": _start_ticks(pid), "host": socket.gethostname()}


def _liveness(status: dict[str, Any]) -> tuple[str, str]:
    """("alive" | "dead" | "unknown", why) of the processes a "running" status names: its
    solver (an orphaned mpirun outlives a killed Python) and the Python process that
    started it. "unknown" when the run was started on another host (a shared file system)."""
    host = status.get("host")
    if host and host != socket.gethostname():
        return "unknown", f"started on host {host}, pid {status.get('pid')}; this is {socket.gethostname()}"
    for pid_key, ticks_key in (("solver_pid", "solver_start_ticks"), ("pid", "pid_start_ticks")):
        pid = status.get(pid_key)
        if not pid or int(pid) == os.getpid():
            continue
        ticks = _start_ticks(int(pid))
        if ticks is None:
            continue
        recorded = status.get(ticks_key)
        if recorded is not None and int(recorded) != ticks:
            continue  # the pid now belongs to another process
        return "alive", f"{pid_key.replace('_', ' ')} {pid} is running"
    names = ", ".join(f"{key.replace('_', ' ')} {status[key]}" for key in ("pid", "solver_pid") if status.get(key))
    return "dead", f"its processes ({names or 'none recorded'}) no longer exist"


def _alive(status: dict[str, Any]) -> bool:
    """Whether the run in ``status`` may still run (alive, or on another host)."""
    return _liveness(status)[0] != "dead"


def diagnose_stale_status(
    run_dir: str | os.PathLike, status: dict[str, Any] | None, resume: bool = False
) -> dict[str, Any] | None:
    """A "running" status whose processes are gone (SIGKILL, a node failure, a closed
    terminal before SIGHUP was handled) is rewritten as ``crashed`` with the reason, so that
    a plain rerun names it and ``--resume`` continues it; any other status is returned as
    is. A run started on another host cannot be checked from here: with ``resume`` the
    caller says it is over (it is then marked crashed like a dead one), without it the
    status stays "running"."""
    if not status or status.get("state") != "running":
        return status
    state, why = _liveness(status)
    if state == "alive" or (state == "unknown" and not resume):
        return status
    has_restarts = Path(run_dir).is_dir() and bool(_restart_files(Path(run_dir)))
    reason = f"killed without a trace ({why}: SIGKILL, a node failure or a lost terminal); " + (
        "its restart files can be continued with --resume"
        if has_restarts
        else "it wrote no restart file: only --fresh starts it again"
    )
    stale = {**status, "state": "crashed", "error": reason, "diagnosed": _now()}
    _write_status(Path(run_dir), stale)
    return stale


class _Progress:
    """tqdm bar of simulated time; postfix: particles held, discharged."""

    def __init__(self, total_s: float, start_s: float, enabled: bool) -> None:
        self.bar = None
        if enabled:
            from tqdm import tqdm

            self.bar = tqdm(
                total=round(total_s, 3),
                initial=round(start_s, 3),
                unit="s sim",
                dynamic_ncols=True,
                bar_format="{l_bar}{bar}| {n:.1f}/{total:.1f} s [{elapsed}<{remaining}{postfix}]",
            )

    def update(self, t_s: float, held, discharged) -> None:
        if self.bar is None:
            return
        self.bar.n = round(min(t_s, self.bar.total), 3)
        post = {"held": held, "discharged": None if discharged is None else int(discharged)}
        self.bar.set_postfix({name: value for name, value in post.items() if value is not None}, refresh=False)
        self.bar.refresh()

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
