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

    /                      attrs: head_sha256, then sha256 (written after everything else,
                                  see below)

Writes are atomic and locked (:func:`coupling.files.replace_file`: the file built in memory,
written to a temporary beside it and renamed into place under the file's lock). A file that
is unreadable, foreign (another format or version), for another key, incomplete, without a
digest or whose digest does not match raises :class:`~coupling.errors.CacheError` from
:func:`load_entry`, and so does any other failure while reading it, whatever its type;
:func:`try_load_entry` turns that into "absent" so the caller rebuilds it.

Integrity: the root attribute ``sha256`` is the SHA-256 of a canonical serialisation of the
whole file as h5py reads it -- every group, every dataset's dtype, shape and bytes, and
every attribute's name and value, walked in sorted order, each item length-prefixed --
except the digests themselves. :func:`load_entry` recomputes it from the open file and
compares before parsing anything. The root attribute ``head_sha256`` is the same over the
head alone (the root's attributes, ``/velocity_table``, the attributes of ``/results``):
:func:`load_head` checks it and reads nothing else, so a reader of the tables alone does
not decompress the per-particle records (most of the file); a file written before it
existed is checked whole. HDF5's own ``fletcher32`` filter was not chosen because it covers
only the chunks of a dataset's data: attributes, where the summary and provenance JSON and
the table's ``window_s``/``min_samples`` live, and the object headers that give a dataset
its dtype and shape are outside it. Measured on 300 seeded damaged copies of the shipped
reference file (100 each of 1-8 bit flips, truncations, 1-512-byte garbage blocks): with no
check 30 loaded with changed data; with ``fletcher32`` on every dataset 0 did, but only
because random offsets rarely land in the attributes (a few hundred bytes of 350 kB): a
digit changed inside the summary JSON loads silently with it and is refused by the digest
(tests/coupling/test_cache_corruption.py); with the digest 0 did, and every other file raised CacheError.
"""

from __future__ import annotations

import hashlib
import json
import os
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import h5py
import numpy as np

from coupling.errors import CacheError, os_reason
from coupling.files import (
    DIGEST_ATTR,
    HEAD_DIGEST_ATTR,
    h5_digest,
    h5_head_digest,
    read_dataset,
    regular_file,
    stored_digest,
)
from coupling.jsonable import dumps_exact
from coupling.tables import GROUP as TABLE_GROUP
from coupling.tables import VelocityTable, atomic_h5, table_from_group, table_to_group

if TYPE_CHECKING:
    import pandas as pd

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
    #: the file it was read from (not stored): what the side that parses the parts names
    #: when one of them is wrong
    source: str = field(default="", compare=False)

    @property
    def key(self) -> str:
        return str(self.provenance.get("key", ""))


def _compressed(data) -> dict:
    """gzip for the datasets HDF5 can chunk: per-particle records and transition counts are
    most of an entry and compress several times (scalars and empty arrays cannot be)."""
    data = np.asarray(data)
    return {"compression": "gzip", "shuffle": True} if data.ndim and data.size else {}


def save_entry(path: str | os.PathLike, entry: CacheEntry) -> Path:
    """Write ``entry`` atomically to ``path``."""
    path = Path(path)
    if not entry.key:
        raise CacheError("provenance must carry the input hash under 'key'")
    try:
        with atomic_h5(path, "results file") as h5:
            table_to_group(h5.create_group(TABLE_GROUP), entry.table)
            group = h5.create_group(RESULTS_GROUP)
            group.attrs["summary"] = dumps_exact(entry.summary)
            frames = group.create_group("frames")
            for name, frame in entry.frames.items():
                sub = frames.create_group(name)
                sub.attrs["columns"] = json.dumps([str(c) for c in frame.columns])
                for column in frame.columns:
                    sub.create_dataset(
                        str(column), data=frame[column].to_numpy(), **_compressed(frame[column].to_numpy())
                    )
            arrays = group.create_group("arrays")
            for name, values in entry.arrays.items():
                arrays.create_dataset(name, data=np.asarray(values), **_compressed(values))
            h5.attrs["format"] = CACHE_FORMAT
            h5.attrs["format_version"] = CACHE_FORMAT_VERSION
            h5.attrs["key"] = entry.key
            h5.attrs["provenance"] = dumps_exact(entry.provenance)
            h5.attrs["complete"] = True  # a file without it was never finished
            # over what was just written, read back through h5py: the same path load_entry takes
            h5.attrs[HEAD_DIGEST_ATTR] = head_digest(h5)
            h5.attrs[DIGEST_ATTR] = file_digest(h5)
    except OSError as exc:
        raise CacheError(f"cannot write cache file {path}: {os_reason(exc)}") from exc
    return path


def load_entry(path: str | os.PathLike, key: str | None = None) -> CacheEntry:
    """Read the entry in ``path``. Raises CacheError naming the problem if the file is
    missing, corrupt, foreign, incomplete or (when ``key`` is given) for other inputs."""
    import pandas as pd  # here: a reader of the head alone (:func:`load_head`) need not import it

    with _open_entry(path) as h5:
        values: dict = {}
        _check_whole(h5, path, values)
        head = _head(h5, path, key, values)
        group = h5[RESULTS_GROUP]
        frames = {}
        for name, sub in group["frames"].items():
            columns = json.loads(sub.attrs["columns"])
            frames[name] = pd.DataFrame({c: read_dataset(sub[c], values) for c in columns}, columns=columns)
        arrays = {name: read_dataset(data, values) for name, data in group["arrays"].items()}
    return CacheEntry(head.table, head.summary, frames, arrays, head.provenance, source=str(path))


def load_head(path: str | os.PathLike, key: str | None = None) -> CacheHead:
    """The table, summary and provenance of the entry in ``path``, without reading its
    frames and arrays (the per-particle records, most of the file): checked against the
    file's head digest, or, in a file written before it existed, against the whole file's.
    Raises CacheError as :func:`load_entry` does."""
    with _open_entry(path) as h5:
        stored = stored_digest(h5, HEAD_DIGEST_ATTR)
        values: dict = {}
        if stored is not None:
            _check(stored, head_digest(h5, values), HEAD_DIGEST_ATTR, path)
        else:
            _check_whole(h5, path, values)
        return _head(h5, path, key, values)


@dataclass(frozen=True)
class CacheHead:
    """The parts of an entry that :func:`load_head` reads."""

    table: VelocityTable
    summary: dict[str, Any]
    provenance: dict[str, Any]


@contextmanager
def _open_entry(path: str | os.PathLike):
    """The open cache file, its format, version and completeness checked; any failure
    inside the block that is not a CacheError becomes one naming the file."""
    # a directory, a FIFO (would block), a device or a symlink loop: refused by name
    path = regular_file(path, "cache file", CacheError)
    try:
        with h5py.File(path, "r") as h5:
            if h5.attrs.get("format") != CACHE_FORMAT:
                raise CacheError(f"{path} is not a pbmdem cache file (format {h5.attrs.get('format')!r})")
            version = int(h5.attrs.get("format_version", -1))
            if version != CACHE_FORMAT_VERSION:
                raise CacheError(
                    f"{path} has cache format_version {version}; this version reads {CACHE_FORMAT_VERSION}"
                )
            if not bool(h5.attrs.get("complete", False)):
                raise CacheError(f"{path} is incomplete (never finished writing)")
            yield h5
    except CacheError:
        raise
    except Exception as exc:  # noqa: BLE001 - h5py and numpy raise many types on damaged files
        # A damaged file surfaces as any of OSError, RuntimeError ("bad local heap
        # signature"), KeyError, ValueError, UnicodeDecodeError, TableError...; every one
        # means the same thing to the caller: do not trust this file.
        raise CacheError(f"{path} is corrupt or unreadable: {type(exc).__name__}: {exc}") from exc


def _check_whole(h5, path, values: dict) -> None:
    """The whole file's digest checked (``values`` receives what the check read)."""
    stored = stored_digest(h5)
    if stored is None:
        raise CacheError(f"{path} carries no '{DIGEST_ATTR}' integrity digest (written before digests existed)")
    _check(stored, file_digest(h5, values), DIGEST_ATTR, path)


def _check(stored: str, actual: str, name: str, path) -> None:
    if stored != actual:
        raise CacheError(
            f"{path} is corrupt or was edited: its content does not match its {name} digest; regenerate it"
        )


def _head(h5, path, key: str | None, values: dict) -> CacheHead:
    """The head of an open entry whose digest was checked (``values``: what the check read)."""
    stored_key = str(h5.attrs.get("key"))
    if key is not None and stored_key != key:
        raise CacheError(f"{path} holds results for inputs {stored_key}, not {key}")
    if TABLE_GROUP not in h5 or RESULTS_GROUP not in h5:
        raise CacheError(f"{path} lacks the '{TABLE_GROUP}' or '{RESULTS_GROUP}' group")
    provenance = json.loads(h5.attrs["provenance"])
    table = table_from_group(h5[TABLE_GROUP], source=str(path), values=values)
    summary = json.loads(h5[RESULTS_GROUP].attrs["summary"])
    return CacheHead(table, summary, provenance)


def head_digest(h5: h5py.File, values: dict | None = None) -> str:
    """SHA-256 (hex) of an open cache file's head: the root's attributes, the velocity table
    and the results' summary (:func:`coupling.files.h5_head_digest`)."""
    return h5_head_digest(h5, groups=(TABLE_GROUP,), attributes_of=(RESULTS_GROUP,), values=values)


def file_digest(h5: h5py.File, values: dict | None = None) -> str:
    """SHA-256 (hex) of everything in an open cache file except its digest attribute
    (:func:`coupling.files.h5_digest`, shared with the velocity-table files; ``values``
    receives the datasets it read)."""
    return h5_digest(h5, values)


def try_load_entry(path: str | os.PathLike, key: str | None = None) -> tuple[CacheEntry | None, str]:
    """Like :func:`load_entry` but returns ``(None, reason)`` instead of raising, so a
    corrupt or foreign file is rebuilt rather than trusted. On success ``(entry, "")``."""
    try:
        return load_entry(path, key), ""
    except CacheError as exc:
        return None, str(exc)
