"""Streaming reader of LIGGGHTS/LAMMPS text dumps (``dump custom``).

A dump is a sequence of snapshots, each::

    ITEM: TIMESTEP
    <step>
    ITEM: NUMBER OF ATOMS
    <n>
    ITEM: BOX BOUNDS <flags>
    <lo> <hi>      (three lines)
    ITEM: ATOMS <col> <col> ...
    <n lines of numbers>

Snapshots come one file each (``dump.*.txt``, the deck's layout) or many to a file; both
are read the same way. Columns are found by the names in each ``ITEM: ATOMS`` header, never
by position, so a deck that dumps more or other columns still reads correctly.

Speed: a file is read (or memory-mapped) as bytes, the header lines are located with
``bytes.find`` and the numeric block of each snapshot goes to pandas' C parser in one call,
so the cost per snapshot is one C-level parse (see ``python -m workflows.bench_dem_post``).
Memory holds one snapshot at a time: flat in the number of snapshots.

Errors: a snapshot cut short at the very end of the *last* file (a killed run) is dropped
with a :class:`TruncatedDumpWarning`; anything else malformed raises
:class:`~coupling.errors.DumpFormatError` naming the file and the line.

One module for one file format: the header parser, the block parser and the error
location share the byte offsets they work on, and a writer (:func:`format_snapshot`, for
tests and tools) sits beside the reader it must satisfy.
"""

from __future__ import annotations

import glob as _glob
import io
import mmap
import os
import re
import warnings
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from coupling.errors import DumpFormatError

__all__ = [
    "Snapshot",
    "TruncatedDumpWarning",
    "dump_paths",
    "iter_snapshots",
    "read_snapshot_file",
    "format_snapshot",
]


class TruncatedDumpWarning(UserWarning):
    """The last snapshot of a dump was cut short (killed run) and was dropped."""


@dataclass(frozen=True)
class Snapshot:
    """One dump snapshot: ``data`` is (n, ncols) float64 with ``columns`` naming its columns."""

    step: int
    columns: tuple[str, ...]
    data: np.ndarray
    box: np.ndarray  # (3, 2) lo/hi per axis [m]
    source: str

    @property
    def n(self) -> int:
        return self.data.shape[0]

    def __contains__(self, name: str) -> bool:
        return name in self.columns

    def __getitem__(self, name: str) -> np.ndarray:
        """Column ``name`` (a view, float64); raises DumpFormatError naming the columns present."""
        try:
            index = self.columns.index(name)
        except ValueError:
            raise DumpFormatError(
                f"{self.source}: snapshot at step {self.step} has no column {name!r}; "
                f"its ITEM: ATOMS header lists {' '.join(self.columns)}"
            ) from None
        return self.data[:, index]

    def time_s(self, timestep_s: float) -> float:
        """Simulated time of the snapshot [s] = step x timestep."""
        return self.step * timestep_s


def dump_paths(pattern: str | os.PathLike | Sequence[str | os.PathLike]) -> list[Path]:
    """Files matching a glob (or a list of paths), in natural order of the numbers in their
    names (``dump.900.txt`` before ``dump.1000.txt``). Raises DumpFormatError if none."""
    if isinstance(pattern, (str, os.PathLike)):
        paths = [Path(p) for p in _glob.glob(str(pattern))]
        if not paths:
            raise DumpFormatError(f"no dump files match {str(pattern)!r}")
    else:
        paths = [Path(p) for p in pattern]
        if not paths:
            raise DumpFormatError("no dump files given")

    def key(path: Path):
        parts = re.split(r"(\d+)", path.name)
        return [int(p) if p.isdigit() else p for p in parts], str(path)

    return sorted(paths, key=key)


def iter_snapshots(
    paths: str | os.PathLike | Iterable[str | os.PathLike],
    columns: Sequence[str] | None = None,
    threads: int | None = None,
) -> Iterator[Snapshot]:
    """Snapshots of one or several dump files, in file order then file position.

    ``paths``: a glob pattern, a path, or a sequence of paths (sorted naturally when a glob).
    ``columns``: if given, every snapshot must carry these columns (DumpFormatError naming
    the missing one otherwise). Steps must increase strictly across the whole sequence.
    A snapshot cut short at the end of the last file is dropped with TruncatedDumpWarning.
    ``threads``: per-snapshot files are parsed ahead by this many threads (pandas' parser
    releases the GIL), at most ``threads`` files in flight, so memory stays flat; default
    min(2, CPUs) for files over 512 kB, else 1; 1 parses in the caller's thread only.
    """
    if isinstance(paths, (str, os.PathLike)):
        files = dump_paths(paths) if any(c in str(paths) for c in "*?[") else [Path(paths)]
    else:
        files = [Path(p) for p in paths]
    if threads is None:
        # parsing ahead pays off for big snapshot files (paper preset: ~1.5 MB); for small
        # ones the thread hand-off costs more than it saves (measured, bench_dem_post)
        big = bool(files) and files[0].is_file() and files[min(1, len(files) - 1)].stat().st_size > (512 << 10)
        threads = min(2, os.cpu_count() or 1) if big else 1
    threads = max(1, int(threads))
    last_step = None
    for path, snap in _snapshots_of_files(files, threads):
        if last_step is not None and snap.step <= last_step:
            raise DumpFormatError(
                f"{path}: snapshot step {snap.step} does not follow the previous step {last_step}; "
                "dump files must be given in time order without duplicates"
            )
        if columns is not None:
            for name in columns:
                if name not in snap.columns:
                    raise DumpFormatError(
                        f"{path}: snapshot at step {snap.step} has no column {name!r}; "
                        f"its ITEM: ATOMS header lists {' '.join(snap.columns)}"
                    )
        last_step = snap.step
        yield snap


def _snapshots_of_files(files: list[Path], threads: int) -> Iterator[tuple[Path, Snapshot]]:
    last = len(files) - 1
    if threads == 1 or len(files) < 2:
        for index, path in enumerate(files):
            for snap in _iter_file(path, allow_truncated=index == last):
                yield path, snap
        return
    from collections import deque
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=threads, thread_name_prefix="dump-reader") as pool:
        pending: deque = deque()
        next_index = 0
        try:
            while pending or next_index <= last:
                while next_index <= last and len(pending) < threads:
                    path = files[next_index]
                    pending.append((path, next_index == last, pool.submit(_load_single_file, path, next_index == last)))
                    next_index += 1
                path, allow, future = pending.popleft()
                loaded = future.result()
                if loaded is None:  # several snapshots in this file: stream it here
                    for snap in _iter_file(path, allow_truncated=allow):
                        yield path, snap
                    continue
                snap, messages = loaded
                for message in messages:  # warnings are issued in the caller's thread
                    warnings.warn(message, TruncatedDumpWarning, stacklevel=4)
                if snap is not None:
                    yield path, snap
        finally:
            for _, _, future in pending:
                future.cancel()


def _load_single_file(path: Path, allow_truncated: bool):
    """Worker: ``(snapshot or None, warning messages)`` for a file of at most one snapshot;
    None if the file holds more than one (the caller streams it instead)."""
    messages: list[str] = []
    snaps = _iter_file(path, allow_truncated, warn=messages.append)
    try:
        first = next(snaps, None)
        if first is not None and next(snaps, None) is not None:
            return None
    finally:
        snaps.close()
    return first, messages


def read_snapshot_file(path: str | os.PathLike) -> list[Snapshot]:
    """Every snapshot of one file, as a list (convenience for small files and tests)."""
    return list(_iter_file(Path(path), allow_truncated=True))


# --------------------------------------------------------------------------------------
_HEADER_ITEMS = (b"ITEM: TIMESTEP", b"ITEM: NUMBER OF ATOMS", b"ITEM: BOX BOUNDS")
_NEXT = b"ITEM: TIMESTEP"


class _Truncated(Exception):
    pass


def _iter_file(path: Path, allow_truncated: bool, warn=None) -> Iterator[Snapshot]:
    """Snapshots of one file; a truncated last snapshot is reported through ``warn(message)``
    (default: a TruncatedDumpWarning) when ``allow_truncated``, else DumpFormatError."""
    if warn is None:

        def warn(message: str) -> None:
            warnings.warn(message, TruncatedDumpWarning, stacklevel=4)

    try:
        size = path.stat().st_size
        handle = open(path, "rb")
    except OSError as exc:
        raise DumpFormatError(f"cannot read dump file {path}: {exc}") from exc
    with handle:
        if size == 0:
            if allow_truncated:
                warn(f"{path}: empty dump file (killed run?) ignored")
                return
            raise DumpFormatError(f"{path}: line 1: empty dump file")
        # Mapped, not read: headers are found without copying the file, and only the snapshot
        # being parsed is resident.
        buf = mmap.mmap(handle.fileno(), 0, access=mmap.ACCESS_READ)
        try:
            pos = 0
            while pos < size:
                if pos == 0:
                    try:
                        single = _parse_single(buf, size, path)
                    except _Truncated:
                        single = None  # the general path below reports it
                    if single is not None:
                        yield single
                        return
                try:
                    snap, pos = _parse_snapshot(buf, pos, size, path)
                except _Truncated as exc:
                    if not allow_truncated:
                        raise DumpFormatError(
                            f"{path}: line {_line_of(buf, pos)}: snapshot cut short ({exc}) in a file "
                            "that is not the last of the sequence"
                        ) from None
                    warn(f"{path}: last snapshot (from line {_line_of(buf, pos)}) is cut short ({exc}); dropped (killed run?)")
                    return
                yield snap
        finally:
            buf.close()


def _line_of(buf, pos: int) -> int:
    return bytes(buf[:pos]).count(b"\n") + 1


def _parse_single(buf, size: int, path: Path) -> Snapshot | None:
    """Fast path for a file holding exactly one complete snapshot (the deck's layout):
    pandas' C parser reads the numbers straight from the file after the 9 header lines,
    exactly like the plain ``read_csv`` baseline but with float64 declared (no type
    inference). Returns None when the file is not such a file (general path then)."""
    if buf[size - 1 : size] != b"\n":
        return None
    step, natoms, box, columns, body_start, header_lines = _parse_header(buf, 0, size, path)
    # No scan for a second snapshot: its header lines would not parse as numbers (pandas
    # raises) or the row count would differ, and the general path takes over.
    if natoms == 0:
        return None
    try:
        frame = pd.read_csv(path, sep=" ", header=None, skiprows=header_lines, dtype=np.float64, engine="c",
                            low_memory=False)  # one snapshot: one chunk, no chunk concatenation
    except (ValueError, pd.errors.ParserError, pd.errors.EmptyDataError):
        return None
    values = _checked_values(frame.to_numpy(), natoms, len(columns))
    if values is None:
        return None
    return Snapshot(step=step, columns=columns, data=values, box=box, source=str(path))


def _checked_values(values: np.ndarray, natoms: int, ncols: int) -> np.ndarray | None:
    # LIGGGHTS ends every atom line with a space: pandas sees an empty last column, which is
    # left out by a view (no copy).
    if values.shape[1] == ncols + 1 and np.isnan(values[:, -1]).all():
        values = values[:, :ncols]
    if values.shape != (natoms, ncols) or np.isnan(values).any():
        return None
    return values


def _read_line(buf, pos: int, size: int, path: Path) -> tuple[bytes, int]:
    end = buf.find(b"\n", pos)
    if end < 0:
        raise _Truncated("header ends before its last line")
    return bytes(buf[pos:end]).rstrip(b"\r"), end + 1


def _parse_header(buf, pos: int, size: int, path: Path):
    """(step, natoms, box, columns, body_start, header_lines) of the snapshot at ``pos``."""

    def fail(at: int, message: str) -> DumpFormatError:
        return DumpFormatError(f"{path}: line {_line_of(buf, at)}: {message}")

    def expect_item(at: int, item: bytes) -> int:
        line, nxt = _read_line(buf, at, size, path)
        if not line.strip().startswith(item):
            raise fail(at, f"expected {item.decode()!r}, found {line[:60].decode(errors='replace')!r}")
        return nxt

    def number(at: int, kind, what: str):
        line, nxt = _read_line(buf, at, size, path)
        try:
            return kind(line.strip()), nxt
        except ValueError:
            raise fail(at, f"expected {what}, found {line[:60].decode(errors='replace')!r}") from None

    pos = expect_item(pos, _HEADER_ITEMS[0])
    step, pos = number(pos, int, "an integer timestep")
    pos = expect_item(pos, _HEADER_ITEMS[1])
    natoms, pos = number(pos, int, "an integer number of atoms")
    if natoms < 0:
        raise fail(pos, f"negative number of atoms {natoms}")
    pos = expect_item(pos, _HEADER_ITEMS[2])
    box = np.zeros((3, 2))
    for axis in range(3):
        line, nxt = _read_line(buf, pos, size, path)
        try:
            box[axis] = [float(v) for v in line.split()[:2]]
        except ValueError:
            raise fail(pos, f"expected box bounds 'lo hi', found {line[:60].decode(errors='replace')!r}") from None
        pos = nxt
    line, nxt = _read_line(buf, pos, size, path)
    if not line.startswith(b"ITEM: ATOMS"):
        raise fail(pos, f"expected 'ITEM: ATOMS <columns>', found {line[:60].decode(errors='replace')!r}")
    columns = tuple(line[len(b"ITEM: ATOMS") :].decode().split())
    if not columns or len(set(columns)) != len(columns):
        raise fail(pos, f"ITEM: ATOMS header must name distinct columns, got {columns}")
    return step, natoms, box, columns, nxt, 9


def _parse_snapshot(buf, pos: int, size: int, path: Path) -> tuple[Snapshot, int]:
    step, natoms, box, columns, body_start, _ = _parse_header(buf, pos, size, path)
    end = buf.find(_NEXT, body_start)
    if end < 0:
        end = size
    block = bytes(buf[body_start:end])
    at_eof = end == size
    data = _parse_block(block, natoms, len(columns), path, buf, body_start, at_eof)
    return Snapshot(step=step, columns=columns, data=data, box=box, source=str(path)), end


def _parse_block(block: bytes, natoms: int, ncols: int, path: Path, buf, body_start: int, at_eof: bool) -> np.ndarray:
    if natoms == 0:
        if block.strip():
            raise DumpFormatError(f"{path}: line {_line_of(buf, body_start)}: data lines after 'NUMBER OF ATOMS 0'")
        return np.zeros((0, ncols))
    if at_eof and not block.endswith(b"\n"):
        raise _Truncated("the last line has no end-of-line")
    nlines = block.count(b"\n")
    if nlines != natoms:  # rare: count the lines that hold something
        stripped = block.strip()
        nlines = stripped.count(b"\n") + 1 if stripped else 0
    if nlines < natoms:
        if at_eof:
            raise _Truncated(f"{nlines} of {natoms} atom lines")
        raise DumpFormatError(
            f"{path}: line {_line_of(buf, body_start)}: snapshot announces {natoms} atoms but has {nlines} lines"
        )
    if nlines > natoms:
        raise DumpFormatError(
            f"{path}: line {_line_of(buf, body_start)}: snapshot announces {natoms} atoms but has {nlines} lines"
        )
    try:
        frame = pd.read_csv(io.BytesIO(block), sep=" ", header=None, dtype=np.float64, engine="c", low_memory=False)
    except (ValueError, pd.errors.ParserError) as exc:
        raise _locate_bad_line(block, ncols, path, buf, body_start, str(exc)) from None
    values = _checked_values(frame.to_numpy(), natoms, ncols)
    if values is None:
        raise _locate_bad_line(block, ncols, path, buf, body_start, f"expected {natoms} lines of {ncols} numbers")
    return values


def _locate_bad_line(block: bytes, ncols: int, path: Path, buf, body_start: int, why: str) -> DumpFormatError:
    """Slow path, only on error: find the first atom line that is not ``ncols`` numbers."""
    first = _line_of(buf, body_start)
    for offset, line in enumerate(block.split(b"\n")[:-1]):
        fields = line.split()
        try:
            ok = len(fields) == ncols and all(float(f) == float(f) for f in fields)
        except ValueError:
            ok = False
        if not ok:
            return DumpFormatError(
                f"{path}: line {first + offset}: expected {ncols} numbers "
                f"({len(fields)} fields: {line[:80].decode(errors='replace')!r})"
            )
    return DumpFormatError(f"{path}: line {first}: malformed atom block ({why})")


def format_snapshot(
    step: int,
    columns: Sequence[str],
    data: np.ndarray,
    box: np.ndarray | Sequence[Sequence[float]] = ((-1.0, 1.0), (-1.0, 1.0), (-1.0, 1.0)),
) -> bytes:
    """One snapshot as LIGGGHTS writes it (``dump custom``; lines end with a space), for
    tests, synthetic data and conversions. ``data`` is (n, len(columns)); columns named
    ``id`` or ``type`` are written as integers."""
    data = np.asarray(data, dtype=float).reshape(-1, len(columns))
    box = np.asarray(box, dtype=float)
    head = (
        f"ITEM: TIMESTEP\n{int(step)}\nITEM: NUMBER OF ATOMS\n{data.shape[0]}\n"
        "ITEM: BOX BOUNDS ff ff ff\n"
        + "".join(f"{lo:.6g} {hi:.6g}\n" for lo, hi in box)
        + "ITEM: ATOMS " + " ".join(columns) + " \n"
    )
    fmt = " ".join("%d" if c in ("id", "type") else "%.9g" for c in columns) + " "
    out = io.StringIO()
    if data.shape[0]:
        np.savetxt(out, data, fmt=fmt)
    return head.encode() + out.getvalue().encode()
