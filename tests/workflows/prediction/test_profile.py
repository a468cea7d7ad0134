"""The slices' zone law of the bed (:mod:`workflows.prediction.profile`) on known answers:
the zones of a blender laid out by hand, a uniform bed holding its density times each
slice's length, a law of known coefficients recovered from its own slices (exactly without
noise; with known lognormal noise per slice, each slice's scatter and the intervals'
coverage of fresh draws), the record read back, and bad input refused naming it."""

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from coupling.errors import ConfigError
from coupling.jsonable import write_json
from workflows.prediction import profile as P
from workflows.prediction.covariates import REFERENCE_FEED_PER_S, REFERENCE_RPM
from workflows.prediction.design import design_point
from workflows.prediction.library import load_model
from workflows.prediction.predict import station_rule
from workflows.shipped import LIBRARY_MODEL

PATTERN = "FB"
HALF_WIDTH_M = 0.012
#: a realistic bed: particles per metre near 4500 (9500 at the inlet), hold-up falling
#: with speed and rising with feed, a gentle slope towards the weir
ZONE_LINES = {
    "inlet": (math.log(9500), -0.2, 0.5),
    "forward blade": (math.log(4200), -0.35, 0.8),
    "backward blade": (math.log(4800), -0.3, 0.75),
    "after forward": (math.log(4500), -0.4, 0.7),
    "after backward": (math.log(4700), -0.45, 0.65),
    "weir": (math.log(4000), -0.25, 0.6),
}
#: the swept zones of the stations with lines of their own (:data:`P.OWN_STATIONS`)
OWN_LINES = [(math.log(3600), -0.3, 0.9), (math.log(5200), -0.2, 0.7), (math.log(4400), -0.3, 0.7)]
N_ZONES = len(P.ZONES) + len(P.OWN_STATIONS)
N_COEFFICIENTS = P.n_coefficients(P.OWN_STATIONS)
SHARED = {"distance": 0.05, "distance2": -0.006, "speed_distance": 0.03, "feed_distance": -0.02, "speed2": 0.15}
SHARED["weir_gap"] = 0.3
TRUE = np.array(
    [c for zone in P.ZONES for c in ZONE_LINES[zone]]
    + [c for line in OWN_LINES[: len(P.OWN_STATIONS)] for c in line]
    + [SHARED[t] for t in P.SHARED_TERMS]
)
#: (rpm, length [m], total feed [particles/s]) of the runs the law is fitted to
RUNS = [
    (150, 0.33, 36.85),
    (350, 0.33, 36.85),
    (250, 0.33, 73.7),
    (250, 0.2475, 36.85),
    (250, 0.495, 36.85),
    (200, 0.28875, 147.4),
    (300, 0.4125, 55.275),
    (175, 0.45375, 110.55),
    (325, 0.2475, 92.0),
    (225, 0.495, 73.7),
    (275, 0.37, 147.4),
    (150, 0.4125, 73.7),
    (350, 0.45375, 110.55),
    (200, 0.33, 55.275),
]
#: points inside the runs' domain that none of them is at
NEW = [
    (275, 0.37, 90.0),
    (180, 0.30, 50.0),
    (320, 0.44, 120.0),
    (210, 0.26, 70.0),
    (260, 0.48, 45.0),
    (240, 0.35, 130.0),
    (190, 0.42, 100.0),
    (330, 0.31, 60.0),
]
#: each slice's scatter about the law (log), inlet to weir
SLICE_SD = np.array([0.02, 0.035, 0.05, 0.06, 0.045, 0.03, 0.04, 0.055, 0.025, 0.01])


def _law(coefficients: np.ndarray, half_width_m: float = HALF_WIDTH_M, nx: int = 10) -> P.ProfileLaw:
    """The law of ``coefficients`` known exactly: no covariance, no scatter."""
    return P.ProfileLaw(
        half_width_m, coefficients, np.zeros((N_COEFFICIENTS,) * 2), np.zeros(nx), 100, PATTERN, np.full(nx, 100.0)
    )


@pytest.fixture(scope="module")
def blender():
    """(the library's first run's point, its blade station rule)."""
    points = [run.point for run in load_model(LIBRARY_MODEL).runs]
    return points[0], station_rule(points)


@pytest.fixture(scope="module")
def runs(blender):
    """(the runs' points, their slices' hold-ups from the true law, the new points)."""
    points = [design_point(*blender, *r) for r in RUNS]
    truth = _law(TRUE)
    held = np.array([truth.at(p)[0] for p in points])
    return points, held, [design_point(*blender, *r) for r in NEW]


@pytest.fixture(scope="module")
def exact(runs):
    points, held, _ = runs
    return P.fit_profile(points, held, PATTERN)


# ------------------------------------------------------------------ zones
def test_the_zones_of_a_blender_laid_out_by_hand(blender):
    """Stations at 5, 10 and 15 cm of a 20-cm barrel, swept 1 cm either side; "FB" makes the
    middle one backward."""
    point = blender[0].replace(length_m=0.2, blade_x_m=(0.05, 0.10, 0.15))
    x, zone = P.zones(point, PATTERN, 0.01, own_stations=())
    assert x[0] == pytest.approx(P.GRID_M / 2) and x[-1] < 0.2 and x.size == round(0.2 / P.GRID_M)
    named = {
        0.02: "inlet",
        0.039: "inlet",
        0.041: "forward blade",
        0.059: "forward blade",
        0.061: "after forward",
        0.089: "after forward",
        0.095: "backward blade",
        0.105: "backward blade",
        0.125: "after backward",
        0.155: "forward blade",
        0.161: "weir",
        0.199: "weir",
    }
    for at, name in named.items():
        assert P.ZONES[zone[np.argmin(np.abs(x - at))]] == name, at
    # each station sweeps 2 cm (40 grid points), the stretches between them 3 cm, the inlet
    # and the weir zone 4 cm each
    counts = np.bincount(zone, minlength=len(P.ZONES))
    assert counts.tolist() == [80, 80, 40, 60, 60, 80]
    # every station forward: no backward zones
    _, forward = P.zones(point, "F", 0.01, own_stations=())
    assert np.bincount(forward, minlength=len(P.ZONES)).tolist() == [80, 120, 0, 120, 0, 80]
    # "BF" turns every station round
    _, turned = P.zones(point, "BF", 0.01, own_stations=())
    assert np.bincount(turned, minlength=len(P.ZONES)).tolist() == [80, 40, 80, 60, 60, 80]
    # stations with zones of their own: the first and the last sweep theirs, a station the
    # blender lacks none; everything else as before
    _, own = P.zones(point, PATTERN, 0.01, own_stations=(0, -1, 5))
    assert np.bincount(own, minlength=len(P.ZONES) + 3).tolist() == [80, 0, 40, 60, 60, 80, 40, 40, 0]


@pytest.mark.parametrize("pattern", ["", "FX", "fb", "F B"])
def test_a_blade_pattern_of_other_letters_is_refused_naming_it(blender, pattern):
    with pytest.raises(ConfigError, match=f"blade pattern {pattern!r}: letters F"):
        P.zones(blender[0], pattern, HALF_WIDTH_M)


# ------------------------------------------------------------------ analytic limits
@pytest.mark.parametrize("length_m", [0.2475, 0.28875, 0.33, 0.37, 0.495])
@pytest.mark.parametrize(("pattern", "half_width_m", "nx"), [("FB", 0.012, 10), ("F", 0.004, 10), ("BBF", 0.016, 7)])
def test_a_uniform_bed_holds_its_density_times_each_slices_length(blender, length_m, pattern, half_width_m, nx):
    """Every zone's line the same and no shared term: the density is one number along the
    barrel, whatever the stations, and each slice holds it times its length, also where a
    slice is no whole number of :data:`GRID_M` steps (0.2475 m over 10 slices)."""
    rpm, feed = 310.0, 95.0
    line = (math.log(4500), -0.3, 0.7)
    coefficients = np.array(line * N_ZONES + (0.0,) * len(P.SHARED_TERMS))
    point = design_point(*blender, rpm, length_m, feed)
    density = math.exp(
        line[0] + line[1] * math.log(rpm / REFERENCE_RPM) + line[2] * math.log(feed / REFERENCE_FEED_PER_S)
    )
    held, half = _law(coefficients, half_width_m, nx).at(point, pattern)
    assert held == pytest.approx(np.full(nx, density * length_m / nx), rel=1e-12)
    assert np.all(half == 0.0)


def test_an_inlet_twice_as_dense_doubles_exactly_the_slice_it_fills(blender):
    """The first station at 4.5 cm swept 1.2 cm either side: the inlet zone is the first
    3.3 cm, the first slice of a 0.33-m blender, which alone holds twice as much."""
    coefficients = np.array((math.log(4500), 0.0, 0.0) * N_ZONES + (0.0,) * len(P.SHARED_TERMS))
    coefficients[0] += math.log(2.0)
    point = design_point(*blender, 250.0, 0.33, 73.7)
    held, _ = _law(coefficients).at(point)
    assert held == pytest.approx([2 * 4500 * 0.033] + [4500 * 0.033] * 9, rel=1e-12)


# ------------------------------------------------------------------ recovery
def test_the_law_is_recovered_exactly_from_its_own_slices(runs, exact):
    """Without noise the fit finds the true half-width among the 13 tried, every
    coefficient (the 14 runs identify all 24), and so every slice at points it never saw."""
    points, _, new = runs
    assert exact.half_width_m == HALF_WIDTH_M
    assert exact.dof == len(points) * 10 - N_COEFFICIENTS
    assert exact.coefficients == pytest.approx(TRUE, rel=1e-6, abs=1e-8)
    truth = _law(TRUE)
    for point in new:
        assert exact.at(point)[0] == pytest.approx(truth.at(point)[0], rel=1e-6)


def test_a_law_is_recovered_when_every_run_lacks_a_slice(runs):
    """A run without one slice's hold-up (NaN or 0) leaves it out; with every run lacking
    one the law is still found, from the mean density of the slices observed."""
    points, held, new = runs
    lacking = held.copy()
    for k in range(len(points)):
        lacking[k, k % 10] = math.nan if k % 2 else 0.0
    law = P.fit_profile(points, lacking, PATTERN, (HALF_WIDTH_M,))
    assert law.dof == len(points) * 9 - N_COEFFICIENTS
    truth = _law(TRUE)
    for point in new:
        assert law.at(point)[0] == pytest.approx(truth.at(point)[0], rel=1e-6)


def test_each_slices_scatter_and_its_intervals_hold_for_known_noise(runs):
    """Each slice's hold-up times a lognormal of its own sd (0.01 to 0.06), two seeds per
    operating point: the law finds each slice's sd within a factor 1.6 (about 24 degrees of
    freedom each), their median within 30 %, and its 95 % intervals at 8 new points hold at
    least 90 % of fresh draws while being no wider than 1.5 times the intervals the true
    sds would give (1.96 sd)."""
    points, held, new = runs
    rng = np.random.default_rng(20261205)
    twice = np.vstack([held, held])
    noisy = twice * np.exp(rng.normal(0.0, SLICE_SD, twice.shape))
    law = P.fit_profile(points * 2, noisy, PATTERN, (0.008, HALF_WIDTH_M, 0.016))
    ratio = law.slice_sd / SLICE_SD
    assert np.all((ratio > 1 / 1.6) & (ratio < 1.6)), ratio
    assert np.median(law.slice_sd) == pytest.approx(np.median(SLICE_SD), rel=0.3)
    truth = _law(TRUE)
    inside, halves = [], []
    for point in new:
        value, half = law.at(point)
        draws = truth.at(point)[0] * np.exp(rng.normal(0.0, SLICE_SD, (40, SLICE_SD.size)))
        inside.append(np.abs(np.log(draws / value)) <= half)
        halves.append(half)
    assert np.mean(inside) >= 0.90
    assert np.median(halves) < 1.5 * 1.96 * np.median(SLICE_SD)


# ------------------------------------------------------------------ record
def test_the_record_written_and_read_back_gives_the_same_predictions(runs, exact, tmp_path):
    _, _, new = runs
    path = write_json(tmp_path / "profile.json", exact.record())
    back = P.ProfileLaw.from_record(json.loads(path.read_text()))
    for point in new:
        for ours, theirs in zip(exact.at(point), back.at(point)):
            assert np.array_equal(ours, theirs)
    assert (back.half_width_m, back.dof, back.pattern) == (exact.half_width_m, exact.dof, exact.pattern)
    assert back.layouts is not None and back.layouts.layouts == exact.layouts.layouts


def test_a_record_of_another_coefficient_count_is_refused(exact):
    record = exact.record()
    record["coefficients"] = record["coefficients"][:-1]
    with pytest.raises(ValueError, match=f"{N_COEFFICIENTS} coefficients"):
        P.ProfileLaw.from_record(record)


# ------------------------------------------------------------------ errors
@pytest.mark.parametrize("unknown", [math.nan, 0.0, -1.0])
def test_runs_without_a_slice_hold_up_are_refused(runs, unknown):
    points, held, _ = runs
    with pytest.raises(ConfigError, match="no slice hold-up"):
        P.fit_profile(points, np.full(held.shape, unknown), PATTERN, (HALF_WIDTH_M,))


def test_too_few_slices_for_a_degree_of_freedom_are_refused_naming_them(runs):
    """One run of 0.33 m observed in its first five slices: its five zones at one speed and
    feed, and the slope and curvature towards the weir, leave every slice spent."""
    points, held, _ = runs
    first = np.where(np.arange(10) < 5, held[0], math.nan)[None]
    with pytest.raises(
        ConfigError, match=r"more slices than its 5 identified coefficients; the library gives 5: add runs"
    ):
        P.fit_profile(points[:1], first, PATTERN, (HALF_WIDTH_M,))
    # all ten slices of that run are spent too, on six zone levels, the first two stations'
    # own and the two terms of the distance to the weir; without the stations' own zones two
    # degrees of freedom are left
    with pytest.raises(ConfigError, match=r"its 10 identified coefficients; the library gives 10"):
        P.fit_profile(points[:1], held[:1], PATTERN, (HALF_WIDTH_M,))
    assert P.fit_profile(points[:1], held[:1], PATTERN, (HALF_WIDTH_M,), own_stations=()).dof == 2


@pytest.mark.parametrize("shape", [(13, 10), (14,), (14, 10, 1), (14, 0)])
def test_hold_ups_of_the_wrong_shape_are_refused_naming_it(runs, shape):
    points, _, _ = runs
    with pytest.raises(ConfigError, match=rf"shape \({shape[0]},.*one row per run \(14\)"):
        P.fit_profile(points, np.full(shape, 100.0), PATTERN, (HALF_WIDTH_M,))


# ------------------------------------------------------------------ layouts run
#: a miss of the shares the zone law cannot carry (log, inlet to weir): the baseline
#: layout's at the baseline's covariates, and a slope in log speed every layout shares
LAYOUT_MISS = np.array([0.01, -0.02, 0.0, 0.015, -0.01, 0.0, 0.02, 0.03, -0.025, -0.02])
LAYOUT_SLOPE = np.array([0.02, 0.0, -0.01, 0.0, 0.01, 0.0, -0.02, 0.0, 0.01, 0.0])


def _baseline(point) -> bool:
    return math.isclose(point.length_m, 0.33)


def _with_miss(law: P.ProfileLaw, point) -> np.ndarray:
    """``law``'s slices at ``point`` with the planted share miss, the total kept."""
    held = law.holdups(point)
    speed = math.log(point.impeller_rpm / REFERENCE_RPM)
    shares = held * np.exp(LAYOUT_MISS * _baseline(point) + LAYOUT_SLOPE * speed)
    return shares * held.sum() / shares.sum()


def test_a_layouts_miss_of_the_shares_is_carried_to_its_other_points(blender, runs):
    """Runs whose shares lie off the zone law by a miss linear in log speed, and at the
    0.33-m layout by a mean miss too: about the true law, the lines recover the slope, and
    the law with them predicts the layouts run at speeds and feeds they never ran to 0.1 %,
    its total the law's; a layout not run keeps the law alone."""
    points, _, new = runs
    truth = _law(TRUE)
    held = np.array([_with_miss(truth, p) for p in points])
    shares = P.fit_layouts(truth, points, held)
    assert shares is not None and shares.layouts.count(P.layout_of(points[0])) == 1
    k = shares.layouts.index(P.layout_of(points[0]))
    assert shares.runs[k] == sum(_baseline(p) for p in points)
    # shares are the same whatever constant every slice's miss shares
    slope = shares.slopes[shares.terms.index("speed")]
    assert slope - slope.mean() == pytest.approx(LAYOUT_SLOPE - LAYOUT_SLOPE.mean(), abs=1e-3)
    known = replace(truth, layouts=shares)
    for rpm, feed in [(180, 50.0), (320, 120.0), (260, 90.0)]:
        point = design_point(*blender, rpm, 0.33, feed)
        assert known.holdups(point) == pytest.approx(_with_miss(truth, point), rel=1e-3)
        assert known.holdups(point).sum() == pytest.approx(truth.holdups(point).sum(), rel=1e-12)
    for point in new:
        if P.layout_of(point) not in shares.layouts:
            assert np.array_equal(known.at(point)[0], truth.at(point)[0])


def test_a_layouts_intervals_hold_for_known_noise(blender, runs):
    """The runs with their layout's miss and a lognormal scatter of 1 % per slice, three
    seeds each: at the layouts run, at speeds and feeds none of them ran, the intervals of
    the shares hold at least 90 % of fresh draws, no wider than twice the true 1.96 sd."""
    points, _, _ = runs
    truth = _law(TRUE)
    rng = np.random.default_rng(20261206)
    sd = 0.01
    clean = np.array([_with_miss(truth, p) for p in points] * 3)
    law = P.fit_profile(points * 3, clean * np.exp(rng.normal(0.0, sd, clean.shape)), PATTERN, (HALF_WIDTH_M,))
    assert law.layouts is not None
    inside, halves = [], []
    for rpm, length_m, feed in [(180, 0.33, 50.0), (320, 0.33, 120.0), (230, 0.2475, 60.0), (260, 0.495, 90.0)]:
        point = design_point(*blender, rpm, length_m, feed)
        assert P.layout_of(point) in law.layouts.layouts
        value, half = law.at(point)
        draws = _with_miss(truth, point) * np.exp(rng.normal(0.0, sd, (50, 10)))
        share = np.log(draws / draws.sum(axis=1, keepdims=True)) - np.log(value / value.sum())
        inside.append(np.abs(share) <= half)
        halves.append(half)
    assert np.mean(inside) >= 0.90
    assert np.median(halves) < 2 * 1.96 * sd


def test_runs_of_a_layout_each_give_the_lines_no_degree_of_freedom(runs):
    """One run per layout says nothing of a layout's scatter: no lines, the law alone."""
    points, held, _ = runs
    single = {}
    for n, p in enumerate(points):
        single.setdefault(P.layout_of(p), n)
    keep = sorted(single.values())
    assert P.fit_layouts(_law(TRUE), [points[n] for n in keep], held[keep]) is None


def test_a_layouts_record_of_another_slice_count_is_refused(exact):
    record = exact.record()
    assert record["layouts"] is not None
    record["layouts"]["sd"] = record["layouts"]["sd"][:-1]
    with pytest.raises(ValueError, match="layout shares of"):
        P.ProfileLaw.from_record(record)


def test_a_layout_away_from_its_runs_along_a_term_they_never_varied_keeps_the_law_alone(blender):
    """Runs of one layout at one feed say nothing of how its shares move with the feed: at
    another feed the law alone, at another speed the layout's lines."""
    truth = _law(TRUE)
    points = [design_point(*blender, rpm, 0.33, 73.7) for rpm in (150, 200, 250, 300, 350)]
    shares = P.fit_layouts(truth, points, np.array([_with_miss(truth, p) for p in points]), ("speed", "feed"))
    assert shares is not None
    assert shares.at(design_point(*blender, 275, 0.33, 73.7)) is not None
    assert shares.runs_at(design_point(*blender, 275, 0.33, 73.7)) == 5
    assert shares.at(design_point(*blender, 275, 0.33, 100.0)) is None
    assert shares.runs_at(design_point(*blender, 275, 0.33, 100.0)) == 0
