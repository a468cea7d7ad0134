"""The stages as the pipeline sees them: the DEM stage (cache, shipped reference, or a
LIGGGHTS run post-processed), the PBM run, and the cluster plan. The CLI commands and
:mod:`workflows.products.compare` call these; reading a results file and the PBM
configuration of the process it describes are :mod:`workflows.pipeline.results`'.

Keys. A LIGGGHTS run is keyed by its deck and the solver version (:func:`dem.run.run_key`);
its post-processed results by that run key *and* the post-processing settings (bins,
windows, the steady-state rule, :data:`POST_VERSION`), so that changing NX never serves a
table binned for another NX, and new post-processing reuses the run without rerunning it.
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from coupling.cache import cache_path, save_entry, stable_hash, try_load_entry
from coupling.errors import ConfigError
from coupling.files import refuse_output_over_inputs, writable_directory
from coupling.tables import VelocityTable, read_table
from dem.deck import DECK_INFO, MESH_DIR, build_deck, deck_hash, dump_step, write_deck
from dem.dumps import dump_paths
from dem.geometry import build_geometry, write_stl
from dem.massflow import massflow_files
from dem.post import DemResults, Postprocessor, postprocess
from dem.resources import check_postprocess_resources
from dem.run import STOPPED, RunInputs, RunRecord, completed_run, prepare_run, read_status, run_dem, solver_counters
from pbm.model import n_phases, require_rates, supported_modes
from pbm.outputs import write_outputs
from pbm.resources import check_pbm_memory
from pbm.simulate import PbmResult, simulate
from workflows.config import Config, dump_toml
from workflows.pipeline.log import Log, quiet
from workflows.pipeline.results import table_with_operating_point, with_operating_point
from workflows.shipped import SHIPPED_RESULTS_DIRS

#: Bump when the post-processing computes anything differently: cached results are redone.
#: Datasets added without changing any other (the compartment sequences and the phase
#: model) do not bump it: results without them are post-processed again by
#: :func:`dem_stage` when the run's dumps are at hand, and otherwise serve without them.
#: Nor did the steady intervals' batch means: they are computed from what the results
#: store, so older results are brought up to them on reading
#: (:meth:`dem.post.DemResults.from_cache_entry`) and keep their keys.
POST_VERSION = 3


def _now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")


def post_hash(config: Config) -> str:
    """Hash of everything the post-processing does with a run's dumps."""
    return stable_hash(
        {
            "tables": config.dem.tables.model_dump(mode="json"),
            "steady_state": dataclasses.asdict(config.steady_state),
            "version": POST_VERSION,
        }
    )


def results_key(run_key: str, post: str) -> str:
    return stable_hash({"run": run_key, "post": post})


def _roots(cache_root: Path, reference_dir: Path | tuple[Path, ...]) -> list[tuple[Path, str]]:
    """Where results are looked for, in order: the cache, then the shipped folder(s)."""
    shipped = (reference_dir,) if isinstance(reference_dir, (str, Path)) else reference_dir
    return [(Path(cache_root), "cache"), *((Path(d), "reference") for d in shipped)]


@dataclass
class DemSide:
    """The DEM's results for one configuration and where they came from: ``source`` is
    "run" (post-processed now), "cache" or "reference" (shipped with the repository)."""

    table: VelocityTable
    results: DemResults
    provenance: dict[str, Any]
    cache_file: Path
    source: str

    @property
    def key(self) -> str:
        return str(self.provenance.get("key", "unknown"))


def _find_cached(inputs: RunInputs, post: str, roots: list[tuple[Path, str]], log: Log) -> DemSide | None:
    """A valid cached entry for these inputs: by key when the solver's version is known,
    else (no solver here) the newest entry made from the same deck and post-processing."""
    for root, source in roots:
        if inputs.key is not None:
            key = results_key(inputs.key, post)
            candidates = [cache_path(root, key)]
        else:
            key = None
            candidates = sorted(Path(root).glob("dem-*.h5"), key=lambda p: p.stat().st_mtime, reverse=True)
        for path in candidates:
            entry, reason = try_load_entry(path, key)
            if entry is None:
                if key is not None and path.exists():
                    log(f"cache file not usable, rebuilding: {reason}")
                continue
            if key is None and (entry.provenance.get("deck_hash"), entry.provenance.get("post_hash")) != (
                inputs.deck_hash,
                post,
            ):
                continue
            entry = with_operating_point(entry)  # a file written before tables recorded it: its config's
            return DemSide(entry.table, DemResults.from_cache_entry(entry), entry.provenance, path, source)
    return None


def results_available(
    config: Config,
    runs_root: str | Path = "runs",
    reference_dir: Path | tuple[Path, ...] = SHIPPED_RESULTS_DIRS,
) -> bool:
    """Whether :func:`dem_stage` can serve ``config`` without running LIGGGHTS: cached or
    shipped results, or a completed run to post-process (which this does not do)."""
    inputs = prepare_run(config.dem)
    runs_root = Path(runs_root)
    if _find_cached(inputs, post_hash(config), _roots(runs_root / "cache", reference_dir), quiet) is not None:
        return True
    return completed_run(inputs, runs_root) is not None


class RunWatch(Protocol):
    """What :func:`dem_stage`'s ``watch`` returns: the solver's line callback (raising
    :class:`dem.run.StopRun` stops the run) and the dumps it has read, if any, for the
    run's post-processing to finish instead of reading them again."""

    def __call__(self, line: str) -> None: ...

    def postprocessor(self) -> Postprocessor | None: ...


def dem_stage(
    config: Config,
    runs_root: str | Path = "runs",
    cache_root: str | Path | None = None,
    np: int | None = None,
    resume: bool = False,
    fresh: bool = False,
    progress: bool = True,
    log: Log = quiet,
    reference_dir: Path | tuple[Path, ...] = SHIPPED_RESULTS_DIRS,
    solver: bool = True,
    watch: Callable[[Path], RunWatch] | None = None,
) -> DemSide:
    """The DEM's velocity table and CQAs for ``config``.

    In order: the cache (``cache_root``, default ``<runs_root>/cache``), the results
    shipped in ``reference_dir`` (one folder or several), else LIGGGHTS (reusing a completed run of the same
    inputs; ``resume`` continues an interrupted one) followed by the post-processing,
    whose result is cached. ``fresh`` skips both caches and reruns the solver. The deck is
    built and the input hash computed once, here. Without LIGGGHTS installed, cached or
    shipped results made from the same deck are still found. ``solver=False`` never starts
    LIGGGHTS: only cached or shipped results, or the dumps of a completed run, serve, else
    LookupError. ``watch``: called with the run directory, returns a :class:`RunWatch`,
    which may stop the run early (:class:`workflows.analysis.convergence.ConvergenceWatch`)
    and hands over the dumps it has read;
    a stopped run's results are cached under a key of their own, never served as the
    complete run's."""
    inputs = prepare_run(config.dem)  # a deck LIGGGHTS would refuse: refused before any directory exists
    runs_root = writable_directory(runs_root, "runs directory").resolve()  # absolute: recorded in the cache
    cache_root = writable_directory(cache_root if cache_root is not None else runs_root / "cache", "cache directory")
    post = post_hash(config)
    if not fresh:
        found = _find_cached(inputs, post, _roots(cache_root, reference_dir), log)
        if found is not None and found.results.sequences is None and completed_run(inputs, runs_root):
            # made before the compartment sequences were recorded: the run's dumps are here,
            # so post-process them again for the sequences and the phase model
            log(f"DEM results {found.cache_file.name} predate the compartment sequences; post-processing again")
        elif found is not None:
            if found.source == "reference":
                log(f"DEM results for inputs {found.key} taken from the shipped reference data")
            return found
    on_line = None
    if solver:
        check_postprocess_resources(config.dem)  # before an hour of LIGGGHTS, not after
        on_line = None if watch is None else watch(runs_root / str(inputs.key))
        record = run_dem(
            inputs, runs_root=runs_root, np=np, resume=resume, fresh=fresh, progress=progress, on_line=on_line
        )
    else:
        record = completed_run(inputs, runs_root)
        if record is None:
            raise LookupError(
                f"no cached or shipped DEM results, nor a completed run under {runs_root}, for the "
                f"deck {inputs.deck_hash} binned as configured"
            )
    stopped = record.state == STOPPED
    stop_step = record.solver_counters.get("step")
    key = results_key(f"{record.key}-stopped-{stop_step}" if stopped else record.key, post)
    log(
        f"run {'reused' if record.reused else 'stopped early' if stopped else 'finished'}: {record.run_dir}; "
        "post-processing the dumps"
    )
    t0 = time.monotonic()
    provenance = _run_provenance(config, inputs, post, record, key)
    table_attrs = {k: provenance[k] for k in ("input_hash", "liggghts_version", "preset", "config_toml", "created")}
    # a watch's checks have read the dumps up to their last one: only the rest is read here
    reader = (on_line.postprocessor() if on_line is not None else None) or Postprocessor(config.dem)
    reader.add([p for p in dump_paths(record.dump_glob) if dump_step(p) > reader.last_step])
    results = reader.results(
        config.steady_state,
        massflow_dir=record.massflow_dir,
        solver_counters=record.solver_counters,
        provenance=table_attrs,
    )
    results = dataclasses.replace(
        results,
        summary=dataclasses.replace(
            results.summary, extra={**results.summary.extra, "wall_time_s": record.wall_time_s}
        ),
    )
    provenance["postprocess_time_s"] = time.monotonic() - t0
    path = save_entry(cache_path(cache_root, key), results.to_cache_entry(provenance))
    return DemSide(results.table, results, provenance, path, "run")


def _run_provenance(config: Config, inputs: RunInputs, post: str, record: RunRecord, key: str) -> dict[str, Any]:
    """What the cache entry of ``record``'s results says of where they came from: the keys
    and hashes they are found by, the configuration, the solver run and its state."""
    stopped = record.state == STOPPED
    return {
        "key": key,
        "input_hash": key,
        "run_key": record.key,
        "deck_hash": inputs.deck_hash,
        "post_hash": post,
        "liggghts_version": record.liggghts_version,
        "preset": config.name,
        "config_toml": dump_toml(config),
        "run_dir": str(record.run_dir),
        "run_started": record.started,
        "run_finished": record.finished,
        "wall_time_s": record.wall_time_s,
        "np": record.np,
        "resumed_from": record.resumed_from,
        "created": _now(),
        "run_state": record.state,
        "stop_reason": (read_status(record.run_dir) or {}).get("stop_reason") if stopped else None,
    }


def postprocess_dumps(
    config: Config,
    dumps: str,
    out: str | Path,
    massflow_dir: str | Path | None = None,
    inputs: tuple[str | Path | None, ...] = (),
) -> DemResults:
    """Post-process existing dumps (glob ``dumps``) into a results file ``out`` (velocity
    table + DEM results, readable as a velocity table). The solver's discharge files are
    looked for beside the dumps (one level up when they sit in the deck's ``dumps/``), and
    its own counters in the run directory, for the particle accounting. ``out`` naming a
    dump, a discharge file or one of the other ``inputs`` (the configuration file) is
    refused before anything is written."""
    out = Path(out)
    if out.is_dir():
        raise ConfigError(f"--out-file {out} is a directory; give a file name such as tables.h5")
    paths = dump_paths(dumps)
    run_dir = paths[0].parent.parent if paths[0].parent.name == "dumps" else paths[0].parent
    if massflow_dir is None:
        massflow_dir = run_dir
    refuse_output_over_inputs(out, [*paths, *massflow_files(massflow_dir), *inputs], "--out-file", ConfigError)
    writable_directory(out.parent, "the directory of --out-file")
    _check_same_deck(config, run_dir)
    t0 = time.monotonic()
    key = stable_hash({"dumps": [str(p.resolve()) for p in paths], "config": config.to_dict()})
    attrs = {
        "input_hash": key,
        "preset": config.name,
        "config_toml": dump_toml(config),
        "created": _now(),
        "liggghts_version": "unknown (post-processed from existing dumps)",
    }
    results = postprocess(
        paths,
        config.dem,
        config.steady_state,
        massflow_dir=massflow_dir,
        solver_counters=solver_counters(run_dir) or None,
        provenance=attrs,
    )
    provenance = {**attrs, "key": key, "dumps": str(dumps), "postprocess_time_s": time.monotonic() - t0}
    save_entry(out, results.to_cache_entry(provenance))
    return results


def run_pbm(
    tables: str | Path,
    config: Config,
    out: str | Path,
    rtd_pulse_s: float | None = None,
    method: str | None = None,
    figures: bool = True,
    rates: str | None = None,
) -> dict[str, tuple[PbmResult, dict[str, Path]]]:
    """``pbmdem pbm run``: the PBM of ``config`` (its ``[pbm]`` section and steady-state
    rule) on the velocity table in ``tables``, in the rate mode ``rates`` ("velocity",
    "measured", "phases", or "all": every mode the table supports, one subdirectory of
    ``out`` each; default the config's). The feed rates and zones ``config.pbm`` leaves
    None are the table's operating point's (:mod:`pbm.feed`); a rate that contradicts it is
    named in each result's ``feed_overrides`` and its ``summary.json``.
    Returns mode -> (result, files written)."""
    updates = {"method": method} if method is not None else {}
    refuse_output_over_inputs(out, [tables], "output directory", ConfigError)
    table = table_with_operating_point(read_table(tables))
    modes = supported_modes(table) if rates == "all" else (rates or config.pbm.rates,)
    for mode in modes:  # refused before anything is written
        require_rates(table, mode)
        check_pbm_memory(table.nx, table.ny, table.n_windows, n_phases=n_phases(table, mode))
    writable_directory(out, "output directory")
    runs = {}
    for mode in modes:
        pbm = config.pbm.model_copy(update={**updates, "rates": mode})
        result = simulate(table, pbm, rtd_pulse_s=rtd_pulse_s, steady=config.steady_state)
        runs[mode] = (result, write_outputs(result, Path(out) / mode if len(modes) > 1 else out, figures=figures))
    return runs


def write_run_directory(
    config: Config, out: str | Path, resume_from: str | None = None, view_stl: bool = False, png: bool = False
) -> tuple[Path, str]:
    """``pbmdem dem deck``: the deck, meshes, ``deck.json`` and the resolved ``config.toml``
    (its first line records the deck hash) in ``out``; optionally STL files of the barrel
    and inlet wall (the deck uses primitives for them) and a picture. Returns (directory,
    deck hash). Everything is validated before anything is written."""
    files = build_deck(config.dem, resume_from=resume_from)
    digest = deck_hash(files)
    files["config.toml"] = f"# deck_hash = {digest}\n" + dump_toml(config)
    run_dir = write_deck(files, writable_directory(out, "run directory"))
    if view_stl:
        for name, mesh in build_geometry(config.dem).view_meshes.items():
            write_stl(mesh, run_dir / MESH_DIR / f"view_{name}.stl")
    if png:
        from dem.render import render_geometry

        render_geometry(config.dem, run_dir / "geometry.png")
    return run_dir, digest


def _check_same_deck(config: Config, run_dir: Path) -> None:
    """Dumps in a run directory written by this project carry the deck they came from
    (``status.json``'s deck hash, else ``deck.json``): refuse a configuration that makes
    another deck, whose timestep would turn steps into wrong times."""
    files = build_deck(config.dem)
    status = read_status(run_dir) or {}
    if status.get("deck_hash"):
        ours = deck_hash(files)
        if status["deck_hash"] != ours:
            raise ConfigError(
                f"the dumps in {run_dir} come from deck {status['deck_hash']}, but the configuration given "
                f"makes deck {ours}: pass the configuration of that run"
            )
    elif (run_dir / DECK_INFO).is_file() and (run_dir / DECK_INFO).read_text() != files[DECK_INFO]:
        raise ConfigError(
            f"the dumps in {run_dir} come from a deck whose {DECK_INFO} differs from the one the "
            "configuration given makes (timestep, intervals or geometry): pass the configuration of that run"
        )
