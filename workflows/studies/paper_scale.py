"""The paper's own particles on this machine: the first seconds of the ``paper`` preset.

``pbmdem study paper-scale`` (``make paper-probe``) runs the ``paper`` preset (2 mm,
1990 /s, Table 1) on 2 ranks for its first :data:`PROBE_DURATION_S` seconds through the
normal DEM stage (cached by input hash and resumable like any run) and reads back what the
solver did:

* whether it inserted at the configured rate (a straight line fitted to the thermo rows'
  inserted count after the first batch);
* whether it lost a particle (inserted - discharged - in the box, on every thermo row;
  positive means lost, since the deck ignores LIGGGHTS' own lost-atom check);
* whether the timestep check stayed clean (its largest fractions of the Rayleigh and Hertz
  times, and every warning line of the log);
* when the first particle went over the weir;
* the throughput in particle-steps per second, from the dump files' modification times:
  each dump is written at a known step and holds a known number of particles, so the rate
  is measured interval by interval as the bed grows, not extrapolated from a smaller one.

The summary (and the thermo rows) ship in ``workflows/reference/paper_scale/`` and are what
``pbmdem dem slurm`` builds its estimate on for runs of the same particles
(:func:`measured_throughput`). The probe's figure goes to ``results/paper_scale/probe.png``
(``--figure``).

``--duration 1.5`` (the shortest whose insertion rate can be fitted,
:func:`shortest_duration_s`) is the same probe cut to 1.5 to 3 min of wall time on two
shared cores. ``--preset NAME`` probes another preset the same way: the test runs the
``smoke`` preset's first seconds (6 mm particles, a few seconds of wall time), a real run
through every step of the probe. :func:`measured_throughput` only ever reads a summary
for runs of the same particles, so a probe of another preset is never taken for the
paper's.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import threading
from pathlib import Path
from typing import Any

import numpy as np

from coupling.errors import ConfigError, error_line
from coupling.jsonable import write_json
from dem import deck
from dem.config import MAX_STABLE_RAYLEIGH_FRACTION
from dem.liggghts_log import loop_details, parse_runs
from dem.run import prepare_run, read_status, run_dem
from workflows.config import dump_toml, load_preset, override
from workflows.shipped import PAPER_SCALE_DIR, PAPER_SCALE_SUMMARY, PAPER_SCALE_THERMO

PROBE_DURATION_S = 15.0
PROBE_NP = 2
PROBE_PRESET = "paper"
#: The probe's wall-time budget: it stops the solver (as a scheduler would) after this long.
MAX_WALL_S = 45 * 60.0
SUMMARY_DIR = PAPER_SCALE_DIR
SUMMARY_FILE = PAPER_SCALE_SUMMARY
THERMO_FILE = PAPER_SCALE_THERMO
#: The throughput quoted for the full run: the dump intervals of the last quarter of the
#: probe, where the bed is largest and closest to the steady hold-up.
LATE_FRACTION = 0.25
#: Outflow at this fraction of the feed rate means the bed has reached the weir.
SUSTAINED_FRACTION = 0.05
#: Insertion starts with one batch at t = 0; the rate is fitted from here on.
FIT_FROM_S = 1.0
#: Where the probe's figure goes (not beside the shipped summary).
FIGURE = Path("results/paper_scale/probe.png")


def probe_config(duration_s: float = PROBE_DURATION_S, preset: str = PROBE_PRESET):
    """The ``preset`` (the ``paper`` one unless told), cut to its first ``duration_s``
    seconds."""
    if not duration_s > 0:
        raise ConfigError(f"the probe's duration must be > 0 s, got {duration_s}")
    return override(load_preset(preset), f"dem.operation.duration_s={duration_s!r}")


def shortest_duration_s(config) -> float:
    """The shortest probe :func:`summarise` can read: the insertion rate is a line fitted
    to the thermo rows from :data:`FIT_FROM_S` on, so two of them must lie past it."""
    return FIT_FROM_S + config.dem.numerics.thermo_interval_s


def thermo_rows(log_text: str) -> dict[str, np.ndarray]:
    """Every thermo row of a LIGGGHTS log of the blender deck, as columns (rows of a
    resumed run follow those of the first part; a step printed twice keeps its last row)."""
    rows: dict[int, list[float]] = {}
    header: list[str] = []
    for run in parse_runs(log_text + "\nLoop time of 0 on 1 procs for 0 steps with 0 atoms\n"):
        if not run.rows:
            continue
        header = run.header
        for row in run.rows:
            rows[int(row[0])] = row
    if not rows:
        raise ValueError("no thermo rows in the log")
    missing = [c for c in deck.THERMO_COLUMNS if c not in header]
    if missing:
        raise ValueError(f"the log's thermo header {' '.join(header)} lacks {' '.join(missing)}")
    data = np.array([rows[k] for k in sorted(rows)])
    return {name: data[:, header.index(name)] for name in deck.THERMO_COLUMNS}


def dump_throughput(dump_files: list[Path]) -> dict[str, np.ndarray]:
    """Particle-steps per second between consecutive dumps, from each file's step (its
    name), particle count (its header) and modification time (when the solver finished
    writing it). Intervals are bounded by two dumps of the same uninterrupted run: a gap
    of more than ten times the median interval (a stop and resume) is dropped."""
    steps, counts, mtimes = [], [], []
    for path in dump_files:
        with open(path, "rb") as fh:
            head = [fh.readline() for _ in range(4)]
        if head[0].strip() != b"ITEM: TIMESTEP" or head[2].strip() != b"ITEM: NUMBER OF ATOMS":
            raise ValueError(f"{path}: not a LIGGGHTS text dump (no ITEM: TIMESTEP / NUMBER OF ATOMS header)")
        steps.append(int(head[1]))
        counts.append(int(head[3]))
        mtimes.append(path.stat().st_mtime)
    order = np.argsort(steps)
    steps_a, counts_a, mtimes_a = (np.asarray(a, float)[order] for a in (steps, counts, mtimes))
    dsteps, dwall = np.diff(steps_a), np.diff(mtimes_a)
    held = 0.5 * (counts_a[1:] + counts_a[:-1])
    keep = (dwall > 0) & (dsteps > 0)
    if keep.sum() > 2:
        keep &= dwall <= 10 * np.median(dwall[keep])
    return {
        "step": steps_a[1:][keep],
        "particles": held[keep],
        "wall_s": dwall[keep],
        "particle_steps_per_s": held[keep] * dsteps[keep] / dwall[keep],
    }


def summarise(
    log_text: str,
    thermo: dict[str, np.ndarray],
    throughput: dict[str, np.ndarray],
    config,
    np_ranks: int,
    wall_time_s: float | None,
    load_average: list[float] | None = None,
) -> dict[str, Any]:
    """The probe's verdicts and measurements from its log, thermo rows and dump timings."""
    dem = config.dem
    t = thermo["simtime"]
    inserted = thermo["insA"] + thermo["insB"]
    discharged = thermo["outA"] + thermo["outB"]
    unaccounted = inserted - discharged - thermo["Atoms"]
    fit = t >= FIT_FROM_S
    if fit.sum() < 2:
        raise ValueError(f"the log reaches {t.max():.2f} s: too short to fit an insertion rate after {FIT_FROM_S} s")
    rate = float(np.polyfit(t[fit], inserted[fit], 1)[0])
    rate_a = float(np.polyfit(t[fit], thermo["insA"][fit], 1)[0])
    rate_b = float(np.polyfit(t[fit], thermo["insB"][fit], 1)[0])
    first_out = t[discharged > 0]
    # a particle flung over the weir is not the bed reaching it: outflow counts as begun
    # once it runs at SUSTAINED_FRACTION of the feed between two thermo rows
    flow = np.diff(discharged) / np.diff(t)
    sustained = t[1:][flow >= SUSTAINED_FRACTION * dem.operation.feed_rate_total_per_s]
    warnings = [line.strip() for line in log_text.splitlines() if re.match(r"\s*WARNING", line)]
    # what fix check/timestep/gran prints; other warnings (a restart forced by the stop) are kept apart
    timestep_warnings = [w for w in warnings if re.search(r"time-?step|rayleigh|hertz", w, re.IGNORECASE)]
    late = throughput["step"] >= throughput["step"].min() + (1 - LATE_FRACTION) * np.ptp(throughput["step"])
    rates = throughput["particle_steps_per_s"]
    steps_reached = int(thermo["Step"].max())
    return {
        "preset": config.name,
        "liggghts_version": None,
        "np": np_ranks,
        "particle_diameter_m": dem.particles.diameter_m,
        "timestep_s": dem.timestep_s,
        "simulated_s": float(t.max()),
        "steps": steps_reached,
        "wall_time_s": wall_time_s,
        "load_average_at_end": load_average,
        "insertion": {
            "configured_per_s": dem.operation.feed_rate_total_per_s,
            "fitted_per_s": rate,
            "fitted_A_per_s": rate_a,
            "fitted_B_per_s": rate_b,
            "relative_error": rate / dem.operation.feed_rate_total_per_s - 1,
            "inserted": int(inserted[-1]),
            "fitted_from_s": FIT_FROM_S,
        },
        "particles_at_end": int(thermo["Atoms"][-1]),
        "discharged": int(discharged[-1]),
        "first_discharge_s": float(first_out[0]) if first_out.size else None,
        "sustained_discharge_s": float(sustained[0]) if sustained.size else None,
        "sustained_fraction": SUSTAINED_FRACTION,
        "lost_max": int(max(0.0, unaccounted.max())),
        "timestep_check": {
            "max_rayleigh_fraction": float(thermo["ts[1]"].max()),
            "max_hertz_fraction": float(thermo["ts[2]"].max()),
            "rayleigh_limit": MAX_STABLE_RAYLEIGH_FRACTION,
            "hertz_warn_fraction": deck.HERTZ_WARN_FRACTION,
            "warnings": len(timestep_warnings),
            "warning_lines": sorted(set(timestep_warnings))[:20],
        },
        "other_warnings": sorted(set(warnings) - set(timestep_warnings))[:20],
        "throughput": {
            "source": "dump files' modification times, interval by interval",
            "late_particles_mean": float(throughput["particles"][late].mean()),
            "late_particle_steps_per_s": float(np.median(rates[late])),
            "late_particle_steps_per_s_per_core": float(np.median(rates[late])) / np_ranks,
            "late_spread": [float(np.percentile(rates[late], 10)), float(np.percentile(rates[late], 90))],
            "whole_probe_particle_steps_per_s": float(
                np.sum(rates * throughput["wall_s"]) / np.sum(throughput["wall_s"])
            ),
        },
        "loop": loop_details(log_text),
    }


def measure(
    runs_root: str | Path = "runs/paper_scale",
    duration_s: float = PROBE_DURATION_S,
    np_ranks: int = PROBE_NP,
    max_wall_s: float = MAX_WALL_S,
    resume: bool = False,
    fresh: bool = False,
    progress: bool = True,
    out_dir: Path = SUMMARY_DIR,
    preset: str = PROBE_PRESET,
) -> dict[str, Any]:
    """Run (or reuse) the probe and write its summary and thermo rows into ``out_dir``.

    The solver is stopped after ``max_wall_s`` seconds of wall time (as a scheduler would:
    SIGTERM, the run is marked interrupted and ``resume`` continues it); what it simulated
    until then is summarised. A probe found stopped is summarised again without running,
    unless ``resume`` (continue it) or ``fresh`` (start again) says otherwise."""
    if not max_wall_s > 0:
        raise ConfigError(f"max_wall_s must be > 0 s, got {max_wall_s}")
    config = probe_config(duration_s, preset)
    # refused before LIGGGHTS starts, not after it has run for nothing
    if duration_s < (shortest := shortest_duration_s(config)):
        raise ConfigError(
            f"the probe's duration {duration_s:g} s is too short to fit an insertion rate: expected >= {shortest:g} s "
            f"(two thermo rows after {FIT_FROM_S:g} s)"
        )
    inputs = prepare_run(config.dem)
    run_dir = Path(runs_root) / str(inputs.key)
    status = read_status(run_dir) or {}
    # a stopped probe is summarised as it stands unless told to continue or start again
    stopped = status.get("state") == "interrupted" and not (resume or fresh)
    if not stopped:
        prior = float(status.get("wall_time_s") or 0) if resume else 0.0
        timer = threading.Timer(max(1.0, max_wall_s - prior), os.kill, (os.getpid(), signal.SIGTERM))
        timer.start()
        try:
            run_dem(inputs, runs_root=runs_root, np=np_ranks, resume=resume, fresh=fresh, progress=progress)
        except KeyboardInterrupt:
            if timer.is_alive():  # a real Ctrl-C, not the wall-time limit
                raise
        finally:
            timer.cancel()
        status = read_status(run_dir) or {}
    log_text = "\n".join(
        path.read_text(errors="replace")
        for path in (run_dir / deck.LOG_FILE, run_dir / deck.RESUME_LOG_FILE)
        if path.is_file()
    )
    thermo = thermo_rows(log_text)
    throughput = dump_throughput(sorted(run_dir.glob(deck.DUMP_GLOB)))
    wall = status.get("wall_time_s")
    summary = summarise(
        log_text,
        thermo,
        throughput,
        config,
        int(status.get("np") or np_ranks),
        float(wall) if wall is not None else None,
        list(os.getloadavg()),
    )
    summary.update(
        {
            "liggghts_version": status.get("liggghts_version"),
            "run_key": inputs.key,
            "state": status.get("state"),
            "stopped_at_wall_limit": status.get("state") == "interrupted",
            "max_wall_s": max_wall_s,
            "run_started": status.get("started"),
            "run_finished": status.get("finished"),
            "config_toml": dump_toml(config),
        }
    )
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json(out_dir / SUMMARY_FILE.name, summary)
    header = ",".join(deck.THERMO_COLUMNS)
    np.savetxt(
        out_dir / THERMO_FILE.name,
        np.column_stack([thermo[c] for c in deck.THERMO_COLUMNS]),
        delimiter=",",
        header=header,
        comments="",
        fmt="%.10g",
    )
    np.savetxt(
        out_dir / "throughput.csv",
        np.column_stack([throughput[k] for k in ("step", "particles", "wall_s", "particle_steps_per_s")]),
        delimiter=",",
        header="step,particles_held,wall_s,particle_steps_per_s",
        comments="",
        fmt="%.6g",
    )
    return summary


def plot_probe(summary_dir: Path = SUMMARY_DIR, out: str | Path = FIGURE) -> Path:
    """Inserted, held and discharged particles against time, and the throughput against
    the particles held."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    summary = json.loads((summary_dir / SUMMARY_FILE.name).read_text())
    thermo = np.genfromtxt(summary_dir / THERMO_FILE.name, delimiter=",", names=True)
    rates = np.genfromtxt(summary_dir / "throughput.csv", delimiter=",", names=True)
    fig = Figure(figsize=(10, 4), layout="constrained")
    ax, bx = fig.subplots(1, 2)
    t = thermo["simtime"]
    ax.plot(t, thermo["insA"] + thermo["insB"], label="inserted")
    ax.plot(
        t, summary["insertion"]["configured_per_s"] * t, "k:", label=f"{summary['insertion']['configured_per_s']:g} /s"
    )
    ax.plot(t, thermo["Atoms"], label="in the blender")
    ax.plot(t, thermo["outA"] + thermo["outB"], label="discharged")
    ax.set(
        xlabel="simulated time [s]",
        ylabel="particles",
        title=f"{summary['preset']}, first {summary['simulated_s']:.0f} s",
    )
    ax.legend()
    bx.plot(rates["particles_held"], rates["particle_steps_per_s"] / 1e6, ".", ms=3)
    bx.set(
        xlabel="particles held",
        ylabel="particle-steps/s [1e6]",
        title=f"throughput on {summary['np']} ranks (from dump times)",
    )
    path = Path(out)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    return path


HELP = "the paper preset's first seconds on this machine: insertion, losses, timestep, throughput"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The command line's options of this study."""
    parser.add_argument("--runs-dir", default="runs/paper_scale")
    parser.add_argument(
        "--preset",
        default=PROBE_PRESET,
        help="the preset probed (default %(default)s; 'smoke' probes the same way in seconds)",
    )
    parser.add_argument("--duration", type=float, default=PROBE_DURATION_S, help="simulated seconds (default 15)")
    parser.add_argument("--np", type=int, default=PROBE_NP)
    parser.add_argument(
        "--max-wall-min",
        type=float,
        default=MAX_WALL_S / 60,
        help="stop the solver after this many minutes of wall time (default 45)",
    )
    parser.add_argument("--resume", action="store_true", help="continue an interrupted probe")
    parser.add_argument("--fresh", action="store_true", help="discard a previous probe of the same inputs")
    parser.add_argument("--out", default=str(SUMMARY_DIR), help="where summary.json and the thermo rows go")
    parser.add_argument("--figure", default=str(FIGURE), help="the probe's figure (default %(default)s)")


def run(args: argparse.Namespace) -> int:
    try:
        summary = measure(
            args.runs_dir,
            args.duration,
            args.np,
            args.max_wall_min * 60,
            args.resume,
            args.fresh,
            out_dir=Path(args.out),
            preset=args.preset,
        )
        figure = plot_probe(Path(args.out), args.figure)
    except ValueError as exc:  # the solver's log or dumps unreadable: one line, like the CLI's own errors
        raise ConfigError(f"paper-scale probe: {error_line(exc)}") from None
    print(report_lines(summary))
    print(f"figure: {figure}")
    return 0


def report_lines(summary: dict[str, Any]) -> str:
    ins, ts, tp = summary["insertion"], summary["timestep_check"], summary["throughput"]
    first, sustained = summary["first_discharge_s"], summary["sustained_discharge_s"]
    wall = f" in {summary['wall_time_s'] / 60:.1f} min" if summary["wall_time_s"] else ""
    stop = " (stopped at the wall-time limit)" if summary.get("stopped_at_wall_limit") else ""
    return "\n".join(
        [
            f"{summary['simulated_s']:.2f} s simulated ({summary['steps']} steps of {summary['timestep_s']:.3g} s) on "
            f"{summary['np']} ranks{wall}{stop}",
            f"insertion: {ins['fitted_per_s']:.1f} /s fitted (A {ins['fitted_A_per_s']:.1f}, B {ins['fitted_B_per_s']:.1f}) "
            f"against {ins['configured_per_s']:g} configured ({ins['relative_error']:+.2%})",
            f"lost particles: {summary['lost_max']}; discharged {summary['discharged']}, the first at "
            + (f"{first:.2f} s" if first is not None else "(none)")
            + "; outflow above "
            f"{summary['sustained_fraction']:.0%} of the feed "
            + (f"from {sustained:.2f} s" if sustained is not None else "not reached"),
            f"timestep check: at most {ts['max_rayleigh_fraction']:.3f} of the Rayleigh time (limit {ts['rayleigh_limit']:g}),"
            f" {ts['max_hertz_fraction']:.3f} of the Hertz time (warns above {ts['hertz_warn_fraction']:g});"
            f" {ts['warnings']} timestep warnings"
            + (f"; other warnings: {'; '.join(summary['other_warnings'])}" if summary.get("other_warnings") else ""),
            f"throughput: {tp['late_particle_steps_per_s']:.3g} particle-steps/s on {summary['np']} ranks with "
            f"{tp['late_particles_mean']:.0f} particles held (10-90 %: {tp['late_spread'][0]:.3g}-{tp['late_spread'][1]:.3g});"
            f" {tp['late_particle_steps_per_s_per_core']:.3g} per core",
        ]
    )
