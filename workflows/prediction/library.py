"""A DEM library and the one transport law fitted to it: what ``pbmdem predict`` runs on.

A library is a set of DEM results files with compartment sequences, at several operating
points. :func:`fit_library` fits one K-phase chain to every particle of every run
(:func:`dem.phases.law.fit_law`), each rate exp(x . beta) of covariates x built from the
run's operating point (:func:`covariate_columns`), and refits it once without each run
(started from the whole library's law, so a fit left out costs a fraction of the first).
The laws left out are what the prediction intervals are calibrated on
(:mod:`workflows.prediction.calibration`): each run predicted by a law that never saw it.

The covariates (the constant always first):

* ``speed``: log(impeller speed / :data:`REFERENCE_RPM`);
* ``length``: log(slice length / :data:`REFERENCE_SLICE_M`): a longer blender on the same
  number of slices has longer slices, crossed more slowly;
* ``position``: the slice's centre from inlet (-0.5) to weir (+0.5);
* ``feed``: log(total feed rate / :data:`REFERENCE_FEED_PER_S`), the same in every slice
  of a run (a proxy of the fill: the bed deepens with the feed);
* ``speed2``, ``position2``: the squares of ``speed`` and ``position`` (a law curved in
  speed; the inlet wall and the weir at both ends of the slices);
* ``weir``: 1 in the last slice, 0 elsewhere: its forward move is the discharge over the
  weir, not a blade's push into the next slice; ``weir_speed``, ``weir_feed``,
  ``weir_length``: ``weir`` times ``speed``, ``feed``, ``length`` (the discharge answers
  the bed's depth at the weir otherwise than the blades' transport does);
* ``blades``: the blade stations in the slice (0, 1 or 2): a blender of another length
  keeps its station spacing, so its slices hold other numbers of stations, and a slice's
  transport is its stations' (the law's rates tied to the blade sections, not to the
  slice's index);
* ``push``: the slice's forward stations less its backward ones (-1, 0 or 1): the paddles
  alternate, so a blender of another length ends on another orientation at the weir, and
  one with an odd number of stations pushes forward once more than back;
* ``gap``: log(gap from the last blade station to the weir / :data:`REFERENCE_GAP_M`),
  the same in every slice: the stations keep their spacing, so the bladeless stretch before
  the weir, where the bed piles up unpushed, comes and goes with the length (0.76-1.37 of
  the baseline's over the shipped lengths) and moves the hold-up by several per cent.

The axial law carries the residence time and the slices' hold-ups. The transverse moves
(across y, which carry the outlet's composition) come from each run's table (its phase
model's transverse rates, the same in every phase) as a least-squares law of the run's
speed, length and feed per compartment (:class:`TransverseLaw`).

Each fit is cached in ``<out>/fits/`` under a hash of its runs' digests and settings, so an
interrupted library fit resumes where it stopped and a refit with one run more redoes only
what that run changes.
"""

from __future__ import annotations

import hashlib
import json
import math
import multiprocessing
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import h5py
import numpy as np

from coupling.errors import ConfigError
from coupling.files import regular_file, stored_digest
from coupling.jsonable import json_ready, write_json
from coupling.operating import OperatingPoint
from dem.phases.data import first_compartments, prepare, steady_window
from dem.phases.diagnostics import chapman_kolmogorov
from dem.phases.law import LawRun, PhaseLaw, fit_law
from dem.phases.settings import PHASE_LAG_S, PhaseSettings
from dem.summary import Estimate
from workflows.pipeline.log import Log, stderr_log
from workflows.pipeline.results import load_results, run_operating_point
from workflows.prediction.covariates import (
    AXIAL_SLICES,
    run_covariates,
)
from workflows.prediction.profile import ProfileLaw

if TYPE_CHECKING:
    from dem.config import DemConfig

COVARIATES = (
    "speed",
    "length",
    "position",
    "feed",
    "speed2",
    "position2",
    "weir",
    "weir_speed",
    "weir_feed",
    "weir_length",
    "blades",
    "push",
    "gap",
)
#: the law's form, chosen by the held-out log-likelihood of the runs predicted from inside
#: the others' domain (``pbmdem library fit --covariates ...`` on the 13 shipped runs; the
#: alternatives and their scores: workflows/reference/library/PREDICTION.md)
DEFAULT_COVARIATES = ("speed", "length", "position", "feed", "speed2", "position2", "weir", "push")
#: the transverse law's covariates: those of the run, not of the slice (it is fitted per
#: compartment)
TRANSVERSE_COVARIATES = ("speed", "length", "feed", "speed2")
#: the law's phases. On the 13 shipped runs (the shipped covariates) four beat three on the
#: held-out log-likelihood of the interpolated runs (-1.03326 against -1.03671 nats per
#: particle-step) and of the extrapolated ones, and narrow every interval (`pbmdem library
#: fit --phases 3|4`; workflows/reference/library/PREDICTION.md)
LIBRARY_PHASES = 4
#: EM iterations of the whole library's fit, and of each fit with one run left out (it
#: starts from the whole library's law). On the 13 shipped runs, from 150 to 500
#: iterations of the whole fit the hold-ups moved by at most 1.4 %.
FIT_ITERATIONS = 500
LEFT_OUT_ITERATIONS = 150
FIT_TOL = 1e-7
#: the lags of each run's Chapman-Kolmogorov test of the law [s]
CK_LAGS_S = (1.0, 2.0, 5.0, 10.0)
#: what a library file says it is
FORMAT = "pbmdem-library"
#: 3: the calibration holds the slices' zone law; 4: the record carries its digest (:data:`DIGEST_KEY`)
VERSION = 4
#: the agreement table's quantities a prediction gives (the keys of ``summary.json``),
#: the slices' hold-ups after them as ``holdup_slice_<i>``
SCALAR_KEYS = (
    "mean_residence_time_s",
    "rtd_variance_s2",
    "little_mean_residence_time_s",
    "holdup",
    "outflow_per_s",
    "C_A",
    "rsd_outlet",
    "lacey_outlet",
)
#: the quantities compared on an absolute scale (fractions near their bounds); every
#: other one is positive and compared by the log of its ratio
ABSOLUTE_KEYS = ("C_A", "lacey_outlet")


def line_alone(key: str, point: OperatingPoint | None = None) -> float:
    """The law's value of ``key`` where it is predicted by its correction's line alone
    (``Calibration.direct``): 0 on an absolute scale, 1 on the log scale, so that the line
    is fitted to the DEM's values themselves. The outlet's RSD is a spread relative to the
    A fraction p of the feed at ``point``: a well-mixed sample of n particles has an RSD of
    sqrt((1 - p) / (p n)), so its line is fitted to the DEM's values over sqrt((1 - p) / p)
    (1 at half and half, as every shipped run) and a point at another share follows it."""
    if key in ABSOLUTE_KEYS:
        return 0.0
    if key == "rsd_outlet" and point is not None:
        share = point.feed_rate_a_per_s / point.feed_rate_total_per_s
        return math.sqrt((1.0 - share) / share) if 0.0 < share < 1.0 else 1.0
    return 1.0


#: what the correction of the law's predictions may be a linear function of
#: (:func:`correction_row`): the run covariates of :func:`run_covariates` and the squares
#: of length and feed, and ``last`` (:func:`last_push`)
CORRECTION_TERMS = ("speed", "speed2", "length", "length2", "feed", "feed2", "gap", "last")
#: the correction's form. ``last`` narrows the mean residence time's intervals of the 16
#: shipped runs, each left out, from 7.3-8.8 to 3.0-4.4 % (median; the law misses it most
#: where the last blade station pushes towards the weir); with ``gap`` beside it the
#: unseen runs' check keeps the run changed on every axis (a last station pushing, 43 mm
#: before the weir) inside on its residence time and hold-up, which ``last`` alone misses.
#: The form was chosen on both checks before the chain was timed by the slices' zone law
#: (then 89.6 % of the runs' values held left out, 96.7 % of the unseen runs'); timed, it
#: holds 98.6 % left out (``law/calibration.md``, "The correction's form";
#: ``law/unseen/check.md``; ``pbmdem library fit --correction ...``)
DEFAULT_CORRECTION = ("speed", "length", "gap", "feed", "last")
#: the degrees of freedom a correction covariate must leave (:func:`workflows.prediction.predict.fit_correction`)
CORRECTION_DOF = 2


#: the fields of a DEM configuration that are not its physics, per section: the law's axes
#: (the length, and with it the stations' count and the last one's place) and what
#: :data:`~workflows.prediction.predict.FIXED` already carries, the run's length, a feed
#: step (the prediction is of the steady state before it), the simulation box, the
#: numerics, and what the deck never reads (the steel's density). Every other field (the
#: particles' and steel's elastic constants, the contacts, the A share of the feed, the
#: first station, the blades' shape, the barrel's facets, the weir, the outlet and the feed
#: zones), and the stations' spacing, is the physics a point must share with the library's
#: runs (:func:`physics_of`): a field added later is checked by default
NOT_PHYSICS = {
    "geometry": (
        "length_m",
        "diameter_m",
        "blade_stations",
        "last_blade_x_m",
        "blade_pattern",
        "box_margin_m",
        "inlet_margin_m",
    ),
    "particles": ("diameter_m", "diameter_sd_m", "size_classes"),
    "steel": ("density_kg_m3",),
    "operation": ("feed_rate_total_per_s", "impeller_rpm", "duration_s", "step_time_s", "step_factor_a"),
    "numerics": None,
    "run": None,
    "tables": None,
}


#: two settings of the physics within this relative difference are the same (a station
#: typed to 0.1 mm moves the spacing by a few 1e-4)
PHYSICS_RTOL = 1e-3


def physics_of(dem: DemConfig) -> dict[str, Any]:
    """The physics of a DEM configuration (:data:`NOT_PHYSICS`), as "section.field": value,
    and ``geometry.blade_spacing_m``, the mean distance between neighbouring stations."""
    out = {}
    for section, values in dem.model_dump().items():
        skipped = NOT_PHYSICS.get(section, ())
        if skipped is None or not isinstance(values, dict):
            continue
        out.update({f"{section}.{k}": v for k, v in values.items() if k not in skipped})
    g = dem.geometry
    if g.blade_stations > 1:
        out["geometry.blade_spacing_m"] = (g.last_blade_x_m - g.first_blade_x_m) / (g.blade_stations - 1)
    return out


def same_setting(a: Any, b: Any) -> bool:
    """Two settings of the physics are the same: numbers within :data:`PHYSICS_RTOL`."""
    numbers = (int, float)
    if isinstance(a, numbers) and isinstance(b, numbers) and not isinstance(a, bool) and not isinstance(b, bool):
        return math.isclose(float(a), float(b), rel_tol=PHYSICS_RTOL, abs_tol=1e-12)
    return a == b


def physics_differences(a: dict[str, Any], b: dict[str, Any]) -> list[str]:
    """The settings in which the physics ``a`` and ``b`` differ (one lacking it included)."""
    return sorted(k for k in set(a) | set(b) if k not in a or k not in b or not same_setting(a[k], b[k]))


def slice_key(i: int) -> str:
    return f"holdup_slice_{i + 1}"


def quantity_keys(nx: int = AXIAL_SLICES) -> tuple[str, ...]:
    return (*SCALAR_KEYS, *(slice_key(i) for i in range(nx)))


def last_push(point: OperatingPoint, pattern: str) -> float:
    """+1 when the blade station nearest the weir pushes towards it ("F" of ``pattern``,
    cycled from the inlet), -1 when it pushes back (an operating point has at least one
    station): a blender with one station more or less turns its last paddle round, and the
    bed before the weir with it."""
    if not pattern or set(pattern) - {"F", "B"}:
        raise ConfigError(f"blade pattern {pattern!r}: letters F (forward) and B (backward) only")
    n = len(point.blade_x_m)
    return 1.0 if pattern[(n - 1) % len(pattern)] == "F" else -1.0


def correction_row(point: OperatingPoint, names: Sequence[str], pattern: str = "") -> np.ndarray:
    """The constant and the correction covariates ``names`` (:data:`CORRECTION_TERMS`) of a
    run at ``point`` whose stations ``pattern`` orients (needed by ``last`` alone: a
    ConfigError without it)."""
    values = run_covariates(point)
    values["length2"] = values["length"] ** 2
    values["feed2"] = values["feed"] ** 2
    if "last" in names:
        values["last"] = last_push(point, pattern)
    return np.array([1.0] + [values[name] for name in names])


def covariate_columns(point: OperatingPoint, nx: int, names: Sequence[str], pattern: str) -> np.ndarray:
    """(NX, 1 + len(names)) covariates of the ``nx`` axial slices of a run at ``point``
    whose blade stations are oriented by ``pattern`` (the geometry's ``blade_pattern``,
    cycled from the inlet: "F" pushes towards the weir, "B" back) (module docstring), the
    constant first. Raises ConfigError for an unknown name or pattern."""
    if not pattern or set(pattern) - {"F", "B"}:
        raise ConfigError(f"blade pattern {pattern!r}: letters F (forward) and B (backward) only")
    unknown = sorted(set(names) - set(COVARIATES))
    if unknown:
        raise ConfigError(f"covariates {unknown} unknown; valid: {', '.join(COVARIATES)}")
    position = (np.arange(nx) + 0.5) / nx - 0.5
    per_run = run_covariates(point, nx)
    values = {name: np.full(nx, value) for name, value in per_run.items()}
    weir = (np.arange(nx) == nx - 1).astype(float)
    edges = np.linspace(0.0, point.length_m, nx + 1)
    edges[-1] += 1e-12  # a station at the weir belongs to the last slice
    stations = np.asarray(point.blade_x_m, dtype=float)
    values["blades"] = np.histogram(stations, bins=edges)[0].astype(float)
    forward = np.array([1.0 if pattern[s % len(pattern)] == "F" else -1.0 for s in range(stations.size)])
    values["push"] = np.histogram(stations, bins=edges, weights=forward)[0]
    values.update({"position": position, "position2": position**2, "weir": weir})
    values.update({f"weir_{name}": weir * per_run[name] for name in ("speed", "feed", "length")})
    return np.column_stack([np.ones(nx)] + [values[name] for name in names])


def dem_quantities(summary) -> dict[str, Estimate]:
    """The DEM's value and 95 % interval of every quantity of :func:`quantity_keys` that
    ``summary`` (:class:`dem.summary.DemSummary`) holds."""
    steady = summary.steady or {}
    out = {key: Estimate.from_record(steady[key]) for key in SCALAR_KEYS if steady.get(key)}
    if summary.has_pooled_rtd:
        pooled = summary.pooled_rtd
        for key, estimate in (
            ("mean_residence_time_s", pooled.mean_residence_time_s),
            ("rtd_variance_s2", pooled.rtd_variance_s2),
        ):
            if estimate is not None:
                out[key] = estimate
    slices = steady.get("holdup_by_slice")
    if slices and len(slices["value"]) % AXIAL_SLICES == 0:
        # a finer grid's slices summed onto the law's
        per = len(slices["value"]) // AXIAL_SLICES
        for i in range(AXIAL_SLICES):
            part = slice(i * per, (i + 1) * per)
            low = np.asarray(slices["low"][part], dtype=float)
            high = np.asarray(slices["high"][part], dtype=float)
            value = float(np.sum(slices["value"][part]))
            # the summed intervals' half-widths in quadrature (the slices' errors are not
            # known to be correlated)
            half = float(np.sqrt(np.sum(((high - low) / 2) ** 2)))
            out[slice_key(i)] = (
                Estimate(value, value - half, value + half)
                if per > 1
                else Estimate(value, float(low[0]), float(high[0]))
            )
    return {key: estimate for key, estimate in out.items() if estimate is not None}


@dataclass(frozen=True)
class LibraryRun:
    """One run of a library: its law data, operating point, the DEM's quantities with their
    intervals, the feed's inlet distribution over the axial slices (2, NX) [particles/s],
    and the transverse rates of its table's phase model (2, NX, NY) [1/s], None when its
    table has no phase model or another number of slices than the law's."""

    name: str
    path: Path
    digest: str
    law_run: LawRun
    point: OperatingPoint
    blade_pattern: str
    seed: int | None
    dem: dict[str, Estimate]
    entering: np.ndarray
    transverse: np.ndarray | None
    #: its configuration's physics (:func:`physics_of`)
    physics: dict[str, Any] = field(default_factory=dict)

    @property
    def holdup(self) -> Estimate:
        return self.dem["holdup"]

    @property
    def little_s(self) -> Estimate:
        return self.dem["little_mean_residence_time_s"]


def file_digest(path: Path) -> str:
    """The results file's stored content digest (its bytes' when it has none); ConfigError
    naming the file when it is not a readable HDF5 file."""
    try:
        with h5py.File(path, "r") as h5:
            digest = stored_digest(h5)
    except OSError as exc:
        raise ConfigError(f"{path} is not a readable HDF5 file: {' '.join(str(exc).split())}") from None
    if digest is None:  # an unsigned file: its bytes
        digest = hashlib.sha256(path.read_bytes()).hexdigest()
    return digest


def library_run(path: str | Path, names: Sequence[str], lag_s: float = PHASE_LAG_S) -> LibraryRun:
    """:class:`LibraryRun` of the results file ``path``: its particles that entered in the
    steady window (and those inside then), on :data:`AXIAL_SLICES` slices. Raises
    ConfigError naming the file when it has no sequences or no steady state."""
    path = regular_file(path, "a library run", ConfigError).resolve()
    results, config = load_results(path)
    sequences, summary = results.sequences, results.summary
    if sequences is None:
        raise ConfigError(f"{path}: the results carry no compartment sequences to fit a law to")
    if summary.steady_time is None or not summary.steady:
        raise ConfigError(f"{path}: the DEM run never reached a steady state to fit and judge a law on")
    if sequences.nx % AXIAL_SLICES:
        raise ConfigError(f"{path}: {sequences.nx} slices cannot be coarsened to the law's {AXIAL_SLICES}")
    point = run_operating_point(results.table, config)
    lag = PhaseSettings(lag_s=lag_s).lag_dumps(sequences.interval_s)
    data = prepare(sequences, steady_window(sequences, summary.steady_time), (AXIAL_SLICES, 1), lag=lag, residents=True)
    feed = point.feed_rate_total_per_s
    entering = first_compartments(data)[:2]
    entering = entering / max(entering.sum(), 1e-300) * feed
    name = f"{path.name} ({point.impeller_rpm:g} rpm, {feed:g} /s, {point.length_m:g} m)"
    pattern = config.dem.geometry.blade_pattern
    table = results.table
    transverse = None
    if table.phases is not None and table.nx == AXIAL_SLICES:
        transverse = table.phases.rates[0, 2:].copy()
    dem = dem_quantities(summary)
    missing = [key for key in ("holdup", "little_mean_residence_time_s") if key not in dem]
    if missing:
        raise ConfigError(f"{path}: the DEM summary lacks {missing}, which a library run needs")
    return LibraryRun(
        name,
        path,
        file_digest(path),
        LawRun(data, covariate_columns(point, AXIAL_SLICES, names, pattern), name),
        point,
        pattern,
        config.dem.numerics.seed,
        dem,
        entering,
        transverse,
        physics_of(config.dem),
    )


# ------------------------------------------------------------------ the transverse law
@dataclass(frozen=True)
class TransverseLaw:
    """The transverse rates (y_pos, y_neg) of every compartment as exp(x . beta) of the
    run's covariates x (:data:`TRANSVERSE_COVARIATES`, the constant first), fitted by least
    squares on the logs of the library's rates; ``coefficients`` (2, NX, NY, P), NaN where
    no run moves (a wall): rate 0 there."""

    coefficients: np.ndarray
    names: tuple[str, ...] = TRANSVERSE_COVARIATES

    @property
    def grid(self) -> tuple[int, int]:
        return int(self.coefficients.shape[1]), int(self.coefficients.shape[2])

    def rates(self, point: OperatingPoint) -> np.ndarray:
        """(2, NX, NY) transverse rates [1/s] at ``point``."""
        values = run_covariates(point, self.grid[0])
        x = np.array([1.0] + [values[name] for name in self.names])
        log_rates = self.coefficients @ x
        return np.where(np.isfinite(log_rates), np.exp(np.nan_to_num(log_rates, nan=-np.inf)), 0.0)

    def record(self) -> dict[str, Any]:
        return {
            "names": list(self.names),
            "coefficients": np.where(np.isnan(self.coefficients), None, self.coefficients).tolist(),
        }

    @classmethod
    def from_record(cls, record: dict, source: str) -> TransverseLaw:
        try:
            names = tuple(str(n) for n in record["names"])
            beta = np.array(record["coefficients"], dtype=float)
        except (KeyError, TypeError, ValueError) as exc:
            raise ConfigError(f"{source}: not a transverse law ({type(exc).__name__}: {exc})") from None
        if beta.ndim != 4 or beta.shape[0] != 2 or beta.shape[3] != 1 + len(names) or set(names) - set(COVARIATES):
            raise ConfigError(f"{source}: transverse coefficients of shape {beta.shape} for covariates {list(names)}")
        return cls(beta, names)


def fit_transverse(runs: Sequence[LibraryRun]) -> TransverseLaw:
    """:class:`TransverseLaw` of the runs with transverse rates; the coefficients of a
    covariate no two runs tell apart are 0 (least squares of minimum norm)."""
    usable = [r for r in runs if r.transverse is not None]
    if not usable:
        raise ConfigError("no run of the library has a phase model with transverse rates to fit a transverse law to")
    shapes = {r.transverse.shape for r in usable}
    if len(shapes) != 1:
        raise ConfigError(f"the runs' transverse grids differ ({sorted(shapes)}): one library needs one grid")
    names = TRANSVERSE_COVARIATES
    x = np.array([[1.0] + [run_covariates(r.point, AXIAL_SLICES)[n] for n in names] for r in usable])
    rates = np.stack([r.transverse for r in usable])  # (runs, 2, NX, NY)
    moving = (rates > 0).all(axis=0)
    logs = np.log(np.where(rates > 0, rates, 1.0)).reshape(len(usable), -1)
    beta, *_ = np.linalg.lstsq(x, logs, rcond=None)  # (P, 2 * NX * NY)
    beta = beta.T.reshape(*rates.shape[1:], len(names) + 1)
    return TransverseLaw(np.where(moving[..., None], beta, np.nan), names)


# ------------------------------------------------------------------ the library model
@dataclass(frozen=True)
class LibraryEntry:
    """What the library model keeps of one run: its file, digest, operating point, seed and
    the DEM's quantities (value and 95 % interval)."""

    file: str
    digest: str
    point: OperatingPoint
    blade_pattern: str
    seed: int | None
    dem: dict[str, Estimate]
    #: its configuration's physics (:func:`physics_of`); empty
    #: in a library made before they were kept
    physics: dict[str, Any] = field(default_factory=dict)

    def record(self) -> dict[str, Any]:
        return {
            "file": self.file,
            "digest": self.digest,
            "point": self.point.record(),
            "blade_pattern": self.blade_pattern,
            "seed": self.seed,
            "dem": {key: e.record() for key, e in self.dem.items()},
            "physics": dict(self.physics),
        }

    @classmethod
    def from_record(cls, record: dict, source: str) -> LibraryEntry:
        return cls(
            str(record["file"]),
            str(record["digest"]),
            OperatingPoint.from_record(record["point"], source),
            str(record["blade_pattern"]),
            None if record.get("seed") is None else int(record["seed"]),
            {str(k): Estimate.from_record(v) for k, v in dict(record["dem"]).items()},
            {str(k): v for k, v in dict(record.get("physics") or {}).items()},
        )


@dataclass(frozen=True)
class Calibration:
    """The library's laws at the library's own runs, what the correction of every
    prediction (:func:`workflows.prediction.predict.correction`) is fitted to and checked
    on: ``whole`` [key] the whole library's law at each run, ``left_out`` [key] [m] [j] the
    law fitted without run m at run j; ``inside`` per run: whether it lies inside the
    domain of the other runs (its prediction without it is an interpolation);
    ``covariates`` the correction's (:data:`CORRECTION_TERMS`)."""

    whole: dict[str, list[float]]
    left_out: dict[str, list[list[float]]]
    inside: list[bool]
    covariates: tuple[str, ...] = ()
    #: the slices' zone law (:mod:`workflows.prediction.profile`) of every run, and of every
    #: run but one (in the order of the runs); None for a library too small for it, whose
    #: slices keep the correction's lines
    profile: ProfileLaw | None = None
    profile_left_out: tuple[ProfileLaw, ...] = ()
    #: the values of every quantity but the slices' are those of the chain timed by the
    #: zone law (each slice's rates scaled so that it holds the zone law's hold-up:
    #: :func:`workflows.prediction.predict.timed`), not of the law's chain as fitted
    timed: bool = False
    #: the quantities predicted by their correction's line alone: their values here are
    #: :func:`line_alone`'s, and a prediction takes that, not the law's chain
    direct: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        n = len(self.inside)
        for key, values in self.whole.items():
            rows = self.left_out.get(key)
            if len(values) != n or rows is None or len(rows) != n or any(len(r) != n for r in rows):
                raise ValueError(f"the calibration's values of {key} are not one per run ({n} runs)")
        unknown = sorted(set(self.covariates) - set(CORRECTION_TERMS))
        if unknown:
            raise ValueError(f"correction covariates {unknown} unknown; valid: {', '.join(CORRECTION_TERMS)}")
        stray = sorted(set(self.direct) - set(self.whole))
        if stray:
            raise ValueError(f"quantities {stray} predicted by their line alone have no calibration values")
        if self.profile is not None and len(self.profile_left_out) != n:
            raise ValueError(f"{len(self.profile_left_out)} slice zone laws left out for {n} runs")

    def time_scale(self) -> ProfileLaw | None:
        """The zone law the chain is timed by, None for the chain as fitted. Raises
        ValueError for values timed by a zone law the calibration no longer holds (a model
        made only for checking, e.g. its slices from the lines or a part of its runs):
        predicting from it would add lines fitted to the timed chain to the untimed one."""
        if not self.timed:
            return None
        if self.profile is None:
            raise ValueError(
                "the calibration's values are the chain timed by the slices' zone law, which it no longer holds: "
                "it can be checked, not predicted from"
            )
        return self.profile

    def record(self) -> dict[str, Any]:
        def clean(values: list[float]) -> list[float | None]:
            return [v if math.isfinite(v) else None for v in values]

        return {
            "whole": {k: clean(v) for k, v in self.whole.items()},
            "left_out": {k: [clean(row) for row in rows] for k, rows in self.left_out.items()},
            "inside": list(self.inside),
            "covariates": list(self.covariates),
            "profile": None if self.profile is None else self.profile.record(),
            "profile_left_out": [law.record() for law in self.profile_left_out],
            "timed": self.timed,
            "direct": list(self.direct),
        }

    @classmethod
    def from_record(cls, record: dict) -> Calibration:
        def read(values: list) -> list[float]:
            return [math.nan if v is None else float(v) for v in values]

        if record.get("timed") and record.get("profile") is None:
            raise ValueError("a calibration timed by the slices' zone law has no zone law")
        return cls(
            {str(k): read(v) for k, v in record["whole"].items()},
            {str(k): [read(row) for row in rows] for k, rows in record["left_out"].items()},
            [bool(v) for v in record["inside"]],
            tuple(str(v) for v in record.get("covariates") or ()),
            None if record.get("profile") is None else ProfileLaw.from_record(record["profile"]),
            tuple(ProfileLaw.from_record(r) for r in record.get("profile_left_out") or ()),
            bool(record.get("timed", False)),
            tuple(str(k) for k in record.get("direct") or ()),
        )


@dataclass(frozen=True)
class LibraryModel:
    """One law for a library (module docstring): the law fitted to every run, the law
    fitted without each run (``left_out``, in the order of ``runs``), the transverse laws
    alike, and the calibration of the intervals on the runs left out (None until made)."""

    law: PhaseLaw
    transverse: TransverseLaw
    runs: tuple[LibraryEntry, ...]
    left_out: tuple[PhaseLaw, ...]
    transverse_left_out: tuple[TransverseLaw, ...]
    interval_s: float
    calibration: Calibration | None = None
    settings: dict[str, Any] = field(default_factory=dict)
    #: each run's log-likelihood under the law fitted without it [nats per particle-step]
    left_out_scores: tuple[float, ...] = ()
    #: each run's Chapman-Kolmogorov test of the whole library's law on its particles
    #: (:func:`dem.phases.diagnostics.chapman_kolmogorov` at :data:`CK_LAGS_S`): (largest
    #: |predicted - observed| slice probability, largest z)
    ck: tuple[tuple[float, float], ...] = ()

    @property
    def names(self) -> tuple[str, ...]:
        """The law's covariates besides the constant."""
        return self.law.covariate_names[1:]

    @property
    def grid(self) -> tuple[int, int]:
        return self.transverse.grid

    @property
    def blade_pattern(self) -> str:
        """The orientation of the library's blade stations (every run's)."""
        return self.runs[0].blade_pattern

    def record(self) -> dict[str, Any]:
        return {
            "format": FORMAT,
            "version": VERSION,
            "settings": self.settings,
            "interval_s": self.interval_s,
            "law": self.law.record(),
            "transverse": self.transverse.record(),
            "runs": [r.record() for r in self.runs],
            "left_out": [law.record() for law in self.left_out],
            "transverse_left_out": [t.record() for t in self.transverse_left_out],
            "calibration": None if self.calibration is None else self.calibration.record(),
            "left_out_scores": list(self.left_out_scores),
            "ck": [list(c) for c in self.ck],
        }

    @classmethod
    def from_record(cls, record: Any, source: str) -> LibraryModel:
        if not isinstance(record, dict) or record.get("format") != FORMAT:
            raise ConfigError(
                f"{source}: not a library model (no format {FORMAT!r}); make one with `pbmdem library fit`"
            )
        if record.get("version") != VERSION:
            raise ConfigError(
                f"{source}: library model version {record.get('version')!r}; this tool reads {VERSION}: "
                "refit it with `pbmdem library fit` (its fits' cache makes that quick)"
            )
        try:
            runs = tuple(LibraryEntry.from_record(r, source) for r in record["runs"])
            left = tuple(PhaseLaw.from_record(r, source) for r in record["left_out"])
            transverse_left = tuple(TransverseLaw.from_record(r, source) for r in record["transverse_left_out"])
            model = cls(
                PhaseLaw.from_record(record["law"], source),
                TransverseLaw.from_record(record["transverse"], source),
                runs,
                left,
                transverse_left,
                float(record["interval_s"]),
                None if record.get("calibration") is None else Calibration.from_record(record["calibration"]),
                dict(record.get("settings") or {}),
                tuple(float(v) for v in record.get("left_out_scores") or ()),
                tuple((float(a), float(b)) for a, b in record.get("ck") or ()),
            )
        except (AttributeError, KeyError, TypeError, ValueError) as exc:
            raise ConfigError(
                f"{source}: library model field missing or malformed ({type(exc).__name__}: {exc})"
            ) from None
        if len(left) != len(runs) or len(transverse_left) != len(runs):
            raise ConfigError(f"{source}: {len(runs)} runs but {len(left)} laws left out; expected one per run")
        return model


#: the key of a library model's integrity digest: the SHA-256 of the rest of its record
DIGEST_KEY = "sha256"


def record_digest(record: dict[str, Any]) -> str:
    """The SHA-256 of a library model's record (:func:`~coupling.jsonable.json_ready`
    values) without its digest, over its canonical JSON: a file whose content was edited or
    damaged but still parses no longer matches it."""
    rest = {k: v for k, v in record.items() if k != DIGEST_KEY}
    text = json.dumps(rest, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode()).hexdigest()


def save_model(model: LibraryModel, path: str | Path) -> Path:
    record = json_ready(model.record())
    return write_json(path, {**record, DIGEST_KEY: record_digest(record)})


def load_model(path: str | Path) -> LibraryModel:
    """The library model of the file ``path`` (or ``path/library.json``); raises
    ConfigError naming the file when it is missing or is not one."""
    path = Path(path)
    if path.is_dir():
        path = path / "library.json"
    path = regular_file(path, "a library model", ConfigError)
    try:
        record = json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ConfigError(f"{path}: not a library model (not JSON: {exc})") from None
    if isinstance(record, dict) and record.get("format") == FORMAT and record.get("version") == VERSION:
        if record.get(DIGEST_KEY) != record_digest(record):
            raise ConfigError(
                f"{path}: its content does not match its {DIGEST_KEY} digest (edited or damaged after "
                "`pbmdem library fit` wrote it); refit it with `pbmdem library fit --out DIR` (its fits' cache "
                "makes that quick)"
            )
    return LibraryModel.from_record(record, str(path))


# ------------------------------------------------------------------ fitting
@dataclass(frozen=True)
class FitSettings:
    """How a library is fitted: the law's phases and covariates, the EM's iterations for the
    whole library and for each fit left out, its stopping gain, and the covariates of the
    correction of its predictions (not the law's: a fit is cached without them)."""

    n_phases: int = LIBRARY_PHASES
    covariates: tuple[str, ...] = DEFAULT_COVARIATES
    iterations: int = FIT_ITERATIONS
    left_out_iterations: int = LEFT_OUT_ITERATIONS
    tol: float = FIT_TOL
    correction: tuple[str, ...] = DEFAULT_CORRECTION

    def __post_init__(self) -> None:
        unknown = sorted(set(self.covariates) - set(COVARIATES))
        if unknown:
            raise ConfigError(f"covariates {unknown} unknown; valid: {', '.join(COVARIATES)}")
        unknown = sorted(set(self.correction) - set(CORRECTION_TERMS))
        if unknown:
            raise ConfigError(f"correction covariates {unknown} unknown; valid: {', '.join(CORRECTION_TERMS)}")
        for name in ("n_phases", "iterations", "left_out_iterations"):
            value = getattr(self, name)
            if isinstance(value, bool) or int(value) != value or value < 1:
                raise ConfigError(f"{name} must be an integer >= 1, got {value!r}")
        if not self.tol > 0:
            raise ConfigError(f"tol must be > 0, got {self.tol!r}")

    def record(self) -> dict[str, Any]:
        return {
            "n_phases": self.n_phases,
            "covariates": list(self.covariates),
            "iterations": self.iterations,
            "left_out_iterations": self.left_out_iterations,
            "tol": self.tol,
            "correction": list(self.correction),
        }


def _fit_key(runs: Sequence[LibraryRun], settings: FitSettings, iterations: int, start: PhaseLaw | None) -> str:
    text = json.dumps(
        {
            "runs": sorted(r.digest for r in runs),
            "settings": {k: v for k, v in settings.record().items() if k != "correction"},
            "iterations": iterations,
            "start": None if start is None else start.record()["coefficients"],
        },
        sort_keys=True,
    )
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def cached_fit(
    runs: Sequence[LibraryRun],
    settings: FitSettings,
    iterations: int,
    cache: Path | None,
    start: PhaseLaw | None = None,
) -> PhaseLaw:
    """:func:`dem.phases.law.fit_law` of ``runs``, read from ``cache`` when it was made
    before (a file that does not read back as a law is refitted and replaced)."""
    key = _fit_key(runs, settings, iterations, start)
    path = None if cache is None else cache / f"law-{key}.json"
    if path is not None and path.is_file():
        try:
            return PhaseLaw.from_record(json.loads(path.read_text()), str(path))
        except (ConfigError, UnicodeDecodeError, json.JSONDecodeError):
            pass  # rebuilt below
    law = fit_law(
        [r.law_run for r in runs],
        settings.n_phases,
        ("1", *settings.covariates),
        iterations,
        settings.tol,
        start=start,
    )
    if path is not None:
        cache.mkdir(parents=True, exist_ok=True)
        write_json(path, law.record())
    return law


def load_runs(paths: Sequence[str | Path], settings: FitSettings) -> list[LibraryRun]:
    """The library's runs; raises ConfigError for fewer than 3, for one file given twice
    (by content: a copy would count one run's particles twice), or for runs whose blade
    patterns or physics (:func:`physics_of`) differ: the law varies neither."""
    runs = [library_run(p, settings.covariates) for p in paths]
    patterns = sorted({run.blade_pattern for run in runs})
    if len(patterns) > 1:
        raise ConfigError(f"the runs' blade patterns differ ({patterns}): one library needs one pattern")
    for run in runs[1:]:
        differ = physics_differences(run.physics, runs[0].physics)
        if differ:
            settings = ", ".join(f"{k} = {run.physics.get(k)}" for k in differ)
            first = ", ".join(f"{runs[0].physics.get(k)}" for k in differ)
            raise ConfigError(
                f"{run.path} has {settings} where {runs[0].path} has {first}: the library's law does not vary "
                "them, so one library holds runs of one physics"
            )
    seen: dict[str, Path] = {}
    for run in runs:
        if run.digest in seen:
            raise ConfigError(f"{run.path} is the same run as {seen[run.digest]}: a library holds each run once")
        seen[run.digest] = run.path
    if len(runs) < 3:
        raise ConfigError(f"a library needs at least 3 runs (one left out, two to fit), got {len(runs)}")
    return runs


def _left_out_fit(
    runs: Sequence[LibraryRun], settings: FitSettings, cache: Path | None, law: PhaseLaw, n: int
) -> PhaseLaw:
    """The law of ``runs`` but the ``n``-th, started from the whole library's ``law``."""
    rest = [r for m, r in enumerate(runs) if m != n]
    return cached_fit(rest, settings, settings.left_out_iterations, cache, start=law)


# A worker's runs, settings, cache and whole law, set once per process by its initializer
# rather than pickled with every task: the runs carry every particle's sequence.
_WORKER: tuple[Sequence[LibraryRun], FitSettings, Path | None, PhaseLaw] | None = None


def _worker_setup(*fit: Any) -> None:
    global _WORKER
    _WORKER = fit


def _worker_fit(n: int) -> PhaseLaw:
    assert _WORKER is not None, "_worker_setup runs first in each worker"
    return _left_out_fit(*_WORKER, n)


def fit_library(
    runs: Sequence[LibraryRun],
    settings: FitSettings = FitSettings(),
    cache: Path | None = None,
    log: Log = stderr_log,
    jobs: int = 1,
) -> LibraryModel:
    """The law of every run, and of every run but one for each (module docstring); the
    model without its calibration (:func:`workflows.prediction.calibration.calibrated`).
    The fits left out, independent of each other once the whole law is there, run in
    ``jobs`` processes; each is cached as it lands, so the result is the same for any
    ``jobs``."""
    log(f"law of {len(runs)} runs, {settings.iterations} EM iterations")
    law = cached_fit(runs, settings, settings.iterations, cache)
    if jobs == 1:
        left = []
        for n, run in enumerate(runs):
            log(f"law without {run.name}")
            left.append(_left_out_fit(runs, settings, cache, law, n))
    else:
        log(f"{len(runs)} laws, each without one run, in {jobs} processes")
        # fork: the workers inherit the runs instead of unpickling a copy each
        context = multiprocessing.get_context("fork")
        with ProcessPoolExecutor(jobs, context, _worker_setup, (runs, settings, cache, law)) as pool:
            futures = {pool.submit(_worker_fit, n): n for n in range(len(runs))}
            for future in as_completed(futures):
                log(f"law without {runs[futures[future]].name}")
            left = [future.result() for future in futures]
    scores = [law_left.score(run.law_run) / max(run.law_run.data.n_steps, 1) for law_left, run in zip(left, runs)]
    ck = []
    for run in runs:
        data = run.law_run.data
        test = chapman_kolmogorov(
            law.run_chain(run.law_run), data, tuple(round(v / data.interval_s) for v in CK_LAGS_S)
        )
        ck.append((test.max_abs_error(), test.max_z()))
    transverse = fit_transverse(runs)
    transverse_left = tuple(fit_transverse([r for m, r in enumerate(runs) if m != n]) for n in range(len(runs)))
    return LibraryModel(
        law,
        transverse,
        tuple(LibraryEntry(r.path.name, r.digest, r.point, r.blade_pattern, r.seed, r.dem, r.physics) for r in runs),
        tuple(left),
        transverse_left,
        float(runs[0].law_run.data.interval_s),
        None,
        settings.record(),
        tuple(scores),
        tuple(ck),
    )
