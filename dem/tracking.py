"""Following every particle through the dumps: the one streaming pass of the
post-processing (:class:`DumpStream`, which can be kept open while a run writes its
dumps) and when each particle left (:func:`find_exits`).

Memory is flat in the number of snapshots: per-particle state is a few arrays indexed by
particle ID (IDs are bounded by the number of particles seen, :func:`id_bound`), the
velocity sums one array per window and the compartment counts one small array per
snapshot. The conventions (times, binning, windows, exits) are listed in
:mod:`dem.post`, which runs these steps.

The one exception to flat memory is optional: with ``record_sequences`` the pass also keeps
every particle's state at every dump (6 bytes per particle-dump: ~36 MB for the reduced
preset's 6e6), from which :func:`compartment_sequences` builds the run-length-encoded
compartment sequences that the hidden-phase transport model is fitted to
(:mod:`dem.phases`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from coupling.compartments import bin_particles
from coupling.errors import DumpFormatError, ResultsError
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

    FLOATS = ("first_t", "first_y", "last_t", "last_x", "exit_t", "vanish_t", "diameter")
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

    def copy(self) -> ParticleLog:
        twin = ParticleLog()
        twin.size, twin.outside_vessel = self.size, self.outside_vessel
        for name in (*self.FLOATS, *self.INTS, "kind", "scratch"):
            setattr(twin, name, getattr(self, name).copy())
        return twin


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
    #: per snapshot (only with ``record_sequences``): the IDs (int32) and their states
    #: (int16: compartment, S past the weir, -1 outside the grid), in dump order
    visits: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)


def snapshot_sums(
    cell: np.ndarray, vx: np.ndarray, vy: np.ndarray, is_a: np.ndarray, is_b: np.ndarray, ncell: int
) -> np.ndarray:
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


class DumpStream:
    """The streaming pass, kept between calls: :meth:`add` reads further dumps (each
    snapshot once, in time order across calls), :meth:`accumulation` is what the dumps read
    so far give, the same however the dumps were split between calls.

    This is what makes a convergence check while the solver runs cost the dumps written
    since the last check, not every dump again."""

    def __init__(
        self, config: DemConfig, types_a: Sequence[int], types_b: Sequence[int], record_sequences: bool = False
    ) -> None:
        g, tables = config.geometry, config.tables
        self.config = config
        self.types_a, self.types_b = tuple(types_a), tuple(types_b)
        self.record_sequences = record_sequences
        self.dt = float(config.timestep_s)
        self.length, self.nx, self.ny = float(g.length_m), int(tables.nx), int(tables.ny)
        self.diameter = float(g.diameter_m)
        self.window, self.tol, self.ncell = float(tables.window_s), 0.5 * self.dt, self.nx * self.ny
        self.max_t = MAX_SAMPLING_INTERVALS * float(tables.sample_interval_s)
        self.log = ParticleLog()
        self.window_sums: dict[int, np.ndarray] = {}
        self.window_snapshots: dict[int, int] = {}
        self.transitions: dict[int, np.ndarray] = {}
        self.interval, self.irregular = float("nan"), 0
        self.prev_t, self.prev_k = float("nan"), -1
        self.times: list[float] = []
        self.counts: list[np.ndarray] = []
        self.prev_ids = np.zeros(0, np.int64)
        self.last_step, self.reappeared = -1, 0
        self.other_types: set[int] = set()
        self.visits: list[tuple[np.ndarray, np.ndarray]] = []
        self.n_seen = 0

    def add(self, dump_paths) -> int:
        """Read the snapshots of ``dump_paths`` (glob, path or sequence), which must all
        come after the ones read before; returns how many were read."""
        n = 0
        for snap in iter_snapshots(dump_paths, columns=REQUIRED_COLUMNS):
            if snap.step <= self.last_step:
                raise DumpFormatError(
                    f"{snap.source}: snapshot step {snap.step} does not follow the step {self.last_step} "
                    "already read; dumps must be added in time order without duplicates"
                )
            self._snapshot(snap)
            n += 1
        return n

    def _snapshot(self, snap) -> None:
        log, dt, tol, ncell = self.log, self.dt, self.tol, self.ncell
        t = snap.time_s(dt)
        if t > self.max_t:
            raise DumpFormatError(
                f"{snap.source}: snapshot at step {snap.step} is at t = {t:.6g} s (timestep {dt:.6g} s), beyond "
                f"{MAX_SAMPLING_INTERVALS} sampling intervals ({self.max_t:.6g} s); a corrupted step, or a "
                "timestep that is not the run's"
            )
        # The reader has checked that ids and types are integers >= 1 and that the columns
        # used here are finite.
        ids = snap["id"].astype(np.int64)
        ptype = snap["type"].astype(np.int64)
        x, y, vx, vy = snap["x"], snap["y"], snap["vx"], snap["vy"]
        if ids.size:
            top = int(ids.max())
            bound = id_bound(self.n_seen + ids.size)
            if top > bound:
                row = int(np.argmax(ids))
                raise DumpFormatError(
                    f"{snap.source}: snapshot at step {snap.step}, atom {row + 1} (column 'id'): particle id {top} "
                    f"is implausible; with {self.n_seen} particles seen before and {ids.size} in this snapshot, "
                    f"ids up to {bound} ({ID_FACTOR} x particles + {ID_HEADROOM}) are accepted (LIGGGHTS numbers "
                    "particles 1, 2, 3, ...)"
                )
            log.ensure(top)
        # a snapshot refused above leaves the stream as it was
        self.last_step = snap.step
        log.outside_vessel += int(
            np.count_nonzero(outside_vessel(x, y, snap["z"] if "z" in snap else None, self.config))
        )
        is_a, is_b = np.isin(ptype, self.types_a), np.isin(ptype, self.types_b)
        if not (is_a | is_b).all():
            self.other_types.update(int(v) for v in np.unique(ptype[~(is_a | is_b)]))

        new = np.isnan(log.first_t[ids])
        log.first_t[ids[new]] = t
        log.first_y[ids[new]] = y[new]
        if "radius" in snap:  # the size a particle was inserted with; NaN where the dumps carry none
            log.diameter[ids[new]] = 2.0 * snap["radius"][new]
        self.n_seen += int(np.count_nonzero(new))  # an id listed twice counts twice: a looser bound, no sort
        log.kind[ids] = np.where(is_a, 1, np.where(is_b, 2, 3))
        back = ~new & ~np.isnan(log.vanish_t[ids])
        if back.any():
            self.reappeared += int(back.sum())
            log.vanish_t[ids[back]] = np.nan
        k = int(math.floor((t + tol) / self.window))
        gap = t - self.prev_t
        if math.isnan(self.interval) and gap > tol:
            self.interval = gap
        # dumps every N steps are exactly periodic; 1 % admits step rounding, not a missed dump
        regular = abs(gap - self.interval) <= max(tol, 0.01 * self.interval)
        prev_ids, prev_k = self.prev_ids, self.prev_k
        self.irregular += int(bool(prev_ids.size) and not regular)
        log.scratch[ids] = True
        gone = prev_ids[~log.scratch[prev_ids]]
        log.vanish_t[gone] = t
        log.vanish_state[gone] = log.last_state[gone]
        log.vanish_window[gone] = prev_k if regular else -1
        log.scratch[ids] = False
        self.prev_ids = ids
        log.last_t[ids] = t
        log.last_x[ids] = x
        past = (x > self.length) & np.isnan(log.exit_t[ids])
        log.exit_t[ids[past]] = t

        inside, cell = bin_particles(x, y, self.length, self.diameter, self.nx, self.ny)
        state = np.full(ids.size, -1, np.int32)
        state[inside] = cell
        state[x > self.length] = ncell
        n_states = ncell + 1
        if regular:
            was = log.last_state[ids]
            moved = (log.last_snapshot[ids] == len(self.times) - 1) & (was >= 0) & (was < ncell) & (state >= 0)
            pairs = np.bincount(was[moved].astype(np.int64) * n_states + state[moved], minlength=n_states**2)
            if prev_k in self.transitions:
                self.transitions[prev_k] += pairs
            else:
                self.transitions[prev_k] = pairs
        log.last_state[ids] = state
        log.last_snapshot[ids] = len(self.times)
        if self.record_sequences:
            self.visits.append((ids.astype(np.int32), state.astype(np.int16)))
        log.last_cell[ids[inside]] = cell
        self.prev_t, self.prev_k = t, k
        sums = snapshot_sums(cell, vx[inside], vy[inside], is_a[inside], is_b[inside], ncell)
        if k in self.window_sums:
            self.window_sums[k] += sums
            self.window_snapshots[k] += 1
        else:
            self.window_sums[k], self.window_snapshots[k] = sums, 1
        self.times.append(t)
        self.counts.append(sums[COMPONENT_ROWS].reshape(2, self.nx, self.ny).copy())  # the sums grow in place

    def accumulation(self) -> Accumulation:
        """What the dumps read so far give; a copy, so reading on leaves it as it is (and
        what a caller does to it leaves the stream as it is)."""
        if not self.times:
            raise DumpFormatError("no complete snapshot read yet")
        return Accumulation(
            self.log.copy(),
            {k: v.copy() for k, v in self.window_sums.items()},
            {k: v.copy() for k, v in self.transitions.items()},
            self.interval,
            self.irregular,
            dict(self.window_snapshots),
            np.asarray(self.times),
            np.stack(self.counts),
            self.prev_ids.copy(),
            self.last_step,
            self.reappeared,
            set(self.other_types),
            list(self.visits),  # the per-dump arrays themselves are never written after being read
        )


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


@dataclass(frozen=True)
class CompartmentSequences:
    """Every particle's compartment at every dump, run-length encoded.

    Particle ``p`` (ID ``ids[p]``) is first seen at dump ``start[p]`` (time
    ``snapshot_t[start[p]]`` [s]) and then sits in state ``run_state[r]`` for
    ``run_length[r]`` consecutive dumps, for its runs ``r`` in
    ``run_offsets[p]:run_offsets[p+1]``. States: flat compartment c = i * NY + j of the
    tables' grid (:func:`coupling.compartments.bin_particles`), or ``n_cells`` = past the
    weir (absorbing: a sequence ends with at most one dump there). A particle that the
    solver deleted between two dumps and :func:`find_exits` counts as discharged gets that
    absorbing state at the dump from which it is absent, as the measured rates count it
    (:func:`transition_counts`). A sequence without the absorbing state is censored: the
    particle was still inside at the last dump, was lost, was once seen outside the grid
    (x < 0) or skipped a dump; it ends at its last regular sight.

    ``component`` (int8): 1 = A, 2 = B, 3 = another type (the feeder a particle came from).
    ``interval_s`` [s]: the dump interval; ``nx``, ``ny``: the grid.
    """

    ids: np.ndarray
    component: np.ndarray
    start: np.ndarray
    run_offsets: np.ndarray
    run_state: np.ndarray
    run_length: np.ndarray
    snapshot_t: np.ndarray
    interval_s: float
    nx: int
    ny: int

    ARRAYS = ("ids", "component", "start", "run_offsets", "run_state", "run_length", "snapshot_t")

    @property
    def n_cells(self) -> int:
        return self.nx * self.ny

    @property
    def n_particles(self) -> int:
        return int(self.ids.size)

    @property
    def lengths(self) -> np.ndarray:
        """Dumps in each particle's sequence (including a final absorbing one)."""
        return np.add.reduceat(self.run_length, self.run_offsets[:-1]) if self.ids.size else np.zeros(0, np.int64)

    @property
    def entry_t(self) -> np.ndarray:
        """First sight of each particle [s]."""
        return self.snapshot_t[self.start]

    @property
    def discharged(self) -> np.ndarray:
        """Whether each sequence ends in the absorbing state (else it is censored)."""
        return self.run_state[self.run_offsets[1:] - 1] == self.n_cells if self.ids.size else np.zeros(0, bool)

    def states(self, particles: np.ndarray | None = None) -> list[np.ndarray]:
        """Decoded state sequences (int16) of ``particles`` (indices; default all)."""
        chosen = np.arange(self.n_particles) if particles is None else np.asarray(particles)
        out = []
        for p in chosen:
            a, b = self.run_offsets[p], self.run_offsets[p + 1]
            out.append(np.repeat(self.run_state[a:b], self.run_length[a:b]))
        return out

    def padded(self, particles: np.ndarray | None = None, fill: int = -1) -> np.ndarray:
        """(P, max length) int16 matrix of decoded sequences, ``fill`` after each one ends
        (vectorised: no Python loop over particles)."""
        chosen = np.arange(self.n_particles) if particles is None else np.asarray(particles, dtype=np.int64)
        run_index, n_runs = self._runs_of(chosen)
        owner = np.repeat(np.arange(chosen.size), n_runs)
        lengths = self.run_length[run_index]
        per_particle = np.bincount(owner, lengths, minlength=chosen.size).astype(np.int64)
        out = np.full((chosen.size, int(per_particle.max()) if chosen.size else 0), fill, np.int16)
        # position of every decoded element inside its particle's row
        element_owner = np.repeat(owner, lengths)
        row_start = np.concatenate([[0], np.cumsum(per_particle)[:-1]])
        position = np.arange(element_owner.size) - row_start[element_owner]
        out[element_owner, position] = np.repeat(self.run_state[run_index], lengths)
        return out

    def _runs_of(self, chosen: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The indices of the runs of particles ``chosen``, particle after particle, and how
        many runs each has."""
        first, last = self.run_offsets[chosen], self.run_offsets[chosen + 1]
        n_runs = last - first
        return np.repeat(first - np.concatenate([[0], np.cumsum(n_runs)[:-1]]), n_runs) + np.arange(
            n_runs.sum()
        ), n_runs

    def _runs(self) -> tuple[np.ndarray, np.ndarray]:
        """Each run's particle (row) and first dump (absolute index)."""
        owner = np.repeat(np.arange(self.n_particles), np.diff(self.run_offsets))
        before = np.cumsum(self.run_length) - self.run_length  # dumps before each run, all particles
        return owner, self.start[owner] + before - before[self.run_offsets[:-1]][owner]

    def counts(self, components: tuple[int, ...] = (1, 2)) -> np.ndarray:
        """(dumps, NX, NY) int: how many particles of ``components`` are in each compartment
        at every dump (from the run-length encoding: a +1 where a run in a compartment
        starts, a -1 where it ends, summed over the dumps)."""
        n_dumps, cells = self.snapshot_t.size, self.n_cells
        owner, first = self._runs()
        state = self.run_state.astype(np.int64)
        chosen = (state < cells) & np.isin(self.component, components)[owner]
        cell = state[chosen]
        size = (n_dumps + 1) * cells
        change = np.bincount(first[chosen] * cells + cell, minlength=size) - np.bincount(
            (first[chosen] + self.run_length[chosen]) * cells + cell, minlength=size
        )
        return np.cumsum(change.reshape(n_dumps + 1, self.nx, self.ny), axis=0)[:n_dumps]

    def subset(self, particles: np.ndarray) -> CompartmentSequences:
        """The record of ``particles`` (indices, in the order given) alone: e.g. one size
        class, whose chain is fitted apart from the others'."""
        chosen = np.asarray(particles, dtype=np.int64)
        runs, n_runs = self._runs_of(chosen)
        return CompartmentSequences(
            ids=self.ids[chosen],
            component=self.component[chosen],
            start=self.start[chosen],
            run_offsets=np.concatenate([[0], np.cumsum(n_runs)]).astype(self.run_offsets.dtype),
            run_state=self.run_state[runs],
            run_length=self.run_length[runs],
            snapshot_t=self.snapshot_t,
            interval_s=self.interval_s,
            nx=self.nx,
            ny=self.ny,
        )

    def until(self, t_end_s: float) -> CompartmentSequences:
        """The record a run stopped at ``t_end_s`` [s] would hold: the dumps after it
        dropped, the particles first seen after it left out, the sequences it cuts
        censored there."""
        last = int(np.searchsorted(self.snapshot_t, t_end_s + 1e-6 * self.interval_s, side="right")) - 1
        owner, first = self._runs()
        kept_runs = first <= last
        kept = self.start <= last
        counts = np.bincount(owner[kept_runs], minlength=self.n_particles)[kept]
        return CompartmentSequences(
            ids=self.ids[kept],
            component=self.component[kept],
            start=self.start[kept],
            run_offsets=np.concatenate([[0], np.cumsum(counts)]).astype(self.run_offsets.dtype),
            run_state=self.run_state[kept_runs],
            run_length=np.minimum(self.run_length[kept_runs], last - first[kept_runs] + 1).astype(
                self.run_length.dtype
            ),
            snapshot_t=self.snapshot_t[: last + 1],
            interval_s=self.interval_s,
            nx=self.nx,
            ny=self.ny,
        )

    def to_arrays(self, prefix: str = "sequences_") -> dict[str, np.ndarray]:
        """Named arrays for a results file; the scalars ride along as 0-d arrays."""
        out = {prefix + name: getattr(self, name) for name in self.ARRAYS}
        out[prefix + "grid"] = np.array([self.nx, self.ny], np.int64)
        out[prefix + "interval_s"] = np.array(self.interval_s)
        return out

    @classmethod
    def from_arrays(
        cls, arrays: dict[str, np.ndarray], prefix: str = "sequences_", source: str = "the results"
    ) -> CompartmentSequences | None:
        """The inverse of :meth:`to_arrays`; None when ``arrays`` holds no sequences (results
        made before they were recorded). Every array is checked against the others first
        (:func:`checked_sequence_arrays`): ResultsError names ``source`` and the array."""
        if prefix + "ids" not in arrays:
            return None
        values, interval_s, (nx, ny) = checked_sequence_arrays(arrays, prefix, source)
        return cls(**values, interval_s=interval_s, nx=nx, ny=ny)


#: Largest grid the sequences can hold: states are stored as int16, with S (past the weir)
#: the largest of them.
MAX_SEQUENCE_CELLS = int(np.iinfo(np.int16).max) - 1


def checked_sequence_arrays(
    arrays: dict[str, np.ndarray], prefix: str, source: str
) -> tuple[dict[str, np.ndarray], float, tuple[int, int]]:
    """The stored compartment sequences' arrays (keyed by :attr:`CompartmentSequences.ARRAYS`),
    dump interval [s] and grid, each checked against the others; ResultsError names
    ``source``, the first bad array and what would be valid.

    Every later step indexes one array by another (runs by offsets, dumps by starts, counts
    by states) and sizes arrays by run lengths, so a value out of range is an IndexError,
    a terabyte allocation or a silently wrong fit there: refused here instead."""

    def refuse(name: str, problem: str) -> ResultsError:
        return ResultsError(f"{source}: stored array '{prefix}{name}' {problem}")

    missing = [
        prefix + name for name in (*CompartmentSequences.ARRAYS, "grid", "interval_s") if prefix + name not in arrays
    ]
    if missing:
        raise ResultsError(f"{source}: the compartment sequences lack {', '.join(missing)}; regenerate the results")
    values = {name: np.asarray(arrays[prefix + name]) for name in CompartmentSequences.ARRAYS}
    for name in ("ids", "component", "start", "run_offsets", "run_state", "run_length"):
        if values[name].ndim != 1 or not (np.issubdtype(values[name].dtype, np.integer) or values[name].size == 0):
            raise refuse(name, f"is {values[name].dtype} of shape {values[name].shape}; a 1-D integer array is valid")
        values[name] = values[name].astype(np.int64) if values[name].size == 0 else values[name]

    grid = np.asarray(arrays[prefix + "grid"])
    if grid.shape != (2,) or not np.issubdtype(grid.dtype, np.integer) or (grid < 1).any():
        raise refuse("grid", f"is {grid.tolist()}; two integers NX, NY >= 1 are valid")
    nx, ny = int(grid[0]), int(grid[1])
    if nx * ny > MAX_SEQUENCE_CELLS:
        raise refuse("grid", f"is {nx} x {ny}; at most {MAX_SEQUENCE_CELLS} compartments fit the stored states")
    interval = np.asarray(arrays[prefix + "interval_s"])
    interval_s = float(interval) if interval.shape == () and np.issubdtype(interval.dtype, np.number) else math.nan
    if not (math.isfinite(interval_s) and interval_s > 0):
        raise refuse("interval_s", f"is {interval.tolist()!r}; a dump interval > 0 s is valid")

    t = values["snapshot_t"]
    if t.ndim != 1 or not np.issubdtype(t.dtype, np.number) or not np.isfinite(t).all():
        raise refuse("snapshot_t", f"of shape {t.shape} is not all finite numbers; dump times in s are valid")
    if t.size > 1 and (np.diff(t) <= 0).any():
        k = int(np.argmax(np.diff(t) <= 0))
        raise refuse(
            "snapshot_t",
            f"goes from {t[k]:.6g} s to {t[k + 1]:.6g} s at dump {k + 1}; strictly increasing times are valid",
        )

    ids, n_dumps = values["ids"], t.size
    p = ids.size
    for name in ("component", "start"):
        if values[name].size != p:
            raise refuse(name, f"has {values[name].size} entries for {p} particles; one per particle is valid")
    if p and np.unique(ids).size != p:
        dup = np.sort(ids)[np.flatnonzero(np.diff(np.sort(ids)) == 0)[0]]
        raise refuse("ids", f"lists particle {int(dup)} twice; each particle once is valid")
    bad = ~np.isin(values["component"], (1, 2, 3))
    if bad.any():
        raise refuse(
            "component", f"holds {int(values['component'][bad][0])}; 1 (A), 2 (B) or 3 (another type) are valid"
        )
    start = values["start"]
    bad = (start < 0) | (start >= n_dumps)
    if bad.any():
        raise refuse("start", f"holds dump {int(start[bad][0])}; dumps 0 to {n_dumps - 1} are recorded")

    offsets, state, length = values["run_offsets"], values["run_state"], values["run_length"]
    n_runs = state.size
    if offsets.size != p + 1:
        raise refuse("run_offsets", f"has {offsets.size} entries for {p} particles; {p + 1} (one more) are valid")
    if offsets[0] != 0 or offsets[-1] != n_runs or (np.diff(offsets) < 1).any():
        raise refuse(
            "run_offsets",
            f"runs {offsets[0]} ... {offsets[-1]}; valid offsets go from 0 to the {n_runs} runs, strictly increasing "
            "(every particle has a run)",
        )
    if length.size != n_runs:
        raise refuse("run_length", f"has {length.size} entries for {n_runs} runs; one per run is valid")
    n_cells = nx * ny
    bad = (state < 0) | (state > n_cells)
    if bad.any():
        raise refuse(
            "run_state",
            f"holds {int(state[bad][0])}; on the {nx} x {ny} grid states 0 to {n_cells - 1} (compartments) and "
            f"{n_cells} (past the weir) are valid",
        )
    bad = (length < 1) | (length > n_dumps)
    if bad.any():
        raise refuse("run_length", f"holds {int(length[bad][0])}; a run lasts 1 to {n_dumps} dumps (those recorded)")
    if p:
        end = start.astype(np.int64) + np.add.reduceat(length.astype(np.int64), offsets[:-1])
        bad = end > n_dumps
        if bad.any():
            q = int(np.argmax(bad))
            raise refuse(
                "run_length",
                f"gives particle {int(ids[q])} (first seen at dump {int(start[q])}) {int(end[q] - start[q])} dumps; "
                f"only {n_dumps} are recorded",
            )
        # past the weir is absorbing: a particle's last run at most, for one dump
        last = np.zeros(n_runs, bool)
        last[offsets[1:] - 1] = True
        bad = (state == n_cells) & (~last | (length != 1))
        if bad.any():
            raise refuse(
                "run_state",
                f"holds the absorbing state {n_cells} (past the weir) in run {int(np.argmax(bad))} other than as a "
                "particle's last run of one dump",
            )
    return values, interval_s, (nx, ny)


def compartment_sequences(acc: Accumulation, exits: Exits, nx: int, ny: int) -> CompartmentSequences:
    """Run-length-encoded compartment sequences of every particle (:class:`CompartmentSequences`)
    from a pass made with ``record_sequences``. Raises ValueError if it was made without."""
    if not acc.visits:
        raise ValueError(
            "the accumulation holds no per-dump states: read the dumps with DumpStream(..., record_sequences=True)"
        )
    n_cells = nx * ny
    ids = np.concatenate([v[0] for v in acc.visits]).astype(np.int64)
    state = np.concatenate([v[1] for v in acc.visits])
    snap = np.repeat(np.arange(len(acc.visits), dtype=np.int32), [v[0].size for v in acc.visits])
    order = np.argsort(ids, kind="stable")  # dumps stay in time order within a particle
    ids, state, snap = ids[order], state[order], snap[order]
    new = np.ones(ids.size, bool)
    new[1:] = ids[1:] != ids[:-1]
    # A sequence stops at the first sight that breaks it: outside the grid, a skipped dump,
    # or anything after the absorbing state (the dumps can show a particle past the weir
    # for a while before the solver deletes it).
    broken = state < 0
    broken[1:] |= ~new[1:] & ((snap[1:] != snap[:-1] + 1) | (state[:-1] == n_cells))
    group = np.cumsum(new) - 1
    breaks_so_far = np.cumsum(broken)
    before_group = (breaks_so_far - broken)[new]  # breaks before each particle's first sight
    keep = breaks_so_far - before_group[group] == 0
    ids, state, snap, group = ids[keep], state[keep], snap[keep], group[keep]
    new = np.ones(ids.size, bool)
    new[1:] = ids[1:] != ids[:-1]
    # Particles first seen past the weir carry no transport information.
    first_state = state[new]
    drop = np.repeat(first_state == n_cells, np.diff(np.append(np.flatnonzero(new), ids.size)))
    ids, state, snap = ids[~drop], state[~drop], snap[~drop]
    new = np.ones(ids.size, bool)
    new[1:] = ids[1:] != ids[:-1]
    last = np.append(np.flatnonzero(new)[1:] - 1, ids.size - 1) if ids.size else np.zeros(0, np.int64)
    # Deleted by the solver between dumps and counted as discharged: absorbed at the next
    # dump, if the kept sequence reaches the particle's last sight (and that dump exists).
    pid = ids[last]
    deleted = (
        exits.exited[pid]
        & (state[last] < n_cells)
        & (snap[last] == acc.particles.last_snapshot[pid])
        & (snap[last] + 1 < len(acc.visits))
    )
    ids = np.insert(ids, last[deleted] + 1, pid[deleted])
    snap = np.insert(snap, last[deleted] + 1, snap[last[deleted]] + 1)
    state = np.insert(state, last[deleted] + 1, np.int16(n_cells))
    # Run-length encoding: a run starts at each particle's first sight and at each change.
    new = np.ones(ids.size, bool)
    new[1:] = ids[1:] != ids[:-1]
    run_start = new.copy()
    run_start[1:] |= state[1:] != state[:-1]
    starts = np.flatnonzero(run_start)
    run_length = np.diff(np.append(starts, ids.size)).astype(np.int32)
    particle_of_run = np.cumsum(new)[starts] - 1
    n_particles = int(new.sum())
    run_offsets = np.searchsorted(particle_of_run, np.arange(n_particles + 1)).astype(np.int64)
    return CompartmentSequences(
        ids=ids[new].astype(np.int64),
        component=acc.particles.kind[ids[new]].astype(np.int8),
        start=snap[new].astype(np.int32),
        run_offsets=run_offsets,
        run_state=state[starts].astype(np.int16),
        run_length=run_length,
        snapshot_t=np.asarray(acc.snapshot_t, float),
        interval_s=float(acc.transition_interval_s),
        nx=int(nx),
        ny=int(ny),
    )
