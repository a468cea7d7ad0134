"""``pbmdem study series``: each curve recovers the shape it is, refuses what its points
cannot fix, a run left out never informs its own prediction, the baseline is the star's
centre wherever it lies, and on the shipped library the bound is never beaten by a form it
picks from."""

import math
import re
from types import SimpleNamespace

import numpy as np
import pytest

from coupling.errors import ConfigError
from dem.operating import operating_point
from dem.summary import Estimate
from workflows.cli.main import main
from workflows.config import load_preset
from workflows.prediction.calibration import Check, CheckedQuantity, check
from workflows.shipped import LIBRARY_MODEL
from workflows.studies import calibrated_library
from workflows.studies.series import BOUND, FORMS, baseline_of, curve_checks, curve_prediction, series_of, table


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
    baseline = set(series["speed"].runs) & set(series["length"].runs) & set(series["feed"].runs)
    assert len(baseline) == 2  # the baseline and its replicate
    assert sum(len(s.runs) for s in series.values()) - 2 * len(baseline) == len(model.runs)
    assert all(abs(series["speed"].u[series["speed"].runs.index(n)]) < 1e-12 for n in baseline)


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
    assert "| speed | 0.6 | end |" in page and BOUND in page
    # the feed series has its two ends, whatever the shipped feeds
    assert len(re.findall(r"^\| feed \| [0-9.]+ \| end \|", page, flags=re.M)) == 2


BASE = operating_point(load_preset("validation").dem)


def _star(rpms, feeds, value, scale=1.0):
    """A hand-made library of one change at a time about (250 rpm, 73.7 /s) x ``scale``,
    each run's hold-up ``value(rpm, feed)``, and the law's check judging it: the DEM's
    interval +-0.1 %, no seed scatter."""
    points = [(r * scale, 73.7) for r in rpms] + [(250.0 * scale, f) for f in feeds]
    runs, rows = [], []
    for n, (rpm, feed) in enumerate(points):
        point = BASE.replace(impeller_rpm=rpm, feed_rate_a_per_s=feed / 2, feed_rate_b_per_s=feed / 2)
        v = value(rpm, feed)
        runs.append(SimpleNamespace(file=f"run{n}", point=point, dem={"holdup": Estimate(v, v * 0.999, v * 1.001)}))
        rows.append(CheckedQuantity(f"run{n}", "holdup", v, v * 0.999, v * 1.001, v, v, v, 0.0))
    return SimpleNamespace(runs=runs), Check(tuple(rows), {}, ())


def test_a_run_left_out_never_informs_its_own_prediction_and_a_parabola_in_log_is_recovered():
    def parabola(rpm, feed):
        u = math.log(rpm / 250.0)
        return math.exp(7.4 - 0.6 * u - 0.9 * u**2) * (feed / 73.7) ** 0.3

    rpms, feeds = (150.0, 200.0, 250.0, 300.0, 350.0), (36.85, 110.55)
    model, law = _star(rpms, feeds, parabola)
    curves = curve_checks(model, law)
    assert set(curves) == {"speed", "feed"}  # the feed's two values and the baseline's
    assert all(r.value == pytest.approx(r.dem, rel=1e-9) for r in curves["feed"]["line in log"].rows)
    fitted = {r.run: r.value for r in curves["speed"]["parabola in log"].rows}
    assert fitted["run0"] == pytest.approx(parabola(150.0, 73.7), rel=1e-9)
    # the left-out run's own value moved: its prediction does not move, the others' do
    moved = _star(rpms, feeds, lambda r, f: parabola(r, f) * (1.5 if r == 150.0 else 1.0))
    again = {r.run: r.value for r in curve_checks(*moved)["speed"]["parabola in log"].rows}
    assert again["run0"] == pytest.approx(fitted["run0"], rel=1e-12)
    assert again["run4"] != pytest.approx(fitted["run4"], rel=1e-3)
    places = {row["run"]: row["place"] for row in table(model, law, curves) if row["series"] == "speed"}
    assert places == {"run0": "end", "run1": "inside", "run2": "inside", "run3": "inside", "run4": "end"}


def test_the_baseline_is_the_stars_centre_wherever_it_lies_and_a_replicate_is_a_twin():
    rpms, feeds = (150.0, 200.0, 250.0, 250.0, 350.0), (36.85, 110.55, 147.4)
    model, law = _star(rpms, feeds, lambda r, f: 1000.0 * (250.0 / r) * (f / 73.7) ** 0.3, scale=0.8)
    assert baseline_of(model)[0] == pytest.approx(math.log(0.8))
    series = series_of(model)
    assert set(series) == {"speed", "feed"}
    rows = table(model, law, curve_checks(model, law))
    ratios = {(r["series"], r["run"]): (r["ratio"], r["place"]) for r in rows}
    assert ratios[("speed", "run0")] == (pytest.approx(0.6), "end")
    assert ratios[("speed", "run2")][1] == "twin" and ratios[("feed", "run3")][1] == "twin"


def test_a_library_without_a_series_is_refused_naming_what_a_series_needs():
    model, _ = _star((150.0, 250.0), (110.55,), lambda r, f: 1000.0)
    with pytest.raises(ConfigError, match="hold no series: a series needs three values"):
        series_of(model)


def test_a_curve_its_points_cannot_fix_predicts_nothing_and_the_run_is_not_predicted_by_it():
    rpms = (150.0, 250.0, 350.0)
    model, law = _star(rpms, (), lambda r, f: 1000.0 * (250.0 / r))
    curves = curve_checks(model, law)["speed"]
    # two points left: no parabola, a line each
    assert not curves["parabola in log"].rows and len(curves["line in log"].rows) == 3
    rows = table(model, law, curve_checks(model, law))
    assert all(row["cells"]["parabola in log"] == "-" and not row["predicted"]["parabola in log"] for row in rows)
