"""The data a phase chain is fitted to: every particle's compartment sequence
(:class:`dem.tracking.CompartmentSequences`) as fit-ready arrays (:class:`PhaseData`),
selected by entry time, coarsened to a grid and observed every few dumps; and synthetic
sequences of a known chain, for tests with a known answer.

A joint fit takes several runs at once: a list of :class:`PhaseData` on the same grid and
observation interval (:func:`as_runs`), whatever operating point each was run at.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.linalg import expm

from coupling.errors import ConfigError
from coupling.phases import PhaseTransport
from dem.tracking import CompartmentSequences

#: components of the feed (the sequences' ``component``): rows of the entry distribution
FEEDERS = (1, 2)


@dataclass(frozen=True)
class PhaseData:
    """Sequences prepared for the forward-backward pass.

    ``obs`` (P, L) int16: state at each dump since first sight (compartment of the fitted
    grid, ``n_cells`` = discharged, -1 after the sequence ended), rows sorted by
    ``lengths`` descending, so that the particles still followed at step t are the first
    ``active[t]`` rows. ``group`` (P,): the row of the initial phase distribution: 0 =
    entered from feeder A (other types count as A), 1 = from feeder B, 2 + c = already
    inside when the data's window opened, first observed in compartment c (its phase then
    is not the feed's). ``start`` (P,): index of the first dump (absolute, in the
    sequences' ``snapshot_t``); ``last_dump``: index of the last dump of the run.
    """

    obs: np.ndarray
    lengths: np.ndarray
    active: np.ndarray
    group: np.ndarray
    start: np.ndarray
    last_dump: int
    nx: int
    ny: int
    interval_s: float
    #: every sequence, one after the other (int64, row order), and where each starts (P + 1,)
    flat: np.ndarray
    offsets: np.ndarray

    @property
    def n_cells(self) -> int:
        return self.nx * self.ny

    @property
    def n_particles(self) -> int:
        return int(self.obs.shape[0])

    @property
    def n_groups(self) -> int:
        """Rows of the initial distribution: the two feeders and one per compartment."""
        return 2 + self.n_cells

    @property
    def n_steps(self) -> int:
        """Particle-steps (pairs of consecutive dumps) in the data."""
        return int(np.maximum(self.lengths - 1, 0).sum())

    def counts(self, lag: int = 1) -> np.ndarray:
        """(S+1, S+1) counts of state a at one dump and b ``lag`` dumps later (moves of the
        observed chain; a particle discharged before then counts as discharged)."""
        s = self.n_cells
        out = np.zeros((s + 1) * (s + 1), np.int64)
        obs, lengths = self.obs, self.lengths
        ends_out = obs[np.arange(obs.shape[0]), np.maximum(lengths - 1, 0)] == s
        for t in range(obs.shape[1] - 1):
            n = int(self.active[t])
            a = obs[:n, t].astype(np.int64)
            ahead = t + lag
            in_range = lengths[:n] > ahead
            b = np.where(in_range, obs[:n, min(ahead, obs.shape[1] - 1)], np.where(ends_out[:n], s, -1))
            ok = (a < s) & (b >= 0)
            out += np.bincount(a[ok] * (s + 1) + b[ok], minlength=out.size)
        return out.reshape(s + 1, s + 1)


def coarsen(states: np.ndarray, nx: int, ny: int, to_nx: int, to_ny: int) -> np.ndarray:
    """Map flat states of an ``nx`` x ``ny`` grid onto a coarser ``to_nx`` x ``to_ny`` grid
    whose edges are a subset (``nx`` and ``ny`` multiples of ``to_nx`` and ``to_ny``);
    the discharged state and -1 are kept as such."""
    if nx % to_nx or ny % to_ny:
        raise ValueError(f"grid {to_nx}x{to_ny} does not divide {nx}x{ny}: its edges must be the finer grid's")
    s = nx * ny
    cells = np.arange(s)
    # one look-up per state (index 0 = -1, then every cell, then discharged): a gather
    # rather than integer divisions over the whole (particles x dumps) array
    table = np.concatenate(
        [[-1], (cells // ny // (nx // to_nx)) * to_ny + cells % ny // (ny // to_ny), [to_nx * to_ny]]
    ).astype(np.int16)
    states = np.asarray(states)
    if states.size and (states.min() < -1 or states.max() > s):
        raise ValueError(
            f"states must lie in -1 ... {s} (the grid's cells and discharged), got {states.min()} ... {states.max()}"
        )
    return table[states + np.int16(1)] if states.dtype == np.int16 else table[states + 1]


def prepare(
    sequences: CompartmentSequences,
    entered_s: tuple[float, float] | None = None,
    grid: tuple[int, int] | None = None,
    lag: int = 1,
    residents: bool = False,
) -> PhaseData:
    """The sequences of the particles first seen in ``entered_s`` = (t0, t1] [s] (default
    all), on ``grid`` = (NX, NY) (default the sequences' own; a coarser grid must divide
    it), observed every ``lag`` dumps (a particle discharged in between is seen discharged
    at the next observation), as a :class:`PhaseData`. With ``residents`` also the
    particles already inside at t0, from their first dump after t0 on (initial group 2 + c):
    the moves they make in the window are data too, and the only data on how long
    particles stay when the window is shorter than the longest stays. Raises ValueError
    for an empty selection or a lag < 1."""
    if not isinstance(lag, (int, np.integer)) or lag < 1:
        raise ValueError(f"lag = {lag!r}: expected a whole number of dumps >= 1")
    entry_t = sequences.entry_t
    chosen = np.ones(sequences.n_particles, bool)
    if entered_s is not None:
        chosen = first_seen_in(sequences, entered_s)
    index = np.flatnonzero(chosen)
    if not index.size:
        raise ValueError(
            f"no particle entered in {entered_s} s (sequences span {entry_t.min() if entry_t.size else 'nothing'}"
            f"..{entry_t.max() if entry_t.size else ''} s)"
        )
    obs = sequences.padded(index)
    group = np.where(sequences.component[index] == FEEDERS[1], 1, 0)
    start = sequences.start[index].astype(np.int64)
    if residents and entered_s is not None:
        old_obs, old_start, old_cells = _residents(sequences, entered_s[0])
        width = max(obs.shape[1], old_obs.shape[1])
        obs = np.concatenate([_widen(obs, width), _widen(old_obs, width)])
        group = np.concatenate(
            [group, 2 + coarsen(old_cells, sequences.nx, sequences.ny, *(grid or (sequences.nx, sequences.ny)))]
        )
        start = np.concatenate([start, old_start])
    nx, ny = grid or (sequences.nx, sequences.ny)
    if (nx, ny) != (sequences.nx, sequences.ny):
        obs = coarsen(obs, sequences.nx, sequences.ny, nx, ny)
    if lag > 1:
        obs = _subsample(obs, lag, nx * ny)
    lengths = (obs >= 0).sum(axis=1)
    order = np.argsort(-lengths, kind="stable")
    obs, lengths = obs[order], lengths[order]
    active = np.searchsorted(-lengths, -np.arange(obs.shape[1]), side="left")  # rows with length > t
    # with a lag, dump indices count observations: start and last dump in units of the lag
    return PhaseData(
        obs=obs,
        lengths=lengths,
        active=active,
        group=group[order].astype(np.int64),
        start=start[order] // lag,
        last_dump=int(sequences.snapshot_t.size - 1) // lag,
        nx=int(nx),
        ny=int(ny),
        interval_s=float(sequences.interval_s) * lag,
        flat=obs[obs >= 0].astype(np.int64),
        offsets=np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64),
    )


def _widen(obs: np.ndarray, width: int) -> np.ndarray:
    return (
        obs
        if obs.shape[1] == width
        else np.concatenate([obs, np.full((obs.shape[0], width - obs.shape[1]), -1, obs.dtype)], axis=1)
    )


def _residents(sequences: CompartmentSequences, t0_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(padded sequences from the first dump after ``t0_s`` on, that dump's index, the
    compartment there) of the particles first seen at or before ``t0_s`` and still in a
    compartment at that dump."""
    first = int(np.searchsorted(sequences.snapshot_t, t0_s + 1e-6 * sequences.interval_s, side="right"))
    entered_before = np.flatnonzero(sequences.start < first)
    ends = sequences.start[entered_before] + sequences.lengths[entered_before]  # one past the last dump
    alive = entered_before[ends > first]
    if not alive.size:
        return np.zeros((0, 1), np.int16), np.zeros(0, np.int64), np.zeros(0, np.int16)
    full = sequences.padded(alive)
    shift = first - sequences.start[alive].astype(np.int64)
    width = full.shape[1] - int(shift.min())
    cols = np.arange(width)[None, :] + shift[:, None]
    obs = np.where(cols < full.shape[1], full[np.arange(alive.size)[:, None], np.minimum(cols, full.shape[1] - 1)], -1)
    keep = (obs[:, 0] >= 0) & (obs[:, 0] < sequences.n_cells)  # not already discharged there
    return obs[keep].astype(np.int16), np.full(int(keep.sum()), first, np.int64), obs[keep, 0].astype(np.int16)


def _subsample(obs: np.ndarray, lag: int, n_cells: int) -> np.ndarray:
    """Every ``lag``-th column of the padded sequences, a discharge in between moved to the
    next kept column."""
    lengths = (obs >= 0).sum(axis=1)
    last = obs[np.arange(obs.shape[0]), np.maximum(lengths - 1, 0)]
    out = obs[:, ::lag].copy()
    out[out == n_cells] = -1
    discharged = (last == n_cells) & (lengths > 0)
    column = -(-(lengths - 1) // lag)  # ceil((length - 1) / lag): first kept column at or after the discharge
    if out.shape[1] <= column.max(initial=0):
        out = np.concatenate([out, np.full((out.shape[0], column.max() + 1 - out.shape[1]), -1, out.dtype)], axis=1)
    out[np.flatnonzero(discharged), column[discharged]] = n_cells
    return out


def first_seen_in(sequences: CompartmentSequences, window: tuple[float, float]) -> np.ndarray:
    """Whether each particle was first seen in ``window`` = (t0, t1] [s] (:func:`prepare`'s rule)."""
    tol = 1e-6 * sequences.interval_s
    return (sequences.entry_t > window[0] + tol) & (sequences.entry_t <= window[1] + tol)


def first_compartments(data: PhaseData) -> np.ndarray:
    """(2, S): how many particles of each feeder were first seen in each compartment."""
    first = data.obs[:, 0].astype(np.int64)
    return np.stack(
        [np.bincount(first[data.group == f], minlength=data.n_cells)[: data.n_cells] for f in (0, 1)]
    ).astype(float)


def steady_window(sequences: CompartmentSequences, steady_time_s: float | None) -> tuple[float, float]:
    """(steady-state time, last dump) [s]: the particles the model is fitted to are those
    first seen in between. Raises ValueError when the run never became steady."""
    if steady_time_s is None or not math.isfinite(steady_time_s):
        raise ValueError("the run has no steady-state time: the phase model is fitted to the steady period")
    return float(steady_time_s), float(sequences.snapshot_t[-1])


def as_runs(data: PhaseData | Sequence[PhaseData]) -> tuple[PhaseData, ...]:
    """One run or several as a tuple of runs, checked to be one fit's data: the same grid
    and observation interval (their expected transitions add up only then). Raises
    ConfigError for no run, something that is not :class:`PhaseData`, or runs that differ."""
    runs = (data,) if isinstance(data, PhaseData) else tuple(data)
    if not runs:
        raise ConfigError("no run to fit: expected one PhaseData or a non-empty list of them")
    for n, run in enumerate(runs):
        if not isinstance(run, PhaseData):
            raise ConfigError(f"run {n} is a {type(run).__name__}: expected PhaseData (dem.phases.prepare)")
    first = runs[0]
    for n, run in enumerate(runs[1:], start=1):
        if (run.nx, run.ny) != (first.nx, first.ny) or not math.isclose(run.interval_s, first.interval_s, rel_tol=1e-9):
            raise ConfigError(
                f"run {n} is on {run.nx}x{run.ny} observed every {run.interval_s:g} s, run 0 on "
                f"{first.nx}x{first.ny} every {first.interval_s:g} s: a joint fit needs one grid and one interval"
            )
    return runs


def simulate_sequences(
    model: PhaseTransport,
    entering: np.ndarray,
    n_particles: int,
    n_dumps: int,
    rng: np.random.Generator,
    entry_every: int = 1,
) -> CompartmentSequences:
    """Sequences of ``n_particles`` particles of the chain ``model`` observed every
    ``model.interval_s`` (exact: each step draws from expm(Q interval)), for tests with a
    known answer. Particle p enters at dump p // (``n_particles`` / (n_dumps / entry_every))...
    precisely: entries are spread evenly over the first half of the ``n_dumps`` dumps, each
    into a compartment drawn from ``entering`` (2, S) (rows: feed A, B; half the particles
    each) and a phase drawn from the model's entry distribution; the record ends at dump
    ``n_dumps`` - 1 (later particles are censored there)."""
    k, s = model.n_phases, model.n_cells
    p = expm(model.generator() * model.interval_s)
    cdf = np.cumsum(p, axis=1)
    cdf[:, -1] = 1.0
    feeder = np.arange(n_particles) % 2
    start = (np.arange(n_particles) * (n_dumps // 2) // max(n_particles, 1)).astype(np.int64)
    entering = np.asarray(entering, float)
    cells = np.empty(n_particles, np.int64)
    phases = np.empty(n_particles, np.int64)
    for f in (0, 1):
        chosen = feeder == f
        cells[chosen] = rng.choice(s, size=int(chosen.sum()), p=entering[f] / entering[f].sum())
        phases[chosen] = rng.choice(k, size=int(chosen.sum()), p=model.entry[f])
    state = cells * k + phases
    obs = np.full((n_particles, n_dumps), -1, np.int16)
    for t in range(n_dumps):
        inside = (start <= t) & (state < s * k)
        entering_now = start == t
        stepping = inside & ~entering_now
        if stepping.any():
            u = rng.random(int(stepping.sum()))
            rows = state[stepping]
            state[stepping] = (u[:, None] > cdf[rows]).sum(axis=1)
        recorded = start <= t
        just_out = (
            recorded & (state == s * k) & (obs[:, t - 1] < s) & (obs[:, t - 1] >= 0)
            if t
            else np.zeros(n_particles, bool)
        )
        obs[inside & (state < s * k), t] = (state[inside & (state < s * k)] // k).astype(np.int16)
        obs[just_out, t] = s
    return sequences_from_padded(
        obs, start, feeder + 1, np.arange(n_dumps) * model.interval_s, model.interval_s, model.nx, model.ny
    )


def sequences_from_padded(
    obs: np.ndarray,
    start: np.ndarray,
    component: np.ndarray,
    snapshot_t: np.ndarray,
    interval_s: float,
    nx: int,
    ny: int,
) -> CompartmentSequences:
    """:class:`CompartmentSequences` from a (P, T) matrix of states at absolute dumps (-1:
    not in the record), each row one contiguous sequence starting at ``start``."""
    rows, cols = np.nonzero(obs >= 0)
    state = obs[rows, cols]
    new = np.ones(rows.size, bool)
    new[1:] = rows[1:] != rows[:-1]
    run_start = new.copy()
    run_start[1:] |= state[1:] != state[:-1]
    starts = np.flatnonzero(run_start)
    present = np.unique(rows)
    particle_of_run = np.searchsorted(present, rows[starts])
    offsets = np.searchsorted(particle_of_run, np.arange(present.size + 1)).astype(np.int64)
    return CompartmentSequences(
        ids=present.astype(np.int64) + 1,
        component=np.asarray(component)[present].astype(np.int8),
        start=np.asarray(start)[present].astype(np.int32),
        run_offsets=offsets,
        run_state=state[starts].astype(np.int16),
        run_length=np.diff(np.append(starts, rows.size)).astype(np.int32),
        snapshot_t=np.asarray(snapshot_t, float),
        interval_s=float(interval_s),
        nx=nx,
        ny=ny,
    )
