"""The solver's own discharge records: ``fix massflow/mesh ... file`` outputs.

One line per particle counted past the weir (header ``# ID [time] diameter x y z u v w``).
With ``mpirun -np N`` every rank writes its own file (suffix ``.0`` ... ``.N-1``); a resumed
run keeps the records made before its restart in ``<name>.upto<step>``. The file names
come from :mod:`dem.deck`, which writes the fixes.
"""

from __future__ import annotations

import glob as _glob
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from coupling.errors import DumpFormatError
from dem import deck


def massflow_files(directory: str | os.PathLike | None) -> list[Path]:
    """The discharge files in ``directory`` (every rank's part and every part set aside
    before a resume); empty if ``directory`` is None or holds none."""
    if directory is None:
        return []
    found: set[Path] = set()
    for pattern in deck.MASSFLOW_GLOBS.values():
        found.update(Path(p) for p in _glob.glob(str(Path(directory) / pattern)))
    return sorted(p for p in found if p.is_file())


def read_massflow(paths: Sequence[str | os.PathLike]) -> tuple[np.ndarray, np.ndarray | None]:
    """IDs (int64) and, if every file has a ``time`` column, discharge times [s].

    The last line of a file may be cut short (a killed run) and is skipped; any other
    malformed row raises DumpFormatError naming file and line."""
    ids: list[np.ndarray] = []
    times: list[np.ndarray] = []
    have_time = True
    for path in paths:
        path = Path(path)
        lines = path.read_text().splitlines()
        header = lines[0].lstrip("#").split() if lines and lines[0].startswith("#") else ["ID", "diameter"]
        time_col = header.index("time") if "time" in header else None
        have_time = have_time and time_col is not None
        rows_id, rows_t = [], []
        for lineno, line in enumerate(lines, start=1):
            if not line.strip() or line.startswith("#"):
                continue
            fields = line.split()
            try:
                rows_id.append(int(fields[0]))
                if time_col is not None:
                    rows_t.append(float(fields[time_col]))
            except (ValueError, IndexError):
                if lineno == len(lines):
                    continue
                raise DumpFormatError(f"{path}: line {lineno}: malformed massflow row {line[:80]!r}") from None
        ids.append(np.asarray(rows_id, dtype=np.int64))
        times.append(np.asarray(rows_t, dtype=float))
    all_ids = np.concatenate(ids) if ids else np.zeros(0, np.int64)
    all_t = np.concatenate(times) if (ids and have_time) else None
    return all_ids, all_t


def latest_records(paths: Sequence[Path]) -> tuple[np.ndarray, np.ndarray | None, int]:
    """``(ids, times, duplicates)``: one record per ID, the latest one.

    Parts set aside before a resume (``.upto<step>``) are read first, so that a particle
    listed both there (discharged just after the restart step, within the file's 4-digit
    time resolution) and in the resumed run's files keeps the resumed run's record."""
    ordered = sorted(paths, key=lambda p: (".upto" not in p.name, p.name))
    ids, times = read_massflow(ordered)
    _, last_index = np.unique(ids[::-1], return_index=True)
    keep = np.sort(ids.size - 1 - last_index)
    return ids[keep], (times[keep] if times is not None else None), int(ids.size - keep.size)
