"""``pbmdem study series``: each curve recovers the shape it is, refuses what its points
cannot fix, and on the shipped library the series are the star's arms and the bound is
never beaten by a form it picks from."""

import math

import numpy as np
import pytest

from workflows.cli.main import main
from workflows.prediction.calibration import check
from workflows.shipped import LIBRARY_MODEL
from workflows.studies import calibrated_library
from workflows.studies.series import BOUND, FORMS, curve_checks, curve_prediction, series_of, table


def test_each_form_predicts_an_end_of_its_own_shape_exactly_and_the_others_do_not():
    u = np.log(np.array([0.8, 1.0, 1.2, 1.4]))
    end = math.log(0.6)
    shapes = {
        "line in log": lambda v: 1.0 - 0.4 * v,
        "parabola in log": lambda v: 1.0 - 0.4 * v - 0.9 * v**2,
        "line in the ratio": lambda v: 1.0 - 0.7 * np.expm1(v),
    }
    for shape, f in shapes.items():
        for form in FORMS:
            error = abs(curve_prediction(u, f(u), end, form) - f(end))
            if form == shape or (shape == "line in log" and form == "parabola in log"):
                assert error < 1e-9, (shape, form)
            else:
                assert error > 1e-3, (shape, form)


def test_a_curve_that_its_distinct_points_cannot_fix_gives_nan():
    u = np.log(np.array([1.0, 1.0, 1.5]))
    assert math.isnan(curve_prediction(u, np.array([1.0, 1.1, 0.9]), 0.0, "parabola in log"))
    assert math.isfinite(curve_prediction(u, np.array([1.0, 1.1, 0.9]), 0.0, "line in log"))


@pytest.fixture(scope="module")
def shipped():
    model = calibrated_library(LIBRARY_MODEL)
    law = check(model)
    return model, law, curve_checks(model, law)


def test_the_shipped_librarys_series_are_its_three_arms_through_the_baseline(shipped):
    model, _, _ = shipped
    series = series_of(model)
    assert set(series) == {"speed", "length", "feed"}
    baseline = set(series["speed"]) & set(series["length"]) & set(series["feed"])
    assert len(baseline) == 2  # the baseline and its replicate
    assert sum(len(runs) for runs in series.values()) - 2 * len(baseline) == len(model.runs)


def test_the_bound_holds_every_value_some_form_holds(shipped):
    model, law, curves = shipped
    for axis, forms in curves.items():
        for run in {r.run for r in forms[BOUND].rows}:
            bound = {r.key: r.inside_widened for r in forms[BOUND].of_run(run)}
            for form in FORMS:
                for r in forms[form].of_run(run):
                    assert bound[r.key] or not r.inside_widened, (axis, run, form, r.key)
    rows = table(model, law, curves)
    assert all(row["inside"][BOUND] >= max(row["inside"][f] for f in FORMS) for row in rows)
    # the law's column is its own check's verdict
    assert all(row["predicted"]["the library's law"] == law.verdict(row["run"])[0] for row in rows)


def test_the_shipped_librarys_page_is_written(tmp_path):
    assert main(["study", "series", "--out", str(tmp_path)]) == 0
    page = (tmp_path / "series.md").read_text()
    assert "| speed | 0.6 | end |" in page and "| feed | 2 | end |" in page and BOUND in page
