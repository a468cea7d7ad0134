"""Feeder-noise filtering of the blender from the PBM: ``python -m workflows.bench.frequency``.

On the synthetic table (:func:`pbm.synthetic.synthetic_table`, 10 x 10, paper-like
magnitudes), with the mean generator of the windows from ``--t-start`` on:

* |H| and the sinusoid VRR = 1 / |H|^2 of each feeder at log-spaced frequencies 0.001-1 Hz;
* the time-domain check (:func:`pbm.frequency.sinusoid_response`) at a few of them;
* the VRR of band-limited feeder noise (white and first order) up to the Nyquist frequency
  of a 1-s noise interval;
* the RTD route (:func:`pbm.frequency.transfer_function_from_rtd`) on the PBM's own pooled
  1-s histogram RTD (tracer spread like the total feed, so compared with the feed-weighted
  mean of H_A and H_B; the pooled RTD sees the table's windows in turn, the transfer
  function their mean generator, so they differ by the table's drift as well);
* the noise ensemble in the time domain (:func:`pbm.ensemble.noise_ensemble`, 10 000
  members, both feeders redrawn every second) on the steady table of the same mean
  velocities: the spread of its outlet C_A against the frequency-domain prediction
  (:func:`pbm.frequency.sampled_ca_sd`);
* the time per frequency point of the transfer function.

Prints a table and writes ``results/bench/frequency.json``.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from collections.abc import Sequence

import numpy as np

from coupling.blas import single_threaded_blas
from coupling.jsonable import json_ready, write_json
from pbm.config import PbmConfig
from pbm.feed import resolve_feed
from pbm.frequency import (
    FEEDERS,
    NOISE_TAUS_S,
    noise_frequencies,
    noise_spectrum,
    sinusoid_response,
    stationary_system,
    system_response,
    transfer_function_from_rtd,
    vrr_sinusoid,
    vrr_spectrum,
)
from pbm.rtd import pooled_rtd
from pbm.synthetic import synthetic_table
from workflows.analysis.vrr import ensemble_check


def run_benchmark(
    points: int = 13,
    check_hz: Sequence[float] = (0.003, 0.01, 0.03, 0.1),
    t_start_s: float = 100.0,
    timing_points: int = 1000,
    quadrature_points: int = 2001,
    seed: int = 2013,
    ensemble_members: int = 10000,
) -> dict:
    """Run the measurements; return them as a JSON-ready dict (times in seconds)."""
    table = synthetic_table(seed=seed)
    config, _ = resolve_feed(PbmConfig(), table)
    freqs = np.logspace(-3, 0, points)
    with single_threaded_blas():
        t0 = time.perf_counter()
        system = stationary_system(table, config, t_start_s=t_start_s)
        build_s = time.perf_counter() - t0
        response = {f: system_response(system, freqs, f) for f in FEEDERS}

        check = np.asarray(check_hz, dtype=float)
        checks = {}
        for feeder in FEEDERS:
            t0 = time.perf_counter()
            measured = sinusoid_response(system, check, feeder)
            elapsed = time.perf_counter() - t0
            exact = system_response(system, check, feeder)
            checks[feeder] = {
                "frequency_hz": check,
                "abs_H": np.abs(exact),
                "relative_error": np.abs(measured - exact) / np.abs(exact),
                "seconds_per_frequency": elapsed / check.size,
            }

        f_max = 0.5 / config.noise_interval_s
        grid = noise_frequencies(f_max, quadrature_points)
        grid_h = {f: system_response(system, grid, f) for f in FEEDERS}
        noise = [
            {
                "tau_s": tau,
                "f_max_hz": f_max,
                **{f"vrr_{f}": vrr_spectrum(grid, grid_h[f], noise_spectrum(grid, tau)) for f in FEEDERS},
            }
            for tau in NOISE_TAUS_S
        ]

        horizon = 100.0
        rtd = pooled_rtd(table, config, entry_window=(t_start_s, table.t_end - horizon), horizon_s=horizon)
        rtd_freqs = freqs[freqs <= 0.5 / config.rtd_bin_s]
        h_rtd = transfer_function_from_rtd(rtd.bin_edges, rtd.density_per_s / rtd.recovered_fraction, rtd_freqs)
        weights = np.array([config.feed_rate_a_per_s, config.feed_rate_b_per_s])
        h_mixed = sum(w * system_response(system, rtd_freqs, f) for w, f in zip(weights / weights.sum(), FEEDERS))

        ensemble = ensemble_check(table, config, t_start_s, members=ensemble_members, sigmas=(0.02, 0.05, 0.1))

        dense = np.logspace(-3, 0, timing_points)
        t0 = time.perf_counter()
        system_response(system, dense, "A")
        per_point = (time.perf_counter() - t0) / timing_points

    return {
        "scenario": {
            "table": f"synthetic_table(seed={seed}), 10 x 10, 52 windows of 5 s",
            "windows_averaged": system.windows.tolist(),
            "t_start_s": t_start_s,
            "rates": config.rates,
            "mean_residence_time_s": {
                f: float(np.linalg.solve(system.generator, -system.feed_column(f)).sum()) for f in FEEDERS
            },
        },
        "sweep": {
            "frequency_hz": freqs,
            **{f"abs_H_{f}": np.abs(response[f]) for f in FEEDERS},
            **{f"phase_rad_{f}": np.unwrap(np.angle(response[f])) for f in FEEDERS},
            **{f"vrr_sinusoid_{f}": vrr_sinusoid(response[f]) for f in FEEDERS},
        },
        "time_domain_check": checks,
        "noise_vrr": noise,
        "rtd_route": {
            "frequency_hz": rtd_freqs,
            "abs_H_rtd": np.abs(h_rtd),
            "abs_H_generator_mixed": np.abs(h_mixed),
            "abs_difference": np.abs(h_rtd - h_mixed),
            "rtd_mean_s": rtd.mean_s,
            "recovered_fraction": rtd.recovered_fraction,
            "horizon_s": horizon,
        },
        "ensemble_check": [row.record() for row in ensemble],
        "timing": {"system_build_s": build_s, "seconds_per_frequency_point": per_point, "points_timed": timing_points},
        "machine": {
            "platform": platform.platform(),
            "python": platform.python_version(),
            "cpus": os.cpu_count(),
            "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        },
    }


def format_report(r: dict) -> str:
    s = r["sweep"]
    lines = [
        f"mean generator of windows {r['scenario']['windows_averaged'][0]}.."
        f"{r['scenario']['windows_averaged'][-1]}; mean residence time "
        + ", ".join(f"{f} {v:.1f} s" for f, v in r["scenario"]["mean_residence_time_s"].items()),
        f"{'f [Hz]':>9}  {'|H_A|':>10}  {'|H_B|':>10}  {'VRR_A':>10}  {'VRR_B':>10}",
        "-" * 57,
    ]
    for i, f in enumerate(s["frequency_hz"]):
        lines.append(
            f"{f:>9.4g}  {s['abs_H_A'][i]:>10.3e}  {s['abs_H_B'][i]:>10.3e}  "
            f"{s['vrr_sinusoid_A'][i]:>10.3e}  {s['vrr_sinusoid_B'][i]:>10.3e}"
        )
    lines += ["", "time-domain check (exact sinusoidal forcing, expm): |H_time - H| / |H|"]
    for feeder, c in r["time_domain_check"].items():
        errs = ", ".join(f"{f:g} Hz: {e:.1e}" for f, e in zip(c["frequency_hz"], c["relative_error"]))
        lines.append(f"  {feeder}: {errs}  ({c['seconds_per_frequency']:.3f} s per frequency)")
    lines += ["", "VRR of band-limited feeder noise, S = 1/(1+(2 pi f tau)^2) on [0, 0.5 Hz]"]
    for row in r["noise_vrr"]:
        lines.append(f"  tau {row['tau_s']:>5.1f} s: VRR_A {row['vrr_A']:.3g}, VRR_B {row['vrr_B']:.3g}")
    rr = r["rtd_route"]
    lines += [
        "",
        f"RTD route on the PBM's pooled 1-s histogram RTD (mean {rr['rtd_mean_s']:.1f} s, "
        f"recovered {rr['recovered_fraction']:.4f}) vs the mean generator",
    ]
    for f, a, b in zip(rr["frequency_hz"], rr["abs_H_rtd"], rr["abs_H_generator_mixed"]):
        lines.append(f"  {f:>8.4g} Hz: |H_rtd| {a:.3e}  |H_gen| {b:.3e}")
    lines += ["", "time-domain noise ensemble vs the frequency domain: SD of the outlet C_A (both feeders, 1-s noise)"]
    for row in r["ensemble_check"]:
        lines.append(
            f"  sigma {row['sigma']:.2f}, {row['members']} members: {row['sd_time_domain']:.4e} vs "
            f"{row['sd_frequency_domain']:.4e} ({row['relative_difference']:+.2%}; {row['ensemble_s']:.2f} s)"
        )
    t = r["timing"]
    lines += [
        "",
        f"system build {t['system_build_s'] * 1e3:.1f} ms; transfer function "
        f"{t['seconds_per_frequency_point'] * 1e6:.0f} us per frequency point ({t['points_timed']} points)",
        f"load average: {r['machine']['load_average']}",
    ]
    return "\n".join(lines)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The command line's options of this benchmark."""
    parser.add_argument("--points", type=int, default=13, help="log-spaced frequencies of the sweep, 0.001-1 Hz")
    parser.add_argument(
        "--check-hz",
        type=float,
        nargs="+",
        default=[0.003, 0.01, 0.03, 0.1],
        help="frequencies of the time-domain check",
    )
    parser.add_argument("--t-start", type=float, default=100.0, help="average the windows from this time on [s]")
    parser.add_argument("--timing-points", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=2013)
    parser.add_argument("--out-file", default="results/bench/frequency.json")


def run(args: argparse.Namespace) -> int:
    report = json_ready(
        run_benchmark(
            points=args.points,
            check_hz=args.check_hz,
            t_start_s=args.t_start,
            timing_points=args.timing_points,
            seed=args.seed,
        )
    )
    out = write_json(args.out_file, report)
    print(format_report(report))
    print(f"wrote {out}")
    return 0
