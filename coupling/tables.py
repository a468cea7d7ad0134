"""Velocity tables: the schema that carries DEM particle velocities to the PBM.

A table holds, for each velocity window k (from ``t[k]`` to ``t[k] + window_s``) and each
compartment (i, j) -- i axial from the inlet, j along y from y = -D/2 -- the means over every
dumped particle seen in that compartment during the window (ratio of sums):

=============  ==========  ===============================================================
dataset        shape       meaning
=============  ==========  ===============================================================
t              (K,)        window start times [s]
x_edges        (NX+1,)     axial compartment edges [m], 0 at the inlet wall
y_edges        (NY+1,)     transverse compartment edges [m], centred on the impeller axis
vx_pos         (K,NX,NY)   mean of max(vx, 0) [m/s]
vx_neg         (K,NX,NY)   mean of max(-vx, 0) [m/s]
vy_pos         (K,NX,NY)   mean of max(vy, 0) [m/s]
vy_neg         (K,NX,NY)   mean of max(-vy, 0) [m/s]
count_A        (K,NX,NY)   mean number of A particles in the compartment per snapshot
count_B        (K,NX,NY)   mean number of B particles in the compartment per snapshot
n_samples      (K,NX,NY)   particle-snapshots behind the velocity means (int)
rate_x_pos     (K,NX,NY)   optional: measured rate of moves (i,j) -> (i+1,j) [1/s per
                           particle]; for the last slice, the discharge rate
rate_x_neg     (K,NX,NY)   optional: measured rate of moves (i,j) -> (i-1,j) [1/s]
rate_y_pos     (K,NX,NY)   optional: measured rate of moves (i,j) -> (i,j+1) [1/s]
rate_y_neg     (K,NX,NY)   optional: measured rate of moves (i,j) -> (i,j-1) [1/s]
=============  ==========  ===============================================================

The four ``rate_*`` datasets (schema 2) are measured by the DEM post-processing from
ID-tracked transitions between dumps; they have the layout and meaning of vx_pos/dx,
vx_neg/dx, vy_pos/dy and vy_neg/dy. A table carries all four or none
(:attr:`VelocityTable.has_rates`). NaN marks a rate not measured (too few observations):
the PBM fills it (``pbm.model.fill_missing_rates``) by the rule that fills missing
velocities. Rates through a wall (x_neg of slice 0, y_neg of j = 0, y_pos of j = NY-1)
are 0: no transition crosses a wall.

Root attributes of the group: ``schema_version`` (written: this module's :data:`SCHEMA_VERSION`;
read: any of :data:`READABLE_VERSIONS`),
``window_s``, ``min_samples`` (a compartment-window with fewer samples carries no velocity
information: see :attr:`VelocityTable.valid`), ``units`` (JSON) and free provenance
(``input_hash``, ``liggghts_version``, ``preset``, ``created``...).

Velocities of compartments without samples are stored as 0 *and* flagged by ``n_samples``;
the PBM decides how to fill them, never reading the 0 as a measured velocity.

Versions: every table is written as version 2, with the rate datasets only when it has
rates. A version-2 file without them holds exactly what a version-1 file holds, so
version-1 files (which never carry rates) are still read.

Schema 3 adds one optional subgroup, ``phases``: the hidden-phase transport model
(:class:`coupling.phases.PhaseTransport`, fitted by :mod:`dem.phases`) with datasets
``phase_rates`` (K, 4, NX, NY) [1/s], ``phase_switching`` (K, K, NX, NY) [1/s],
``phase_entry`` (2, K) [-] and attributes ``interval_s`` (the dump interval it was fitted
at) and ``attrs`` (JSON provenance). Only a table that carries it is written as version 3;
every other table is still written as version 2, byte for byte as before.

The optional root attribute ``operating_point`` (JSON, :class:`coupling.operating.OperatingPoint`)
records the speed, feed rates, blender, blade stations, size classes and feed zones the
table was measured at. It adds no dataset and changes no other, so it needs no new schema
version: a reader that does not know it sees one more provenance attribute.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from coupling import phases as phase_model
from coupling.errors import TableError, os_reason
from coupling.files import DIGEST_ATTR, FORMAT_ATTR, h5_digest, open_verified_h5, read_dataset, replace_file
from coupling.operating import ATTR as OPERATING_ATTR
from coupling.operating import OperatingPoint
from coupling.phases import MAX_RATE_PER_S, PhaseTransport

SCHEMA_VERSION = 2
#: the version of a table that carries the hidden-phase model (its ``phases`` subgroup)
PHASES_SCHEMA_VERSION = 3
READABLE_VERSIONS = (1, 2, 3)
PHASES_GROUP = "phases"
GROUP = "velocity_table"
#: Root attribute ``format`` of a table file written by :func:`write_table` (it also carries
#: the ``sha256`` digest of :func:`coupling.files.h5_digest`).
TABLE_FORMAT = "pbmdem-table"
#: Physical bounds on a table's values, beyond which it is a corrupted file or a unit error,
#: not a blender. Speeds: 100 m/s is 45x the fastest particle of these runs (2.2 m/s, smoke
#: preset) and 75x the blade-tip speed of the paper's 250 rpm in a 100 mm barrel (1.3 m/s);
#: a bladed powder blender with particles at 100 m/s is not a granular flow any DEM here
#: resolves. Rates: :data:`coupling.phases.MAX_RATE_PER_S`. Sizes: compartment edges within 1 km, window times within
#: 1e9 s (32 years), counts and samples below 2**53 (exact in float64).
MAX_SPEED_M_S = 100.0
MAX_EDGE_M = 1e3
MAX_TIME_S = 1e9
MAX_COUNT = float(2**53)
VELOCITY_NAMES = ("vx_pos", "vx_neg", "vy_pos", "vy_neg")
# In the order of VELOCITY_NAMES: rate_x_pos plays the role of vx_pos / dx, and so on.
RATE_NAMES = ("rate_x_pos", "rate_x_neg", "rate_y_pos", "rate_y_neg")
FIELD_NAMES = (*VELOCITY_NAMES, "count_A", "count_B", "n_samples")
UNITS = {
    "t": "s",
    "x_edges": "m",
    "y_edges": "m",
    **{name: "m/s" for name in VELOCITY_NAMES},
    "count_A": "particles",
    "count_B": "particles",
    "n_samples": "particle-snapshots",
    **{name: "1/s" for name in RATE_NAMES},
    "window_s": "s",
}


@dataclass(frozen=True)
class VelocityTable:
    """Compartment velocities per window; validated on construction (raises TableError)."""

    t: np.ndarray
    x_edges: np.ndarray
    y_edges: np.ndarray
    vx_pos: np.ndarray
    vx_neg: np.ndarray
    vy_pos: np.ndarray
    vy_neg: np.ndarray
    count_A: np.ndarray
    count_B: np.ndarray
    n_samples: np.ndarray
    window_s: float
    min_samples: int = 1
    attrs: dict[str, Any] = field(default_factory=dict)
    rate_x_pos: np.ndarray | None = None
    rate_x_neg: np.ndarray | None = None
    rate_y_pos: np.ndarray | None = None
    rate_y_neg: np.ndarray | None = None
    #: the hidden-phase transport model (schema 3), time-invariant; None without it
    phases: PhaseTransport | None = None
    #: the speed, feed and blender the table was measured at; None when unknown (a
    #: synthetic table, or a file written before it was recorded)
    operating_point: OperatingPoint | None = None

    def __post_init__(self) -> None:
        present = [name for name in RATE_NAMES if getattr(self, name) is not None]
        for name in ("t", "x_edges", "y_edges", *VELOCITY_NAMES, "count_A", "count_B", *present):
            object.__setattr__(self, name, np.ascontiguousarray(getattr(self, name), dtype=float))
        object.__setattr__(self, "n_samples", np.ascontiguousarray(self.n_samples, dtype=np.int64))
        object.__setattr__(self, "window_s", float(self.window_s))
        object.__setattr__(self, "min_samples", int(self.min_samples))
        _validate(self)

    @property
    def has_phases(self) -> bool:
        """The table carries a hidden-phase transport model (schema 3)."""
        return self.phases is not None

    @property
    def has_rates(self) -> bool:
        """The table carries the four measured transition rates (schema 2, :data:`RATE_NAMES`)."""
        return self.rate_x_pos is not None

    @property
    def nx(self) -> int:
        return self.x_edges.size - 1

    @property
    def ny(self) -> int:
        return self.y_edges.size - 1

    @property
    def n_windows(self) -> int:
        return self.t.size

    @property
    def dx(self) -> np.ndarray:
        """Axial compartment widths [m], shape (NX,)."""
        return np.diff(self.x_edges)

    @property
    def dy(self) -> np.ndarray:
        """Transverse compartment widths [m], shape (NY,)."""
        return np.diff(self.y_edges)

    @property
    def t_end(self) -> float:
        """End of the last window [s]."""
        return float(self.t[-1] + self.window_s)

    @property
    def valid(self) -> np.ndarray:
        """(K, NX, NY) bool: the compartment-window has enough samples to trust its velocity."""
        return self.n_samples >= self.min_samples

    def window_index(self, time_s: float) -> int:
        """Index of the window in force at ``time_s`` (the last one beyond the table's end)."""
        return int(np.clip(np.searchsorted(self.t, time_s, side="right") - 1, 0, self.n_windows - 1))

    def replace(self, **changes: Any) -> VelocityTable:
        """A copy with some fields changed, validated again."""
        return replace(self, **changes)


def _validate(table: VelocityTable) -> None:
    t = table.t
    if t.ndim != 1 or t.size == 0:
        raise TableError(f"dataset 't' must be a non-empty 1-D array of window start times, got shape {t.shape}")
    if not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
        raise TableError(f"dataset 't' must be finite and strictly increasing, got {t[:6]}...")
    if np.abs(t).max() > MAX_TIME_S:
        raise TableError(
            f"dataset 't' holds {t[np.argmax(np.abs(t))]:.6g} s; window times within {MAX_TIME_S:g} s are valid"
        )
    if not (np.isfinite(table.window_s) and 0 < table.window_s <= MAX_TIME_S):
        raise TableError(f"attribute 'window_s' must be > 0 s (and at most {MAX_TIME_S:g} s), got {table.window_s}")
    if table.min_samples < 1:
        raise TableError(f"attribute 'min_samples' must be >= 1, got {table.min_samples}")
    for name in ("x_edges", "y_edges"):
        edges = getattr(table, name)
        if edges.ndim != 1 or edges.size < 2:
            raise TableError(f"dataset '{name}' must be 1-D with at least 2 edges, got shape {edges.shape}")
        if not np.all(np.isfinite(edges)) or np.any(np.diff(edges) <= 0):
            raise TableError(f"dataset '{name}' must be finite and strictly increasing, got {edges}")
        if np.abs(edges).max() > MAX_EDGE_M:
            raise TableError(
                f"dataset '{name}' holds {edges[np.argmax(np.abs(edges))]:.6g} m; compartment edges "
                f"within {MAX_EDGE_M:g} m are valid"
            )
    shape = (t.size, table.x_edges.size - 1, table.y_edges.size - 1)
    for name in FIELD_NAMES:
        velocity = name in VELOCITY_NAMES
        _check_values(
            name,
            getattr(table, name),
            shape,
            False,
            MAX_SPEED_M_S if velocity else MAX_COUNT,
            "m/s" if velocity else "",
        )
    present = [name for name in RATE_NAMES if getattr(table, name) is not None]
    if present and len(present) < len(RATE_NAMES):
        missing = [name for name in RATE_NAMES if name not in present]
        raise TableError(
            f"dataset(s) {missing} missing while {present} are given; a table carries all four "
            f"measured rates {RATE_NAMES} or none"
        )
    for name in present:
        # NaN is how the DEM post-processing marks a rate it observed too few transitions for.
        _check_values(name, getattr(table, name), shape, True, MAX_RATE_PER_S, "/s")
    point = table.operating_point
    if point is not None and not np.isclose(table.x_edges[-1], point.length_m, rtol=1e-9, atol=0):
        raise TableError(
            f"the operating point's blender is {point.length_m:.6g} m long but the compartments end at "
            f"x = {table.x_edges[-1]:.6g} m; a table's last edge is the weir"
        )
    if table.phases is not None and (table.phases.nx, table.phases.ny) != shape[1:]:
        raise TableError(
            f"the phase model's grid {table.phases.nx}x{table.phases.ny} differs from the table's {shape[1]}x{shape[2]}"
        )


def _check_values(
    name: str, values: np.ndarray, shape: tuple[int, ...], nan_allowed: bool, bound: float, unit: str
) -> None:
    """Every entry in [0, ``bound``] (NaN too where ``nan_allowed``): one pass over the
    values, which every table derived in a design search pays; the first problem is then
    named by :func:`_check_field` and :func:`_check_bound`."""
    if values.shape == shape:
        with np.errstate(invalid="ignore"):
            good = (values >= 0) & (values <= bound)
        if nan_allowed:
            good |= np.isnan(values)
        if good.all():
            return
    _check_field(name, values, shape, nan_allowed)
    _check_bound(name, values, bound, unit)


def _check_bound(name: str, values: np.ndarray, bound: float, unit: str) -> None:
    """Refuse a value beyond the physical bound of its dataset (module constants)."""
    with np.errstate(invalid="ignore"):
        over = values > bound
    if over.any():
        k, i, j = np.argwhere(over)[0]
        raise TableError(
            f"dataset '{name}' holds {values[k, i, j]:.6g}{' ' + unit if unit else ''} in window {k}, compartment "
            f"({i}, {j}); values up to {bound:g}{' ' + unit if unit else ''} are physical (coupling.tables bounds)"
        )


def check_motion(table: VelocityTable, source: str = "") -> None:
    """Refuse a table in which nothing moves: every velocity of every compartment-window
    with enough samples is 0. A DEM of a turning blender never
    gives that; it is an emptied or overwritten file, and the PBM would hold the feed forever
    (the velocity rule) -- measured rates beside such velocities come from no DEM either."""
    where = f" in {source}" if source else ""
    valid = table.valid
    if not valid.any():
        raise TableError(
            f"no compartment-window has min_samples = {table.min_samples} samples{where}: "
            "the table carries no velocity information"
        )
    moving = any(np.any(getattr(table, name)[valid] > 0) for name in VELOCITY_NAMES)
    if not moving:
        raise TableError(
            f"every velocity is 0 in all {int(valid.sum())} compartment-windows with samples{where}: "
            "a table of a moving blender needs some velocities > 0"
        )


def _check_field(name: str, values: np.ndarray, shape: tuple[int, ...], nan_allowed: bool) -> None:
    if values.shape != shape:
        raise TableError(
            f"dataset '{name}' has shape {values.shape}; expected (K, NX, NY) = {shape} "
            "from 't', 'x_edges' and 'y_edges'"
        )
    if nan_allowed and np.any(np.isinf(values)):
        raise TableError(f"dataset '{name}' contains infinite values; every entry must be finite or NaN (not measured)")
    if not nan_allowed and not np.all(np.isfinite(values)):
        raise TableError(f"dataset '{name}' contains NaN or infinite values; every entry must be finite")
    if np.any(values < 0):
        k, i, j = np.argwhere(values < 0)[0]
        raise TableError(
            f"dataset '{name}' must be >= 0 everywhere; window {k}, compartment ({i}, {j}) holds {values[k, i, j]}"
        )


def make_table(
    t,
    x_edges,
    y_edges,
    vx_pos,
    vx_neg,
    vy_pos,
    vy_neg,
    count_A=None,
    count_B=None,
    n_samples=None,
    window_s: float | None = None,
    min_samples: int = 1,
    attrs: dict[str, Any] | None = None,
    rate_x_pos=None,
    rate_x_neg=None,
    rate_y_pos=None,
    rate_y_neg=None,
) -> VelocityTable:
    """Build a table from arrays; scalars and (NX, NY) arrays are broadcast to every window.

    Missing counts default to 0 and missing ``n_samples`` to ``min_samples`` (every
    compartment-window trusted), which is what synthetic tables for tests and studies want.
    ``window_s`` defaults to the spacing of ``t`` (1 s for a single window). The measured
    rates are given all four or none (None: a table without rates); NaN marks "not measured".
    """
    t = np.atleast_1d(np.asarray(t, dtype=float))
    x_edges = np.asarray(x_edges, dtype=float)
    y_edges = np.asarray(y_edges, dtype=float)
    shape = (t.size, x_edges.size - 1, y_edges.size - 1)
    if window_s is None:
        window_s = float(t[1] - t[0]) if t.size > 1 else 1.0

    def full(value, default):
        value = default if value is None else value
        try:
            return np.broadcast_to(np.asarray(value, dtype=float), shape).copy()
        except ValueError as exc:
            raise TableError(f"cannot broadcast an array of shape {np.shape(value)} to (K, NX, NY) = {shape}") from exc

    return VelocityTable(
        t=t,
        x_edges=x_edges,
        y_edges=y_edges,
        vx_pos=full(vx_pos, 0.0),
        vx_neg=full(vx_neg, 0.0),
        vy_pos=full(vy_pos, 0.0),
        vy_neg=full(vy_neg, 0.0),
        count_A=full(count_A, 0.0),
        count_B=full(count_B, 0.0),
        n_samples=full(n_samples, min_samples).astype(np.int64),
        window_s=window_s,
        min_samples=min_samples,
        attrs=dict(attrs or {}),
        **{
            name: None if value is None else full(value, np.nan)
            for name, value in zip(RATE_NAMES, (rate_x_pos, rate_x_neg, rate_y_pos, rate_y_neg))
        },
    )


def table_to_group(group: h5py.Group, table: VelocityTable) -> None:
    """Write ``table`` into an open HDF5 group (datasets and attributes)."""
    group.create_dataset("t", data=table.t)
    group.create_dataset("x_edges", data=table.x_edges)
    group.create_dataset("y_edges", data=table.y_edges)
    for name in FIELD_NAMES + (RATE_NAMES if table.has_rates else ()):
        group.create_dataset(name, data=getattr(table, name), compression="gzip", shuffle=True)
    for key, value in table.attrs.items():
        group.attrs[key] = _attr_value(value)
    group.attrs["schema_version"] = SCHEMA_VERSION
    if table.phases is not None:
        sub = group.create_group(PHASES_GROUP)
        for name, values in phase_model.to_arrays(table.phases).items():
            sub.create_dataset(name, data=values)
        sub.attrs["interval_s"] = table.phases.interval_s
        sub.attrs["attrs"] = json.dumps(table.phases.attrs, sort_keys=True, default=str)
        group.attrs["schema_version"] = PHASES_SCHEMA_VERSION
    group.attrs["window_s"] = table.window_s
    group.attrs["min_samples"] = table.min_samples
    group.attrs["units"] = json.dumps(UNITS)
    if table.operating_point is not None:
        group.attrs[OPERATING_ATTR] = table.operating_point.to_json()


def table_from_group(group: h5py.Group, source: str = "", values: dict | None = None) -> VelocityTable:
    """Read and validate a table from an open HDF5 group; raises TableError naming what is
    wrong. ``values``: datasets already read, keyed by their path (a digest check's), taken
    from there rather than read again."""
    where = f" in {source}" if source else ""

    version = group.attrs.get("schema_version")
    if version is None:
        raise TableError(f"attribute 'schema_version' is missing{where}; this is not a velocity table")
    if isinstance(version, (bool, np.bool_)) or not isinstance(version, (int, np.integer)):
        raise TableError(
            f"attribute 'schema_version' = {_attr_python(version)!r} ({type(version).__name__}){where} is not an "
            f"integer; valid versions: {READABLE_VERSIONS}"
        )
    if int(version) not in READABLE_VERSIONS:
        raise TableError(
            f"unknown velocity-table schema_version {int(version)}{where}; this version reads {READABLE_VERSIONS}"
        )
    arrays = {}
    for name in ("t", "x_edges", "y_edges", *FIELD_NAMES):
        if name not in group:
            raise TableError(
                f"dataset '{name}' is missing{where}; a velocity table needs {('t', 'x_edges', 'y_edges', *FIELD_NAMES)}"
            )
        arrays[name] = read_dataset(group[name], values)
    # Version 1 predates the rates; in version 2 they are optional, and VelocityTable
    # refuses a partial set by name.
    if int(version) >= 2:
        arrays.update({name: read_dataset(group[name], values) for name in RATE_NAMES if name in group})
    for name in ("window_s", "min_samples"):
        if name not in group.attrs:
            raise TableError(f"attribute '{name}' is missing{where}")
    if int(version) >= 3 and PHASES_GROUP in group:
        arrays["phases"] = _phases_from_group(group[PHASES_GROUP], where, values)
    if OPERATING_ATTR in group.attrs:
        arrays["operating_point"] = OperatingPoint.from_json(_attr_text(group.attrs[OPERATING_ATTR]), source)
    reserved = {"schema_version", "window_s", "min_samples", "units", OPERATING_ATTR}
    attrs = {k: _attr_python(v) for k, v in group.attrs.items() if k not in reserved}
    min_samples = group.attrs["min_samples"]
    if isinstance(min_samples, (bool, np.bool_)) or not isinstance(min_samples, (int, np.integer)):
        raise TableError(
            f"attribute 'min_samples' = {_attr_python(min_samples)!r}{where} is not an integer; "
            "an integer >= 1 is needed"
        )
    try:
        table = VelocityTable(
            **arrays,
            window_s=float(group.attrs["window_s"]),
            min_samples=int(min_samples),
            attrs=attrs,
        )
    except TableError as exc:
        raise TableError(f"{exc}{where}") from None
    check_motion(table, source)
    return table


def _phases_from_group(sub: h5py.Group, where: str, values: dict | None) -> PhaseTransport:
    names = ("phase_rates", "phase_switching", "phase_entry")
    missing = [name for name in names if name not in sub]
    if missing:
        raise TableError(f"dataset(s) {missing} of the '{PHASES_GROUP}' subgroup are missing{where}")
    attrs = _attr_python(sub.attrs.get("attrs", "{}"))  # JSON text -> dict
    try:
        return phase_model.from_arrays(
            {name: read_dataset(sub[name], values) for name in names},
            float(sub.attrs.get("interval_s", np.nan)),
            attrs if isinstance(attrs, dict) else {},
        )
    except TableError as exc:
        raise TableError(f"{exc}{where}") from None


def write_table(path: str | os.PathLike, table: VelocityTable) -> Path:
    """Write ``table`` to a new HDF5 file atomically (temporary file, then rename)."""
    path = Path(path)
    try:
        with atomic_h5(path, "velocity table") as h5:
            table_to_group(h5.create_group(GROUP), table)
            h5.attrs[FORMAT_ATTR] = TABLE_FORMAT
            h5.attrs[DIGEST_ATTR] = h5_digest(h5)  # last: over everything written above
    except OSError as exc:
        raise TableError(f"cannot write velocity table {path}: {os_reason(exc)}") from exc
    return path


def read_table(path: str | os.PathLike) -> VelocityTable:
    """Read the velocity table stored in ``path`` (its ``velocity_table`` group): a table
    file or a cache / results file (:mod:`coupling.cache`). The file goes through the one
    verified loader (:func:`coupling.files.open_verified_h5`): a regular file, its digest
    checked when it has one (every file this project writes does; a digest mismatch is
    refused naming the file). Raises TableError naming the file and the problem."""
    path = Path(path)
    try:
        with open_verified_h5(path, "velocity table file", TableError) as h5:
            if GROUP not in h5:
                raise TableError(f"{path} has no '{GROUP}' group; groups present: {sorted(h5.keys())}")
            return table_from_group(h5[GROUP], source=str(path))
    except TableError:
        raise
    except Exception as exc:  # noqa: BLE001 - h5py and numpy raise many types on damaged files
        # RuntimeError ("bad local heap signature"), KeyError, ValueError, UnicodeDecodeError...
        # from a damaged file all mean the same: this file holds no usable table.
        raise TableError(f"{path} is corrupt or unreadable: {type(exc).__name__}: {exc}") from exc


class atomic_h5:
    """Context manager: a new HDF5 file for ``path``, an h5py.File the block fills, built in
    memory (HDF5's core driver) and written by :func:`coupling.files.replace_file` only when
    the block finishes without an exception. HDF5 never writes to the disk itself: a write
    of its that failed (a full disk, ``ulimit -f``) left handles it could not close and the
    process died closing them (exit 139), and the image's size is the exact size the free
    space is checked against. The in-memory file is closed before any error propagates.
    ``what`` names the file in a refusal ("velocity table", "results file")."""

    def __init__(self, path: Path, what: str = "HDF5 file"):
        self.path = Path(path)
        self.what = what

    def __enter__(self) -> h5py.File:
        # the name only identifies the in-memory file within HDF5 (backing_store=False)
        self.h5 = h5py.File(f"{self.path}.{os.getpid()}.{id(self)}.mem", "w", driver="core", backing_store=False)
        return self.h5

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            if exc_type is None:
                self.h5.flush()
                image = self.h5.id.get_file_image()
        finally:
            self.h5.close()
        if exc_type is None:
            replace_file(self.path, image, self.what)


def _attr_value(value: Any) -> Any:
    if isinstance(value, (dict, list, tuple)):
        return json.dumps(value, sort_keys=True, default=str)
    if value is None:
        return "null"
    return value


def _attr_text(value: Any) -> str:
    return value.decode() if isinstance(value, bytes) else str(value)


def _attr_python(value: Any) -> Any:
    if isinstance(value, bytes):
        value = value.decode()
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, str) and value[:1] in "[{":
        try:
            return json.loads(value)
        except json.JSONDecodeError:
            return value
    return value
