"""``pbmdem study series``: how near any smooth curve of one change, fitted to the DEM's own
values, comes to each run of the library left out, judged by the law's own verdict.

A library of one change at a time is a star: its *baseline* (the point from which the
most runs differ in at most one of speed, length and feed) and, per axis, the runs that
change only that one from it (a *series*, the baseline's runs in each). Left out, a run
is predicted by the library's law (:func:`check`); here it is predicted instead by a
curve through the DEM's values of the other runs of its series, on each quantity's scale
(the log; the value for C_A and the Lacey index), in u, the log of the series' covariate
over the baseline's (:func:`run_covariates`):

* a line in u;
* a parabola in u;
* a line in the ratio e^u (the DEM's hold-up falls nearly linearly in the speed);
* per quantity, the one of those nearest the DEM's value, picked after seeing it.

The last is no prediction: it is the nearest these shapes through the other runs of the
series come, whichever a law of that one covariate took. Each is judged by the law's
verdict (:meth:`Check.verdict`: every headline quantity and all but two others inside the
DEM's interval widened by the seed scatter); a curve its points cannot fix predicts
nothing, and a run missing a headline quantity is not predicted. A run is at an *end* of
its series, or *inside* it, or has a *twin* (a replicate at its point, left in: the
curves then pass through it). The length series changes more than one thing: its
blenders have other stations and another gap to the weir. Writes ``series.md`` and
``series.json``.
"""

from __future__ import annotations

import argparse
import math
import os
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import NamedTuple

import numpy as np

from coupling.errors import ConfigError
from workflows.prediction.calibration import HEADLINE, Check, CheckedQuantity, check
from workflows.prediction.covariates import run_covariates
from workflows.prediction.library import ABSOLUTE_KEYS, LibraryModel
from workflows.prediction.predict import DOMAIN_AXES
from workflows.studies import add_library_arguments, calibrated_library, write_page

HELP = "how near a smooth curve of one change, through the DEM's other runs of it, comes to each run left out"
OUT = Path("results/series")
#: each form's columns of the series' covariate u (module docstring)
FORMS = {
    "line in log": lambda u: [np.ones_like(u), u],
    "parabola in log": lambda u: [np.ones_like(u), u, u**2],
    "line in the ratio": lambda u: [np.ones_like(u), np.expm1(u)],
}
BOUND = "nearest of the three (picked after seeing the DEM)"
#: two covariates closer than this are the same
TOL = 1e-9


class Series(NamedTuple):
    """The library's runs of one series, and each one's log ratio u to the baseline's."""

    runs: list[int]
    u: np.ndarray


def _covariates(model: LibraryModel) -> np.ndarray:
    return np.array([[run_covariates(r.point)[a] for a in DOMAIN_AXES] for r in model.runs])


def baseline_of(model: LibraryModel) -> np.ndarray:
    """The library's baseline (module docstring): its covariates on :data:`DOMAIN_AXES`."""
    x = _covariates(model)
    points = np.unique(np.round(x, 9), axis=0)

    def reach(p: np.ndarray) -> tuple[int, int]:
        off = np.abs(x - p) > TOL
        return int(np.sum(off.sum(axis=1) <= 1)), int(np.sum(off.sum(axis=1) == 0))

    return max(points, key=reach)


def series_of(model: LibraryModel) -> dict[str, Series]:
    """Per axis of :data:`DOMAIN_AXES`, the :class:`Series` of the library's runs whose other
    two covariates are the baseline's (the baseline's runs in each), those of at least three
    distinct values. Raises ConfigError when no axis has one: the study needs a star."""
    x = _covariates(model) - baseline_of(model)
    out = {}
    for k, axis in enumerate(DOMAIN_AXES):
        others = np.delete(x, k, axis=1)
        runs = [n for n in range(len(model.runs)) if np.all(np.abs(others[n]) < TOL)]
        if len(np.unique(np.round(x[runs, k], 9))) >= 3:
            out[axis] = Series(runs, x[runs, k])
    if not out:
        raise ConfigError(
            f"the library's {len(model.runs)} runs hold no series: a series needs three values of one of "
            f"{', '.join(DOMAIN_AXES)} with the other two at the baseline's"
        )
    return out


def curve_prediction(u: np.ndarray, y: np.ndarray, at: float, form: str) -> float:
    """The value at ``at`` of the least-squares curve ``form`` (:data:`FORMS`) through
    (``u``, ``y``); NaN when the distinct values of ``u`` cannot fix its coefficients."""
    columns = FORMS[form]
    p = len(columns(np.zeros(1)))
    if len(np.unique(np.round(u, 9))) < p:
        return math.nan
    coefficients = np.linalg.lstsq(np.column_stack(columns(u)), y, rcond=None)[0]
    return float((np.column_stack(columns(np.array([at]))) @ coefficients)[0])


def _scale(key: str, value: float) -> float:
    return value if key in ABSOLUTE_KEYS else (math.log(value) if value > 0 else math.nan)


def _unscale(key: str, value: float) -> float:
    return value if key in ABSOLUTE_KEYS else math.exp(value)


def curve_checks(model: LibraryModel, law: Check) -> dict[str, dict[str, Check]]:
    """Per series and form (:data:`FORMS` and :data:`BOUND`), each of the series' runs
    predicted by the curve through the others, as rows of ``law`` (the law's check: the
    DEM's intervals and seed scatter it judges by) with the curve's value; no row where the
    curve predicts nothing."""
    out: dict[str, dict[str, Check]] = {}
    for axis, (runs, u) in series_of(model).items():
        by_form: dict[str, list[CheckedQuantity]] = {form: [] for form in (*FORMS, BOUND)}
        for i, n in enumerate(runs):
            for row in law.of_run(model.runs[n].file):
                known = [(u[j], model.runs[m].dem.get(row.key)) for j, m in enumerate(runs) if j != i]
                pairs = [(v, _scale(row.key, e.value)) for v, e in known if e is not None]
                pairs = [(v, y) for v, y in pairs if math.isfinite(y)]
                if not pairs:
                    continue
                uu, yy = np.array([v for v, _ in pairs]), np.array([y for _, y in pairs])
                values = {form: _unscale(row.key, curve_prediction(uu, yy, u[i], form)) for form in FORMS}
                values = {form: v for form, v in values.items() if math.isfinite(v)}
                for form, value in values.items():
                    by_form[form].append(replace(row, value=value, low=value, high=value))
                if values:
                    nearest = min(values.values(), key=lambda v: abs(v - row.dem))
                    by_form[BOUND].append(replace(row, value=nearest, low=nearest, high=nearest))
        out[axis] = {form: Check(tuple(rows), law.seed_sd, law.seed_pairs) for form, rows in by_form.items()}
    return out


def predicted(result: Check, run: str) -> bool:
    """The verdict on ``run``, a headline quantity its predictor gave no value for a miss."""
    keys = {r.key for r in result.of_run(run)}
    return all(k in keys for k in HEADLINE) and result.verdict(run)[0]


def _cell(result: Check, run: str, of: int) -> str:
    rows = result.of_run(run)
    if not rows:
        return "-"
    inside = sum(r.inside_widened for r in rows)
    return f"{inside}/{of}{' **yes**' if predicted(result, run) else ''}"


#: where a run lies in its series (module docstring), in the page's order
PLACES = ("end", "inside", "twin")


def table(model: LibraryModel, law: Check, curves: dict[str, dict[str, Check]]) -> list[dict]:
    """One row per (series, run): where the run lies in its series (:data:`PLACES`), and per
    predictor the quantities inside the DEM's interval widened by the seed scatter, those
    missed, the values and the verdict."""
    rows = []
    series = series_of(model)
    for axis, forms in curves.items():
        runs, u = series[axis]
        for n, value in zip(runs, u):
            run = model.runs[n].file
            of = len(law.of_run(run))
            twins = int(np.sum(np.abs(u - value) < TOL)) - 1
            place = "twin" if twins else ("end" if value <= u.min() + TOL or value >= u.max() - TOL else "inside")
            predictors = {"the library's law": law, **forms}
            rows.append(
                {
                    "series": axis,
                    "run": run,
                    "ratio": math.exp(value),
                    "place": place,
                    "of": of,
                    "inside": {
                        name: sum(r.inside_widened for r in result.of_run(run)) for name, result in predictors.items()
                    },
                    "predicted": {name: predicted(result, run) for name, result in predictors.items()},
                    "missed": {
                        name: [r.key for r in result.of_run(run) if not r.inside_widened]
                        for name, result in predictors.items()
                    },
                    "values": {
                        name: {r.key: r.value for r in result.of_run(run)} for name, result in predictors.items()
                    },
                    "cells": {name: _cell(result, run, of) for name, result in predictors.items()},
                }
            )
    return rows


def markdown(rows: Sequence[dict], library: str, n_runs: int) -> str:
    names = list(rows[0]["cells"]) if rows else []
    lines = [
        "# One change at a time: how near a smooth curve through the other runs comes to each run",
        "",
        f"Made by `pbmdem study series --library {library}` from its {n_runs} runs "
        "(`workflows/studies/series.py`). Each run of a series (the runs that change one covariate from the "
        "baseline's) left out and predicted by the library's law, and by curves through the DEM's values of the "
        "series' other runs in that covariate's log ratio u to the baseline's. Each cell: the quantities inside "
        "the DEM's interval widened by the seed scatter, and **yes** where the verdict predicts the run (every "
        "headline quantity and all but two others inside); - where the curve's points cannot fix it. The last "
        "column picks, per quantity, the curve nearest the DEM's value after seeing it: not a prediction, but the "
        "nearest any of these shapes through the other runs comes. A run is at an end of its series, inside it, "
        "or has a twin, a replicate at its point that stays in. The length series changes the stations and the "
        "gap to the weir with the length.",
        "",
        "| series | ratio to the baseline | place | " + " | ".join(names) + " |",
        "|" + " --- |" * (len(names) + 3),
    ]
    for row in rows:
        cells = " | ".join(row["cells"][n] for n in names)
        lines.append(f"| {row['series']} | {row['ratio']:.4g} | {row['place']} | {cells} |")
    groups = {place: [r for r in rows if r["place"] == place] for place in PLACES}
    lines += ["", "Runs predicted, by where they lie in their series:", ""]
    lines += ["| predictor | " + " | ".join(f"{p} ({len(g)})" for p, g in groups.items()) + " |"]
    lines += ["|" + " --- |" * (len(PLACES) + 1)]
    for name in names:
        counts = [str(sum(r["predicted"][name] for r in group)) for group in groups.values()]
        lines.append(f"| {name} | " + " | ".join(counts) + " |")
    return "\n".join(lines) + "\n"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_library_arguments(parser, OUT)


def run(args: argparse.Namespace) -> int:
    model = calibrated_library(args.library)
    law = check(model)
    rows = table(model, law, curve_checks(model, law))
    text = markdown(rows, os.path.relpath(args.library), len(model.runs))
    write_page(args.out, "series", text, {"runs": [{k: v for k, v in row.items() if k != "cells"} for row in rows]})
    return 0
