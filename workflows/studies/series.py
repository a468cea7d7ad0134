"""``pbmdem study series``: how near any smooth curve of one change, fitted to the DEM's own
values, comes to each run of the library left out, judged by the law's own verdict.

The library is a star: runs that change the speed, the feed or the length from the
baseline one at a time (a *series*: the runs whose other two covariates are the
baseline's). Left out, a run is predicted by the library's law (:func:`check`); here it is
predicted instead by a curve through the DEM's values of the other runs of its series, on
each quantity's scale (the log; the value for C_A and the Lacey index), in the series'
covariate u (the log of the ratio to the baseline's: :func:`run_covariates`):

* a line in u;
* a parabola in u;
* a line in the ratio e^u (the DEM's hold-up falls linearly in the speed);
* per quantity, the one of those nearest the DEM's value, picked after seeing it.

The last is no prediction: it is the bound that a law of one covariate could reach from
the other runs of the series, whichever of those shapes it took. Each is judged by the
law's verdict (:meth:`Check.verdict`: every headline quantity and all but two others
inside the DEM's interval widened by the seed scatter). A run the bound does not predict
is one that no curve of these shapes through the library's other runs predicts: only a
DEM run at or beyond its point can. Writes ``series.md`` and ``series.json``.
"""

from __future__ import annotations

import argparse
import math
import os
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from coupling.files import writable_directory
from coupling.jsonable import write_json
from workflows.prediction.calibration import Check, CheckedQuantity, check
from workflows.prediction.covariates import run_covariates
from workflows.prediction.library import ABSOLUTE_KEYS, LibraryModel
from workflows.prediction.predict import DOMAIN_AXES
from workflows.studies import add_library_arguments, calibrated_library

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


def series_of(model: LibraryModel) -> dict[str, list[int]]:
    """Per axis of :data:`DOMAIN_AXES`, the library's runs whose other two covariates are the
    baseline's (the baseline's runs in each), those of at least three distinct values."""
    x = np.array([[run_covariates(r.point)[a] for a in DOMAIN_AXES] for r in model.runs])
    out = {}
    for k, axis in enumerate(DOMAIN_AXES):
        others = np.delete(x, k, axis=1)
        runs = [n for n in range(len(model.runs)) if np.all(np.abs(others[n]) < TOL)]
        if len(np.unique(np.round(x[runs, k], 9))) >= 3:
            out[axis] = runs
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
    DEM's intervals and seed scatter it judges by) with the curve's value."""
    out: dict[str, dict[str, Check]] = {}
    for axis, runs in series_of(model).items():
        u = np.array([run_covariates(model.runs[n].point)[axis] for n in runs])
        by_form: dict[str, list[CheckedQuantity]] = {form: [] for form in (*FORMS, BOUND)}
        for i, n in enumerate(runs):
            others = np.arange(len(runs)) != i
            for row in law.of_run(model.runs[n].file):
                y = np.array([_scale(row.key, model.runs[m].dem[row.key].value) for m in np.array(runs)[others]])
                use = np.isfinite(y)
                values = {
                    form: _unscale(row.key, curve_prediction(u[others][use], y[use], u[i], form)) for form in FORMS
                }
                for form, value in values.items():
                    by_form[form].append(replace(row, value=value, low=value, high=value))
                finite = {f: v for f, v in values.items() if math.isfinite(v)}
                if finite:
                    nearest = min(finite.values(), key=lambda v: abs(v - row.dem))
                    by_form[BOUND].append(replace(row, value=nearest, low=nearest, high=nearest))
        out[axis] = {form: Check(tuple(rows), law.seed_sd, law.seed_pairs) for form, rows in by_form.items()}
    return out


def _cell(result: Check, run: str) -> str:
    rows = result.of_run(run)
    if not rows:
        return "-"
    ok, _ = result.verdict(run)
    inside = sum(r.inside_widened for r in rows)
    return f"{inside}/{len(rows)}{' **yes**' if ok else ''}"


def table(model: LibraryModel, law: Check, curves: dict[str, dict[str, Check]]) -> list[dict]:
    """One row per (series, run): where the run lies in its series, and per predictor the
    quantities inside the DEM's interval widened by the seed scatter, those missed, and
    the verdict."""
    rows = []
    for axis, forms in curves.items():
        runs = series_of(model)[axis]
        u = [run_covariates(model.runs[n].point)[axis] for n in runs]
        for n, value in zip(runs, u):
            run = model.runs[n].file
            end = value <= min(u) + TOL or value >= max(u) - TOL
            twins = sum(abs(v - value) < TOL for v in u) - 1
            predictors = {"the library's law": law, **forms}
            rows.append(
                {
                    "series": axis,
                    "run": run,
                    "ratio": math.exp(value),
                    "place": ("end" if end else "inside") + (f", {twins} twin" if twins else ""),
                    "inside": {
                        name: sum(r.inside_widened for r in result.of_run(run)) for name, result in predictors.items()
                    },
                    "of": len(law.of_run(run)),
                    "predicted": {name: result.verdict(run)[0] for name, result in predictors.items()},
                    "missed": {
                        name: [r.key for r in result.of_run(run) if not r.inside_widened]
                        for name, result in predictors.items()
                    },
                    "cells": {name: _cell(result, run) for name, result in predictors.items()},
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
        "series' other runs in that covariate's log ratio u. Each cell: the quantities inside the DEM's interval "
        "widened by the seed scatter, and **yes** where the verdict predicts the run (every headline quantity and "
        "all but two others inside). The last column picks, per quantity, the curve nearest the DEM's value after "
        "seeing it: not a prediction, but the nearest any of these shapes through the other runs comes.",
        "",
        "| series | ratio to the baseline | place | " + " | ".join(names) + " |",
        "|" + " --- |" * (len(names) + 3),
    ]
    for row in rows:
        cells = " | ".join(row["cells"][n] for n in names)
        lines.append(f"| {row['series']} | {row['ratio']:.4g} | {row['place']} | {cells} |")
    lines += ["", "Runs predicted, of those at the ends of their series and of those inside:", ""]
    lines += ["| predictor | ends | inside |", "| --- | --- | --- |"]
    ends = [r for r in rows if r["place"].startswith("end")]
    inside = [r for r in rows if not r["place"].startswith("end")]
    for name in names:
        counts = [f"{sum(r['predicted'][name] for r in group)} of {len(group)}" for group in (ends, inside)]
        lines.append(f"| {name} | {counts[0]} | {counts[1]} |")
    return "\n".join(lines) + "\n"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_library_arguments(parser, OUT)


def run(args: argparse.Namespace) -> int:
    model = calibrated_library(args.library)
    law = check(model)
    rows = table(model, law, curve_checks(model, law))
    text = markdown(rows, os.path.relpath(args.library), len(model.runs))
    print(text)
    out = writable_directory(args.out, "--out")
    (out / "series.md").write_text(text)
    records = [{k: v for k, v in row.items() if k != "cells"} for row in rows]
    written = write_json(out / "series.json", {"runs": records})
    print(f"wrote {out / 'series.md'} and {written}")
    return 0
