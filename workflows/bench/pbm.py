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

* the two exact kernels (:mod:`pbm.solver`: dense exponentials, :mod:`pbm.action`:
  uniformization) and the automatic choice, on the shipped tables users run: the reduced
  reference at 10 x 10 and 20 x 10 (velocity and measured rates) and its phase model with
  K = 1, 2, 3 phases (the K fastest of the shipped three, or of its largest size class's
  three, so that every K has the same fastest rate and the times compare the state
  counts); each with its work -- the dense
  path's products, the action's multiply-adds -- and the rate it ran at, and the number of
  other runnable tasks when it ran;
* the 10 x 10 run again with a CPU-bound process on every core (``--no-loaded`` skips it).

Prints a small table and writes ``results/bench/pbm.json``. Timings on a shared machine
are noisy: compare medians, and read ``load_average`` in the JSON.
"""

from __future__ import annotations

import argparse
import cProfile
import math
import multiprocessing
import os
import platform
import pstats
import statistics
import time
import tracemalloc
from pathlib import Path

import numpy as np

from coupling.blas import single_threaded_blas
from coupling.jsonable import write_json
from coupling.phases import PhaseTransport, kinds
from coupling.tables import read_table
from pbm.config import PbmConfig
from pbm.ensemble import noise_ensemble
from pbm.model import feed_distribution, filled_table
from pbm.simulate import noise_intervals, simulate
from pbm.solver import MAX_THREADS, Propagators, breakpoints, kernel_work, multiples
from pbm.synthetic import synthetic_table
from workflows.shipped import REFERENCE_DIR

# The shipped tables the kernels are timed on: the reduced reference binned at NX = 10 and 20.
KERNEL_TABLES = {"10x10": "dem-17ea4c9cc143cd3e.h5", "20x10": "dem-ac547c3f930c80c8.h5"}
PULSE_S = 50.0

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
    """Seconds of one exact run by stage (cProfile, cumulative; the kernels run on worker
    threads, so they count as their callers' wall time), with the dense-product bound: the
    exponentials the dense path would compute, their products and one product's time."""

    profiler = cProfile.Profile()
    profiler.enable()
    simulate(table, config, rtd_pulse_s=rtd_pulse_s)
    profiler.disable()
    stats = pstats.Stats(profiler).stats

    def cumulative(name: str) -> float:
        return sum(v[3] for (_f, _l, fn), v in stats.items() if fn == name)

    total = cumulative("simulate")
    kernels = cumulative("prepare") + cumulative("_march_columns")
    stages = {
        "dense operators (Propagators.prepare: matrix exponentials, threaded)": cumulative("prepare"),
        "action kernel (pbm.action.march_action, threaded)": cumulative("_march_columns"),
        "march (state updates, kernel choice)": cumulative("march") - kernels,
        "filled_table (fill rule)": cumulative("filled_table"),
        "generators (dense or by diagonals)": cumulative("generator_matrix") + cumulative("diagonals"),
    }
    stages["the rest (CQAs, RTD, checks)"] = (
        total - kernels - stages["march (state updates, kernel choice)"] - stages["filled_table (fill rule)"]
    )
    # the products the dense path would need: 5 per exponential, plus its squarings
    work = scenario_work(table, config)
    m = work["states"] + 2
    a = np.random.default_rng(0).standard_normal((m, m))
    product_s = statistics.median(_timed(lambda: a @ a, 200)[0])
    products = work["dense_products"]
    return {
        "total_s": total,
        "stages_s": stages,
        "matrix_size": m,
        "exponentials": work["dense_exponentials"],
        "mean_squarings": products / work["dense_exponentials"] - 5,
        "dense_products": products,
        "one_product_s": product_s,
        "product_bound_s": products * product_s,
        "product_bound_two_threads_s": products * product_s / 2,
    }


def running_tasks() -> int:
    """Runnable tasks on the machine now, this one included (/proc/loadavg)."""
    try:
        return int(Path("/proc/loadavg").read_text().split()[3].split("/")[0])
    except (OSError, IndexError, ValueError):
        return -1


def fastest_phases(table, k: int):
    """``table`` whose phase model keeps only its ``k`` most mobile phases (entry renormalised);
    of a chain per size class, those of its largest, fastest class."""
    model = kinds(table.phases)[-1]
    keep = slice(model.n_phases - k, None)
    entry = model.entry[:, keep] + 1e-12
    entry = entry / entry.sum(axis=1, keepdims=True)
    return table.replace(phases=PhaseTransport(model.rates[keep], model.switching[keep, keep], entry, model.interval_s))


def scenario_work(table, config: PbmConfig) -> dict:
    """What one run of the paper scenario (pulse at PULSE_S, outputs and bins every second,
    A, B and tracer as three columns) asks of each kernel (:func:`pbm.solver.kernel_work`)."""
    filled, _ = filled_table(table, config.rates)
    props = Propagators(filled, feed_distribution(table, None, None, config.rates), config.rates)
    times = breakpoints(0.0, table.t_end, table.t, multiples(config.output_interval_s, 0.0, table.t_end), [PULSE_S])
    windows = props.schedule.windows(times)
    work = kernel_work(props, windows, np.diff(times), 3)
    return {
        "states": props.n_states,
        "dense_exponentials": int(np.unique(windows).size),
        "dense_products": work.products,
        "dense_multiply_adds": work.dense_products + work.dense_apply,
        "action_multiply_adds": work.action,
        "diagonals": int(props.diagonals.offsets.size),
        "max_leaving_rate_per_s": float(props.diagonals.rate.max()),
    }


def time_kernels(table, rates: str, repeats: int) -> dict:
    """Median seconds of the paper scenario on ``table`` with each kernel, and the work."""
    row = {"rates": rates, **scenario_work(table, PbmConfig(rates=rates))}
    reference = None
    for kernel in ("dense", "action", "auto"):
        config = PbmConfig(rates=rates, kernel=kernel)
        simulate(table, config, rtd_pulse_s=PULSE_S)  # warm-up (compilation, caches)
        tasks = running_tasks()
        times, result, _ = _timed(lambda config=config: simulate(table, config, rtd_pulse_s=PULSE_S), repeats)
        row[kernel] = {"median_s": statistics.median(times), "runs_s": times, "running_tasks_before": tasks}
        if reference is None:
            reference = result
        else:
            row[kernel]["max_rel_diff_vs_dense"] = max(
                _max_rel_diff(getattr(result, name), getattr(reference, name)) for name in COMPARED + ("counts",)
            )
    work = {"dense": row["dense_multiply_adds"], "action": row["action_multiply_adds"]}
    for kernel, fma in work.items():
        row[kernel]["multiply_adds_per_ns"] = fma / row[kernel]["median_s"] * 1e-9
    return row


def ensemble_floor(table, config: PbmConfig, members: int) -> dict | None:
    """What the superposition ensemble's products must cost on this machine: its multiply-
    adds, counted on the factors it builds (one ensemble run, its :func:`pbm.ensemble._low_rank`
    calls recorded): per block of outputs and species, R (rank x J) times the members' feeds
    and Q (rows x rank) times that (rows: the outlet's cells and the discharge, output after
    output), and the final state's cells once; over this machine's DGEMM rate on the block
    products' shapes, one thread per free core. None when ``members`` is too few for the
    superposition (each member is then propagated itself)."""
    from unittest import mock

    import pbm.ensemble as ensemble

    blocks = []  # ((rows, intervals), rank) of each factored block

    def recorded(block: np.ndarray, factor=ensemble._low_rank):
        q, r = factor(block)
        blocks.append((block.shape, q.shape[1]))
        return q, r

    with mock.patch.object(ensemble, "_low_rank", recorded):
        noise_ensemble(table, config, sigma=0.1, members=members)
    if not blocks:
        return None
    n_int = int(math.ceil(table.t_end / config.noise_interval_s))
    final = 2 * table.nx * table.ny * n_int * members
    macs = final + sum((rank * used + rows * rank) * members for (rows, used), rank in blocks)
    unfactored = final + sum(rows * used * members for (rows, used), _ in blocks)
    threads = min(MAX_THREADS, members, len(os.sched_getaffinity(0)))  # a floor: every core
    rank = int(np.median([r for _, r in blocks]))
    a = np.random.default_rng(0).random((blocks[0][0][0], rank))
    b = np.random.default_rng(1).random((rank, members // threads))
    with single_threaded_blas():
        a @ b
        t0 = time.perf_counter()
        for _ in range(5):
            a @ b
        rate = 5 * a.shape[0] * a.shape[1] * b.shape[1] / (time.perf_counter() - t0)
    return {
        "multiply_adds": macs,
        "multiply_adds_unfactored": unfactored,
        "median_rank": rank,
        "threads": threads,
        "rate_per_ns_one_thread": rate * 1e-9,
        "products_floor_s": macs / (rate * threads),
    }


def _spin(stop) -> None:
    while not stop.is_set():
        pass


def loaded_time(table, config: PbmConfig, repeats: int) -> dict:
    """Median seconds of the run with a CPU-bound process spinning on every core."""
    stop = multiprocessing.Event()
    spinners = [multiprocessing.Process(target=_spin, args=(stop,), daemon=True) for _ in range(os.cpu_count() or 1)]
    for p in spinners:
        p.start()
    try:
        time.sleep(0.5)
        tasks = running_tasks()
        times, _, _ = _timed(lambda: simulate(table, config, rtd_pulse_s=PULSE_S), repeats)
    finally:
        stop.set()
        for p in spinners:
            p.join(5)
    return {"median_s": statistics.median(times), "runs_s": times, "running_tasks_before": tasks}


def run_kernels(repeats: int = 7, loaded: bool = True) -> dict:
    """The kernels on the shipped tables (module docstring)."""
    tables = {name: read_table(REFERENCE_DIR / file) for name, file in KERNEL_TABLES.items()}
    rows = {}
    for grid, table in tables.items():
        for rates in ("velocity", "measured"):
            rows[f"{grid} {rates}"] = time_kernels(table, rates, repeats)
    for k in (1, 2, 3):
        rows[f"10x10 phases K={k}"] = time_kernels(fastest_phases(tables["10x10"], k), "phases", repeats)
    base = rows["10x10 measured"]["auto"]["median_s"]
    ratios = {
        "20x10 / 10x10 (measured)": rows["20x10 measured"]["auto"]["median_s"] / base,
        "K=2 / K=1 (phases)": rows["10x10 phases K=2"]["auto"]["median_s"]
        / rows["10x10 phases K=1"]["auto"]["median_s"],
        "K=3 / K=1 (phases)": rows["10x10 phases K=3"]["auto"]["median_s"]
        / rows["10x10 phases K=1"]["auto"]["median_s"],
    }
    out = {"tables": KERNEL_TABLES, "pulse_s": PULSE_S, "rows": rows, "ratios": ratios}
    if loaded:
        busy = loaded_time(tables["10x10"], PbmConfig(rates="measured"), repeats)
        out["loaded_10x10_measured"] = busy
        ratios["loaded / quiet (10x10 measured)"] = busy["median_s"] / base
    return out


#: what the measurements are held to (seconds, bytes, ratios): the targets of workflows/bench/PERFORMANCE.md
TARGETS = {
    "expm_median_s": 0.02,
    "speedup_vs_bdf": 100.0,
    "ensemble_members": 10000,
    "ensemble_s": 0.5,
    "ensemble_peak_bytes": 2**30,
    "loaded_over_quiet": 2.5,
    "20x10_over_10x10": 2.5,
    "phases_K2_over_K1": 3.0,
    "phases_K3_over_K1": 6.0,
}


def time_ensemble(table, config: PbmConfig, members: int, repeats: int) -> dict:
    """The noise ensemble of ``members`` members (sigma 0.1) timed ``repeats`` times [s,
    wall and CPU], its peak traced memory and the process's peak resident size [bytes]."""
    # warm-up: imports, thread pools and LAPACK's first calls, on the superposition path
    # (more members than noise intervals) that the timed runs take
    noise_ensemble(table, config, sigma=0.1, members=min(members, 2 * noise_intervals(config, table.t_end) + 1))
    ens_times, _, ens_cpu = _timed(lambda: noise_ensemble(table, config, sigma=0.1, members=members), repeats)
    tracemalloc.start()
    noise_ensemble(table, config, sigma=0.1, members=members)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    try:
        import resource

        max_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # Linux reports KiB
    except ImportError:  # not on POSIX
        max_rss = None
    return {
        "members": members,
        "sigma": 0.1,
        "median_s": statistics.median(ens_times),
        "runs_s": ens_times,
        "median_cpu_s": statistics.median(ens_cpu),
        "peak_traced_bytes": peak,
        "peak_traced_MiB": peak / 2**20,
        "process_max_rss_bytes": max_rss,
    }


def run_benchmark(
    repeats: int = 15,
    bdf_repeats: int = 3,
    ensemble_repeats: int = 5,
    members: int = 10000,
    rtd_pulse_s: float = PULSE_S,
    kernel_repeats: int = 7,
    loaded: bool = True,
) -> dict:
    """Run the measurements; return them as a JSON-ready dict (times in seconds)."""
    table = synthetic_table()
    config = PbmConfig()
    bdf_config = config.model_copy(update={"method": "bdf"})

    simulate(table, config, rtd_pulse_s=rtd_pulse_s)  # warm-up: imports, BLAS thread pools
    expm_times, exact, expm_cpu = _timed(lambda: simulate(table, config, rtd_pulse_s=rtd_pulse_s), repeats)
    detect_times, _, _ = _timed(lambda: simulate(table, config), max(3, repeats // 3))
    bdf_times, bdf, bdf_cpu = _timed(lambda: simulate(table, bdf_config, rtd_pulse_s=rtd_pulse_s), bdf_repeats)

    ensemble = time_ensemble(table, config, members, ensemble_repeats)
    ensemble["products"] = ensemble_floor(table, config, members)
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
            "expm": exact.summary.mean_residence_time_s,
            "bdf": bdf.summary.mean_residence_time_s,
        },
        "ensemble": ensemble,
        "profile": profile,
        "kernels": run_kernels(kernel_repeats, loaded),
        "targets": dict(TARGETS),
        "machine": {
            "platform": platform.platform(),
            "python": platform.python_version(),
            "cpus": os.cpu_count(),
            "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        },
    }


def _products_row(p: dict | None) -> tuple[str, str, str]:
    if p is None:
        return ("  its products: none (too few members for the superposition)", "", "")
    return (
        f"  its products: {p['multiply_adds'] / 1e9:.2f} G multiply-adds (rank-{p['median_rank']} factors; "
        f"{p['multiply_adds_unfactored'] / 1e9:.1f} G without) at {p['rate_per_ns_one_thread']:.1f}/ns x "
        f"{p['threads']} threads (DGEMM here), at least",
        f"{p['products_floor_s'] * 1e3:8.1f} ms",
        "",
    )


def format_report(r: dict) -> str:
    rows = [
        ("exact, A+B+tracer, 260 s (synthetic 10x10)", f"{r['expm']['median_s'] * 1e3:8.1f} ms", "<= 20 ms"),
        ("  its CPU time (all threads)", f"{r['expm']['median_cpu_s'] * 1e3:8.1f} ms", ""),
        ("  same, steady-state pulse detected", f"{r['expm_detected_pulse']['median_s'] * 1e3:8.1f} ms", ""),
        ("solve_ivp BDF rtol 1e-6", f"{r['bdf']['median_s'] * 1e3:8.1f} ms", ""),
        ("speed-up vs BDF", f"{r['speedup_vs_bdf']:8.1f} x", ">= 100 x"),
        ("max rel. diff expm vs BDF (states, E)", f"{max(r['max_rel_diff_expm_vs_bdf'].values()):10.2e}", "<= 1e-6"),
        ("max rel. diff (C_A, RSD)", f"{max(r['max_rel_diff_derived'].values()):10.2e}", ""),
        (
            f"ensemble {r['ensemble']['members']} members, sigma 0.1",
            f"{r['ensemble']['median_s'] * 1e3:8.1f} ms",
            "<= 500 ms",
        ),
        ("  peak traced memory", f"{r['ensemble']['peak_traced_MiB']:8.1f} MiB", "<= 1024 MiB"),
        _products_row(r["ensemble"]["products"]),
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
    k = r["kernels"]
    rows.append(("kernels on the shipped tables: dense / action / auto", "", "work, rate (multiply-adds/ns)"))
    for name, row in k["rows"].items():
        times = " / ".join(f"{row[kernel]['median_s'] * 1e3:.1f}" for kernel in ("dense", "action", "auto"))
        rows.append(
            (
                f"  {name}, {row['states']} states",
                f"{times} ms",
                f"dense {row['dense_multiply_adds'] / 1e6:.0f}M @ {row['dense']['multiply_adds_per_ns']:.1f}, "
                f"action {row['action_multiply_adds'] / 1e6:.0f}M @ {row['action']['multiply_adds_per_ns']:.1f}; "
                f"max rel. diff {max(row[x]['max_rel_diff_vs_dense'] for x in ('action', 'auto')):.1e}",
            )
        )
    limits = {
        "20x10 / 10x10 (measured)": "<= 2.5",
        "K=2 / K=1 (phases)": "<= 3",
        "K=3 / K=1 (phases)": "<= 6",
        "loaded / quiet (10x10 measured)": "<= 2.5",
    }
    rows += [(f"  {name}", f"{value:8.2f} x", limits.get(name, "")) for name, value in k["ratios"].items()]
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
    parser.add_argument("--kernel-repeats", type=int, default=7, help="timed runs per kernel and shipped table")
    parser.add_argument("--no-loaded", action="store_true", help="skip the run with a CPU-bound process on every core")
    parser.add_argument("--out-file", default="results/bench/pbm.json")


def run(args: argparse.Namespace) -> int:
    report = run_benchmark(
        repeats=args.repeats,
        bdf_repeats=args.bdf_repeats,
        members=args.members,
        kernel_repeats=args.kernel_repeats,
        loaded=not args.no_loaded,
    )
    out = write_json(args.out_file, report)
    print(format_report(report))
    print(f"wrote {out}")
    return 0
