"""The hold-up along the blender, zone by zone of its blade stations: each slice's hold-up
that ``pbmdem predict`` gives.

The library's chain (:mod:`workflows.prediction.library`) is fitted to the particles'
moves between slices of a fixed fraction of the length; a blender of another length puts
other blade stations in each slice, and at the weir a layout the law has never seen. Left
out, it misses a slice's hold-up by up to 80 % (the x1.25 blender), and a correction line
per slice (six coefficients from 14 runs) leaves the slices' intervals at 11 % of the
value. The slices are predicted instead from the bed itself, in metres of barrel, so that
a blender with more or fewer stations reuses what every other blender showed.

The bed's linear density (particles per metre of barrel) is a law of the zone it lies in,
the zones set by the blade stations (:func:`zones`, :data:`ZONES`): the inlet, from the
inlet wall to the first blade's swept zone; the swept zone of a forward and of a backward
station (the station +- ``half_width_m``); the stretch after a forward and after a
backward station, up to the next one's swept zone; the weir zone, from the last blade's
swept zone to the weir; and the swept zones of the two stations beside the inlet's pile,
each its own (:data:`OWN_STATIONS`). Its logarithm is each zone's own line in log speed and log feed,
plus terms every zone shares (:data:`SHARED_TERMS`): the distance to the weir d and d^2
(the bed slopes down towards the weir), d times log speed and log feed, (log speed)^2, and
in the weir zone the log gap from the last station to the weir. A slice's hold-up is the
density integrated over the slice (on a :data:`GRID_M` grid).

The law is fitted by Gauss-Newton to the log of the DEM's slice hold-ups, each slice
position weighted by its own scatter about the law (re-estimated from the residuals,
:data:`WEIGHT_ROUNDS` times: the slices at the inlet and the weir follow the law more
closely than the middle ones). The swept half-width is the one of :data:`HALF_WIDTHS_M`
with the greatest likelihood (on the shipped library 13 mm, about half the blades' 25 mm
chord: the zone a paddle sweeps as it turns).

A slice's 95 % interval is its log hold-up +- t(0.975, nu_i) sqrt(s_i^2 + g_i' C g_i): s_i
the slice's scatter, g_i the gradient of its log hold-up in the coefficients, C their
covariance (J'WJ)^-1, nu_i the slice's own degrees of freedom (its observations less their
leverage: s_i is estimated from that slice's residuals alone).

A blade layout the library has run (:class:`LayoutShares`: the same length and stations)
shows what the zone law misses of it: the law's smooth terms must serve every layout, and
a slice of one layout can hold a station where another's holds a gap (slice 8 of the
baseline's 0.33 m, +5 % over its runs whatever the speed and the feed). Its runs' misses
of each slice's share of the bed (the log of the DEM's share over the law's) are therefore
a line of their own: the layout's mean miss, moved along slopes in :data:`LAYOUT_TERMS`
that every layout with two runs or more shares. At such a layout the law's shares take
that miss, its total unchanged; a slice's interval is then its share's, t(0.975, nu)
s_i sqrt(1 + 1/n + (x - x_L)' (X'X)^+ (x - x_L)) (s_i the slice's scatter about the lines
within the layouts, nu their degrees of freedom, n the layout's runs, x_L their mean
covariates, X the runs' covariates less their layout's mean), the total's error left to
the predicted hold-up the slices are scaled to. A layout the library has not run keeps
the law as it is.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from functools import cached_property
from typing import Any

import numpy as np
from scipy.special import stdtrit

from coupling.errors import ConfigError
from coupling.operating import OperatingPoint
from workflows.prediction.covariates import run_covariates

#: the zones of the bed, in the order of the law's coefficients
ZONES = ("inlet", "forward blade", "backward blade", "after forward", "after backward", "weir")
#: each zone's own terms
ZONE_TERMS = ("1", "speed", "feed")
#: the terms every zone shares (module docstring)
SHARED_TERMS = ("distance", "distance2", "speed_distance", "feed_distance", "speed2", "weir_gap")
#: the stations (counted from the inlet; negative from the weir) whose swept zones have
#: their own line, after :data:`ZONES`: the two beside the inlet's pile. Every run left out
#: on the shipped library (``pbmdem study profile-forms``), the interpolated runs' slices
#: are missed by 4.1 % (root mean square of the log error) with none, 3.9 % with the first,
#: 3.2 % with the first two. The third from the weir beside them misses them by 3.0 %, but
#: the library's verdicts and its unseen runs' coverage fall with it (PREDICTION.md)
OWN_STATIONS = (0, 1)
#: the distance to the weir is measured in this unit [m]
DISTANCE_UNIT_M = 0.1
#: the greatest step of the grid the density is integrated on [m] (each run's fills its slices)
GRID_M = 0.0005
#: the swept half-widths tried [m]
HALF_WIDTHS_M = tuple(round(0.001 * k, 4) for k in range(4, 17))
WEIGHT_ROUNDS = 3
LEVEL = 0.95
#: Gauss-Newton's limits: iterations, and the relative fall of the misfit it stops under
ITERATIONS = 60
TOL = 1e-12
#: the covariates (:func:`~workflows.prediction.covariates.run_covariates`) a layout's
#: misses of the slices' shares follow (module docstring). Every run of the shipped
#: library's 0.33-m layout left out, the shares are missed by 2.8 % (root mean square of
#: the log error) by the law alone, 2.2 % with speed and feed, 2.0 % with speed and
#: speed^2, 1.5 % with all three (``pbmdem study profile-forms``, its second table)
LAYOUT_TERMS = ("speed", "feed", "speed2")
#: two blade stations or lengths closer than this are the same [m]: a station typed to a
#: tenth of a millimetre is the station the library ran (its physics is compared alike)
LAYOUT_TOL_M = 1e-4


def n_coefficients(own_stations: Sequence[int]) -> int:
    """The law's coefficients with swept zones of their own at ``own_stations``."""
    return (len(ZONES) + len(own_stations)) * len(ZONE_TERMS) + len(SHARED_TERMS)


def zones(
    point: OperatingPoint,
    pattern: str,
    half_width_m: float,
    own_stations: Sequence[int] = OWN_STATIONS,
    grid_m: float = GRID_M,
) -> tuple[np.ndarray, np.ndarray]:
    """(x [m], zone index) of the grid points along ``point``'s barrel, its stations
    oriented by ``pattern`` ("F" forward, "B" backward, cycled from the inlet): an index
    into :data:`ZONES`, or past them the k-th of ``own_stations``' swept zones (a station
    the blender lacks has none)."""
    if not pattern or set(pattern) - {"F", "B"}:
        raise ConfigError(f"blade pattern {pattern!r}: letters F (forward) and B (backward) only")
    x = np.arange(grid_m / 2, point.length_m, grid_m)
    stations = np.asarray(point.blade_x_m, dtype=float)
    forward = np.array([pattern[k % len(pattern)] == "F" for k in range(stations.size)])
    zone = np.full(x.size, 3)
    for k in range(stations.size - 1):
        zone[(x > stations[k]) & (x < stations[k + 1])] = 3 if forward[k] else 4
    zone[x < stations[0] - half_width_m] = 0
    for k, s in enumerate(stations):
        zone[np.abs(x - s) < half_width_m] = 1 if forward[k] else 2
    zone[x > stations[-1] + half_width_m] = 5
    for k, station in enumerate(own_stations):
        if -stations.size <= station < stations.size:
            zone[np.abs(x - stations[station]) < half_width_m] = len(ZONES) + k
    return x, zone


@dataclass(frozen=True)
class _Design:
    """The law's linear part on one run's grid: log density = ``rows`` @ coefficients;
    ``slice_of`` each grid point's slice; ``step_m`` the grid's step."""

    rows: np.ndarray
    slice_of: np.ndarray
    nx: int
    step_m: float


def _with_shares(log_held: np.ndarray, miss: np.ndarray) -> np.ndarray:
    """The log hold-ups ``log_held`` with each slice's share moved by ``miss`` (log), their
    total kept."""
    moved = log_held + miss
    return moved - np.logaddexp.reduce(moved) + np.logaddexp.reduce(log_held)


def _design(point: OperatingPoint, pattern: str, half_width_m: float, own_stations: Sequence[int], nx: int) -> _Design:
    # the step nearest GRID_M that fills each slice with whole steps: a slice of 0.02475 m
    # on a 0.5-mm grid would hold 49 or 50 of them, 1 % off the slice it integrates
    step = point.length_m / nx / math.ceil(point.length_m / nx / GRID_M - 1e-9)
    x, zone = zones(point, pattern, half_width_m, own_stations, step)
    covariates = run_covariates(point, nx)
    speed, feed, gap = covariates["speed"], covariates["feed"], covariates["gap"]
    own = np.zeros((x.size, len(ZONES) + len(own_stations), len(ZONE_TERMS)))
    own[np.arange(x.size), zone] = (1.0, speed, feed)
    d = (point.length_m - x) / DISTANCE_UNIT_M
    shared = np.column_stack([d, d**2, speed * d, feed * d, np.full(x.size, speed**2), (zone == 5) * gap])
    edges = np.linspace(0.0, point.length_m, nx + 1)
    slice_of = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, nx - 1)
    return _Design(np.hstack([own.reshape(x.size, -1), shared]), slice_of, nx, step)


def _held(design: _Design, coefficients: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(the particles on each grid step, each slice's hold-up)."""
    density = np.exp(np.clip(design.rows @ coefficients, -700.0, 700.0)) * design.step_m
    held = np.bincount(design.slice_of, weights=density, minlength=design.nx)
    return density, np.maximum(held, 1e-300)


def _log_slices(design: _Design, coefficients: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(log hold-up of each slice, its gradient in the coefficients (NX, P))."""
    density, held = _held(design, coefficients)
    weighted = np.zeros((design.nx, design.rows.shape[1]))
    np.add.at(weighted, design.slice_of, design.rows * density[:, None])
    return np.log(held), weighted / held[:, None]


def layout_of(point: OperatingPoint) -> tuple[float, ...]:
    """``point``'s blade layout: its length and stations [m], to the micrometre."""
    return (round(point.length_m, 6), *(round(x, 6) for x in point.blade_x_m))


def same_layout(a: tuple[float, ...], b: tuple[float, ...]) -> bool:
    """Whether layouts ``a`` and ``b`` are one: as many stations, each and the length within
    :data:`LAYOUT_TOL_M`."""
    return len(a) == len(b) and all(abs(x - y) <= LAYOUT_TOL_M for x, y in zip(a, b))


def layout_index(layouts: Sequence[tuple[float, ...]], layout: tuple[float, ...]) -> int | None:
    """The index of the first of ``layouts`` that is ``layout`` (:func:`same_layout`), None
    when none is."""
    return next((k for k, other in enumerate(layouts) if same_layout(other, layout)), None)


def _terms(point: OperatingPoint, terms: Sequence[str]) -> np.ndarray:
    covariates = run_covariates(point)
    return np.array([covariates[t] for t in terms], dtype=float)


def _log_shares(held: np.ndarray) -> np.ndarray:
    return np.log(held) - np.log(held.sum(axis=-1, keepdims=True))


@dataclass(frozen=True, eq=False)
class LayoutShares:
    """What the zone law misses of the slices' shares at the blade layouts the library has
    run (module docstring): per layout (``layouts``, :func:`layout_of`) its ``runs``, their
    mean covariates ``centres`` (L, P) in ``terms`` and mean miss ``means`` (L, NX); the
    ``slopes`` (P, NX) every layout shares, ``inverse`` (X'X)^+ of the runs' covariates less
    their layout's mean, ``sd`` each slice's scatter about the lines and ``dof`` its degrees
    of freedom."""

    layouts: tuple[tuple[float, ...], ...]
    runs: np.ndarray
    centres: np.ndarray
    means: np.ndarray
    slopes: np.ndarray
    inverse: np.ndarray
    sd: np.ndarray
    dof: int
    terms: tuple[str, ...] = LAYOUT_TERMS

    def runs_at(self, point: OperatingPoint) -> int:
        """How many of the library's runs set ``point``'s shares: its layout's, where
        :meth:`at` applies their lines; 0 where the law alone does."""
        return 0 if self.at(point) is None else int(self.runs[layout_index(self.layouts, layout_of(point))])

    @cached_property
    def _seen(self) -> np.ndarray:
        """(P, P) the projection onto the covariates the layouts' runs varied."""
        return self.inverse @ np.linalg.pinv(self.inverse)

    def at(self, point: OperatingPoint) -> tuple[np.ndarray, np.ndarray] | None:
        """(the miss of each slice's log share at ``point``, the standard deviation of a run's
        share about it), or None at a layout the library has not run, or away from its runs
        along a term its layouts' runs never varied (the lines cannot tell that slope)."""
        k = layout_index(self.layouts, layout_of(point))
        if k is None:
            return None
        offset = _terms(point, self.terms) - self.centres[k]
        if np.linalg.norm(offset - self._seen @ offset) > 1e-9 * (1.0 + np.linalg.norm(offset)):
            return None
        leverage = 1.0 / self.runs[k] + float(offset @ self.inverse @ offset)
        return self.means[k] + offset @ self.slopes, self.sd * math.sqrt(1.0 + leverage)

    def record(self) -> dict[str, Any]:
        return {
            "layouts": [list(layout) for layout in self.layouts],
            "runs": self.runs.tolist(),
            "centres": self.centres.tolist(),
            "means": self.means.tolist(),
            "slopes": self.slopes.tolist(),
            "inverse": self.inverse.tolist(),
            "sd": self.sd.tolist(),
            "dof": self.dof,
            "terms": list(self.terms),
        }

    @classmethod
    def from_record(cls, record: dict) -> LayoutShares:
        shares = cls(
            tuple(tuple(float(x) for x in layout) for layout in record["layouts"]),
            np.asarray(record["runs"], dtype=float),
            np.asarray(record["centres"], dtype=float),
            np.asarray(record["means"], dtype=float),
            np.asarray(record["slopes"], dtype=float),
            np.asarray(record["inverse"], dtype=float),
            np.asarray(record["sd"], dtype=float),
            int(record["dof"]),
            tuple(str(t) for t in record["terms"]),
        )
        n_layouts, p, nx = len(shares.layouts), len(shares.terms), shares.sd.size
        if (
            shares.runs.shape != (n_layouts,)
            or shares.centres.shape != (n_layouts, p)
            or shares.means.shape != (n_layouts, nx)
            or shares.slopes.shape != (p, nx)
            or shares.inverse.shape != (p, p)
            or shares.dof < 1
            or p < 1
            or np.any(shares.runs < 1)
        ):
            raise ValueError(
                f"layout shares of {n_layouts} layouts in {p} terms over {nx} slices: "
                "at least one term, one count (at least 1), centre and mean miss per layout, "
                "one slope per term and slice, and at least one degree of freedom"
            )
        return shares


def fit_layouts(
    law: ProfileLaw, points: Sequence[OperatingPoint], holdups: np.ndarray, terms: Sequence[str] = LAYOUT_TERMS
) -> LayoutShares | None:
    """The :class:`LayoutShares` of the runs at ``points`` whose slices held ``holdups``
    (runs x slices; a run lacking a slice is left out), about ``law``'s shares; None when
    the runs that share a layout give the lines no degree of freedom."""
    holdups = np.asarray(holdups, dtype=float)
    complete = [n for n in range(len(points)) if np.all(np.isfinite(holdups[n]) & (holdups[n] > 0))]
    if not complete:
        return None
    misses = np.array([_log_shares(holdups[n]) - _log_shares(law.holdups(points[n])) for n in complete])
    x = np.array([_terms(points[n], terms) for n in complete])
    layouts: list[tuple[float, ...]] = []
    for n in complete:
        if layout_index(layouts, layout_of(points[n])) is None:
            layouts.append(layout_of(points[n]))
    group = np.array([layout_index(layouts, layout_of(points[n])) for n in complete])
    layouts = tuple(layouts)
    runs = np.bincount(group, minlength=len(layouts)).astype(float)
    centres = np.array([x[group == k].mean(axis=0) for k in range(len(layouts))])
    means = np.array([misses[group == k].mean(axis=0) for k in range(len(layouts))])
    within_x, within_miss = x - centres[group], misses - means[group]
    rank = np.linalg.matrix_rank(within_x) if within_x.size else 0
    dof = int(runs.sum() - len(layouts) - rank)
    if dof < 1:
        return None
    slopes = np.linalg.lstsq(within_x, within_miss, rcond=None)[0]
    scatter = within_miss - within_x @ slopes
    sd = np.sqrt(np.maximum(np.sum(scatter**2, axis=0) / dof, 1e-12))
    return LayoutShares(
        layouts, runs, centres, means, slopes, np.linalg.pinv(within_x.T @ within_x), sd, dof, tuple(terms)
    )


@dataclass(frozen=True, eq=False)
class ProfileLaw:
    """The zone law of the bed's density (module docstring): ``coefficients`` in the order
    of :data:`ZONES` and then the swept zones of ``own_stations``, each with its
    :data:`ZONE_TERMS`, then :data:`SHARED_TERMS`; ``covariance`` theirs;
    ``slice_sd`` each slice's scatter about the law (log), estimated from its own residuals
    with ``slice_dof`` degrees of freedom; ``dof`` the slices observed less the
    coefficients identified; ``pattern`` the library's blade pattern; ``layouts`` what it
    misses of the shares at the layouts the library has run (None: the law alone)."""

    half_width_m: float
    coefficients: np.ndarray
    covariance: np.ndarray
    slice_sd: np.ndarray
    dof: int
    pattern: str
    #: each slice's degrees of freedom: its observations less their leverage
    slice_dof: np.ndarray
    own_stations: tuple[int, ...] = OWN_STATIONS
    layouts: LayoutShares | None = None

    @property
    def nx(self) -> int:
        return int(self.slice_sd.size)

    def _missed(self, point: OperatingPoint) -> tuple[np.ndarray, np.ndarray] | None:
        return self.layouts.at(point) if self.layouts is not None else None

    def log_slices(self, point: OperatingPoint, pattern: str | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(log hold-up of each slice at ``point``, the standard deviation of its prediction:
        at a layout the library has run, of its share, module docstring)."""
        values, gradient = self.gradient(point, pattern)
        missed = self._missed(point)
        if missed is not None:
            return _with_shares(values, missed[0]), missed[1]
        spread = np.einsum("ip,pq,iq->i", gradient, self.covariance, gradient)
        return values, np.sqrt(self.slice_sd**2 + np.maximum(spread, 0.0))

    def at(self, point: OperatingPoint, pattern: str | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(each slice's predicted hold-up, the half-width of its 95 % interval on the log
        scale) at ``point``: Student's t of each slice's own degrees of freedom, since its
        scatter is estimated from its residuals alone (at a layout the library has run, of
        the layouts' lines)."""
        values, sd = self.log_slices(point, pattern)
        dof = self.layouts.dof if self._missed(point) is not None else np.maximum(self.slice_dof, 1e-3)
        return np.exp(values), stdtrit(dof, 0.5 + LEVEL / 2) * sd

    def holdups(self, point: OperatingPoint, pattern: str | None = None) -> np.ndarray:
        """Each slice's predicted hold-up at ``point``: :meth:`at`'s values, without the
        gradient its interval needs (what ``design`` evaluates at every point it searches)."""
        design = _design(point, pattern or self.pattern, self.half_width_m, self.own_stations, self.nx)
        held = _held(design, self.coefficients)[1]
        missed = self._missed(point)
        return held if missed is None else np.exp(_with_shares(np.log(held), missed[0]))

    def gradient(self, point: OperatingPoint, pattern: str | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(log hold-up of each slice at ``point`` by the zone law alone, its gradient in the
        coefficients (NX, P))."""
        design = _design(point, pattern or self.pattern, self.half_width_m, self.own_stations, self.nx)
        return _log_slices(design, self.coefficients)

    def information(self) -> np.ndarray:
        """J'WJ of the runs the law was fitted to (P, P): the inverse of its covariance,
        W = diag(1 / slice_sd^2)."""
        return np.linalg.pinv(self.covariance, hermitian=True)

    def covariance_after(self, gradients: np.ndarray) -> np.ndarray:
        """(..., P, P) the coefficients' covariance with one more run whose slices' log
        hold-ups have ``gradients`` (..., NX, P) (:meth:`gradient`) and lie on the law:
        pinv(J'WJ + G'WG), each slice weighted by its present scatter. Such a run leaves
        the coefficients where they are, so its information adds to the runs' exactly."""
        gradients = np.asarray(gradients, dtype=float)
        added = np.einsum("...ip,i,...iq->...pq", gradients, self.slice_sd**-2.0, gradients)
        return np.linalg.pinv(self.information() + added, hermitian=True)

    def record(self) -> dict[str, Any]:
        return {
            "half_width_m": self.half_width_m,
            "coefficients": self.coefficients.tolist(),
            "covariance": self.covariance.tolist(),
            "slice_sd": self.slice_sd.tolist(),
            "dof": self.dof,
            "pattern": self.pattern,
            "slice_dof": self.slice_dof.tolist(),
            "own_stations": list(self.own_stations),
            "layouts": None if self.layouts is None else self.layouts.record(),
        }

    @classmethod
    def from_record(cls, record: dict) -> ProfileLaw:
        law = cls(
            float(record["half_width_m"]),
            np.asarray(record["coefficients"], dtype=float),
            np.asarray(record["covariance"], dtype=float),
            np.asarray(record["slice_sd"], dtype=float),
            int(record["dof"]),
            str(record["pattern"]),
            np.asarray(record["slice_dof"], dtype=float),
            tuple(int(k) for k in record["own_stations"]),
            None if record.get("layouts") is None else LayoutShares.from_record(record["layouts"]),
        )
        p = n_coefficients(law.own_stations)
        if (
            law.coefficients.shape != (p,)
            or law.covariance.shape != (p, p)
            or law.slice_sd.ndim != 1
            or law.slice_dof.shape != law.slice_sd.shape
            or (law.layouts is not None and law.layouts.sd.shape != law.slice_sd.shape)
        ):
            raise ValueError(f"a profile law has {p} coefficients, their {p} x {p} covariance and one sd per slice")
        return law


def _gauss_newton(
    designs: Sequence[_Design], observed: np.ndarray, weights: np.ndarray, start: np.ndarray
) -> np.ndarray:
    """The coefficients of least weighted squared log misfit (NaN observations skipped)."""
    mask = np.isfinite(observed)

    def misfit(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        parts = [_log_slices(d, theta) for d in designs]
        residual = (np.array([p[0] for p in parts]) - observed) / weights
        jacobian = np.array([p[1] for p in parts]) / weights[None, :, None]
        return residual[mask], jacobian[mask]

    theta = start.copy()
    r, j = misfit(theta)
    cost = float(r @ r)
    for _ in range(ITERATIONS):
        step = np.linalg.lstsq(j, -r, rcond=None)[0]
        scale = 1.0
        while scale > 1e-6:
            trial = theta + scale * step
            r_new, j_new = misfit(trial)
            new = float(r_new @ r_new)
            if new <= cost:
                break
            scale /= 2.0
        else:
            break
        fall = cost - new
        theta, r, j, cost = trial, r_new, j_new, new
        if fall <= TOL * max(cost, 1e-300):
            break
    return theta


def _fit(
    designs: Sequence[_Design],
    observed: np.ndarray,
    half_width_m: float,
    pattern: str,
    own_stations: tuple[int, ...],
) -> tuple[ProfileLaw, float]:
    """The law at one swept half-width, and its Gaussian log-likelihood."""
    nx = observed.shape[1]
    mask = np.isfinite(observed)
    start = np.zeros(n_coefficients(own_stations))
    lengths = np.array([d.rows.shape[0] * d.step_m for d in designs])
    # the mean density of the slices observed: a run may lack any of its slices
    start[0 : -len(SHARED_TERMS) : len(ZONE_TERMS)] = math.log(
        float(np.nanmean(np.exp(observed) * nx / lengths[:, None]))
    )
    weights = np.ones(nx)
    theta = start
    for _ in range(WEIGHT_ROUNDS + 1):
        theta = _gauss_newton(designs, observed, weights, theta)
        parts = [_log_slices(d, theta) for d in designs]
        residual = np.array([p[0] for p in parts]) - observed
        jacobian = np.array([p[1] for p in parts])
        rank = np.linalg.matrix_rank(jacobian[mask] / weights[np.nonzero(mask)[1]][:, None])
        m = int(mask.sum())
        dof = m - rank
        if dof < 1:
            raise ConfigError(
                f"the slice profile law needs more slices than its {rank} identified coefficients; "
                f"the library gives {m}: add runs"
            )
        # each slice's scatter over its own degrees of freedom: its observations less
        # their leverage (the weir zone's coefficients are spent on the last slice alone)
        rows = np.nonzero(mask)[1]
        weighted = jacobian[mask] / weights[rows][:, None]
        leverage = np.einsum("ip,pq,iq->i", weighted, np.linalg.pinv(weighted.T @ weighted), weighted)
        free = np.bincount(rows, weights=1.0 - leverage, minlength=nx)
        per_slice = np.bincount(rows, weights=residual[mask] ** 2, minlength=nx)
        weights = np.sqrt(np.maximum(per_slice / np.maximum(free, 1e-3), 1e-12))
    weighted = jacobian[mask] / weights[np.nonzero(mask)[1]][:, None]
    covariance = np.linalg.pinv(weighted.T @ weighted)
    z = residual[mask] / weights[np.nonzero(mask)[1]]
    loglik = -0.5 * float(z @ z) - float(np.log(weights[np.nonzero(mask)[1]]).sum())
    return ProfileLaw(half_width_m, theta, covariance, weights, dof, pattern, free, own_stations), loglik


def fit_profile(
    points: Sequence[OperatingPoint],
    holdups: np.ndarray,
    pattern: str,
    half_widths_m: Sequence[float] = HALF_WIDTHS_M,
    own_stations: Sequence[int] = OWN_STATIONS,
    layouts: Sequence[str] | None = LAYOUT_TERMS,
) -> ProfileLaw:
    """The :class:`ProfileLaw` of the runs at ``points`` (their stations oriented by
    ``pattern``) whose slices held ``holdups`` (runs x slices; NaN or <= 0 where unknown),
    with swept zones of their own at ``own_stations``, at the swept half-width of
    ``half_widths_m`` with the greatest likelihood, and its misses at the layouts run in
    the terms ``layouts`` (:func:`fit_layouts`; None: the law alone). Raises ConfigError when the runs do not give the law
    a degree of freedom."""
    holdups = np.asarray(holdups, dtype=float)
    if holdups.ndim != 2 or holdups.shape[0] != len(points) or holdups.shape[1] < 1:
        raise ConfigError(
            f"slice hold-ups of shape {holdups.shape}: one row per run ({len(points)}), one column per slice"
        )
    observed = np.log(np.where(holdups > 0, holdups, np.nan))
    if not np.isfinite(observed).any():
        raise ConfigError("the runs give no slice hold-up: the slice profile law needs them")
    own = tuple(int(k) for k in own_stations)
    best: tuple[ProfileLaw, float] | None = None
    for half in half_widths_m:
        designs = [_design(p, pattern, half, own, holdups.shape[1]) for p in points]
        law, loglik = _fit(designs, observed, float(half), pattern, own)
        if best is None or loglik > best[1]:
            best = (law, loglik)
    law = best[0]
    return law if layouts is None else replace(law, layouts=fit_layouts(law, points, holdups, layouts))


def refit(law: ProfileLaw, points: Sequence[OperatingPoint], holdups: np.ndarray) -> ProfileLaw:
    """``law``'s form (its swept half-width, own stations, and its layouts' terms) fitted
    to other runs: the fits with one run left out keep the whole library's
    half-width, chosen once like the law's covariates."""
    terms = None if law.layouts is None else law.layouts.terms
    return fit_profile(points, holdups, law.pattern, (law.half_width_m,), law.own_stations, terms)


def without_layouts(law: ProfileLaw) -> ProfileLaw:
    """``law`` alone, without its misses at the layouts the library has run."""
    return replace(law, layouts=None)
