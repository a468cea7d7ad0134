"""Would compartments stacked in height give the chain the DEM's dispersion? Rates fitted on
x-y-z grids, and the pooled RTD of each chain against the DEM's
(``pbmdem study layers --run-dir runs/<key> --results <dem-*.h5> [--preset P]``).

The measured-rate PBM's compartments span the vessel's full height, so the thin stream the
blades throw over the bed and the slow bed below it share one state; its pooled RTD has too
little variance, and less the finer the axial grid. This asks how much of that is the
missing vertical structure. For each grid ``NXxNY`` or ``NXxNYxNZ`` it bins every
particle of the run's dumps in (x, y, height layer), the NZ layers bounded at quantiles of
the steady particles' heights (so each holds about 1/NZ of the bed, whatever the fill),
counts dump-to-dump moves after the steady-state time (a particle that the solver
discharged in between moves to the outside state, from whichever compartment it was
last seen in), fits the nearest-neighbour rates (x, y and z moves) by the maximum
likelihood of :func:`dem.rates.fit_pattern`, and computes the chain's pooled RTD exactly as
the DEM's is defined: tracers enter in the DEM's entry window, in the compartment where
the dumps first show them, and count as recovered within the same horizon. The DEM's
values, with their 95 % intervals, are the run's own (its results file). A grid of one
layer is the PBM's own chain (steady rates pooled over the window), which checks that the
study measures what the PBM does.

Also reports where the DEM's tracers spend their time, by residence-time class: what a
chain would need to represent. Writes ``results/bench/layers.json``.

Needs the run's dumps and its discharge files (a completed run directory).
"""

from __future__ import annotations

import argparse
import glob
import json
from pathlib import Path

import numpy as np
from scipy.linalg import expm

from coupling.blas import single_threaded_blas
from coupling.cache import try_load_entry
from coupling.errors import ConfigError, DumpFormatError
from coupling.jsonable import write_json
from dem import rates as rates_module
from dem.dumps import iter_snapshots
from dem.massflow import latest_records
from dem.post import DemResults
from dem.summary import PooledRtdSummary
from workflows.config import load_preset

OUT = Path("results/bench/layers.json")
DEFAULT_GRIDS = "10x10,10x1,10x1x3,10x1x5,20x1x3,10x10x3"
#: residence-time classes of the occupancy table, in mean residence times
CLASSES = ((0.0, 0.4, "fast"), (0.4, 3.0, "middle"), (3.0, np.inf, "slow"))


def parse_grid(text: str) -> tuple[int, int, int]:
    """``"10x10"`` -> (10, 10, 1); ``"10x1x3"`` -> (10, 1, 3)."""
    parts = text.lower().split("x")
    try:
        values = [int(p) for p in parts]
    except ValueError:
        values = []
    if len(values) not in (2, 3) or min(values) < 1:
        raise ValueError(f"grid {text!r}: expected NXxNY or NXxNYxNZ with whole numbers >= 1, e.g. 10x1x3")
    return (*values, 1)[:3] if len(values) == 2 else tuple(values)


class Snapshots:
    """Every dump's particles, kept in memory (id, x, y, z; ~16 bytes per particle-dump)."""

    def __init__(self, dump_glob: str, timestep_s: float):
        times, ids, xyz, sizes = [], [], [], []
        for snap in iter_snapshots(dump_glob, columns=("id", "x", "y", "z")):
            times.append(snap.time_s(timestep_s))
            ids.append(snap["id"].astype(np.int64))
            xyz.append(np.stack([snap["x"], snap["y"], snap["z"]]).astype(np.float32))
            sizes.append(ids[-1].size)
        if not times:
            raise DumpFormatError(f"no snapshot in {dump_glob}")
        self.t = np.asarray(times)
        self.offsets = np.concatenate([[0], np.cumsum(sizes)])
        self.ids = np.concatenate(ids)
        self.xyz = np.concatenate(xyz, axis=1)

    def __len__(self) -> int:
        return self.t.size

    def at(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        a, b = self.offsets[n], self.offsets[n + 1]
        return self.ids[a:b], self.xyz[:, a:b]


def layer_edges(snaps: Snapshots, t_from: float, length_m: float, nz: int) -> np.ndarray:
    """Inner z edges [m] at the 1/NZ, ..., (NZ-1)/NZ quantiles of the heights of the particles
    inside the blender from ``t_from`` on."""
    first = int(np.searchsorted(snaps.t, t_from))
    x, z = snaps.xyz[0, snaps.offsets[first] :], snaps.xyz[2, snaps.offsets[first] :]
    inside = (x >= 0) & (x <= length_m)
    return np.quantile(z[inside], np.arange(1, nz) / nz) if nz > 1 else np.zeros(0)


def states(xyz: np.ndarray, length_m: float, diameter_m: float, grid, z_edges) -> np.ndarray:
    """Flat state (i * NY + j) * NZ + l inside, S = NX*NY*NZ past the weir, -1 elsewhere."""
    nx, ny, nz = grid
    x, y, z = xyz
    i = np.clip((x / (length_m / nx)).astype(np.int64), 0, nx - 1)
    j = np.clip(np.floor((y + diameter_m / 2) / (diameter_m / ny)).astype(np.int64), 0, ny - 1)
    layer = np.searchsorted(z_edges, z, side="right")
    s = nx * ny * nz
    return np.where(x > length_m, s, np.where(x >= 0, (i * ny + j) * nz + layer, -1))


def chain_data(
    snaps: Snapshots, grid, z_edges, length_m: float, diameter_m: float, t_ss: float, discharged: np.ndarray
):
    """(counts (S+1, S+1) of dump-to-dump moves from ``t_ss`` on, first state of every id)."""
    s = int(np.prod(grid))
    top = int(snaps.ids.max()) + 1
    counts = np.zeros((s + 1) * (s + 1), np.int64)
    first = np.full(top, -2, np.int64)
    last = np.full(top, -1, np.int64)
    left = np.zeros(top, bool)
    left[discharged[discharged < top]] = True
    prev = np.zeros(0, np.int64)
    for n in range(len(snaps)):
        ids, xyz = snaps.at(n)
        state = states(xyz, length_m, diameter_m, grid, z_edges)
        new = first[ids] == -2
        first[ids[new]] = state[new]
        if snaps.t[n] >= t_ss and prev.size:
            was = last[ids]
            ok = ~new & (was >= 0) & (was < s) & (state >= 0)
            counts += np.bincount(was[ok] * (s + 1) + state[ok], minlength=counts.size)
            gone = np.setdiff1d(prev, ids, assume_unique=True)
            from_inside = gone[left[gone] & (last[gone] >= 0) & (last[gone] < s)]
            counts += np.bincount(last[from_inside] * (s + 1) + s, minlength=counts.size)
        last[ids] = state
        prev = ids
    return counts.reshape(s + 1, s + 1), first


@single_threaded_blas()
def fit_chain(counts: np.ndarray, grid, interval_s: float, max_iterations: int = 5000) -> tuple[np.ndarray, dict]:
    """Generator (S+1, S+1) of the nearest-neighbour chain on ``grid`` fitted to ``counts``."""
    nx, ny, nz = grid
    transitions = rates_module.allowed_transitions(nx, ny, nz)
    counts = counts.astype(float)
    counts[-1] = 0.0
    rows = counts[:-1].sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        start = {key: counts[src, dst] / (interval_s * rows[src]) for key, (src, dst, _) in transitions.items()}
    rates, fit = rates_module.fit_pattern(counts, transitions, start, interval_s, max_iterations)
    src = np.concatenate([t[0] for t in transitions.values()])
    dst = np.concatenate([t[1] for t in transitions.values()])
    q = np.zeros_like(counts)
    q[src, dst] = rates
    q[np.diag_indices_from(q)] = -q.sum(axis=1)
    cap = rates_module.MAX_RATE_X_INTERVAL / interval_s
    return q, {
        "iterations": fit.iterations,
        "converged": fit.converged,
        "rates": int(rates.size),
        "capped": int(np.count_nonzero(rates >= 0.999 * cap)),
    }


def chain_rtd(q: np.ndarray, entry: np.ndarray, horizon_s: float, step_s: float) -> dict:
    """Pooled-RTD moments of a chain whose tracers start in ``entry`` (shares per state),
    counted if they leave within ``horizon_s``; exact at the ``step_s`` grid."""
    p = expm(q * step_s)
    v = np.zeros(q.shape[0])
    v[:-1] = entry
    out = [0.0]
    for _ in range(int(round(horizon_s / step_s))):
        v = v @ p
        out.append(v[-1])
    cdf = np.asarray(out)
    e = np.diff(cdf)
    t = (np.arange(e.size) + 0.5) * step_s
    recovered = float(cdf[-1])
    mean = float(e @ t / recovered)
    return {
        "mean_s": mean,
        "variance_s2": float(e @ (t - mean) ** 2 / recovered),
        "recovered_fraction": recovered,
        "cdf_t_s": (np.arange(cdf.size) * step_s).tolist(),
        "cdf": cdf.tolist(),
    }


def occupancy_by_class(
    snaps: Snapshots, records, tracers, mean_s: float, length_m: float, nx: int, z_edges: np.ndarray
) -> dict:
    """Share of the dumps in which the tracers of each residence-time class were seen in each
    axial slice and height layer (``z_edges``: inner edges)."""
    tau = records["exit_t_s"].to_numpy() - records["entry_t_s"].to_numpy()
    ids = records["id"].to_numpy()
    top = int(snaps.ids.max()) + 1
    label = np.full(top, -1)
    for k, (lo, hi, _) in enumerate(CLASSES):
        pick = tracers & (tau >= lo * mean_s) & (tau < hi * mean_s) & (ids < top)
        label[ids[pick]] = k
    nz = z_edges.size + 1
    occ = np.zeros((len(CLASSES), nx, nz))
    for n in range(len(snaps)):
        pid, (x, _, z) = snaps.at(n)
        lab = label[pid]
        use = (lab >= 0) & (x >= 0) & (x <= length_m)
        i = np.clip((x[use] / (length_m / nx)).astype(np.int64), 0, nx - 1)
        np.add.at(occ, (lab[use], i, np.searchsorted(z_edges, z[use], side="right")), 1)
    out = {}
    for k, (lo, hi, name) in enumerate(CLASSES):
        total = occ[k].sum()
        share = occ[k] / total if total else occ[k]
        out[name] = {
            "tau_over_mean": [lo, None if np.isinf(hi) else hi],
            "tracers": int(np.count_nonzero(label == k)),
            "slice_share": share.sum(axis=1).tolist(),
            "layer_share": share.sum(axis=0).tolist(),
        }
    return out


HELP = "compartment chains with layers in height against the DEM's pooled RTD (needs a run's dumps)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The command line's options of this study."""
    parser.add_argument("--run-dir", required=True, help="completed run directory with dumps/ and deck.json")
    parser.add_argument("--results", required=True, help="the run's DEM results file (dem-*.h5)")
    parser.add_argument("--preset", default="validation", help="the run's preset (geometry and timestep)")
    parser.add_argument("--grids", default=DEFAULT_GRIDS, help="comma-separated NXxNY[xNZ] (default %(default)s)")
    parser.add_argument("--out-file", default=str(OUT))


#: what the study reads from a run directory's deck.json
DECK_KEYS = ("length_m", "timestep_s", "dump_every_steps", "massflow_globs", "dump_glob")


def read_deck(run_dir: Path) -> dict:
    """The run directory's ``deck.json``; ConfigError naming the directory when it has
    none or lacks one of :data:`DECK_KEYS`."""
    deck_file = run_dir / "deck.json"
    if not deck_file.is_file():
        raise ConfigError(f"--run-dir {run_dir}: no deck.json (not a run directory of this project)")
    deck = json.loads(deck_file.read_text())
    missing = [key for key in DECK_KEYS if key not in deck]
    if missing:
        raise ConfigError(f"--run-dir {run_dir}: deck.json lacks {missing} (written by another version?)")
    return deck


def read_results(path: str) -> tuple[DemResults, PooledRtdSummary]:
    """The run's results and its pooled RTD; ConfigError naming the file when it cannot be
    read or has no pooled RTD with tracers."""
    entry, reason = try_load_entry(Path(path))
    if entry is None:
        raise ConfigError(f"--results {path}: {reason}")
    dem = DemResults.from_cache_entry(entry)
    spec = dem.summary.pooled_rtd
    if spec is None or not spec.has_tracers:
        note = spec.note if spec is not None and spec.note else "too short a run"
        raise ConfigError(f"--results {path}: no pooled RTD in this run's results ({note})")
    return dem, spec


def run(args: argparse.Namespace) -> int:
    try:
        grids = [parse_grid(g) for g in args.grids.split(",")]
    except ValueError as error:
        raise ConfigError(str(error)) from None
    run_dir = Path(args.run_dir)
    deck = read_deck(run_dir)
    dem, spec = read_results(args.results)
    try:
        config = load_preset(args.preset).dem
    except (KeyError, ValueError, OSError) as error:
        raise ConfigError(f"--preset {args.preset}: {error}") from None
    length, diameter = float(deck["length_m"]), float(config.geometry.diameter_m)
    timestep = float(deck["timestep_s"])
    interval = float(deck["dump_every_steps"]) * timestep
    window = tuple(spec.entry_window_s)
    horizon = float(spec.horizon_s)
    massflow = [
        Path(p) for pattern in deck["massflow_globs"].values() for p in sorted(glob.glob(str(run_dir / pattern)))
    ]
    discharged, _, _ = latest_records(massflow)
    try:
        snaps = Snapshots(str(run_dir / deck["dump_glob"]), timestep)
    except DumpFormatError as error:
        raise ConfigError(f"--run-dir {run_dir}: {error}") from None

    records = dem.particles
    entry_t = records["entry_t_s"].to_numpy()
    tracers = (entry_t > window[0]) & (entry_t <= window[1])
    tracer_ids = records["id"].to_numpy()[tracers]
    dem_mean, dem_var = spec.mean_residence_time_s, spec.rtd_variance_s2
    out = {
        "run_dir": str(run_dir),
        "results": str(args.results),
        "entry_window_s": window,
        "horizon_s": horizon,
        "dump_interval_s": interval,
        "dem": {"mean_s": dem_mean.record(), "variance_s2": dem_var.record()},
        "grids": {},
    }
    print(
        f"DEM pooled RTD ({int(tracers.sum())} tracers): mean {dem_mean.value:.2f} s "
        f"[{dem_mean.low:.2f}, {dem_mean.high:.2f}], variance {dem_var.value:.1f} s^2 "
        f"[{dem_var.low:.1f}, {dem_var.high:.1f}]"
    )
    for grid in grids:
        z_edges = layer_edges(snaps, window[0], length, grid[2])
        counts, first = chain_data(snaps, grid, z_edges, length, diameter, window[0], discharged)
        q, fit = fit_chain(counts, grid, interval)
        start = first[tracer_ids[tracer_ids < first.size]]
        start = start[(start >= 0) & (start < q.shape[0] - 1)]
        rtd = chain_rtd(q, np.bincount(start, minlength=q.shape[0] - 1) / start.size, horizon, interval)
        name = "x".join(str(v) for v in grid)
        inside = {
            key: dem_val.low <= rtd[key] <= dem_val.high
            for key, dem_val in (("mean_s", dem_mean), ("variance_s2", dem_var))
        }
        out["grids"][name] = {"z_edges_m": z_edges.tolist(), **fit, **rtd, "inside": inside}
        print(
            f"  {name:>8}: mean {rtd['mean_s']:6.2f} s ({'inside' if inside['mean_s'] else 'outside'}), variance "
            f"{rtd['variance_s2']:6.1f} s^2 ({'inside' if inside['variance_s2'] else 'outside'}); "
            f"{fit['capped']}/{fit['rates']} rates at the cap, {fit['iterations']} iterations"
            f"{'' if fit['converged'] else ' (not converged)'}",
            flush=True,
        )
    z3 = layer_edges(snaps, window[0], length, 3)
    out["occupancy"] = occupancy_by_class(snaps, records, tracers, dem_mean.value, length, 10, z3)
    print("where the DEM's tracers spend their time (10 slices; 3 layers of equal steady occupancy, bottom first):")
    for name, row in out["occupancy"].items():
        print(
            f"  {name:>6} ({row['tracers']} tracers): first slice {row['slice_share'][0]:.0%}, last "
            f"{row['slice_share'][-1]:.0%}; layers " + ", ".join(f"{v:.0%}" for v in row["layer_share"])
        )
    print(f"wrote {write_json(args.out_file, out)}")
    return 0
