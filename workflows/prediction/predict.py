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

A law fitted to the particles' moves may keep a slow phase that holds what the bed does
not: left out, the shipped law put 80 % too many particles in the x1.25 blender, whose
slices the zone law of the bed (:mod:`workflows.prediction.profile`) missed by 3 %. Where
the library has that zone law, the chain is therefore timed by it (:func:`timed`, chosen
over the chain as fitted by the intervals of every run left out,
:func:`workflows.prediction.calibration.chain_scores`): every rate out of a slice scaled so
that the slice holds the zone law's hold-up. Particles go where the law sends them and stay
as long as the bed says.

The law is fitted to the particles' moves, not to the quantities: at the library's own runs
its chain, timed, misses the DEM's hold-up by -4.1 to +3.6 % (as fitted by up to 6 %),
smoothly over the operating point, while the DEM's own scatter between seeds is 0.4-1 %. What it misses there is carried to the point (:func:`predict`): on each
quantity's scale (the log of the value, or the value itself for
:data:`~workflows.prediction.library.ABSOLUTE_KEYS`) the residuals DEM less law at the
library's runs are fitted by least squares as a line in the correction covariates x
(:data:`~workflows.prediction.library.DEFAULT_CORRECTION`: log speed, log slice length,
the log gap from the last blade to the weir, log feed and the last station's orientation;
:func:`fit_correction` keeps those the runs identify). The prediction is the law's value
moved by the line at the point, and its 95 % interval the line's prediction interval,
+- t(0.975, n - p) s sqrt(1 + x'(A'A)^-1 x), n the runs, p the line's coefficients, s the
residuals' standard deviation about it (the DEM's scatter between seeds and what the line
cannot follow) and A the runs' covariates: it widens away from the runs, where the line's
own coefficients are uncertain. The slices' hold-ups (from the zone law, or each moved by
its own line) are scaled alike to the predicted total (:func:`held_in_total`): one bed,
whose total the hold-up's line corrects. The chain written for the PBM has each slice's
time scale set so that it holds them (:func:`rescaled`): ``pbm run`` on the table settles
where the prediction says.

Outside the domain's ranges (:func:`placement`) a prediction is refused unless
extrapolation is asked for; then it is labelled, its half-width is at least the
extrapolation floor (t times the root mean square error of the library's end runs, each
predicted without it: the line knows nothing of how the law bends beyond its runs, these
errors do; :func:`extrapolation_floor`), and it is multiplied by 1 + the distance outside
the domain in units of the domain's width (one more for each fixed property the library
does not vary, e.g. a particle size it never ran).

Inside the ranges, a point may still combine speed, length and feed as no run does: a
library that changes one thing at a time spans a star, not the box of its ranges, and the
line has no term for two changes at once (the library's run at 150 rpm and twice the feed,
each an end of its range, was missed by 15 % on its hold-up and residence time by an
interval of 5 %). A point beyond the runs' convex hull is labelled, its interval widened
by 1 + its distance from the hull and kept at least a share of the floor: the distance
over the median distance of the library's own end runs from the others' hull, at most
all of it (:class:`Placement`). Only the ranges refuse.

A blender of a length no run has puts its blade stations where no run had them (its
slices take the zone law alone, its gap to the weir and last station the line's terms
from the few runs that differ in them), and the library's runs of a layout no other run
has miss by more, left out, than the line's interval says. At such a layout the half-width
is therefore at least the layout floor: t times the root mean square error of those runs
inside the others' hull, each predicted without it (:func:`layout_floor`). It is a floor,
not a widening: the point is inside the domain.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy.linalg import expm
from scipy.optimize import nnls
from scipy.special import stdtrit

from coupling.compartments import grid_edges
from coupling.errors import ConfigError, TableError
from coupling.metrics import sampled_lacey, sampled_rsd
from coupling.operating import OperatingPoint
from coupling.phases import PhaseTransport
from coupling.tables import VelocityTable, make_table
from dem.phases.assembly import axial_part, with_transverse
from dem.phases.chain import steady_occupancy
from dem.phases.law import MAX_LAW_RATE, PhaseLaw
from pbm.feed import feed_at
from workflows.prediction.covariates import AXIAL_SLICES, AXIS_REFERENCES, axis_value, run_covariates, weir_gap_m
from workflows.prediction.library import (
    ABSOLUTE_KEYS,
    CORRECTION_DOF,
    LibraryModel,
    TransverseLaw,
    correction_row,
    covariate_columns,
    line_alone,
    quantity_keys,
    same_setting,
    slice_key,
)
from workflows.prediction.profile import ProfileLaw, layout_index, layout_of, same_layout

#: binomial draws of the predicted outlet RSD and Lacey index (fixed seed: the law at the
#: library's runs and at the point is sampled alike, so the correction compares laws, not
#: draws)
SAMPLING_DRAWS = 2000
#: the interval's coverage
LEVEL = 0.95
#: the operating-point covariates whose range spans the library's domain. Not the gap to the
#: weir: at the baseline's station spacing every length has its own (25-54 mm); a
#: configuration's gap is checked against the stations' rule instead (:func:`_gap_issue`)
DOMAIN_AXES = ("speed", "length", "feed")
#: how far ``--extrapolate`` reaches beyond each axis' range, in widths of that range: a
#: feed 27 times the library's greatest, or a speed a third of its least, is no
#: extrapolation of its runs but a guess (its hold-up can exceed what the barrel holds)
EXTRAPOLATION_REACH = 1.0
#: the packing fraction no bed exceeds (random close packing of spheres): a predicted
#: hold-up beyond it in the barrel's volume is refused
CLOSE_PACKING = 0.64
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
    """The quantities of the law's chain at ``point`` (:func:`point_chain`, :func:`chain_values`)."""
    return chain_values(point_chain(law, transverse, point, pattern, interval_s), point)


def chain_values(model: PhaseTransport, point: OperatingPoint) -> PointValues:
    """The agreement table's quantities of ``model`` fed as ``point`` says, at steady state
    (module docstring)."""
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


def timed(values: PointValues, profile: ProfileLaw, point: OperatingPoint, pattern: str) -> PointValues:
    """The chain of ``values`` timed by the slices' zone law ``profile``: every rate out of
    slice i scaled so that the slice holds the zone law's hold-up at ``point`` (its
    stations oriented by ``pattern``; :func:`rescaled`). Where particles go is the law's,
    how long they stay the bed's: the hold-up, Little's-law time and the mean residence
    time are the zone law's total over the feed. Raises ConfigError when a slice holds
    nothing, or no finite number, in the chain or in the zone law."""
    held = values.counts.sum(axis=(0, 2))
    bed = profile.holdups(point, pattern)
    bad = ~(np.isfinite(held) & np.isfinite(bed) & (held > 0) & (bed > 1e-300))
    if bad.any():
        i = int(np.argmax(bad))
        raise ConfigError(
            f"slice {i + 1} holds {held[i]:.6g} particles in the law's chain and {bed[i]:.6g} in the zone law at "
            f"{point.impeller_rpm:g} rpm, {point.length_m:g} m, {point.feed_rate_total_per_s:g} /s: the chain can "
            "be timed only where both are positive and finite"
        )
    return chain_values(rescaled(values.model, held / bed), point)


def timed_values(chain: PointValues, timed_chain: PointValues) -> dict[str, float]:
    """The quantities the corrections of a timed library are fitted to: ``timed_chain``'s
    (:func:`timed`), each slice's hold-up ``chain``'s as fitted (the slices' own source is
    chosen apart: the zone law, or the correction's lines on the chain as fitted)."""
    slices = {slice_key(i) for i in range(chain.model.nx)}
    return {key: chain.values[key] if key in slices else v for key, v in timed_chain.values.items()}


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
    greatest covariate value over the runs, the fixed properties every run shares, and the
    runs' covariates on the axes that vary (``vertices``, in units of each axis' width)
    whose convex hull is where the runs' combinations reach; ``end_distance`` the median
    distance of the runs beyond the hull of the others (how far the library's own
    extrapolations, which calibrate the floor, reach)."""

    ranges: dict[str, tuple[float, float]]
    fixed: dict[str, Any]
    vertices: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)), compare=False)
    end_distance: float = 1.0
    #: the physics every run shares (:func:`shared_physics`): materials, contacts, blades,
    #: weir, feed zones and the feed's A share
    physics: dict[str, Any] = field(default_factory=dict)
    #: the runs' blade layouts (:func:`~workflows.prediction.profile.layout_of`)
    layouts: tuple[tuple[float, ...], ...] = ()
    #: how the runs place their stations (:func:`station_rule`): a point's last station
    #: lies between the least gap before the weir and one spacing more, or the point has a
    #: bladeless stretch (or a blade at the weir) no run has
    stations: tuple[float, float, float] | None = None

    @property
    def gaps_m(self) -> tuple[float, float] | None:
        """The gaps from the last blade station to the weir the runs' layouts allow [m]."""
        if self.stations is None:
            return None
        _, spacing, least = self.stations
        return least, least + spacing

    def span(self, axis: str, reach: float = 0.0) -> tuple[float, float]:
        """The range of ``axis`` in the units a user gives it (:data:`AXIS_REFERENCES`),
        each end moved out by ``reach`` of its width."""
        low, high = self.ranges[axis]
        width = (high - low) * reach
        return axis_value(axis, low - width), axis_value(axis, high + width)

    def describe(self) -> str:
        rpm, slice_m, feed = (self.span(axis) for axis in ("speed", "length", "feed"))
        shared = f", and the {len(self.physics)} settings of materials, contacts, blades, weir and feed its runs share"
        gaps = self.gaps_m
        gap = f", the last blade station {gaps[0] * 1e3:.4g}-{gaps[1] * 1e3:.4g} mm before the weir" if gaps else ""
        return (
            f"{rpm[0]:.4g}-{rpm[1]:.4g} rpm, length {slice_m[0]:.4g}-{slice_m[1]:.4g} m{gap}, "
            f"total feed {feed[0]:.4g}-{feed[1]:.4g} particles/s, "
            + ", ".join(f"{k} {v}" for k, v in self.fixed.items())
            + (shared if self.physics else ", its runs' physics unknown (a library fitted before they were kept)")
        )

    def _scaled(self, point: OperatingPoint) -> np.ndarray:
        """``point``'s covariates on the axes that vary, clipped into their ranges, in
        units of each range (what lies beyond a range is counted by :func:`placement`)."""
        values = run_covariates(point)
        return np.array(
            [min(max(values[a], lo), hi) / (hi - lo) for a, (lo, hi) in self.ranges.items() if hi - lo > 1e-9]
        )

    def beyond(self, point: OperatingPoint) -> float:
        """``point``'s distance from the runs' convex hull, in widths of the axes (0 inside),
        once brought into the ranges."""
        return hull_distance(self.vertices, self._scaled(point))


def hull_distance(vertices: np.ndarray, x: np.ndarray) -> float:
    """The Euclidean distance from ``x`` to the convex hull of the rows of ``vertices``:
    non-negative weights of the rows nearest ``x``, their sum held at 1 by a heavy row;
    0 without a row or a column (one run, or no axis that varies)."""
    if vertices.size == 0:
        return 0.0
    heavy = 1e3 * (1.0 + float(np.abs(vertices).max(initial=0.0)))
    a = np.vstack([vertices.T, np.full(vertices.shape[0], heavy)])
    weights = nnls(a, np.append(x, heavy))[0]
    distance = float(np.linalg.norm(vertices.T @ weights - x))
    return distance if distance > 1e-6 else 0.0


def _fixed(point: OperatingPoint, pattern: str) -> dict[str, Any]:
    return {**{name: getattr(point, name) for name in FIXED}, "blade_pattern": pattern}


def _setting(value: Any) -> str:
    return f"{value:.6g}" if isinstance(value, float) else str(value)


def shared_physics(physics: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """What every one of ``physics`` (:func:`~workflows.prediction.library.physics_of`) holds alike: the physics a point
    must share with them. Empty when one of them is unknown (a library made before its
    runs' physics were kept checks none)."""
    if not physics or any(not p for p in physics):
        return {}
    first = physics[0]
    return {k: v for k, v in first.items() if all(k in p and same_setting(p[k], v) for p in physics[1:])}


def least_gap(points: Sequence[OperatingPoint]) -> float:
    """The least gap from the last blade station to the weir over ``points`` [m]."""
    return min(weir_gap_m(p) for p in points)


def station_rule(points: Sequence[OperatingPoint]) -> tuple[float, float, float] | None:
    """(first station [m], spacing [m], least gap from the last station to the weir [m]) of
    the runs ``points``; None when no run has two stations (no spacing to keep)."""
    spacings = [float(np.mean(np.diff(p.blade_x_m))) for p in points if len(p.blade_x_m) > 1]
    if not spacings:
        return None
    return points[0].blade_x_m[0], min(spacings), least_gap(points)


def stations_for(rule: tuple[float, float, float], length_m: float) -> int:
    """How many stations a ``length_m`` blender holds at ``rule``'s first station and spacing,
    leaving at least its gap before the weir (:func:`station_rule`)."""
    first, spacing, gap = rule
    return math.floor((length_m - gap - first) / spacing + 1e-9) + 1


def domain(points: Sequence[OperatingPoint], pattern: str, physics: Sequence[Mapping[str, Any]] = ()) -> Domain:
    """The :class:`Domain` of a library's operating points, its stations oriented by
    ``pattern``, its runs' physics ``physics`` (:func:`~workflows.prediction.library.physics_of`, one per point; none:
    unchecked)."""
    values = [run_covariates(p) for p in points]
    ranges = {axis: (min(v[axis] for v in values), max(v[axis] for v in values)) for axis in DOMAIN_AXES}
    box = Domain(
        ranges,
        _fixed(points[0], pattern),
        physics=shared_physics(physics),
        layouts=tuple(dict.fromkeys(map(layout_of, points))),
        stations=station_rule(points),
    )
    vertices = np.array([box._scaled(p) for p in points])
    ends = [hull_distance(np.delete(vertices, n, axis=0), vertices[n]) for n in range(len(points))]
    ends = [d for d in ends if d > 0]
    return replace(box, vertices=vertices, end_distance=float(np.median(ends)) if ends else 1.0)


@dataclass(frozen=True)
class Placement:
    """Where a point lies against a library's :class:`Domain`: ``issues`` what lies outside
    its ranges or differs from its fixed properties (a prediction there is refused unless
    extrapolation is asked for); ``beyond`` its distance from the runs' convex hull (a
    combination of speed, length and feed no run brackets: inside the ranges of a library
    of one change at a time, two changes at once leave it); ``widening`` the interval's
    factor, 1 + the distance outside the ranges + ``beyond`` (+1 per fixed property);
    ``floor_share`` the share of the extrapolation floor the interval keeps: all of it
    outside the ranges, else ``beyond`` over the library's own extrapolations' reach;
    ``new_layout`` whether no run has the point's blade layout (its length and stations),
    where the interval keeps the layout floor (:func:`layout_floor`)."""

    issues: tuple[str, ...]
    beyond: float
    widening: float
    floor_share: float
    new_layout: bool = False
    #: the axes beyond :data:`EXTRAPOLATION_REACH` of their ranges, each named with its
    #: distance and how far the reach goes (empty inside it)
    out_of_reach: tuple[str, ...] = ()

    @property
    def extrapolated(self) -> bool:
        return bool(self.issues) or self.beyond > 0

    def labels(self) -> tuple[str, ...]:
        """What an extrapolated prediction is labelled with."""
        if self.beyond > 0:
            return (*self.issues, f"beyond the combinations the runs span ({self.beyond:.2f} domain widths from them)")
        return self.issues


def placement(dom: Domain, point: OperatingPoint, pattern: str, physics: Mapping[str, Any] | None = None) -> Placement:
    """The :class:`Placement` of ``point`` (its stations oriented by ``pattern``, its
    configuration's physics ``physics``, :func:`physics_of`; None: not checked) in ``dom``."""
    issues, distance, reach = [], 0.0, []
    values = run_covariates(point)
    for axis in DOMAIN_AXES:
        low, high = dom.ranges[axis]
        excess = max(low - values[axis], values[axis] - high, 0.0)
        if excess > 1e-9:
            issues.append(f"{axis} outside the library's range")
            # an axis the library never varied counts like a fixed property it does not vary
            widths = excess / (high - low) if high - low > 1e-9 else 1.0
            distance += widths
            if high - low > 1e-9 and widths > EXTRAPOLATION_REACH + 1e-9:
                ends = dom.span(axis, EXTRAPOLATION_REACH)
                reach.append(
                    f"{axis} {widths:.2f} widths of its range beyond it (--extrapolate reaches "
                    f"{ends[0]:.4g}-{ends[1]:.4g} {AXIS_REFERENCES[axis][1]})"
                )
    for name, value in _fixed(point, pattern).items():
        library = dom.fixed[name]
        if not (value == library or (isinstance(value, float) and math.isclose(value, library, rel_tol=1e-9))):
            issues.append(f"{name} = {value} (the library's is {library})")
            distance += 1.0
    for name, library in dom.physics.items() if physics is not None else ():
        value = physics.get(name)
        if not same_setting(value, library):
            issues.append(f"{name} = {_setting(value)} (the library's runs have {_setting(library)})")
            distance += 1.0
    if physics is not None and dom.gaps_m is not None:
        issue, excess = _gap_issue(dom, point)
        if issue:
            issues.append(issue)
            distance += excess
    beyond = dom.beyond(point)
    share = 1.0 if issues else min(1.0, beyond / max(dom.end_distance, 1e-9))
    new_layout = bool(dom.layouts) and layout_index(dom.layouts, layout_of(point)) is None
    return Placement(tuple(issues), beyond, 1.0 + distance + beyond, share, new_layout, tuple(reach))


def barrel_capacity(point: OperatingPoint) -> float:
    """The most particles the barrel of ``point`` holds: its volume at close packing over
    one particle's (the shaft and blades, a few % of it, left in: an upper bound)."""
    volume = math.pi / 4 * point.diameter_m**2 * point.length_m
    return CLOSE_PACKING * volume / (math.pi / 6 * point.particle_diameter_m**3)


def _gap_issue(dom: Domain, point: OperatingPoint) -> tuple[str, float]:
    """What is wrong with ``point``'s gap from its last blade station to the weir against
    ``dom``'s layouts (empty when nothing), and how far beyond them it lies in spacings.
    Checked with the physics only: the library's own runs, left out, keep the gap as a
    correction covariate, whose leverage widens their intervals."""
    low, high = dom.gaps_m
    first, spacing, _ = dom.stations
    gap = weir_gap_m(point)
    excess = max(low - gap, gap - high, 0.0)
    if excess <= 1e-9:
        return "", 0.0
    n = stations_for(dom.stations, point.length_m)
    fit = (
        f"; at {point.length_m:g} m the library's layout has {n} stations, the last at {first + (n - 1) * spacing:.4g} m"
        if n >= 1
        else ""
    )
    return (
        f"the last blade station {gap * 1e3:.4g} mm before the weir (the library's layouts leave "
        f"{low * 1e3:.4g}-{high * 1e3:.4g} mm{fit})",
        excess / spacing,
    )


# ------------------------------------------------------------------ the prediction
def residual(key: str, dem: float, predicted: float) -> float:
    """The prediction error on ``key``'s scale (module docstring)."""
    if key in ABSOLUTE_KEYS:
        return dem - predicted
    if dem > 0 and predicted > 0:
        return math.log(dem / predicted)
    return math.nan


def shifted(key: str, value: float, shift: float) -> float:
    """``value`` moved by ``shift`` on ``key``'s scale."""
    if key in ABSOLUTE_KEYS:
        return value + shift
    return math.copysign(math.inf, value) if shift > 700.0 else value * math.exp(shift)  # past exp's range


def bounds(key: str, value: float, half: float) -> tuple[float, float]:
    return shifted(key, value, -half), shifted(key, value, half)


@dataclass(frozen=True)
class Correction:
    """What the law misses of one quantity where the library ran, as a least-squares line
    in the correction covariates (module docstring): ``names`` the covariates the runs
    identify, ``coefficients`` the constant's first, ``variance`` the residuals' about the
    line, ``inverse`` (A'A)^-1 of the runs' covariates A, ``dof`` the runs less the
    coefficients, ``pattern`` the blade pattern of the runs' stations."""

    names: tuple[str, ...]
    coefficients: np.ndarray
    variance: float
    inverse: np.ndarray
    dof: int
    pattern: str = ""

    def at(self, point: OperatingPoint, pattern: str | None = None) -> tuple[float, float, float]:
        """(shift, half-width of the 95 % prediction interval, leverage x'(A'A)^-1 x) at
        ``point`` (its stations oriented by ``pattern``, default the runs') on the
        quantity's scale; the half-width NaN without a degree of freedom."""
        x = correction_row(point, self.names, pattern or self.pattern)
        shift = float(x @ self.coefficients)
        leverage = float(x @ self.inverse @ x)
        if self.dof < 1 or not math.isfinite(self.variance):
            return shift, math.nan, leverage
        t = float(stdtrit(self.dof, 0.5 + LEVEL / 2))  # Student's t quantile
        return shift, t * math.sqrt(self.variance * (1.0 + leverage)), leverage


def fit_correction(
    points: Sequence[OperatingPoint], residuals: Sequence[float], names: Sequence[str], pattern: str = ""
) -> Correction:
    """The :class:`Correction` of ``residuals`` (one per point, NaN skipped) in the
    covariates ``names`` (the points' stations oriented by ``pattern``: :func:`correction_row`),
    taken in their order, each kept when the points identify it (it
    raises the rank of the runs' covariates) and leave :data:`CORRECTION_DOF` degrees of
    freedom: a library too small or too narrow for the whole form gets the part it
    supports, down to the constant (the law's mean error)."""
    use = [(p, float(r)) for p, r in zip(points, residuals) if math.isfinite(r)]
    if not use:
        return Correction((), np.zeros(1), math.nan, np.full((1, 1), math.inf), 0, pattern)
    kept: list[str] = []
    for name in names:
        trial = [*kept, name]
        rows = np.array([correction_row(p, trial, pattern) for p, _ in use])
        if len(use) - rows.shape[1] >= CORRECTION_DOF and np.linalg.matrix_rank(rows) == rows.shape[1]:
            kept = trial
    a = np.array([correction_row(p, kept, pattern) for p, _ in use])
    y = np.array([r for _, r in use])
    coefficients = np.linalg.lstsq(a, y, rcond=None)[0]
    dof = len(use) - a.shape[1]
    misfit = y - a @ coefficients
    variance = float(misfit @ misfit / dof) if dof > 0 else math.nan
    return Correction(tuple(kept), coefficients, variance, np.linalg.pinv(a.T @ a), dof, pattern)


def corrections(model: LibraryModel, leave: int | None = None) -> dict[str, Correction]:
    """Per quantity, the :class:`Correction` of the whole library's law on every run, or,
    with ``leave``, of the law fitted without that run on the other runs. Raises
    ConfigError when ``model`` has no calibration."""
    calibration = model.calibration
    if calibration is None:
        raise ConfigError("the library model has no calibration: make it with `pbmdem library fit`")
    out = {}
    for key in quantity_keys():
        if key in calibration.whole:
            out[key] = fit_correction(*correction_data(model, key, leave), calibration.covariates, model.blade_pattern)
    return out


def correction_data(
    model: LibraryModel, key: str, leave: int | None = None
) -> tuple[list[OperatingPoint], list[float]]:
    """The runs' points and ``key``'s residuals (DEM less law) that :func:`corrections`
    fits ``key``'s line to: the whole library's law at every run, or, with ``leave``, the
    law fitted without that run at the other runs. ``model`` calibrated."""
    calibration = model.calibration
    law = calibration.whole[key] if leave is None else calibration.left_out[key][leave]
    points, residuals = [], []
    for j, entry in enumerate(model.runs):
        if j != leave and key in entry.dem:
            points.append(entry.point)
            residuals.append(residual(key, entry.dem[key].value, law[j]))
    return points, residuals


def held_out(
    model: LibraryModel, n: int, widening: float = 1.0, floor: dict[str, float] | None = None
) -> tuple[PredictedQuantity, ...]:
    """Run ``n`` predicted without it (:func:`assembled`): the law fitted without it (its
    chain timed by the zone law fitted without it, when the library's is timed), corrected
    by the lines of that law's misses on the other runs, and its slices by the zone law
    fitted without it. ``model`` calibrated."""
    calibration = model.calibration
    entry = model.runs[n]
    law = {key: rows[n][n] for key, rows in calibration.left_out.items()}
    profile = calibration.profile_left_out[n] if calibration.profile is not None else None
    return assembled(law, corrections(model, leave=n), profile, entry.point, model.blade_pattern, widening, floor)


def left_out_errors(model: LibraryModel, runs: Sequence[int]) -> dict[str, list[float]]:
    """Per quantity, the error of each run of ``runs`` predicted without it (:func:`held_out`)."""
    out: dict[str, list[float]] = {key: [] for key in quantity_keys()}
    for n in runs:
        entry = model.runs[n]
        for q in held_out(model, n):
            if q.key in entry.dem:
                out[q.key].append(residual(q.key, entry.dem[q.key].value, q.value))
    return out


def _floor(model: LibraryModel, runs: Sequence[int]) -> dict[str, float]:
    """Per quantity, t(0.975, m) times the root mean square error of the m runs ``runs``,
    each predicted without it (:func:`left_out_errors`); none without such a run."""
    out = {}
    for key, errors in left_out_errors(model, runs).items():
        errors = [e for e in errors if math.isfinite(e)]
        if errors:
            out[key] = float(stdtrit(len(errors), 0.5 + LEVEL / 2)) * math.sqrt(float(np.mean(np.square(errors))))
    return out


def end_runs(model: LibraryModel, leave: int | None = None) -> list[int]:
    """The runs beyond the other runs' hull (the ends of the library's ranges, and its
    corners off a star of one change at a time), ``leave`` not among them."""
    return [n for n, inside in enumerate(model.calibration.inside) if not inside and n != leave]


def lone_layout_runs(model: LibraryModel, leave: int | None = None) -> list[int]:
    """The runs inside the others' hull whose blade layout no other run has (``leave``
    neither among them nor counted as another): left out, each was predicted at a layout
    the law had not seen."""
    layouts = [layout_of(r.point) for r in model.runs]
    kept = [n for n in range(len(layouts)) if n != leave]
    return [
        n for n in kept if model.calibration.inside[n] and sum(same_layout(layouts[m], layouts[n]) for m in kept) == 1
    ]


def extrapolation_floor(model: LibraryModel, leave: int | None = None) -> dict[str, float]:
    """Per quantity, the least half-width of an extrapolation (:func:`_floor`) from the end
    runs (:func:`end_runs`). The line's own interval knows nothing of how the law bends
    beyond its runs; these errors do."""
    return _floor(model, end_runs(model, leave))


def layout_floor(model: LibraryModel, leave: int | None = None) -> dict[str, float]:
    """Per quantity, the least half-width at a blade layout no run has (:func:`_floor`) from
    the runs alone at their layouts inside the hull (:func:`lone_layout_runs`), each
    predicted without it as such a point is. Inside the hull only, since an end's error is
    the extrapolation floor's."""
    return _floor(model, lone_layout_runs(model, leave))


@dataclass(frozen=True)
class Floors:
    """The least half-widths, per quantity, that a library's own runs left out set: beyond
    its runs' hull (``ends``, :func:`extrapolation_floor`) and at a blade layout no run has
    (``layout``, :func:`layout_floor`)."""

    ends: dict[str, float]
    layout: dict[str, float]

    def at(self, place: Placement) -> dict[str, float]:
        """Per quantity, the least half-width at a point placed as ``place`` says: the
        extrapolation floor times the point's share of it beyond the hull, the layout floor
        at a layout no run has, the larger of the two; none inside the hull at a layout run."""
        ends = {k: v * place.floor_share for k, v in self.ends.items()} if place.extrapolated else {}
        layout = self.layout if place.new_layout else {}
        return {k: max(ends.get(k, 0.0), layout.get(k, 0.0)) for k in ends.keys() | layout.keys()}


def floors(model: LibraryModel, leave: int | None = None) -> Floors:
    """The :class:`Floors` of ``model`` (calibrated), ``leave`` not among their runs."""
    return Floors(extrapolation_floor(model, leave), layout_floor(model, leave))


def floor_at(model: LibraryModel, place: Placement, leave: int | None = None) -> dict[str, float]:
    """Per quantity, the least half-width at a point placed as ``place`` says
    (:meth:`Floors.at`), ``leave`` not among the floors' runs."""
    if not (place.extrapolated or place.new_layout):
        return {}
    return floors(model, leave).at(place)


@dataclass(frozen=True)
class PredictedQuantity:
    """One quantity: ``value`` the law's ``law_value`` moved by ``shift`` (on the quantity's
    scale), with its 95 % prediction interval ``low``-``high``; ``correction`` the line it
    came from and ``leverage`` the point's, or for a slice's hold-up ``profile``, the zone
    law it came from (:mod:`workflows.prediction.profile`); ``widening`` the factor outside
    the domain."""

    key: str
    value: float
    low: float
    high: float
    law_value: float
    shift: float
    correction: Correction | None
    leverage: float
    widening: float = 1.0
    profile: ProfileLaw | None = None
    #: predicted by the correction's line alone (``Calibration.direct``): ``law_value`` is
    #: :func:`~workflows.prediction.library.line_alone`'s, not the law's
    alone: bool = False
    #: a slice's: the library's runs of the point's blade layout whose misses of the
    #: shares it takes (:class:`~workflows.prediction.profile.LayoutShares`; 0: none)
    layout_runs: int = 0

    def record(self) -> dict[str, Any]:
        return {"key": self.key, "value": self.value, "low": self.low, "high": self.high}

    def details(self) -> dict[str, Any]:
        if self.correction is None:
            i = int(self.key.rpartition("_")[2]) - 1
            if self.layout_runs:
                return {
                    "law_value": self.law_value,
                    "correction": self.shift,
                    "source": f"the slices' zone law (workflows.prediction.profile) with the misses of the shares "
                    f"of the {self.layout_runs} library runs of this blade layout, scaled to the predicted hold-up",
                    "residual_sd": float(self.profile.layouts.sd[i]),
                    "degrees_of_freedom": float(self.profile.layouts.dof),
                    "widening": self.widening,
                }
            return {
                "law_value": self.law_value,
                "correction": self.shift,
                "source": "the slices' zone law (workflows.prediction.profile), scaled to the predicted hold-up",
                "residual_sd": float(self.profile.slice_sd[i]),
                "degrees_of_freedom": float(self.profile.slice_dof[i]),
                "widening": self.widening,
            }
        return {
            **({"source": "the correction's line alone, fitted to the DEM's values"} if self.alone else {}),
            "law_value": self.law_value,
            "correction": self.shift,
            "correction_covariates": list(self.correction.names),
            "residual_sd": math.sqrt(self.correction.variance) if math.isfinite(self.correction.variance) else None,
            "degrees_of_freedom": self.correction.dof,
            "leverage": self.leverage,
            "widening": self.widening,
        }


def corrected(
    key: str,
    value: float,
    correction: Correction,
    point: OperatingPoint,
    widening: float = 1.0,
    floor: float = 0.0,
    pattern: str | None = None,
) -> PredictedQuantity:
    """The law's ``value`` of ``key`` at ``point`` (its stations oriented by ``pattern``,
    default the library's) corrected, with its interval (module docstring): the line's
    half-width, at least ``floor`` (an extrapolation's), times ``widening``; NaN bounds
    where the correction has no degree of freedom."""
    shift, half, leverage = correction.at(point, pattern)
    centre = shifted(key, value, shift)
    low, high = bounds(key, centre, max(half, floor) * widening)
    return PredictedQuantity(key, centre, low, high, value, shift, correction, leverage, widening)


def profiled(
    key: str,
    law_value: float,
    value: float,
    half: float,
    profile: ProfileLaw,
    widening: float = 1.0,
    floor: float = 0.0,
    layout_runs: int = 0,
) -> PredictedQuantity:
    """A slice's hold-up ``value`` from the zone law ``profile`` (with the misses of its
    layout's ``layout_runs`` runs), its half-width ``half`` on the log scale, at least
    ``floor`` (an extrapolation's), times ``widening``."""
    low, high = bounds(key, value, max(half, floor) * widening)
    shift = residual(key, value, law_value)
    return PredictedQuantity(
        key, value, low, high, law_value, shift, None, math.nan, widening, profile, layout_runs=layout_runs
    )


def assembled(
    law: dict[str, float],
    lines: dict[str, Correction],
    profile: ProfileLaw | None,
    point: OperatingPoint,
    pattern: str,
    widening: float = 1.0,
    floor: dict[str, float] | None = None,
) -> tuple[PredictedQuantity, ...]:
    """Every quantity a line corrects, at ``point`` (its stations oriented by ``pattern``):
    the law's value ``law`` moved by its line (:func:`corrected`), or, with ``profile``,
    each slice's hold-up from the zone law (:func:`profiled`); each half-width at least
    ``floor``'s, times ``widening``. The slices are then scaled alike so that they hold the
    predicted hold-up (:func:`held_in_total`)."""
    floor = floor or {}
    slices, layout_runs = {}, 0
    if profile is not None:
        values, halves = profile.at(point, pattern)
        slices = {slice_key(i): (float(v), float(h)) for i, (v, h) in enumerate(zip(values, halves))}
        layout_runs = profile.layouts.runs_at(point) if profile.layouts is not None else 0
    out = []
    for key in quantity_keys():
        if key not in lines:
            continue
        if key in slices:
            out.append(profiled(key, law[key], *slices[key], profile, widening, floor.get(key, 0.0), layout_runs))
        else:
            out.append(corrected(key, law[key], lines[key], point, widening, floor.get(key, 0.0), pattern))
    return held_in_total(tuple(out))


def held_in_total(quantities: Sequence[PredictedQuantity]) -> tuple[PredictedQuantity, ...]:
    """``quantities`` with every slice's hold-up scaled alike so that the slices sum to the
    predicted hold-up, where both are predicted: one bed, whose total the hold-up's line
    corrects, and which the PBM's table (:func:`predict`) and ``design`` keep. Each slice's
    half-width (log) is its own and the hold-up's in quadrature: the slice then carries the
    total's error as well as its share's. Its own also holds the zone law's error in the
    total, so this errs wide: every run of the shipped library left out (before the zone
    law kept its misses at the layouts run), the slices so scaled held the DEM's in 98.7 %
    of their intervals, interval score 0.239 (unscaled
    96.0 %, 0.242; scaled with their own widths 98.0 %, 0.222, but the unseen runs'
    extrapolated slices lost coverage with the total's error: ``law/calibration.md``, "The
    slices' hold-ups", and ``law/unseen/check.md``)."""
    by_key = {q.key: q for q in quantities}
    keys = [slice_key(i) for i in range(AXIAL_SLICES)]
    if "holdup" not in by_key or not all(k in by_key for k in keys):
        return tuple(quantities)
    held, total = sum(by_key[k].value for k in keys), by_key["holdup"]
    if not (held > 0 and math.isfinite(held) and total.value > 0 and math.isfinite(total.value)):
        return tuple(quantities)
    scale = total.value / held
    # without an interval of the hold-up (a line without a degree of freedom) a slice keeps
    # its own
    spread = math.log(total.high / total.low) / 2 if total.low > 0 and total.high > 0 else 0.0
    spread = spread if math.isfinite(spread) else 0.0

    def moved(q: PredictedQuantity) -> PredictedQuantity:
        value, shift = q.value * scale, q.shift + math.log(scale)
        if not (q.low > 0 and q.high > 0):  # an empty slice, or no interval: scaled as it is
            return replace(q, value=value, low=q.low * scale, high=q.high * scale, shift=shift)
        half = math.hypot(math.log(q.high / q.low) / 2, spread)
        return replace(q, value=value, low=value * math.exp(-half), high=value * math.exp(half), shift=shift)

    return tuple(moved(q) if q.key in keys else q for q in quantities)


@dataclass(frozen=True)
class Prediction:
    point: OperatingPoint
    quantities: tuple[PredictedQuantity, ...]
    outside: tuple[str, ...]
    domain: Domain
    #: the law's chain with each slice's time scale set to the predicted slice hold-ups
    values: PointValues
    rtd_times_s: np.ndarray
    rtd: np.ndarray  # (3, T): E(t) at the predicted mean residence time, and at its interval's ends
    #: no library run has the point's blade layout: its intervals keep the layout floor
    new_layout: bool = False

    @property
    def extrapolated(self) -> bool:
        return bool(self.outside)

    def quantity(self, key: str) -> PredictedQuantity:
        return next(q for q in self.quantities if q.key == key)


def rescaled(model: PhaseTransport, factors: np.ndarray) -> PhaseTransport:
    """``model`` with every rate out of slice i (moves, switching, discharge) multiplied by
    ``factors[i]``: the jump chain is the same, so are the steady flows, and slice i holds
    1/factors[i] as many particles (module docstring). A rate the law holds at its bound
    (:data:`dem.phases.law.MAX_LAW_RATE`), instantaneous at any interval, stays there."""
    scale = np.asarray(factors, dtype=float)[None, None, :, None]
    return replace(
        model,
        rates=np.minimum(model.rates * scale, MAX_LAW_RATE),
        switching=np.minimum(model.switching * scale, MAX_LAW_RATE),
    )


def stretched(curve: np.ndarray, times: np.ndarray, factor: float) -> np.ndarray:
    """The density ``curve`` on ``times`` of a time to discharge multiplied by ``factor``."""
    return np.interp(times / factor, times, curve, right=0.0) / factor


def model_domain(model: LibraryModel) -> Domain:
    """The :class:`Domain` of a library model's runs."""
    return domain([r.point for r in model.runs], model.blade_pattern, [r.physics for r in model.runs])


def predict(
    model: LibraryModel,
    point: OperatingPoint,
    pattern: str,
    extrapolate: bool = False,
    physics: Mapping[str, Any] | None = None,
    least: Floors | None = None,
) -> Prediction:
    """The prediction of ``point``, its blade stations oriented by ``pattern``, its
    configuration's physics ``physics`` (:func:`~workflows.prediction.library.physics_of`; None: taken as the library's),
    from ``model`` (module docstring); ``least`` the model's :func:`floors`, when the caller
    has them already (made here when needed). Raises ConfigError when the model has no
    calibration, or the point lies outside the library's domain and ``extrapolate`` is
    False."""
    lines = corrections(model)
    dom = model_domain(model)
    place = placement(dom, point, pattern, physics)
    if place.issues and not extrapolate:
        raise ConfigError(
            f"the point lies outside the library's domain ({'; '.join(place.issues)}); the domain is "
            f"{dom.describe()}. Add a DEM run there, or pass --extrapolate for a labelled, widened prediction"
        )
    if place.out_of_reach:
        raise ConfigError(
            f"the point lies too far beyond the library's domain to extrapolate ({'; '.join(place.out_of_reach)}); "
            f"the domain is {dom.describe()}. Add a DEM run nearer it to the library"
        )
    try:
        law = point_values(model.law, model.transverse, point, pattern, model.interval_s)
        values = law.values
        scale = model.calibration.time_scale()
        if scale is not None:
            chain = law
            law = timed(chain, scale, point, pattern)
            values = timed_values(chain, law)
    except TableError as exc:
        raise ConfigError(
            f"the library's law cannot be evaluated at {point.impeller_rpm:g} rpm, {point.length_m:g} m, "
            f"{point.feed_rate_total_per_s:g} /s ({exc}): too far beyond its domain, {dom.describe()}"
        ) from None
    values = {key: line_alone(key, point) if key in model.calibration.direct else v for key, v in values.items()}
    floor = least.at(place) if least is not None else floor_at(model, place)
    quantities = assembled(values, lines, model.calibration.profile, point, pattern, place.widening, floor)
    quantities = tuple(replace(q, alone=True) if q.key in model.calibration.direct else q for q in quantities)
    by_key = {q.key: q for q in quantities}
    if "holdup" in by_key and by_key["holdup"].value > barrel_capacity(point):
        raise ConfigError(
            f"the predicted hold-up, {by_key['holdup'].value:.0f} particles, exceeds the {barrel_capacity(point):.0f} "
            f"the barrel holds at close packing: {point.impeller_rpm:g} rpm, {point.feed_rate_total_per_s:g} /s and "
            f"{point.length_m:g} m lie beyond what the library's law can say; the domain is {dom.describe()}"
        )
    held = law.counts.sum(axis=(0, 2))
    slices = np.array([by_key[slice_key(i)].value if slice_key(i) in by_key else held[i] for i in range(held.size)])
    if "holdup" in by_key:
        slices *= by_key["holdup"].value / slices.sum()
    values = chain_values(rescaled(law.model, held / slices), point)
    mean = values.values["mean_residence_time_s"]
    times = np.linspace(0.0, RTD_SPAN * mean, RTD_POINTS)
    curve = rtd_curve(values.model, values.feed, times)
    ends = [mean]
    if "mean_residence_time_s" in by_key:
        q = by_key["mean_residence_time_s"]
        ends = [q.value, q.low, q.high]
    curves = np.array([stretched(curve, times, end / mean) if math.isfinite(end) else curve for end in ends])
    rtd = np.vstack([curves[0], curves.min(axis=0), curves.max(axis=0)])
    outside = place.labels() if place.extrapolated else ()
    return Prediction(point, quantities, outside, dom, values, times, rtd, place.new_layout)
