"""DEM post-processing: dumps -> velocity table and CQAs (DESIGN.md definitions exactly).

Entry point::

    results = postprocess(dump_paths, config, massflow_dir=None, solver_counters=None,
                          provenance=None)          # -> DemResults
    results.table        # coupling.tables.VelocityTable (the DEM -> PBM interface)
    results.timeseries   # pandas DataFrame, one row per sampling interval
    results.rtd          # pandas DataFrame: t_s (bin centres), E_per_s, count
    results.summary      # dict of scalars (mirrors the PBM's summary keys)

The dumps are streamed once (memory flat in the number of snapshots; per-particle state is
a few arrays indexed by particle ID).

Conventions (documented choices where DESIGN.md leaves room)
------------------------------------------------------------
* Time of a snapshot = step x ``config.timestep_s``.
* Compartments: NX x NY bins over x in [0, L], y in [-D/2, D/2]; particles outside x in
  [0, L] are not binned; y is clipped into the outer bins (the barrel is round, so only
  rounding can put a particle centre outside).
* Velocity window k covers [k w, (k+1) w); the snapshot at exactly the end time of the run
  joins the last window. K = ceil(t_last / w).
* Sampling interval n covers (n d, (n+1) d] and is labelled by its end ``t_s = (n+1) d``:
  an event first *seen* in the dump at time t happened during (t - dump interval, t], so
  it belongs to the interval ending at or after t. Snapshot quantities (RSD, hold-up) of
  interval n are those of the last snapshot at or before ``t_s``.
* Exit (discharge) of a particle, in order of preference:
  1. the first snapshot in which it is past the weir (x > L) -- the paper's method;
  2. otherwise, if the solver's per-particle discharge file (``fix massflow/mesh ... file``)
     is available and lists its ID: the time written there (``writeTime``) or, if the file
     has no time column, the first snapshot from which it is absent;
  3. otherwise, without such files: the first snapshot from which it is absent, if its last
     position was in the last axial slice (it can only have been deleted by the outlet
     face); else it is counted as *lost* (left through the domain boundary).
  With the massflow files present, an ID that vanishes without being listed there is lost.
* Entry of a particle: its first appearance in the dumps.
* Random-mixture floor of an RSD over compartments c with n_c particles and pooled A
  fraction p: with X_c ~ Binomial(n_c, p), the expected sample variance of the fractions
  X_c/n_c across m compartments is exactly mean_c p(1-p)/n_c; the floor is its square root
  over p (analytic, deterministic; empty compartments left out as in the RSD itself).
* Steady state: the first sampling time t at which, over the trailing window W
  (``steady_window_s``, default the velocity window), the hold-up changed by at most
  ``holdup_tol`` (5 %) of its value and the mean outflow rate is within ``flow_tol``
  (10 %) of the mean inflow (first appearances) over the same window.
* Accounting and cross-checks: inserted (IDs seen) = held (in the last dump, not exited)
  + discharged; ``lost`` counts IDs that vanished without a discharge record, and
  ``accounting_mismatch`` = inserted - held - discharged is reported, never hidden.
  ``discharge_crosscheck_diff`` = our discharged particles already deleted by the last dump
  minus the solver's massflow records of particles absent from the last dump (exact, by ID);
  the thermo counters (``solver_counters``) are compared only if taken at the last dump's
  step (``solver_*_diff``), otherwise a warning says why not.
* RTD: particles entering during (t_ss, t_ss + tag window] are tagged; residence time =
  exit - entry; E(t) is their 1 s histogram normalised to unit area over the recovered
  particles; mean and variance (population) from the individual residence times.
"""

from __future__ import annotations

import glob as _glob
import math
import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from coupling.errors import DumpFormatError
from coupling.tables import VelocityTable
from dem import deck
from dem.dumps import iter_snapshots

__all__ = [
    "DemResults",
    "postprocess",
    "random_mixture_rsd",
    "rsd_of_fractions",
    "read_massflow",
    "massflow_files",
    "massflow_patterns",
]

REQUIRED_COLUMNS = ("id", "type", "x", "y", "vx", "vy")


@dataclass
class DemResults:
    """Everything the DEM side reports. Field names match ``workflows.report.SideResults``.

    * ``table``: velocity table (coupling interface).
    * ``timeseries``: columns t_s, outflow_A_per_s, outflow_B_per_s, C_A, rsd_outlet,
      rsd_outlet_floor, rsd_blender, rsd_blender_floor, holdup_A, holdup_B, inflow_per_s.
    * ``holdup``: per dump: t_s, holdup_A, holdup_B (particles with 0 <= x <= L).
    * ``rsd_by_slice`` / ``rsd_by_slice_floor``: (NX,) RSD of each axial slice at the last dump.
    * ``rtd``: t_s (1 s bin centres), E_per_s, count.
    * ``residence_times_s``: per recovered tagged particle [s].
    * ``summary``: scalars (see :func:`postprocess`).
    """

    table: VelocityTable
    timeseries: pd.DataFrame
    holdup: pd.DataFrame
    rsd_by_slice: np.ndarray
    rsd_by_slice_floor: np.ndarray
    rtd: pd.DataFrame
    residence_times_s: np.ndarray
    summary: dict[str, Any] = field(default_factory=dict)


# ----------------------------------------------------------------------------- statistics
def rsd_of_fractions(count_a: np.ndarray, count_b: np.ndarray) -> float:
    """RSD (sample SD / mean, eq. 6) of the A fraction across compartments, empty ones left
    out; NaN with fewer than two non-empty compartments or a zero mean."""
    a = np.asarray(count_a, dtype=float).ravel()
    n = a + np.asarray(count_b, dtype=float).ravel()
    keep = n > 0
    if keep.sum() < 2:
        return float("nan")
    f = a[keep] / n[keep]
    mean = f.mean()
    return float(f.std(ddof=1) / mean) if mean > 0 else float("nan")


def random_mixture_rsd(count_a: np.ndarray, count_b: np.ndarray) -> float:
    """RSD floor of a random (binomial) mixture with the same per-compartment counts and
    the same pooled A fraction p: sqrt(mean_c p (1-p) / n_c) / p over non-empty compartments
    (the exact expected sample variance of the fractions; see module docstring)."""
    a = np.asarray(count_a, dtype=float).ravel()
    n = a + np.asarray(count_b, dtype=float).ravel()
    keep = n > 0
    if keep.sum() < 2:
        return float("nan")
    p = a[keep].sum() / n[keep].sum()
    if p <= 0:
        return float("nan")
    return float(math.sqrt(np.mean(p * (1 - p) / n[keep])) / p)


# ----------------------------------------------------------------------------- massflow
def massflow_patterns() -> list[str]:
    """Glob patterns of the solver's per-particle discharge files, relative to the run
    directory: the deck's ``MASSFLOW_FILES`` plus any suffix (``.0``/``.1`` per MPI rank,
    ``.upto<step>`` for the part of a resumed run before its restart)."""
    names = list(deck.MASSFLOW_FILES.values()) or ["massflow*"]
    return [pattern for name in names for pattern in (name, name + ".*")]


def massflow_files(directory: str | os.PathLike | None, patterns: Sequence[str] | None = None) -> list[Path]:
    """The solver's per-particle discharge files found in ``directory`` (see
    :func:`massflow_patterns`); empty if ``directory`` is None or holds none."""
    if directory is None:
        return []
    found: set[Path] = set()
    for pattern in patterns or massflow_patterns():
        found.update(Path(p) for p in _glob.glob(str(Path(directory) / pattern)))
    return sorted(p for p in found if p.is_file())


def read_massflow(paths: Sequence[str | os.PathLike]) -> tuple[np.ndarray, np.ndarray | None]:
    """IDs (int64) and, if every file has a ``time`` column, discharge times [s] from
    ``fix massflow/mesh ... file`` outputs (header ``# ID [time] diameter x y z u v w``).

    Raises DumpFormatError naming file and line on malformed rows."""
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
                if lineno == len(lines):  # last line of a killed run's file
                    continue
                raise DumpFormatError(f"{path}: line {lineno}: malformed massflow row {line[:80]!r}") from None
        ids.append(np.asarray(rows_id, dtype=np.int64))
        times.append(np.asarray(rows_t, dtype=float))
    all_ids = np.concatenate(ids) if ids else np.zeros(0, np.int64)
    all_t = np.concatenate(times) if (ids and have_time) else None
    return all_ids, all_t


# ----------------------------------------------------------------------------- accumulator
class _Grow:
    """Per-particle arrays indexed by ID, grown by doubling."""

    def __init__(self) -> None:
        self.size = 0
        self.first_t = np.zeros(0)
        self.last_t = np.zeros(0)
        self.last_x = np.zeros(0)
        self.exit_t = np.zeros(0)
        self.vanish_t = np.zeros(0)
        self.kind = np.zeros(0, np.int8)  # 0 unseen, 1 A, 2 B, 3 other type
        self.present = np.zeros(0, bool)

    def ensure(self, max_id: int) -> None:
        if max_id < self.size:
            return
        new = max(1024, 2 * self.size, max_id + 1)
        for name, fill in (("first_t", np.nan), ("last_t", np.nan), ("last_x", np.nan), ("exit_t", np.nan), ("vanish_t", np.nan)):
            arr = np.full(new, fill)
            arr[: self.size] = getattr(self, name)
            setattr(self, name, arr)
        kind = np.zeros(new, np.int8)
        kind[: self.size] = self.kind
        self.kind = kind
        present = np.zeros(new, bool)
        present[: self.size] = self.present
        self.present = present
        self.size = new


def postprocess(
    dump_paths: str | os.PathLike | Iterable[str | os.PathLike],
    config,
    massflow_dir: str | os.PathLike | None = None,
    solver_counters: dict[str, float] | None = None,
    provenance: dict[str, Any] | None = None,
    *,
    types_a: Sequence[int] | None = None,
    types_b: Sequence[int] | None = None,
    rtd_tag_time_s: float | None = None,
    steady_window_s: float | None = None,
    holdup_tol: float = 0.05,
    flow_tol: float = 0.10,
) -> DemResults:
    """Post-process LIGGGHTS dumps into the velocity table and the DEM CQAs.

    Parameters
    ----------
    dump_paths: glob pattern, path or sequence of dump files (columns id type x y vx vy
        at least, named in each ``ITEM: ATOMS`` header).
    config: a ``DemConfig`` or the pipeline ``Config`` (its ``.dem`` is used): geometry
        (length_m, diameter_m), tables (nx, ny, window_s, sample_interval_s, min_samples,
        rtd_tag_window_s) and the timestep (step -> time).
    massflow_dir: directory holding the solver's massflow/mesh per-particle files (exit
        detection for particles deleted between dumps, and the discharge cross-check).
    solver_counters: the solver's own totals, e.g. {"discharged": n, "inserted": n} from
        thermo, reported beside ours (differences in ``summary``).
    provenance: attributes stored on the velocity table (input_hash, liggghts_version,
        preset, config TOML...).
    rtd_tag_time_s: start of the RTD tag window; default the detected steady-state time.

    Returns :class:`DemResults`. ``summary`` keys: mean_residence_time_s, rtd_variance_s2,
    rtd_recovered_fraction, rtd_recovered_ok, rtd_tagged, rtd_tag_time_s,
    steady_state_time_s, steady_state_reached, steady_outflow_per_s, steady_C_A,
    final_rsd_outlet(+_floor), final_rsd_blender(+_floor), holdup_final, inserted, held,
    discharged, lost, accounting_mismatch, exits_seen_past_weir, exits_from_massflow,
    exits_from_vanishing, massflow_discharged, discharge_crosscheck_diff, warnings (list).
    """
    dem = getattr(config, "dem", config)
    geometry, tables = dem.geometry, dem.tables
    dt = float(dem.timestep_s)
    length, diameter = float(geometry.length_m), float(geometry.diameter_m)
    nx, ny = int(tables.nx), int(tables.ny)
    window = float(tables.window_s)
    interval = float(tables.sample_interval_s)
    types_a = tuple(types_a if types_a is not None else (deck.ATOM_TYPES["A"],))
    types_b = tuple(types_b if types_b is not None else (deck.ATOM_TYPES["B"],))
    steady_window_s = float(steady_window_s if steady_window_s is not None else window)
    dx, dy = length / nx, diameter / ny
    # Snapshot times are step x dt: within half a timestep of a boundary counts as on it.
    tol = 0.5 * dt
    ncell = nx * ny

    particles = _Grow()
    window_sums: dict[int, np.ndarray] = {}  # k -> (7, ncell): 4 velocity sums, n, A, B
    window_snaps: dict[int, int] = {}
    snap_t: list[float] = []
    snap_rows: list[tuple[float, ...]] = []  # holdup_A, holdup_B, rsd_out, floor_out, rsd_all, floor_all
    last_counts = None
    prev_ids = np.zeros(0, np.int64)
    n_snapshots = 0
    reappeared = 0
    other_types: set[int] = set()

    last_step = -1
    for snap in iter_snapshots(dump_paths, columns=REQUIRED_COLUMNS):
        t = snap.time_s(dt)
        last_step = snap.step
        n_snapshots += 1
        ids = snap["id"].astype(np.int64)
        ptype = snap["type"].astype(np.int64)
        x, y, vx, vy = snap["x"], snap["y"], snap["vx"], snap["vy"]
        if ids.size:
            if ids.min() < 0:
                raise DumpFormatError(f"{snap.source}: negative particle id at step {snap.step}")
            particles.ensure(int(ids.max()))
        is_a = np.isin(ptype, types_a)
        is_b = np.isin(ptype, types_b)
        if not (is_a | is_b).all():
            other_types.update(int(v) for v in np.unique(ptype[~(is_a | is_b)]))

        # entries, reappearances, vanishings
        new = np.isnan(particles.first_t[ids])
        particles.first_t[ids[new]] = t
        particles.kind[ids] = np.where(is_a, 1, np.where(is_b, 2, 3))
        back = ~new & ~np.isnan(particles.vanish_t[ids])
        if back.any():
            reappeared += int(back.sum())
            particles.vanish_t[ids[back]] = np.nan
        particles.present[ids] = True
        gone = prev_ids[~particles.present[prev_ids]]
        particles.vanish_t[gone] = t
        particles.present[ids] = False  # reset the scratch flags
        prev_ids = ids
        particles.last_t[ids] = t
        particles.last_x[ids] = x

        # exits seen past the weir
        past = (x > length) & np.isnan(particles.exit_t[ids])
        particles.exit_t[ids[past]] = t

        # binning
        inside = (x >= 0) & (x <= length)
        i = np.minimum((x[inside] / dx).astype(np.int64), nx - 1)
        j = np.clip(np.floor((y[inside] + diameter / 2) / dy).astype(np.int64), 0, ny - 1)
        cell = i * ny + j
        vxi, vyi = vx[inside], vy[inside]
        a_in, b_in = is_a[inside], is_b[inside]
        sums = np.empty((7, ncell))
        sums[0] = np.bincount(cell, np.maximum(vxi, 0), ncell)
        sums[1] = np.bincount(cell, np.maximum(-vxi, 0), ncell)
        sums[2] = np.bincount(cell, np.maximum(vyi, 0), ncell)
        sums[3] = np.bincount(cell, np.maximum(-vyi, 0), ncell)
        sums[4] = np.bincount(cell, minlength=ncell)
        sums[5] = np.bincount(cell[a_in], minlength=ncell)
        sums[6] = np.bincount(cell[b_in], minlength=ncell)
        k = int(math.floor((t + tol) / window))
        if k in window_sums:
            window_sums[k] += sums
            window_snaps[k] += 1
        else:
            window_sums[k] = sums
            window_snaps[k] = 1

        count_a = sums[5].reshape(nx, ny)
        count_b = sums[6].reshape(nx, ny)
        last_counts = (count_a.copy(), count_b.copy())
        snap_t.append(t)
        snap_rows.append(
            (
                float(a_in.sum()),
                float(b_in.sum()),
                rsd_of_fractions(count_a[-1], count_b[-1]),
                random_mixture_rsd(count_a[-1], count_b[-1]),
                rsd_of_fractions(count_a, count_b),
                random_mixture_rsd(count_a, count_b),
            )
        )

    if n_snapshots == 0:
        raise DumpFormatError(f"no complete snapshot in {dump_paths!r}")
    warn_list: list[str] = []
    if other_types:
        warn_list.append(f"atom types {sorted(other_types)} are neither A {types_a} nor B {types_b}; counted in neither")
    if reappeared:
        warn_list.append(f"{reappeared} particle-snapshots reappeared after vanishing from the dumps (ID reuse?)")

    t_snap = np.asarray(snap_t)
    t_last = float(t_snap[-1])

    # ---- velocity table
    n_windows = max(1, math.ceil((t_last - tol) / window))
    acc = np.zeros((n_windows, 7, ncell))
    nsnap = np.zeros(n_windows)
    for k, sums in window_sums.items():
        kk = min(max(k, 0), n_windows - 1)
        acc[kk] += sums
        nsnap[kk] += window_snaps[k]
    nsamp = acc[:, 4]
    with np.errstate(invalid="ignore", divide="ignore"):
        means = np.where(nsamp[:, None, :] > 0, acc[:, :4] / np.maximum(nsamp, 1)[:, None, :], 0.0)
        per_snap = np.where(nsnap[:, None, None] > 0, acc[:, 5:7] / np.maximum(nsnap, 1)[:, None, None], 0.0)
    shape = (n_windows, nx, ny)
    attrs = dict(provenance or {})
    attrs.setdefault("source", "DEM (LIGGGHTS) dumps, dem.post.postprocess")
    attrs["timestep_s"] = dt
    attrs["n_snapshots"] = n_snapshots
    attrs["snapshots_per_window"] = nsnap.astype(int).tolist()
    table = VelocityTable(
        t=np.arange(n_windows) * window,
        x_edges=np.linspace(0.0, length, nx + 1),
        y_edges=np.linspace(-diameter / 2, diameter / 2, ny + 1),
        vx_pos=means[:, 0].reshape(shape),
        vx_neg=means[:, 1].reshape(shape),
        vy_pos=means[:, 2].reshape(shape),
        vy_neg=means[:, 3].reshape(shape),
        count_A=per_snap[:, 0].reshape(shape),
        count_B=per_snap[:, 1].reshape(shape),
        n_samples=nsamp.reshape(shape).astype(np.int64),
        window_s=window,
        min_samples=int(tables.min_samples),
        attrs=attrs,
    )

    # ---- exits: dumps, then massflow files, then vanishing
    seen = ~np.isnan(particles.first_t)
    exit_how = np.zeros(particles.size, np.int8)  # 1 past weir, 2 massflow, 3 vanished in last slice
    exit_how[seen & ~np.isnan(particles.exit_t)] = 1
    vanished = seen & np.isnan(particles.exit_t) & ~np.isnan(particles.vanish_t)
    mf_paths = massflow_files(massflow_dir)
    massflow_discharged = None
    massflow_discharged_by_last_dump = None
    massflow_duplicates = 0
    massflow_unseen = 0
    if mf_paths:
        # Parts set aside before a resume (``.upto<step>``) first, so that a particle listed
        # both there (discharged just after the restart step, within the file's 4-digit time
        # resolution) and in the resumed run's files keeps the resumed run's record.
        mf_paths = sorted(mf_paths, key=lambda p: (".upto" not in p.name, p.name))
        mf_ids, mf_t = read_massflow(mf_paths)
        _, last_index = np.unique(mf_ids[::-1], return_index=True)
        keep = np.sort(mf_ids.size - 1 - last_index)
        massflow_duplicates = int(mf_ids.size - keep.size)
        mf_ids = mf_ids[keep]
        mf_t = mf_t[keep] if mf_t is not None else None
        massflow_discharged = int(mf_ids.size)
        in_range = mf_ids < particles.size
        # Compare at the same instant: a particle deleted after the last dump is still in it.
        # (Exact; the file's time column has only 4 significant digits.)
        in_last_dump = np.zeros(mf_ids.size, bool)
        in_last_dump[in_range] = np.isin(mf_ids[in_range], prev_ids)
        massflow_discharged_by_last_dump = int((~in_last_dump).sum())
        massflow_unseen = int((~in_range).sum() + (~seen[mf_ids[in_range]]).sum())
        listed = np.zeros(particles.size, bool)
        listed[mf_ids[in_range]] = True
        use = vanished & listed
        if mf_t is not None:
            tmap = np.full(particles.size, np.nan)
            tmap[mf_ids[in_range]] = mf_t[in_range]
            # the file's time has 4 significant digits: keep it between last sight and vanishing
            particles.exit_t[use] = np.clip(tmap[use], particles.last_t[use], particles.vanish_t[use])
        else:
            particles.exit_t[use] = particles.vanish_t[use]
        exit_how[use] = 2
    else:
        use = vanished & (particles.last_x >= length - dx)
        particles.exit_t[use] = particles.vanish_t[use]
        exit_how[use] = 3
    lost_mask = vanished & (exit_how == 0)

    exited = exit_how > 0
    kind = particles.kind
    last_present = np.zeros(particles.size, bool)
    last_present[prev_ids] = True
    held_mask = last_present & ~exited

    # ---- sampling grid
    n_int = max(1, math.ceil((t_last - tol) / interval))
    t_s = (np.arange(n_int) + 1) * interval

    def per_interval(times: np.ndarray) -> np.ndarray:
        idx = np.clip(np.ceil((times - tol) / interval).astype(np.int64) - 1, 0, n_int - 1)
        return np.bincount(idx, minlength=n_int)[:n_int].astype(float)

    out_a = per_interval(particles.exit_t[exited & (kind == 1)])
    out_b = per_interval(particles.exit_t[exited & (kind == 2)])
    out_all = per_interval(particles.exit_t[exited])
    inflow = per_interval(particles.first_t[seen])
    with np.errstate(invalid="ignore", divide="ignore"):
        c_a = np.where(out_a + out_b > 0, out_a / (out_a + out_b), np.nan)
    rows = np.asarray(snap_rows)
    pick = np.searchsorted(t_snap, t_s + tol, side="right") - 1
    valid_pick = pick >= 0
    pick = np.clip(pick, 0, None)
    sampled = np.where(valid_pick[:, None], rows[pick], np.nan)
    timeseries = pd.DataFrame(
        {
            "t_s": t_s,
            "outflow_A_per_s": out_a / interval,
            "outflow_B_per_s": out_b / interval,
            "outflow_per_s": out_all / interval,
            "inflow_per_s": inflow / interval,
            "C_A": c_a,
            "rsd_outlet": sampled[:, 2],
            "rsd_outlet_floor": sampled[:, 3],
            "rsd_blender": sampled[:, 4],
            "rsd_blender_floor": sampled[:, 5],
            "holdup_A": sampled[:, 0],
            "holdup_B": sampled[:, 1],
        }
    )
    holdup = pd.DataFrame({"t_s": t_snap, "holdup_A": rows[:, 0], "holdup_B": rows[:, 1]})

    # ---- RSD by slice at the last dump
    ca, cb = last_counts
    rsd_slice = np.array([rsd_of_fractions(ca[i], cb[i]) for i in range(nx)])
    rsd_slice_floor = np.array([random_mixture_rsd(ca[i], cb[i]) for i in range(nx)])

    # ---- steady state
    hold = timeseries["holdup_A"].to_numpy() + timeseries["holdup_B"].to_numpy()
    lag = max(1, int(round(steady_window_s / interval)))
    t_ss = float("nan")
    for n in range(lag, n_int):
        h_now, h_then = hold[n], hold[n - lag]
        if not (np.isfinite(h_now) and np.isfinite(h_then)) or h_now <= 0:
            continue
        inflow_mean = inflow[n - lag + 1 : n + 1].mean()
        outflow_mean = out_all[n - lag + 1 : n + 1].mean()
        if abs(h_now - h_then) <= holdup_tol * h_now and inflow_mean > 0 and abs(outflow_mean - inflow_mean) <= flow_tol * inflow_mean:
            t_ss = float(t_s[n])
            break
    after = t_s > t_ss if np.isfinite(t_ss) else np.zeros(n_int, bool)
    steady_outflow = float(out_all[after].sum() / (after.sum() * interval)) if after.any() else float("nan")
    steady_c_a = float(out_a[after].sum() / (out_a[after].sum() + out_b[after].sum())) if after.any() and (out_a[after].sum() + out_b[after].sum()) > 0 else float("nan")

    # ---- RTD
    tag_time = float(rtd_tag_time_s) if rtd_tag_time_s is not None else t_ss
    tag_window = float(tables.rtd_tag_window_s)
    residence = np.zeros(0)
    n_tagged = 0
    if np.isfinite(tag_time):
        first = particles.first_t
        tagged = seen & (first > tag_time + tol) & (first <= tag_time + tag_window + tol)
        n_tagged = int(tagged.sum())
        rec = tagged & exited
        residence = particles.exit_t[rec] - first[rec]
    recovered_fraction = residence.size / n_tagged if n_tagged else float("nan")
    if residence.size:
        edges = np.arange(0.0, math.floor(residence.max() + tol) + 2.0, 1.0)
        counts, _ = np.histogram(residence + tol, bins=edges)  # on an edge = in the bin above
        rtd = pd.DataFrame({"t_s": edges[:-1] + 0.5, "E_per_s": counts / (residence.size * 1.0), "count": counts})
        mean_rt, var_rt = float(residence.mean()), float(residence.var())
    else:
        rtd = pd.DataFrame({"t_s": np.zeros(0), "E_per_s": np.zeros(0), "count": np.zeros(0, int)})
        mean_rt = var_rt = float("nan")
    recovered_ok = bool(np.isfinite(recovered_fraction) and recovered_fraction >= 0.95)
    if not np.isfinite(tag_time):
        warn_list.append("steady state not detected: no RTD (tag window undefined)")
    elif not recovered_ok:
        warn_list.append(
            f"RTD: only {recovered_fraction:.1%} of the {n_tagged} tagged particles were recovered "
            "(the paper requires >= 95 %); run longer"
        )

    # ---- accounting
    inserted = int(seen.sum()) + massflow_unseen
    held = int(held_mask.sum())
    discharged = int(exited.sum()) + massflow_unseen
    lost = int(lost_mask.sum())
    mismatch = inserted - held - discharged
    if lost or mismatch:
        warn_list.append(f"accounting: inserted {inserted} != held {held} + discharged {discharged} (lost {lost})")
    counters = dict(solver_counters or {})
    summary: dict[str, Any] = {
        "mean_residence_time_s": mean_rt,
        "rtd_variance_s2": var_rt,
        "rtd_recovered_fraction": recovered_fraction,
        "rtd_recovered_ok": recovered_ok,
        "rtd_tagged": n_tagged,
        "rtd_tag_time_s": tag_time,
        "rtd_tag_window_s": tag_window,
        "steady_state_time_s": t_ss,
        "steady_state_reached": bool(np.isfinite(t_ss)),
        "steady_outflow_per_s": steady_outflow,
        "steady_C_A": steady_c_a,
        "final_rsd_outlet": float(rows[-1, 2]),
        "final_rsd_outlet_floor": float(rows[-1, 3]),
        "final_rsd_blender": float(rows[-1, 4]),
        "final_rsd_blender_floor": float(rows[-1, 5]),
        "holdup_final": float(rows[-1, 0] + rows[-1, 1]),
        "t_end_s": t_last,
        "last_dump_step": last_step,
        "n_snapshots": n_snapshots,
        "inserted": inserted,
        "held": held,
        "discharged": discharged,
        "lost": lost,
        "accounting_mismatch": mismatch,
        "exits_seen_past_weir": int((exit_how == 1).sum()),
        "exits_from_massflow": int((exit_how == 2).sum()),
        "exits_from_vanishing": int((exit_how == 3).sum()),
        "massflow_discharged": massflow_discharged,
        "massflow_unseen_in_dumps": massflow_unseen,
        "massflow_duplicate_ids": massflow_duplicates,
    }
    # Cross-check with the solver's own counters: only particles already deleted by the outlet
    # face are in its count; those past the weir but not yet deleted are in ours only.
    pending = int((exited & last_present).sum())
    summary["discharged_pending_deletion"] = pending
    summary["massflow_discharged_by_last_dump"] = massflow_discharged_by_last_dump
    if massflow_discharged_by_last_dump is not None:
        summary["discharge_crosscheck_diff"] = (discharged - pending) - massflow_discharged_by_last_dump
        if summary["discharge_crosscheck_diff"]:
            warn_list.append(
                f"discharge cross-check: {discharged - pending} deleted particles in the dumps vs "
                f"{massflow_discharged_by_last_dump} in the solver's massflow files up to the last dump"
            )
    for key, value in counters.items():
        summary[f"solver_{key}"] = value
    # The thermo counters are only comparable when taken at the last dump's step.
    counters_step = counters.get("step")
    comparable = counters_step is None or int(counters_step) == last_step
    if not comparable:
        warn_list.append(
            f"solver thermo counters are at step {int(counters_step)}, the last dump at step {last_step}: "
            "not compared (the deck's end step is not a multiple of the dump interval)"
        )
    if counters.get("discharged") is not None and comparable:
        summary["solver_discharge_diff"] = (discharged - pending) - counters["discharged"]
    if counters.get("inserted") is not None and comparable:
        summary["solver_inserted_diff"] = inserted - counters["inserted"]
    # Flags, not Python warnings: the caller (CLI, report) shows them; a library warning would
    # turn into an exception wherever warnings are errors.
    summary["warnings"] = warn_list
    return DemResults(
        table=table,
        timeseries=timeseries,
        holdup=holdup,
        rsd_by_slice=rsd_slice,
        rsd_by_slice_floor=rsd_slice_floor,
        rtd=rtd,
        residence_times_s=residence,
        summary=summary,
    )
