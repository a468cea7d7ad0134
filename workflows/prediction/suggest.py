"""The next DEM run of a library: the operating point that most narrows the prediction
intervals over the region that matters (``pbmdem library suggest``).

A prediction's 95 % interval on a quantity (:mod:`workflows.prediction.predict`) is the
correction line's, +- t(0.975, n - p) s sqrt(1 + x'(A'A)^-1 x): A the runs' correction
covariates, x the point's. One more run at a candidate point c adds the row x_c to A. Its
residual is unknown before the run, so s is expected to stay; what changes is known in
advance: the leverage of every point (A'A grows by x_c x_c'), the degrees of freedom (one
more: the t quantile drops, which matters most in a small library), and, in a library too
small for the correction's whole form, the covariates the runs identify (the form grows
once the runs allow it, :func:`~workflows.prediction.predict.fit_correction`).

The slices' hold-ups are judged as ``pbmdem predict`` gives them: when the library has a
zone law of its bed (:mod:`workflows.prediction.profile`, ``calibration.profile``), by it,
in place of their lines (:func:`profile_half_widths`). Slice i's half-width at a point is
then t(0.975, d_i) sqrt(s_i^2 + g_i' C g_i): g_i the gradient of its log hold-up in the
law's coefficients there, C = (J'WJ)^-1 their covariance, W = diag(1 / s_i^2), d_i the
slice's degrees of freedom (its observations less their leverage). A run at c whose
slices lie on the law leaves the coefficients where they are and adds its information:
C becomes (J'WJ + G_c'W G_c)^-1, G_c the gradients of its slices
(:meth:`~workflows.prediction.profile.ProfileLaw.covariance_after`); s_i is expected to
stay. Each d_i is taken to grow by one: the run adds one observation per slice and no
coefficient, so the leverages' sum stays and the law's degrees of freedom grow by exactly
one per slice, while how they share among the slices needs the refit itself (the refits
of synthetic slices in tests/workflows/prediction/test_suggest.py put each slice's growth
between 0.8 and 1.1). Counting only the new observation's own 1 - h_i instead would leave
out the leverage it takes off the runs before it, and so cut the gain most where the run
teaches the law most. Whatever their source, ``predict`` scales the slices to the predicted
hold-up, so each slice's half-width is then taken with the hold-up's interval in
quadrature (:func:`~workflows.prediction.predict.held_in_total`), now and after the run.
At a layout the library has run, the zone law takes its misses there
(:class:`~workflows.prediction.profile.LayoutShares`) and a slice's interval is its
layout's lines'; such a point keeps that interval whatever the candidate (one more run of
the layout would add a degree of freedom to its lines, which this rule leaves out).

The rule is I-optimal: per quantity the mean over the region's points of the squared
half-width, divided by the square of the quantity's target half-width
(:data:`~workflows.prediction.calibration.USEFUL_HALF_WIDTH`: 4 % of the mean residence
time and the hold-up, 15 % of the RTD variance, 8 % of each slice's hold-up), averaged over
the slices, then over the four targets (:func:`criterion`). The candidate that lowers it
most is suggested (:func:`rank`); its expected reduction is reported per quantity as the
median half-width over the region now and after the run (the targets are medians).

The line's leverage alone falls most where the runs reach the domain's ends, so on it
alone the rule piles run after run onto the corners. Where the line misses a curvature
(the shipped runs' spread about it is 2-20 times the DEM's scatter between seeds), that
curvature is largest there: the spread the runs measure, and every interval, come out
wider than the line's misses over the domain (``pbmdem study suggest``). When the library
measures its seed scatter (replicate runs), each squared half-width is therefore taken
with t^2 times the expected squared bias of the line at the point under a quadratic
discrepancy of the size the excess spread implies (:func:`_bias`), and its variance part
with the seed scatter instead of the spread: Box and Draper's mean squared error, least
where the runs' moments match the region's. The zone law's slices take no such term: it
is a discrepancy quadratic in a line's covariates, of the size of the line's spread beyond
the seed scatter, and the zone law is no such line; its scatter s_i is each slice's about
a law of the whole bed, and the law was chosen over the lines by the intervals of runs
left out (:func:`~workflows.prediction.calibration.calibrated`): what it misses from one
blender to another was scored there.

Last, each half-width is taken as ``pbmdem predict`` gives it
(:func:`~workflows.prediction.predict.corrected`): at least the library's floors (the
errors of its end runs left out, beyond the runs' hull; of its runs alone at their blade
layout, at a layout no run has) and widened by 1 + the point's distance from the hull
(:func:`least_bounds`). A library of one change at a time spans a star, so most of the
box of its ranges lies beyond the hull and most lengths at a layout no run has: there the
floors, not the line, set the intervals, and a run that brings a stretch of the box inside
the hull narrows them most. Over the shipped library's domain the median half-widths so
taken are about twice the line's alone (``pbmdem library suggest``'s page).

The region is the library's domain (each of speed, length and feed between its runs'
least and greatest) or a part of it (:func:`parse_region`); the candidates a grid over the
domain, optionally widened beyond its edges (:func:`widened`). A candidate of another
length keeps the base configuration's blade-station spacing and holds as many stations as
leave the library's least gap before the weir (:func:`config_at`), so its gap covariate is
the one its DEM run will have.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from scipy.special import stdtrit

from coupling.errors import ConfigError
from coupling.operating import OperatingPoint
from dem.operating import operating_point
from workflows.config import Config, config_from_dict
from workflows.prediction.calibration import USEFUL_HALF_WIDTH, seed_scatter
from workflows.prediction.covariates import AXIAL_SLICES
from workflows.prediction.library import (
    CORRECTION_TERMS,
    LibraryModel,
    correction_row,
    physics_of,
    quantity_keys,
    slice_key,
)
from workflows.prediction.predict import (
    LEVEL,
    Correction,
    Domain,
    Floors,
    correction_data,
    domain,
    fit_correction,
    floors,
    least_gap,
    model_domain,
    placement,
)
from workflows.prediction.profile import ProfileLaw, layout_of, same_layout

#: the region's axes, as the command line names them, and their units
AXES = {"speed": "rpm", "length": "m", "feed": "particles/s"}
#: the levels per axis of the region's points and of the candidates
REGION_LEVELS = 5
CANDIDATE_LEVELS = 7


def target_half_width(key: str) -> tuple[str, float] | None:
    """(the target's name, its half-width as a fraction of the value) of ``key``, None
    for a quantity without a target."""
    if key in USEFUL_HALF_WIDTH:
        return key, USEFUL_HALF_WIDTH[key]
    if key in {slice_key(i) for i in range(AXIAL_SLICES)}:
        return "holdup_slice", USEFUL_HALF_WIDTH["holdup_slice"]
    return None


# ------------------------------------------------------------------ the region
@dataclass(frozen=True)
class Region:
    """Ranges of impeller speed [rpm], barrel length [m] and total feed [particles/s]."""

    speed: tuple[float, float]
    length: tuple[float, float]
    feed: tuple[float, float]

    def __post_init__(self) -> None:
        for axis in AXES:
            low, high = getattr(self, axis)
            if not (0 < low <= high and math.isfinite(high)):
                raise ConfigError(f"region {axis} = {low}:{high}: need 0 < low <= high")

    def grid(self, levels: int) -> list[tuple[float, float, float]]:
        """(speed, length, feed) on ``levels`` evenly spaced logs per axis (one where the
        range is a single value)."""
        axes = [
            np.exp(np.linspace(math.log(low), math.log(high), levels if high > low else 1))
            for low, high in (self.speed, self.length, self.feed)
        ]
        return [(_round(s), _round(x), _round(f)) for s in axes[0] for x in axes[1] for f in axes[2]]

    def contains(self, speed: float, length: float, feed: float, tol: float = 1e-9) -> bool:
        return all(
            low * (1 - tol) <= v <= high * (1 + tol)
            for v, (low, high) in zip((speed, length, feed), (self.speed, self.length, self.feed))
        )

    def describe(self) -> str:
        return ", ".join(
            f"{axis} {low:.4g}-{high:.4g} {unit}" for axis, unit in AXES.items() for low, high in [getattr(self, axis)]
        )

    def record(self) -> dict[str, Any]:
        return {axis: list(getattr(self, axis)) for axis in AXES}


def _round(value: float) -> float:
    """Four significant digits: a configuration's values as a person would write them."""
    return float(f"{value:.4g}")


def domain_region(dom: Domain) -> Region:
    """The :class:`Region` of a library's :class:`~workflows.prediction.predict.Domain`."""
    return Region(*(dom.span(axis) for axis in ("speed", "length", "feed")))


def widened(region: Region, fraction: float) -> Region:
    """``region`` with each axis widened on both sides by ``fraction`` of its width in
    logs (a range of one value stays)."""
    if not fraction >= 0:
        raise ConfigError(f"--extend {fraction}: the widening must be >= 0 (a fraction of each axis' width)")

    def wide(low: float, high: float) -> tuple[float, float]:
        step = fraction * math.log(high / low)
        return low * math.exp(-step), high * math.exp(step)

    try:
        return Region(*(wide(*getattr(region, axis)) for axis in AXES))
    except (OverflowError, ConfigError):  # an axis beyond any float, or down to 0
        raise ConfigError(
            f"--extend {fraction:g} widens the domain ({region.describe()}) beyond any operating point"
        ) from None


def parse_region(text: str | None, span: Region) -> Region:
    """The region of ``text`` (``speed=200:300,length=0.33:0.41,feed=60``: any of the
    axes of :data:`AXES`, each a range low:high or one value, in their units), the axes
    it leaves out spanning ``span``; None or empty: ``span``. Raises ConfigError naming a
    bad part, or a range outside ``span``."""
    ranges = {axis: getattr(span, axis) for axis in AXES}
    if not text:
        return span
    seen = set()
    for part in text.split(","):
        axis, sep, value = (s.strip() for s in part.partition("="))
        if not sep or axis not in AXES:
            raise ConfigError(f"--region part {part!r}: expected AXIS=LOW:HIGH with AXIS one of {', '.join(AXES)}")
        if axis in seen:
            raise ConfigError(f"--region gives {axis} twice")
        seen.add(axis)
        try:
            numbers = [float(v) for v in value.split(":")]
        except ValueError:
            raise ConfigError(f"--region {axis}={value!r}: expected LOW:HIGH or one value, in {AXES[axis]}") from None
        if len(numbers) not in (1, 2) or not all(math.isfinite(v) and v > 0 for v in numbers):
            raise ConfigError(f"--region {axis}={value!r}: expected LOW:HIGH or one value, positive, in {AXES[axis]}")
        low, high = numbers[0], numbers[-1]
        if low > high:
            raise ConfigError(f"--region {axis}={value}: low {low:g} above high {high:g}")
        valid = getattr(span, axis)
        if low < valid[0] * (1 - 1e-9) or high > valid[1] * (1 + 1e-9):
            raise ConfigError(
                f"--region {axis}={value} leaves the candidates' span {valid[0]:.4g}-{valid[1]:.4g} {AXES[axis]} "
                "(the library's domain; --extend widens it)"
            )
        ranges[axis] = (low, high)
    return Region(**ranges)


# ------------------------------------------------------------------ a candidate's run
def config_at(
    base: Config, speed: float, length: float, feed: float, gap_m: float, duration_s: float | None = None
) -> Config:
    """``base`` run at ``speed`` [rpm], ``length`` [m] and total ``feed`` [particles/s]:
    its blade stations kept at their spacing from the first, as many as leave at least
    ``gap_m`` before the weir; the PBM's feed rates (when ``base`` states them) scaled
    with the feed; ``duration_s`` when given. Validated; ConfigError names what does not
    fit."""
    g = base.dem.geometry
    if g.blade_stations < 2:
        raise ConfigError(f"the base configuration has {g.blade_stations} blade station: no spacing to keep")
    spacing = (g.last_blade_x_m - g.first_blade_x_m) / (g.blade_stations - 1)
    stations = math.floor((length - gap_m - g.first_blade_x_m) / spacing + 1e-9) + 1
    if stations < 1:
        raise ConfigError(
            f"length {length:g} m holds no blade station {gap_m:g} m before the weir "
            f"(the first sits at {g.first_blade_x_m:g} m)"
        )
    data = base.to_dict()
    data["name"] = f"suggest-{speed:.4g}rpm-{length:.4g}m-{feed:.4g}per-s"
    data["dem"]["geometry"].update(
        length_m=length, blade_stations=stations, last_blade_x_m=g.first_blade_x_m + (stations - 1) * spacing
    )
    operation = data["dem"]["operation"]
    ratio = feed / base.dem.operation.feed_rate_total_per_s
    operation.update(impeller_rpm=speed, feed_rate_total_per_s=feed)
    if duration_s is not None:
        operation["duration_s"] = duration_s
    for name in ("feed_rate_a_per_s", "feed_rate_b_per_s"):
        if data["pbm"].get(name) is not None:
            data["pbm"][name] *= ratio
    return config_from_dict(data, f"the base configuration at {speed:g} rpm, {length:g} m, {feed:g} /s")


def point_at(base: Config, speed: float, length: float, feed: float, gap_m: float) -> OperatingPoint:
    """The operating point of :func:`config_at`."""
    return operating_point(config_at(base, speed, length, feed, gap_m).dem)


def scaled_duration(base_s: float, base_mean_s: float, mean_s: float, step_s: float = 10.0) -> float:
    """The base run's duration in units of its mean residence time, at a point whose mean
    residence time is ``mean_s`` (never shorter than the base's), rounded up to
    ``step_s``: the fill, the entry window and the pooled RTD's horizon all scale with it."""
    return step_s * math.ceil(base_s * max(1.0, mean_s / base_mean_s) / step_s - 1e-9)


# ------------------------------------------------------------------ the criterion
@dataclass(frozen=True)
class Quantity:
    """One quantity of a library: the runs' points and its residuals there (DEM less law,
    on its scale), what its correction line is fitted to."""

    key: str
    points: tuple[OperatingPoint, ...]
    residuals: tuple[float, ...]

    def usable(self) -> Quantity:
        keep = [(p, r) for p, r in zip(self.points, self.residuals) if math.isfinite(r)]
        return Quantity(self.key, tuple(p for p, _ in keep), tuple(r for _, r in keep))


def covariate_terms(points: Sequence[OperatingPoint], pattern: str = "") -> np.ndarray:
    """(N, 1 + len(CORRECTION_TERMS)) every correction covariate of each point, its
    stations oriented by ``pattern``; without a pattern the ``last`` column is NaN, so that
    a line using it has NaN half-widths rather than wrong ones."""
    if pattern:
        return np.array([correction_row(p, CORRECTION_TERMS, pattern) for p in points]).reshape(len(points), -1)
    names = tuple(n for n in CORRECTION_TERMS if n != "last")
    rows = np.full((len(points), 1 + len(CORRECTION_TERMS)), math.nan)
    if points:
        rows[:, term_columns(names)] = np.array([correction_row(p, names) for p in points])
    return rows


def term_columns(names: Sequence[str]) -> list[int]:
    """The columns of :func:`covariate_terms` that a line in ``names`` uses, the constant first."""
    return [0] + [1 + CORRECTION_TERMS.index(n) for n in names]


def _t(dof: int) -> float:
    return float(stdtrit(dof, 0.5 + LEVEL / 2)) if dof >= 1 else math.nan


def half_widths(line: Correction, terms: np.ndarray) -> np.ndarray:
    """The half-width of ``line``'s interval (:meth:`Correction.at`) at each row of
    ``terms`` (:func:`covariate_terms` of the points)."""
    x = terms[:, term_columns(line.names)]
    leverage = np.einsum("ij,jk,ik->i", x, line.inverse, x)
    return _t(line.dof) * np.sqrt(line.variance * (1.0 + leverage))


def after_run(
    line: Correction, points: Sequence[OperatingPoint], names: Sequence[str], candidate: OperatingPoint
) -> Correction:
    """``line`` as expected with one more run at ``candidate``: the form the runs then
    identify, their (A'A)^-1 and degrees of freedom, the residuals' variance unchanged."""
    grown = fit_correction([*points, candidate], [0.0] * (len(points) + 1), names, line.pattern)
    return replace(grown, coefficients=np.zeros(len(grown.names) + 1), variance=line.variance)


def _after_widths(
    line: Correction,
    points: Sequence[OperatingPoint],
    names: Sequence[str],
    candidates: Sequence[OperatingPoint],
    cand_terms: np.ndarray,
    region_terms: np.ndarray,
) -> np.ndarray:
    """(C, R) expected half-widths at the region's points after a run at each candidate.
    When the line has its whole form already, one more run cannot change the form and
    (A'A + x x')^-1 follows from Sherman-Morrison; otherwise the form is rebuilt
    (:func:`after_run`)."""
    if tuple(line.names) == tuple(names) and len(points) >= len(names) + 1:
        cols = term_columns(names)
        xr, xc, m = region_terms[:, cols], cand_terms[:, cols], line.inverse
        lev_r = np.einsum("ij,jk,ik->i", xr, m, xr)
        lev_c = np.einsum("ij,jk,ik->i", xc, m, xc)
        cross = xc @ m @ xr.T  # (C, R)
        leverage = lev_r[None, :] - cross**2 / (1.0 + lev_c)[:, None]
        return _t(line.dof + 1) * np.sqrt(line.variance * (1.0 + leverage))
    return np.array([half_widths(after_run(line, points, names, c), region_terms) for c in candidates])


def profile_half_widths(
    profile: ProfileLaw,
    region_points: Sequence[OperatingPoint],
    candidate_points: Sequence[OperatingPoint],
    pattern: str | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The half-widths of the zone law's slice intervals (log scale, :meth:`ProfileLaw.at`)
    at the region's points, (NX, R) now and (NX, C, R) expected after one more run at each
    candidate (module docstring): t(slice_dof_i) sqrt(s_i^2 + g_i' C g_i), then with the
    candidate's information added to C (:meth:`ProfileLaw.covariance_after`) and one more
    degree of freedom per slice. A point at a layout the library has run keeps its
    layout's interval (:class:`~workflows.prediction.profile.LayoutShares`) now and after."""
    region = np.array([profile.gradient(p, pattern)[1] for p in region_points])  # (R, NX, P)
    grown = profile.covariance_after(np.array([profile.gradient(p, pattern)[1] for p in candidate_points]))

    def spread(covariance: np.ndarray) -> np.ndarray:
        return np.maximum(np.sum((region @ covariance) * region, axis=2).T, 0.0)  # (NX, R)

    now = spread(profile.covariance)
    after = np.stack([spread(c) for c in grown], axis=1)
    s2 = (profile.slice_sd**2)[:, None]
    t_now = stdtrit(np.maximum(profile.slice_dof, 1e-3), 0.5 + LEVEL / 2)[:, None]
    t_after = stdtrit(profile.slice_dof + 1.0, 0.5 + LEVEL / 2)[:, None, None]
    now, after = t_now * np.sqrt(s2 + now), t_after * np.sqrt(s2[:, None] + after)
    if profile.layouts is not None:
        for r, point in enumerate(region_points):
            if profile.layouts.runs_at(point):
                half = profile.at(point, pattern)[1]
                now[:, r] = half
                after[:, :, r] = half[:, None]
    return now, after


def potential_terms(terms: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """(N, 6) the potential terms at the rows ``terms`` (:func:`covariate_terms`): the
    squares and products of log speed, log length and log feed, each scaled to -1..1 over
    the rows ``reference``, less their least-squares line in the three over ``reference``,
    and scaled to a range of 1 there (the convention of DuMouchel and Jones' potential
    terms, Technometrics 36 (1994) 37-47)."""
    cols = term_columns(("speed", "length", "feed"))[1:]
    low, high = reference[:, cols].min(axis=0), reference[:, cols].max(axis=0)
    width = np.where(high > low, high - low, 1.0)

    def quadratic(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        u = 2 * (rows[:, cols] - low) / width - 1
        a, b, c = u.T
        z = np.column_stack([a * a, b * b, c * c, a * b, a * c, b * c])
        return z, np.column_stack([np.ones(len(rows)), u])

    z_ref, x_ref = quadratic(reference)
    beta = np.linalg.lstsq(x_ref, z_ref, rcond=None)[0]
    rest = z_ref - x_ref @ beta
    spread = rest.max(axis=0) - rest.min(axis=0)
    spread = np.where(spread > 1e-12, spread, 1.0)
    z, x = quadratic(terms)
    return (z - x @ beta) / spread


def _bias(
    line: Correction, run_terms: np.ndarray, cand_terms: np.ndarray, region_terms: np.ndarray, pure_sd: float | None
) -> tuple[np.ndarray, np.ndarray] | None:
    """The expected squared bias of the line at the region's points, now (R,) and after a
    run at each candidate (C, R), on the quantity's scale; None when it is not estimable.

    The line's residual variance is the DEM's scatter between seeds (``pure_sd``, from
    replicate runs) plus what the line cannot follow. Taken as a quadratic discrepancy
    (:func:`potential_terms` Z over the region, each coefficient of variance v), the line
    fitted to the runs misses it at a region point r by (z_r - B'x_r) gamma, B = (X'X)^-1
    X'Z of the runs, of expected square v |z_r - B'x_r|^2; v follows from the spread now:
    s^2 = pure_sd^2 + v tr(Z'(I - H)Z) / (n - p). This bias is least where the runs' moments
    match the region's (Box and Draper's all-bias designs): without it the rule piles every
    run onto the domain's ends, where a curvature is largest, and the intervals measured
    there are wider than the line's misses over the domain."""
    if pure_sd is None or not pure_sd > 0 or line.variance <= pure_sd**2:
        return None
    cols = term_columns(line.names)
    x, z = run_terms[:, cols], potential_terms(run_terms, region_terms)
    xc, zc = cand_terms[:, cols], potential_terms(cand_terms, region_terms)
    xr, zr = region_terms[:, cols], potential_terms(region_terms, region_terms)
    n, p = x.shape
    m = np.linalg.pinv(x.T @ x)
    g = x.T @ z
    lack = (np.trace(z.T @ z) - np.trace(g.T @ m @ g)) / (n - p)
    if not lack > 1e-12:
        return None
    v = (line.variance - pure_sd**2) / lack
    now = v * np.sum((zr - xr @ (m @ g)) ** 2, axis=1)
    mx = xc @ m  # (C, p)
    m_c = m[None] - mx[:, :, None] * mx[:, None, :] / (1.0 + np.einsum("ij,ij->i", mx, xc))[:, None, None]
    b_c = np.einsum("cpq,cqk->cpk", m_c, g[None] + xc[:, :, None] * zc[:, None, :])  # (C, p, 6)
    after = v * np.sum((zr[None] - np.einsum("rp,cpk->crk", xr, b_c)) ** 2, axis=2)
    return now, after


def criterion(widths: dict[str, np.ndarray]) -> np.ndarray:
    """The I-optimal criterion of half-widths (key -> (..., R) at the region's points):
    per target the mean over its quantities and the points of (half-width / target)^2,
    averaged over the targets; quantities without a target or without an interval are
    left out."""
    groups: dict[str, list[np.ndarray]] = {}
    for key, h in widths.items():
        target = target_half_width(key)
        if target is not None and np.all(np.isfinite(h)):
            groups.setdefault(target[0], []).append(np.mean((h / target[1]) ** 2, axis=-1))
    if not groups:
        raise ConfigError("no quantity with a target has a prediction interval yet: the library needs more runs")
    return np.mean([np.mean(parts, axis=0) for parts in groups.values()], axis=0)


@dataclass(frozen=True)
class Reduction:
    """One quantity's median half-width over the region [fraction of the value], now and
    expected after the suggested run, and its target."""

    key: str
    target: float
    now: float
    after: float

    def record(self) -> dict[str, Any]:
        return {"key": self.key, "target": self.target, "now": self.now, "after": self.after}


@dataclass(frozen=True)
class Suggestion:
    """A candidate run: its speed [rpm], length [m] and total feed [particles/s], its
    operating point, the criterion now and expected after it (:func:`criterion`), each
    target quantity's :class:`Reduction`, the region the criterion is taken over, and
    whether the point lies outside the library's domain."""

    speed: float
    length: float
    feed: float
    point: OperatingPoint
    criterion_now: float
    criterion_after: float
    reductions: tuple[Reduction, ...]
    region: Region
    outside_domain: bool
    #: the correction covariates the library identifies once it holds this run: its
    #: intervals are then those of the larger form, which may be wider where the new
    #: coefficient is uncertain (the residuals' spread is taken as it is now)
    gains: tuple[str, ...] = ()

    @property
    def relative_reduction(self) -> float:
        return 1.0 - self.criterion_after / self.criterion_now

    def record(self) -> dict[str, Any]:
        return {
            "speed_rpm": self.speed,
            "length_m": self.length,
            "feed_per_s": self.feed,
            "criterion_now": self.criterion_now,
            "criterion_after": self.criterion_after,
            "relative_reduction": self.relative_reduction,
            "reductions": [r.record() for r in self.reductions],
            "region": self.region.record(),
            "outside_domain": self.outside_domain,
            "gains": list(self.gains),
        }


@dataclass(frozen=True)
class Candidate:
    speed: float
    length: float
    feed: float
    point: OperatingPoint


@dataclass(frozen=True)
class Least:
    """What bounds a prediction's interval from below and widens it, as ``pbmdem predict``
    applies it (:meth:`~workflows.prediction.predict.Floors.at`): the library's ``floors``
    and its ``runs``, whose hull and blade layouts place a point against them, their
    stations oriented by ``pattern``."""

    floors: Floors
    runs: tuple[OperatingPoint, ...]
    pattern: str = ""


@dataclass(frozen=True)
class Bounds:
    """Per quantity, the least half-width at each region point (``floor``, key -> (..., R))
    and each point's widening (``widening``, (..., R)): now, or after each candidate's run
    (a leading candidate axis)."""

    floor: dict[str, np.ndarray]
    widening: np.ndarray

    def applied(self, key: str, half: np.ndarray) -> np.ndarray:
        """``half`` at least the floor, times the widening (:func:`~workflows.prediction.predict.corrected`)."""
        return np.maximum(half, self.floor.get(key, 0.0)) * self.widening


def _beyond_others(points: Sequence[OperatingPoint], n: int, pattern: str) -> bool:
    """Whether ``points[n]`` lies beyond the other points' hull or ranges: left out, an end
    run (:func:`~workflows.prediction.predict.end_runs`)."""
    others = [p for m, p in enumerate(points) if m != n]
    return placement(domain(others, pattern), points[n], pattern).extrapolated


def _lone(points: Sequence[OperatingPoint], ends: set[int]) -> int:
    """How many of ``points`` lie inside the others' hull (not in ``ends``) at a blade
    layout no other point has (:func:`~workflows.prediction.predict.lone_layout_runs`)."""
    layouts = [layout_of(p) for p in points]
    return sum(n not in ends and sum(same_layout(a, layouts[n]) for a in layouts) == 1 for n in range(len(points)))


def _t_ratio(now: int, after: int) -> float:
    """How a floor of t(0.975, m) times a root mean square error moves when its m errors
    become ``after`` (the mean square expected to stay); 0 once none is left."""
    if now < 1 or after < 1:
        return 0.0 if after < 1 else 1.0
    return float(stdtrit(after, 0.5 + LEVEL / 2) / stdtrit(now, 0.5 + LEVEL / 2))


def _placed(
    dom: Domain, ends: dict[str, float], layout: dict[str, float], points, pattern: str, every_layout_new: bool
) -> Bounds:
    """The :class:`Bounds` at ``points`` in ``dom``, the floors ``ends`` and ``layout``;
    every point at a layout no run has if ``every_layout_new``."""
    places = [placement(dom, p, pattern) for p in points]
    if every_layout_new:
        places = [replace(q, new_layout=True) for q in places]
    least = [Floors(ends, layout).at(q) for q in places]
    floor = {k: np.array([at.get(k, 0.0) for at in least]) for k in ends.keys() | layout.keys()}
    return Bounds(floor, np.array([q.widening for q in places]))


def least_bounds(
    least: Least, region: Region, region_points: Sequence[OperatingPoint], candidates: Sequence[OperatingPoint]
) -> tuple[Bounds, Bounds]:
    """The :class:`Bounds` at the region's points now and expected after one more run at
    each candidate. The run joins the hull: a point it brings inside loses the extrapolation
    floor's share and the widening beyond the hull. Each floor's mean square error is
    expected to stay, its count of runs to change as the run changes which runs are ends
    and which are alone at their layout (t(0.975, m) of the new count). A blade layout is
    a length to the micrometre, so over a region of lengths almost every point is at a
    layout no run has: each keeps the layout floor, and a run's own length does not take
    it off the region's points that happen to share it (an accident of the grids); a
    region of one length is placed as it is."""
    runs, pattern = list(least.runs), least.pattern
    continuous = region.length[1] > region.length[0]
    ends_now = {n for n in range(len(runs)) if _beyond_others(runs, n, pattern)}
    lone_now = _lone(runs, ends_now)
    now_domain = domain(runs, pattern)
    now = _placed(now_domain, least.floors.ends, least.floors.layout, region_points, pattern, continuous)
    floor_after = {k: np.zeros((len(candidates), len(region_points))) for k in now.floor}
    widening_after = np.ones((len(candidates), len(region_points)))
    for c, point in enumerate(candidates):
        grown = [*runs, point]
        ends = {e for e in ends_now if _beyond_others(grown, e, pattern)}
        if placement(now_domain, point, pattern).extrapolated:
            ends.add(len(runs))
        ratio_ends, ratio_layout = _t_ratio(len(ends_now), len(ends)), _t_ratio(lone_now, _lone(grown, ends))
        after = _placed(
            domain(grown, pattern),
            {k: v * ratio_ends for k, v in least.floors.ends.items()},
            {k: v * ratio_layout for k, v in least.floors.layout.items()},
            region_points,
            pattern,
            continuous,
        )
        for key, values in after.floor.items():
            floor_after[key][c] = values
        widening_after[c] = after.widening
    return now, Bounds(floor_after, widening_after)


def _with_total(half: np.ndarray, total: np.ndarray | None) -> np.ndarray:
    """A slice's half-width ``half`` with the hold-up's ``total`` in quadrature, as
    ``pbmdem predict`` gives it; alone without a hold-up interval."""
    return half if total is None else np.hypot(half, total)


def rank(
    quantities: Sequence[Quantity],
    names: Sequence[str],
    region: Region,
    region_points: Sequence[OperatingPoint],
    candidates: Sequence[Candidate],
    domain: Region | None = None,
    pure_sd: dict[str, float] | None = None,
    pattern: str = "",
    profile: ProfileLaw | None = None,
    least: Least | None = None,
) -> list[Suggestion]:
    """Every candidate as a :class:`Suggestion`, the one that lowers the criterion over
    ``region_points`` most first (module docstring); ``names`` the correction's form,
    ``domain`` the library's (to label candidates outside it); ``pure_sd`` per quantity
    the DEM's scatter between seeds on its scale (:func:`_bias`; None: the line's
    intervals alone); ``pattern`` the blade pattern of every point's stations (needed by a
    form with ``last``); ``profile`` the slices' zone law, which then judges the slices
    in place of their lines (:func:`profile_half_widths`); ``least`` the library's floors
    and runs, which bound every interval from below and widen it beyond the runs' hull
    (:func:`least_bounds`; None: neither)."""
    if not candidates or not region_points:
        raise ConfigError("no candidate or no region point to rank")
    region_terms = covariate_terms(region_points, pattern)
    cand_terms = covariate_terms([c.point for c in candidates], pattern)
    now: dict[str, np.ndarray] = {}  # the line's half-widths, reported
    after: dict[str, np.ndarray] = {}
    ranked_now: dict[str, np.ndarray] = {}  # with the expected bias, ranked on
    ranked_after: dict[str, np.ndarray] = {}
    zoned = [slice_key(i) for i in range(profile.nx)] if profile is not None else []
    for q in quantities:
        q = q.usable()
        if target_half_width(q.key) is None or not q.points or q.key in zoned:
            continue
        line = fit_correction(q.points, q.residuals, names, pattern)
        if line.dof < 1 or not math.isfinite(line.variance):
            continue
        now[q.key] = half_widths(line, region_terms)
        after[q.key] = _after_widths(line, q.points, names, [c.point for c in candidates], cand_terms, region_terms)
        ranked_now[q.key], ranked_after[q.key] = now[q.key], after[q.key]
        bias = None
        if pure_sd is not None and tuple(line.names) == tuple(names):
            bias = _bias(line, covariate_terms(q.points, pattern), cand_terms, region_terms, pure_sd.get(q.key))
        if bias is not None:
            # Box and Draper's mean squared error: the variance of the DEM's scatter between
            # seeds (not the residuals' spread, which holds the bias the design measures) and
            # the expected squared bias, in units of the interval (t^2)
            pure = pure_sd[q.key] ** 2 / line.variance
            ranked_now[q.key] = np.sqrt(pure * now[q.key] ** 2 + _t(line.dof) ** 2 * bias[0])
            ranked_after[q.key] = np.sqrt(pure * after[q.key] ** 2 + _t(line.dof + 1) ** 2 * bias[1])
    if profile is not None:
        # no bias term: the zone law's scatter is measured about a law that carries the
        # bed from blender to blender, and chosen over the lines on runs left out
        halves = profile_half_widths(profile, region_points, [c.point for c in candidates], pattern or None)
        for key, h_now, h_after in zip(zoned, *halves):
            now[key] = ranked_now[key] = h_now
            after[key] = ranked_after[key] = h_after
    if least is not None:
        bounds_now, bounds_after = least_bounds(least, region, region_points, [c.point for c in candidates])
        for key in list(now):
            now[key], ranked_now[key] = bounds_now.applied(key, now[key]), bounds_now.applied(key, ranked_now[key])
            after[key] = bounds_after.applied(key, after[key])
            ranked_after[key] = bounds_after.applied(key, ranked_after[key])
    # whatever their source, the slices are scaled to the predicted hold-up, its interval's
    # half-width in quadrature with theirs (predict.held_in_total): the hold-up's interval,
    # not its bias term, which is the ranking's own
    total_now, total_after = now.get("holdup"), after.get("holdup")
    for key in [slice_key(i) for i in range(AXIAL_SLICES) if slice_key(i) in now]:
        now[key], ranked_now[key] = _with_total(now[key], total_now), _with_total(ranked_now[key], total_now)
        after[key], ranked_after[key] = (
            _with_total(after[key], total_after),
            _with_total(ranked_after[key], total_after),
        )
    gains = [()] * len(candidates)
    widest = max((q.usable() for q in quantities), key=lambda q: len(q.points))
    line = fit_correction(widest.points, widest.residuals, names, pattern)
    if tuple(line.names) != tuple(names):
        gains = [
            tuple(n for n in after_run(line, widest.points, names, c.point).names if n not in line.names)
            for c in candidates
        ]
    score_now = float(criterion(ranked_now))
    scores = criterion(ranked_after)
    # a run that lets the line identify more of its form comes first: until the form is
    # whole its intervals are the smaller form's, narrower by what that form cannot see
    # (e.g. the last station's orientation on runs of two lengths), a bias the criterion
    # cannot weigh; among such runs, and then among the others, the criterion ranks
    order = np.lexsort((scores, [0 if g else 1 for g in gains]))
    out = []
    for c in order:
        candidate = candidates[c]
        reductions = tuple(
            Reduction(key, target_half_width(key)[1], float(np.median(now[key])), float(np.median(after[key][c])))
            for key in now
        )
        outside = domain is not None and not domain.contains(candidate.speed, candidate.length, candidate.feed)
        out.append(
            Suggestion(
                candidate.speed,
                candidate.length,
                candidate.feed,
                candidate.point,
                score_now,
                float(scores[c]),
                reductions,
                region,
                outside,
                gains[c],
            )
        )
    return out


# ------------------------------------------------------------------ a library's next run
def library_quantities(model: LibraryModel) -> list[Quantity]:
    """The target quantities of a calibrated library: each run's residual from the whole
    library's law (what :func:`~workflows.prediction.predict.predict` corrects by)."""
    if model.calibration is None:
        raise ConfigError("the library model has no calibration: make it with `pbmdem library fit`")
    out = []
    for key in quantity_keys():
        if key in model.calibration.whole and target_half_width(key) is not None:
            points, residuals = correction_data(model, key)
            out.append(Quantity(key, tuple(points), tuple(residuals)))
    return out


def candidates_over(base: Config, span: Region, gap_m: float, levels: int = CANDIDATE_LEVELS) -> list[Candidate]:
    """The grid of ``span`` (``levels`` per axis), each point run from ``base``
    (:func:`point_at`)."""
    return [Candidate(s, x, f, point_at(base, s, x, f, gap_m)) for s, x, f in span.grid(levels)]


def suggest(model: LibraryModel, base: Config, region: str | None = None, extend: float = 0.0) -> list[Suggestion]:
    """The candidates for ``model``'s next run, best first (:func:`rank`): a grid over
    the library's domain widened by ``extend`` (:func:`widened`), each run from ``base``;
    the criterion over ``region`` (:func:`parse_region`, within the candidates' span;
    default the library's domain, not widened)."""
    points = [r.point for r in model.runs]
    library_domain = model_domain(model)
    dom = domain_region(library_domain)
    gap = least_gap(points)
    # the base moved to a point of the domain: only what the law does not vary is left to differ
    inside = point_at(base, dom.speed[0], dom.length[0], dom.feed[0], gap)
    fixed = placement(library_domain, inside, base.dem.geometry.blade_pattern, physics_of(base.dem)).issues
    if fixed:
        raise ConfigError(
            f"the base configuration differs from the library's runs in what its law does not vary: "
            f"{'; '.join(fixed)}; its runs would not belong to this library"
        )
    span = widened(dom, extend)
    chosen = parse_region(region, span) if region else dom
    region_points = [point_at(base, s, x, f, gap) for s, x, f in chosen.grid(REGION_LEVELS)]
    names = model.calibration.covariates if model.calibration is not None else ()
    scatter = seed_scatter(model).sd or None
    try:
        candidates = candidates_over(base, span, gap)
    except ConfigError as exc:
        if not extend:
            raise
        raise ConfigError(f"--extend {extend:g} reaches candidates no blender can run: {exc}") from None
    profile = model.calibration.profile if model.calibration is not None else None
    least = Least(floors(model), tuple(points), model.blade_pattern)
    return rank(
        library_quantities(model),
        names,
        chosen,
        region_points,
        candidates,
        dom,
        scatter,
        model.blade_pattern,
        profile,
        least,
    )
