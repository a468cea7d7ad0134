"""Is the DEM's compartment motion Markovian? Rates fitted at longer lags, and what the PBM
makes of them (``pbmdem study lag [--results dem-*.h5] [--run-dir runs/<key>] [--preset reduced]``).

A Markov chain fitted to moves one dump apart predicts the moves L dumps apart; a process
with memory (a fast stream over the bed, particles that stay in a slow pocket) does not
obey it, and rates fitted at a longer lag absorb more of the long-time behaviour (the
"lag time" of Markov state models). For each lag L this counts every particle's
compartment at dump n and at dump n + L (discharged in between: the outside state), fits
the rates per window with :func:`dem.rates.fit_windows` at the interval L x dump interval
(the cap kept at the same absolute rate as at lag 1, so that lags are comparable), and
runs the PBM in measured-rate mode for the DEM's pooled-RTD window and horizon. Prints the
pooled mean and variance against the DEM's and writes ``results/bench/lag.json``.

The compartments at every dump come from the run's dumps (``--run-dir``, a completed run
directory) or, without one, from the results file's compartment sequences, which hold the
same states on the table's grid (every shipped results file has them).

Each window's fit runs to :data:`MAX_ITERATIONS` by default, about 100 s per lag on the
shipped run; ``--max-iterations 10`` stops each fit early (warm-started from the previous
window, the pooled mean and variance move by about 1 %), which is what the test runs.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import dem.rates as rates_module
from coupling.cache import try_load_entry
from coupling.compartments import bin_particles
from coupling.errors import ConfigError
from coupling.jsonable import write_json
from dem.dumps import iter_snapshots
from dem.post import DemResults
from dem.summary import PooledRtdSummary
from dem.tracking import CompartmentSequences
from pbm.rtd import pooled_rtd
from workflows.config import load_preset
from workflows.pipeline.results import pbm_config_for
from workflows.shipped import REFERENCE_DIR

OUT = Path("results/bench/lag.json")
#: the rate fit's iterations per window, :func:`dem.rates.fit_windows`' own default
MAX_ITERATIONS = 500


def snapshot_states(dump_glob: str, config) -> tuple[np.ndarray, np.ndarray]:
    """(times (n,), states (n, max id + 1)): each particle's flat compartment per dump,
    S = NX*NY past the weir, -1 absent."""
    g, t = config.geometry, config.tables
    n_cells = t.nx * t.ny
    times, rows = [], []
    for snap in iter_snapshots(dump_glob, columns=("id", "x", "y")):
        ids = snap["id"].astype(np.int64)
        x, y = snap["x"], snap["y"]
        inside, cell = bin_particles(x, y, g.length_m, g.diameter_m, t.nx, t.ny)
        state = np.full(ids.size, -1, np.int32)
        state[inside] = cell
        state[x > g.length_m] = n_cells
        times.append(snap.time_s(config.timestep_s))
        rows.append((ids, state))
    top = max(int(ids.max()) for ids, _ in rows if ids.size) + 1
    states = np.full((len(rows), top), -1, np.int16)
    for n, (ids, state) in enumerate(rows):
        states[n, ids] = state
    return np.asarray(times), states


def lag_counts(times, states, exit_t, lag: int, window_s: float, n_windows: int, n_cells: int) -> np.ndarray:
    n_states = n_cells + 1
    counts = np.zeros((n_windows, n_states * n_states), np.int64)
    for n in range(len(times) - lag):
        a, b = states[n], states[n + lag].astype(np.int64)
        start = (a >= 0) & (a < n_cells)
        gone = start & (b < 0) & (exit_t[: a.size] <= times[n + lag])
        b = np.where(gone, n_cells, b)
        use = start & (b >= 0)
        k = min(int(times[n] // window_s), n_windows - 1)
        counts[k] += np.bincount(a[use].astype(np.int64) * n_states + b[use], minlength=n_states * n_states)
    return counts.reshape(n_windows, n_states, n_states)


HELP = (
    "the measured chain fitted at longer dump lags: is the missing dispersion the dump interval? "
    "(a run's dumps, or the compartment sequences of its results file)"
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The command line's options of this study."""
    parser.add_argument(
        "--run-dir",
        default=None,
        help="completed run directory with its dumps/ (default: the results file's compartment sequences)",
    )
    parser.add_argument("--preset", default="reduced")
    parser.add_argument("--lags", default="1,2,5,10", help="lags in dump intervals")
    parser.add_argument("--results", default=None, help="the run's DEM results file (default: the shipped one)")
    parser.add_argument(
        "--max-iterations",
        type=int,
        default=MAX_ITERATIONS,
        help=(
            "iterations of each window's rate fit (default %(default)s); a few tens give the pooled "
            "mean and variance within about 1 %% in a fraction of the time"
        ),
    )
    parser.add_argument("--out-file", default=str(OUT))


def sequence_states(sequences: CompartmentSequences) -> tuple[np.ndarray, np.ndarray]:
    """(times (n,), states (n, max id + 1)) as :func:`snapshot_states` gives them, read off a
    results file's compartment sequences (each particle's compartment at every dump, on the
    table's grid): past the weir only at the one dump where a particle is first seen
    there, -1 after it (:func:`lag_counts` counts a particle discharged by then as
    outside)."""
    top = int(sequences.ids.max()) + 1 if sequences.n_particles else 0
    states = np.full((sequences.snapshot_t.size, top), -1, np.int16)
    for pid, first, state in zip(sequences.ids, sequences.start, sequences.states()):
        states[first : first + state.size, pid] = state
    return np.asarray(sequences.snapshot_t, float), states


def parse_lags(text: str) -> list[int]:
    """``"1,2,5"`` -> [1, 2, 5]; ConfigError unless every lag is a whole number >= 1."""
    try:
        lags = [int(v) for v in text.split(",")]
    except ValueError:
        lags = []
    if not lags or min(lags) < 1:
        raise ConfigError(f"--lags {text!r}: expected comma-separated whole numbers of dump intervals >= 1, e.g. 1,2,5")
    return lags


def default_results(nx: int) -> Path:
    """The first shipped results file whose table has ``nx`` slices."""
    for path in sorted(REFERENCE_DIR.glob("dem-*.h5")):
        entry, _ = try_load_entry(path)
        if entry is not None and entry.table.nx == nx:
            return path
    raise ConfigError(f"no shipped DEM results file in {REFERENCE_DIR} has {nx} slices: give --results")


def load_results(path: Path, need_sequences: bool) -> tuple[DemResults, PooledRtdSummary]:
    """The run's results and its pooled RTD; ConfigError naming the file when it cannot be
    read or lacks what the study needs."""
    entry, reason = try_load_entry(path)
    if entry is None:
        raise ConfigError(f"--results {path}: {reason}")
    dem = DemResults.from_cache_entry(entry)
    spec = dem.summary.pooled_rtd
    if spec is None or not spec.has_tracers:
        note = spec.note if spec is not None and spec.note else "too short a run"
        raise ConfigError(f"--results {path}: no pooled RTD in this run's results ({note})")
    if need_sequences and dem.sequences is None:
        raise ConfigError(f"--results {path}: no compartment sequences in this results file; give the run's --run-dir")
    return dem, spec


def run(args: argparse.Namespace) -> int:
    lags = parse_lags(args.lags)
    if args.max_iterations < 1:
        raise ConfigError(f"--max-iterations {args.max_iterations}: expected a whole number >= 1")
    config = load_preset(args.preset)
    dem_config = config.dem
    results_path = Path(args.results) if args.results else default_results(dem_config.tables.nx)
    dem, spec = load_results(results_path, need_sequences=args.run_dir is None)
    records = dem.particles
    if args.run_dir is None:
        times, states = sequence_states(dem.sequences)
        nx, ny = dem.sequences.nx, dem.sequences.ny
    else:
        dumps = Path(args.run_dir) / "dumps"
        if not any(dumps.glob("dump.*.txt")):
            raise ConfigError(f"--run-dir {args.run_dir}: no dumps/dump.*.txt (not a completed run directory)")
        times, states = snapshot_states(str(dumps / "dump.*.txt"), dem_config)
        nx, ny = dem_config.tables.nx, dem_config.tables.ny
    exit_t = np.full(states.shape[1], np.inf)
    exited = np.isfinite(records["exit_t_s"].to_numpy())
    ids = records["id"].to_numpy()[exited]
    exit_t[ids[ids < exit_t.size]] = records["exit_t_s"].to_numpy()[exited][ids < exit_t.size]
    interval = float(np.median(np.diff(times)))
    n_cells = nx * ny
    cap_per_s = rates_module.MAX_RATE_X_INTERVAL / interval
    pbm_config = pbm_config_for(config, dem.table, rtd_pulse_s=None).model_copy(update={"rates": "measured"})
    dem_mean, dem_var = spec.mean_residence_time_s, spec.rtd_variance_s2
    out = {"dem_mean_s": dem_mean.record(), "dem_variance_s2": dem_var.record(), "lags": {}}
    print(f"DEM pooled RTD: mean {dem_mean.value:.2f} s, variance {dem_var.value:.1f} s^2")
    for lag in lags:
        counts = lag_counts(times, states, exit_t, lag, dem_config.tables.window_s, dem.table.n_windows, n_cells)
        fits = rates_module.fit_windows(
            counts,
            nx,
            ny,
            lag * interval,
            min_observations=dem.table.min_samples,
            max_iterations=args.max_iterations,
            max_rate_x_interval=cap_per_s * lag * interval,
        )  # the same absolute cap
        table = dem.table.replace(**fits.rates)
        pooled = pooled_rtd(table, pbm_config, entry_window=tuple(spec.entry_window_s), horizon_s=spec.horizon_s)
        out["lags"][lag] = {
            "interval_s": lag * interval,
            "mean_s": pooled.mean_s,
            "variance_s2": pooled.variance_s2,
            "capped": fits.capped,
            "unconverged_windows": len(fits.unconverged),
        }
        print(
            f"  lag {lag:>3} ({lag * interval:.1f} s): PBM mean {pooled.mean_s:.2f} s, variance "
            f"{pooled.variance_s2:.1f} s^2 ({fits.capped} rates at the cap, "
            f"{len(fits.unconverged)}/{dem.table.n_windows} windows stopped at {args.max_iterations} iterations)",
            flush=True,
        )
    write_json(args.out_file, out)
    return 0
