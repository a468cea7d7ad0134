"""Pipeline steps shared by the CLI commands and ``workflows.compare``.

:func:`dem_results` is the DEM stage seen from outside: the velocity table and DEM CQAs
for a configuration, from the cache when valid, else from a (reused or new) LIGGGHTS run
post-processed by ``dem.post`` and written to the cache.
"""

from __future__ import annotations

import datetime as _dt
import time
from pathlib import Path


def dem_results(config, runs_root="runs", cache_root=None, np=None, resume=False, fresh=False, progress=True,
                log=None):
    """Pipeline step for the lead's workflows: the (table, results, provenance) of the DEM for
    ``config``, from the cache when valid, else from a (reused or new) LIGGGHTS run.

    Returns ``(table, results, provenance, cache_file, source)`` with source one of "cache",
    "run". ``log``: callable for progress messages (the CLI passes print to stderr)."""
    from coupling.cache import cache_path, save_dem_results, try_load_dem_results
    from dem import deck
    from dem.post import postprocess
    from dem.run import liggghts_version, run_dem, run_key
    from coupling.errors import SolverNotFoundError
    from workflows.config import dump_toml

    log = log or (lambda message: None)
    cache_root = Path(cache_root or runs_root)
    files = deck.build_deck(config.dem)
    try:
        key = run_key(files, liggghts_version(config.dem.run.liggghts))
    except SolverNotFoundError:
        key = None
    if key is not None and not fresh:
        loaded, reason = try_load_dem_results(cache_path(cache_root, key), key)
        if loaded is not None:
            table, results, provenance = loaded
            return table, results, provenance, cache_path(cache_root, key), "cache"
        if cache_path(cache_root, key).exists():
            log(f"cache file not usable, rebuilding: {reason}")
    record = run_dem(config, runs_root=runs_root, np=np, resume=resume, fresh=fresh, progress=progress)
    key = record.key
    target = cache_path(cache_root, key)
    if not fresh:
        loaded, _ = try_load_dem_results(target, key)
        if loaded is not None:
            return (*loaded, target, "cache")
    log(f"run {'reused' if record.reused else 'finished'}: {record.run_dir}; post-processing the dumps")
    t0 = time.monotonic()
    provenance = {
        "key": key,
        "input_hash": key,
        "liggghts_version": record.liggghts_version,
        "preset": config.name,
        "config_toml": dump_toml(config),
        "run_dir": str(record.run_dir),
        "run_started": record.started,
        "run_finished": record.finished,
        "wall_time_s": record.wall_time_s,
        "np": record.np,
        "resumed_from": record.resumed_from,
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
    }
    table_attrs = {k: provenance[k] for k in ("input_hash", "liggghts_version", "preset", "config_toml", "created")}
    results = postprocess(record.dump_glob, config.dem, massflow_dir=record.massflow_dir,
                          solver_counters=record.solver_counters, provenance=table_attrs)
    results.summary["wall_time_s"] = record.wall_time_s
    provenance["postprocess_time_s"] = time.monotonic() - t0
    save_dem_results(target, results.table, results, provenance)
    return results.table, results, provenance, target, "run"
