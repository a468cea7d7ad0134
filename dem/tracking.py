"""Following every particle through the dumps: the one streaming pass of the
post-processing (:func:`accumulate`) and when each particle left (:func:`find_exits`).

Memory is flat in the number of snapshots: per-particle state is a few arrays indexed by
particle ID (IDs are bounded by the number of particles seen, :func:`id_bound`), the
velocity sums one array per window and the compartment counts one small array per
snapshot. The conventions (times, binning, windows, exits) are listed in
:mod:`dem.post`, which runs these steps.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from coupling.compartments import bin_particles
from coupling.errors import DumpFormatError
from coupling.tables import VELOCITY_NAMES
from dem.config import DemConfig
from dem.dumps import iter_snapshots
from dem.massflow import latest_records
from dem.vessel import outside_vessel

REQUIRED_COLUMNS = ("id", "type", "x", "y", "vx", "vy")
#: Bound on particle IDs (see :func:`id_bound`): the per-particle arrays are indexed by ID.
ID_HEADROOM, ID_FACTOR = 1_000_000, 10
#: Bound on a snapshot's time, in sampling intervals: the time series holds one row (and one
#: NX x NY count array) per interval up to the last snapshot. The paper's run is 260 of them.
MAX_SAMPLING_INTERVALS = 100_000
#: Rows of a window's sums: the four velocity parts, particle-snapshots, A and B counts.
SUM_ROWS = (*VELOCITY_NAMES, "n_samples", "count_A", "count_B")
#: the rows of the component counts in a snapshot's sums
COMPONENT_ROWS = slice(SUM_ROWS.index("count_A"), SUM_ROWS.index("count_B") + 1)
#: How a particle's exit was found (:func:`find_exits`).
EXIT_NONE, EXIT_PAST_WEIR, EXIT_MASSFLOW, EXIT_VANISHED = 0, 1, 2, 3


class ParticleLog:
    """Per-particle state indexed by ID, grown by doubling. Times [s]; NaN = not yet.

    States (``last_state``, ``vanish_state``): a flat compartment index c = i * NY + j,
    :func:`outside_state` (past the weir), or -1 (not seen / in no compartment).
    ``last_cell`` is the last compartment a particle was seen in (the compartment it left
    the blender from, once it has exited)."""

    FLOATS = ("first_t", "first_y", "last_t", "last_x", "exit_t", "vanish_t")
    #: integer arrays, -1 = none: states, the snapshot index of the last sight, the window
    #: of the snapshot a particle vanished after
    INTS = ("last_state", "last_cell", "last_snapshot", "vanish_state", "vanish_window")

    def __init__(self) -> None:
        self.size = 0
        for name in self.FLOATS:
            setattr(self, name, np.zeros(0))
        for name in self.INTS:
            setattr(self, name, np.zeros(0, np.int32))
        self.kind = np.zeros(0, np.int8)  # 0 unseen, 1 A, 2 B, 3 other type
        self.scratch = np.zeros(0, bool)
        #: particle-snapshots whose centre lies outside the vessel (dem.vessel): a warning
        self.outside_vessel = 0

    def ensure(self, max_id: int) -> None:
        if max_id < self.size:
            return
        new = max(1024, 2 * self.size, max_id + 1)
        for name in self.FLOATS:
            grown = np.full(new, np.nan)
            grown[: self.size] = getattr(self, name)
            setattr(self, name, grown)
        for name in self.INTS:
            grown = np.full(new, -1, np.int32)
            grown[: self.size] = getattr(self, name)
            setattr(self, name, grown)
        for name, dtype in (("kind", np.int8), ("scratch", bool)):
            grown = np.zeros(new, dtype)
            grown[: self.size] = getattr(self, name)
            setattr(self, name, grown)
        self.size = new

    @property
    def seen(self) -> np.ndarray:
        return ~np.isnan(self.first_t)


def id_bound(particles_seen: int) -> int:
    """Largest particle ID accepted once ``particles_seen`` particles are known (an ID listed
    twice in one snapshot counts twice, which only loosens the bound).

    The per-particle arrays are indexed by ID (42 bytes per ID up to the largest), which is
    what keeps the streaming pass a few vector operations per snapshot. LIGGGHTS numbers
    inserted particles 1, 2, 3, ... and never reuses an ID, so the largest ID is about the
    number inserted so far; dumps that start late in a run see fewer particles than that.
    The headroom of 10**6 IDs (at most ~84 MB with the doubling) accepts any such window of
    a run inserting up to a million particles (the paper preset inserts ~520 000 in
    260 s), and the factor 10 larger runs seen sparsely; an ID beyond both is a corrupted
    dump, not a particle, and would otherwise cost memory in proportion to its value.
    """
    return ID_FACTOR * int(particles_seen) + ID_HEADROOM


@dataclass
class Accumulation:
    """What the streaming pass keeps: the particle log, the window sums (window index ->
    (len(SUM_ROWS), NX*NY)), snapshots per window, and per snapshot its time and its
    (2, NX, NY) counts of A and B."""

    particles: ParticleLog
    window_sums: dict[int, np.ndarray]
    #: window index -> flat (S+1)^2 counts of particles in state a at one snapshot and b at
    #: the next (S = NX*NY: past the weir); particles deleted in between are added by
    #: :func:`transition_counts`, which knows who was discharged
    transitions: dict[int, np.ndarray]
    #: the time between consecutive snapshots that the transitions are counted over [s]
    #: (the first gap seen; pairs of snapshots further or closer apart are skipped)
    transition_interval_s: float
    irregular_gaps: int
    window_snapshots: dict[int, int]
    snapshot_t: np.ndarray
    snapshot_counts: np.ndarray
    last_ids: np.ndarray
    last_step: int
    reappeared: int
    other_types: set[int]


def snapshot_sums(cell: np.ndarray, vx: np.ndarray, vy: np.ndarray, is_a: np.ndarray, is_b: np.ndarray,
                  ncell: int) -> np.ndarray:
    """One snapshot's sums per compartment, rows in :data:`SUM_ROWS` order: the velocity
    parts max(+-v, 0) [m/s] of every particle inside (``cell``: its compartment), the
    number of particles, and of A and of B. Their window means are the velocity table."""
    rows = {
        "vx_pos": np.bincount(cell, np.maximum(vx, 0), ncell),
        "vx_neg": np.bincount(cell, np.maximum(-vx, 0), ncell),
        "vy_pos": np.bincount(cell, np.maximum(vy, 0), ncell),
        "vy_neg": np.bincount(cell, np.maximum(-vy, 0), ncell),
        "n_samples": np.bincount(cell, minlength=ncell),
        "count_A": np.bincount(cell[is_a], minlength=ncell),
        "count_B": np.bincount(cell[is_b], minlength=ncell),
    }
    return np.stack([rows[name].astype(float) for name in SUM_ROWS])


def accumulate(dump_paths, config: DemConfig, types_a: Sequence[int], types_b: Sequence[int]) -> Accumulation:
    """Stream every snapshot once into an :class:`Accumulation`."""
    g, tables = config.geometry, config.tables
    dt = float(config.timestep_s)
    length, diameter, nx, ny = float(g.length_m), float(g.diameter_m), int(tables.nx), int(tables.ny)
    window, tol, ncell = float(tables.window_s), 0.5 * dt, nx * ny
    log = ParticleLog()
    window_sums: dict[int, np.ndarray] = {}
    window_snapshots: dict[int, int] = {}
    transitions: dict[int, np.ndarray] = {}
    n_states = ncell + 1
    interval, irregular, prev_t, prev_k = float("nan"), 0, float("nan"), -1
    times: list[float] = []
    counts: list[np.ndarray] = []
    prev_ids = np.zeros(0, np.int64)
    last_step, reappeared, other_types = -1, 0, set()
    n_seen = 0
    max_t = MAX_SAMPLING_INTERVALS * float(tables.sample_interval_s)
    # The reader has checked that ids and types are integers >= 1 and that the columns used
    # here are finite.
    for snap in iter_snapshots(dump_paths, columns=REQUIRED_COLUMNS):
        t = snap.time_s(dt)
        if t > max_t:
            raise DumpFormatError(
                f"{snap.source}: snapshot at step {snap.step} is at t = {t:.6g} s (timestep {dt:.6g} s), beyond "
                f"{MAX_SAMPLING_INTERVALS} sampling intervals ({max_t:.6g} s); a corrupted step, or a timestep "
                "that is not the run's")
        last_step = snap.step
        ids = snap["id"].astype(np.int64)
        ptype = snap["type"].astype(np.int64)
        x, y, vx, vy = snap["x"], snap["y"], snap["vx"], snap["vy"]
        if ids.size:
            top = int(ids.max())
            bound = id_bound(n_seen + ids.size)
            if top > bound:
                row = int(np.argmax(ids))
                raise DumpFormatError(
                    f"{snap.source}: snapshot at step {snap.step}, atom {row + 1} (column 'id'): particle id {top} "
                    f"is implausible; with {n_seen} particles seen before and {ids.size} in this snapshot, ids up "
                    f"to {bound} ({ID_FACTOR} x particles + {ID_HEADROOM}) are accepted (LIGGGHTS numbers "
                    "particles 1, 2, 3, ...)")
            log.ensure(top)
        log.outside_vessel += int(np.count_nonzero(outside_vessel(x, y, snap["z"] if "z" in snap else None, config)))
        is_a, is_b = np.isin(ptype, types_a), np.isin(ptype, types_b)
        if not (is_a | is_b).all():
            other_types.update(int(v) for v in np.unique(ptype[~(is_a | is_b)]))

        new = np.isnan(log.first_t[ids])
        log.first_t[ids[new]] = t
        log.first_y[ids[new]] = y[new]
        n_seen += int(np.count_nonzero(new))  # an id listed twice counts twice: a looser bound, no sort
        log.kind[ids] = np.where(is_a, 1, np.where(is_b, 2, 3))
        back = ~new & ~np.isnan(log.vanish_t[ids])
        if back.any():
            reappeared += int(back.sum())
            log.vanish_t[ids[back]] = np.nan
        k = int(math.floor((t + tol) / window))
        gap = t - prev_t
        if math.isnan(interval) and gap > tol:
            interval = gap
        # dumps every N steps are exactly periodic; 1 % admits step rounding, not a missed dump
        regular = abs(gap - interval) <= max(tol, 0.01 * interval)
        irregular += int(bool(prev_ids.size) and not regular)
        log.scratch[ids] = True
        gone = prev_ids[~log.scratch[prev_ids]]
        log.vanish_t[gone] = t
        log.vanish_state[gone] = log.last_state[gone]
        log.vanish_window[gone] = prev_k if regular else -1
        log.scratch[ids] = False
        prev_ids = ids
        log.last_t[ids] = t
        log.last_x[ids] = x
        past = (x > length) & np.isnan(log.exit_t[ids])
        log.exit_t[ids[past]] = t

        inside, cell = bin_particles(x, y, length, diameter, nx, ny)
        state = np.full(ids.size, -1, np.int32)
        state[inside] = cell
        state[x > length] = ncell
        if regular:
            was = log.last_state[ids]
            moved = (log.last_snapshot[ids] == len(times) - 1) & (was >= 0) & (was < ncell) & (state >= 0)
            pairs = np.bincount(was[moved].astype(np.int64) * n_states + state[moved], minlength=n_states**2)
            if prev_k in transitions:
                transitions[prev_k] += pairs
            else:
                transitions[prev_k] = pairs
        log.last_state[ids] = state
        log.last_snapshot[ids] = len(times)
        log.last_cell[ids[inside]] = cell
        prev_t, prev_k = t, k
        sums = snapshot_sums(cell, vx[inside], vy[inside], is_a[inside], is_b[inside], ncell)
        if k in window_sums:
            window_sums[k] += sums
            window_snapshots[k] += 1
        else:
            window_sums[k], window_snapshots[k] = sums, 1
        times.append(t)
        counts.append(sums[COMPONENT_ROWS].reshape(2, nx, ny).copy())  # the window sums grow in place
    if not times:
        raise DumpFormatError(f"no complete snapshot in {dump_paths!r}")
    return Accumulation(log, window_sums, transitions, interval, irregular, window_snapshots, np.asarray(times),
                        np.stack(counts), prev_ids, last_step, reappeared, other_types)


@dataclass
class Exits:
    """Exit time [s] per ID (NaN: still inside or lost), how it was found (EXIT_*), and
    what the solver's discharge files said (None without them)."""

    time: np.ndarray
    how: np.ndarray
    massflow_discharged: int | None = None
    massflow_discharged_by_last_dump: int | None = None
    massflow_unseen: int = 0
    massflow_duplicates: int = 0
    #: particles still in a dump after the time of their discharge record (beyond the
    #: record's 4 significant digits and half a timestep): a warning
    seen_after_discharge: int = 0

    @property
    def exited(self) -> np.ndarray:
        return self.how != EXIT_NONE


def find_exits(acc: Accumulation, config: DemConfig, massflow_paths: Sequence[Path]) -> Exits:
    """Exit of every particle (module docstring, "Exit of a particle")."""
    log = acc.particles
    seen = log.seen
    exit_t = log.exit_t.copy()
    how = np.full(log.size, EXIT_NONE, np.int8)
    how[seen & ~np.isnan(exit_t)] = EXIT_PAST_WEIR
    vanished = seen & np.isnan(exit_t) & ~np.isnan(log.vanish_t)
    exits = Exits(exit_t, how)
    if not massflow_paths:
        dx = float(config.geometry.length_m) / int(config.tables.nx)
        use = vanished & (log.last_x >= float(config.geometry.length_m) - dx)
        exit_t[use] = log.vanish_t[use]
        how[use] = EXIT_VANISHED
        return exits
    ids, times, exits.massflow_duplicates = latest_records(massflow_paths)
    exits.massflow_discharged = int(ids.size)
    in_range = ids < log.size
    # Compare at the same instant: a particle deleted after the last dump is still in it.
    in_last_dump = np.zeros(ids.size, bool)
    in_last_dump[in_range] = np.isin(ids[in_range], acc.last_ids)
    exits.massflow_discharged_by_last_dump = int((~in_last_dump).sum())
    exits.massflow_unseen = int((~in_range).sum() + (~seen[ids[in_range]]).sum())
    listed = np.zeros(log.size, bool)
    listed[ids[in_range]] = True
    use = vanished & listed
    if times is not None:
        by_id = np.full(log.size, np.nan)
        by_id[ids[in_range]] = times[in_range]
        exit_t[use] = np.clip(by_id[use], log.last_t[use], log.vanish_t[use])
        exits.seen_after_discharge = seen_after_discharge(log.last_t, by_id, float(config.timestep_s))
    else:
        exit_t[use] = log.vanish_t[use]
    how[use] = EXIT_MASSFLOW
    return exits


def seen_after_discharge(last_seen_t: np.ndarray, discharge_t: np.ndarray, timestep_s: float) -> int:
    """How many particles were seen in a dump later than their discharge record: the record
    is written with 4 significant digits (half a unit of the 4th digit of slack) and the
    dump's time is exact to half a timestep."""
    known = np.isfinite(discharge_t) & np.isfinite(last_seen_t)
    t = np.abs(discharge_t[known])
    digits = 0.5 * 10.0 ** (np.floor(np.log10(np.maximum(t, 1e-300))) - 3)
    return int(np.count_nonzero(last_seen_t[known] > discharge_t[known] + digits + 0.5 * timestep_s))


def transition_counts(acc: Accumulation, exits: Exits, n_windows: int, n_cells: int) -> np.ndarray:
    """(K, S+1, S+1) counts of particles in state a at a snapshot of window k and in b at the
    next one (S = ``n_cells``: discharged). A particle deleted by the solver between two
    snapshots moved to S if it was discharged (:func:`find_exits`); one lost is not counted.
    Windows past ``n_windows`` join the last one, as the velocity sums do."""
    n_states = n_cells + 1
    counts = np.zeros((n_windows, n_states * n_states), np.int64)
    for k, pairs in acc.transitions.items():
        counts[min(max(k, 0), n_windows - 1)] += pairs
    log = acc.particles
    left = exits.exited & (log.vanish_window >= 0) & (log.vanish_state >= 0) & (log.vanish_state < n_cells)
    k = np.minimum(log.vanish_window[left], n_windows - 1)
    np.add.at(counts, (k, log.vanish_state[left].astype(np.int64) * n_states + n_cells), 1)
    return counts.reshape(n_windows, n_states, n_states)
