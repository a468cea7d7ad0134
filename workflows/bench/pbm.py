"""Benchmark of the PBM: ``python -m workflows.bench.pbm`` (``make bench`` calls :func:`main`).

Scenario (the paper's): 10 x 10 compartments, A + B + tracer, 260 s, 52 velocity windows
of 5 s, outputs every 1 s, on a seeded synthetic table of DEM-like velocities
(:func:`pbm.synthetic.synthetic_table`). Measures, in one process:

* the exact propagation (median wall time of several runs, each from scratch: no
  operator cache survives between runs);
* scipy ``solve_ivp`` BDF (rtol 1e-6, sparse analytic Jacobian) on the same problem, and
  the largest disagreement between the two, relative to each series' largest value;
* a 10 000-member feed-noise ensemble (sigma 0.1): median wall time, and its peak memory
  (tracemalloc, numpy buffers included) in a separate run so tracing does not slow the
  timed ones;
* where the exact run's time goes (:func:`profile_simulate`): the operators (the matrix
  exponentials), the march, the rest; and what bounds it: the time of one dense product of
  the operators' size, of which each exponential needs 5 plus its squarings.

Prints a small table and writes ``results/bench/pbm.json``. Timings on a shared machine
are noisy: compare medians, and read ``load_average`` in the JSON.
"""

from __future__ import annotations

import argparse
import cProfile
import os
import platform
import pstats
import statistics
import time
import tracemalloc

import numpy as np

from coupling.jsonable import write_json
from pbm.config import PbmConfig
from pbm.ensemble import noise_ensemble
from pbm.simulate import simulate
from pbm.synthetic import synthetic_table

COMPARED = ("holdup_A", "holdup_B", "discharged_A", "discharged_B", "outflow_A", "outflow_B", "rtd_E")
DERIVED = ("C_A", "rsd_outlet", "rsd_blender")


def _timed(fn, repeats: int) -> tuple[list[float], object, list[float]]:
    """Wall times [s], the last result, and process CPU times [s] (all threads)."""
    times, cpu, result = [], [], None
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        result = fn()
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return times, result, cpu


def _max_rel_diff(a: np.ndarray, b: np.ndarray) -> float:
    ok = np.isfinite(a) & np.isfinite(b)
    scale = np.max(np.abs(b[ok])) if ok.any() else 0.0
    return float(np.max(np.abs(a[ok] - b[ok])) / scale) if scale > 0 else 0.0


def profile_simulate(table, config: PbmConfig, rtd_pulse_s: float) -> dict:
    """Seconds of one exact run by stage (cProfile, cumulative; the exponentials run on
    worker threads, so they count as the wall time of ``prepare``), with the dense-product
    bound: the exponentials computed, the product count they need and one product's time."""
    from pbm.solver import _THETA18, Propagators

    profiler = cProfile.Profile()
    profiler.enable()
    simulate(table, config, rtd_pulse_s=rtd_pulse_s)
    profiler.disable()
    stats = pstats.Stats(profiler).stats

    def cumulative(name: str) -> float:
        return sum(v[3] for (_f, _l, fn), v in stats.items() if fn == name)

    total = cumulative("simulate")
    stages = {
        "operators (Propagators.prepare: matrix exponentials, threaded)": cumulative("prepare"),
        "march (state updates, without the operators)": cumulative("march") - cumulative("prepare"),
        "filled_table (fill rule)": cumulative("filled_table"),
        "generator_matrix": cumulative("generator_matrix"),
    }
    stages["the rest (CQAs, RTD, checks)"] = (
        total
        - stages[next(iter(stages))]
        - stages["march (state updates, without the operators)"]
        - stages["filled_table (fill rule)"]
    )
    # the products one run's exponentials need: 5 each, plus the squarings its norm asks for
    props = Propagators(table, np.zeros((table.nx * table.ny, 2)), config.rates)
    m = props.n_states + 2
    squarings = []
    for k in range(table.n_windows):
        g = props.generator(k)
        shift = max(0.0, -float(np.diag(g).min()))
        norm = np.abs(g + shift * np.eye(g.shape[0])).sum(axis=0).max() * config.output_interval_s
        squarings.append(max(0, int(np.ceil(np.log2(norm / _THETA18)))) if norm > 0 else 0)
    a = np.random.default_rng(0).standard_normal((m, m))
    product_s = statistics.median(_timed(lambda: a @ a, 200)[0])
    products = sum(5 + s for s in squarings)
    return {
        "total_s": total,
        "stages_s": stages,
        "matrix_size": m,
        "exponentials": table.n_windows,
        "mean_squarings": float(np.mean(squarings)),
        "dense_products": products,
        "one_product_s": product_s,
        "product_bound_s": products * product_s,
        "product_bound_two_threads_s": products * product_s / 2,
    }


def run_benchmark(
    repeats: int = 15, bdf_repeats: int = 3, ensemble_repeats: int = 3, members: int = 10000, rtd_pulse_s: float = 50.0
) -> dict:
    """Run the measurements; return them as a JSON-ready dict (times in seconds)."""
    table = synthetic_table()
    config = PbmConfig()
    bdf_config = config.model_copy(update={"method": "bdf"})

    simulate(table, config, rtd_pulse_s=rtd_pulse_s)  # warm-up: imports, BLAS thread pools
    expm_times, exact, expm_cpu = _timed(lambda: simulate(table, config, rtd_pulse_s=rtd_pulse_s), repeats)
    detect_times, _, _ = _timed(lambda: simulate(table, config), max(3, repeats // 3))
    bdf_times, bdf, bdf_cpu = _timed(lambda: simulate(table, bdf_config, rtd_pulse_s=rtd_pulse_s), bdf_repeats)

    noise_ensemble(table, config, sigma=0.1, members=8)  # warm-up
    ens_times, _, ens_cpu = _timed(lambda: noise_ensemble(table, config, sigma=0.1, members=members), ensemble_repeats)
    tracemalloc.start()
    noise_ensemble(table, config, sigma=0.1, members=members)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    try:
        import resource

        max_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # Linux reports KiB
    except ImportError:  # not on POSIX
        max_rss = None

    profile = profile_simulate(table, config, rtd_pulse_s)
    expm_median = statistics.median(expm_times)
    bdf_median = statistics.median(bdf_times)
    return {
        "scenario": {
            "nx": table.nx,
            "ny": table.ny,
            "windows": table.n_windows,
            "window_s": table.window_s,
            "duration_s": table.t_end,
            "output_interval_s": config.output_interval_s,
            "species": ["A", "B", "tracer"],
            "rtd_pulse_s": rtd_pulse_s,
            "table": "pbm.synthetic.synthetic_table(seed=2013)",
        },
        "expm": {
            "median_s": expm_median,
            "min_s": min(expm_times),
            "runs_s": expm_times,
            "median_cpu_s": statistics.median(expm_cpu),
        },
        "expm_detected_pulse": {
            "median_s": statistics.median(detect_times),
            "runs_s": detect_times,
            "note": "default path: A+B, steady-state detection, then the tracer",
        },
        "bdf": {
            "median_s": bdf_median,
            "runs_s": bdf_times,
            "rtol": bdf_config.bdf_rtol,
            "median_cpu_s": statistics.median(bdf_cpu),
        },
        "speedup_vs_bdf": bdf_median / expm_median,
        "max_rel_diff_expm_vs_bdf": {
            name: _max_rel_diff(getattr(exact, name), getattr(bdf, name)) for name in COMPARED
        },
        "max_rel_diff_derived": {name: _max_rel_diff(getattr(exact, name), getattr(bdf, name)) for name in DERIVED},
        "mean_residence_time_s": {
            "expm": exact.summary["mean_residence_time_s"],
            "bdf": bdf.summary["mean_residence_time_s"],
        },
        "ensemble": {
            "members": members,
            "sigma": 0.1,
            "median_s": statistics.median(ens_times),
            "runs_s": ens_times,
            "median_cpu_s": statistics.median(ens_cpu),
            "peak_traced_bytes": peak,
            "peak_traced_MiB": peak / 2**20,
            "process_max_rss_bytes": max_rss,
        },
        "profile": profile,
        "targets": {
            "expm_median_s": 0.01,
            "speedup_vs_bdf": 100.0,
            "ensemble_members": 10000,
            "ensemble_s": 2.0,
            "ensemble_peak_bytes": 2**30,
        },
        "machine": {
            "platform": platform.platform(),
            "python": platform.python_version(),
            "cpus": os.cpu_count(),
            "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        },
    }


def format_report(r: dict) -> str:
    rows = [
        ("exact (expm), A+B+tracer, 260 s", f"{r['expm']['median_s'] * 1e3:8.1f} ms", "<= 10 ms"),
        ("  its CPU time (all threads)", f"{r['expm']['median_cpu_s'] * 1e3:8.1f} ms", ""),
        ("  same, steady-state pulse detected", f"{r['expm_detected_pulse']['median_s'] * 1e3:8.1f} ms", ""),
        ("solve_ivp BDF rtol 1e-6", f"{r['bdf']['median_s'] * 1e3:8.1f} ms", ""),
        ("speed-up vs BDF", f"{r['speedup_vs_bdf']:8.1f} x", ">= 100 x"),
        ("max rel. diff expm vs BDF (states, E)", f"{max(r['max_rel_diff_expm_vs_bdf'].values()):10.2e}", "<= 1e-6"),
        ("max rel. diff (C_A, RSD)", f"{max(r['max_rel_diff_derived'].values()):10.2e}", ""),
        (
            f"ensemble {r['ensemble']['members']} members, sigma 0.1",
            f"{r['ensemble']['median_s'] * 1e3:8.1f} ms",
            "<= 2000 ms",
        ),
        ("  peak traced memory", f"{r['ensemble']['peak_traced_MiB']:8.1f} MiB", "<= 1024 MiB"),
    ]
    p = r["profile"]
    rows.append(("where one exact run's time goes (cProfile)", f"{p['total_s'] * 1e3:8.1f} ms", ""))
    rows += [(f"  {stage}", f"{sec * 1e3:8.1f} ms", "") for stage, sec in p["stages_s"].items()]
    rows += [
        (
            f"  bound: {p['exponentials']} expm x (5 + {p['mean_squarings']:.1f} squarings) = {p['dense_products']} "
            f"products of {p['matrix_size']}x{p['matrix_size']}",
            f"{p['one_product_s'] * 1e6:8.1f} us",
            "each",
        ),
        (
            "  products alone, 1 / 2 threads",
            f"{p['product_bound_s'] * 1e3:6.1f}/{p['product_bound_two_threads_s'] * 1e3:.1f} ms",
            "",
        ),
    ]
    width = max(len(name) for name, _, _ in rows)
    lines = [f"{'measurement':<{width}}  {'median':>12}  target", "-" * (width + 26)]
    lines += [f"{name:<{width}}  {value:>12}  {target}" for name, value, target in rows]
    lines.append(f"load average: {r['machine']['load_average']}")
    return "\n".join(lines)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The command line's options of this benchmark."""
    parser.add_argument("--repeats", type=int, default=15, help="timed runs of the exact path")
    parser.add_argument("--bdf-repeats", type=int, default=3)
    parser.add_argument("--members", type=int, default=10000)
    parser.add_argument("--out", default="results/bench/pbm.json")


def run(args: argparse.Namespace) -> int:
    report = run_benchmark(repeats=args.repeats, bdf_repeats=args.bdf_repeats, members=args.members)
    out = write_json(args.out, report)
    print(format_report(report))
    print(f"wrote {out}")
    return 0
