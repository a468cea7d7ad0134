"""``pbmdem predict``: the files it writes.

``predict`` reads a configuration and a library model and writes, into its output folder:
``prediction.json`` (one ``{key, value, low, high}`` per quantity of the comparison's
agreement table, with the point, the domain and each interval's parts; under ``dynamics``
the VRR of feeder A's white noise and the outlet's answer to feeder A's rate doubled, each
with its interval, :func:`workflows.prediction.design.point_dynamics`; under ``rtd`` the
predicted E(t) with its band), ``table.h5`` (the PBM's table at the point: ``pbmdem pbm run
--tables`` runs it), and ``prediction.png`` and ``report.html``, made from the record
``prediction.json`` holds by a process that imports matplotlib alone
(:data:`workflows.report.PREDICTION_FIGURES`).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from coupling.errors import ConfigError
from coupling.files import output_directory_path, refuse_output_over_inputs, replace_file, writable_directory
from coupling.forked import Prepared
from coupling.jsonable import write_json
from coupling.tables import write_table
from dem.operating import operating_point
from workflows.config import load_config, override
from workflows.prediction.design import Dynamics, Noise, point_dynamics, surrogate
from workflows.prediction.library import load_model, physics_of
from workflows.prediction.predict import LEVEL, Prediction, point_table, predict
from workflows.report import PREDICTION_FIGURES
from workflows.shipped import LIBRARY_MODEL


@dataclass(frozen=True)
class PredictOutput:
    prediction: Prediction
    dynamics: Dynamics
    files: dict[str, Path]
    wall_time_s: float


#: the feeder noise whose VRR ``predict`` reports
NOISE = Noise()


def prediction_record(prediction: Prediction, dynamics: Dynamics, config_name: str, library: Path) -> dict[str, Any]:
    """``prediction.json``'s content, from which the page and its figure are made too."""
    return {
        "config": config_name,
        "library": str(library),
        "point": prediction.point.record(),
        "extrapolated": prediction.extrapolated,
        "outside_domain": list(prediction.outside),
        # no library run has its blade layout: each interval at least the layout floor
        "new_layout": prediction.new_layout,
        "domain": prediction.domain.describe(),
        "level": LEVEL,
        # the library's grid: the slices of holdup_slice_<i>, whatever grid the configuration's DEM would bin on
        "grid": [prediction.values.model.nx, prediction.values.model.ny],
        "quantities": [q.record() for q in prediction.quantities],
        "interval_parts": {q.key: q.details() for q in prediction.quantities},
        "dynamics": dynamics.record(),
        "noise": NOISE._asdict(),
        # E(t) at the predicted mean residence time, and the envelope at its interval's ends
        "rtd": {
            "times_s": prediction.rtd_times_s.tolist(),
            "density_per_s": dict(zip(("value", "low", "high"), (row.tolist() for row in prediction.rtd))),
        },
    }


def run_predict(
    config_path: str | Path,
    library: str | Path | None = None,
    out: str | Path = "results/predict",
    extrapolate: bool = False,
    figures: bool = True,
    drawer: Prepared | None = None,
    settings: Sequence[str] = (),
) -> PredictOutput:
    """Predict the configuration at ``config_path``, with ``settings`` (``PATH=VALUE``,
    :func:`workflows.config.override`) applied, from the library model ``library``
    (default the shipped one) and write the files of the module docstring. ``drawer``: a
    process of :data:`workflows.report.PREDICTION_FIGURES` forked by the caller before its
    own imports, which draws the figure and makes the page while this process writes the
    rest; else they are made here."""
    started = time.perf_counter()
    config = load_config(config_path)
    if settings:
        config = override(config, *settings)
    library_path = Path(library) if library is not None else LIBRARY_MODEL
    # before any work, nothing created: an output over an input, or no directory, is refused at once
    planned = output_directory_path(out, "--out", ConfigError)
    for written in ("prediction.json", "table.h5", "prediction.png", "report.html"):
        refuse_output_over_inputs(planned / written, [config_path, library_path], "--out", ConfigError)
    model = load_model(library_path)
    point = operating_point(config.dem)
    physics = physics_of(config.dem)
    # the design's surrogate holds the floors the prediction keeps: made once
    design = surrogate(model, extrapolate)
    prediction = predict(model, point, config.dem.geometry.blade_pattern, extrapolate, physics, design.floors)
    dynamics = point_dynamics(design, point, NOISE, physics)
    folder = writable_directory(out, "--out")
    name = config.name or str(config_path)
    record = prediction_record(
        prediction, dynamics, f"{name} with {', '.join(settings)}" if settings else name, library_path
    )
    if figures:
        drawer = drawer or Prepared(PREDICTION_FIGURES, fork=False)
        links = {"prediction.json": "prediction.json", "PBM table (HDF5)": "table.h5"}
        drawer.start("draw", record, folder / "prediction.png", links)
    duration = config.dem.operation.duration_s
    files = {
        "prediction": write_json(folder / "prediction.json", record),
        "table": write_table(folder / "table.h5", point_table(prediction.values, point, duration)),
    }
    if figures:
        page = drawer.result()
        files["figure"] = folder / "prediction.png"
        files["report"] = folder / "report.html"
        replace_file(files["report"], page, "page")
    return PredictOutput(prediction, dynamics, files, time.perf_counter() - started)
