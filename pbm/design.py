"""Design inversion: the smallest blender, and the impeller speeds, that meet a spec.

A spec (:class:`DesignSpec`) bounds what leaves the blender at steady state:

* the outlet composition C_A within +-``ca_tolerance`` (``coverage_sigmas`` standard
  deviations of it, 3 by default) and/or its relative standard deviation below
  ``rsd_max``, for a feeder whose rate fluctuates with relative SD ``noise_sigma``,
  correlation time ``noise_tau_s`` and bandwidth ``noise_band_hz``;
* the mean residence time within [``mrt_min_s``, ``mrt_max_s``].

The composition follows from the variance reduction ratio of :mod:`pbm.frequency`: a
feeder noise of relative SD sigma moves the inlet composition by C (1 - C) sigma (SD), the
blender divides its variance by VRR, so the outlet's SD is C (1 - C) sigma / sqrt(VRR)
and its RSD that over C. The mean residence time is Little's law on the stationary system,
hold-up / feed rate, each feeder weighted by its rate.

The candidates come from a table library (:class:`TableLibrary`): DEM velocity tables at
several impeller speeds on one grid. A speed between two of them is interpolated
(:func:`pbm.studies.interpolate_tables`), a length is the paper's rescaling of the
compartments (:func:`pbm.studies.scale_blender`, every axial rate over the length factor).
Both are models: the speed range ends at the library's, and the length factor at
:data:`LENGTH_FACTOR_LIMITS`; a spec that asks for more is refused, never extrapolated.

For each speed of a grid over the range, the feasible length factors form an interval
(the composition and the lower residence bound improve with length, the upper bound
worsens), found by a scan and refined by root finding on the binding margin
(:func:`design`). The answer is the smallest length over the speeds, and the speed range
in which that length meets the spec, with every criterion's margin.
"""

from __future__ import annotations

import math
import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator
from scipy.optimize import brentq

from coupling.blas import free_cores, single_threaded_blas
from coupling.errors import ConfigError
from coupling.tables import VelocityTable
from pbm.config import PbmConfig
from pbm.feed import resolve_feed
from pbm.fill import fill_samples, fit_fill_law, steady_table, steady_windows
from pbm.frequency import (
    noise_frequencies,
    noise_spectrum,
    stationary_system,
    system_response,
    vrr_spectrum,
)
from pbm.studies import interpolate_tables, scale_blender

#: Length factors the rescaling may be asked for, relative to the library's blender: the
#: paper's own study spans 0.5-1.5, and the campaign checked x1.25 against DEM.
LENGTH_FACTOR_LIMITS = (0.5, 2.0)
#: Frequencies of the VRR quadrature: 201 log-spaced points hold the VRR within 0.06 %
#: of a 2001-point grid on a DEM-like 10 x 10 table, at a tenth of the cost.
N_FREQUENCIES = 201
#: Length factors scanned per speed before the edges are refined, and speeds per library span.
SCAN_POINTS = 7
SPEEDS_PER_SPAN = 4
#: Relative precision of the refined feasible edges.
EDGE_RTOL = 1e-5
#: Processes the speeds are shared among, at most (fewer when fewer cores are free).
MAX_WORKERS = 4


class DesignSpec(BaseModel):
    """What the blender must deliver, and the design space to search."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    ca_tolerance: float | None = Field(None, gt=0, lt=1, description="outlet C_A within +- this (absolute fraction)")
    coverage_sigmas: float = Field(3.0, gt=0, description="standard deviations of C_A that must fit in the tolerance")
    rsd_max: float | None = Field(None, gt=0, description="largest relative SD of the outlet C_A")
    noise_sigma: float = Field(0.0, ge=0, description="relative SD of the noisy feeder's rate")
    noise_tau_s: float = Field(0.0, ge=0, description="correlation time of the feeder noise [s] (0: white)")
    noise_band_hz: float = Field(
        0.5, gt=0, description="the feeder noise's bandwidth [Hz] (0.5: a rate set every second)"
    )
    noise_feeder: Literal["A", "B"] = "A"
    mrt_min_s: float | None = Field(None, gt=0, description="shortest acceptable mean residence time [s]")
    mrt_max_s: float | None = Field(None, gt=0, description="longest acceptable mean residence time [s]")
    rpm_min: float | None = Field(None, gt=0, description="lowest impeller speed to consider (default: the library's)")
    rpm_max: float | None = Field(None, gt=0, description="highest impeller speed to consider (default: the library's)")
    length_factor_min: float = Field(LENGTH_FACTOR_LIMITS[0], gt=0)
    length_factor_max: float = Field(LENGTH_FACTOR_LIMITS[1], gt=0)

    @model_validator(mode="after")
    def _consistent(self) -> DesignSpec:
        composition = self.ca_tolerance is not None or self.rsd_max is not None
        if not composition and self.mrt_min_s is None and self.mrt_max_s is None:
            raise ValueError("give at least one criterion: ca_tolerance, rsd_max, mrt_min_s or mrt_max_s")
        if composition and self.noise_sigma <= 0:
            raise ValueError("a composition criterion (ca_tolerance, rsd_max) needs the feeder noise: noise_sigma > 0")
        if self.mrt_min_s is not None and self.mrt_max_s is not None and self.mrt_min_s >= self.mrt_max_s:
            raise ValueError(f"mrt_min_s ({self.mrt_min_s}) must be < mrt_max_s ({self.mrt_max_s})")
        if self.rpm_min is not None and self.rpm_max is not None and self.rpm_min > self.rpm_max:
            raise ValueError(f"rpm_min ({self.rpm_min}) must be <= rpm_max ({self.rpm_max})")
        lo, hi = LENGTH_FACTOR_LIMITS
        if not lo <= self.length_factor_min < self.length_factor_max <= hi:
            raise ValueError(
                f"length factors {self.length_factor_min}..{self.length_factor_max} must satisfy "
                f"{lo} <= min < max <= {hi}: the rescaling is not trusted beyond that (a DEM run of that blender is "
                "needed)"
            )
        return self

    @property
    def composition(self) -> bool:
        return self.ca_tolerance is not None or self.rsd_max is not None

    @property
    def criteria(self) -> tuple[str, ...]:
        """The margins an evaluation judges, by name (:class:`Evaluation`)."""
        given = {"mrt_min_s": self.mrt_min_s, "mrt_max_s": self.mrt_max_s}
        given |= {"ca_tolerance": self.ca_tolerance, "rsd_max": self.rsd_max}
        return tuple(name for name, value in given.items() if value is not None)


def design_spec(**values: Any) -> DesignSpec:
    """A validated :class:`DesignSpec`; ConfigError names the bad value."""
    try:
        return DesignSpec(**values)
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(map(str, e['loc'])) or 'spec'}: {e['msg']}" for e in exc.errors())
        raise ConfigError(f"design spec: {problems}") from None


@dataclass(frozen=True)
class TableLibrary:
    """DEM velocity tables of one blender at several impeller speeds, on one grid.

    ``points``: (rpm, table) pairs; ``pbm_config``: the feed (rates, inlet weights) and
    rate mode the PBM uses; ``steady_time_s``: the windows from this time on are averaged
    into the stationary system; ``length_m``: the library blender's length.
    """

    points: tuple[tuple[float, VelocityTable], ...]
    pbm_config: PbmConfig
    steady_time_s: float
    length_m: float
    _cache: dict = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self) -> None:
        if not self.points:
            raise ConfigError("a table library needs at least one table")
        speeds = [float(v) for v, _ in self.points]
        if len(set(speeds)) != len(speeds) or not all(math.isfinite(v) and v > 0 for v in speeds):
            raise ConfigError(f"the library's speeds must be distinct and > 0, got {speeds}")
        if not (math.isfinite(self.length_m) and self.length_m > 0):
            raise ConfigError(f"the library's blender length must be > 0 m, got {self.length_m}")
        object.__setattr__(self, "points", tuple(sorted(((float(v), t) for v, t in self.points), key=lambda p: p[0])))
        # a feed left None: the slowest run's operating point's (pbm.feed)
        object.__setattr__(self, "pbm_config", resolve_feed(self.pbm_config, self.points[0][1])[0])

    @property
    def rpm_range(self) -> tuple[float, float]:
        return self.points[0][0], self.points[-1][0]

    def table_at(self, rpm: float) -> VelocityTable:
        """The library's table at ``rpm``: a run's own, else interpolated between the two
        that bracket it (ConfigError outside the range)."""
        for value, table in self.points:
            if math.isclose(value, rpm, rel_tol=1e-12):
                return table
        if rpm not in self._cache:
            self._cache[rpm] = interpolate_tables(self.points, rpm)
        return self._cache[rpm]


@dataclass(frozen=True)
class Evaluation:
    """One candidate (speed, length factor): its outlet quantities and every margin
    (positive: met, by that much, in the criterion's own unit). Where a residence-time
    margin fails, the composition is not judged (:func:`_judged`): ``ca_sd``, ``ca_rsd``
    and ``vrr`` are None and its margins absent."""

    rpm: float
    length_factor: float
    mean_residence_time_s: float
    ca_sd: float | None
    ca_rsd: float | None
    vrr: float | None
    margins: dict[str, float]
    feed_per_s: float | None = None

    @property
    def feasible(self) -> bool:
        return all(m >= 0 for m in self.margins.values())

    def to_dict(self) -> dict[str, Any]:
        return {
            "rpm": self.rpm,
            "length_factor": self.length_factor,
            "mean_residence_time_s": self.mean_residence_time_s,
            "ca_sd": self.ca_sd,
            "ca_rsd": self.ca_rsd,
            "vrr": self.vrr,
            "margins": dict(self.margins),
            "feasible": self.feasible,
            "feed_per_s": self.feed_per_s,
        }


@single_threaded_blas()
def evaluate(
    library: TableLibrary, spec: DesignSpec, rpm: float, length_factor: float, composition: bool = True
) -> Evaluation:
    """The outlet quantities and margins of the blender ``length_factor`` x the library's
    length at ``rpm`` (within the library's range); with ``composition`` False, the
    residence-time margins only (no frequency response: the composition is not judged)."""
    config = library.pbm_config
    table = scale_blender(library.table_at(rpm), length_factor=length_factor)
    system = stationary_system(table, config, t_start_s=library.steady_time_s)
    return _judged(spec, system, config, float(rpm), float(length_factor), composition=composition)


def _judged(
    spec: DesignSpec, system, config: PbmConfig, rpm: float, length_factor: float, feed=None, composition: bool = True
) -> Evaluation:
    """The :class:`Evaluation` of a stationary system fed at ``config``'s rates (without
    the composition's margins when ``composition`` is False). The composition is judged
    only where the residence time is met: where it fails, the point is infeasible whatever
    its composition, and its frequency response is spared."""
    rates = np.array([config.feed_rate_a_per_s, config.feed_rate_b_per_s])
    if not rates.sum() > 0:
        raise ConfigError("the library's feed rates are both 0: nothing flows through the blender")
    if system.steady_holdup is not None:  # the fill law's steady state
        mrt = system.steady_holdup / float(rates.sum())
    else:
        # Little's law: the hold-up of one particle/s of each feeder is its mean residence time.
        per_feeder = np.linalg.solve(system.generator, -system.feed).sum(axis=0)
        mrt = float(per_feeder @ rates / rates.sum())
    margins: dict[str, float] = {}
    if spec.mrt_min_s is not None:
        margins["mrt_min_s"] = mrt - spec.mrt_min_s
    if spec.mrt_max_s is not None:
        margins["mrt_max_s"] = spec.mrt_max_s - mrt
    sd = rsd = vrr = None
    if spec.composition and composition and not _residence_failed(margins):
        c = float(rates[0] / rates.sum())
        freqs = noise_frequencies(spec.noise_band_hz, N_FREQUENCIES)
        h = system_response(system, freqs, spec.noise_feeder)
        vrr = vrr_spectrum(freqs, h, noise_spectrum(freqs, spec.noise_tau_s))
        sd = c * (1 - c) * spec.noise_sigma / math.sqrt(vrr)
        rsd = sd / c if c > 0 else math.inf
        if spec.ca_tolerance is not None:
            margins["ca_tolerance"] = spec.ca_tolerance - spec.coverage_sigmas * sd
        if spec.rsd_max is not None:
            margins["rsd_max"] = spec.rsd_max - rsd
    return Evaluation(rpm, length_factor, mrt, sd, rsd, vrr, margins, feed)


#: Margins that grow with the blender's length; the others shrink with it.
_GROWING = ("mrt_min_s", "ca_tolerance", "rsd_max")
#: Margins judged without the composition.
_RESIDENCE = ("mrt_min_s", "mrt_max_s")


def _residence_failed(margins: dict[str, float]) -> bool:
    return any(margins.get(k, 0.0) < 0 for k in _RESIDENCE)


def _least(e: Evaluation, kinds: tuple[str, ...]) -> float:
    """The least of the ``kinds`` margins of ``e``; where its composition was spared (a
    residence margin failed, :func:`_judged`), the least failed one: negative too, so
    that the sign a root finding brackets is the point's feasibility."""
    failed = [m for k, m in e.margins.items() if k in _RESIDENCE and m < 0]
    return min([e.margins[k] for k in kinds if k in e.margins] + failed)


def _judged_whole(e: Evaluation, spec: DesignSpec) -> bool:
    """Whether ``e`` is what :func:`evaluate` gives for ``spec``: every criterion judged, or
    the composition spared where a residence margin failed."""
    return all(k in e.margins for k in spec.criteria) or (
        all(k in e.margins for k in spec.criteria if k in _RESIDENCE) and _residence_failed(e.margins)
    )


@dataclass(frozen=True)
class SpeedRow:
    """The feasible length factors at one speed: [lo, hi], None when none is."""

    rpm: float
    length_factor_lo: float | None
    length_factor_hi: float | None
    at_lo: Evaluation | None
    scanned: list[Evaluation]

    @property
    def feasible(self) -> bool:
        return self.length_factor_lo is not None


@dataclass(frozen=True)
class DesignResult:
    """The smallest length (``best``, None when nothing meets the spec), the speed ranges
    in which the library's own blender meets it, and every searched speed's feasible lengths."""

    spec: DesignSpec
    library_rpm: tuple[float, ...]
    length_m: float
    rows: list[SpeedRow]
    best: Evaluation | None
    rpm_ranges: list[tuple[float, float]]
    notes: list[str]

    def to_dict(self) -> dict[str, Any]:
        return {
            "spec": self.spec.model_dump(),
            "library_rpm": list(self.library_rpm),
            "library_length_m": self.length_m,
            "best": None
            if self.best is None
            else {**self.best.to_dict(), "length_m": self.best.length_factor * self.length_m},
            "rpm_ranges_at_library_length": [list(r) for r in self.rpm_ranges],
            "speeds": [
                {
                    "rpm": r.rpm,
                    "length_factor_lo": r.length_factor_lo,
                    "length_factor_hi": r.length_factor_hi,
                    "length_m_lo": None if r.length_factor_lo is None else r.length_factor_lo * self.length_m,
                    "length_m_hi": None if r.length_factor_hi is None else r.length_factor_hi * self.length_m,
                    "at_lo": None if r.at_lo is None else r.at_lo.to_dict(),
                }
                for r in self.rows
            ],
            "notes": list(self.notes),
        }


def speed_grid(library: TableLibrary, spec: DesignSpec) -> np.ndarray:
    """The speeds searched: the spec's range (default the library's), refused where it
    leaves the library; every library speed inside it plus SPEEDS_PER_SPAN - 1 between
    neighbours."""
    lo_lib, hi_lib = library.rpm_range
    lo = lo_lib if spec.rpm_min is None else spec.rpm_min
    hi = hi_lib if spec.rpm_max is None else spec.rpm_max
    if lo < lo_lib - 1e-9 or hi > hi_lib + 1e-9:
        covered = f"{lo_lib:g} rpm only" if lo_lib == hi_lib else f"{lo_lib:g}..{hi_lib:g} rpm"
        raise ConfigError(
            f"impeller speeds {lo:g}..{hi:g} rpm leave the table library, which covers {covered}: "
            "a DEM run at the missing speed is needed (no extrapolation)"
        )
    knots = np.array([v for v, _ in library.points])
    grid = [lo, hi, *knots[(knots > lo) & (knots < hi)]]
    for a, b in zip(knots[:-1], knots[1:]):
        grid += list(np.linspace(a, b, SPEEDS_PER_SPAN + 1)[1:-1])
    return np.array(sorted({float(v) for v in grid if lo <= v <= hi}))


def feasible_lengths(library: TableLibrary, spec: DesignSpec, rpm: float) -> SpeedRow:
    """The interval of length factors that meet ``spec`` at ``rpm``: a geometric scan over
    [length_factor_min, length_factor_max], then each edge refined on the margin that
    binds there. Margins that grow with length set the lower edge, the others the upper;
    the first feasible stretch of the scan is returned."""
    evaluated: dict[float, Evaluation] = {}
    residence_only: dict[float, Evaluation] = {}

    def at(f: float, composition: bool = True) -> Evaluation:
        # the edges' root finding starts from the scanned points it brackets, and ends on one
        f = float(f)
        if f in evaluated:
            return evaluated[f]
        if composition:
            evaluated[f] = evaluate(library, spec, rpm, f)
            return evaluated[f]
        if f not in residence_only:
            residence_only[f] = evaluate(library, spec, rpm, f, composition=False)
        return residence_only[f]

    factors = np.geomspace(spec.length_factor_min, spec.length_factor_max, SCAN_POINTS)
    scanned = [at(f) for f in factors]
    ok = [e.feasible for e in scanned]
    if not any(ok):
        return SpeedRow(rpm, None, None, None, scanned)
    first = ok.index(True)
    last = first
    while last + 1 < len(ok) and ok[last + 1]:
        last += 1

    def edge(outside: float, inside: float, kinds: tuple[str, ...]) -> float:
        # the shrinking margins bound the residence time only: their edge needs no
        # frequency response, a sixth of the responses a design computes otherwise
        composition = any(k not in _RESIDENCE for k in kinds)

        def margin(f: float) -> float:
            return _least(at(f, composition), kinds)

        if margin(outside) * margin(inside) > 0:  # not the margin that failed: keep the scanned point
            return inside
        return _feasible_root(margin, outside, inside)

    growing = tuple(k for k in spec.criteria if k in _GROWING)
    shrinking = tuple(k for k in spec.criteria if k not in _GROWING)
    lo = factors[first]
    if first > 0 and growing:
        lo = edge(factors[first - 1], factors[first], growing)
    hi = factors[last]
    if last + 1 < len(factors) and shrinking:
        hi = edge(factors[last], factors[last + 1], shrinking)
    return SpeedRow(rpm, float(lo), float(hi), at(lo), scanned)


def speed_rows(library: TableLibrary, spec: DesignSpec, speeds) -> list[SpeedRow]:
    """:func:`feasible_lengths` at every speed of ``speeds``, in their order.

    The speeds are independent: they are dealt round-robin (neighbouring speeds cost
    alike) to this process and to workers forked on the cores that are free, each with a
    single-threaded BLAS. Threads would not help: scipy's Schur decomposition holds the
    GIL. Where processes cannot be forked, or one core is free, they run here in turn."""
    speeds = [float(v) for v in speeds]
    workers = search_processes(len(speeds))
    if workers == 1:
        return _speed_rows(library, spec, speeds)
    shares = [speeds[k::workers] for k in range(workers)]
    context = multiprocessing.get_context("fork")
    with ProcessPoolExecutor(workers - 1, mp_context=context) as pool:
        pending = [pool.submit(_speed_rows, library, spec, share) for share in shares[1:]]
        done = _speed_rows(library, spec, shares[0]) + [row for job in pending for row in job.result()]
    by_speed = {row.rpm: row for row in done}
    return [by_speed[v] for v in speeds]


def search_processes(n_speeds: int) -> int:
    """How many processes :func:`speed_rows` shares ``n_speeds`` speeds among now."""
    if "fork" not in multiprocessing.get_all_start_methods():
        return 1
    return free_cores(min(n_speeds, MAX_WORKERS))


def _speed_rows(library: TableLibrary, spec: DesignSpec, speeds: list[float]) -> list[SpeedRow]:
    return [feasible_lengths(library, spec, rpm) for rpm in speeds]


def speed_ranges(
    library: TableLibrary,
    spec: DesignSpec,
    speeds,
    length_factor: float = 1.0,
    known=(),
) -> list[tuple[float, float]]:
    """The speed intervals in which the blender ``length_factor`` x the library's meets
    ``spec``: the feasible stretches of ``speeds``, each open edge refined between its grid
    speeds by root finding on the smallest margin. ``known``: evaluations already made
    (any speed and length; those at ``length_factor`` are not made again)."""
    speeds = [float(v) for v in speeds]
    evaluated: dict[float, float] = {
        e.rpm: _least(e, spec.criteria)
        for e in known  # one judged on other criteria is no use
        if e.length_factor == length_factor and _judged_whole(e, spec)
    }

    def margin(rpm: float) -> float:
        # the root finding starts from the grid speeds it brackets
        if rpm not in evaluated:
            evaluated[rpm] = _least(evaluate(library, spec, rpm, length_factor), spec.criteria)
        return evaluated[rpm]

    values = [margin(v) for v in speeds]
    ranges = []
    k = 0
    while k < len(speeds):
        if values[k] < 0:
            k += 1
            continue
        first = k
        while k + 1 < len(speeds) and values[k + 1] >= 0:
            k += 1
        lo, hi = speeds[first], speeds[k]
        if first > 0:
            lo = _feasible_root(margin, speeds[first - 1], speeds[first])
        if k + 1 < len(speeds):
            hi = _feasible_root(margin, speeds[k + 1], speeds[k])
        ranges.append((lo, hi))
        k += 1
    return ranges


def _feasible_root(margin, outside: float, inside: float) -> float:
    """Where ``margin`` crosses 0 between ``outside`` (< 0) and ``inside`` (>= 0), on the
    feasible side of the crossing."""
    root = brentq(margin, min(outside, inside), max(outside, inside), rtol=EDGE_RTOL, xtol=1e-12)
    return root if margin(root) >= 0 else root + math.copysign(2 * EDGE_RTOL * abs(root), inside - outside)


def design(library: TableLibrary, spec: DesignSpec) -> DesignResult:
    """The smallest blender length over the searched speeds that meets ``spec``, the speed
    ranges in which the library's own blender meets it, and every speed's feasible lengths."""
    speeds = speed_grid(library, spec)
    rows = speed_rows(library, spec, speeds)
    feasible = [r for r in rows if r.feasible]
    ranges = speed_ranges(library, spec, speeds, known=[e for r in rows for e in r.scanned])
    library_rpm = tuple(v for v, _ in library.points)
    notes: list[str] = []
    if not ranges:
        notes.append(f"the library's own {library.length_m:g}-m blender meets the spec at none of the speeds searched")
    if not feasible:
        notes.append(
            f"no blender of {spec.length_factor_min:g}-{spec.length_factor_max:g} x {library.length_m:g} m "
            "at these speeds meets the spec"
        )
        return DesignResult(spec, library_rpm, library.length_m, rows, None, ranges, notes)
    best = min(feasible, key=lambda r: r.length_factor_lo).at_lo
    if math.isclose(best.length_factor, spec.length_factor_min, rel_tol=1e-9):
        notes.append(
            f"the smallest length searched ({spec.length_factor_min:g} x) already meets the spec: a shorter "
            "blender may too, but the rescaling is not trusted below it"
        )
    if len(feasible) < len(rows):
        notes.append("no length meets the spec at " + ", ".join(f"{r.rpm:g}" for r in rows if not r.feasible) + " rpm")
    return DesignResult(spec, library_rpm, library.length_m, rows, best, ranges, notes)


# --------------------------------------------------------------------------- throughput
#: Total feed rates scanned over the feed library's range before the edge is refined.
FEED_SCAN_POINTS = 9


@dataclass(frozen=True)
class FeedLibrary:
    """DEM runs of one blender at one speed and several total feed rates: each run's
    steady reference (one window, :func:`pbm.fill.steady_table`) keyed by its total feed
    [particles/s], and the fill law of their steady points (``exponents``). A feed between
    two runs takes their references interpolated (:func:`pbm.studies.interpolate_tables`)
    under the one law. ``pbm_config``: the feed weights, the rate mode and the A share
    (its feed rates); ``rpm``, ``length_m``: the blender."""

    points: tuple[tuple[float, VelocityTable], ...]
    exponents: tuple[tuple[float, float], ...]
    pbm_config: PbmConfig
    rpm: float
    length_m: float

    @property
    def feed_range(self) -> tuple[float, float]:
        return self.points[0][0], self.points[-1][0]

    def config_at(self, total: float) -> PbmConfig:
        """The PBM configuration at the total feed ``total`` [particles/s], same A share."""
        a, b = self.pbm_config.feed_rate_a_per_s, self.pbm_config.feed_rate_b_per_s
        share = a / (a + b)
        return self.pbm_config.model_copy(
            update={
                "feed_rate_a_per_s": total * share,
                "feed_rate_b_per_s": total * (1 - share),
                "rate_law": "fill",
                "fill_exponents": [list(e) for e in self.exponents],
            }
        )


def feed_library(
    runs: list[tuple[float, VelocityTable]], pbm_config: PbmConfig, rpm: float, length_m: float
) -> FeedLibrary:
    """The :class:`FeedLibrary` of ``runs`` (total feed, table), its law fitted in
    ``pbm_config.rates``' rates. Raises ConfigError for fewer than two distinct feeds.
    A feed left None in ``pbm_config`` is the first run's operating point's (pbm.feed)."""
    pbm_config = resolve_feed(pbm_config, runs[0][1])[0] if runs else pbm_config
    feeds = sorted(float(f) for f, _ in runs)
    if len(runs) < 2 or len(set(feeds)) != len(feeds):
        raise ConfigError(f"a feed library needs >= 2 runs at distinct feed rates, got {feeds}")
    if not pbm_config.feed_rate_a_per_s + pbm_config.feed_rate_b_per_s > 0:
        raise ConfigError("the feed library's configuration feeds nothing: its A share is undefined")
    law = fit_fill_law([fill_samples(t, pbm_config.rates) for _, t in runs])
    points = tuple(
        sorted(
            ((float(f), steady_table(t, steady_windows(t)).replace(t=np.zeros(1))) for f, t in runs),
            key=lambda p: p[0],
        )
    )
    return FeedLibrary(points, tuple(map(tuple, law.beta.tolist())), pbm_config, float(rpm), float(length_m))


@single_threaded_blas()
def evaluate_feed(feeds: FeedLibrary, spec: DesignSpec, total: float) -> Evaluation:
    """The outlet quantities and margins of the library's blender fed ``total``
    [particles/s] (inside the library's range), its rates following the fill."""
    config = feeds.config_at(total)
    system = stationary_system(interpolate_tables(feeds.points, total), config)
    return _judged(spec, system, config, feeds.rpm, 1.0, float(total))


@dataclass(frozen=True)
class ThroughputResult:
    """The largest total feed [particles/s] in the library's range at which its blender
    meets the spec (``best``: None when no feed does), the feeds scanned (those whose
    residence time fails without their composition, :class:`Evaluation`), and notes."""

    feed_range: tuple[float, float]
    best: Evaluation | None
    scanned: list[Evaluation]
    notes: list[str]

    def to_dict(self) -> dict[str, Any]:
        return {
            "feed_range_per_s": list(self.feed_range),
            "best": None if self.best is None else self.best.to_dict(),
            "scanned": [e.to_dict() for e in self.scanned],
            "notes": list(self.notes),
        }


def max_feed(feeds: FeedLibrary, spec: DesignSpec) -> ThroughputResult:
    """The largest total feed inside the feed library's range at which its blender meets
    ``spec``: a log-spaced scan, then the edge refined by root finding on the least margin
    between the last feasible feed and the next. Higher feeds are outside the library:
    refused, never extrapolated (a note says when the top of the range still meets it)."""
    lo, hi = feeds.feed_range
    evaluated: dict[float, Evaluation] = {}

    def at(f: float) -> Evaluation:
        # the root finding starts from the scanned feeds it brackets, and ends on one
        f = float(f)
        if f not in evaluated:
            evaluated[f] = evaluate_feed(feeds, spec, f)
        return evaluated[f]

    grid = np.geomspace(lo, hi, FEED_SCAN_POINTS)
    scanned = [at(f) for f in grid]
    ok = [e.feasible for e in scanned]
    notes: list[str] = []
    if not any(ok):
        notes.append(f"no feed in the library's range {lo:g}-{hi:g} /s meets the spec")
        return ThroughputResult((lo, hi), None, scanned, notes)
    last = max(k for k, good in enumerate(ok) if good)
    if last == len(grid) - 1:
        notes.append(
            f"the library's highest feed ({hi:g} /s) still meets the spec: a higher one may too, but it is "
            "outside the runs the law was fitted to (a DEM run there is needed)"
        )
        return ThroughputResult((lo, hi), scanned[-1], scanned, notes)

    def least(f: float) -> float:
        return _least(at(f), spec.criteria)

    edge = _feasible_root(least, float(grid[last + 1]), float(grid[last]))
    if not all(ok[: last + 1]):
        notes.append(
            "not met at the lower feeds scanned: "
            + ", ".join(f"{g:.4g}" for g, k in zip(grid[: last + 1], ok[: last + 1]) if not k)
            + " /s"
        )
    return ThroughputResult((lo, hi), at(edge), scanned, notes)
