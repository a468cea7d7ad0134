"""The next DEM run of a library (workflows.prediction.suggest, ``pbmdem library suggest``
and ``add``): the interval's arithmetic by hand, a noise-free linear truth, a corner
region, the blade-station rule against the shipped configurations, and the commands'
files and refusals."""

import json
import math
import shutil
import tomllib
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from coupling.errors import ConfigError
from dem.operating import operating_point
from tests.workflows.prediction.small_library import SPEEDS
from workflows.cli.main import main
from workflows.config import config_from_dict, load_config, load_preset
from workflows.prediction.covariates import run_covariates
from workflows.prediction.library import CORRECTION_DOF, correction_row, load_model, slice_key
from workflows.prediction.predict import Floors, domain, fit_correction, floors, placement
from workflows.prediction.profile import fit_profile, refit, without_layouts
from workflows.prediction.suggest import (
    Candidate,
    Least,
    Quantity,
    Region,
    config_at,
    criterion,
    half_widths,
    least_bounds,
    library_quantities,
    parse_region,
    profile_half_widths,
    rank,
    scaled_duration,
    widened,
)
from workflows.shipped import LIBRARY_DIR, VALIDATION_DIR

BASE = load_preset("validation")
POINT = operating_point(BASE.dem)
SPAN = Region((150.0, 350.0), (0.33, 0.33), (36.85, 147.4))


def _at(rpm: float, feed: float = 73.7):
    return POINT.replace(impeller_rpm=rpm, feed_rate_a_per_s=feed / 2, feed_rate_b_per_s=feed / 2)


def _candidates(speeds, feeds=(73.7,)):
    return [Candidate(s, 0.33, f, _at(s, f)) for s in speeds for f in feeds]


def test_the_expected_half_widths_after_one_run_are_the_textbook_line_refitted_by_hand():
    """One covariate (log speed): the criterion after a run at c is the mean over the
    region of (t(n + 1 - 2) s sqrt(1 + x'(A'A + x_c x_c')^-1 x) / target)^2, s unchanged."""
    speeds, residuals = [150.0, 200.0, 250.0, 350.0], [0.01, -0.02, 0.015, 0.03]
    points = [_at(s) for s in speeds]
    region = [_at(s) for s in (150.0, 250.0, 350.0)]
    q = Quantity("holdup", tuple(points), tuple(residuals))
    out = rank([q], ("speed",), SPAN, region, _candidates([175.0, 300.0]))
    a = np.array([[1.0, math.log(s / 250.0)] for s in speeds])
    y = np.array(residuals)
    misfit = y - a @ np.linalg.lstsq(a, y, rcond=None)[0]
    s2 = misfit @ misfit / (4 - 2)
    x = np.array([[1.0, math.log(s / 250.0)] for s in (150.0, 250.0, 350.0)])

    def score(rows, dof):
        inverse = np.linalg.inv(rows.T @ rows)
        lev = np.array([r @ inverse @ r for r in x])
        h = stats.t.ppf(0.975, dof) * np.sqrt(s2 * (1 + lev))
        return float(np.mean((h / 0.04) ** 2))

    assert out[0].criterion_now == pytest.approx(score(a, 2), rel=1e-10)
    by_speed = {s.speed: s for s in out}
    for c in (175.0, 300.0):
        grown = np.vstack([a, [1.0, math.log(c / 250.0)]])
        assert by_speed[c].criterion_after == pytest.approx(score(grown, 3), rel=1e-10)
    assert out[0].criterion_after <= out[1].criterion_after


def test_a_run_that_lets_the_line_identify_a_covariate_is_scored_with_the_larger_form():
    """Three runs at one feed: the feed term is not identified; a fourth at another feed
    identifies it (and leaves CORRECTION_DOF degrees of freedom)."""
    points = [_at(s) for s in (150.0, 250.0, 350.0)]
    q = Quantity("holdup", tuple(points), (0.01, -0.01, 0.02))
    out = rank([q], ("feed",), SPAN, [_at(250.0)], _candidates([250.0], (36.85, 73.7)))
    grows = next(s for s in out if s.feed == 36.85)
    assert grows.gains == ("feed",) and next(s for s in out if s.feed == 73.7).gains == ()
    rows = np.array([correction_row(p, ("feed",)) for p in [*points, _at(250.0, 36.85)]])
    lev = correction_row(_at(250.0), ("feed",)) @ np.linalg.inv(rows.T @ rows) @ correction_row(_at(250.0), ("feed",))
    s2 = np.var([0.01, -0.01, 0.02], ddof=1)
    h = stats.t.ppf(0.975, CORRECTION_DOF) * math.sqrt(s2 * (1 + lev))
    assert grows.criterion_after == pytest.approx((h / 0.04) ** 2, rel=1e-10)


def test_the_vectorised_half_widths_are_the_corrections_own_intervals():
    rng = np.random.default_rng(5)
    points = [_at(s, f) for s in (150.0, 250.0, 350.0) for f in (40.0, 80.0, 140.0)]
    line = fit_correction(points, rng.normal(0, 0.02, len(points)), ("speed", "feed", "speed2"))
    region = [_at(s, f) for s in (170.0, 320.0) for f in (50.0, 120.0)]
    terms = np.array(
        [correction_row(p, ("speed", "speed2", "length", "length2", "feed", "feed2", "gap")) for p in region]
    )
    assert half_widths(line, terms) == pytest.approx([line.at(p)[1] for p in region], rel=1e-12)


def test_a_noise_free_linear_truth_is_learnt_exactly_once_the_runs_identify_the_line():
    """Residuals exactly linear in speed and feed: with p + CORRECTION_DOF runs the line
    is the truth and every interval has collapsed, and the rule has nothing left to gain."""
    names = ("speed", "feed")

    def truth(p):
        c = run_covariates(p)
        return 0.04 - 0.3 * c["speed"] + 0.1 * c["feed"]

    points = [_at(s, f) for s, f in ((150.0, 40.0), (350.0, 40.0), (150.0, 140.0), (350.0, 140.0), (250.0, 73.7))]
    assert len(points) == 3 + CORRECTION_DOF
    line = fit_correction(points, [truth(p) for p in points], names)
    assert line.names == names
    new = _at(300.0, 100.0)
    shift, half, _ = line.at(new)
    assert shift == pytest.approx(truth(new), abs=1e-12) and half == pytest.approx(0.0, abs=1e-12)
    q = Quantity("holdup", tuple(points), tuple(truth(p) for p in points))
    out = rank([q], names, SPAN, [new], _candidates([200.0, 300.0], (50.0, 120.0)))
    assert all(s.criterion_now == pytest.approx(0.0, abs=1e-20) for s in out)


def test_the_suggestion_for_a_region_at_a_corner_lies_at_that_corner():
    rng = np.random.default_rng(11)
    speeds, feeds = (150.0, 250.0, 350.0), (36.85, 73.7, 147.4)
    points = [_at(s, f) for s in speeds for f in feeds]
    q = Quantity("holdup", tuple(points), tuple(rng.normal(0, 0.01, len(points))))
    corner = Region((300.0, 350.0), (0.33, 0.33), (110.0, 147.4))
    region_points = [_at(s, f) for s, _, f in corner.grid(5)]
    grid = _candidates(
        np.exp(np.linspace(math.log(150), math.log(350), 7)), np.exp(np.linspace(math.log(36.85), math.log(147.4), 7))
    )
    best = rank([q], ("speed", "feed"), corner, region_points, grid)[0]
    assert best.speed >= 300.0 and best.feed >= 110.0
    whole = rank([q], ("speed", "feed"), SPAN, [_at(s, f) for s, _, f in SPAN.grid(5)], grid)[0]
    assert whole.criterion_after < whole.criterion_now


def test_a_region_is_parsed_within_the_span_and_refused_naming_what_is_wrong():
    region = parse_region("speed=200:300, feed=60", SPAN)
    assert region.speed == (200.0, 300.0) and region.feed == (60.0, 60.0) and region.length == SPAN.length
    assert parse_region(None, SPAN) == SPAN
    for text, words in (
        ("rpm=200:300", "AXIS=LOW:HIGH"),
        ("speed=300:200", "above high"),
        ("speed=100:200", "leaves the candidates' span"),
        ("speed=a:b", "LOW:HIGH"),
        ("speed=200,speed=250", "twice"),
    ):
        with pytest.raises(ConfigError, match=words):
            parse_region(text, SPAN)
    wide = widened(SPAN, 0.5)
    assert wide.speed[0] == pytest.approx(150.0 * (150.0 / 350.0) ** 0.5) and wide.length == SPAN.length
    assert parse_region("speed=120:350", wide).speed == (120.0, 350.0)


@pytest.mark.parametrize("name", ["length-x0.75", "length-x0.875", "length-x1.375", "length-x1.5"])
def test_a_length_keeps_the_station_spacing_as_the_shipped_library_configurations_do(name):
    shipped = load_config(LIBRARY_DIR / f"{name}.toml").dem.geometry
    built = config_at(BASE, 250.0, shipped.length_m, 73.7, 0.025).dem.geometry
    assert built.blade_stations == shipped.blade_stations
    assert built.last_blade_x_m == pytest.approx(shipped.last_blade_x_m, abs=1e-9)


def test_a_candidates_configuration_scales_the_feed_and_the_duration():
    config = config_at(BASE, 300.0, 0.4125, 36.85, 0.025, scaled_duration(200.0, 21.0, 34.0))
    assert config.dem.operation.impeller_rpm == 300.0 and config.dem.operation.duration_s == 330.0
    assert config.pbm.feed_rate_a_per_s == pytest.approx(36.85 / 2)
    assert (config.dem.geometry.blade_stations, config.dem.geometry.last_blade_x_m) == (13, pytest.approx(0.385))
    assert scaled_duration(200.0, 21.0, 15.0) == 200.0
    with pytest.raises(ConfigError, match="no blade station"):
        config_at(BASE, 250.0, 0.06, 73.7, 0.025)


def test_library_suggest_writes_a_configuration_that_runs_the_suggested_point(tmp_path, capsys):
    assert main(["library", "suggest", "--out", str(tmp_path), "--top", "3"]) == 0
    printed = capsys.readouterr().out.splitlines()
    assert (
        printed[0].startswith("1. ")
        and "criterion" in printed[0]
        and len([p for p in printed if p[:2] in ("1.", "2.", "3.")]) == 3
    )
    text = (tmp_path / "suggest.toml").read_text()
    config = config_from_dict(tomllib.loads(text))
    record = json.loads((tmp_path / "suggest.json").read_text())
    best = record["suggestions"][0]
    op = config.dem.operation
    assert (op.impeller_rpm, config.dem.geometry.length_m, op.feed_rate_total_per_s) == (
        best["speed_rpm"],
        best["length_m"],
        best["feed_per_s"],
    )
    assert best["criterion_after"] < best["criterion_now"] and op.duration_s >= 200.0
    assert "| mean_residence_time_s | 4 |" in (tmp_path / "suggest.md").read_text()


def test_library_suggest_refuses_a_region_outside_the_domain_in_one_line(tmp_path, capsys):
    assert main(["library", "suggest", "--out", str(tmp_path), "--region", "speed=100:200"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "150-350 rpm" in err[0]
    assert not (tmp_path / "suggest.toml").exists()


def test_library_suggest_refuses_a_base_of_other_particles_in_one_line(tmp_path, capsys):
    # the reduced preset's 5 mm particles: a run from it would not be a point of the 6 mm library
    argv = ["library", "suggest", "--out", str(tmp_path / "s"), "--base", "workflows/presets/reduced.toml"]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "particle_diameter_m = 0.005 (the library's is 0.006)" in err[0]
    assert not (tmp_path / "s").exists()


def test_library_suggest_refuses_a_model_file_it_would_not_read(tmp_path, capsys):
    # beside another library.json, other.json would have been passed over for it
    shutil.copytree(LIBRARY_DIR / "law", tmp_path / "law", ignore=shutil.ignore_patterns("fits", "unseen"))
    other = tmp_path / "law" / "other.json"
    shutil.copy(tmp_path / "law" / "library.json", other)
    assert main(["library", "suggest", "--library", str(other), "--out", str(tmp_path / "s")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"pbmdem: error: --library {other}: give a library's folder or the library.json in it"]
    assert not (tmp_path / "s").exists()


def test_an_extension_beyond_any_blender_is_refused_naming_extend(tmp_path, capsys):
    with pytest.raises(ConfigError, match=r"^--extend 1000 widens the domain .* beyond any operating point"):
        widened(SPAN, 1000.0)
    # five widths below the shortest library blender: no room for a blade station
    assert main(["library", "suggest", "--extend", "5", "--out", str(tmp_path / "s")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("pbmdem: error: --extend 5 reaches candidates no blender can run")
    assert not (tmp_path / "s").exists()


FEED = VALIDATION_DIR / "dem-26a744879a705d14.h5"


def test_library_add_refits_with_the_new_run_and_lists_every_runs_file(library, tmp_path):
    folder = tmp_path / "lib"
    shutil.copytree(library, folder)
    assert main(["library", "add", str(FEED), "--library", str(folder)]) == 0
    model = load_model(folder)
    assert [r.file for r in model.runs] == [p.name for p in SPEEDS] + [FEED.name]
    assert len(model.left_out) == 4 and model.settings["iterations"] == 3
    listed = {r["file"] for r in json.loads((folder / "runs.json").read_text())["runs"]}
    # relative to the library's folder, which is what a library moved with its runs needs
    assert not [f for f in listed if Path(f).is_absolute()]
    assert {(folder / f).resolve() for f in listed} == {p.resolve() for p in [*SPEEDS, FEED]}


def test_library_add_refuses_a_run_it_holds_and_a_missing_file_before_any_fit(library, tmp_path, capsys):
    folder = tmp_path / "lib"
    shutil.copytree(library, folder)
    before = (folder / "library.json").read_bytes()
    copy = tmp_path / "copy.h5"
    shutil.copyfile(SPEEDS[0], copy)
    for args, words in (([str(copy)], "copy of"), ([str(tmp_path / "none.h5")], "none.h5")):
        assert main(["library", "add", *args, "--library", str(folder)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and words in err[0]
    assert (folder / "library.json").read_bytes() == before
    assert main(["library", "add", str(FEED), "--library", str(tmp_path / "nowhere")]) == 2


def test_with_the_seed_scatter_known_a_curvature_the_line_misses_keeps_the_rule_off_the_corners():
    """Residuals that bend (a product of speed and feed) far beyond the seed scatter: on
    the line's intervals alone the rule picks a corner of the domain, where that bend is
    largest; with the bias it expects there it picks a point inside."""
    rng = np.random.default_rng(1)
    design = [(150.0, 36.85), (150.0, 147.4), (350.0, 36.85), (350.0, 147.4), (250.0, 73.7)]
    design += [(150.0, 73.7), (350.0, 73.7), (250.0, 36.85), (250.0, 147.4)]
    points = [_at(s, f) for s, f in design]

    def bend(p):
        c = run_covariates(p)
        return 0.05 * (c["speed"] / 0.4) * (c["feed"] / 0.69)

    q = Quantity("holdup", tuple(points), tuple(bend(p) + rng.normal(0, 0.002) for p in points))
    speeds = np.exp(np.linspace(math.log(150), math.log(350), 7))
    grid = _candidates(speeds, np.exp(np.linspace(math.log(36.85), math.log(147.4), 7)))
    region = [_at(s, f) for s, _, f in SPAN.grid(5)]
    corner = rank([q], ("speed", "feed"), SPAN, region, grid)[0]
    inside = rank([q], ("speed", "feed"), SPAN, region, grid, None, {"holdup": 0.002})[0]
    assert min(abs(corner.speed - 150.0), abs(corner.speed - 350.0)) < 1e-9
    assert min(abs(corner.feed - 36.85), abs(corner.feed - 147.4)) < 1e-9
    assert 151.0 < inside.speed < 349.0 and 37.0 < inside.feed < 147.0
    # within the seed scatter there is no bias to expect: the line's intervals alone
    same = rank([q], ("speed", "feed"), SPAN, region, grid, None, {"holdup": 1.0})[0]
    assert (same.speed, same.feed) == (corner.speed, corner.feed)


def test_candidates_beyond_the_domain_are_labelled_and_the_region_stays_the_domain():
    from workflows.prediction.suggest import suggest

    model = load_model(LIBRARY_DIR / "law")
    points = [r.point for r in model.runs]
    speeds = (min(p.impeller_rpm for p in points), max(p.impeller_rpm for p in points))
    feeds = (min(p.feed_rate_total_per_s for p in points), max(p.feed_rate_total_per_s for p in points))
    lengths = (min(p.length_m for p in points), max(p.length_m for p in points))
    ranked = suggest(model, BASE, extend=0.25)
    assert ranked[0].region.speed == pytest.approx(speeds) and ranked[0].region.feed == pytest.approx(feeds)
    outside = [s for s in ranked if s.outside_domain]

    def beyond(value, ends):
        return value < ends[0] * (1 - 1e-4) or value > ends[1] * (1 + 1e-4)

    assert outside and all(
        beyond(s.speed, speeds) or beyond(s.feed, feeds) or beyond(s.length, lengths) for s in outside
    )


def test_a_run_that_lets_the_line_see_a_covariate_of_its_form_comes_first():
    """Every run at one feed: the line cannot identify the feed term of its form, so its
    intervals leave out what the feed does. A run at another feed comes first, though
    another speed would narrow the smaller form's intervals more."""
    points = [_at(s) for s in (150.0, 200.0, 250.0, 300.0, 350.0)]
    q = Quantity("holdup", tuple(points), tuple(0.01 * (i % 2) for i in range(len(points))))
    grid = _candidates([150.0, 250.0, 350.0], (36.85, 73.7, 147.4))
    region = [_at(s, f) for s, _, f in SPAN.grid(3)]
    ranked = rank([q], ("speed", "feed"), SPAN, region, grid)
    assert ranked[0].feed != 73.7 and ranked[0].gains == ("feed",)
    assert all(not r.gains for r in ranked if r.feed == 73.7)
    first_plain = next(i for i, r in enumerate(ranked) if not r.gains)
    assert all(r.gains for r in ranked[:first_plain])


# ------------------------------------------------------------------ the slices' zone law
@pytest.fixture(scope="module")
def zoned():
    """A zone law fitted to nine of the shipped library's operating points (three
    lengths), their slices the shipped law's hold-ups times a known log-normal scatter."""
    shipped = load_model(LIBRARY_DIR / "law")
    truth = shipped.calibration.profile
    points = [r.point for r in shipped.runs[:9]]
    rng = np.random.default_rng(3)
    held = np.array([np.exp(truth.gradient(p)[0] + rng.normal(0.0, 0.03, truth.nx)) for p in points])
    law = fit_profile(points, held, shipped.blade_pattern, (truth.half_width_m,))
    return law, points, held, shipped


def _shortest(shipped):
    """The index of the shipped library's shortest blender, a layout the first nine runs lack."""
    return min(range(len(shipped.runs)), key=lambda n: shipped.runs[n].point.length_m)


def _information(gradients, sd):
    return sum(np.einsum("ip,i,iq->pq", g, sd**-2.0, g) for g in gradients)


def test_the_zone_laws_information_is_its_runs_gradients_weighted_by_each_slices_scatter(zoned):
    law, points, _, _ = zoned
    runs = [law.gradient(p)[1] for p in points]
    info = _information(runs, law.slice_sd)
    assert law.information() == pytest.approx(info, rel=1e-8, abs=1e-8 * np.abs(info).max())
    values, sd = without_layouts(law).log_slices(points[2])
    assert law.gradient(points[2])[0] == pytest.approx(values, rel=1e-14)
    extra = law.gradient(points[0])[1]
    expected = np.linalg.pinv(info + extra.T @ np.diag(law.slice_sd**-2.0) @ extra)
    assert law.covariance_after(extra) == pytest.approx(expected, rel=1e-6, abs=1e-9 * np.abs(expected).max())


@pytest.mark.parametrize("far", [True, False])
def test_the_covariance_after_a_run_on_the_law_is_the_refitted_laws(zoned, far):
    """A run whose slices lie on the law: refitted with it, the law's information is the
    runs' and the run's at the re-estimated scatters, the coefficients barely moved; each
    slice's degrees of freedom grow by about one, all of them by exactly one per slice."""
    law, points, held, shipped = zoned
    c = shipped.runs[_shortest(shipped)].point if far else points[4]
    values, extra = law.gradient(c)
    refitted = refit(law, [*points, c], np.vstack([held, np.exp(values)]))
    assert np.abs(refitted.coefficients - law.coefficients).max() < 0.05
    runs = _information([law.gradient(p)[1] for p in points], refitted.slice_sd)
    before = replace(law, slice_sd=refitted.slice_sd, covariance=np.linalg.pinv(runs))
    after = np.linalg.pinv(before.covariance_after(extra))
    assert np.abs(after - refitted.information()).max() < 1e-3 * np.abs(after).max()
    region = [r.point for r in shipped.runs]
    for p in region[::3]:
        g = law.gradient(p)[1]
        ours = np.einsum("ip,pq,iq->i", g, before.covariance_after(extra), g)
        theirs = np.einsum("ip,pq,iq->i", g, refitted.covariance, g)
        assert ours == pytest.approx(theirs, rel=0.02)
    grown = refitted.slice_dof - law.slice_dof
    assert grown.sum() == pytest.approx(law.nx, rel=1e-9) and np.all(np.abs(grown - 1.0) < 0.25)


def test_the_zone_laws_half_widths_now_are_its_intervals_and_a_run_far_from_the_runs_narrows_them_most(zoned):
    law, points, _, shipped = zoned
    region = [r.point for r in shipped.runs]
    short = _shortest(shipped)
    far, near = shipped.runs[short].point, points[4]  # the shortest blender; the centre run
    now, after = profile_half_widths(law, region, [far, near])
    assert now.shape == (law.nx, len(region)) and after.shape == (law.nx, 2, len(region))
    assert now == pytest.approx(np.array([law.at(p)[1] for p in region]).T, rel=1e-12)
    assert np.all(after <= now[:, None, :] * (1 + 1e-12))
    # after the run, at a layout the law has not run: its information added, and one
    # more degree of freedom per slice; at a layout run, its layout's interval stays
    assert not law.layouts.runs_at(region[short]) and law.layouts.runs_at(region[7])
    g, grown = law.gradient(region[short])[1], law.covariance_after(law.gradient(far)[1])
    by_hand = stats.t.ppf(0.975, law.slice_dof + 1) * np.sqrt(law.slice_sd**2 + np.einsum("ip,pq,iq->i", g, grown, g))
    assert after[:, 0, short] == pytest.approx(by_hand, rel=1e-10)
    assert np.array_equal(after[:, 1, 7], now[:, 7])
    keys = [slice_key(i) for i in range(law.nx)]
    score = criterion(dict(zip(keys, after)))  # (candidates,)
    assert score[0] < score[1] < criterion(dict(zip(keys, now)))


def test_with_a_zone_law_the_slices_are_judged_by_it_not_by_their_lines(zoned):
    law, points, _, shipped = zoned
    region = [r.point for r in shipped.runs[9:]]
    rng = np.random.default_rng(2)
    slices = [Quantity(slice_key(i), tuple(points), tuple(rng.normal(0, 0.3, len(points)))) for i in range(law.nx)]
    short = _shortest(shipped)
    cands = [Candidate(0.0, 0.0, 0.0, shipped.runs[n].point) for n in (10, short)]
    lines = rank(slices, ("speed",), SPAN, region, cands, pattern=shipped.blade_pattern)
    zone = rank(slices, ("speed",), SPAN, region, cands, pattern=shipped.blade_pattern, profile=law)
    now = np.array([law.at(p)[1] for p in region])
    for ranked, expected in ((zone, np.median(now, axis=0)), (lines, None)):
        got = np.array([r.now for r in ranked[0].reductions])
        assert [r.key for r in ranked[0].reductions] == [slice_key(i) for i in range(law.nx)]
        if expected is not None:
            assert got == pytest.approx(expected, rel=1e-12)
        else:
            assert not got == pytest.approx(np.median(now, axis=0), rel=0.1)
    assert zone[0].point is shipped.runs[short].point


def test_with_a_holdup_line_the_slices_carry_its_half_width_in_quadrature_as_predict_gives_them(zoned):
    law, points, _, shipped = zoned
    region = [r.point for r in shipped.runs[9:]]
    rng = np.random.default_rng(5)
    holdup = Quantity("holdup", tuple(points), tuple(rng.normal(0.0, 0.02, len(points))))
    cands = [Candidate(0.0, 0.0, 0.0, shipped.runs[_shortest(shipped)].point)]
    ranked = rank([holdup], ("speed",), SPAN, region, cands, pattern=shipped.blade_pattern, profile=law)
    line = fit_correction(holdup.points, holdup.residuals, ("speed",), shipped.blade_pattern)
    total = np.array([line.at(p)[1] for p in region])
    zone = np.array([law.at(p)[1] for p in region])  # (R, NX)
    by_key = {r.key: r for r in ranked[0].reductions}
    assert by_key["holdup"].now == pytest.approx(np.median(total), rel=1e-10)
    for i in range(law.nx):
        assert by_key[slice_key(i)].now == pytest.approx(np.median(np.hypot(zone[:, i], total)), rel=1e-10)


def test_without_a_zone_law_the_slices_lines_carry_the_holdups_half_width_too(zoned):
    _law, points, _, shipped = zoned
    region = [r.point for r in shipped.runs[9:]]
    rng = np.random.default_rng(6)
    holdup = Quantity("holdup", tuple(points), tuple(rng.normal(0.0, 0.02, len(points))))
    first = Quantity(slice_key(0), tuple(points), tuple(rng.normal(0.0, 0.05, len(points))))
    cands = [Candidate(0.0, 0.0, 0.0, shipped.runs[_shortest(shipped)].point)]
    ranked = rank([holdup, first], ("speed",), SPAN, region, cands, pattern=shipped.blade_pattern)
    lines = [fit_correction(q.points, q.residuals, ("speed",), shipped.blade_pattern) for q in (holdup, first)]
    total, own = (np.array([line.at(p)[1] for p in region]) for line in lines)
    by_key = {r.key: r for r in ranked[0].reductions}
    assert by_key[slice_key(0)].now == pytest.approx(np.median(np.hypot(own, total)), rel=1e-10)


# ------------------------------------------------------------------ the floors in the rule
def _star():
    """A star in speed and feed at the baseline's layout: its four ends lie beyond the
    others' hull, the centre inside."""
    return (_at(250.0), _at(150.0), _at(350.0), _at(250.0, 36.85), _at(250.0, 147.4))


def test_a_run_at_a_corner_takes_the_widening_and_the_end_floor_off_that_corner():
    """Predict's rule at a corner of a star (beyond the runs' hull): at least the end floor
    times its share, times 1 + the distance from the hull; after a run there, neither."""
    runs = _star()
    least = Least(Floors({"holdup": 0.05}, {}), runs, BASE.dem.geometry.blade_pattern)
    corner, centre = _at(350.0, 147.4), _at(250.0)
    region = Region((150.0, 350.0), (0.33, 0.33), (36.85, 147.4))
    now, after = least_bounds(least, region, [corner, centre], [corner, _at(200.0)])
    place = placement(domain(list(runs), least.pattern), corner, least.pattern)
    assert place.beyond > 0
    assert now.widening[0] == pytest.approx(place.widening) and now.widening[1] == 1.0
    assert now.floor["holdup"][0] == pytest.approx(0.05 * place.floor_share) and now.floor["holdup"][1] == 0.0
    # the corner's own run: the corner joins the hull; the run is a fifth end, so a point
    # still beyond it would keep t(5) / t(4) of the floor
    assert after.widening[0, 0] == 1.0 and after.floor["holdup"][0, 0] == 0.0
    # a run inside the hull leaves the corner's distance; its share of the floor is over
    # the ends' reach, which the run shortens (150 rpm is nearer 200 than 250)
    assert after.widening[1, 0] == pytest.approx(place.widening)
    grown = placement(domain([*runs, _at(200.0)], least.pattern), corner, least.pattern)
    assert grown.floor_share > place.floor_share
    assert after.floor["holdup"][1, 0] == pytest.approx(0.05 * grown.floor_share)
    half = np.array([0.01, 0.01])
    assert now.applied("holdup", half) == pytest.approx([0.05 * place.floor_share * place.widening, 0.01])


def test_an_end_run_more_moves_the_end_floor_by_student_t_of_its_count():
    runs = _star()
    least = Least(Floors({"holdup": 0.05}, {}), runs, BASE.dem.geometry.blade_pattern)
    region = Region((150.0, 400.0), (0.33, 0.33), (36.85, 147.4))
    far = _at(400.0)  # beyond the speed range: keeps all of the floor
    now, after = least_bounds(least, region, [far], [_at(150.0, 147.4)])
    ratio = stats.t.ppf(0.975, 5) / stats.t.ppf(0.975, 4)
    assert now.floor["holdup"][0] == pytest.approx(0.05)
    assert after.floor["holdup"][0, 0] == pytest.approx(0.05 * ratio)


def test_over_a_range_of_lengths_every_point_keeps_the_layout_floor_and_at_one_length_it_is_placed():
    runs = _star()
    least = Least(Floors({}, {"holdup": 0.03}), runs, BASE.dem.geometry.blade_pattern)
    inside = _at(250.0)  # the runs' layout
    lengths = Region((150.0, 350.0), (0.2475, 0.495), (36.85, 147.4))
    now, _ = least_bounds(least, lengths, [inside], [_at(200.0)])
    assert now.floor["holdup"][0] == pytest.approx(0.03)
    now, _ = least_bounds(least, SPAN, [inside], [_at(200.0)])
    assert now.floor["holdup"][0] == 0.0


def test_the_shipped_library_ranks_by_the_intervals_predict_gives():
    """Over the shipped library's domain, the rule's half-widths now are at least the
    line's: the floors and the widening beyond the hull only add."""
    model = load_model(LIBRARY_DIR / "law")
    region = Region(*(tuple(r) for r in (SPAN.speed, (0.33, 0.33), SPAN.feed)))
    points = [_at(s, f) for s, _, f in region.grid(3)]
    quantities = library_quantities(model)
    names = model.calibration.covariates
    plain = rank(quantities, names, region, points, _candidates([200.0]), pattern=model.blade_pattern)[0]
    least = Least(floors(model), tuple(r.point for r in model.runs), model.blade_pattern)
    held = rank(quantities, names, region, points, _candidates([200.0]), pattern=model.blade_pattern, least=least)[0]
    assert held.criterion_now > plain.criterion_now
    assert all(h.now >= p.now - 1e-12 for h, p in zip(held.reductions, plain.reductions))
