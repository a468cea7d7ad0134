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
so the cost per snapshot is one C-level parse (see ``python -m workflows.bench.dem_post``).
Memory holds one snapshot at a time: flat in the number of snapshots.

Errors: a snapshot cut short at the very end of the *last* file (a killed run) is dropped
with a :class:`TruncatedDumpWarning`; anything else malformed raises
:class:`~coupling.errors.DumpFormatError` naming the file and the line (and the column and
value for a bad atom field). Checked: header bytes (column names are ASCII), steps and atom
counts in [0, 2**63), box bounds (two finite numbers lo < hi per axis; three, the last the
tilt factor, for a triclinic ``BOX BOUNDS xy xz yz`` header), every field a number, no NaN,
no infinity in the columns the caller asks for (all columns if it names none), ``id`` and
``type`` integers >= 1 (ids up to 2**53, types up to 2**31 - 1), no id twice in one
snapshot (the error names the file, the step, the id and both lines), positions x, y, z
within one box length of the box. Every path must be a regular file: a FIFO matched by a
glob would block the reader forever, a symlink loop would raise deep inside it. The checks are vector reductions over each parsed snapshot; the
line and column are found by a slow scan only once a check has failed.

One module for one file format: the header parser, the block parser and the error
location share the byte offsets they work on, and a writer (:func:`format_snapshot`, for
tests and tools) sits beside the reader it must satisfy.
"""

from __future__ import annotations

import glob as _glob
import io
import math
import mmap
import os
import re
import warnings
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from coupling.errors import DumpFormatError
from coupling.files import regular_file
from coupling.tables import MAX_SPEED_M_S

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

    for path in paths:
        regular_file(path, "dump file", DumpFormatError)
    return sorted(paths, key=key)


def iter_snapshots(
    paths: str | os.PathLike | Iterable[str | os.PathLike],
    columns: Sequence[str] | None = None,
    threads: int | None = None,
) -> Iterator[Snapshot]:
    """Snapshots of one or several dump files, in file order then file position.

    ``paths``: a glob pattern, a path, or a sequence of paths (sorted naturally when a glob).
    ``columns``: if given, every snapshot must carry these columns (DumpFormatError naming
    the missing one otherwise) and their values must be finite. Steps must increase strictly across the whole sequence.
    A snapshot cut short at the end of the last file is dropped with TruncatedDumpWarning.
    ``threads``: per-snapshot files are parsed ahead by this many threads (pandas' parser
    releases the GIL), at most ``threads`` files in flight, so memory stays flat; default
    min(2, CPUs) for files over 512 kB, else 1; 1 parses in the caller's thread only.
    """
    if isinstance(paths, (str, os.PathLike)):
        files = dump_paths(paths) if any(c in str(paths) for c in "*?[") else [Path(paths)]
    else:
        files = [Path(p) for p in paths]
    for path in files:  # a FIFO would block the reader forever; a loop, a device: one line
        regular_file(path, "dump file", DumpFormatError)
    if threads is None:
        # parsing ahead pays off for big snapshot files (paper preset: ~1.5 MB); for small
        # ones the thread hand-off costs more than it saves (measured, bench_dem_post)
        big = bool(files) and files[0].is_file() and files[min(1, len(files) - 1)].stat().st_size > (512 << 10)
        threads = min(2, os.cpu_count() or 1) if big else 1
    threads = max(1, int(threads))
    last_step = None
    checked = tuple(columns) if columns is not None else None
    for path, snap in _snapshots_of_files(files, threads, checked):
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


def _snapshots_of_files(files: list[Path], threads: int, checked) -> Iterator[tuple[Path, Snapshot]]:
    last = len(files) - 1
    if threads == 1 or len(files) < 2:
        for index, path in enumerate(files):
            for snap in _iter_file(path, allow_truncated=index == last, checked=checked):
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
                    pending.append(
                        (path, next_index == last, pool.submit(_load_single_file, path, next_index == last, checked))
                    )
                    next_index += 1
                path, allow, future = pending.popleft()
                loaded = future.result()
                if loaded is None:  # several snapshots in this file: stream it here
                    for snap in _iter_file(path, allow_truncated=allow, checked=checked):
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


def _load_single_file(path: Path, allow_truncated: bool, checked):
    """Worker: ``(snapshot or None, warning messages)`` for a file of at most one snapshot;
    None if the file holds more than one (the caller streams it instead)."""
    messages: list[str] = []
    snaps = _iter_file(path, allow_truncated, warn=messages.append, checked=checked)
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


def _iter_file(path: Path, allow_truncated: bool, warn=None, checked=None) -> Iterator[Snapshot]:
    """Snapshots of one file; a truncated last snapshot is reported through ``warn(message)``
    (default: a TruncatedDumpWarning) when ``allow_truncated``, else DumpFormatError.
    ``checked``: the columns that must be finite (None: all of them)."""
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
                        single = _parse_single(buf, size, path, checked)
                    except _Truncated:
                        single = None  # the general path below reports it
                    if single is not None:
                        yield single
                        return
                try:
                    snap, pos = _parse_snapshot(buf, pos, size, path, checked)
                except _Truncated as exc:
                    if not allow_truncated:
                        raise DumpFormatError(
                            f"{path}: line {_line_of(buf, pos)}: snapshot cut short ({exc}) in a file "
                            "that is not the last of the sequence"
                        ) from None
                    warn(
                        f"{path}: last snapshot (from line {_line_of(buf, pos)}) is cut short ({exc}); dropped (killed run?)"
                    )
                    return
                yield snap
        finally:
            buf.close()


def _line_of(buf, pos: int) -> int:
    return bytes(buf[:pos]).count(b"\n") + 1


def _parse_single(buf, size: int, path: Path, checked=None) -> Snapshot | None:
    """Fast path for a file holding exactly one complete snapshot (the deck's layout):
    pandas' C parser reads the numbers straight from the file after the 9 header lines,
    exactly like the plain ``read_csv`` baseline but with float64 declared (no type
    inference). Returns None when the file is not such a file, or its values fail a check
    (the general path then parses it again and names the line)."""
    if buf[size - 1 : size] != b"\n":
        return None
    step, natoms, box, columns, body_start, header_lines = _parse_header(buf, 0, size, path)
    # No scan for a second snapshot: its header lines would not parse as numbers (pandas
    # raises) or the row count would differ, and the general path takes over.
    if natoms == 0:
        return None
    import pandas as pd  # here, not with the module: what reads results files never needs it

    try:
        frame = pd.read_csv(
            path, sep=" ", header=None, skiprows=header_lines, dtype=np.float64, engine="c", low_memory=False
        )  # one snapshot: one chunk, no chunk concatenation
    except (ValueError, pd.errors.ParserError, pd.errors.EmptyDataError):
        return None
    values = _checked_values(frame.to_numpy(), natoms, columns, checked, box)
    if values is None:
        return None
    _refuse_duplicate_ids(values, columns, path, step, header_lines + 1)
    return Snapshot(step=step, columns=columns, data=values, box=box, source=str(path))


#: Ids and types are C integers in LIGGGHTS, >= 1. Ids are held here as float64, exact up to
#: 2**53 (beyond it two ids could read as one); types are C ``int``.
_MAX_ID = float(2**53)
_MAX_TYPE = float(2**31 - 1)
_INTEGER_COLUMNS = {"id": _MAX_ID, "type": _MAX_TYPE}
#: Positions: LIGGGHTS loses (fixed boundaries) or wraps (periodic) an atom that leaves the
#: box at the next neighbour-list build, before which it moves less than the skin; so a
#: dumped position lies in the box give or take a little. One box length of margin on each
#: side accepts any such position and refuses a corrupted one (1e300 would count as a
#: discharge).
_POSITION_AXES = {"x": 0, "y": 1, "z": 2}
#: Velocities: at most coupling.tables.MAX_SPEED_M_S (100 m/s) in magnitude per component: a
#: particle faster than that in a bladed blender is an exploded simulation or a corrupted
#: field, and one such value would dominate its compartment's mean (the table refuses the
#: same bound).
_VELOCITY_COLUMNS = ("vx", "vy", "vz")
#: Steps are LIGGGHTS' ``bigint`` (int64).
_MAX_STEP = 2**63 - 1


def _position_range(box: np.ndarray, axis: int) -> tuple[float, float]:
    lo, hi = box[axis]
    return lo - (hi - lo), hi + (hi - lo)


def _checked_values(
    values: np.ndarray, natoms: int, columns: tuple[str, ...], checked, box: np.ndarray
) -> np.ndarray | None:
    """The (natoms, ncols) values, or None if their shape is wrong or a value fails a check
    (:func:`_field_problem` then names it)."""
    ncols = len(columns)
    # LIGGGHTS ends every atom line with a space: pandas sees an empty last column, which is
    # left out by a view (no copy).
    if values.shape[1] == ncols + 1 and np.isnan(values[:, -1]).all():
        values = values[:, :ncols]
    if values.shape != (natoms, ncols):
        return None
    if not np.isfinite(values).all():  # rare: which non-finite values are allowed?
        # NaN anywhere also means an empty field (two spaces), which pandas reads as NaN.
        if np.isnan(values).any():
            return None
        names = columns if checked is None else [name for name in checked if name in columns]
        if any(not np.isfinite(values[:, columns.index(name)]).all() for name in names):
            return None
    # min/max are single reductions over a strided column, cheaper than boolean masks
    for name, bound in _INTEGER_COLUMNS.items():
        if name in columns:
            v = values[:, columns.index(name)]
            if v.min() < 1 or v.max() > bound or not np.array_equal(v, np.floor(v)):
                return None
    for name, axis in _POSITION_AXES.items():
        if name in columns:
            low, high = _position_range(box, axis)
            v = values[:, columns.index(name)]
            if v.min() < low or v.max() > high:
                return None
    for name in _VELOCITY_COLUMNS:
        if name in columns:
            v = values[:, columns.index(name)]
            if v.min() < -MAX_SPEED_M_S or v.max() > MAX_SPEED_M_S:
                return None
    return values


def _refuse_duplicate_ids(values: np.ndarray, columns: tuple[str, ...], path: Path, step: int, first_line: int) -> None:
    """DumpFormatError naming the file, the step, the id and both lines if an id occurs
    twice in the snapshot (a LIGGGHTS atom id is unique: a repeated one is a corrupted or
    concatenated dump, and would count a particle twice in the hold-up). ``first_line``:
    the file line of the snapshot's first atom."""
    if "id" not in columns or values.shape[0] < 2:
        return
    ids = values[:, columns.index("id")].astype(np.int64)  # checked: integers in [1, 2**53]
    n = ids.size
    top = int(ids.max())
    if top <= 8 * n + (1 << 20):  # the usual case: ids near 1..N, one bincount
        if np.bincount(ids, minlength=top + 1).max() <= 1:
            return
    order = np.argsort(ids, kind="stable")
    ranked = ids[order]
    same = np.flatnonzero(ranked[1:] == ranked[:-1])
    if not same.size:
        return
    # the repeat that comes first in the file
    seconds = order[same + 1]
    k = int(np.argmin(seconds))
    second, first = int(seconds[k]), int(order[same[k]])
    raise DumpFormatError(
        f"{path}: line {first_line + second}: snapshot at step {step} lists atom id {int(ids[second])} twice "
        f"(lines {first_line + first} and {first_line + second}); every id must be unique within a snapshot"
    )


def _field_problem(name: str, text: bytes, checked, box: np.ndarray) -> str | None:
    """Why the field ``text`` of column ``name`` is invalid, or None (the per-value form of
    :func:`_checked_values`, used only to name a bad value)."""
    shown = text[:40].decode(errors="replace")
    try:
        value = float(text)
    except ValueError:
        return f"column {name!r}: {shown!r} is not a number"
    if math.isnan(value):
        return f"column {name!r}: {shown!r} is not a number (NaN)"
    if math.isinf(value) and (checked is None or name in checked):
        return f"column {name!r}: {shown!r} is not finite; a finite number is needed"
    bound = _INTEGER_COLUMNS.get(name)
    if bound is not None and not (1 <= value <= bound and value == math.floor(value)):
        return f"column {name!r}: {shown!r} is not a valid {name}; an integer in [1, {int(bound)}] is needed"
    if name in _VELOCITY_COLUMNS and math.isfinite(value) and abs(value) > MAX_SPEED_M_S:
        return (
            f"column {name!r}: {shown!r} m/s is not a particle velocity of a blender; |{name}| up to "
            f"{MAX_SPEED_M_S:g} m/s is accepted"
        )
    axis = _POSITION_AXES.get(name)
    if axis is not None and math.isfinite(value):
        low, high = _position_range(box, axis)
        if not low <= value <= high:
            return (
                f"column {name!r}: {shown!r} lies far outside the box [{box[axis][0]:.6g}, {box[axis][1]:.6g}]; "
                f"positions within one box length of it, [{low:.6g}, {high:.6g}], are accepted"
            )
    return None


def _read_line(buf, pos: int, size: int, path: Path) -> tuple[bytes, int]:
    end = buf.find(b"\n", pos)
    if end < 0:
        raise _Truncated("header ends before its last line")
    return bytes(buf[pos:end]).rstrip(b"\r"), end + 1


def _shown(line: bytes) -> str:
    return repr(line[:60].decode(errors="replace"))


def _parse_header(buf, pos: int, size: int, path: Path):
    """(step, natoms, box, columns, body_start, header_lines) of the snapshot at ``pos``."""

    def fail(at: int, message: str) -> DumpFormatError:
        return DumpFormatError(f"{path}: line {_line_of(buf, at)}: {message}")

    def expect_item(at: int, item: bytes) -> tuple[bytes, int]:
        line, nxt = _read_line(buf, at, size, path)
        if not line.strip().startswith(item):
            raise fail(at, f"expected {item.decode()!r}, found {_shown(line)}")
        return line, nxt

    def number(at: int, what: str, low: int, high: int):
        line, nxt = _read_line(buf, at, size, path)
        try:
            value = int(line.strip())
        except ValueError:
            raise fail(at, f"expected {what}, found {_shown(line)}") from None
        if not low <= value <= high:
            raise fail(at, f"{what} {value} is out of range; it must lie in [{low}, {high}]")
        return value, nxt

    _, pos = expect_item(pos, _HEADER_ITEMS[0])
    step, pos = number(pos, "timestep", 0, _MAX_STEP)
    _, pos = expect_item(pos, _HEADER_ITEMS[1])
    natoms, pos = number(pos, "number of atoms", 0, _MAX_STEP)
    flags, pos = expect_item(pos, _HEADER_ITEMS[2])
    # A triclinic box (LIGGGHTS writes 'BOX BOUNDS xy xz yz ...') adds its tilt factor as a
    # third number per line; lo and hi are then the bounding box's, still lo < hi.
    triclinic = b"xy" in flags.split()
    per_line = 3 if triclinic else 2
    box = np.zeros((3, 2))
    for axis in range(3):
        line, nxt = _read_line(buf, pos, size, path)
        fields = line.split()
        try:
            values = [float(v) for v in fields]
        except ValueError:
            values = []
        if len(values) != per_line or not all(math.isfinite(v) for v in values) or not values[0] < values[1]:
            layout = "'lo hi tilt'" if triclinic else "'lo hi'"
            raise fail(
                pos,
                f"box bounds of axis {'xyz'[axis]} must be {layout}: {per_line} finite numbers "
                f"with lo < hi, found {_shown(line)}",
            )
        box[axis] = values[:2]
        pos = nxt
    line, nxt = _read_line(buf, pos, size, path)
    if not line.startswith(b"ITEM: ATOMS"):
        raise fail(pos, f"expected 'ITEM: ATOMS <columns>', found {_shown(line)}")
    try:
        columns = tuple(line[len(b"ITEM: ATOMS") :].decode("ascii").split())
    except UnicodeDecodeError as exc:
        raise fail(
            pos,
            f"column names must be ASCII; byte {line[len(b'ITEM: ATOMS') + exc.start]:#04x} at "
            f"character {len(b'ITEM: ATOMS') + exc.start + 1} of {_shown(line)} is not",
        ) from None
    if not columns or len(set(columns)) != len(columns):
        raise fail(pos, f"ITEM: ATOMS header must name distinct columns, got {columns}")
    return step, natoms, box, columns, nxt, 9


def _parse_snapshot(buf, pos: int, size: int, path: Path, checked=None) -> tuple[Snapshot, int]:
    step, natoms, box, columns, body_start, _ = _parse_header(buf, pos, size, path)
    end = buf.find(_NEXT, body_start)
    if end < 0:
        end = size
    block = bytes(buf[body_start:end])
    at_eof = end == size
    data = _parse_block(block, natoms, columns, path, buf, body_start, at_eof, checked, box)
    if natoms > 1 and "id" in columns:
        _refuse_duplicate_ids(data, columns, path, step, _line_of(buf, body_start))
    return Snapshot(step=step, columns=columns, data=data, box=box, source=str(path)), end


def _parse_block(
    block: bytes,
    natoms: int,
    columns: tuple[str, ...],
    path: Path,
    buf,
    body_start: int,
    at_eof: bool,
    checked=None,
    box=None,
) -> np.ndarray:
    ncols = len(columns)
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
    import pandas as pd  # here, not with the module: what reads results files never needs it

    try:
        frame = pd.read_csv(io.BytesIO(block), sep=" ", header=None, dtype=np.float64, engine="c", low_memory=False)
    except (ValueError, pd.errors.ParserError) as exc:
        raise _locate_bad_line(block, columns, path, buf, body_start, str(exc), checked, box) from None
    values = _checked_values(frame.to_numpy(), natoms, columns, checked, box)
    if values is None:
        raise _locate_bad_line(
            block, columns, path, buf, body_start, f"expected {natoms} lines of {ncols} numbers", checked, box
        )
    return values


def _locate_bad_line(
    block: bytes, columns: tuple[str, ...], path: Path, buf, body_start: int, why: str, checked=None, box=None
) -> DumpFormatError:
    """Slow path, only on error: the first atom line that is not ``len(columns)`` valid numbers."""
    first = _line_of(buf, body_start)
    ncols = len(columns)
    for offset, line in enumerate(block.split(b"\n")[:-1]):
        fields = line.split()
        if len(fields) != ncols:
            return DumpFormatError(
                f"{path}: line {first + offset}: expected {ncols} numbers ({' '.join(columns)}), "
                f"found {len(fields)} fields: {line[:80].decode(errors='replace')!r}"
            )
        for name, text in zip(columns, fields):
            problem = _field_problem(name, text, checked, box)
            if problem is not None:
                return DumpFormatError(f"{path}: line {first + offset}: {problem}")
        # pandas splits on single spaces: two in a row make an empty field
        if b"  " in line.strip() or b"\t" in line:
            return DumpFormatError(
                f"{path}: line {first + offset}: fields must be separated by single spaces, "
                f"found {line[:80].decode(errors='replace')!r}"
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
        + "ITEM: ATOMS "
        + " ".join(columns)
        + " \n"
    )
    fmt = " ".join("%d" if c in ("id", "type") else "%.9g" for c in columns) + " "
    out = io.StringIO()
    if data.shape[0]:
        np.savetxt(out, data, fmt=fmt)
    return head.encode() + out.getvalue().encode()
