"""Benchmark of the compartment transfer-rate estimators: ``python -m workflows.bench.rates``.

On synthetic, exactly simulated dump-to-dump transitions of a known nearest-neighbour chain
(10 x 10 compartments; forward-biased axial rates, x_pos 4-8 and x_neg 1-4, transverse
rates 2-10, in proportion; scaled so that the largest rate x interval is 0.1, 0.3, 0.5 or
1.0 at an interval of 0.1 s), the worst and median relative error over every rate of the
compartments with at least ``--min-observations`` observations, for

* the maximum-likelihood fit (:func:`dem.rates.fit_rates`),
* the naive one-jump estimator (:func:`dem.rates.naive_rates`),
* the matrix logarithm of the empirical transition matrix (``scipy.linalg.logm``) divided
  by the interval and projected onto the allowed pattern (negative rates set to 0);

and the fit time per window of :func:`dem.rates.fit_windows` (warm-started windows with
~1e5 observations each) for 10 x 10 and 20 x 10 compartments at rate x interval 1.0.

Prints a table and writes ``results/bench/rates.json``. BLAS runs single-threaded
throughout (:func:`coupling.blas.single_threaded_blas`, as the product's fits do): the
matrices are small, and BLAS threads fighting other jobs for the cores made expm several
times slower in our measurements (on this 2-core machine at load 4-5, the whole benchmark
at ``--particles 200000 --steps 10 --windows 2 --observations 10000`` took 158 s with
OpenBLAS' default threads, 13 s with one).
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import numpy as np
from scipy.linalg import logm

from coupling.blas import single_threaded_blas
from coupling.jsonable import write_json
from dem.rates import RATE_KEYS, fit_rates, fit_windows, generator, naive_rates, simulate_observations

INTERVAL_S = 0.1
RATE_X_INTERVAL = (0.1, 0.3, 0.5, 1.0)


def blender_rates(nx: int, ny: int, peak_rate: float, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """A DEM-like pattern: axial flow forward-biased, transverse exchange faster, no rate
    through a wall; scaled so that the largest rate is ``peak_rate`` [1/s]."""
    rates = {
        "x_pos": rng.uniform(4, 8, (nx, ny)),
        "x_neg": rng.uniform(1, 4, (nx, ny)),
        "y_pos": rng.uniform(2, 10, (nx, ny)),
        "y_neg": rng.uniform(2, 10, (nx, ny)),
    }
    rates["x_neg"][0] = 0.0
    rates["y_pos"][:, -1] = 0.0
    rates["y_neg"][:, 0] = 0.0
    top = max(float(r.max()) for r in rates.values())
    return {key: r * peak_rate / top for key, r in rates.items()}


def logm_rates(counts: np.ndarray, nx: int, ny: int, interval_s: float) -> dict[str, np.ndarray] | None:
    """logm of the empirical transition matrix over the interval, on the allowed pattern;
    None when it has no usable real logarithm (an unobserved state, or a significantly
    complex result)."""
    s = nx * ny
    rows = counts[:s].sum(axis=1)
    if np.any(rows == 0):
        return None
    p = np.zeros((s + 1, s + 1))
    p[:s] = counts[:s] / rows[:, None]
    p[s, s] = 1.0
    log_p = logm(p)
    if not np.all(np.isfinite(log_p)) or np.abs(np.imag(log_p)).max() > 1e-8 * np.abs(log_p).max():
        return None
    q = np.real(log_p) / interval_s
    c = np.arange(s).reshape(nx, ny)
    i, j = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    forward = np.where(i == nx - 1, s, c + ny)
    out = {
        "x_pos": q[c, forward],
        "x_neg": np.where(i > 0, q[c, np.maximum(c - ny, 0)], 0.0),
        "y_pos": np.where(j < ny - 1, q[c, np.minimum(c + 1, s - 1)], 0.0),
        "y_neg": np.where(j > 0, q[c, np.maximum(c - 1, 0)], 0.0),
    }
    return {key: np.clip(r, 0.0, None) for key, r in out.items()}


def relative_errors(
    estimate: dict[str, np.ndarray] | None, truth: dict[str, np.ndarray], reported: np.ndarray
) -> dict[str, float]:
    """Worst and median |estimate - truth| / truth over the rates that are not walls, in the
    compartments ``reported``; NaN for an estimator that gave nothing."""
    if estimate is None:
        return {"max": float("nan"), "median": float("nan")}
    errors = np.concatenate(
        [
            np.abs(estimate[key] - truth[key])[reported & (truth[key] > 0)] / truth[key][reported & (truth[key] > 0)]
            for key in RATE_KEYS
        ]
    )
    return {"max": float(errors.max()), "median": float(np.median(errors))}


def accuracy(nx: int, ny: int, particles: int, steps: int, min_observations: int, seed: int) -> list[dict]:
    rng = np.random.default_rng(seed)
    rows = []
    for rate_dt in RATE_X_INTERVAL:
        truth = blender_rates(nx, ny, rate_dt / INTERVAL_S, rng)
        start = np.full(nx * ny, particles // (nx * ny))
        counts = simulate_observations(generator(truth, nx, ny), start, steps, INTERVAL_S, rng)
        t0 = time.perf_counter()
        fit = fit_rates(counts, nx, ny, INTERVAL_S, min_observations=min_observations)
        fit_s = time.perf_counter() - t0
        reported = fit.n_observations >= min_observations
        rows.append(
            {
                "rate_x_interval": rate_dt,
                "observations": int(counts.sum()),
                "compartments_reported": int(reported.sum()),
                "mle": relative_errors(fit.rates(), truth, reported),
                "naive": relative_errors(naive_rates(counts, nx, ny, INTERVAL_S), truth, reported),
                "logm": relative_errors(logm_rates(counts, nx, ny, INTERVAL_S), truth, reported),
                "mle_fit_s": fit_s,
                "mle_iterations": fit.iterations,
                "mle_converged": fit.converged,
            }
        )
    return rows


def timing(nx: int, ny: int, windows: int, observations: int, seed: int) -> dict:
    """Per-window time of fit_windows on ``windows`` windows whose rates drift by ~10 %
    from one to the next (as DEM windows do), ~``observations`` transitions each."""
    rng = np.random.default_rng(seed)
    base = blender_rates(nx, ny, 1.0 / INTERVAL_S, rng)
    steps = 20
    drifted = [
        generator({k: r * rng.uniform(0.9, 1.1, r.shape) for k, r in base.items()}, nx, ny) for _ in range(windows)
    ]
    # Particles discharge during a window: calibrate the starting number on a trial run.
    trial = simulate_observations(drifted[0], np.full(nx * ny, 100), steps, INTERVAL_S, rng).sum()
    start = np.full(nx * ny, max(1, round(100 * observations / trial)))
    counts = np.stack([simulate_observations(q, start, steps, INTERVAL_S, rng) for q in drifted])
    fit_windows(counts[:1], nx, ny, INTERVAL_S)  # warm-up: imports, BLAS initialisation
    t0 = time.perf_counter()
    fit_windows(counts, nx, ny, INTERVAL_S)
    total = time.perf_counter() - t0
    t0 = time.perf_counter()
    fit_rates(counts[0], nx, ny, INTERVAL_S)
    cold = time.perf_counter() - t0
    return {
        "nx": nx,
        "ny": ny,
        "states": nx * ny + 1,
        "windows": windows,
        "observations_per_window": float(counts.sum(axis=(1, 2)).mean()),
        "per_window_s": total / windows,
        "cold_start_s": cold,
    }


def run_benchmark(
    particles: int = 4_000_000,
    steps: int = 30,
    min_observations: int = 2000,
    windows: int = 5,
    observations: int = 100_000,
    seed: int = 2013,
) -> dict:
    """Run the measurements with single-threaded BLAS; return them as a JSON-ready dict
    (times in seconds)."""
    with single_threaded_blas():
        accuracy_rows = accuracy(10, 10, particles, steps, min_observations, seed)
        timings = [timing(10, 10, windows, observations, seed), timing(20, 10, windows, observations, seed)]
    return {
        "scenario": {
            "interval_s": INTERVAL_S,
            "grid_accuracy": [10, 10],
            "particles": particles,
            "steps": steps,
            "min_observations": min_observations,
            "seed": seed,
            "rates": "x_pos 4-8, x_neg 1-4, y_pos/y_neg 2-10 (relative), walls 0",
        },
        "accuracy": accuracy_rows,
        "timing": timings,
        "machine": {
            "platform": platform.platform(),
            "python": platform.python_version(),
            "cpus": os.cpu_count(),
            "OPENBLAS_NUM_THREADS": os.environ.get("OPENBLAS_NUM_THREADS"),
            "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        },
    }


def format_report(r: dict) -> str:
    def pct(e: dict) -> str:
        return "   fails" if np.isnan(e["max"]) else f"{e['max'] * 100:7.1f}%"

    lines = [
        "worst relative error over the rates (10 x 10, interval 0.1 s)",
        f"{'rate x interval':>15}  {'observations':>12}  {'MLE':>8}  {'naive':>8}  {'logm':>8}  {'MLE fit':>8}",
        "-" * 70,
    ]
    for row in r["accuracy"]:
        lines.append(
            f"{row['rate_x_interval']:>15.1f}  {row['observations']:>12.3g}  {pct(row['mle'])}  "
            f"{pct(row['naive'])}  {pct(row['logm'])}  {row['mle_fit_s']:7.3f}s"
        )
    lines += [
        "",
        "fit_windows time per window (rate x interval 1.0, warm start)",
        f"{'grid':>8}  {'states':>6}  {'obs/window':>10}  {'per window':>10}  {'cold start':>10}",
        "-" * 54,
    ]
    for t in r["timing"]:
        lines.append(
            f"{t['nx']:>4} x{t['ny']:>2}  {t['states']:>6}  {t['observations_per_window']:>10.3g}  "
            f"{t['per_window_s']:>9.3f}s  {t['cold_start_s']:>9.3f}s"
        )
    lines.append(
        f"load average: {r['machine']['load_average']}, OPENBLAS_NUM_THREADS={r['machine']['OPENBLAS_NUM_THREADS']}"
    )
    return "\n".join(lines)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The command line's options of this benchmark."""
    parser.add_argument("--particles", type=int, default=4_000_000, help="particles per accuracy run")
    parser.add_argument("--steps", type=int, default=30, help="dump intervals followed per accuracy run")
    parser.add_argument("--min-observations", type=int, default=2000)
    parser.add_argument("--windows", type=int, default=5, help="windows per timing run")
    parser.add_argument("--observations", type=int, default=100_000, help="transitions per timing window")
    parser.add_argument("--seed", type=int, default=2013)
    parser.add_argument("--out-file", default="results/bench/rates.json")


def run(args: argparse.Namespace) -> int:
    report = run_benchmark(
        particles=args.particles,
        steps=args.steps,
        min_observations=args.min_observations,
        windows=args.windows,
        observations=args.observations,
        seed=args.seed,
    )
    out = write_json(args.out_file, report)
    print(format_report(report))
    print(f"wrote {out}")
    return 0
