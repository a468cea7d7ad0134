"""The notebook API's own functions (the names ``workflows`` exports, :mod:`workflows`);
the others are the library's, exported as they are."""

from __future__ import annotations

from pathlib import Path

from dem.operating import operating_point
from workflows.config import Config, load_config
from workflows.prediction.library import load_model, physics_of
from workflows.prediction.predict import Prediction
from workflows.prediction.predict import predict as predict_point
from workflows.shipped import LIBRARY_MODEL


def predict(config: Config | str | Path, library: str | Path | None = None, extrapolate: bool = False) -> Prediction:
    """The operating point of ``config`` (a :class:`Config`, or the path of its TOML file)
    predicted from a DEM library's law, without a DEM run: what ``pbmdem predict`` prints.

    ``library``: a library model (``library.json``, made by ``pbmdem library fit``); default
    the shipped one (:data:`LIBRARY_MODEL`). Returns a
    :class:`~workflows.prediction.predict.Prediction` whose ``quantities`` each hold a
    ``value`` and its 95 % prediction interval ``low``-``high``, keyed (``.quantity(key)``) as
    the comparison's agreement table: ``mean_residence_time_s`` [s], ``rtd_variance_s2``
    [s^2], ``little_mean_residence_time_s`` [s] (hold-up / outflow), ``holdup``
    [particles], ``outflow_per_s`` [particles/s], ``C_A`` [-], ``rsd_outlet`` [-],
    ``lacey_outlet`` [-], ``holdup_slice_<i>`` [particles], i from 1 at the inlet
    (:data:`~workflows.prediction.library.AXIAL_SLICES` slices). A point outside the
    library's domain raises ConfigError unless ``extrapolate``; then the prediction is
    labelled (``.extrapolated``) and its intervals widened."""
    if not isinstance(config, Config):
        config = load_config(config)
    model = load_model(LIBRARY_MODEL if library is None else library)
    point = operating_point(config.dem)
    return predict_point(model, point, config.dem.geometry.blade_pattern, extrapolate, physics_of(config.dem))
