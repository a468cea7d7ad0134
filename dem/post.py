"""DEM post-processing: LIGGGHTS dumps -> the velocity table and the CQAs, in named steps.

Entry point::

    results = postprocess(dump_paths, dem_config, steady=SteadyStateRule(),
                          massflow_dir=None, solver_counters=None, provenance=None)

The steps, each a function of this module, in the order :func:`postprocess` runs them:

1. :class:`dem.tracking.DumpStream` -- one streaming pass over the dumps (memory flat in the number of
   snapshots): the particle log (entry, last sight, first time past the weir, vanishing),
   per-window velocity sums and the per-snapshot compartment counts. :class:`Postprocessor`
   keeps it open, so a run's dumps can be read as they are written and the steps below
   taken whenever needed.
2. :func:`velocity_table` -- the coupling table from the window sums.
3. :func:`dem.tracking.find_exits` -- when each particle left.
4. :func:`cqa_timeseries` -- outflow, inflow, C_A, RSDs and hold-up per sampling interval.
5. the steady state -- :class:`coupling.metrics.SteadyStateRule` on that hold-up.
6. :func:`tagged_rtd` -- residence times of the particles that entered in the tag window.
7. :func:`accounting` -- inserted = held + discharged, and the cross-checks with the solver.
8. :func:`particle_records` -- one row per particle: component, entry, exit.
9. :func:`measured_rates` -- transfer rates fitted to the ID-tracked moves between dumps
   (:mod:`dem.rates`), stored in the table beside the velocities.
10. :mod:`dem.steady` -- the steady-state quantities with 95 % intervals, and the pooled RTD.

The CQAs are defined in :mod:`coupling.metrics` (shared with the PBM); the conventions
below are the DEM's own.

* Time of a snapshot = step x the config's timestep; within half a timestep of a boundary
  counts as on it.
* Binning: :func:`coupling.compartments.bin_particles` (0 <= x <= L; y clipped).
* Velocity window k covers [k w, (k+1) w); the snapshot at exactly the end time of the run
  joins the last window. K = ceil(t_last / w). Means are ratios of sums over every
  particle-snapshot of the window.
* Sampling interval n covers (n d, (n+1) d] and is labelled by its end ``t_s = (n+1) d``:
  an event first *seen* in the dump at time t happened during (t - dump interval, t], so
  it belongs to the interval ending at or after t. Snapshot quantities (RSD, hold-up) of
  interval n are those of the last snapshot at or before ``t_s``.
* Exit of a particle, in order of preference: (1) the first snapshot in which it is past
  the weir (x > L), the paper's method; (2) otherwise, if the solver's discharge files are
  there and list its ID, the time written there (kept between its last sight and its
  vanishing: the file has 4 significant digits) or, without a time column, the first
  snapshot from which it is absent; (3) without such files, the first snapshot from which
  it is absent if it was last seen in the last axial slice (only the outlet face deletes
  particles there). An ID that vanishes otherwise is *lost*. Entry: first appearance.
* RTD: particles entering during (t_tag, t_tag + tag window] (t_tag: the steady-state time
  unless given); residence time = exit - entry; E(t) is their 1-s histogram over the
  recovered particles; mean and (population) variance from the individual times.
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from coupling.cache import CacheEntry
from coupling.compartments import grid_edges
from coupling.errors import ConfigError, DumpFormatError, ResultsError
from coupling.files import input_directory
from coupling.metrics import SteadyStateRule, outflow_fraction_a, random_mixture_rsd, rsd
from coupling.tables import VELOCITY_NAMES, VelocityTable
from dem import deck, phases
from dem.config import DemConfig
from dem.massflow import massflow_files
from dem.operating import operating_point
from dem.rates import fit_windows
from dem.resources import check_postprocess_resources
from dem.steady import STALE_INTERVALS, intervals_are_current, pooled_rtd, steady_quantities
from dem.summary import DemSummary
from dem.tracking import (
    EXIT_MASSFLOW,
    EXIT_PAST_WEIR,
    EXIT_VANISHED,
    SUM_ROWS,
    Accumulation,
    CompartmentSequences,
    DumpStream,
    Exits,
    compartment_sequences,
    find_exits,
    transition_counts,
)

__all__ = ["DemResults", "Postprocessor", "postprocess"]

#: names of the compartment sequences' arrays in a results file start with this
SEQUENCE_PREFIX = "sequences_"


@dataclass
class DemResults:
    """Everything the DEM side reports.

    * ``table``: velocity table (the coupling interface).
    * ``timeseries``: one row per sampling interval, columns t_s, outflow_A_per_s,
      outflow_B_per_s, outflow_per_s, inflow_per_s, C_A, rsd_outlet, rsd_outlet_floor,
      rsd_blender, rsd_blender_floor, holdup_A, holdup_B.
    * ``holdup``: per dump: t_s, holdup_A, holdup_B (particles with 0 <= x <= L).
    * ``rsd_by_slice`` / ``rsd_by_slice_floor``: (NX,) RSD of each axial slice at the last dump.
    * ``rtd``: t_s (1 s bin centres), E_per_s, count.
    * ``residence_times_s``: per recovered tagged particle [s].
    * ``particles``: :func:`particle_records`.
    * ``transitions``: (K, S+1, S+1) particle moves between consecutive dumps
      (:func:`dem.tracking.transition_counts`), what the measured rates were fitted to.
    * ``summary``: the scalars (:class:`dem.summary.DemSummary`).
    * ``sequences``: every particle's compartment at every dump, run-length encoded
      (:class:`dem.tracking.CompartmentSequences`), what the hidden-phase model is fitted
      to (:mod:`dem.phases`); None in results made before they were recorded.
    * ``snapshot_counts``: (dumps, 2, NX, NY) particles of A and B in each compartment at
      every dump of ``holdup``: what the steady quantities and their intervals are computed
      from (:func:`dem.steady.steady_quantities`), kept so that they can be recomputed
      without the dumps; the outlet's (:meth:`steady_outlet_counts`) are the counts at
      which the PBM's composition is sampled. None in results made before they were kept.
    """

    table: VelocityTable
    timeseries: pd.DataFrame
    holdup: pd.DataFrame
    rsd_by_slice: np.ndarray
    rsd_by_slice_floor: np.ndarray
    rtd: pd.DataFrame
    residence_times_s: np.ndarray
    particles: pd.DataFrame
    transitions: np.ndarray
    summary: DemSummary = field(default_factory=DemSummary)
    sequences: CompartmentSequences | None = None
    snapshot_counts: np.ndarray | None = None

    def to_cache_entry(self, provenance: dict[str, Any]) -> CacheEntry:
        frames = {"timeseries": self.timeseries, "holdup": self.holdup, "rtd": self.rtd, "particles": self.particles}
        arrays = {
            "rsd_by_slice": self.rsd_by_slice,
            "rsd_by_slice_floor": self.rsd_by_slice_floor,
            "residence_times_s": self.residence_times_s,
            "transitions": self.transitions,
        }
        if self.snapshot_counts is not None:
            arrays["snapshot_counts"] = self.snapshot_counts
        if self.sequences is not None:
            arrays.update(self.sequences.to_arrays(SEQUENCE_PREFIX))
        return CacheEntry(self.table, self.summary.record(), frames, arrays, provenance)

    @classmethod
    def from_cache_entry(cls, entry: CacheEntry) -> DemResults:
        """The results an entry stores. Steady quantities whose intervals an earlier version
        computed (:func:`dem.steady.intervals_are_current`) are computed again from the
        stored counts (:func:`recompute_steady`), so no stale interval is judged against;
        without counts to do it they stay, with a warning saying so."""
        source = entry.source or "the DEM results"
        arrays = {name: np.asarray(values) for name, values in entry.arrays.items()}
        sequences = CompartmentSequences.from_arrays(arrays, SEQUENCE_PREFIX, source)
        plain = {name: values for name, values in arrays.items() if not name.startswith(SEQUENCE_PREFIX)}
        if "snapshot_counts" in plain:
            check_snapshot_counts(plain["snapshot_counts"], entry.table, len(entry.frames.get("holdup", ())), source)
        results = cls(
            table=entry.table,
            summary=DemSummary.from_record(entry.summary),
            **entry.frames,
            **plain,
            sequences=sequences,
        )
        if intervals_are_current(results.summary.steady, entry.summary.get("pooled_rtd")):
            return results
        try:
            return recompute_steady(results)
        except ValueError:
            record = results.summary.record()
            record["warnings"] = [*record.get("warnings", []), STALE_INTERVALS]
            return dataclasses.replace(results, summary=DemSummary.from_record(record))

    def steady_outlet_counts(self) -> np.ndarray | None:
        """(steady dumps, 2, NY) particles of A and of B in each outlet compartment at each
        dump after the steady state (the dumps the DEM's outlet RSD averages over), from
        :meth:`compartment_counts`; None without them or without a steady state."""
        counts, t_ss = self.compartment_counts(), self.summary.steady_time
        if counts is None or t_ss is None:
            return None
        return counts[self.holdup["t_s"].to_numpy() > t_ss][:, :, -1, :]

    def compartment_counts(self) -> np.ndarray | None:
        """(dumps, 2, NX, NY) particles of A and of B in every compartment at every dump:
        :attr:`snapshot_counts`, or read off the sequences for results made before those
        were kept (they leave out the rare particles whose record was cut short, e.g. seen
        at x < 0 or skipping a dump: 0.2 % of the outlet's on the shipped reduced run, 7e-5
        of the hold-up); None without either."""
        seq = self.sequences
        if self.snapshot_counts is not None:
            return self.snapshot_counts
        if seq is None or (seq.nx, seq.ny) != (self.table.nx, self.table.ny) or seq.snapshot_t.size != len(self.holdup):
            return None
        return np.stack([seq.counts((c,)) for c in phases.FEEDERS], axis=1)


def check_snapshot_counts(counts: np.ndarray, table: VelocityTable, n_dumps: int, source: str) -> None:
    """Refuse (ResultsError naming ``source``) stored per-dump counts that are not
    (dumps, 2, NX, NY) non-negative integers on ``table``'s grid, one row per dump of the
    hold-up: the steady quantities recomputed from counts on another grid or of other dumps
    would be wrong without any error."""
    counts = np.asarray(counts)
    expected = (n_dumps, 2, table.nx, table.ny)
    if counts.shape != expected:
        raise ResultsError(
            f"{source}: stored array 'snapshot_counts' has shape {counts.shape}; (dumps, A and B, NX, NY) = "
            f"{expected} (the hold-up's dumps on the table's {table.nx} x {table.ny} grid) is valid"
        )
    if counts.size and (not np.issubdtype(counts.dtype, np.integer) or counts.min() < 0):
        raise ResultsError(
            f"{source}: stored array 'snapshot_counts' holds {counts.dtype} values down to {counts.min()}; "
            "particle counts (integers >= 0) are valid"
        )


def _compact_counts(counts: np.ndarray) -> np.ndarray:
    """Per-compartment particle counts in the smallest integer type that holds them."""
    counts = np.asarray(counts)
    dtype = np.int16 if counts.size == 0 or counts.max() < np.iinfo(np.int16).max else np.int32
    return counts.astype(dtype)


def sequence_diameters(sequences: CompartmentSequences, records: pd.DataFrame) -> np.ndarray | None:
    """The diameter [m] of each sequence's particle from the per-particle ``records`` (NaN
    where unknown); None when the records carry no diameters (made before they were kept)."""
    if "diameter_m" not in records:
        return None
    by_id = pd.Series(records["diameter_m"].to_numpy(float), index=records["id"].to_numpy(np.int64))
    return by_id.reindex(np.asarray(sequences.ids, np.int64)).to_numpy(float)


def fit_phases(
    table: VelocityTable,
    sequences: CompartmentSequences,
    steady_time_s: float | None,
    diameters: np.ndarray | None = None,
) -> tuple[VelocityTable, dict[str, Any] | None, str | None]:
    """The table carrying the hidden-phase transport (:func:`dem.phases.table_with_phases`,
    K chosen for the grid by :func:`dem.phases.choose_phases`, a chain per size class where
    ``diameters`` are known) fitted to the particles that entered during the steady period,
    with a record of the fit; a run with no steady state, or no particle entering after it,
    keeps its table without phases and gets a note saying why. Where the halves hold too few
    particles to choose, K is :data:`dem.phases.PHASES`."""
    if steady_time_s is None:
        return table, None, "no phase model: the run never reached the steady state it is fitted to"
    started = time.perf_counter()
    try:
        k, gain = phases.choose_phases(sequences, steady_time_s)
    except (ValueError, FloatingPointError, np.linalg.LinAlgError):  # too few data to compare: the default
        k, gain = phases.PHASES, None
    choosing_s = time.perf_counter() - started
    try:
        with_phases, fits = phases.table_with_phases(table, sequences, steady_time_s, k, diameters=diameters)
    except (ValueError, FloatingPointError, np.linalg.LinAlgError) as exc:  # too few data to fit
        return table, None, f"no phase model: {exc}"
    record = phases.fits_record(fits, with_phases.phases)
    # the fit's cost is the choice's fits and the model's: the budget judges both
    record = {
        **record,
        "wall_time_s": float(record["wall_time_s"]) + choosing_s,
        "moving_phases": k,
        "held_out_gain_per_step": gain,
    }
    return with_phases, record, None


#: A move between two consecutive dumps is far when it changes slice by more than this share
#: of the slices (the weir counted as slice NX): 4 or more of 10 slices in 0.1 s on the
#: shipped runs, 0.002-0.014 % of their slice-changing moves.
FAR_MOVE_SLICES = 1 / 3
#: Above this share of far moves a refit is said to be slow: the fit explains a far move by
#: several hidden jumps, and results where every particle's second run was five slices on
#: (about 5 % of the slice changes far) took 6 times a clean refit (188 s against 30 s).
FAR_MOVE_SHARE_SLOW = 1e-3


def far_move_share(sequences: CompartmentSequences) -> float:
    """The share of the particles' slice-changing moves between consecutive dumps that are
    far (:data:`FAR_MOVE_SLICES`); 0 when none changes slice."""
    owner = np.repeat(np.arange(sequences.n_particles), np.diff(sequences.run_offsets))
    state = sequences.run_state.astype(np.int64)
    slices = np.where(state >= sequences.n_cells, sequences.nx, state // sequences.ny)
    moved = np.abs(np.diff(slices))[owner[1:] == owner[:-1]]
    moved = moved[moved > 0]
    return float(np.mean(moved > FAR_MOVE_SLICES * sequences.nx)) if moved.size else 0.0


def slow_refit_note(results: DemResults) -> str | None:
    """A line saying why :func:`refit_phases` will take long, when the results' moves are
    far more often than a DEM run's (:data:`FAR_MOVE_SHARE_SLOW`); else None."""
    if results.sequences is None:
        return None
    share = far_move_share(results.sequences)
    if share <= FAR_MOVE_SHARE_SLOW:
        return None
    return (
        f"{share:.1%} of the particles' slice changes between dumps cross more than a third of the slices "
        "(under 0.02 % in the shipped DEM runs): the phase fit explains each by several jumps and may take "
        "several times longer than usual"
    )


def refit_phases(results: DemResults) -> DemResults:
    """``results`` with the hidden-phase model fitted again to its own compartment sequences
    (:func:`fit_phases`, this version's fit), for results made before the fit changed: no
    dumps are needed. The summary's ``phase_fit`` record and its phase note follow. Raises
    ValueError when the results carry no sequences or the fit fails (too few data; the
    results are then left as they are)."""
    if results.sequences is None:
        raise ValueError("the results carry no compartment sequences to refit the phase model to")
    table, record, note = fit_phases(
        results.table.replace(phases=None),
        results.sequences,
        results.summary.steady_time,
        sequence_diameters(results.sequences, results.particles),
    )
    if record is None:
        raise ValueError(note)
    summary = results.summary.record()
    summary["phase_fit"] = record
    summary["warnings"] = [w for w in summary.get("warnings", []) if not str(w).startswith("no phase model")]
    return dataclasses.replace(results, table=table, summary=DemSummary.from_record(summary))


def recompute_steady(results: DemResults) -> DemResults:
    """``results`` with the steady quantities and the pooled RTD computed again, this
    version's way (:mod:`dem.steady`), from what the results store: the compartment counts
    (:meth:`DemResults.compartment_counts`), the sampling intervals and the particle
    records; no dumps are needed. Raises ValueError when the results carry neither counts
    nor compartment sequences on the table's grid."""
    counts = results.compartment_counts()
    if counts is None:
        raise ValueError("the results carry neither compartment counts nor compartment sequences on the table's grid")
    summary = results.summary.record()
    t_s = results.holdup["t_s"].to_numpy(float)
    steady_time = results.summary.steady_time
    block_s = float(results.table.window_s)
    steady = steady_quantities(t_s, counts, results.timeseries, steady_time, block_s)
    little = steady.get("little_mean_residence_time_s", {}).get("value", float("nan"))
    summary["steady"] = steady
    summary["pooled_rtd"] = pooled_rtd(results.particles, steady_time, float(t_s[-1]), little, block_s)
    return dataclasses.replace(results, summary=DemSummary.from_record(summary))


def check_windows_covered(snapshot_t: np.ndarray, config: DemConfig) -> None:
    """Refuse (ConfigError) velocity windows longer than the dumps: the first window,
    [0, window_s), must end by the last dump, or the table would claim velocities over a
    span (and the PBM would run for a time) the DEM never simulated; the steady-state
    bootstrap's blocks are window_s long too."""
    window = float(config.tables.window_s)
    last = float(snapshot_t[-1]) + 0.5 * float(config.timestep_s)
    if window > last:
        raise ConfigError(
            f"tables.window_s = {window:g} s is longer than the dumps, which end at t = {float(snapshot_t[-1]):.6g} s "
            f"({snapshot_t.size} snapshots from t = {float(snapshot_t[0]):.6g} s): a velocity window needs dumps over its "
            f"whole length; choose tables.window_s <= {float(snapshot_t[-1]):.6g} s or give the dumps of a longer run"
        )


# ----------------------------------------------------------------------------- 2. table
def velocity_table(acc: Accumulation, config: DemConfig, attrs: dict[str, Any]) -> VelocityTable:
    """Window means (ratio of sums) of every compartment, as the coupling table."""
    g, tables = config.geometry, config.tables
    nx, ny, window = int(tables.nx), int(tables.ny), float(tables.window_s)
    tol = 0.5 * float(config.timestep_s)
    n_windows = max(1, math.ceil((float(acc.snapshot_t[-1]) - tol) / window))
    total = np.zeros((n_windows, len(SUM_ROWS), nx * ny))
    snapshots = np.zeros(n_windows)
    for k, sums in acc.window_sums.items():
        kk = min(max(k, 0), n_windows - 1)
        total[kk] += sums
        snapshots[kk] += acc.window_snapshots[k]
    row = {name: total[:, n] for n, name in enumerate(SUM_ROWS)}
    shape = (n_windows, nx, ny)
    samples = row["n_samples"]
    means = {
        name: np.where(samples > 0, row[name] / np.maximum(samples, 1), 0.0).reshape(shape) for name in VELOCITY_NAMES
    }
    per_snapshot = {
        name: np.where(snapshots[:, None] > 0, row[name] / np.maximum(snapshots, 1)[:, None], 0.0).reshape(shape)
        for name in ("count_A", "count_B")
    }
    attrs = {
        "source": "DEM (LIGGGHTS) dumps, dem.post.postprocess",
        **attrs,
        "timestep_s": float(config.timestep_s),
        "n_snapshots": int(acc.snapshot_t.size),
        "snapshots_per_window": snapshots.astype(int).tolist(),
    }
    x_edges, y_edges = grid_edges(float(g.length_m), float(g.diameter_m), nx, ny)
    return VelocityTable(
        t=np.arange(n_windows) * window,
        x_edges=x_edges,
        y_edges=y_edges,
        **means,
        **per_snapshot,
        n_samples=samples.reshape(shape).astype(np.int64),
        window_s=window,
        min_samples=int(tables.min_samples),
        attrs=attrs,
        operating_point=operating_point(config),
    )


# ----------------------------------------------------------------------------- 4. time series
def _per_interval(times: np.ndarray, interval: float, n_int: int, tol: float) -> np.ndarray:
    idx = np.clip(np.ceil((times - tol) / interval).astype(np.int64) - 1, 0, n_int - 1)
    return np.bincount(idx, minlength=n_int)[:n_int].astype(float)


def cqa_timeseries(acc: Accumulation, exits: Exits, config: DemConfig) -> pd.DataFrame:
    """One row per sampling interval (module docstring, "Sampling interval")."""
    interval = float(config.tables.sample_interval_s)
    tol = 0.5 * float(config.timestep_s)
    n_int = max(1, math.ceil((float(acc.snapshot_t[-1]) - tol) / interval))
    t_s = (np.arange(n_int) + 1) * interval
    kind, exited, seen = acc.particles.kind, exits.exited, acc.particles.seen
    out_a = _per_interval(exits.time[exited & (kind == 1)], interval, n_int, tol)
    out_b = _per_interval(exits.time[exited & (kind == 2)], interval, n_int, tol)
    out_all = _per_interval(exits.time[exited], interval, n_int, tol)
    inflow = _per_interval(acc.particles.first_t[seen], interval, n_int, tol)

    pick = np.searchsorted(acc.snapshot_t, t_s + tol, side="right") - 1
    counts = acc.snapshot_counts[np.clip(pick, 0, None)].copy()
    counts[pick < 0] = np.nan  # before the first dump: unknown
    a, b = counts[:, 0], counts[:, 1]
    flat_a, flat_b = a.reshape(n_int, -1), b.reshape(n_int, -1)
    return pd.DataFrame(
        {
            "t_s": t_s,
            "outflow_A_per_s": out_a / interval,
            "outflow_B_per_s": out_b / interval,
            "outflow_per_s": out_all / interval,
            "inflow_per_s": inflow / interval,
            "C_A": outflow_fraction_a(out_a, out_b),
            "rsd_outlet": rsd(a[:, -1, :], b[:, -1, :], axis=1),
            "rsd_outlet_floor": random_mixture_rsd(a[:, -1, :], b[:, -1, :], axis=1),
            "rsd_blender": rsd(flat_a, flat_b, axis=1),
            "rsd_blender_floor": random_mixture_rsd(flat_a, flat_b, axis=1),
            "holdup_A": flat_a.sum(axis=1),
            "holdup_B": flat_b.sum(axis=1),
        }
    )


def steady_means(timeseries: pd.DataFrame, steady_time_s: float | None) -> tuple[float, float]:
    """Mean outflow [1/s] and C_A over the sampling intervals after the steady state."""
    if steady_time_s is None:
        return float("nan"), float("nan")
    after = timeseries["t_s"].to_numpy() > steady_time_s
    if not after.any():
        return float("nan"), float("nan")
    out_a = timeseries["outflow_A_per_s"].to_numpy()[after].sum()
    out_b = timeseries["outflow_B_per_s"].to_numpy()[after].sum()
    outflow = timeseries["outflow_per_s"].to_numpy()[after].mean()
    return float(outflow), float(outflow_fraction_a(out_a, out_b))


# ----------------------------------------------------------------------------- 6. RTD
def tagged_rtd(acc: Accumulation, exits: Exits, tag_time_s: float, tag_window_s: float, tol: float):
    """``(rtd frame, residence times of the recovered, number tagged)`` for the particles
    that entered during (tag_time, tag_time + tag_window]."""
    empty = pd.DataFrame({"t_s": np.zeros(0), "E_per_s": np.zeros(0), "count": np.zeros(0, int)})
    if not np.isfinite(tag_time_s):
        return empty, np.zeros(0), 0
    first = acc.particles.first_t
    tagged = acc.particles.seen & (first > tag_time_s + tol) & (first <= tag_time_s + tag_window_s + tol)
    recovered = tagged & exits.exited
    residence = exits.time[recovered] - first[recovered]
    if not residence.size:
        return empty, residence, int(tagged.sum())
    edges = np.arange(0.0, math.floor(residence.max() + tol) + 2.0, 1.0)
    counts, _ = np.histogram(residence + tol, bins=edges)  # on an edge = in the bin above
    frame = pd.DataFrame({"t_s": edges[:-1] + 0.5, "E_per_s": counts / residence.size, "count": counts})
    return frame, residence, int(tagged.sum())


# ----------------------------------------------------------------------------- 7. accounting
def accounting(acc: Accumulation, exits: Exits, solver_counters: dict[str, float] | None) -> tuple[dict, list[str]]:
    """Particle balance and the cross-checks with the solver's own records.

    inserted (IDs seen) = held (in the last dump, not exited) + discharged; ``lost``
    counts IDs that vanished without a discharge record. ``discharge_crosscheck_diff``:
    our discharged particles already deleted by the last dump minus the solver's records
    of particles absent from the last dump (exact, by ID). The thermo counters are
    compared only when taken at the last dump's step."""
    log, exited = acc.particles, exits.exited
    seen = log.seen
    last_present = np.zeros(log.size, bool)
    last_present[acc.last_ids] = True
    vanished = seen & ~np.isnan(log.vanish_t)
    inserted = int(seen.sum()) + exits.massflow_unseen
    held = int((last_present & ~exited).sum())
    discharged = int(exited.sum()) + exits.massflow_unseen
    lost = int((vanished & ~exited).sum())
    pending = int((exited & last_present).sum())  # past the weir, not yet deleted
    warnings: list[str] = []
    if lost or inserted - held - discharged:
        warnings.append(f"accounting: inserted {inserted} != held {held} + discharged {discharged} (lost {lost})")
    out: dict[str, Any] = {
        "inserted": inserted,
        "held": held,
        "discharged": discharged,
        "lost": lost,
        "accounting_mismatch": inserted - held - discharged,
        "exits_seen_past_weir": int((exits.how == EXIT_PAST_WEIR).sum()),
        "exits_from_massflow": int((exits.how == EXIT_MASSFLOW).sum()),
        "exits_from_vanishing": int((exits.how == EXIT_VANISHED).sum()),
        "massflow_discharged": exits.massflow_discharged,
        "massflow_unseen_in_dumps": exits.massflow_unseen,
        "massflow_duplicate_ids": exits.massflow_duplicates,
        "discharged_pending_deletion": pending,
        "massflow_discharged_by_last_dump": exits.massflow_discharged_by_last_dump,
    }
    if exits.massflow_discharged_by_last_dump is not None:
        out["discharge_crosscheck_diff"] = (discharged - pending) - exits.massflow_discharged_by_last_dump
        if out["discharge_crosscheck_diff"]:
            warnings.append(
                f"discharge cross-check: {discharged - pending} deleted particles in the dumps vs "
                f"{exits.massflow_discharged_by_last_dump} in the solver's massflow files up to the last dump"
            )
    counters = dict(solver_counters or {})
    for key, value in counters.items():
        out[f"solver_{key}"] = value
    counters_step = counters.get("step")
    comparable = counters_step is None or int(counters_step) == acc.last_step
    if not comparable:
        warnings.append(
            f"solver thermo counters are at step {int(counters_step)}, the last dump at step "
            f"{acc.last_step}: not compared (the deck's end step is not a multiple of the dump interval)"
        )
    if counters.get("discharged") is not None and comparable:
        out["solver_discharge_diff"] = (discharged - pending) - counters["discharged"]
    if counters.get("inserted") is not None and comparable:
        out["solver_inserted_diff"] = inserted - counters["inserted"]
    if counters.get("atoms") is not None and comparable:
        # the dumps' own particle number against the solver's: a dump that lists particles
        # twice or loses some disagrees here, whatever the bookkeeping by ID says
        out["dumps_particles_last"] = int(acc.last_ids.size)
        out["solver_atoms_diff"] = int(acc.last_ids.size) - int(counters["atoms"])
        if out["solver_atoms_diff"]:
            warnings.append(
                f"the last dump lists {acc.last_ids.size} particles, the solver's thermo {int(counters['atoms'])} "
                f"at the same step (difference {out['solver_atoms_diff']:+d})"
            )
    out["positions_outside_vessel"] = int(log.outside_vessel)
    if log.outside_vessel:
        warnings.append(
            f"{log.outside_vessel} particle-snapshots lie outside the vessel (beyond a wall by more than "
            "the largest particle diameter): counted as they are"
        )
    out["ids_seen_after_discharge"] = int(exits.seen_after_discharge)
    if exits.seen_after_discharge:
        warnings.append(
            f"{exits.seen_after_discharge} particles are still in the dumps after the time of their "
            "discharge record (ID reuse, or dumps and discharge files of different runs?)"
        )
    out["ids_reappeared"] = int(acc.reappeared)
    return out, warnings


# ----------------------------------------------------------------------------- 8. records
def particle_records(acc: Accumulation, exits: Exits) -> pd.DataFrame:
    """One row per particle seen: ``id``, ``component`` (1 A, 2 B, 3 other), ``entry_t_s``
    and ``entry_y_m`` (first sight), ``exit_t_s`` (NaN while inside, or lost),
    ``exit_cell`` (flat index i * NY + j of the last compartment it was seen in before it
    left; -1 while inside) and ``diameter_m`` (at first sight; NaN when the dumps carry no
    radius). Files made before the diameter was recorded lack that column."""
    log = acc.particles
    ids = np.flatnonzero(log.seen)
    exited = exits.exited[ids]
    return pd.DataFrame(
        {
            "id": ids.astype(np.int64),
            "component": log.kind[ids].astype(np.int8),
            "entry_t_s": log.first_t[ids],
            "entry_y_m": log.first_y[ids],
            "exit_t_s": np.where(exited, exits.time[ids], np.nan),
            "exit_cell": np.where(exited, log.last_cell[ids], -1).astype(np.int32),
            "diameter_m": log.diameter[ids],
        }
    )


# ----------------------------------------------------------------------------- 9. rates
def measured_rates(
    acc: Accumulation, exits: Exits, table: VelocityTable, memo: dict | None = None
) -> tuple[VelocityTable, np.ndarray]:
    """The table with its measured rates (:mod:`dem.rates`, fitted per window to the moves
    between consecutive dumps), and the transition counts they were fitted to. A run with
    a single dump has no moves: its table is returned without rates. ``memo``: the fits of
    earlier calls (:func:`dem.rates.fit_windows`)."""
    nx, ny = table.nx, table.ny
    counts = transition_counts(acc, exits, table.n_windows, nx * ny)
    if not math.isfinite(acc.transition_interval_s) or not counts.any():
        return table, counts
    # the velocities' own threshold: below min_samples observations a compartment-window
    # carries no information, and the PBM fills it by the velocities' rule
    fits = fit_windows(counts, nx, ny, acc.transition_interval_s, min_observations=table.min_samples, memo=memo)
    if not fits.any_finite:
        return table, counts
    attrs = {
        **table.attrs,
        "rates_interval_s": float(acc.transition_interval_s),
        "rates_capped": int(fits.capped),
        "rates_unconverged_windows": [int(k) for k in fits.unconverged],
        "rates_finite": fits.finite,
        "rates_method": "maximum likelihood of the discretely observed nearest-neighbour chain (dem.rates)",
    }
    return table.replace(**fits.rates, attrs=attrs), counts


# ----------------------------------------------------------------------------- the whole
def postprocess(
    dump_paths: str | os.PathLike | Iterable[str | os.PathLike],
    config: DemConfig,
    steady: SteadyStateRule = SteadyStateRule(),
    massflow_dir: str | os.PathLike | None = None,
    solver_counters: dict[str, float] | None = None,
    provenance: dict[str, Any] | None = None,
    *,
    types_a: Sequence[int] | None = None,
    types_b: Sequence[int] | None = None,
    rtd_tag_time_s: float | None = None,
) -> DemResults:
    """Post-process LIGGGHTS dumps into the velocity table and the DEM CQAs.

    ``dump_paths``: glob pattern, path or sequence of dump files (columns id type x y vx vy
    at least, named in each ``ITEM: ATOMS`` header). ``config``: geometry, tables (nx, ny,
    window_s, sample_interval_s, min_samples, rtd_tag_window_s) and the timestep.
    ``steady``: the steady-state rule (the PBM is judged by the same one).
    ``massflow_dir``: directory of the solver's discharge files (exits of particles deleted
    between dumps; the discharge cross-check). ``solver_counters``: the solver's totals,
    e.g. {"discharged": n, "inserted": n, "step": s} from thermo. ``provenance``:
    attributes stored on the velocity table. ``rtd_tag_time_s``: start of the RTD tag
    window; default the steady-state time. ``types_a``/``types_b``: the atom types of A
    and B (default the deck's).

    ``summary`` keys: mean_residence_time_s, rtd_variance_s2, rtd_recovered_fraction,
    rtd_recovered_ok, rtd_tagged, rtd_tag_time_s, rtd_tag_window_s, steady_state_time_s,
    steady_state_reached, steady_outflow_per_s, steady_C_A, final_rsd_outlet(_floor),
    final_rsd_blender(_floor), holdup_final, t_end_s, last_dump_step, n_snapshots, the
    :func:`accounting` keys and warnings (list of text; flags for the caller to show).
    """
    post = Postprocessor(config, types_a, types_b)
    if massflow_dir is not None:  # refused before reading: the pass can be long
        input_directory(massflow_dir, "massflow directory (the solver's discharge files)", ConfigError)
    if not post.add(dump_paths):
        raise DumpFormatError(f"no complete snapshot in {dump_paths!r}")
    return post.results(steady, massflow_dir, solver_counters, provenance, rtd_tag_time_s=rtd_tag_time_s)


class Postprocessor:
    """:func:`postprocess` kept open while a run writes its dumps: :meth:`add` reads further
    dumps (each snapshot once, in time order across calls), :meth:`results` gives what the
    dumps read so far give, exactly what :func:`postprocess` of them in one pass gives, and
    leaves it open to read on. Window rate fits are kept between calls
    (:func:`dem.rates.fit_windows`' memo), so a window whose moves have not changed is not
    fitted again: a convergence check while the run goes costs the new dumps and windows."""

    def __init__(
        self, config: DemConfig, types_a: Sequence[int] | None = None, types_b: Sequence[int] | None = None
    ) -> None:
        types_a = tuple(types_a if types_a is not None else (deck.ATOM_TYPES["A"],))
        types_b = tuple(types_b if types_b is not None else (deck.ATOM_TYPES["B"],))
        check_postprocess_resources(config)  # a grid that cannot be held or fitted: refused before reading
        self.stream = DumpStream(config, types_a, types_b, record_sequences=True)
        self._window_fits: dict = {}

    @property
    def last_step(self) -> int:
        """The step of the last snapshot read; -1 before any."""
        return self.stream.last_step

    def add(self, dump_paths: str | os.PathLike | Iterable[str | os.PathLike]) -> int:
        """Read the snapshots of ``dump_paths``; returns how many."""
        return self.stream.add(dump_paths)

    def results(
        self,
        steady: SteadyStateRule = SteadyStateRule(),
        massflow_dir: str | os.PathLike | None = None,
        solver_counters: dict[str, float] | None = None,
        provenance: dict[str, Any] | None = None,
        *,
        rtd_tag_time_s: float | None = None,
    ) -> DemResults:
        """The results of the dumps read so far; the arguments are :func:`postprocess`'s."""
        return _results(
            self.stream, self._window_fits, steady, massflow_dir, solver_counters, provenance, rtd_tag_time_s
        )


def _results(
    stream: DumpStream,
    window_fits: dict,
    steady: SteadyStateRule,
    massflow_dir: str | os.PathLike | None,
    solver_counters: dict[str, float] | None,
    provenance: dict[str, Any] | None,
    rtd_tag_time_s: float | None,
) -> DemResults:
    config, types_a, types_b = stream.config, stream.types_a, stream.types_b
    tol = 0.5 * float(config.timestep_s)
    if massflow_dir is not None:  # given and missing would silently drop the discharge cross-check
        input_directory(massflow_dir, "massflow directory (the solver's discharge files)", ConfigError)
    acc = stream.accumulation()
    check_windows_covered(acc.snapshot_t, config)
    table = velocity_table(acc, config, dict(provenance or {}))
    exits = find_exits(acc, config, massflow_files(massflow_dir))
    table, transitions = measured_rates(acc, exits, table, window_fits)
    sequences = compartment_sequences(acc, exits, table.nx, table.ny)
    acc.visits.clear()  # the per-dump states now live, encoded, in ``sequences``
    records = particle_records(acc, exits)
    timeseries = cqa_timeseries(acc, exits, config)
    steady_time = steady.time(timeseries["t_s"], timeseries["holdup_A"] + timeseries["holdup_B"])
    t_ss = float("nan") if steady_time is None else steady_time
    steady_outflow, steady_c_a = steady_means(timeseries, steady_time)
    table, phase_fit, phase_note = fit_phases(table, sequences, steady_time, sequence_diameters(sequences, records))
    tag_time = float(rtd_tag_time_s) if rtd_tag_time_s is not None else t_ss
    tag_window = float(config.tables.rtd_tag_window_s)
    rtd, residence, n_tagged = tagged_rtd(acc, exits, tag_time, tag_window, tol)
    recovered = residence.size / n_tagged if n_tagged else float("nan")
    recovered_ok = bool(np.isfinite(recovered) and recovered >= 0.95)
    balance, warnings = accounting(acc, exits, solver_counters)
    block_s = float(config.tables.window_s)
    steady_stats = steady_quantities(acc.snapshot_t, acc.snapshot_counts, timeseries, steady_time, block_s)
    little = steady_stats.get("little_mean_residence_time_s", {}).get("value", float("nan"))
    pooled = pooled_rtd(records, steady_time, float(acc.snapshot_t[-1]), little, block_s)
    if acc.irregular_gaps:
        warnings.append(
            f"{acc.irregular_gaps} pairs of consecutive dumps are not {acc.transition_interval_s:g} s "
            "apart: their particle moves are left out of the measured rates"
        )

    notes = _run_notes(acc, types_a, types_b, tag_time, recovered_ok, recovered, n_tagged, pooled)
    last_a, last_b = acc.snapshot_counts[-1]
    summary: dict[str, Any] = {
        "mean_residence_time_s": float(residence.mean()) if residence.size else float("nan"),
        "rtd_variance_s2": float(residence.var()) if residence.size else float("nan"),
        "rtd_recovered_fraction": recovered,
        "rtd_recovered_ok": recovered_ok,
        "rtd_tagged": n_tagged,
        "rtd_tag_time_s": tag_time,
        "rtd_tag_window_s": tag_window,
        "steady_state_time_s": t_ss,
        "steady_state_reached": steady_time is not None,
        "steady_outflow_per_s": steady_outflow,
        "steady_C_A": steady_c_a,
        "final_rsd_outlet": float(rsd(last_a[-1], last_b[-1])),
        "final_rsd_outlet_floor": float(random_mixture_rsd(last_a[-1], last_b[-1])),
        "final_rsd_blender": float(rsd(last_a.ravel(), last_b.ravel())),
        "final_rsd_blender_floor": float(random_mixture_rsd(last_a.ravel(), last_b.ravel())),
        "holdup_final": float(last_a.sum() + last_b.sum()),
        "t_end_s": float(acc.snapshot_t[-1]),
        "last_dump_step": acc.last_step,
        "n_snapshots": int(acc.snapshot_t.size),
        **balance,
        "steady": steady_stats,
        "pooled_rtd": pooled,
        "phase_fit": phase_fit,
        "warnings": notes + warnings + ([phase_note] if phase_note else []),
    }
    holdup = pd.DataFrame(
        {
            "t_s": acc.snapshot_t,
            "holdup_A": acc.snapshot_counts[:, 0].sum(axis=(1, 2)),
            "holdup_B": acc.snapshot_counts[:, 1].sum(axis=(1, 2)),
        }
    )
    return DemResults(
        table=table,
        timeseries=timeseries,
        holdup=holdup,
        rsd_by_slice=rsd(last_a, last_b, axis=1),
        rsd_by_slice_floor=random_mixture_rsd(last_a, last_b, axis=1),
        rtd=rtd,
        residence_times_s=residence,
        particles=records,
        transitions=transitions,
        summary=DemSummary.from_record(summary),
        sequences=sequences,
        snapshot_counts=_compact_counts(acc.snapshot_counts),
    )


def _run_notes(
    acc: Accumulation,
    types_a: Any,
    types_b: Any,
    tag_time: float,
    recovered_ok: bool,
    recovered: float,
    n_tagged: int,
    pooled: dict[str, Any],
) -> list[str]:
    """What a reader of the summary must know about the run's data: particles counted in
    neither component, IDs that reappeared, an RTD that could not be tagged or was not
    recovered (the paper's 95 %)."""
    notes: list[str] = []
    if acc.other_types:
        notes.append(
            f"atom types {sorted(acc.other_types)} are neither A {types_a} nor B {types_b}; counted in neither"
        )
    if acc.reappeared:
        notes.append(f"{acc.reappeared} particle-snapshots reappeared after vanishing from the dumps (ID reuse?)")
    if not np.isfinite(tag_time):
        notes.append("steady state not detected: no RTD (tag window undefined)")
    elif not recovered_ok:
        notes.append(
            f"RTD: only {recovered:.1%} of the {n_tagged} tagged particles were recovered "
            "(the paper requires >= 95 %); run longer"
        )
    if pooled.get("n_entered") and not pooled["recovered_ok"]:
        notes.append(
            f"pooled RTD: only {pooled['recovered_fraction']['value']:.1%} of "
            f"{pooled['n_entered']} particles recovered within the horizon"
        )
    return notes
