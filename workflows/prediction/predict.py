"""An operating point the DEM never ran, predicted from a library's law, with its interval.

The law (:mod:`workflows.prediction.library`) gives the K-phase axial chain of the point's
slices from its covariates, and the transverse law the moves across y; together they are
the PBM's phase model on the library's grid (:func:`point_table`, the table ``pbm run``
reads). The agreement table's quantities follow from that chain at steady state, where
the PBM settles (:func:`point_values`): the hold-up and each slice's from the chain's
steady occupancy under the feed (``pbm.simulate`` reaches the same, tests), Little's-law
time from it, the outflow and C_A from the feed (mass balance), the outlet RSD and Lacey
index sampled binomially at the predicted outlet counts, and the RTD's mean and variance
as the moments of the chain's time to discharge (the DEM's pooled RTD recovers 99-100 %
of its tracers, so its truncation is not modelled).

The interval of a quantity (:func:`predict`): on its scale (the log of the value, or the
value itself for :data:`~workflows.prediction.library.ABSOLUTE_KEYS`), each library run
predicted by the law fitted without it gives one error (the calibration: it holds the
law's misfit, the seed's scatter of the DEM value and the fit's own uncertainty at library
points). Their mean b is the law's bias on that quantity (the RTD's mean, for one, is
defined over the DEM's entry window, a little shorter than Little's-law time that the
chain's own mean equals): the prediction is the law's value less b. Their standard
deviation s, and the jackknife variance v(x) over the laws left out of the prediction at x
itself, which grows away from the library, make the 95 % interval: the prediction
+- t(0.975, n - 1) sqrt(s^2 (1 + 1/n) + max(v(x) - v_c, 0)), n the count of calibration
runs and v_c the mean of v at their points (s already holds that much of it). Inside the domain (:func:`domain_issues`) the calibration runs are those
that lay inside the domain of the others (their prediction was an interpolation too).
Outside it a prediction is refused unless extrapolation is asked for; then it is labelled,
its calibration is every run's (the extrapolated ones' larger errors included), and its
half-width is multiplied by 1 + the distance outside the domain in units of the domain's
width (one more for each fixed property the library does not vary, e.g. a particle size it
never ran).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.linalg import expm
from scipy.special import stdtrit

from coupling.compartments import grid_edges
from coupling.errors import ConfigError
from coupling.metrics import sampled_lacey, sampled_rsd
from coupling.operating import OperatingPoint
from coupling.phases import PhaseTransport
from coupling.tables import VelocityTable, make_table
from dem.phases.assembly import axial_part, with_transverse
from dem.phases.chain import steady_occupancy
from dem.phases.law import PhaseLaw
from pbm.feed import feed_at
from workflows.prediction.library import (
    ABSOLUTE_KEYS,
    AXIAL_SLICES,
    REFERENCE_FEED_PER_S,
    REFERENCE_RPM,
    REFERENCE_SLICE_M,
    ErrorModel,
    LibraryModel,
    TransverseLaw,
    covariate_columns,
    quantity_keys,
    run_covariates,
    slice_key,
)

#: binomial draws of the predicted outlet RSD and Lacey index (fixed seed: the jackknife
#: compares laws, not draws)
SAMPLING_DRAWS = 2000
#: the interval's coverage
LEVEL = 0.95
#: the operating-point covariates whose range spans the library's domain
DOMAIN_AXES = ("speed", "length", "feed")
#: properties of a point the law does not vary: a point must share them with the library
FIXED = ("diameter_m", "particle_diameter_m", "particle_diameter_sd_m", "size_classes")
#: the times of the predicted RTD curve, as multiples of the mean residence time
RTD_SPAN = 6.0
RTD_POINTS = 240


# ------------------------------------------------------------------ the chain of a point
def point_chain(
    law: PhaseLaw, transverse: TransverseLaw, point: OperatingPoint, pattern: str, interval_s: float
) -> PhaseTransport:
    """The law's phase model of ``point`` (its stations oriented by ``pattern``) on the
    library's grid (module docstring)."""
    names = law.covariate_names[1:]
    axial = law.chain(covariate_columns(point, AXIAL_SLICES, names, pattern), AXIAL_SLICES, 1, interval_s)
    nx, ny = transverse.grid
    if nx != AXIAL_SLICES:
        raise ConfigError(f"the transverse law's grid has {nx} slices; the law's is {AXIAL_SLICES}")
    rates = np.zeros((1, 4, nx, ny))
    rates[0, 2:] = transverse.rates(point)
    one_phase = PhaseTransport(rates, np.zeros((1, 1, nx, ny)), np.ones((2, 1)))
    return with_transverse(axial, one_phase)


def entering(point: OperatingPoint, nx: int, ny: int) -> np.ndarray:
    """(2, NX * NY) feed of A and B into each compartment [particles/s]: each feeder's zone
    on the grid (:func:`pbm.feed.feed_at`, the PBM's own rule)."""
    x_edges, y_edges = grid_edges(point.length_m, point.diameter_m, nx, ny)
    fields = feed_at(point, x_edges, y_edges)
    out = np.zeros((2, nx * ny))
    for f, feeder in enumerate(("a", "b")):
        weights = np.asarray(fields[f"feed_weights_{feeder}"], dtype=float)
        out[f, : weights.size] = weights / weights.sum() * fields[f"feed_rate_{feeder}_per_s"]
    return out


def rtd_moments(model: PhaseTransport, feed: np.ndarray) -> tuple[float, float]:
    """(mean [s], variance [s^2]) of the time to discharge of particles entering as
    ``feed`` (2, S) says, in the model's entry phases: the phase-type moments
    a (-T)^-1 1 and 2 a (-T)^-2 1 of the chain's transient part T."""
    model, feed = _axial(model, feed)
    alpha = _initial(model, feed)
    t = model.generator()[:-1, :-1]
    first = np.linalg.solve(-t.T, alpha)  # a (-T)^-1 as a column
    mean = float(first.sum())
    second = 2.0 * float(np.linalg.solve(-t.T, first).sum())
    return mean, max(second - mean**2, 0.0)


def _axial(model: PhaseTransport, feed: np.ndarray) -> tuple[PhaseTransport, np.ndarray]:
    """The chain lumped onto its slices and the feed summed over y: the time to discharge
    is the same (the axial moves and switching do not depend on y), from a far smaller
    chain."""
    if model.ny == 1:
        return model, feed
    return axial_part(model), feed.reshape(2, model.nx, model.ny).sum(axis=2)


def _initial(model: PhaseTransport, feed: np.ndarray) -> np.ndarray:
    """The entering particles' distribution over the (compartment, phase) states."""
    entry = (feed[0][:, None] * model.entry[0][None, :] + feed[1][:, None] * model.entry[1][None, :]).ravel()
    return entry / max(feed.sum(), 1e-300)


def rtd_curve(model: PhaseTransport, feed: np.ndarray, times: np.ndarray) -> np.ndarray:
    """E(t) [1/s] of the chain at ``times`` (evenly spaced from 0): the density of the time
    to discharge, a exp(T t) (-T 1)."""
    model, feed = _axial(model, feed)
    alpha = _initial(model, feed)
    q = model.generator()
    t, exit_rate = q[:-1, :-1], q[:-1, -1]
    step = expm(t * (times[1] - times[0]))
    out, state = np.empty(times.size), alpha.copy()
    for n in range(times.size):
        out[n] = float(state @ exit_rate)
        state = state @ step
    return out


@dataclass(frozen=True)
class PointValues:
    """The agreement table's quantities of one chain at steady state (module docstring):
    ``values`` keyed like :func:`~workflows.prediction.library.quantity_keys`."""

    values: dict[str, float]
    model: PhaseTransport
    feed: np.ndarray
    #: (2, S, K) steady particles of feed A and of feed B in each (compartment, phase)
    occupancy: np.ndarray

    @property
    def counts(self) -> np.ndarray:
        """(2, NX, NY) steady particles of A and B."""
        return self.occupancy.sum(axis=2).reshape(2, self.model.nx, self.model.ny)


def point_values(
    law: PhaseLaw, transverse: TransverseLaw, point: OperatingPoint, pattern: str, interval_s: float
) -> PointValues:
    model = point_chain(law, transverse, point, pattern, interval_s)
    nx, ny = model.nx, model.ny
    feed = entering(point, nx, ny)
    # each feeder's particles alone: the chain is linear and A and B move alike
    occupancy = np.stack([steady_occupancy(model, feed * (np.arange(2) == f)[:, None]) for f in (0, 1)])
    counts = occupancy.sum(axis=2).reshape(2, nx, ny)
    slices = counts.sum(axis=(0, 2))
    holdup = float(slices.sum())
    outflow = float(feed.sum())
    outlet = counts[:, -1, :]
    totals = outlet.sum(axis=0)
    fraction = np.divide(outlet[0], totals, out=np.full(ny, np.nan), where=totals > 0)
    # The DEM's RSD is a mean over dumps of the RSD at that dump's counts, which fluctuate
    # about their means: a compartment holding 0.7 particles on average holds 1-3 at many
    # dumps. Each draw takes every outlet compartment's count from a Poisson law of its
    # steady mean, the compositions then binomially (:func:`coupling.metrics.sampled_rsd`).
    every = np.random.default_rng(0).poisson(np.broadcast_to(totals, (SAMPLING_DRAWS, ny)))
    mean, variance = rtd_moments(model, feed)
    values = {
        "mean_residence_time_s": mean,
        "rtd_variance_s2": variance,
        "little_mean_residence_time_s": holdup / outflow,
        "holdup": holdup,
        "outflow_per_s": outflow,
        "C_A": float(feed[0].sum() / outflow),
        "rsd_outlet": float(np.nanmean(sampled_rsd(fraction, every, draws=1))),
        "lacey_outlet": float(np.nanmean(sampled_lacey(fraction, every, draws=1))),
        **{slice_key(i): float(v) for i, v in enumerate(slices)},
    }
    return PointValues(values, model, feed, occupancy)


def point_table(values: PointValues, point: OperatingPoint, duration_s: float) -> VelocityTable:
    """The PBM's table of a predicted point: the phase model on the library's grid, one
    window over the run, the steady counts; its velocities the chain's mean rates times the
    compartments' widths (what the ``velocity`` mode would use)."""
    model = values.model
    x_edges, y_edges = grid_edges(point.length_m, point.diameter_m, model.nx, model.ny)
    occupancy = values.occupancy.sum(axis=0).reshape(model.nx, model.ny, model.n_phases)
    weights = occupancy / np.maximum(occupancy.sum(axis=2, keepdims=True), 1e-300)
    mean_rates = np.einsum("hdij,ijh->dij", model.rates, weights)
    dx, dy = np.diff(x_edges)[:, None], np.diff(y_edges)[None, :]
    table = make_table(
        [0.0],
        x_edges,
        y_edges,
        mean_rates[0] * dx,
        mean_rates[1] * dx,
        mean_rates[2] * dy,
        mean_rates[3] * dy,
        count_A=values.counts[0],
        count_B=values.counts[1],
        window_s=float(duration_s),
        attrs={"source": "pbmdem predict: the library law at this operating point"},
    )
    return table.replace(phases=model, operating_point=point)


# ------------------------------------------------------------------ the domain
@dataclass(frozen=True)
class Domain:
    """The library's domain: each axis of :data:`DOMAIN_AXES` from its least to its
    greatest covariate value over the runs, and the fixed properties every run shares."""

    ranges: dict[str, tuple[float, float]]
    fixed: dict[str, Any]

    def describe(self) -> str:
        rpm = [REFERENCE_RPM * math.exp(v) for v in self.ranges["speed"]]
        slice_m = [REFERENCE_SLICE_M * math.exp(v) * AXIAL_SLICES for v in self.ranges["length"]]
        feed = [REFERENCE_FEED_PER_S * math.exp(v) for v in self.ranges["feed"]]
        return (
            f"{rpm[0]:.4g}-{rpm[1]:.4g} rpm, length {slice_m[0]:.4g}-{slice_m[1]:.4g} m, "
            f"total feed {feed[0]:.4g}-{feed[1]:.4g} particles/s, "
            + ", ".join(f"{k} {v}" for k, v in self.fixed.items())
        )


def _fixed(point: OperatingPoint, pattern: str) -> dict[str, Any]:
    return {**{name: getattr(point, name) for name in FIXED}, "blade_pattern": pattern}


def domain(points: Sequence[OperatingPoint], pattern: str) -> Domain:
    """The :class:`Domain` of a library's operating points, its stations oriented by ``pattern``."""
    values = [run_covariates(p) for p in points]
    ranges = {axis: (min(v[axis] for v in values), max(v[axis] for v in values)) for axis in DOMAIN_AXES}
    return Domain(ranges, _fixed(points[0], pattern))


def domain_issues(dom: Domain, point: OperatingPoint, pattern: str) -> tuple[list[str], float]:
    """(what lies outside ``dom``, the widening factor of :func:`predict`'s interval)."""
    issues, distance = [], 0.0
    values = run_covariates(point)
    for axis in DOMAIN_AXES:
        low, high = dom.ranges[axis]
        excess = max(low - values[axis], values[axis] - high, 0.0)
        if excess > 1e-9:
            issues.append(f"{axis} outside the library's range")
            distance += excess / max(high - low, 1e-9)
    for name, value in _fixed(point, pattern).items():
        library = dom.fixed[name]
        if not (value == library or (isinstance(value, float) and math.isclose(value, library, rel_tol=1e-9))):
            issues.append(f"{name} = {value} (the library's is {library})")
            distance += 1.0
    return issues, 1.0 + distance


# ------------------------------------------------------------------ the prediction
def residual(key: str, dem: float, predicted: float) -> float:
    """The prediction error on ``key``'s scale (module docstring)."""
    if key in ABSOLUTE_KEYS:
        return dem - predicted
    if dem > 0 and predicted > 0:
        return math.log(dem / predicted)
    return math.nan


def bounds(key: str, value: float, half: float) -> tuple[float, float]:
    if key in ABSOLUTE_KEYS:
        return value - half, value + half
    return value * math.exp(-half), value * math.exp(half)


@dataclass(frozen=True)
class PredictedQuantity:
    """One quantity: ``value`` the law's prediction less its calibration bias, with its 95 %
    prediction interval; ``law_value`` the law's own; ``error`` the calibration's error
    model and ``spread`` the jackknife's standard deviation at the point beyond the calibration's (both on the
    quantity's scale); ``widening`` the factor outside the domain."""

    key: str
    value: float
    low: float
    high: float
    law_value: float
    error: ErrorModel
    spread: float
    widening: float = 1.0

    def record(self) -> dict[str, Any]:
        return {"key": self.key, "value": self.value, "low": self.low, "high": self.high}

    def details(self) -> dict[str, Any]:
        return {
            "law_value": self.law_value,
            "bias": self.error.bias,
            "sd": self.error.sd,
            "calibration_runs": self.error.n,
            "jackknife_excess_sd": self.spread,
            "widening": self.widening,
        }


def corrected(
    key: str, value: float, error: ErrorModel, spread: float, widening: float = 1.0
) -> tuple[float, float, float]:
    """(centre, low, high): ``value`` less the calibration's bias, and the 95 % prediction
    interval about it (module docstring); NaN without a calibration of ``key``."""
    if not math.isfinite(error.sd):
        return value, math.nan, math.nan
    centre = value + error.bias if key in ABSOLUTE_KEYS else value * math.exp(error.bias)
    t = float(stdtrit(error.n - 1, 0.5 + LEVEL / 2))  # Student's t quantile
    half = t * math.sqrt(error.sd**2 * (1 + 1 / error.n) + spread**2) * widening
    low, high = bounds(key, centre, half)
    return centre, low, high


@dataclass(frozen=True)
class Prediction:
    point: OperatingPoint
    quantities: tuple[PredictedQuantity, ...]
    outside: tuple[str, ...]
    domain: Domain
    values: PointValues
    rtd_times_s: np.ndarray
    rtd: np.ndarray  # (3, T): the law's E(t), and the least and greatest over the laws left out

    @property
    def extrapolated(self) -> bool:
        return bool(self.outside)

    def quantity(self, key: str) -> PredictedQuantity:
        return next(q for q in self.quantities if q.key == key)


def jackknife(values: list[dict[str, float]], key: str) -> float:
    """Jackknife variance of ``key`` on its scale over the laws left out."""
    scaled = []
    for v in values:
        x = v.get(key, math.nan)
        scaled.append(x if key in ABSOLUTE_KEYS else (math.log(x) if x > 0 else math.nan))
    scaled = np.asarray(scaled, dtype=float)
    scaled = scaled[np.isfinite(scaled)]
    n = scaled.size
    return float((n - 1) / n * np.sum((scaled - scaled.mean()) ** 2)) if n > 1 else 0.0


def predict(model: LibraryModel, point: OperatingPoint, pattern: str, extrapolate: bool = False) -> Prediction:
    """The prediction of ``point``, its blade stations oriented by ``pattern``, from
    ``model`` (module docstring). Raises ConfigError when the model has no calibration, or
    the point lies outside the library's domain and ``extrapolate`` is False."""
    if model.calibration is None:
        raise ConfigError("the library model has no calibration: make it with `pbmdem library fit`")
    dom = domain([r.point for r in model.runs], model.blade_pattern)
    issues, widening = domain_issues(dom, point, pattern)
    if issues and not extrapolate:
        raise ConfigError(
            f"the point lies outside the library's domain ({'; '.join(issues)}); the domain is {dom.describe()}. "
            "Add a DEM run there, or pass --extrapolate for a labelled, widened prediction"
        )
    values = point_values(model.law, model.transverse, point, pattern, model.interval_s)
    left = [
        point_values(law, transverse, point, pattern, model.interval_s)
        for law, transverse in zip(model.left_out, model.transverse_left_out)
    ]
    quantities = []
    for key in quantity_keys():
        value = values.values[key]
        error = model.calibration.error(key, extrapolated=bool(issues))
        spread = math.sqrt(model.calibration.excess(key, jackknife([v.values for v in left], key)))
        centre, low, high = corrected(key, value, error, spread, widening)
        quantities.append(PredictedQuantity(key, centre, low, high, value, error, spread, widening))
    mean = values.values["mean_residence_time_s"]
    times = np.linspace(0.0, RTD_SPAN * mean, RTD_POINTS)
    curves = np.array([rtd_curve(v.model, v.feed, times) for v in (values, *left)])
    rtd = np.vstack([curves[0], curves[1:].min(axis=0), curves[1:].max(axis=0)])
    return Prediction(point, tuple(quantities), tuple(issues), dom, values, times, rtd)
