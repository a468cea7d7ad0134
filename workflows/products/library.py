"""``pbmdem library fit`` and ``pbmdem library check``: the files they write.

``library fit`` fits the law of a DEM library and its laws left out
(:func:`workflows.prediction.library.fit_library`), calibrates the intervals on them
(:mod:`workflows.prediction.calibration`) and writes ``library.json``, the check of the
intervals on every run left out (``calibration.md``, ``calibration.json``) and the fits'
cache (``fits/``). ``library check`` predicts DEM runs the library does not hold and judges
each against its DEM (``check.md``, ``check.json``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from coupling.files import writable_directory
from coupling.jsonable import write_json
from workflows.pipeline.log import Log, stderr_log
from workflows.prediction import calibration
from workflows.prediction.library import FitSettings, LibraryModel, fit_library, load_model, load_runs, save_model
from workflows.shipped import LIBRARY_MODEL


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
        + "\n\n"
        + calibration.alternatives(model)
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
