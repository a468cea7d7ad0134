"""Keys for runs and caches, and the results cache.

Keys: a hash of the inputs names the run directory or cache file (signac's recipe), so a
changed input can never be served a stale result.

A cache entry holds one velocity table and the results that came with it, as generic
parts: a JSON summary, named tables of columns (pandas DataFrames) and named arrays. The
side that made the results turns them into these parts and back; this module knows
nothing of what they mean. File layout (one file per key, ``<root>/dem-<key>.h5``)::

    /                      attrs: format = "pbmdem-cache", format_version, key,
                                  provenance (JSON), complete = True (written last)
    /velocity_table        the coupling table (coupling.tables.table_to_group)
    /results               attrs: summary (JSON, NaN kept)
        frames/<name>/<column>   attrs of frames/<name>: columns (JSON, in order)
        arrays/<name>

Writes are atomic (temporary file renamed into place). A file that is unreadable, foreign
(another format or version), for another key, or incomplete raises
:class:`~coupling.errors.CacheError` from :func:`load_entry`; :func:`try_load_entry`
turns that into "absent" so the caller rebuilds it.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pandas as pd

from coupling.errors import CacheError, TableError
from coupling.jsonable import dumps_exact
from coupling.tables import GROUP as TABLE_GROUP
from coupling.tables import VelocityTable, atomic_h5, table_from_group, table_to_group

CACHE_FORMAT = "pbmdem-cache"
CACHE_FORMAT_VERSION = 2
RESULTS_GROUP = "results"


def stable_hash(data: Any, length: int = 16) -> str:
    """Hash of JSON-serialisable data, independent of dict key order."""
    text = json.dumps(data, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:length]


def cache_path(root: str | os.PathLike, key: str) -> Path:
    """Where the entry for input hash ``key`` lives under ``root``."""
    return Path(root) / f"dem-{key}.h5"


@dataclass(frozen=True)
class CacheEntry:
    """One cached result: the velocity table plus generic parts. ``provenance`` must
    carry the entry's input hash under ``key``."""

    table: VelocityTable
    summary: dict[str, Any]
    frames: dict[str, pd.DataFrame] = field(default_factory=dict)
    arrays: dict[str, np.ndarray] = field(default_factory=dict)
    provenance: dict[str, Any] = field(default_factory=dict)

    @property
    def key(self) -> str:
        return str(self.provenance.get("key", ""))


def save_entry(path: str | os.PathLike, entry: CacheEntry) -> Path:
    """Write ``entry`` atomically to ``path``."""
    path = Path(path)
    if not entry.key:
        raise CacheError("provenance must carry the input hash under 'key'")
    try:
        with atomic_h5(path) as h5:
            table_to_group(h5.create_group(TABLE_GROUP), entry.table)
            group = h5.create_group(RESULTS_GROUP)
            group.attrs["summary"] = dumps_exact(entry.summary)
            frames = group.create_group("frames")
            for name, frame in entry.frames.items():
                sub = frames.create_group(name)
                sub.attrs["columns"] = json.dumps([str(c) for c in frame.columns])
                for column in frame.columns:
                    sub.create_dataset(str(column), data=frame[column].to_numpy())
            arrays = group.create_group("arrays")
            for name, values in entry.arrays.items():
                arrays.create_dataset(name, data=np.asarray(values))
            h5.attrs["format"] = CACHE_FORMAT
            h5.attrs["format_version"] = CACHE_FORMAT_VERSION
            h5.attrs["key"] = entry.key
            h5.attrs["provenance"] = dumps_exact(entry.provenance)
            h5.attrs["complete"] = True  # written last: a file without it was never finished
    except OSError as exc:
        raise CacheError(f"cannot write cache file {path}: {exc}") from exc
    return path


def load_entry(path: str | os.PathLike, key: str | None = None) -> CacheEntry:
    """Read the entry in ``path``. Raises CacheError naming the problem if the file is
    missing, corrupt, foreign, incomplete or (when ``key`` is given) for other inputs."""
    path = Path(path)
    if not path.is_file():
        raise CacheError(f"cache file {path} does not exist")
    try:
        with h5py.File(path, "r") as h5:
            if h5.attrs.get("format") != CACHE_FORMAT:
                raise CacheError(f"{path} is not a pbmdem cache file (format {h5.attrs.get('format')!r})")
            version = int(h5.attrs.get("format_version", -1))
            if version != CACHE_FORMAT_VERSION:
                raise CacheError(f"{path} has cache format_version {version}; this version reads {CACHE_FORMAT_VERSION}")
            if not bool(h5.attrs.get("complete", False)):
                raise CacheError(f"{path} is incomplete (never finished writing)")
            stored_key = str(h5.attrs.get("key"))
            if key is not None and stored_key != key:
                raise CacheError(f"{path} holds results for inputs {stored_key}, not {key}")
            provenance = json.loads(h5.attrs["provenance"])
            if TABLE_GROUP not in h5 or RESULTS_GROUP not in h5:
                raise CacheError(f"{path} lacks the '{TABLE_GROUP}' or '{RESULTS_GROUP}' group")
            table = table_from_group(h5[TABLE_GROUP], source=str(path))
            group = h5[RESULTS_GROUP]
            summary = json.loads(group.attrs["summary"])
            frames = {}
            for name, sub in group["frames"].items():
                columns = json.loads(sub.attrs["columns"])
                frames[name] = pd.DataFrame({c: sub[c][()] for c in columns}, columns=columns)
            arrays = {name: data[()] for name, data in group["arrays"].items()}
    except CacheError:
        raise
    except (OSError, KeyError, ValueError, TableError) as exc:
        raise CacheError(f"{path} is corrupt or unreadable: {exc}") from exc
    return CacheEntry(table, summary, frames, arrays, provenance)


def try_load_entry(path: str | os.PathLike, key: str | None = None) -> tuple[CacheEntry | None, str]:
    """Like :func:`load_entry` but returns ``(None, reason)`` instead of raising, so a
    corrupt or foreign file is rebuilt rather than trusted. On success ``(entry, "")``."""
    try:
        return load_entry(path, key), ""
    except CacheError as exc:
        return None, str(exc)
