"""``pbmdem predict`` and ``pbmdem library fit``: the files they write.

``library fit`` fits the law of a DEM library and its laws left out
(:func:`workflows.prediction.library.fit_library`), calibrates the intervals on them
(:mod:`workflows.prediction.calibration`) and writes ``library.json``, the check of the
intervals on every run left out (``calibration.md``, ``calibration.json``) and the fits'
cache (``fits/``).

``predict`` reads a configuration and a library model and writes, into its output folder:
``prediction.json`` (one ``{key, value, low, high}`` per quantity of the comparison's
agreement table, with the point, the domain and each interval's parts), ``table.h5`` (the
PBM's table at the point: ``pbmdem pbm run --tables`` runs it), ``prediction.png`` and
``report.html``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from coupling.errors import ConfigError
from coupling.files import writable_directory
from coupling.jsonable import write_json
from coupling.tables import write_table
from dem.operating import operating_point
from workflows.config import load_config
from workflows.pipeline.log import Log, stderr_log
from workflows.prediction import calibration
from workflows.prediction.library import FitSettings, LibraryModel, fit_library, load_model, load_runs, save_model
from workflows.prediction.predict import Prediction, point_table, predict
from workflows.shipped import LIBRARY_DIR, LIBRARY_MODEL, VALIDATION_DIR

#: the shipped library's runs: the validation campaign and the library beside it
DEFAULT_RUNS = (VALIDATION_DIR, LIBRARY_DIR)


def default_runs() -> list[str]:
    return [str(p) for folder in DEFAULT_RUNS for p in sorted(folder.glob("dem-*.h5"))]


@dataclass(frozen=True)
class LibraryFitOutput:
    model: LibraryModel
    check: calibration.Check
    files: dict[str, Path]


def library_fit(
    paths: list[str], out: str | Path, settings: FitSettings | None = None, log: Log = stderr_log
) -> LibraryFitOutput:
    """Fit, calibrate and check the library of ``paths`` into the folder ``out``
    (``settings`` default :class:`FitSettings`)."""
    settings = settings or FitSettings()
    folder = writable_directory(out, "--out")
    runs = load_runs(paths, settings)
    model = calibration.calibrated(fit_library(runs, settings, folder / "fits", log))
    check = calibration.check(model)
    files = {
        "model": save_model(model, folder / "library.json"),
        "check": write_json(folder / "calibration.json", check.record()),
    }
    files["page"] = folder / "calibration.md"
    files["page"].write_text(
        "# The library's law, each run predicted without it\n\n"
        f"Made by `pbmdem library fit --out {out}` from {len(runs)} DEM runs.\n\n"
        + calibration.markdown(model, check)
        + "\n"
    )
    return LibraryFitOutput(model, check, files)


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
    check = calibration.judge_results(model, paths, extrapolate)
    text = calibration.markdown(model, check, calibration.NOT_HELD)
    files: dict[str, Path] = {}
    if out is not None:
        folder = writable_directory(out, "--out")
        files["check"] = write_json(folder / "check.json", check.record())
        files["page"] = folder / "check.md"
        shown = library if library is not None else "the shipped library (workflows/reference/library/law)"
        files["page"].write_text(f"# DEM runs the library does not hold, predicted by {shown}\n\n{text}\n")
    return LibraryCheckOutput(check, text, files)


@dataclass(frozen=True)
class PredictOutput:
    prediction: Prediction
    files: dict[str, Path]
    wall_time_s: float


def prediction_record(prediction: Prediction, config_name: str, library: Path) -> dict[str, Any]:
    return {
        "config": config_name,
        "library": str(library),
        "point": prediction.point.record(),
        "extrapolated": prediction.extrapolated,
        "outside_domain": list(prediction.outside),
        "domain": prediction.domain.describe(),
        "level": 0.95,
        # the library's grid: the slices of holdup_slice_<i>, whatever grid the configuration's DEM would bin on
        "grid": [prediction.values.model.nx, prediction.values.model.ny],
        "quantities": [q.record() for q in prediction.quantities],
        "interval_parts": {q.key: q.details() for q in prediction.quantities},
    }


def run_predict(
    config_path: str | Path,
    library: str | Path | None = None,
    out: str | Path = "results/predict",
    extrapolate: bool = False,
    figures: bool = True,
) -> PredictOutput:
    """Predict the configuration at ``config_path`` from the library model ``library``
    (default the shipped one) and write the files of the module docstring."""
    started = time.perf_counter()
    config = load_config(config_path)
    library_path = Path(library) if library is not None else LIBRARY_MODEL
    model = load_model(library_path)
    point = operating_point(config.dem)
    prediction = predict(model, point, config.dem.geometry.blade_pattern, extrapolate)
    folder = writable_directory(out, "--out")
    duration = config.dem.operation.duration_s
    if not duration > 0:
        raise ConfigError(f"dem.operation.duration_s = {duration!r}: the PBM's table needs a run length > 0")
    files = {
        "prediction": write_json(
            folder / "prediction.json", prediction_record(prediction, config.name or str(config_path), library_path)
        ),
        "table": write_table(folder / "table.h5", point_table(prediction.values, point, duration)),
    }
    if figures:
        from workflows.report.prediction import plot_prediction, prediction_html

        files["figure"] = plot_prediction(prediction, folder / "prediction.png")
        page = prediction_html(
            prediction,
            config.name or str(config_path),
            files["figure"].name,
            {"prediction.json": "prediction.json", "PBM table (HDF5)": "table.h5"},
        )
        files["report"] = folder / "report.html"
        files["report"].write_text(page)
    return PredictOutput(prediction, files, time.perf_counter() - started)
