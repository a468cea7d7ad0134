"""Keys for runs and caches, and the DEM results cache.

Keys: a hash of the inputs names the run directory or cache file (signac's recipe), so a
changed input can never be served a stale result.

Cache file (one per DEM input hash, ``<root>/dem-<key>.h5``)::

    /                      attrs: format = "pbmdem-dem-cache", format_version, key,
                                  provenance (JSON: config TOML, input hash, LIGGGHTS
                                  version, dates, wall time...), complete = True
    /velocity_table        the coupling table (coupling.tables.table_to_group)
    /dem_results           attrs: summary (JSON)
        timeseries/<col>   one dataset per column
        holdup/<col>
        rtd/<col>
        rsd_by_slice, rsd_by_slice_floor, residence_times_s

Writes are atomic (temporary file renamed into place). A file that is unreadable, foreign
(another format), for another key, or incomplete raises :class:`~coupling.errors.CacheError`
from :func:`load_dem_results`; :func:`try_load_dem_results` turns that into "absent" so the
caller rebuilds it.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from coupling.errors import CacheError, TableError
from coupling.tables import GROUP as TABLE_GROUP
from coupling.tables import VelocityTable, atomic_h5, table_from_group, table_to_group

CACHE_FORMAT = "pbmdem-dem-cache"
CACHE_FORMAT_VERSION = 1
RESULTS_GROUP = "dem_results"
_FRAMES = ("timeseries", "holdup", "rtd")
_ARRAYS = ("rsd_by_slice", "rsd_by_slice_floor", "residence_times_s")


def stable_hash(data: Any, length: int = 16) -> str:
    """Hash of JSON-serialisable data, independent of dict key order."""
    text = json.dumps(data, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:length]


def file_digest(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    """SHA-256 of a file's bytes (meshes and other binary inputs of a run)."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        while block := handle.read(chunk):
            digest.update(block)
    return digest.hexdigest()


def cache_path(root: str | os.PathLike, key: str) -> Path:
    """Where the DEM results for input hash ``key`` live under ``root``."""
    return Path(root) / f"dem-{key}.h5"


def save_dem_results(path: str | os.PathLike, table: VelocityTable, results, provenance: dict[str, Any]) -> Path:
    """Write the velocity table and the DEM results (a ``dem.post.DemResults`` or any object
    with the same attributes) atomically to ``path``. ``provenance`` must hold ``key``."""
    path = Path(path)
    if "key" not in provenance:
        raise CacheError("provenance must carry the input hash under 'key'")
    try:
        with atomic_h5(path) as h5:
            table_to_group(h5.create_group(TABLE_GROUP), table)
            group = h5.create_group(RESULTS_GROUP)
            group.attrs["summary"] = json.dumps(_jsonable(results.summary), sort_keys=True)
            for name in _FRAMES:
                frame = getattr(results, name)
                sub = group.create_group(name)
                sub.attrs["columns"] = json.dumps(list(frame.columns))
                for column in frame.columns:
                    sub.create_dataset(column, data=frame[column].to_numpy())
            for name in _ARRAYS:
                group.create_dataset(name, data=np.asarray(getattr(results, name), dtype=float))
            h5.attrs["format"] = CACHE_FORMAT
            h5.attrs["format_version"] = CACHE_FORMAT_VERSION
            h5.attrs["key"] = str(provenance["key"])
            h5.attrs["provenance"] = json.dumps(_jsonable(provenance), sort_keys=True)
            h5.attrs["complete"] = True  # written last: a file without it was never finished
    except OSError as exc:
        raise CacheError(f"cannot write cache file {path}: {exc}") from exc
    return path


def load_dem_results(path: str | os.PathLike, key: str | None = None):
    """Read ``(table, results, provenance)`` from a cache file.

    ``results`` is a ``dem.post.DemResults`` (``table`` also set on it). Raises CacheError
    naming the problem if the file is missing, corrupt, foreign, incomplete or (when ``key``
    is given) belongs to other inputs."""
    import pandas as pd

    from dem.post import DemResults  # coupling may know the DEM results' shape, not vice versa

    path = Path(path)
    if not path.is_file():
        raise CacheError(f"cache file {path} does not exist")
    try:
        with h5py.File(path, "r") as h5:
            if h5.attrs.get("format") != CACHE_FORMAT:
                raise CacheError(f"{path} is not a pbmdem DEM cache file (format {h5.attrs.get('format')!r})")
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
            for name in _FRAMES:
                sub = group[name]
                columns = json.loads(sub.attrs["columns"])
                frames[name] = pd.DataFrame({c: sub[c][()] for c in columns}, columns=columns)
            arrays = {name: group[name][()] for name in _ARRAYS}
    except CacheError:
        raise
    except (OSError, KeyError, ValueError, TableError) as exc:
        raise CacheError(f"{path} is corrupt or unreadable: {exc}") from exc
    results = DemResults(table=table, summary=_restore_nan(summary), **frames, **arrays)
    return table, results, provenance


def try_load_dem_results(path: str | os.PathLike, key: str | None = None):
    """Like :func:`load_dem_results` but returns ``(None, reason)`` instead of raising, so a
    corrupt or foreign file is rebuilt rather than trusted. On success ``(loaded, "")``."""
    try:
        return load_dem_results(path, key), ""
    except CacheError as exc:
        return None, str(exc)


def _jsonable(value: Any) -> Any:
    """JSON-safe copy: numpy scalars to Python, NaN/inf to strings (JSON has none)."""
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return {"__float__": repr(value)}
    if isinstance(value, (str, int, float, bool)) or value is None:
        return value
    return str(value)


def _restore_nan(value: Any) -> Any:
    if isinstance(value, dict):
        if set(value) == {"__float__"}:
            return float(value["__float__"])
        return {k: _restore_nan(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_restore_nan(v) for v in value]
    return value
