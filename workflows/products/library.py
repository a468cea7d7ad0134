"""``pbmdem library fit``, ``check``, ``suggest`` and ``add``: the files they write
(``build`` and ``status``: :mod:`workflows.products.library_build`).

``library fit`` fits the law of a DEM library and its laws left out
(:func:`workflows.prediction.library.fit_library`), calibrates the intervals on them
(:mod:`workflows.prediction.calibration`) and writes ``library.json``, the check of the
intervals on every run left out (``calibration.md``, ``calibration.json``) and the fits'
cache (``fits/``). ``library check`` predicts DEM runs the library does not hold and judges
each against its DEM (``check.md``, ``check.json``).

``library suggest`` writes the configuration of the library's next DEM run
(:mod:`workflows.prediction.suggest`) with its expected reduction of the intervals
(``suggest.toml``, ``suggest.json``, ``suggest.md``); ``library add`` refits a library with
more runs.

Where a library's runs are: ``library.json`` holds each run's file name, content digest,
operating point and DEM values, not its path; ``runs.json`` beside it maps digests to the
paths the runs were fitted from (written before ``library.json``, so that it lists at least
the model's runs whatever is interrupted). A library without it (the shipped one) has its
runs looked up by name and digest in its folder, the folder above it and the shipped
folders (:func:`run_files`).
"""

from __future__ import annotations

import json
import math
import os
import tomllib
from dataclasses import dataclass
from pathlib import Path

from coupling.errors import ConfigError
from coupling.files import (
    distinct_inputs,
    input_directory,
    output_directory_path,
    refuse_output_over_inputs,
    regular_file,
    replace_file,
    writable_directory,
)
from coupling.jsonable import write_json
from dem.operating import operating_point
from workflows.config import Config, config_from_dict, dump_toml, load_config
from workflows.pipeline.log import Log, stderr_log
from workflows.pipeline.results import load_table
from workflows.prediction import calibration
from workflows.prediction.covariates import run_covariates
from workflows.prediction.library import (
    FitSettings,
    LibraryModel,
    file_digest,
    fit_library,
    library_run,
    load_model,
    load_runs,
    physics_of,
    save_model,
)
from workflows.prediction.predict import least_gap, predict
from workflows.prediction.suggest import Suggestion, config_at, scaled_duration, suggest
from workflows.shipped import LIBRARY_DIR, LIBRARY_MODEL, VALIDATION_DIR, library_runs

#: beside ``library.json``: the paths of the runs (module docstring)
RUNS_FILE = "runs.json"


@dataclass(frozen=True)
class LibraryFitOutput:
    model: LibraryModel
    check: calibration.Check
    files: dict[str, Path]


def library_fit(
    paths: list[str],
    out: str | Path,
    settings: FitSettings | None = None,
    log: Log = stderr_log,
    jobs: int = 1,
) -> LibraryFitOutput:
    """Fit, calibrate and check the library of ``paths`` into the folder ``out``
    (``settings`` default :class:`FitSettings`; ``jobs`` processes for the fits left out)."""
    settings = settings or FitSettings()
    if jobs < 1:
        raise ConfigError(f"--jobs {jobs}: a library fit needs at least 1 process")
    folder = writable_directory(out, "--out")
    runs = load_runs(paths, settings)
    found = calibration.sources(fit_library(runs, settings, folder / "fits", log, jobs))
    model = found.chosen
    check = calibration.check(model)
    files = {"runs": _write_runs(folder, {r.digest: r.path for r in runs})}
    files["model"] = save_model(model, folder / "library.json")
    files["check"] = write_json(folder / "calibration.json", check.record())
    files["page"] = replace_file(
        folder / "calibration.md",
        "# The library's law, each run predicted without it\n\n"
        f"Made by `pbmdem library fit{_results_argument(paths)} --out {out}` from {len(runs)} DEM runs.\n\n"
        + calibration.markdown(model, check)
        + "\n\n"
        + calibration.alternatives(model)
        + "\n\n"
        + calibration.slice_sources(found)
        + "\n"
        + "".join(
            f"\n{table}\n"
            for table in [
                calibration.layout_sources(found),
                calibration.chain_sources(found),
                calibration.alone_sources(found),
            ]
            if table
        ),
        "library page",
    )
    return LibraryFitOutput(model, check, files)


def _results_argument(paths: list[str]) -> str:
    """`` --results ...`` of the command that fits ``paths``; empty for the shipped runs
    (the command's default)."""
    if sorted(Path(p).resolve() for p in paths) == sorted(Path(p).resolve() for p in library_runs()):
        return ""
    return " --results " + " ".join(os.path.relpath(Path(p).resolve()) for p in paths)


def _write_runs(folder: Path, runs: dict[str, Path]) -> Path:
    """``runs.json``: these runs' paths and those it lists already (a superset of the
    model's runs until the model is written), each relative to ``folder``, so that a
    library moved or cloned with its runs beside it still finds them."""
    listed = _listed_runs(folder)
    listed.update({digest: Path(path).resolve() for digest, path in runs.items()})
    home = folder.resolve()
    record = {"runs": [{"digest": d, "file": os.path.relpath(p, home)} for d, p in sorted(listed.items())]}
    return write_json(folder / RUNS_FILE, record)


def _listed_runs(folder: Path) -> dict[str, Path]:
    path = folder / RUNS_FILE
    if not path.is_file():
        return {}
    try:
        return {str(r["digest"]): (folder / r["file"]).resolve() for r in json.loads(path.read_text())["runs"]}
    except (KeyError, TypeError, ValueError) as exc:
        raise ConfigError(f"{path}: not a list of library runs ({type(exc).__name__}: {exc})") from None


def run_files(folder: Path, model: LibraryModel) -> list[Path]:
    """The results file of each of ``model``'s runs, in its order (module docstring);
    ConfigError names the runs not found."""
    listed = _listed_runs(folder)
    places = (folder, folder.parent, LIBRARY_DIR, VALIDATION_DIR)
    found, missing = [], []
    for entry in model.runs:
        tries = [listed[entry.digest]] if entry.digest in listed else []
        tries += [place / entry.file for place in places]
        path = next((p for p in tries if p.is_file() and file_digest(p) == entry.digest), None)
        (found if path is not None else missing).append(path or entry.file)
    if missing:
        raise ConfigError(
            f"the library {folder} holds runs whose results files are not found: {', '.join(map(str, missing))} "
            f"(looked in {RUNS_FILE} and in {', '.join(str(p) for p in places)}); refit it with "
            "`pbmdem library fit --results ...`"
        )
    return found


def _library_folder(library: str | Path | None) -> Path:
    if library is None:
        return LIBRARY_MODEL.parent
    path = Path(library)
    if path.is_file():
        if path.name != "library.json":  # the folder's own model is read, whatever file was named
            raise ConfigError(f"--library {library}: give a library's folder or the library.json in it")
        path = path.parent
    folder = input_directory(path, "--library", ConfigError)
    regular_file(folder / "library.json", "the library model", ConfigError)
    return folder


@dataclass(frozen=True)
class LibraryAddOutput:
    model: LibraryModel
    check: calibration.Check
    added: tuple[Path, ...]
    files: dict[str, Path]


def library_add(paths: list[str], library: str | Path, log: Log = stderr_log, jobs: int = 1) -> LibraryAddOutput:
    """The library in the folder ``library`` refitted with the DEM results ``paths`` added
    (its own settings; the fits it made before reused from its cache). Refused before any
    fit (ConfigError) when a file is missing, unreadable as a library run, or a run the
    library holds or one given twice; the library's files are rewritten whole or not at
    all, the model last."""
    folder = _library_folder(library)
    model = load_model(folder)
    held = run_files(folder, model)
    added = distinct_inputs([*held, *paths], "a library run", ConfigError)[len(held) :]
    settings = FitSettings(
        **{
            k: tuple(v) if isinstance(v, list) else v
            for k, v in model.settings.items()
            if k in FitSettings.__dataclass_fields__
        }
    )
    for path in added:  # readable, with sequences and a steady state, before the long fit
        run = library_run(path, settings.covariates)
        if run.blade_pattern != model.blade_pattern:
            raise ConfigError(
                f"{path}: blade pattern {run.blade_pattern!r}, the library's is {model.blade_pattern!r}: "
                "one library needs one pattern"
            )
    output = library_fit([*map(str, held), *map(str, added)], folder, settings, log, jobs)
    return LibraryAddOutput(output.model, output.check, tuple(added), output.files)


@dataclass(frozen=True)
class LibrarySuggestOutput:
    suggestions: tuple[Suggestion, ...]
    config: Config
    text: str
    files: dict[str, Path]


def base_run(model: LibraryModel, folder: Path) -> tuple[Config, int]:
    """The configuration of the library's run nearest its reference point (speed, length
    and feed covariates all 0: the validation baseline in the shipped library), read from
    its results file, and the run's index."""
    files = run_files(folder, model)

    def distance(n: int) -> float:
        c = run_covariates(model.runs[n].point)
        return math.hypot(c["speed"], c["length"], c["feed"])

    n = min(range(len(model.runs)), key=distance)
    return load_table(files[n])[2], n


def library_suggest(
    library: str | Path | None = None,
    out: str | Path | None = None,
    region: str | None = None,
    extend: float = 0.0,
    base: str | Path | None = None,
    top: int = 5,
) -> LibrarySuggestOutput:
    """The library's next DEM run (:func:`workflows.prediction.suggest.suggest`) as a
    configuration built from ``base`` (a TOML file; default the configuration of the
    library's run nearest its reference point), its duration the base's in units of the
    predicted mean residence time; ``out``: the folder of ``suggest.toml``,
    ``suggest.json`` and ``suggest.md``."""
    folder = _library_folder(library)
    model = load_model(folder)
    if base is None:
        base_config, n = base_run(model, folder)
        base_mean = model.runs[n].dem["mean_residence_time_s"].value
        base_name = model.runs[n].file
    else:
        base_config, base_name = load_config(base), str(base)
        base_mean = (
            predict(
                model,
                operating_point(base_config.dem),
                base_config.dem.geometry.blade_pattern,
                extrapolate=True,
                physics=physics_of(base_config.dem),
            )
            .quantity("mean_residence_time_s")
            .value
        )
    ranked = suggest(model, base_config, region, extend)
    best = ranked[0]
    pattern = base_config.dem.geometry.blade_pattern
    mean = predict(model, best.point, pattern, extrapolate=True).quantity("mean_residence_time_s").value
    gap = least_gap([r.point for r in model.runs])
    duration = scaled_duration(base_config.dem.operation.duration_s, base_mean, mean)
    config = config_at(base_config, best.speed, best.length, best.feed, gap, duration)
    text = _suggest_markdown(ranked[:top], base_name, mean, duration, folder)
    toml = (
        f"# The library's next DEM run (`pbmdem library suggest`, library {folder}): {best.speed:.4g} rpm, "
        f"{best.length:.4g} m, {best.feed:.4g} particles/s,\n# built from {base_name}; expected to lower the "
        f"criterion over the region by {best.relative_reduction:.1%}.\n" + dump_toml(config)
    )
    config_from_dict(tomllib.loads(toml), "the suggested configuration")  # reads back as written
    files: dict[str, Path] = {}
    if out is not None:
        target = writable_directory(out, "--out")
        files["config"] = replace_file(target / "suggest.toml", toml, "suggested configuration")
        files["record"] = write_json(
            target / "suggest.json",
            {
                "library": str(folder),
                "base": base_name,
                "duration_s": duration,
                "predicted_mean_residence_time_s": mean,
                "suggestions": [s.record() for s in ranked[:top]],
            },
        )
        files["page"] = replace_file(target / "suggest.md", f"# The library's next DEM run\n\n{text}\n", "page")
    return LibrarySuggestOutput(tuple(ranked[:top]), config, text, files)


def _suggest_markdown(ranked: list[Suggestion], base: str, mean: float, duration: float, folder: Path) -> str:
    best = ranked[0]
    lines = [
        f"Library {folder}; criterion over {best.region.describe()}: the mean over the region of (half-width / "
        "target)^2, averaged over the targets (mean residence time 4 %, hold-up 4 %, RTD variance 15 %, each "
        "slice's hold-up 8 %), each squared half-width with t^2 times the line's expected squared bias under a "
        "curvature it cannot follow (from the spread beyond the seed scatter; `workflows/prediction/suggest.py`), "
        "the slices' from the zone law of the bed where the library has one, without that bias, each with the "
        "hold-up's interval in quadrature (the slices are scaled to the predicted hold-up), and each, as "
        "`pbmdem predict` gives it, at least the library's floors (beyond the runs' hull, at a blade layout no "
        "run has) and widened beyond the hull; "
        f"now {best.criterion_now:.3g}.",
        "",
        f"Suggested run: {best.speed:.4g} rpm, {best.length:.4g} m, {best.feed:.4g} particles/s"
        + (" (outside the library's domain)" if best.outside_domain else "")
        + (
            f" With it the correction gains {', '.join(best.gains)}: its intervals are then the larger form's, "
            "wider where the new coefficient is uncertain (the residuals' spread taken as it is now)"
            if best.gains
            else ""
        )
        + f", from {base}, {duration:g} s (predicted mean residence time {mean:.3g} s).",
        "",
        "| rank | rpm | length [m] | feed [/s] | criterion after | expected change |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for n, s in enumerate(ranked, 1):
        lines.append(
            f"| {n} | {s.speed:.4g} | {s.length:.4g} | {s.feed:.4g} | {s.criterion_after:.3g} | "
            f"{-s.relative_reduction:+.1%} |"
        )
    lines += [
        "",
        "Median half-width over the region [% of the value], now and expected after the suggested run:",
        "",
        "| quantity | target | now | after |",
        "| --- | --- | --- | --- |",
    ]
    lines += [f"| {r.key} | {100 * r.target:g} | {100 * r.now:.2f} | {100 * r.after:.2f} |" for r in best.reductions]
    return "\n".join(lines)


@dataclass(frozen=True)
class LibraryCheckOutput:
    check: calibration.Check
    text: str
    files: dict[str, Path]


def library_check(
    paths: list[str], library: str | Path | None = None, extrapolate: bool = False, out: str | Path | None = None
) -> LibraryCheckOutput:
    """DEM runs the library does not hold, predicted and judged
    (:func:`workflows.prediction.calibration.judge_results`); ``out``: the folder of
    ``check.json`` and ``check.md``."""
    library_path = Path(library) if library is not None else LIBRARY_MODEL
    model = load_model(library_path)
    runs = distinct_inputs(paths, "--results")
    if out is not None:  # before the runs are judged, nothing created: a bad output is refused at once
        planned = output_directory_path(out, "--out", ConfigError)
        for name in ("check.json", "check.md"):
            refuse_output_over_inputs(planned / name, [*runs, library_path], "--out", ConfigError)
    check = calibration.judge_results(model, runs, extrapolate)
    text = calibration.markdown(model, check, calibration.NOT_HELD)
    files: dict[str, Path] = {}
    if out is not None:
        folder = writable_directory(out, "--out")
        files["check"] = write_json(folder / "check.json", check.record())
        shown = library if library is not None else "the shipped library (workflows/reference/library/law)"
        page = f"# DEM runs the library does not hold, predicted by {shown}\n\n{text}\n"
        files["page"] = replace_file(folder / "check.md", page, "page")
    return LibraryCheckOutput(check, text, files)
