"""Prediction from a library's law (workflows.prediction): analytic limits of the chain's
quantities, the interval's coverage of errors drawn from a known law, the domain, and the
PBM's table agreeing with the prediction it was written from."""

import math

import numpy as np
import pytest

from coupling.errors import ConfigError
from coupling.phases import PhaseTransport
from dem.operating import operating_point
from dem.phases.law import PhaseLaw
from dem.summary import Estimate
from pbm.config import PbmConfig
from pbm.simulate import simulate
from workflows.config import load_preset
from workflows.prediction.library import (
    Calibration,
    ErrorModel,
    LibraryEntry,
    LibraryModel,
    TransverseLaw,
    quantity_keys,
)
from workflows.prediction.predict import corrected, point_table, point_values, predict, rtd_moments

NAMES = ("1", "speed", "feed")


def _chain(rates: list[float]) -> PhaseTransport:
    """One phase on len(rates) slices in series, forward only."""
    nx = len(rates)
    r = np.zeros((1, 4, nx, 1))
    r[0, 0, :, 0] = rates
    return PhaseTransport(r, np.zeros((1, 1, nx, 1)), np.ones((2, 1)))


@pytest.mark.parametrize("rates", [[0.5], [0.5, 0.5], [0.2, 1.0, 0.4]])
def test_rtd_moments_of_slices_in_series_are_the_sums_of_exponentials(rates):
    feed = np.zeros((2, len(rates)))
    feed[:, 0] = [3.0, 1.0]
    mean, variance = rtd_moments(_chain(rates), feed)
    assert mean == pytest.approx(sum(1 / k for k in rates))
    assert variance == pytest.approx(sum(1 / k**2 for k in rates))


def test_the_interval_holds_95_percent_of_new_errors_drawn_like_the_calibration():
    rng = np.random.default_rng(3)
    bias, sd, n, covered, trials = 0.03, 0.05, 13, 0, 4000
    for _ in range(trials):
        residuals = rng.normal(bias, sd, n)
        error = ErrorModel(float(residuals.mean()), float(residuals.std(ddof=1)), n)
        _centre, low, high = corrected("holdup", 1000.0, error, 0.0)
        dem = 1000.0 * math.exp(rng.normal(bias, sd))
        covered += low <= dem <= high
    assert covered / trials == pytest.approx(0.95, abs=0.012)


# ---------------------------------------------------------------- a hand-made library
def _law(k_pos: float = 0.6) -> PhaseLaw:
    """One phase whose forward rate grows as rpm^0.5 and feed^0.3 [1/s]."""
    coefficients = {
        "x_pos/0": np.array([math.log(k_pos), 0.5, 0.3]),
        "x_neg/0": np.array([math.log(0.1), 0.5, 0.0]),
    }
    return PhaseLaw(1, coefficients, np.ones((2, 1)), NAMES, 0.0, 1, 1, True)


def _transverse() -> TransverseLaw:
    beta = np.zeros((2, 10, 10, 5))
    beta[..., 0] = math.log(0.8)
    beta[0, :, -1] = np.nan  # the walls
    beta[1, :, 0] = np.nan
    return TransverseLaw(beta)


BASE = operating_point(load_preset("validation").dem)


def _model(spread_laws: bool = True) -> LibraryModel:
    points = [BASE.replace(impeller_rpm=rpm) for rpm in (150.0, 250.0, 350.0)]
    dem = {"holdup": Estimate(1.0, 0.9, 1.1)}
    runs = tuple(LibraryEntry(f"run{n}.h5", str(n), p, "FB", 15485863, dem) for n, p in enumerate(points))
    left = tuple(_law(0.6 * (1 + 0.02 * (n - 1) * spread_laws)) for n in range(3))
    residuals = {key: [0.01, -0.02, 0.04] for key in quantity_keys()}
    return LibraryModel(
        _law(), _transverse(), runs, left, (_transverse(),) * 3, 0.1, Calibration(residuals, [False, True, False])
    )


def test_a_point_inside_the_domain_is_predicted_with_every_quantity_and_its_interval():
    model = _model()
    point = BASE.replace(impeller_rpm=200.0)
    prediction = predict(model, point, "FB")
    assert [q.key for q in prediction.quantities] == list(quantity_keys())
    law = point_values(_law(), _transverse(), point, "FB", 0.1).values
    error = model.calibration.error("holdup")
    assert error.n == 3 and error.bias == pytest.approx(0.01)
    holdup = prediction.quantity("holdup")
    assert holdup.law_value == pytest.approx(law["holdup"])
    assert holdup.value == pytest.approx(law["holdup"] * math.exp(0.01))
    assert holdup.low < holdup.value < holdup.high
    assert holdup.spread > 0  # the laws left out differ at this point
    # mass balance: the outflow is the feed, C_A its share of A
    assert prediction.quantity("outflow_per_s").law_value == pytest.approx(BASE.feed_rate_total_per_s)
    assert prediction.quantity("C_A").law_value == pytest.approx(0.5)
    assert not prediction.extrapolated


def test_a_point_outside_the_domain_is_refused_naming_it_unless_extrapolated():
    model = _model()
    point = BASE.replace(impeller_rpm=450.0)
    with pytest.raises(ConfigError, match=r"outside the library's domain \(speed.*150-350 rpm"):
        predict(model, point, "FB")
    inside = predict(model, BASE.replace(impeller_rpm=350.0), "FB").quantity("holdup")
    outside = predict(model, point, "FB", extrapolate=True)
    assert outside.extrapolated and outside.outside == ("speed outside the library's range",)
    q = outside.quantity("holdup")
    assert q.widening == pytest.approx(1 + math.log(450 / 350) / math.log(350 / 150))
    assert math.log(q.high / q.value) > math.log(inside.high / inside.value)
    other_size = BASE.replace(particle_diameter_sd_m=0.0)
    with pytest.raises(ConfigError, match="particle_diameter_sd_m = 0.0"):
        predict(model, other_size, "FB")
    with pytest.raises(ConfigError, match="blade_pattern = FFB .the library's is FB"):
        predict(model, BASE, "FFB")


def test_the_pbm_on_the_written_table_settles_where_the_prediction_says():
    point = BASE.replace(impeller_rpm=200.0)
    values = point_values(_law(), _transverse(), point, "FB", 0.1)
    table = point_table(values, point, 400.0)
    result = simulate(table, PbmConfig(rates="phases", duration_s=400.0, output_interval_s=5.0))
    late = result.times > 300.0
    counts = result.counts[late].mean(axis=0)  # (2, NX, NY)
    assert counts.sum() == pytest.approx(values.values["holdup"], rel=2e-3)
    assert np.allclose(counts.sum(axis=(0, 2)), [values.values[f"holdup_slice_{i + 1}"] for i in range(10)], rtol=5e-3)
    outflow = (result.outflow_A + result.outflow_B)[late].mean()
    assert outflow == pytest.approx(values.values["outflow_per_s"], rel=2e-3)


def test_an_extrapolated_blade_pattern_is_predicted_with_its_own_stations():
    model = _model()
    push = PhaseLaw(
        1,
        {
            "x_pos/0": np.array([math.log(0.6), 0.5, 0.3, 0.4]),
            "x_neg/0": np.array([math.log(0.1), 0.5, 0.0, 0.0]),
        },
        np.ones((2, 1)),
        (*NAMES, "push"),
        0.0,
        1,
        1,
        True,
    )
    model = LibraryModel(
        push,
        *[getattr(model, f) for f in ("transverse", "runs")],
        (push,) * 3,
        model.transverse_left_out,
        0.1,
        model.calibration,
    )
    other = predict(model, BASE, "FFB", extrapolate=True)
    assert other.outside == ("blade_pattern = FFB (the library's is FB)",)
    own = point_values(push, _transverse(), BASE, "FFB", 0.1).values["holdup"]
    assert other.quantity("holdup").law_value == pytest.approx(own)
    assert own != pytest.approx(point_values(push, _transverse(), BASE, "FB", 0.1).values["holdup"])
