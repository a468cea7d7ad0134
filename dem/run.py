"""Run LIGGGHTS on a deck, in a directory keyed by the hash of the run's inputs.

Entry point::

    record = run_dem(config, runs_root="runs", np=None, resume=False, fresh=False,
                     progress=True)   # -> RunRecord

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
interrupted and re-raises KeyboardInterrupt.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import re
import shlex
import shutil
import signal
import subprocess
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from coupling.cache import stable_hash
from coupling.errors import SolverNotFoundError, SolverRunError
from dem import deck

__all__ = [
    "RunRecord",
    "ThermoParser",
    "run_dem",
    "run_key",
    "liggghts_version",
    "solver_command",
    "read_status",
    "INSTALL_HINT",
]

INSTALL_HINT = "install it with `apt-get install liggghts openmpi-bin` (or `make setup`)"
STATUS_FILE = "status.json"
SOLVER_OUT = "solver.out"
LOG_FILE = "log.liggghts"
MAIN_INPUT = "in.blender"
# thermo columns summed into the solver's own counters when dem.deck.THERMO_MEANING is silent
DISCHARGED_COLUMNS = ("f_outA[2]", "f_outB[2]")
INSERTED_COLUMNS = ("f_insA[1]", "f_insB[1]")


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


# ----------------------------------------------------------------------------- helpers
def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def liggghts_version(liggghts: str = "liggghts") -> str:
    """The banner of ``liggghts -h`` (e.g. 'LIGGGHTS-PUBLIC 3.8.0, compiled ...').

    Raises SolverNotFoundError when the executable is missing."""
    exe = shlex.split(liggghts)
    if not exe or shutil.which(exe[0]) is None:
        raise SolverNotFoundError(f"LIGGGHTS executable {liggghts!r} not found on PATH; {INSTALL_HINT}")
    try:
        # -log none: otherwise `liggghts -h` leaves a log.liggghts in the caller's directory
        out = subprocess.run([*exe, "-log", "none", "-h"], capture_output=True, text=True, errors="replace",
                             timeout=60, stdin=subprocess.DEVNULL)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise SolverNotFoundError(f"cannot run {liggghts!r} -h: {exc}; {INSTALL_HINT}") from exc
    match = re.search(r"LIGGGHTS \(Version ([^)]*)\)", out.stdout + out.stderr)
    if not match:
        raise SolverNotFoundError(f"{liggghts!r} -h did not print a LIGGGHTS version banner; {INSTALL_HINT}")
    return match.group(1).strip()


def solver_command(run_config, np: int | None = None, main_input: str = MAIN_INPUT) -> list[str]:
    """argv: ``[<launcher formatted with np>] [stdbuf -oL] <liggghts> -in <main_input>``.

    The launcher is skipped for np == 1 when it is an ``{np}`` template (plain mpirun);
    a launcher without ``{np}`` (``srun``) is always used. Raises SolverNotFoundError naming
    the missing executable."""
    nprocs = int(np if np is not None else run_config.np)
    if nprocs < 1:
        raise SolverRunError(f"number of MPI ranks must be >= 1, got {nprocs}")
    launcher = run_config.launcher.strip()
    prefix: list[str] = []
    if launcher and not (nprocs == 1 and "{np}" in launcher):
        prefix = shlex.split(launcher.format(np=nprocs))
        if shutil.which(prefix[0]) is None:
            raise SolverNotFoundError(f"MPI launcher {prefix[0]!r} not found on PATH; {INSTALL_HINT}")
    exe = shlex.split(run_config.liggghts)
    if not exe or shutil.which(exe[0]) is None:
        raise SolverNotFoundError(f"LIGGGHTS executable {run_config.liggghts!r} not found on PATH; {INSTALL_HINT}")
    # Line-buffer the solver's stdout so an ERROR line is not lost in a pipe buffer when it
    # aborts (measured on LIGGGHTS 3.8.0, DESIGN.md). stdbuf goes after the launcher so it
    # applies to the solver itself, on every rank.
    stdbuf = ["stdbuf", "-oL"] if shutil.which("stdbuf") else []
    return [*prefix, *stdbuf, *exe, "-in", main_input]


def run_key(files: dict[str, str | bytes], version: str) -> str:
    """Hash of the run's inputs: every deck file's content (texts and meshes) + version."""
    import hashlib

    digests = {}
    for name, content in files.items():
        data = content.encode() if isinstance(content, str) else bytes(content)
        digests[name] = hashlib.sha256(data).hexdigest()
    return stable_hash({"files": digests, "liggghts_version": version, "layout": 1}, length=16)


def read_status(run_dir: str | os.PathLike) -> dict[str, Any] | None:
    """The run's status.json, or None if absent or unreadable (treated as not completed)."""
    path = Path(run_dir) / STATUS_FILE
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None


def _write_status(run_dir: Path, data: dict[str, Any]) -> None:
    tmp = run_dir / (STATUS_FILE + ".tmp")
    tmp.write_text(json.dumps(data, indent=2, sort_keys=True, default=str) + "\n")
    os.replace(tmp, run_dir / STATUS_FILE)


def _tail(path: Path, lines: int = 25) -> str:
    try:
        text = path.read_text(errors="replace")
    except OSError:
        return ""
    return "\n".join(text.rstrip().splitlines()[-lines:])


# ----------------------------------------------------------------------------- thermo
class ThermoParser:
    """Parses LIGGGHTS thermo lines as they stream: a header line starting with ``Step``,
    then rows of numbers with as many fields. ``latest`` maps column name to value.

    ``discharged_columns``: names whose sum is the solver's discharge count (the deck's
    massflow counters); ``inserted_columns`` likewise for insertion counters."""

    def __init__(self, discharged_columns=(), inserted_columns=(), columns=()) -> None:
        self.header: list[str] | None = None
        self.latest: dict[str, float] = {}
        self.discharged_columns = tuple(discharged_columns)
        self.inserted_columns = tuple(inserted_columns)
        self.columns = tuple(columns)

    def feed(self, line: str) -> bool:
        """Consume one line; True if it was a thermo data row."""
        tokens = line.split()
        if not tokens:
            return False
        if tokens[0] == "Step":
            self.header = self._names(tokens)
            return False
        if self.header is None or len(tokens) != len(self.header):
            return False
        try:
            values = [float(v) for v in tokens]
        except ValueError:
            return False
        self.latest = dict(zip(self.header, values))
        return True

    def _names(self, printed: list[str]) -> list[str]:
        """LIGGGHTS 3.8.0 prints thermo names without their ``v_``/``f_`` prefix and cut to a
        few characters (``f_tscheck[1]`` -> ``tscheck[``): when the printed header matches the
        deck's declared columns that way, the declared names are used."""
        if len(printed) != len(self.columns):
            return printed
        for shown, declared in zip(printed, self.columns):
            bare = declared[2:] if declared[:2] in ("v_", "f_", "c_") else declared
            if not (bare.startswith(shown) or declared == shown):
                return printed
        return list(self.columns)

    @property
    def step(self) -> int | None:
        return int(self.latest["Step"]) if "Step" in self.latest else None

    @property
    def atoms(self) -> int | None:
        return int(self.latest["Atoms"]) if "Atoms" in self.latest else None

    def _sum(self, names) -> float | None:
        present = [self.latest[n] for n in names if n in self.latest]
        return float(sum(present)) if present else None

    @property
    def discharged(self) -> float | None:
        return self._sum(self.discharged_columns)

    @property
    def inserted(self) -> float | None:
        return self._sum(self.inserted_columns)

    def counters(self) -> dict[str, float]:
        out = {}
        if self.discharged is not None:
            out["discharged"] = self.discharged
        if self.inserted is not None:
            out["inserted"] = self.inserted
        if self.atoms is not None:
            out["atoms"] = self.atoms
        if self.step is not None:
            out["step"] = self.step
        return out


class _Progress:
    """tqdm bar of simulated time; postfix: particles held, discharged."""

    def __init__(self, total_s: float, start_s: float, enabled: bool) -> None:
        self.bar = None
        if enabled:
            from tqdm import tqdm

            self.bar = tqdm(total=round(total_s, 3), initial=round(start_s, 3), unit="s sim", dynamic_ncols=True,
                            bar_format="{l_bar}{bar}| {n:.1f}/{total:.1f} s [{elapsed}<{remaining}{postfix}]")

    def update(self, t_s: float, held, discharged) -> None:
        if self.bar is None:
            return
        self.bar.n = round(min(t_s, self.bar.total), 3)
        post = {}
        if held is not None:
            post["held"] = held
        if discharged is not None:
            post["discharged"] = int(discharged)
        self.bar.set_postfix(post, refresh=False)
        self.bar.refresh()

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


# ----------------------------------------------------------------------------- run
def _thermo_roles(deck) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """Thermo columns summed into the solver's discharge and insertion counters, from the
    deck's THERMO_MEANING ("... discharged ...", "... inserted ..."); defaults otherwise."""
    meaning = getattr(deck, "THERMO_MEANING", {})
    discharged = tuple(name for name, text in meaning.items() if "discharged" in text)
    inserted = tuple(name for name, text in meaning.items() if "inserted" in text)
    return discharged or DISCHARGED_COLUMNS, inserted or INSERTED_COLUMNS


def _step_of(path: Path) -> int:
    numbers = re.findall(r"\d+", path.name)
    return int(numbers[-1]) if numbers else -1


def _restart_files(run_dir: Path) -> list[Path]:
    """Restart files known to be complete, oldest first.

    A restart file carries no end marker, and a run killed while writing one leaves it
    truncated. LIGGGHTS writes a step's restart before that step's thermo line, so a restart
    at step S is complete once solver.out shows a thermo row at a step >= S; newer ones
    are ignored (the resume then starts from an older restart: safe, a little slower)."""
    pattern = deck.RESTART_GLOB
    files = [p for p in run_dir.glob(pattern) if p.is_file() and p.stat().st_size > 0]
    parser = ThermoParser()
    last_step = -1
    try:
        with open(run_dir / SOLVER_OUT, errors="replace") as handle:
            for line in handle:
                if parser.feed(line) and parser.step is not None:
                    last_step = max(last_step, parser.step)
    except OSError:
        return []
    return sorted((p for p in files if _step_of(p) <= last_step), key=_step_of)


def _clear_outputs(run_dir: Path) -> None:
    """Remove a previous attempt's outputs so they can never mix with a new run's."""
    from dem.post import massflow_patterns

    for name in (LOG_FILE, SOLVER_OUT, STATUS_FILE):
        (run_dir / name).unlink(missing_ok=True)
    patterns = [deck.DUMP_GLOB, deck.RESTART_GLOB,
                *massflow_patterns()]
    for pattern in patterns:
        for path in run_dir.glob(pattern):
            if path.is_file():
                path.unlink()


def _set_aside_massflow(run_dir: Path, restart_step: int, dt: float) -> None:
    """Before a resume: LIGGGHTS reopens the discharge files for writing (``file``
    truncates them), so the records written before the crash are moved to
    ``<name>.upto<step>``, keeping only the particles discharged up to the restart step
    (the resumed run discharges the later ones again)."""
    limit = restart_step * dt + 0.5 * dt
    names = list(deck.MASSFLOW_FILES.values())
    for name in names:
        for path in sorted(run_dir.glob(name)) + sorted(run_dir.glob(name + ".[0-9]")) + sorted(run_dir.glob(name + ".[0-9][0-9]")):
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
            target = path.with_name(f"{path.name}.upto{restart_step}")
            target.write_text("\n".join(kept) + "\n")
            path.unlink()


def run_dem(
    config,
    runs_root: str | os.PathLike = "runs",
    np: int | None = None,
    resume: bool = False,
    fresh: bool = False,
    progress: bool = True,
    on_line: Callable[[str], None] | None = None,
) -> RunRecord:
    """Write the deck, run LIGGGHTS in ``<runs_root>/<key>/`` and return its RunRecord.

    ``config``: the pipeline ``Config`` (or whatever ``dem.deck.build_deck`` takes).
    ``np``: MPI ranks (default ``config.dem.run.np``). ``resume``: continue a crashed or
    interrupted run from its newest restart file. ``fresh``: delete the run directory and
    start again. ``progress``: tqdm bar on stderr. ``on_line``: called with every solver
    output line (tests, custom logging).

    A completed run with the same inputs is returned as is (``reused=True``) without starting
    a simulation. The key includes the LIGGGHTS version, asked from ``liggghts -h``; if the
    solver is not installed at all, a completed run of the same deck (same deck hash) under
    ``runs_root`` is still reused, and only a run that must actually start raises
    SolverNotFoundError.
    """
    dem = getattr(config, "dem", config)
    run_config = dem.run
    files = deck.build_deck(dem)
    deck_digest = run_key(files, "")
    try:
        version = liggghts_version(run_config.liggghts)
    except SolverNotFoundError:
        if not fresh:
            done = _completed_for_deck(Path(runs_root), deck_digest)
            if done is not None:
                return _record_from_status(done, read_status(done) or {}, reused=True)
        raise
    key = run_key(files, version)
    run_dir = Path(runs_root) / key
    status = read_status(run_dir)

    if fresh and run_dir.exists():
        shutil.rmtree(run_dir)
        status = None
    if status and status.get("state") == "completed" and not resume:
        return _record_from_status(run_dir, status, reused=True)
    if status and status.get("state") == "running":
        pid = status.get("pid")
        if pid and _alive(int(pid)):
            raise SolverRunError(f"run {key} is already running (pid {pid})", run_dir=run_dir)

    nprocs = int(np if np is not None else run_config.np)
    resumed_from = None
    if resume:
        restarts = _restart_files(run_dir) if run_dir.exists() else []
        if status and status.get("state") == "completed":
            return _record_from_status(run_dir, status, reused=True)
        if not restarts:
            raise SolverRunError(
                f"cannot resume run {key}: no complete restart file in {run_dir} (start it without --resume)",
                run_dir=run_dir,
            )
        restart = restarts[-1]
        resumed_from = str(restart.relative_to(run_dir))
        run_files = deck.build_deck(dem, resume_from=resumed_from)
        main_input = deck.RESUME_DECK
        _set_aside_massflow(run_dir, _step_of(restart), float(dem.timestep_s))
        # LIGGGHTS overwrites its log: keep the interrupted attempt's log beside it
        if (run_dir / LOG_FILE).exists():
            attempt = 1 + len(list(run_dir.glob(LOG_FILE + ".attempt*")))
            os.replace(run_dir / LOG_FILE, run_dir / f"{LOG_FILE}.attempt{attempt}")
    else:
        run_dir.mkdir(parents=True, exist_ok=True)
        _clear_outputs(run_dir)
        run_files = files
        main_input = deck.MAIN_DECK

    command = solver_command(run_config, nprocs, main_input)
    # Never edit a deck in place while LIGGGHTS may read it (DESIGN.md): the run directory is
    # ours alone and the files are written before the solver starts.
    deck.write_deck(run_files, run_dir)

    started = _now()
    base = {
        "key": key,
        "deck_hash": deck_digest,
        "liggghts_version": version,
        "command": command,
        "np": nprocs,
        "started": started,
        "resumed_from": resumed_from,
        "previous": status if resume else None,
    }
    _write_status(run_dir, {**base, "state": "running", "pid": os.getpid()})

    dt = float(dem.timestep_s)
    duration = float(dem.operation.duration_s)
    parser = ThermoParser(*_thermo_roles(deck), getattr(deck, "THERMO_COLUMNS", ()))
    start_s = _step_of(Path(resumed_from)) * dt if resumed_from else 0.0
    bar = _Progress(duration, start_s, progress)
    t0 = time.monotonic()
    # wall time accumulates over the attempts of a resumed run
    prior_wall = float(status.get("wall_time_s") or 0.0) if (resume and status) else 0.0
    error_lines: list[str] = []
    proc = None
    mode = "a" if resume else "w"
    try:
        with open(run_dir / SOLVER_OUT, mode, buffering=1) as out:
            if resume:
                out.write(f"\n# --- resumed from {resumed_from} at {started} ---\n")
            proc = subprocess.Popen(
                command,
                cwd=run_dir,
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL,
                text=True,
                errors="replace",
                bufsize=1,
                start_new_session=True,  # own process group: Ctrl-C handling kills all ranks
            )
            _write_status(run_dir, {**base, "state": "running", "pid": os.getpid(), "solver_pid": proc.pid})
            rc = _stream(proc, out, on_line, error_lines, parser, bar, dt)
    except KeyboardInterrupt:
        if proc is not None:
            _terminate_group(proc)
        bar.close()
        _write_status(run_dir, {**base, "state": "interrupted", "finished": _now(),
                                "wall_time_s": prior_wall + time.monotonic() - t0, "solver_counters": parser.counters()})
        raise
    except BaseException:
        if proc is not None:
            _terminate_group(proc)
        bar.close()
        _write_status(run_dir, {**base, "state": "crashed", "finished": _now(),
                                "wall_time_s": prior_wall + time.monotonic() - t0})
        raise
    finally:
        if proc is not None and proc.stdout is not None:
            proc.stdout.close()
    bar.close()
    wall = time.monotonic() - t0
    log_path = run_dir / LOG_FILE if (run_dir / LOG_FILE).exists() else run_dir / SOLVER_OUT
    dumps = list(run_dir.glob(deck.DUMP_GLOB))
    problem = None
    if error_lines:
        problem = f"LIGGGHTS reported an error: {error_lines[0]}"
    elif rc != 0:
        problem = f"LIGGGHTS exited with status {rc}"
    elif not dumps:
        problem = "LIGGGHTS finished but wrote no particle dump"
    elif parser.step is None or parser.step * dt < duration - 2 * dt - 1e-9:
        reached = "no thermo output" if parser.step is None else f"t = {parser.step * dt:.3f} s"
        problem = f"LIGGGHTS stopped before the end time {duration} s ({reached})"
    final = {**base, "finished": _now(), "wall_time_s": prior_wall + wall, "solver_counters": parser.counters()}
    if problem:
        _write_status(run_dir, {**final, "state": "crashed", "error": problem})
        raise SolverRunError(problem, run_dir=run_dir, log_tail=_tail(log_path))
    _write_status(run_dir, {**final, "state": "completed", "wall_time_this_attempt_s": wall})
    return _record_from_status(run_dir, read_status(run_dir) or {}, reused=False)


def _stream(proc, out, on_line, error_lines, parser, bar, dt, error_grace_s: float = 30.0) -> int:
    """Copy the solver's output to ``out`` line by line, parse thermo, collect ERROR lines.

    A reader thread feeds a queue so that the main thread stays responsive to Ctrl-C and can
    stop a solver that hangs after printing an ERROR (an MPI rank waiting for the others)."""
    import queue
    import threading

    lines: queue.Queue = queue.Queue()

    def reader() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.put(line)
        lines.put(None)

    thread = threading.Thread(target=reader, name="liggghts-output", daemon=True)
    thread.start()
    error_since = None
    while True:
        try:
            line = lines.get(timeout=1.0)
        except queue.Empty:
            if error_since is not None and time.monotonic() - error_since > error_grace_s and proc.poll() is None:
                _terminate_group(proc)
            continue
        if line is None:
            break
        out.write(line)
        if on_line is not None:
            on_line(line)
        if line.lstrip().startswith("ERROR"):
            error_lines.append(line.strip())
            error_since = error_since or time.monotonic()
        if parser.feed(line) and parser.step is not None:
            bar.update(parser.step * dt, parser.atoms, parser.discharged)
    thread.join()
    return proc.wait()


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


def _completed_for_deck(runs_root: Path, deck_digest: str) -> Path | None:
    """Newest completed run directory under ``runs_root`` made from the same deck."""
    best = None
    for status_path in runs_root.glob(f"*/{STATUS_FILE}"):
        status = read_status(status_path.parent)
        if status and status.get("state") == "completed" and status.get("deck_hash") == deck_digest:
            if best is None or str(status.get("finished")) > str(best[0]):
                best = (status.get("finished"), status_path.parent)
    return best[1] if best else None


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return False
    try:
        os.kill(pid, 0)
    except (ProcessLookupError, PermissionError):
        return False
    return True


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


def _terminate_group(proc: subprocess.Popen, grace_s: float = 10.0) -> None:
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
