"""Design on the library's law: the operating points (speed, length, feed) that meet a spec,
each with the probability that it does, without a DEM or PBM run.

A spec (:class:`DesignSpec`) bounds what a blender delivers at steady state: its mean
residence time and hold-up within windows, and its outlet composition under a noisy feeder
(C_A within +-``ca_tolerance`` for ``coverage_sigmas`` standard deviations, and/or its RSD
below ``rsd_max``, for a feeder whose rate fluctuates with relative SD ``noise_sigma``,
correlation time ``noise_tau_s``, bandwidth ``noise_band_hz``). The outlet's SD is
C (1 - C) sigma / sqrt(VRR) (:mod:`pbm.frequency`).

Every quantity comes from the prediction of :mod:`workflows.prediction.predict`, evaluated
only as far as the spec needs it (:func:`evaluate`): the law's axial chain at the point
(the transverse moves change neither the hold-up nor the time to discharge), its steady
hold-up and mean residence time (of a library timed by the slices' zone law, the zone law's
total and that total over the feed: :func:`~workflows.prediction.predict.timed`) corrected by
the library's lines, each with its t prediction interval. The feeder-noise VRR and the step response are those of the chain
``predict`` writes for the PBM (each slice's time scale set to the predicted slice hold-ups,
:func:`~workflows.prediction.predict.rescaled`), its time scale stretched so that its mean
residence time is the predicted one; their intervals are that chain stretched to the mean
residence time's interval ends (:func:`noise_vrr`, :func:`step_response`). The chain's
shape is the law's: only its time scale is uncertain here, which is what the library's
runs calibrate (the mean residence time's line); a spread of shapes between the runs left
out is not added. It is the chain the PBM's validated rate mode (``phases``) runs on
``predict``'s table: ``design`` answers for the mode that ``pbmdem validate`` judged.

The probability that the spec is met at a point (:func:`joint_probability`): on each
quantity's scale (log) the prediction is value + scale T, T Student's t with the line's
degrees of freedom, scale the interval's half-width over t(0.975) (so the probability and
the printed interval agree). The residence-time and composition criteria are all functions
of the one mean-residence-time variable (the composition through the stretched chain's
VRR), so their joint probability is the t mass of the set where they all hold (the
composition's margin tabulated at :data:`T_NODES`, linear between: no independence
assumed). The
hold-up is a second variable; the two are taken as bivariate t with the correlation of the
two lines' residuals at the library's runs (:func:`residual_correlation`; 0.77 on the
shipped library: the DEM's hold-up and its residence time miss the law together), and the
rectangle's probability is integrated by Gauss-Legendre over the first, the second's
conditional law being t with one degree of freedom more. When the two lines' degrees of
freedom differ the smaller is used for both (heavier tails: a lower probability).

The search (:func:`design`) evaluates the spec's box in speed x length x feed (the
library's domain by default; a box leaving it is refused in one line naming the domain,
unless ``extrapolate``, when each point's interval is widened as ``predict`` widens it) on a
grid, then refines the two answers between their grid neighbours: the shortest blender,
and the largest feed, with P(spec met) >= ``confidence``. A blender of another length keeps
the library's blade-station spacing from its first station, with as many stations as leave
the library's smallest gap before the weir (:func:`design_point`): the library's lengths
were built so.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, fields, replace
from typing import Any, Literal, NamedTuple

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator
from scipy.special import stdtr, stdtrit

from coupling.errors import ConfigError
from coupling.operating import OperatingPoint
from coupling.phases import transitions
from dem.phases.law import PhaseLaw, law_rates
from pbm.frequency import StationarySystem, noise_frequencies, noise_spectrum, system_response, vrr_spectrum
from workflows.pipeline.results import VALIDATED_RATES
from workflows.prediction.covariates import (
    AXIAL_SLICES,
    run_covariates,
)
from workflows.prediction.library import LibraryModel, covariate_columns, slice_key
from workflows.prediction.predict import (
    LEVEL,
    Correction,
    Domain,
    Floors,
    PredictedQuantity,
    corrected,
    corrections,
    entering,
    floors,
    model_domain,
    placement,
    residual,
    stations_for,
)

MRT = "mean_residence_time_s"
HOLDUP = "holdup"
#: grid points per axis of the search: speed, length, feed (each answer is then refined
#: between it and its grid neighbour, :data:`REFINE_POINTS`)
GRID = (5, 7, 5)
#: speeds x lengths of the finer region at the shortest blender's feed, the figure's
REGION = (13, 17)
#: points of each answer's refinement between its grid neighbours
REFINE_POINTS = 8
#: frequencies of the VRR quadrature: on the law's 40-state axial chain 201 log-spaced
#: points hold the VRR within 0.1 % of 2001 (tests)
N_FREQUENCIES = 201
#: t values at which the composition's margin is tabulated for its probability (linear
#: between: the margin is smooth in t, tests): beyond +-12 the t law with the library's 10
#: degrees of freedom holds < 1e-6
T_NODES = np.linspace(-12.0, 12.0, 13)
#: frequencies of the one log grid every point's stretched transfer function is read off
#: (:func:`evaluate_many`): the VRR within 0.1 % of the direct response's (tests)
TRANSFER_POINTS = 300
#: P(spec met) of the residence time and hold-up alone below which a point's composition
#: is not judged (it cannot raise it)
SPARED_BELOW = 1e-9
#: Gauss-Legendre nodes of the bivariate t rectangle
GAUSS_NODES = 48
#: the step of feeder A's rate the step response answers (the validation's step check)
STEP_FACTOR_A = 2.0
#: the step response's times, in mean residence times
STEP_SPAN = 5.0
STEP_POINTS = 200


# ------------------------------------------------------------------ the spec
class Noise(NamedTuple):
    """A feeder's rate noise, first order (:func:`pbm.frequency.noise_spectrum`): its
    correlation time [s] (0: white), bandwidth [Hz] and feeder."""

    tau_s: float = 0.0
    band_hz: float = 0.5
    feeder: str = "A"


class DesignSpec(BaseModel):
    """What the blender must deliver, the feeder noise it is judged under, and the box of
    operating points searched (default: the library's domain)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    ca_tolerance: float | None = Field(None, gt=0, lt=1, description="outlet C_A within +- this (absolute fraction)")
    coverage_sigmas: float = Field(3.0, gt=0, description="standard deviations of C_A that must fit in the tolerance")
    rsd_max: float | None = Field(None, gt=0, description="largest relative SD of the outlet C_A")
    noise_sigma: float = Field(0.0, ge=0, description="relative SD of the noisy feeder's rate")
    noise_tau_s: float = Field(0.0, ge=0, description="correlation time of the feeder noise [s] (0: white)")
    noise_band_hz: float = Field(0.5, gt=0, description="the feeder noise's bandwidth [Hz]")
    noise_feeder: Literal["A", "B"] = "A"
    mrt_min_s: float | None = Field(None, gt=0, description="shortest acceptable mean residence time [s]")
    mrt_max_s: float | None = Field(None, gt=0, description="longest acceptable mean residence time [s]")
    holdup_min: float | None = Field(None, gt=0, description="least acceptable hold-up [particles]")
    holdup_max: float | None = Field(None, gt=0, description="largest acceptable hold-up [particles]")
    rpm_min: float | None = Field(None, gt=0, description="lowest impeller speed searched (default: the library's)")
    rpm_max: float | None = Field(None, gt=0, description="highest impeller speed searched (default: the library's)")
    length_min_m: float | None = Field(None, gt=0, description="shortest blender searched [m] (default: the library's)")
    length_max_m: float | None = Field(None, gt=0, description="longest blender searched [m] (default: the library's)")
    feed_min_per_s: float | None = Field(None, gt=0, description="lowest total feed searched [particles/s]")
    feed_max_per_s: float | None = Field(None, gt=0, description="highest total feed searched [particles/s]")
    confidence: float = Field(0.95, gt=0, lt=1, description="least P(spec met) of an answer")

    @model_validator(mode="after")
    def _consistent(self) -> DesignSpec:
        if not self.criteria:
            raise ValueError(
                "give at least one criterion: ca_tolerance, rsd_max, mrt_min_s, mrt_max_s, holdup_min or holdup_max"
            )
        if self.composition and self.noise_sigma <= 0:
            raise ValueError("a composition criterion (ca_tolerance, rsd_max) needs the feeder noise: noise_sigma > 0")
        for low, high in (
            ("mrt_min_s", "mrt_max_s"),
            ("holdup_min", "holdup_max"),
            ("rpm_min", "rpm_max"),
            ("length_min_m", "length_max_m"),
            ("feed_min_per_s", "feed_max_per_s"),
        ):
            a, b = getattr(self, low), getattr(self, high)
            if a is not None and b is not None and a > b:
                raise ValueError(f"{low} ({a}) must be <= {high} ({b})")
        return self

    @property
    def noise(self) -> Noise:
        return Noise(self.noise_tau_s, self.noise_band_hz, self.noise_feeder)

    @property
    def composition(self) -> bool:
        return self.ca_tolerance is not None or self.rsd_max is not None

    @property
    def criteria(self) -> tuple[str, ...]:
        """The margins a point is judged on, by name (:class:`Margin`)."""
        names = ("mrt_min_s", "mrt_max_s", "holdup_min", "holdup_max", "ca_tolerance", "rsd_max")
        return tuple(name for name in names if getattr(self, name) is not None)


def design_spec(names: Mapping[str, str] | None = None, **values: Any) -> DesignSpec:
    """A validated :class:`DesignSpec`; ConfigError names the bad value, each field by its
    name in ``names`` (the command line's flags) where it has one."""
    try:
        return DesignSpec(**values)
    except ValidationError as exc:
        problems = "; ".join(
            f"{'.'.join(map(str, e['loc']))} = {e['input']!r}: {e['msg']}" if e["loc"] else e["msg"]
            for e in exc.errors()
        ).replace("Value error, ", "")
        for field_name, shown in (names or {}).items():
            problems = re.sub(rf"\b{field_name}\b", shown, problems)
        raise ConfigError(f"design spec: {problems}") from None


# ------------------------------------------------------------------ the law at a point
@dataclass(frozen=True)
class Surrogate:
    """What a design evaluates points with: the library model, its correction lines, the
    correlation of the hold-up's and the residence time's residuals at the runs, the
    domain, the point every searched point is made from and the runs' blade stations
    (:func:`design_point`, :func:`~workflows.prediction.predict.station_rule`), and the least half-widths beyond the
    runs and at a blade layout no run has (:class:`~workflows.prediction.predict.Floors`)."""

    model: LibraryModel
    lines: dict[str, Correction]
    correlation: float
    domain: Domain
    base: OperatingPoint
    rule: tuple[float, float, float]
    extrapolate: bool = False
    floors: Floors = field(default_factory=lambda: Floors({}, {}))

    @property
    def pattern(self) -> str:
        return self.model.blade_pattern


def residual_correlation(model: LibraryModel, lines: dict[str, Correction], a: str, b: str) -> float:
    """The correlation of the residuals of quantities ``a`` and ``b`` about their lines at
    the library's runs that hold both (0 with fewer than three)."""
    calibration = model.calibration
    pairs = []
    for j, entry in enumerate(model.runs):
        if a in entry.dem and b in entry.dem and a in calibration.whole and b in calibration.whole:
            ra = residual(a, entry.dem[a].value, calibration.whole[a][j])
            rb = residual(b, entry.dem[b].value, calibration.whole[b][j])
            ra -= lines[a].at(entry.point)[0]
            rb -= lines[b].at(entry.point)[0]
            if math.isfinite(ra) and math.isfinite(rb):
                pairs.append((ra, rb))
    if len(pairs) < 3:
        return 0.0
    x = np.array(pairs)
    return float(np.corrcoef(x[:, 0], x[:, 1])[0, 1])


def surrogate(model: LibraryModel, extrapolate: bool = False) -> Surrogate:
    """The :class:`Surrogate` of ``model`` (ConfigError without a calibration). The base
    point is the library's run nearest the domain's centre."""
    lines = corrections(model)
    for key in (MRT, HOLDUP):
        if key not in lines:
            raise ConfigError(f"the library model's calibration has no {key}: a design needs it")
    dom = model_domain(model)
    centre = {axis: sum(bounds) / 2 for axis, bounds in dom.ranges.items()}
    base = min(
        (r.point for r in model.runs),
        key=lambda p: sum((run_covariates(p)[axis] - centre[axis]) ** 2 for axis in centre),
    )
    rule = dom.stations
    if rule is None:
        raise ConfigError("the library's runs have no two blade stations: a design has no spacing to keep")
    correlation = residual_correlation(model, lines, MRT, HOLDUP)
    return Surrogate(model, lines, correlation, dom, base, rule, extrapolate, floors(model))


def design_point(
    base: OperatingPoint, rule: tuple[float, float, float], rpm: float, length_m: float, feed_per_s: float
) -> OperatingPoint:
    """``base`` at ``rpm``, ``length_m`` and a total feed of ``feed_per_s`` (its A share
    kept), its blade stations at ``rule``'s spacing from the first, as many as leave at
    least ``rule``'s gap before the weir (:func:`~workflows.prediction.predict.station_rule`). Raises ConfigError for a
    blender too short for one station."""
    first, spacing, gap = rule
    count = stations_for(rule, length_m)
    if count < 1:
        raise ConfigError(
            f"a {length_m:g}-m blender is too short for a blade station at {first:g} m and a {gap:g}-m gap to the weir"
        )
    share = base.feed_rate_a_per_s / base.feed_rate_total_per_s
    return replace(
        base,
        impeller_rpm=float(rpm),
        length_m=float(length_m),
        blade_x_m=tuple(first + k * spacing for k in range(count)),
        feed_rate_a_per_s=float(feed_per_s) * share,
        feed_rate_b_per_s=float(feed_per_s) * (1 - share),
    )


# ------------------------------------------------------------------ one point
@dataclass(frozen=True)
class Band:
    """A value and its 95 % interval."""

    value: float
    low: float
    high: float

    def record(self) -> dict[str, float]:
        return {"value": self.value, "low": self.low, "high": self.high}


@dataclass(frozen=True)
class Margin:
    """One criterion at a point: the margin (positive: met, in the criterion's unit) with
    its 95 % interval, and the probability that it is met."""

    name: str
    margin: Band
    probability: float

    def record(self) -> dict[str, Any]:
        return {"name": self.name, **self.margin.record(), "probability": self.probability}


@dataclass(frozen=True)
class PointDesign:
    """One operating point: the predicted mean residence time and hold-up, the outlet's
    VRR and C_A SD under the spec's noise (None without a composition criterion), every
    margin, P(spec met), and what lies outside the library's domain."""

    point: OperatingPoint
    mrt: PredictedQuantity
    holdup: PredictedQuantity
    vrr: Band | None
    ca_sd: Band | None
    margins: tuple[Margin, ...]
    probability: float
    outside: tuple[str, ...]

    @property
    def length_m(self) -> float:
        return self.point.length_m

    @property
    def feed_per_s(self) -> float:
        return self.point.feed_rate_total_per_s

    def record(self) -> dict[str, Any]:
        return {
            "rpm": self.point.impeller_rpm,
            "length_m": self.point.length_m,
            "feed_per_s": self.feed_per_s,
            "blade_stations": len(self.point.blade_x_m),
            "mean_residence_time_s": self.mrt.record(),
            "holdup": self.holdup.record(),
            "vrr": None if self.vrr is None else self.vrr.record(),
            "ca_sd": None if self.ca_sd is None else self.ca_sd.record(),
            "margins": [m.record() for m in self.margins],
            "probability": self.probability,
            "outside_domain": list(self.outside),
        }


def t_scale(q: PredictedQuantity) -> float:
    """The scale of ``q``'s t law on its (log) scale: its interval's half-width over the t
    quantile (0 without an interval)."""
    t = float(stdtrit(q.correction.dof, 0.5 + LEVEL / 2)) if q.correction.dof >= 1 else math.nan
    half = math.log(q.high / q.value) if q.value > 0 and q.high > 0 else math.nan
    return half / t if math.isfinite(half) and math.isfinite(t) else 0.0


def noise_vrr(system: StationarySystem, noise: Noise, stretches: np.ndarray) -> np.ndarray:
    """The VRR of the feeder ``noise`` through ``system`` with its time scale multiplied by
    each of ``stretches``: H(f) of the stretched chain is H(stretch f)."""
    freqs = noise_frequencies(noise.band_hz, N_FREQUENCIES)
    stretches = np.atleast_1d(np.asarray(stretches, dtype=float))
    h = system_response(system, stretches[:, None] * freqs[None, :], noise.feeder)
    return np.atleast_1d(vrr_spectrum(freqs, h, noise_spectrum(freqs, noise.tau_s)))


def outlet_sd(spec: DesignSpec, points: Sequence[OperatingPoint], vrr: np.ndarray) -> np.ndarray:
    """The outlet C_A's SD C (1 - C) sigma / sqrt(VRR) under the spec's noise, ``vrr``
    (B, ...) at B points."""
    c = np.array([p.feed_rate_a_per_s / p.feed_rate_total_per_s for p in points])
    c = c.reshape(-1, *([1] * (np.ndim(vrr) - 1)))
    return c * (1 - c) * spec.noise_sigma / np.sqrt(vrr)


def _composition_margin(spec: DesignSpec, point: OperatingPoint, sd: np.ndarray) -> np.ndarray:
    """The least composition margin at each SD, in units of the C_A tolerance's."""
    c = point.feed_rate_a_per_s / point.feed_rate_total_per_s
    out = np.full(np.shape(sd), np.inf)
    if spec.ca_tolerance is not None:
        out = np.minimum(out, (spec.ca_tolerance - spec.coverage_sigmas * sd) / spec.ca_tolerance)
    if spec.rsd_max is not None:
        out = np.minimum(out, (spec.rsd_max - sd / c) / spec.rsd_max)
    return out


def evaluate(
    s: Surrogate, spec: DesignSpec, point: OperatingPoint, physics: Mapping[str, Any] | None = None
) -> PointDesign:
    """The quantities the spec needs at ``point`` (its configuration's physics ``physics``:
    :func:`~workflows.prediction.predict.placement`), their margins and P(spec met) (module
    docstring). Raises ConfigError outside the library's domain unless ``s.extrapolate``."""
    return evaluate_many(s, spec, [point], physics)[0]


def law_generators(law: PhaseLaw, covariates: np.ndarray) -> np.ndarray:
    """(B, NX K + 1, NX K + 1) generators of the law's axial chains of B points whose
    slices have ``covariates`` (B, NX, P): :func:`dem.phases.law.law_chain`'s chains, every
    point at once (its rates exp(x . beta) of each move, the layout of
    :func:`coupling.phases.transitions`)."""
    b, nx, _ = covariates.shape
    n = nx * law.n_phases + 1
    q = np.zeros((b, n, n))
    for name, (src, dst, comp) in transitions(nx, 1, law.n_phases).items():
        if comp.size:
            q[:, src, dst] += law_rates(covariates[:, comp, :] @ law.coefficients[name])
    diagonal = np.arange(n)
    q[:, diagonal, diagonal] = -q.sum(axis=2)
    return q


def _feeds(points: Sequence[OperatingPoint]) -> np.ndarray:
    """(B, 2, NX) feed into the axial slices of each point, the feed zones' shares computed
    once per length."""
    shares: dict[float, np.ndarray] = {}
    out = np.empty((len(points), 2, AXIAL_SLICES))
    for n, point in enumerate(points):
        if point.length_m not in shares:
            unit = replace(point, feed_rate_a_per_s=1.0, feed_rate_b_per_s=1.0)
            shares[point.length_m] = entering(unit, AXIAL_SLICES, 1)
        out[n] = shares[point.length_m] * np.array([point.feed_rate_a_per_s, point.feed_rate_b_per_s])[:, None]
    return out


def _transfer_squared(generators: np.ndarray, inlet: np.ndarray, outlet: np.ndarray, freqs: np.ndarray) -> np.ndarray:
    """|H(f)|^2 (B, F) of B systems dN/dt = G N + inlet F(t), outflow ``outlet`` . N, at
    ``freqs``: by their eigendecompositions, H = sum_k l_k r_k / (i 2 pi f - lambda_k). A
    system whose decomposition misses H(0) = 1 (every particle leaves) by more than 1e-9
    (nearly defective, e.g. equal tanks in series: eigenvectors too ill-conditioned to
    trust) is solved by :func:`pbm.frequency.system_response`'s Schur form instead."""
    w, v = np.linalg.eig(generators)
    rhs = np.linalg.solve(v, inlet[..., None].astype(complex))[..., 0]
    weights = np.einsum("bi,bik->bk", outlet, v) * rhs
    h = np.einsum("bk,bkf->bf", weights, 1.0 / (2j * np.pi * freqs[None, None, :] - w[:, :, None]))
    for n in np.nonzero(np.abs((weights / -w).sum(axis=1) - 1.0) > 1e-9)[0]:
        system = StationarySystem(
            generators[n], np.stack([inlet[n], inlet[n]], axis=1), np.stack([outlet[n]] * 2), np.zeros(1)
        )
        h[n] = system_response(system, freqs)
    return np.abs(h) ** 2


@dataclass(frozen=True)
class Chains:
    """The law's axial chains of B points at steady state: ``transient`` (B, S, S) the
    generators' transient parts (row: from), ``exit_rate`` (B, S), ``inlet`` (B, 2, S) the
    particles/s of feed A and B entering each (slice, phase) state, ``occupancy`` (B, S)
    the steady particles, ``held`` (B, NX) per slice, ``totals`` (B,) the feeds; ``bed``
    (B, NX) each slice's hold-up the prediction takes before it is scaled to the total:
    the slices' zone law's where the library has one, else the chain's moved by each
    slice's line."""

    transient: np.ndarray
    exit_rate: np.ndarray
    inlet: np.ndarray
    occupancy: np.ndarray
    held: np.ndarray
    totals: np.ndarray
    bed: np.ndarray

    def subset(self, rows: Sequence[int]) -> Chains:
        return Chains(*(getattr(self, f.name)[list(rows)] for f in fields(self)))


def solved_chains(s: Surrogate, points: Sequence[OperatingPoint]) -> Chains:
    """The :class:`Chains` of ``points``: the steady hold-up and the time to discharge of
    :func:`~workflows.prediction.predict.point_chain`, whose transverse moves change
    neither, from chains a tenth its size, all solved at once. The mean residence time is
    the steady hold-up over the feed (Little's law: the chain's
    :func:`~workflows.prediction.predict.rtd_moments` mean, tests)."""
    law = s.model.law
    x = np.stack([covariate_columns(p, AXIAL_SLICES, law.covariate_names[1:], s.pattern) for p in points])
    q = law_generators(law, x)
    transient, exit_rate = q[:, :-1, :-1], q[:, :-1, -1]
    feeds = _feeds(points)
    inlet = (feeds[:, :, :, None] * law.entry[None, :, None, :]).reshape(len(points), 2, -1)
    occupancy = np.linalg.solve(-np.swapaxes(transient, 1, 2), inlet.sum(axis=1)[..., None])[..., 0]
    held = occupancy.reshape(len(points), AXIAL_SLICES, law.n_phases).sum(axis=2)
    profile = s.model.calibration.profile
    if profile is not None:
        bed = np.array([profile.holdups(p, s.pattern) for p in points])
    else:
        bed = np.empty_like(held)
        for i in range(AXIAL_SLICES):
            line = s.lines.get(slice_key(i))
            shift = 0.0 if line is None else np.array([line.at(p)[0] for p in points])
            bed[:, i] = held[:, i] * np.exp(shift)
    return Chains(transient, exit_rate, inlet, occupancy, held, feeds.sum(axis=(1, 2)), bed)


@dataclass(frozen=True)
class Systems:
    """The chains ``predict`` writes at B points as linear systems dN/dt = G N + b F(t)
    (:class:`pbm.frequency.StationarySystem`'s convention): ``generators`` (B, S, S),
    ``inlets`` (B, 2, S) one particle/s of each feeder, ``outlets`` (B, S) the exit rates."""

    generators: np.ndarray
    inlets: np.ndarray
    outlets: np.ndarray

    def system(self, n: int) -> StationarySystem:
        return StationarySystem(
            self.generators[n], self.inlets[n].T, np.stack([self.outlets[n], self.outlets[n]]), np.zeros(1)
        )


def predicted_systems(
    s: Surrogate,
    points: Sequence[OperatingPoint],
    chains: Chains,
    mrts: Sequence[PredictedQuantity],
    holdups: Sequence[PredictedQuantity],
) -> Systems:
    """The chain ``predict`` writes at each point (each slice's time scale set to its
    predicted hold-up, from the slices' zone law where the library has one, scaled to the
    predicted total:
    :func:`~workflows.prediction.predict.rescaled`, every rate out of a slice multiplied
    alike), its time scale then stretched so that its mean residence time is the
    predicted one."""
    k = s.model.law.n_phases
    slices = chains.bed * (np.array([h.value for h in holdups]) / chains.bed.sum(axis=1))[:, None]
    factors = np.repeat(chains.held / slices, k, axis=1)  # per (slice, phase) state
    mrt_rescaled = (chains.occupancy / factors).sum(axis=1) / chains.totals
    stretch = (np.array([m.value for m in mrts]) / mrt_rescaled)[:, None]
    generators = np.swapaxes(chains.transient * factors[:, :, None], 1, 2) / stretch[:, :, None]
    inlets = chains.inlet / np.maximum(chains.inlet.sum(axis=2, keepdims=True), 1e-300)
    return Systems(generators, inlets, chains.exit_rate * factors / stretch)


def predicted_system(s: Surrogate, design: PointDesign) -> StationarySystem:
    """The :class:`Systems` system of one designed point."""
    chains = solved_chains(s, [design.point])
    return predicted_systems(s, [design.point], chains, [design.mrt], [design.holdup]).system(0)


def evaluate_many(
    s: Surrogate, spec: DesignSpec, points: Sequence[OperatingPoint], physics: Mapping[str, Any] | None = None
) -> list[PointDesign]:
    """:func:`evaluate` of every point of ``points``, their chains solved together."""
    rows = [placement(s.domain, p, s.pattern, physics) for p in points]
    far = [(p, place) for p, place in zip(points, rows) if place.out_of_reach]
    if far:
        p, place = far[0]
        raise ConfigError(
            f"{p.impeller_rpm:g} rpm, {p.length_m:g} m, {p.feed_rate_total_per_s:g} /s lies too far beyond the "
            f"library's domain to extrapolate ({'; '.join(place.out_of_reach)}); the domain is {s.domain.describe()}"
        )
    outside = [p for p, place in zip(points, rows) if place.issues]
    if outside and not s.extrapolate:
        p = outside[0]
        raise ConfigError(
            f"{p.impeller_rpm:g} rpm, {p.length_m:g} m, {p.feed_rate_total_per_s:g} /s lies outside the library's "
            f"domain ({'; '.join(rows[points.index(p)].issues)}); the domain is {s.domain.describe()}. "
            "Pass --extrapolate for labelled, widened intervals"
        )
    chains = solved_chains(s, points)
    # a chain timed by the zone law holds the zone law's total (Little's law gives its time)
    held_by = chains.bed if s.model.calibration.time_scale() is not None else chains.held
    mrts, holdups = [], []
    for n, (p, place) in enumerate(zip(points, rows)):
        widen = place.widening if place.extrapolated else 1.0
        held = float(held_by[n].sum())
        least = s.floors.at(place)
        for key, value, into in ((HOLDUP, held, holdups), (MRT, held / chains.totals[n], mrts)):
            into.append(corrected(key, float(value), s.lines[key], p, widen, least.get(key, 0.0)))
    judged = list(range(len(points)))
    if spec.composition:
        # where the residence time or the hold-up alone fails for certain, so does the
        # spec: its composition is spared (its chain's frequency response the most costly part)
        judged = [n for n in judged if joint_probability(spec, mrts[n], holdups[n], s.correlation) > SPARED_BELOW]
    composition = {}
    if spec.composition and judged:
        chosen = [points[n] for n in judged]
        systems = predicted_systems(
            s, chosen, chains.subset(judged), [mrts[n] for n in judged], [holdups[n] for n in judged]
        )
        values, sds = _composition(spec, chosen, systems, [mrts[n] for n in judged])
        composition = {n: (values[j], sds[j]) for j, n in enumerate(judged)}
    out = []
    for n, p in enumerate(points):
        vrr = sd = None
        composition_t, composition_p = None, math.nan
        if spec.composition and n not in composition:
            composition_t = np.full(T_NODES.size, -1.0)  # not judged: the spec fails anyway
        if n in composition:
            values, sds = composition[n]
            vrr = Band(float(values[0]), float(values[1:3].min()), float(values[1:3].max()))
            sd = Band(float(sds[0]), float(sds[1:3].min()), float(sds[1:3].max()))
            composition_t = _composition_margin(spec, p, sds[3:])
            nu = mrts[n].correction.dof
            composition_p = float(
                sum(stdtr(nu, hi) - stdtr(nu, lo) for lo, hi in intervals_where(T_NODES, composition_t))
            )
        margins = _margins(spec, p, mrts[n], holdups[n], sd, composition_p)
        probability = joint_probability(spec, mrts[n], holdups[n], s.correlation, composition_t)
        out.append(PointDesign(p, mrts[n], holdups[n], vrr, sd, margins, probability, rows[n].labels()))
    return out


def _composition(
    spec: DesignSpec, points: Sequence[OperatingPoint], systems: Systems, mrts: Sequence[PredictedQuantity]
) -> tuple[np.ndarray, np.ndarray]:
    """(VRR, outlet C_A SD), each (B, 3 + len(T_NODES)): at the predicted mean residence
    time, its interval's ends, and its t values :data:`T_NODES`, every point at once."""
    b = len(points)
    scales = np.array([t_scale(m) for m in mrts])
    relative = np.column_stack(
        [
            np.ones(b),
            [m.low / m.value for m in mrts],
            [m.high / m.value for m in mrts],
            np.exp(scales[:, None] * T_NODES[None, :]),
        ]
    )
    freqs = noise_frequencies(spec.noise_band_hz, N_FREQUENCIES)
    # |H|^2 on one log grid spanning every stretched frequency, read off it by linear
    # interpolation in log f: H of the chain stretched by r is H(r f)
    lowest, highest = freqs[1] * relative.min(), freqs[-1] * relative.max()
    grid = np.geomspace(lowest, highest, TRANSFER_POINTS)
    feeder = 0 if spec.noise_feeder == "A" else 1
    squared = _transfer_squared(systems.generators, systems.inlets[:, feeder], systems.outlets, grid)
    position = (np.log(relative[:, :, None] * freqs[None, None, 1:]) - math.log(lowest)) / (
        math.log(highest / lowest) / (TRANSFER_POINTS - 1)
    )
    left = np.clip(np.floor(position).astype(int), 0, TRANSFER_POINTS - 2)
    weight = np.clip(position - left, 0.0, 1.0)
    rows = np.arange(b)[:, None, None]
    interpolated = squared[rows, left] * (1 - weight) + squared[rows, left + 1] * weight
    magnitude = np.concatenate([np.ones((b, relative.shape[1], 1)), interpolated], axis=2)  # H(0) = 1
    vrr = np.asarray(vrr_spectrum(freqs, np.sqrt(magnitude), noise_spectrum(freqs, spec.noise_tau_s)))
    return vrr, outlet_sd(spec, points, vrr)


def _margins(
    spec: DesignSpec,
    point: OperatingPoint,
    mrt: PredictedQuantity,
    holdup: PredictedQuantity,
    sd: Band | None,
    composition_p: float,
) -> tuple[Margin, ...]:
    """Each criterion's margin with its interval and the probability that it alone is
    met (the composition's both criteria together: one variable drives them)."""
    out = []

    def add(name: str, q, sign: float, bound: float, key: PredictedQuantity | None) -> None:
        ends = sorted((sign * (q.value - bound), sign * (q.low - bound), sign * (q.high - bound)))
        margin = Band(sign * (q.value - bound), ends[0], ends[2])
        probability = composition_p
        if key is not None:
            h = t_scale(key)
            z = math.log(bound / key.value) / h if h > 0 else math.copysign(math.inf, bound - key.value)
            below = float(stdtr(key.correction.dof, z)) if math.isfinite(z) else float(z > 0)
            probability = 1 - below if sign > 0 else below
        out.append(Margin(name, margin, probability))

    if spec.mrt_min_s is not None:
        add("mrt_min_s", mrt, 1.0, spec.mrt_min_s, mrt)
    if spec.mrt_max_s is not None:
        add("mrt_max_s", mrt, -1.0, spec.mrt_max_s, mrt)
    if spec.holdup_min is not None:
        add("holdup_min", holdup, 1.0, spec.holdup_min, holdup)
    if spec.holdup_max is not None:
        add("holdup_max", holdup, -1.0, spec.holdup_max, holdup)
    if sd is not None:
        c = point.feed_rate_a_per_s / point.feed_rate_total_per_s
        if spec.ca_tolerance is not None:
            k = spec.coverage_sigmas
            add("ca_tolerance", Band(k * sd.value, k * sd.low, k * sd.high), -1.0, spec.ca_tolerance, None)
        if spec.rsd_max is not None:
            add("rsd_max", Band(sd.value / c, sd.low / c, sd.high / c), -1.0, spec.rsd_max, None)
    return tuple(out)


# ------------------------------------------------------------------ the probability
def intervals_where(t: np.ndarray, margin: np.ndarray) -> list[tuple[float, float]]:
    """The stretches of ``t`` (increasing) where ``margin`` (tabulated there, linear
    between) is >= 0, the ends at +-inf when it holds at the table's ends."""
    ok = margin >= 0
    out, k = [], 0
    while k < t.size:
        if not ok[k]:
            k += 1
            continue
        start = -math.inf if k == 0 else _crossing(t[k - 1], t[k], margin[k - 1], margin[k])
        while k + 1 < t.size and ok[k + 1]:
            k += 1
        end = math.inf if k == t.size - 1 else _crossing(t[k], t[k + 1], margin[k], margin[k + 1])
        out.append((start, end))
        k += 1
    return out


def _crossing(t0: float, t1: float, m0: float, m1: float) -> float:
    return float(t0 + (t1 - t0) * m0 / (m0 - m1)) if m0 != m1 else float(t0)


def _bounds_t(q: PredictedQuantity, low: float | None, high: float | None) -> tuple[float, float]:
    """The interval of q's t variable where ``low`` <= q <= ``high`` (module docstring)."""
    h = t_scale(q)

    def at(bound: float | None, side: float) -> float:
        if bound is None:
            return side * math.inf
        if h <= 0:  # no interval: the value decides, as the limit h -> 0 of the line below
            return math.copysign(math.inf, bound - q.value)
        return math.log(bound / q.value) / h

    return at(low, -1.0), at(high, 1.0)


def rectangle(nu: float, rho: float, a: float, b: float, c: float, d: float) -> float:
    """P(a <= X <= b, c <= Y <= d) for (X, Y) standard bivariate t with ``nu`` degrees of
    freedom and correlation ``rho``: the integral over X of its density times the
    conditional probability of Y, a t with nu + 1 degrees of freedom about rho X of scale
    sqrt((nu + X^2)(1 - rho^2) / (nu + 1)); Gauss-Legendre in u = F(X)."""
    if b <= a or d <= c:
        return 0.0
    rho = float(np.clip(rho, -0.999, 0.999))
    ua, ub = float(stdtr(nu, a)), float(stdtr(nu, b))
    nodes, weights = np.polynomial.legendre.leggauss(GAUSS_NODES)
    u = ua + (ub - ua) * (nodes + 1) / 2
    x = stdtrit(nu, np.clip(u, 1e-300, 1 - 1e-16))
    scale = np.sqrt((nu + x**2) * (1 - rho**2) / (nu + 1))
    inner = stdtr(nu + 1, (d - rho * x) / scale) - stdtr(nu + 1, (c - rho * x) / scale)
    return float(np.clip((ub - ua) / 2 * np.sum(weights * inner), 0.0, 1.0))


def joint_probability(
    spec: DesignSpec,
    mrt: PredictedQuantity,
    holdup: PredictedQuantity,
    correlation: float,
    composition: np.ndarray | None = None,
) -> float:
    """P(spec met) (module docstring): ``composition`` the composition's margin at the
    mean residence time's t values :data:`T_NODES` (None without that criterion)."""
    a, b = _bounds_t(mrt, spec.mrt_min_s, spec.mrt_max_s)
    stretches = [(a, b)]
    if composition is not None:
        stretches = [(max(a, lo), min(b, hi)) for lo, hi in intervals_where(T_NODES, composition)]
    stretches = [(lo, hi) for lo, hi in stretches if hi > lo]
    c, d = _bounds_t(holdup, spec.holdup_min, spec.holdup_max)
    nu_m, nu_h = mrt.correction.dof, holdup.correction.dof
    if (c, d) == (-math.inf, math.inf):  # the hold-up is not judged (or met for certain)
        return float(sum(stdtr(nu_m, hi) - stdtr(nu_m, lo) for lo, hi in stretches))
    if (a, b) == (-math.inf, math.inf) and composition is None:  # the hold-up alone
        return float(max(stdtr(nu_h, d) - stdtr(nu_h, c), 0.0))
    return sum(rectangle(min(nu_m, nu_h), correlation, lo, hi, c, d) for lo, hi in stretches)


# ------------------------------------------------------------------ noise and step of a point
@dataclass(frozen=True)
class Dynamics:
    """A predicted point's answer to its feeders: the VRR of the spec's feeder noise, and
    the outlet C_A after feeder A's rate is multiplied by ``step_factor`` at t = 0
    (``step`` (3, T): at the predicted mean residence time, and the envelope of its
    interval's ends), with the response's mean delay, int (C_after - C(t)) dt / (C_after -
    C_before) (the continuous form of :func:`workflows.analysis.step.mean_delay`). Each
    interval is the chain stretched to the mean residence time's interval ends (module
    docstring)."""

    vrr: Band
    step_factor: float
    levels: tuple[float, float]
    times_s: np.ndarray
    step: np.ndarray
    mean_delay_s: Band

    def record(self) -> dict[str, Any]:
        return {
            "vrr": self.vrr.record(),
            "step_factor_a": self.step_factor,
            "ca_before_after": list(self.levels),
            "mean_delay_s": self.mean_delay_s.record(),
            "step_times_s": self.times_s.tolist(),
            "step_ca": {"value": self.step[0].tolist(), "low": self.step[1].tolist(), "high": self.step[2].tolist()},
        }


def discharged(system: StationarySystem, times: np.ndarray, feeder: str = "A") -> np.ndarray:
    """F(t): the share of ``feeder``'s particles entering at t = 0 discharged by each of
    ``times`` (evenly spaced from 0), the cumulative RTD."""
    from scipy.linalg import expm

    step = expm(system.generator * (times[1] - times[0]))
    state = system.feed_column(feeder).copy()
    out = np.empty(times.size)
    for n in range(times.size):
        out[n] = 1.0 - state.sum()
        state = step @ state
    return out


def step_response(
    system: StationarySystem, point: OperatingPoint, mrt: PredictedQuantity, factor: float = STEP_FACTOR_A
) -> tuple[np.ndarray, np.ndarray, tuple[float, float], Band]:
    """(times [s], C_A (3, T), the levels before and after, the mean delay) of the outlet
    after feeder A's rate is multiplied by ``factor``: A's outflow is F_A (1 + (factor - 1)
    F(t)), B's unchanged (the chain is linear and A and B move alike), so C(t) = C g / (C g
    + 1 - C), g = 1 + (factor - 1) F(t). ``system`` holds the predicted mean residence
    time; its stretches to the interval's ends give the band."""
    c0 = point.feed_rate_a_per_s / point.feed_rate_total_per_s
    c1 = factor * c0 / (factor * c0 + 1 - c0)
    ends = [1.0, mrt.low / mrt.value, mrt.high / mrt.value]
    ends = [e if math.isfinite(e) and e > 0 else 1.0 for e in ends]
    times = np.linspace(0.0, STEP_SPAN * mrt.value * max(ends), STEP_POINTS)
    cumulative = discharged(system, times)
    curves, delays = [], []
    for e in ends:
        g = 1.0 + (factor - 1.0) * np.interp(times / e, times, cumulative)
        curve = c0 * g / (c0 * g + 1 - c0)
        curves.append(curve)
        delays.append(float(np.trapezoid(c1 - curve, times) / (c1 - c0)))
    step = np.vstack([curves[0], np.min(curves, axis=0), np.max(curves, axis=0)])
    return times, step, (c0, c1), Band(delays[0], min(delays), max(delays))


def dynamics(s: Surrogate, noise: Noise, design: PointDesign) -> Dynamics:
    """The :class:`Dynamics` of a designed point under the feeder ``noise`` (its VRR the
    design's own when it judged the composition under that noise)."""
    system, mrt = predicted_system(s, design), design.mrt
    vrr = design.vrr
    if vrr is None:
        values = noise_vrr(system, noise, np.array([1.0, mrt.low / mrt.value, mrt.high / mrt.value]))
        vrr = Band(float(values[0]), float(values[1:].min()), float(values[1:].max()))
    times, step, levels, delay = step_response(system, design.point, mrt)
    return Dynamics(vrr, STEP_FACTOR_A, levels, times, step, delay)


def point_dynamics(
    s: Surrogate, point: OperatingPoint, noise: Noise | None = None, physics: Mapping[str, Any] | None = None
) -> Dynamics:
    """The feeder-noise VRR and the step response, with their intervals, of any predicted
    point (what ``pbmdem predict`` predicts there; its configuration's physics ``physics``):
    the design of a spec with no composition criterion, its noise ``noise`` (default
    :class:`Noise`'s: feeder A's white noise). Raises ConfigError outside the library's
    domain unless ``s.extrapolate``."""
    noise = noise or Noise()
    spec = design_spec(
        mrt_min_s=1e-300, noise_tau_s=noise.tau_s, noise_band_hz=noise.band_hz, noise_feeder=noise.feeder
    )
    return dynamics(s, noise, evaluate(s, spec, point, physics))


# ------------------------------------------------------------------ the search
def box(s: Surrogate, spec: DesignSpec) -> tuple[tuple[float, float], tuple[float, float], tuple[float, float]]:
    """The (rpm, length [m], total feed [particles/s]) ranges searched: the spec's, each
    default the library's domain. Raises ConfigError, in one line naming the domain, when
    they leave it and ``s.extrapolate`` is False."""
    rpm, length, feed = (s.domain.span(axis) for axis in ("speed", "length", "feed"))
    out = (
        (spec.rpm_min or rpm[0], spec.rpm_max or rpm[1]),
        (spec.length_min_m or length[0], spec.length_max_m or length[1]),
        (spec.feed_min_per_s or feed[0], spec.feed_max_per_s or feed[1]),
    )
    # one bound given beyond the domain's other end: the default left for the other would invert the range
    for (low, high), names, unit in zip(
        out,
        (("rpm_min", "rpm_max"), ("length_min_m", "length_max_m"), ("feed_min_per_s", "feed_max_per_s")),
        ("rpm", "m", "particles/s"),
    ):
        if low > high:
            given, default = (names[1], names[0]) if getattr(spec, names[1]) is not None else names
            end = low if given == names[1] else high
            raise ConfigError(
                f"{given} {getattr(spec, given):g} lies beyond the library's domain, whose end {end:g} {unit} is the "
                f"default {default}: give {default} too (and --extrapolate to search outside the domain)"
            )
    corners = [placement(s.domain, design_point(s.base, s.rule, *(o[k] for o in out)), s.pattern) for k in (0, 1)]
    far = [i for c in corners for i in c.out_of_reach]
    if far:
        raise ConfigError(
            f"the design space {out[0][0]:g}-{out[0][1]:g} rpm, {out[1][0]:g}-{out[1][1]:g} m, "
            f"{out[2][0]:g}-{out[2][1]:g} /s reaches too far beyond the library's domain ({'; '.join(far)}); "
            f"the domain is {s.domain.describe()}"
        )
    if not s.extrapolate:
        issues = []
        for c in corners:
            issues += [i for i in c.issues if i not in issues]
        if issues:
            raise ConfigError(
                f"the design space {out[0][0]:g}-{out[0][1]:g} rpm, {out[1][0]:g}-{out[1][1]:g} m, "
                f"{out[2][0]:g}-{out[2][1]:g} /s leaves the library's domain ({'; '.join(issues)}); "
                f"the domain is {s.domain.describe()}. Pass --extrapolate for labelled, widened intervals"
            )
    return out


@dataclass(frozen=True)
class Slice:
    """P(spec met) over ``speeds`` x ``lengths`` at one total feed ``feed_per_s``: the
    region the figure draws, finer than the search's grid."""

    feed_per_s: float
    speeds: np.ndarray
    lengths: np.ndarray
    points: tuple[PointDesign, ...]

    @property
    def probability(self) -> np.ndarray:
        return np.array([p.probability for p in self.points]).reshape(self.speeds.size, self.lengths.size)

    def record(self) -> dict[str, Any]:
        return {
            "feed_per_s": self.feed_per_s,
            "rpm": self.speeds.tolist(),
            "length_m": self.lengths.tolist(),
            "probability": self.probability.tolist(),
        }


@dataclass(frozen=True)
class DesignResult:
    """The grid searched (``speeds`` x ``lengths`` x ``feeds``, every point in ``points``
    in that order), the finer slice at the shortest blender's feed (``region``), the two
    answers with P(spec met) >= the spec's confidence (None when no point has it): the
    shortest blender (``shortest``, ties: the largest feed, then the highest P) and the
    largest feed (``largest_feed``, ties: the shortest, then the highest P), their noise
    and step (``dynamics``, keyed "shortest", "largest_feed"), the correlation the joint
    probability used, and notes."""

    spec: DesignSpec
    speeds: np.ndarray
    lengths: np.ndarray
    feeds: np.ndarray
    points: tuple[PointDesign, ...]
    region: Slice
    shortest: PointDesign | None
    largest_feed: PointDesign | None
    dynamics: dict[str, Dynamics]
    correlation: float
    domain: str
    notes: tuple[str, ...]
    library_points: tuple[tuple[float, float, float], ...]
    #: the operating points the search evaluated
    evaluated: int = 0

    @property
    def probability(self) -> np.ndarray:
        """(speeds, lengths, feeds) P(spec met)."""
        return np.array([p.probability for p in self.points]).reshape(self.speeds.size, self.lengths.size, -1)

    def grid(self, name: str, part: str = "value") -> np.ndarray:
        """(speeds, lengths, feeds) of a predicted quantity's ``part``: "mrt", "holdup"."""
        q = {"mrt": lambda p: p.mrt, "holdup": lambda p: p.holdup}[name]
        return np.array([getattr(q(p), part) for p in self.points]).reshape(self.speeds.size, self.lengths.size, -1)

    def record(self) -> dict[str, Any]:
        shape = (self.speeds.size, self.lengths.size, self.feeds.size)
        return {
            "spec": self.spec.model_dump(),
            "level": LEVEL,
            # the chain design judges is the one `pbm run` runs on predict's table in this mode
            "rates": VALIDATED_RATES,
            "domain": self.domain,
            "dependence": (
                "the residence-time and composition criteria on the mean residence time's one t variable (no "
                "independence assumed); a hold-up bound's t variable bivariate t with it, correlation "
                f"{self.correlation:.3f} (the two lines' residuals at the library's runs)"
            ),
            "correlation": self.correlation,
            "grid": {
                "rpm": self.speeds.tolist(),
                "length_m": self.lengths.tolist(),
                "feed_per_s": self.feeds.tolist(),
                "probability": self.probability.tolist(),
                "mean_residence_time_s": {p: self.grid("mrt", p).tolist() for p in ("value", "low", "high")},
                "holdup": {p: self.grid("holdup", p).tolist() for p in ("value", "low", "high")},
                "shape": list(shape),
            },
            "region": self.region.record(),
            "shortest": None if self.shortest is None else self.shortest.record(),
            "largest_feed": None if self.largest_feed is None else self.largest_feed.record(),
            "dynamics": {k: d.record() for k, d in self.dynamics.items()},
            "library_points": [list(p) for p in self.library_points],
            "notes": list(self.notes),
        }


def _rank_shortest(p: PointDesign) -> tuple[float, float, float]:
    return (p.length_m, -p.feed_per_s, -p.probability)


def _rank_feed(p: PointDesign) -> tuple[float, float, float]:
    return (-p.feed_per_s, p.length_m, -p.probability)


def band_tops(rule: tuple[float, float, float], low: float, high: float) -> np.ndarray:
    """The longest length in [``low``, ``high``] of each count of stations ``rule`` places
    (:func:`design_point`): the next station comes just past it. Within a count the
    bladeless stretch before the weir, and the bed with it, grows with the length, so the
    residence time is not monotone in the length but a sawtooth whose teeth end there."""
    first, spacing, gap = rule
    n = np.arange(1, stations_for(rule, high) + 1)
    tops = first + gap + n * spacing - 1e-6
    return tops[(tops >= low) & (tops <= high)]


def _tied(
    good: Sequence[PointDesign],
    answer: PointDesign,
    along: Callable[[PointDesign], float],
    column: Callable[[PointDesign], tuple[float, float]],
) -> list[tuple[float, float]]:
    """The columns (the other two axes' values, ``column``) of the points of ``good`` whose
    value ``along`` the answer's axis ties ``answer``'s, each once."""
    return list(dict.fromkeys(column(p) for p in good if math.isclose(along(p), along(answer), rel_tol=1e-12)))


def _axis(low: float, high: float, n: int, geometric: bool = False) -> np.ndarray:
    if not high > low:
        return np.array([low])
    return np.geomspace(low, high, n) if geometric else np.linspace(low, high, n)


def design(
    s: Surrogate, spec: DesignSpec, grid: tuple[int, int, int] = GRID, region: tuple[int, int] = REGION
) -> DesignResult:
    """The search of the module docstring: the grid, then at the feed of its shortest
    blender (else of its most likely point) the finer ``region`` over speed and length,
    whose points the answers are chosen among too, then each answer refined along its
    own axis."""
    (r0, r1), (l0, l1), (f0, f1) = box(s, spec)
    speeds, lengths, feeds = _axis(r0, r1, grid[0]), _axis(l0, l1, grid[1]), _axis(f0, f1, grid[2], geometric=True)

    def at(rpm: float, length: float, feed: float) -> OperatingPoint:
        return design_point(s.base, s.rule, rpm, length, feed)

    evaluated = 0

    def judged(points: list[OperatingPoint]) -> list[PointDesign]:
        nonlocal evaluated
        evaluated += len(points)
        return evaluate_many(s, spec, points)

    def met(found: Sequence[PointDesign]) -> list[PointDesign]:
        return [p for p in found if p.probability >= spec.confidence]

    points = tuple(judged([at(r, length, f) for r in speeds for length in lengths for f in feeds]))
    good = met(points)
    shown = min(good, key=_rank_shortest) if good else max(points, key=lambda p: p.probability)
    fine_speeds, fine_lengths = _axis(r0, r1, region[0]), _axis(l0, l1, region[1])
    fine = tuple(judged([at(r, length, shown.feed_per_s) for r in fine_speeds for length in fine_lengths]))
    good += met(fine)
    notes = []
    shortest = largest = None
    if good:
        # each answer refined in every column of the space where it could improve: the
        # columns whose own best on the grid ties the answer's (the others fail before it)
        shortest = min(good, key=_rank_shortest)
        searched = np.union1d(lengths, fine_lengths)
        shorter = searched[searched < shortest.length_m * (1 - 1e-12)]
        if shorter.size:  # between the next shorter length searched and the answer
            trial = np.linspace(shorter[-1], shortest.length_m, REFINE_POINTS + 2)[1:-1]
            columns = _tied(good, shortest, lambda p: p.length_m, lambda p: (p.point.impeller_rpm, p.feed_per_s))
            found = judged([at(r, v, f) for r, f in columns for v in trial])
            shortest = min([shortest, *met(found)], key=_rank_shortest)
        tops = band_tops(s.rule, l0, shortest.length_m * (1 - 1e-12))
        if tops.size:  # a blender one station short of a shorter band's next can beat a longer one
            found = judged([at(r, v, f) for r in speeds for f in feeds for v in tops])
            shortest = min([shortest, *met(found)], key=_rank_shortest)
        largest = min(good, key=_rank_feed)
        higher = feeds[feeds > largest.feed_per_s * (1 + 1e-12)]
        if higher.size:
            trial = np.geomspace(largest.feed_per_s, higher[0], REFINE_POINTS + 2)[1:-1]
            columns = _tied(good, largest, lambda p: p.feed_per_s, lambda p: (p.point.impeller_rpm, p.length_m))
            found = judged([at(r, length, v) for r, length in columns for v in trial])
            largest = min([largest, *met(found)], key=_rank_feed)
        if math.isclose(shortest.length_m, l0):
            notes.append(f"the shortest blender searched ({l0:g} m) already meets the spec: a shorter one may too")
        if math.isclose(largest.feed_per_s, f1):
            notes.append(f"the highest feed searched ({f1:g} /s) still meets the spec: a higher one may too")
    else:
        notes.append(
            f"no point searched meets the spec with P >= {spec.confidence:g}; the most likely is "
            f"{shown.point.impeller_rpm:g} rpm, {shown.length_m:.4g} m, {shown.feed_per_s:.4g} /s "
            f"(P = {shown.probability:.3f})"
        )
    if any(p.outside for p in points):
        notes.append(
            "EXTRAPOLATED: part of the space searched lies outside the library's domain or beyond the combinations "
            "its runs span; its intervals widened"
        )
    answers = {"shortest": shortest, "largest_feed": largest}
    moves = {k: dynamics(s, spec.noise, p) for k, p in answers.items() if p is not None}
    library = tuple((r.point.impeller_rpm, r.point.length_m, r.point.feed_rate_total_per_s) for r in s.model.runs)
    return DesignResult(
        spec,
        speeds,
        lengths,
        feeds,
        points,
        Slice(shown.feed_per_s, fine_speeds, fine_lengths, fine),
        shortest,
        largest,
        moves,
        s.correlation,
        s.domain.describe(),
        tuple(notes),
        library,
        evaluated,
    )
