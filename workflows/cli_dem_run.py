"""``pbmdem dem run`` and ``pbmdem dem post``: run LIGGGHTS, post-process dumps, cache results.

    pbmdem dem run  --preset NAME|--config FILE.toml [--np N] [--resume] [--fresh]
                    [--runs-dir DIR] [--cache-dir DIR] [--no-progress]
    pbmdem dem post --preset NAME|--config FILE.toml --dumps 'GLOB' --out TABLES.h5
                    [--massflow-dir DIR]

``run`` writes the deck (dem.deck), runs it in ``<runs-dir>/<input hash>/`` (reusing a
completed run), post-processes the dumps and writes one cache file per input hash,
``<cache-dir>/dem-<hash>.h5`` (velocity table + DEM results + provenance); a valid cache
file for the same inputs is reused without starting LIGGGHTS. ``post`` needs only the
dumps and the resolved config; the solver's discharge files are used for the
cross-check when they sit beside the dumps (or in ``--massflow-dir``).
"""

from __future__ import annotations

import argparse
import datetime as _dt
import math
import sys
import time
from pathlib import Path
from typing import Any

from workflows.cli_dem import add_config_arguments


def register(sub: argparse._SubParsersAction) -> None:
    run = sub.add_parser("run", help="run LIGGGHTS on the deck, post-process, cache the velocity table and results")
    add_config_arguments(run)
    run.add_argument("--np", type=int, default=None, help="MPI ranks (default: the config's dem.run.np)")
    run.add_argument("--resume", action="store_true", help="continue an interrupted run from its last restart file")
    run.add_argument("--fresh", action="store_true", help="discard a previous run and cache of the same inputs")
    run.add_argument("--runs-dir", default="runs", help="root of the run directories (default: ./runs)")
    run.add_argument("--cache-dir", default=None, help="where dem-<hash>.h5 goes (default: the runs dir)")
    run.add_argument("--no-progress", action="store_true", help="no progress bar")
    run.set_defaults(func=_cmd_run)

    post = sub.add_parser("post", help="post-process existing dumps into a velocity table + DEM results file")
    add_config_arguments(post)
    post.add_argument("--dumps", required=True, help="glob of the dump files, quoted: 'run/dumps/dump.*.txt'")
    post.add_argument("--out", required=True, help="output HDF5 file (velocity table + DEM results)")
    post.add_argument("--massflow-dir", default=None, help="directory of the discharge files (default: beside the dumps)")
    post.set_defaults(func=_cmd_post)


def _cmd_run(args) -> int:
    from workflows.config import resolve_config

    config = resolve_config(args.preset, args.config)

    def log(message: str) -> None:
        print(f"pbmdem: {message}", file=sys.stderr)

    from workflows.pipeline import dem_results

    table, results, provenance, path, source = dem_results(
        config, runs_root=args.runs_dir, cache_root=args.cache_dir, np=args.np, resume=args.resume,
        fresh=args.fresh, progress=not args.no_progress, log=log,
    )
    if source == "cache":
        log("DEM results reused from the cache (LIGGGHTS not started)")
    _print_summary(results.summary)
    print(f"DEM results and velocity table: {path}")
    print(f"run directory: {provenance.get('run_dir')}")
    return 0


def _cmd_post(args) -> int:
    from coupling.cache import save_dem_results
    from coupling.errors import ConfigError
    from dem.dumps import dump_paths
    from dem.post import postprocess
    from workflows.config import dump_toml, resolve_config

    config = resolve_config(args.preset, args.config)
    paths = dump_paths(args.dumps)
    massflow_dir = Path(args.massflow_dir) if args.massflow_dir else paths[0].parent
    # the deck's layout puts the discharge files one level above dumps/
    if args.massflow_dir is None and paths[0].parent.name == "dumps":
        massflow_dir = paths[0].parent.parent
    out = Path(args.out)
    if out.is_dir():
        raise ConfigError(f"--out {out} is a directory; give a file name such as tables.h5")
    t0 = time.monotonic()
    from coupling.cache import stable_hash

    key = stable_hash({"dumps": [str(p.resolve()) for p in paths], "config": config.to_dict()})
    attrs = {"input_hash": key, "preset": config.name, "config_toml": dump_toml(config),
             "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
             "liggghts_version": "unknown (post-processed from existing dumps)"}
    results = postprocess(paths, config.dem, massflow_dir=massflow_dir, provenance=attrs)
    provenance = {**attrs, "key": key, "dumps": args.dumps, "postprocess_time_s": time.monotonic() - t0}
    save_dem_results(out, results.table, results, provenance)
    _print_summary(results.summary)
    print(f"velocity table and DEM results: {out} ({len(paths)} dump files, {time.monotonic() - t0:.1f} s)")
    return 0


def _print_summary(summary: dict[str, Any]) -> None:
    keys = ("t_end_s", "steady_state_time_s", "steady_outflow_per_s", "steady_C_A", "mean_residence_time_s",
            "rtd_variance_s2", "rtd_recovered_fraction", "final_rsd_outlet", "final_rsd_outlet_floor",
            "final_rsd_blender", "final_rsd_blender_floor", "holdup_final", "inserted", "held", "discharged",
            "lost", "accounting_mismatch", "massflow_discharged", "discharge_crosscheck_diff")
    for key in keys:
        value = summary.get(key)
        if value is None:
            continue
        if isinstance(value, float):
            value = "nan" if math.isnan(value) else f"{value:.4g}"
        print(f"  {key:28s} {value}")
    for message in summary.get("warnings", []):
        print(f"pbmdem: warning: {message}", file=sys.stderr)
