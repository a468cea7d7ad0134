"""What ``--stop-when-converged`` costs and saves: ``pbmdem bench convergence``.

Replays, on a completed run directory, the checks :class:`workflows.analysis.convergence.ConvergenceWatch`
would have made while the run went (every ``--every`` simulated seconds from 2 x that,
until the first converged one), with the check the product uses
(:class:`~workflows.analysis.convergence.RunDirectoryCheck`: each dump read once over all
checks). Per check: the dumps it read, the seconds spent reading them, finishing the
results and judging the PBMs, and the DEM's own wall time between checks. At the stop it
also times what the earlier check cost, post-processing every dump up to T again, and
says whether the results finished from the checks' reading equal that one pass's.

The wall time a stopped run would have taken is the DEM's wall time to the stop T, plus
the converged check (the run goes on meanwhile and stops at the next solver line after
it), plus finishing the post-processing the checks kept open; the complete run's is its
wall time plus the post-processing of all its dumps. The DEM's wall time to T is its total in
proportion to the particle-steps done by T (the hold-up integrated over time; a contact
solver's cost grows with its particles), since the dumps' own times do not survive a
resumed or copied run. A check that takes longer than the DEM needs for ``--every``
simulated seconds delays the stop; the table shows whether they kept up. Writes
``results/bench/convergence.json``.
"""

from __future__ import annotations

import argparse
import math
import os
import time
from pathlib import Path

import numpy as np
import pandas as pd

from coupling.errors import ConfigError
from coupling.jsonable import json_ready, write_json
from coupling.tables import RATE_NAMES, VELOCITY_NAMES
from dem import deck
from dem.dumps import dump_paths
from dem.post import DemResults, postprocess
from dem.run import prepare_run, read_status
from workflows.analysis.convergence import CHECK_EVERY_S, RunDirectoryCheck
from workflows.config import Config, add_config_arguments, resolve_config


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_config_arguments(parser, required=False)
    parser.add_argument(
        "--run-dir", help="the completed run directory (default: <runs-dir>/<the config's key>)", default=None
    )
    parser.add_argument("--runs-dir", default="runs", help="where runs live (default runs)")
    parser.add_argument("--every", type=float, default=CHECK_EVERY_S, help="simulated seconds between checks")
    parser.add_argument("--out-file", default="results/bench/convergence.json")


def _dem_wall_to(t_s: float, holdup: pd.DataFrame, wall_s: float) -> float:
    """The DEM's wall time to ``t_s`` [s]: ``wall_s`` in proportion to the particle-steps."""
    t = holdup["t_s"].to_numpy()
    n = (holdup["holdup_A"] + holdup["holdup_B"]).to_numpy()
    done = np.concatenate([[0.0], np.cumsum(0.5 * (n[1:] + n[:-1]) * np.diff(t))])
    return wall_s * float(np.interp(t_s, t, done)) / float(done[-1])


def _differences(a: DemResults, b: DemResults) -> list[str]:
    """The parts in which two post-processings of the same dumps differ (none should)."""
    fields = (*VELOCITY_NAMES, *RATE_NAMES, "count_A", "count_B", "n_samples")
    differ = [
        name
        for name in fields
        if not np.array_equal(np.asarray(getattr(a.table, name)), np.asarray(getattr(b.table, name)), equal_nan=True)
    ]
    if (a.table.phases is None) != (b.table.phases is None) or (
        a.table.phases is not None and not np.array_equal(a.table.phases.rates, b.table.phases.rates)
    ):
        differ.append("phases")
    if not np.array_equal(a.transitions, b.transitions):
        differ.append("transitions")
    differ += [
        name for name in ("timeseries", "holdup", "rtd", "particles") if not getattr(a, name).equals(getattr(b, name))
    ]
    return differ


def completed_run(args: argparse.Namespace) -> tuple[Config, str, Path, dict]:
    """The configuration, its run key, the completed run directory and its status;
    ConfigError naming the directory when it is not the configuration's completed run."""
    config = resolve_config(args.preset, args.config) if (args.preset or args.config) else resolve_config("validation")
    key = prepare_run(config.dem).key
    run_dir = Path(args.run_dir) if args.run_dir else Path(args.runs_dir) / key
    status = read_status(run_dir)
    if not status or status.get("state") != "completed":
        raise ConfigError(
            f"{run_dir}: not a completed run directory (status {status and status.get('state')!r}); "
            f"run it first: pbmdem dem run {'--preset ' + args.preset if args.preset else '--config FILE'}"
        )
    if status.get("key") != key:
        raise ConfigError(f"{run_dir} holds run {status.get('key')!r}, but the configuration's run is {key!r}")
    if not (math.isfinite(args.every) and args.every > 0):
        raise ConfigError(f"--every must be a number of seconds > 0, got {args.every}")
    return config, key, run_dir, status


def replay_checks(
    check: RunDirectoryCheck,
    files: list,
    steps: list[int],
    dt: float,
    every_s: float,
    holdup: pd.DataFrame,
    dem_wall: float,
) -> tuple[list[dict], tuple | None]:
    """The checks the watch would have made every ``every_s`` simulated seconds [s] from
    2 x that until the first converged one: a row per check (its costs [s] and the DEM's
    wall time [s] since the previous one), and at the stop (T [s], the dumps up to T, the
    DEM's wall time to T [s], the converged check's cost [s]), None when none converged."""
    rows, stop = [], None
    t, t_prev_wall = 2 * every_s, 0.0
    t_last = steps[-1] * dt
    while t <= t_last + 0.5 * dt and stop is None:
        upto = [p for p, s in zip(files, steps) if s <= round(t / dt)]
        answer = check(t)
        cost = check.costs[-1]
        wall_t = _dem_wall_to(t, holdup, dem_wall)
        row = {
            "t_s": t,
            "dumps_read": cost.dumps_read,
            "read_s": cost.read_s,
            "results_s": cost.results_s,
            "criterion_s": cost.criterion_s,
            "check_s": cost.total_s,
            "dem_wall_since_last_check_s": wall_t - t_prev_wall,
            "converged": answer.converged,
            "why": answer.why,
        }
        rows.append(row)
        print(
            f"T = {t:6.1f} s: {row['dumps_read']:4d} dumps read in {row['read_s']:5.1f} s, results "
            f"{row['results_s']:5.1f} s, PBMs judged in {row['criterion_s']:5.1f} s; the DEM took "
            f"{row['dem_wall_since_last_check_s']:6.0f} s since the last check -> "
            + ("converged" if answer.converged else f"not yet ({answer.why})"),
            flush=True,
        )
        if answer.converged:
            stop = (t, upto, wall_t, row["check_s"])
        t_prev_wall = wall_t
        t += every_s
    return rows, stop


def stopped_run(
    check: RunDirectoryCheck, config: Config, run_dir: Path, stop: tuple, rows: list[dict], complete_wall_s: float
) -> dict:
    """What the run stopped at ``stop`` (:func:`replay_checks`) would have cost [s], and
    whether the results finished from the checks' reading differ from one pass over the
    dumps up to T (the names of the quantities that differ)."""
    t_stop, upto, wall_stop, check_stop = stop
    # the run's own post-processing finishes what the checks read (dem_stage)
    t0 = time.perf_counter()
    finished = check.post.results(config.steady_state, massflow_dir=run_dir)
    post_stop = time.perf_counter() - t0
    # before, every check and the stopped run's post-processing read every dump again
    t0 = time.perf_counter()
    once = postprocess(upto, config.dem, config.steady_state, massflow_dir=run_dir)
    scratch_post = time.perf_counter() - t0
    stopped = wall_stop + check_stop + post_stop
    return dict(
        stop_t_s=t_stop,
        dem_wall_to_stop_s=wall_stop,
        post_at_stop_s=post_stop,
        post_at_stop_from_scratch_s=scratch_post,
        last_check_from_scratch_s=scratch_post + rows[-1]["criterion_s"],
        checks_total_s=sum(r["check_s"] for r in rows),
        stopped_run_wall_s=stopped,
        saved_fraction=1 - stopped / complete_wall_s,
        differs_from_one_pass=_differences(finished, once),
    )


def run(args: argparse.Namespace) -> int:
    config, key, run_dir, status = completed_run(args)
    dem_wall = float(status["wall_time_s"])
    files = dump_paths(str(run_dir / deck.DUMP_GLOB))
    dt = config.dem.timestep_s
    steps = [deck.dump_step(p) for p in files]
    t_last = steps[-1] * dt
    print(f"run {key} in {run_dir}: {len(files)} dumps to {t_last:g} s, DEM wall time {dem_wall:.0f} s", flush=True)
    t0 = time.perf_counter()
    whole = postprocess(files, config.dem, config.steady_state, massflow_dir=run_dir)
    post_all = time.perf_counter() - t0
    print(f"post-processing every dump in one pass: {post_all:.0f} s", flush=True)

    check = RunDirectoryCheck(run_dir, config, args.every)
    rows, stop = replay_checks(check, files, steps, dt, args.every, whole.holdup, dem_wall)
    record = {
        "run": key,
        "run_dir": str(run_dir),
        "dem_wall_s": dem_wall,
        "every_s": args.every,
        "checks": rows,
        "post_all_dumps_s": post_all,
        "complete_run_wall_s": dem_wall + post_all,
        "load_average": os.getloadavg(),
    }
    print(f"complete run: DEM {dem_wall:.0f} s + post-processing {post_all:.0f} s")
    if stop is None:
        print("never converged: the run would have gone to its end (plus the checks' cost)")
    else:
        record.update(stopped_run(check, config, run_dir, stop, rows, record["complete_run_wall_s"]))
        differing = record["differs_from_one_pass"]
        print(
            f"stopped at T = {record['stop_t_s']:g} s: DEM {record['dem_wall_to_stop_s']:.0f} s + the converged "
            f"check {stop[3]:.0f} s + post-processing {record['post_at_stop_s']:.0f} s = "
            f"{record['stopped_run_wall_s']:.0f} s against {record['complete_run_wall_s']:.0f} s "
            f"for the complete run ({record['saved_fraction']:.0%} saved). All checks: "
            f"{record['checks_total_s']:.0f} s; the last one reading every dump again would take "
            f"{record['last_check_from_scratch_s']:.0f} s, not {stop[3]:.0f} s. The results finished from "
            "the checks' reading " + (f"DIFFER from one pass in {differing}" if differing else "equal one pass's")
        )
    out = write_json(args.out_file, json_ready(record))
    print(f"wrote {out}")
    return 0
