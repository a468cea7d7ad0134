"""The prediction intervals' calibration, and the check that they hold on runs left out.

The calibration (:func:`calibrated`) is the library's laws evaluated at the library's own
runs: the whole library's law at each, and each law fitted without one run at every run.
From it :func:`workflows.prediction.predict.corrections` fits the line of what a law
misses at the runs it knows, which corrects every prediction and gives its interval.

Whether those intervals hold is measured without the run judged (:func:`check`): run i
predicted by the law fitted without it, moved by the line of that law's misses on the
other runs, with that line's interval (an end run's at least the extrapolation floor of
the other end runs); the DEM's value inside that interval or not. Beside it, the DEM's
scatter between seeds, from the library's replicate pairs (two runs at one operating
point, :func:`seed_scatter`), and whether each prediction lies inside the DEM's interval
widened by that scatter (t(0.975, pairs) seed standard deviations: the scatter is measured
from that many pairs). :func:`alternatives` repeats the check for other forms of the line,
which is how its form is chosen; :func:`slice_sources` and :func:`chain_sources` compare the
sources each prediction may take its slices and its other quantities from.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from scipy.special import stdtrit

from coupling.errors import ConfigError
from coupling.files import regular_file
from coupling.operating import OperatingPoint
from workflows.pipeline.results import load_results, run_operating_point
from workflows.prediction.covariates import AXIAL_SLICES
from workflows.prediction.library import (
    ABSOLUTE_KEYS,
    DEFAULT_CORRECTION,
    Calibration,
    LibraryModel,
    dem_quantities,
    file_digest,
    line_alone,
    physics_differences,
    physics_of,
    quantity_keys,
    slice_key,
)
from workflows.prediction.predict import (
    LEVEL,
    Placement,
    PointValues,
    domain,
    end_runs,
    extrapolation_floor,
    floor_at,
    held_out,
    layout_floor,
    lone_layout_runs,
    placement,
    point_values,
    predict,
    residual,
    timed,
    timed_values,
)
from workflows.prediction.profile import ProfileLaw, fit_profile, refit, without_layouts

#: the headline quantities and the half-widths the issue asks of them, as fractions of the
#: value (slices: every slice)
USEFUL_HALF_WIDTH = {
    "mean_residence_time_s": 0.04,
    "holdup": 0.04,
    "rtd_variance_s2": 0.15,
    "holdup_slice": 0.08,
}


#: the quantities a change must have inside the DEM's interval (widened by the seed
#: scatter) for the law to predict it, and how many others it may miss
HEADLINE = ("mean_residence_time_s", "rtd_variance_s2", "little_mean_residence_time_s", "holdup")
MAY_MISS = 2


def _slice_of(key: str, family: str) -> bool:
    """``key`` is one slice's of ``family`` (``holdup_slice_3`` of ``holdup_slice``)."""
    head, _, tail = key.rpartition("_")
    return head == family and tail.isdigit()


def _others(model: LibraryModel, n: int) -> Placement:
    """Run ``n``'s place against the domain of the other runs (as
    :func:`workflows.prediction.predict.predict` would place it)."""
    others = domain([r.point for m, r in enumerate(model.runs) if m != n], model.blade_pattern)
    return placement(others, model.runs[n].point, model.blade_pattern)


@dataclass(frozen=True)
class Sources:
    """A library calibrated from each source :func:`calibrated` chooses between:
    ``chosen`` the one it keeps; ``fitted`` and ``timed`` the library with its slices from
    the zone law and its other quantities from the law's chain as fitted and timed by the
    zone law (both None where the library has no zone law or its slices keep the lines);
    ``zone`` and ``lines`` the two its slices were chosen between, the zone law on the
    chosen chain and the lines on the chain as fitted (both None without a zone law);
    ``layouts`` the zone law with and without its misses at the layouts the library has
    run, on the chain as fitted, which was chosen first (None where it has none)."""

    chosen: LibraryModel
    fitted: LibraryModel | None = None
    timed: LibraryModel | None = None
    zone: LibraryModel | None = None
    lines: LibraryModel | None = None
    layouts: tuple[LibraryModel, LibraryModel] | None = None
    #: per quantity of :data:`MIXING_KEYS`, the interval scores of every run left out from
    #: the law corrected and from the correction's line alone (:func:`line_alone_scores`)
    alone: dict[str, tuple[float, float]] = field(default_factory=dict)


def calibrated(model: LibraryModel, covariates: Sequence[str] | None = None) -> LibraryModel:
    """``model`` with its :class:`Calibration`: the whole library's law and each law left
    out at every run, whether each run lay inside the others' domain, and the correction's
    ``covariates`` (default: the model's settings', else
    :data:`~workflows.prediction.library.DEFAULT_CORRECTION`). Each choice of source is
    made on every run left out, by the interval score (:func:`interval_score`): where the
    library has a zone law of the bed, the other quantities from the law's chain as fitted
    or timed by it (:func:`chain_scores`); then the slices, scaled to that chain's
    hold-up, from the zone law or from the correction's lines (:func:`slice_scores`),
    the chain as fitted with the lines."""
    return sources(model, covariates).chosen


def sources(model: LibraryModel, covariates: Sequence[str] | None = None) -> Sources:
    """:func:`calibrated`'s choice, with the libraries it chose between."""
    names = tuple(covariates if covariates is not None else model.settings.get("correction", DEFAULT_CORRECTION))
    inside = [not _others(model, n).extrapolated for n in range(len(model.runs))]
    whole, left = _chains(model)
    profile, profiles = slice_profiles(model)
    calibration = _calibration([v.values for v in whole], [[v.values for v in row] for row in left], inside, names)
    model = replace(model, calibration=replace(calibration, profile=profile, profile_left_out=profiles))
    if profile is None:
        return _with_lines_alone(Sources(model))
    layouts = None
    if profile.layouts is not None:
        layouts = (model, _without_layouts(model))
        by_layouts, alone = _scores(*layouts, lambda key: _slice_of(key, "holdup_slice"))
        model = model if by_layouts < alone else layouts[1]
    timed_model = _timed_model(model, whole, left)
    by_timed, by_chain = chain_scores(timed_model, model)
    chain = timed_model if by_timed < by_chain else model
    # each source judged as it would be shipped: the zone law's slices scaled to the chosen
    # chain's hold-up (predict.held_in_total), the lines' to the chain as fitted's (a timed
    # chain needs the zone law); a tie (neither bounds a slice both can) keeps the lines
    lines = without_profile(model)
    by_zone, by_lines = slice_scores(chain, lines)
    if not by_zone < by_lines:
        return _with_lines_alone(Sources(lines, zone=chain, lines=lines, layouts=layouts))
    return _with_lines_alone(Sources(chain, model, timed_model, chain, lines, layouts))


def _without_layouts(model: LibraryModel) -> LibraryModel:
    """``model`` (calibrated, with the slices' zone law) with its zone laws alone, without
    their misses at the layouts the library has run."""
    cal = model.calibration
    return replace(
        model,
        calibration=replace(
            cal,
            profile=without_layouts(cal.profile),
            profile_left_out=tuple(without_layouts(law) for law in cal.profile_left_out),
        ),
    )


def _with_lines_alone(found: Sources) -> Sources:
    """``found`` with each quantity of :data:`MIXING_KEYS` predicted by the law corrected
    or by its correction's line alone, whichever has the lower interval score on every run
    left out (:func:`line_alone_scores`; a tie keeps the law)."""
    scores = line_alone_scores(found.chosen)
    keys = [key for key, (law, alone) in scores.items() if alone < law]
    return replace(found, chosen=lines_alone(found.chosen, keys), alone=scores)


def _score(value: float | None) -> str:
    """A held-out log-likelihood in a table: "-" for a run no law was fitted without (one the
    library does not hold)."""
    return "-" if value is None or not math.isfinite(value) else f"{value:.4f}"


def lines_alone(model: LibraryModel, keys: Sequence[str]) -> LibraryModel:
    """``model`` (calibrated) with the quantities ``keys`` predicted by their correction's
    line alone: their law values at every run replaced by
    :func:`~workflows.prediction.library.line_alone`'s, so that each line is fitted to the
    DEM's values themselves."""
    if not keys:
        return model
    cal = model.calibration
    n = len(cal.inside)
    whole, left = dict(cal.whole), dict(cal.left_out)
    alone = {key: [line_alone(key, r.point) for r in model.runs] for key in keys}
    for key in keys:
        whole[key] = alone[key]
        left[key] = [list(alone[key]) for _ in range(n)]
    direct = tuple(dict.fromkeys([*cal.direct, *keys]))
    return replace(model, calibration=replace(cal, whole=whole, left_out=left, direct=direct))


#: the quantities that may be predicted by their correction's line alone: the outlet's
#: mixing indices, which the law gives as binomial samples of its chain's expected outlet
#: counts, the part of it least tied to the particles' moves it is fitted to. The residence
#: time, the hold-up and the bed are what the law carries: chosen between the two by the
#: scores of a few runs left out, they would take the line on noise (the six-run synthetic
#: library of tests/workflows/prediction/test_synthetic_library.py, a known law, took it for
#: all four headline quantities, and its intervals then held 71 of 84 unseen values)
MIXING_KEYS = ("rsd_outlet", "lacey_outlet")


def line_alone_scores(model: LibraryModel, keys: Sequence[str] = MIXING_KEYS) -> dict[str, tuple[float, float]]:
    """Per quantity of ``keys``: (the law corrected, the correction's line alone), the
    interval score (:func:`interval_score`) of every run left out by each. A law fitted to
    the particles' moves may carry no more of a quantity than the operating point does (the
    outlet's mixing indices, sampled from the chain's expected outlet counts): the line
    alone then predicts it better."""
    keys = [k for k in keys if k in model.calibration.whole and k not in model.calibration.direct]
    law, alone = check(model), check(lines_alone(model, keys))
    return {key: _paired(law, alone, lambda k, key=key: k == key) for key in keys}


def _chains(model: LibraryModel) -> tuple[list[PointValues], list[list[PointValues]]]:
    """The whole library's chain at every run, and each chain left out at every run."""
    whole = [_chain(model.law, model.transverse, model, entry.point) for entry in model.runs]
    left = [
        [_chain(law, transverse, model, entry.point) for entry in model.runs]
        for law, transverse in zip(model.left_out, model.transverse_left_out)
    ]
    return whole, left


def _timed_model(
    model: LibraryModel, whole: Sequence[PointValues], left: Sequence[Sequence[PointValues]]
) -> LibraryModel:
    """``model`` (calibrated, with the slices' zone law) with its values those of the
    chains ``whole`` and ``left`` (:func:`_chains`) timed by the zone law, the whole
    library's and each left out."""
    cal = model.calibration
    points = [entry.point for entry in model.runs]
    pattern = model.blade_pattern
    timed_whole = [timed_values(v, timed(v, cal.profile, p, pattern)) for v, p in zip(whole, points)]
    timed_left = [
        [timed_values(v, timed(v, law, p, pattern)) for v, p in zip(row, points)]
        for row, law in zip(left, cal.profile_left_out)
    ]
    chained = _calibration(timed_whole, timed_left, cal.inside, cal.covariates)
    return replace(
        model, calibration=replace(chained, profile=cal.profile, profile_left_out=cal.profile_left_out, timed=True)
    )


def _calibration(
    whole: Sequence[dict[str, float]], left: Sequence[Sequence[dict[str, float]]], inside: list[bool], names: tuple
) -> Calibration:
    keys = quantity_keys()
    return Calibration(
        {key: [v[key] for v in whole] for key in keys},
        {key: [[v[key] for v in row] for row in left] for key in keys},
        inside,
        names,
    )


def without_profile(model: LibraryModel) -> LibraryModel:
    """``model`` (calibrated) with its slices taken from the correction's lines. A model
    timed by the zone law (``calibration.timed``) keeps the timed chain's values for its
    other quantities, so it can be checked (:func:`check`) but not predicted from
    (:meth:`~workflows.prediction.library.Calibration.time_scale` refuses)."""
    return replace(model, calibration=replace(model.calibration, profile=None, profile_left_out=()))


def interval_score(rows: Sequence[CheckedQuantity]) -> float:
    """The mean 95 % interval score of ``rows`` on the log scale (Gneiting and Raftery's
    proper score: the interval's width, plus 2 / 0.05 times how far the DEM's value lies
    outside it); infinite when a row has no interval."""
    scores = []
    for r in rows:
        if not (r.low > 0 and r.high > 0 and r.dem > 0):
            return math.inf
        low, high, dem = math.log(r.low), math.log(r.high), math.log(r.dem)
        scores.append(high - low + 2 / (1 - LEVEL) * (max(low - dem, 0.0) + max(dem - high, 0.0)))
    return float(np.mean(scores)) if scores else math.inf


def _scores(a: LibraryModel, b: LibraryModel, keep) -> tuple[float, float]:
    """The interval scores (:func:`interval_score`) of ``a`` and ``b``'s checks over the
    rows of the quantities ``keep`` accepts (:func:`_paired`)."""
    return _paired(check(a), check(b), keep)


def _paired(a: Check, b: Check, keep) -> tuple[float, float]:
    """The interval scores of the checks ``a`` and ``b`` over the rows of the quantities
    ``keep`` accepts, where both give an interval: a value neither can bound says nothing
    of which is better."""

    def rows(result: Check) -> dict[tuple[str, str], CheckedQuantity]:
        return {(r.run, r.key): r for r in result.rows if keep(r.key)}

    first, second = rows(a), rows(b)
    both = [
        k
        for k in first
        if k in second and math.isfinite(interval_score([first[k]])) and math.isfinite(interval_score([second[k]]))
    ]
    return interval_score([first[k] for k in both]), interval_score([second[k] for k in both])


def slice_scores(zone: LibraryModel, lines: LibraryModel) -> tuple[float, float]:
    """(the slices' zone law of ``zone``, the correction's lines of ``lines``): the interval
    score (:func:`interval_score`) of every run's slices predicted without it by each. The
    slices take the lower (:func:`calibrated`): the zone law carries what one blender
    shows of the bed to another, the lines follow each slice alone, which only a library of
    one blade layout supports."""
    if zone.calibration.profile is None:
        raise ConfigError("the library model has no slice zone law to score")
    return _scores(zone, lines, lambda key: _slice_of(key, "holdup_slice"))


def chain_scores(timed_model: LibraryModel, chain_model: LibraryModel) -> tuple[float, float]:
    """(the chain timed by the zone law, the law's chain as fitted): the interval score of
    every run's quantities but the slices, predicted without it from each. A law fitted to
    the particles' moves may keep a slow phase that holds what the bed does not (left out,
    the shipped law put 80 % too many particles in the x1.25 blender, whose slices the
    zone law missed by 3 %); timed, the chain keeps its moves and takes the bed's time
    scale (:func:`~workflows.prediction.predict.timed`)."""
    return _scores(timed_model, chain_model, lambda key: not _slice_of(key, "holdup_slice"))


def slice_holdups(model: LibraryModel) -> np.ndarray:
    """(runs, slices) the DEM's hold-up of each slice of each library run, NaN where a run
    lacks it: what the slices' zone law is fitted to."""
    keys = [slice_key(i) for i in range(AXIAL_SLICES)]
    return np.array([[e.dem[k].value if k in e.dem else math.nan for k in keys] for e in model.runs])


def slice_profiles(model: LibraryModel) -> tuple[ProfileLaw | None, tuple[ProfileLaw, ...]]:
    """The slices' zone law of every run of ``model``, and of every run but one (the
    swept half-width chosen once, on every run); (None, ()) when the runs left out leave
    it no degree of freedom: the slices then keep the correction's lines."""
    held = slice_holdups(model)
    points = [e.point for e in model.runs]
    try:
        whole = fit_profile(points, held, model.blade_pattern)
        left = tuple(
            refit(whole, [p for m, p in enumerate(points) if m != n], np.delete(held, n, axis=0))
            for n in range(len(points))
        )
    except ConfigError:
        return None, ()
    return whole, left


def recalibrated(model: LibraryModel, covariates: Sequence[str]) -> LibraryModel:
    """``model`` (calibrated) with another correction form; no law is evaluated again."""
    if model.calibration is None:
        return calibrated(model, covariates)
    return replace(model, calibration=replace(model.calibration, covariates=tuple(covariates)))


def _chain(law, transverse, model: LibraryModel, point: OperatingPoint) -> PointValues:
    return point_values(law, transverse, point, model.blade_pattern, model.interval_s)


class SeedScatter(NamedTuple):
    """The DEM's scatter between seeds (:func:`seed_scatter`): per quantity its standard
    deviation ``sd`` on the quantity's scale and ``dof`` the pairs it was measured from;
    ``pairs`` the replicate pairs' files."""

    sd: dict[str, float]
    pairs: list[tuple[str, str]]
    dof: dict[str, int]


def replicate_pairs(model: LibraryModel) -> list[tuple[int, int]]:
    """The pairs (a < b) of library runs at one operating point (other seeds)."""
    runs = model.runs
    return [
        (a, b)
        for a in range(len(runs))
        for b in range(a + 1, len(runs))
        if not runs[a].point.differences(runs[b].point)
    ]


def twin_rows(judged: str, dem: dict, by: str, twin: dict, scatter: SeedScatter) -> list[CheckedQuantity]:
    """Run ``judged`` (its DEM quantities ``dem``) with the DEM quantities ``twin`` of the
    run ``by`` at its operating point taken as its prediction, value and interval: the
    rows of the verdict a second DEM run gets, judged like the law's (labelled
    "``judged`` by ``by``")."""
    label = f"{judged} by {by}"
    return [
        CheckedQuantity(
            label,
            key,
            float(dem[key].value),
            float(dem[key].low),
            float(dem[key].high),
            float(twin[key].value),
            float(twin[key].low),
            float(twin[key].high),
            scatter.sd.get(key, 0.0),
            True,
            scatter.dof.get(key, 0),
        )
        for key in quantity_keys()
        if key in dem and key in twin
    ]


def seed_scatter(model: LibraryModel, leave: tuple[int, int] | None = None) -> SeedScatter:
    """Per quantity, the DEM's standard deviation between seeds on the quantity's scale,
    from every pair of library runs at one operating point (half the mean square of their
    differences) but the pair ``leave``; and the pairs. Empty without a pair."""
    pairs = [pair for pair in replicate_pairs(model) if pair != leave]
    sd, dof = {}, {}
    for key in quantity_keys():
        diffs = []
        for a, b in pairs:
            ea, eb = model.runs[a].dem.get(key), model.runs[b].dem.get(key)
            if ea is not None and eb is not None:
                diffs.append(residual(key, ea.value, eb.value))
        diffs = [d for d in diffs if math.isfinite(d)]
        if diffs:
            sd[key] = math.sqrt(float(np.mean(np.square(diffs))) / 2)
            dof[key] = len(diffs)
    return SeedScatter(sd, [(model.runs[a].file, model.runs[b].file) for a, b in pairs], dof)


@dataclass(frozen=True)
class CheckedQuantity:
    """One run's quantity predicted without it: the DEM's value and interval, the
    prediction and its interval, and the two verdicts (module docstring)."""

    run: str
    key: str
    dem: float
    dem_low: float
    dem_high: float
    value: float
    low: float
    high: float
    seed_sd: float
    #: the run lay inside the other runs' domain: its prediction was an interpolation
    interpolated: bool = True
    #: the degrees of freedom of ``seed_sd``: the replicate pairs it was measured from
    seed_dof: int = 0

    @property
    def covered(self) -> bool:
        """The DEM's value lies inside the prediction interval."""
        return self.low <= self.dem <= self.high

    @property
    def inside_widened(self) -> bool:
        """The prediction lies inside the DEM's interval widened by the seed scatter (in
        quadrature with its half-width): the 95 % range of the operating point's value
        about this run's, t(0.975, pairs) seed standard deviations, the standard deviation
        measured from that many replicate pairs."""
        half = (self.dem_high - self.dem_low) / 2
        t = float(stdtrit(self.seed_dof, 0.5 + LEVEL / 2)) if self.seed_dof >= 1 else 0.0
        seed = t * self.seed_sd * (1.0 if self.key in ABSOLUTE_KEYS else abs(self.dem))
        return abs(self.value - self.dem) <= math.hypot(half, seed)

    @property
    def relative_half_width(self) -> float:
        return (self.high - self.low) / 2 / abs(self.value) if self.value else math.nan

    def record(self) -> dict[str, Any]:
        return {
            "run": self.run,
            "key": self.key,
            "dem": self.dem,
            "dem_low": self.dem_low,
            "dem_high": self.dem_high,
            "value": self.value,
            "low": self.low,
            "high": self.high,
            "covered": self.covered,
            "inside_widened": self.inside_widened,
            "interpolated": self.interpolated,
        }


@dataclass(frozen=True)
class Check:
    rows: tuple[CheckedQuantity, ...]
    seed_sd: dict[str, float]
    seed_pairs: tuple[tuple[str, str], ...]
    #: the operating points of runs that are not the library's (:func:`judge_results`)
    points: dict[str, OperatingPoint] = field(default_factory=dict)
    #: each replicate judged with its twin's DEM values as the prediction (:func:`twin_rows`)
    twins: tuple[CheckedQuantity, ...] = ()

    def _rows(self, interpolated: bool | None) -> list[CheckedQuantity]:
        return [r for r in self.rows if interpolated is None or r.interpolated == interpolated]

    def coverage(self, interpolated: bool | None = True) -> float:
        """The share of the DEM's values inside their prediction intervals, over the runs
        predicted from inside the others' domain (``interpolated`` True), from outside it
        (False), or all (None)."""
        rows = [r for r in self._rows(interpolated) if math.isfinite(r.low)]
        return sum(r.covered for r in rows) / len(rows) if rows else math.nan

    def runs(self) -> list[str]:
        return list(dict.fromkeys(r.run for r in self.rows))

    def of_run(self, run: str) -> list[CheckedQuantity]:
        return [r for r in self.rows if r.run == run]

    def verdict(self, run: str) -> tuple[bool, str]:
        """Whether the law predicts ``run`` left out: every :data:`HEADLINE` quantity and
        all but :data:`MAY_MISS` of the others inside the DEM's interval widened by the seed
        scatter; and the verdict's text."""
        rows = self.of_run(run)
        missed = [r.key for r in rows if not r.inside_widened]
        ok = self.headline_inside(run) and len(missed) <= MAY_MISS
        inside = f"{len(rows) - len(missed)}/{len(rows)} inside the DEM's interval widened by the seed scatter"
        if ok:
            return True, f"the library's law predicts this ({inside})"
        return False, f"needs a new DEM run: {inside}; missed {', '.join(missed)}"

    def headline_inside(self, run: str) -> bool:
        """Every :data:`HEADLINE` quantity of ``run`` lies inside the DEM's interval widened
        by the seed scatter: the first half of :meth:`verdict`."""
        rows = {r.key: r for r in self.of_run(run)}
        return bool(rows) and all(rows[k].inside_widened for k in HEADLINE if k in rows)

    def median_half_width(self, key: str, interpolated: bool | None = True) -> float:
        """The median half-width of ``key`` (or of every slice's ``key_<i>``) as a fraction of
        the value, over the runs of ``interpolated`` (:meth:`coverage`)."""
        values = [r.relative_half_width for r in self._rows(interpolated) if r.key == key or _slice_of(r.key, key)]
        return float(np.median(values)) if values else math.nan

    def record(self) -> dict[str, Any]:
        return {
            "coverage_interpolated": self.coverage(True),
            "coverage_extrapolated": self.coverage(False),
            "rows": [r.record() for r in self.rows],
            "seed_sd": self.seed_sd,
            "seed_pairs": [list(p) for p in self.seed_pairs],
            "twins": [r.record() for r in self.twins],
            "median_relative_half_width": {key: self.median_half_width(key) for key in USEFUL_HALF_WIDTH},
            "target_half_width": USEFUL_HALF_WIDTH,
        }


def check(model: LibraryModel) -> Check:
    """Every run predicted by the law fitted without it, corrected by the line of that
    law's misses on the other runs (module docstring); ``model`` calibrated first when it
    is not."""
    if model.calibration is None:
        model = calibrated(model)
    scatter, pairs, dof = seed_scatter(model)
    rows = []
    for n, entry in enumerate(model.runs):
        place = _others(model, n)
        for q in held_out(model, n, place.widening, floor_at(model, place, leave=n)):
            dem = entry.dem.get(q.key)
            if dem is None:
                continue
            key = q.key
            rows.append(
                CheckedQuantity(
                    entry.file,
                    key,
                    float(dem.value),
                    float(dem.low),
                    float(dem.high),
                    q.value,
                    q.low,
                    q.high,
                    scatter.get(key, 0.0),
                    not place.extrapolated,
                    dof.get(key, 0),
                )
            )
    twins = []
    for a, b in replicate_pairs(model):
        # the pair's own difference left out of the scatter it is judged by: with it, a
        # pair of two or three could not fail (its difference is at most sqrt(2 n) sd,
        # under t(0.975, n) sd)
        others = seed_scatter(model, leave=(a, b))
        if not others.pairs:
            continue
        for judged, by in ((model.runs[a], model.runs[b]), (model.runs[b], model.runs[a])):
            twins += twin_rows(judged.file, judged.dem, by.file, by.dem, others)
    return Check(tuple(rows), scatter, tuple(pairs), twins=tuple(twins))


def judge_results(model: LibraryModel, paths: Sequence[str | Path], extrapolate: bool = False) -> Check:
    """DEM runs the library does not hold, each predicted by the library's law
    (:func:`workflows.prediction.predict.predict`) and judged like :func:`check` judges the
    runs left out. A run outside the domain is judged only with ``extrapolate`` (else
    ConfigError names it); a run the library holds is refused (it was fitted to it)."""
    seeds = seed_scatter(model)
    scatter, pairs, dof = seeds
    held = {r.digest: r.file for r in model.runs}
    rows, points, twins = [], {}, []
    for path in paths:
        path = regular_file(path, "a DEM results file", ConfigError)
        digest = file_digest(path)
        if digest in held:
            raise ConfigError(
                f"{path} is the library's run {held[digest]}: judge it with `pbmdem library fit`, left out"
            )
        results, config = load_results(path)
        point = run_operating_point(results.table, config)
        points[path.name] = point
        physics = physics_of(config.dem)
        try:
            prediction = predict(model, point, config.dem.geometry.blade_pattern, extrapolate, physics)
        except ConfigError as exc:
            raise ConfigError(f"{path}: {exc}") from None
        dem = dem_quantities(results.summary)
        for entry in model.runs:
            # a replicate: the same point and physics (a library made before its runs'
            # physics were kept has none to compare)
            if not point.differences(entry.point) and not (
                entry.physics and physics_differences(physics, entry.physics)
            ):
                twins += twin_rows(path.name, dem, entry.file, entry.dem, seeds)
        for q in prediction.quantities:
            if q.key in dem:
                d = dem[q.key]
                rows.append(
                    CheckedQuantity(
                        path.name,
                        q.key,
                        float(d.value),
                        float(d.low),
                        float(d.high),
                        q.value,
                        q.low,
                        q.high,
                        scatter.get(q.key, 0.0),
                        not prediction.extrapolated,
                        dof.get(q.key, 0),
                    )
                )
    return Check(tuple(rows), scatter, tuple(pairs), points, tuple(twins))


#: what :func:`markdown` says a check of runs the library does not hold is
NOT_HELD = (
    "Each run predicted by the library's law, which was not fitted to it; inside the library's domain an "
    "interpolation, else an extrapolation (labelled and widened)."
)


def markdown(model: LibraryModel, result: Check, intro: str | None = None) -> str:
    """The check as tables: per run, the quantities covered and inside the widened DEM
    interval; per quantity, the coverage and the median relative half-width. ``intro``:
    what the runs were predicted by (default: each by the law fitted without it)."""
    keys = quantity_keys()
    n_keys = len(keys)
    point = {r.file: r.point for r in model.runs}
    point.update(result.points)
    scores = dict(zip((r.file for r in model.runs), model.left_out_scores))
    ck = dict(zip((r.file for r in model.runs), model.ck))
    mean_scores = "" if intro else _mean_scores(model, result) + _law_misses(model)
    intro = intro or (
        f"Each run predicted by the law fitted without it ({len(model.runs)} runs, {n_keys} quantities each), its "
        "interval calibrated without it. A run inside the other runs' domain is an interpolation, calibrated on the "
        "other such runs; one outside it (an end of a range, or a combination beyond the others' convex hull) an "
        "extrapolation, calibrated on every other run and widened by its distance."
    )
    lines = [
        f"{intro} Coverage of the 95 % intervals: {_percent(result.coverage(True))} interpolated, "
        f"{_percent(result.coverage(False))} extrapolated, {_percent(result.coverage(None))} in all.{mean_scores}"
        + _verdicts(result),
        "",
        f"| run | rpm | feed [/s] | length [m] | predicted | held-out log-likelihood [nats/step] | CK test of the "
        f"law: largest error, z | DEM inside the prediction interval (of {n_keys}) | prediction inside the DEM "
        "interval widened by seed scatter | verdict |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for run in result.runs():
        rows = result.of_run(run)
        p = point[run]
        _ok, verdict = result.verdict(run)
        how = "interpolated" if rows[0].interpolated else "extrapolated"
        lines.append(
            f"| {run} | {p.impeller_rpm:g} | {p.feed_rate_total_per_s:g} | {p.length_m:g} | {how} | "
            f"{_score(scores.get(run))} | {_ck(ck.get(run))} | {sum(r.covered for r in rows)} | "
            f"{sum(r.inside_widened for r in rows)} | "
            f"{verdict} |"
        )
    lines += [
        "",
        "| quantity | coverage, interpolated | median half-width, interpolated [% of value] | error, interpolated "
        "(rms) | coverage, extrapolated | median half-width, extrapolated [%] | error, extrapolated (rms) | seed "
        "scatter sd |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for key in keys:
        inside = [r for r in result.rows if r.key == key and r.interpolated]
        outside = [r for r in result.rows if r.key == key and not r.interpolated]
        seed = result.seed_sd.get(key, math.nan)
        scale = "" if key in ABSOLUTE_KEYS else " (log)"
        lines.append(
            f"| {key} | {_share(inside)} | {_half(inside)} | {_rms_error(inside)} | {_share(outside)} | "
            f"{_half(outside)} | {_rms_error(outside)} | {seed:.3g}{scale} |"
        )
    slices = [r for r in result.rows if _slice_of(r.key, "holdup_slice")]
    if slices:
        lines += [
            "",
            "Every slice's error (root mean square of log DEM / prediction): "
            f"{_rms_error([r for r in slices if r.interpolated])} interpolated, "
            f"{_rms_error([r for r in slices if not r.interpolated])} extrapolated.",
        ]
    lines += ["", _floors(model, keys)]
    if result.seed_pairs:
        n = len(result.seed_pairs)
        t = float(stdtrit(n, 0.5 + LEVEL / 2))
        lines += [
            "",
            "Seed pairs: " + "; ".join(f"{a} and {b}" for a, b in result.seed_pairs) + ". The DEM's interval is "
            f"widened (in quadrature) by t(0.975, {n}) = {t:.2f} seed standard deviations: the standard deviation is "
            f"measured from {n} pair{'s' if n > 1 else ''}." + _twin_verdicts(result),
        ]
    return "\n".join(lines)


def _floors(model: LibraryModel, keys: Sequence[str]) -> str:
    """The least half-widths of :func:`~workflows.prediction.predict.floors`, as the
    library's predictions take them, with the runs they come from."""
    parts = []
    for what, runs, floor in (
        ("beyond the runs' hull", end_runs(model), extrapolation_floor(model)),
        ("at a blade layout no run has", lone_layout_runs(model), layout_floor(model)),
    ):
        if not floor:
            parts.append(f"{what}, none (no such run)")
            continue
        m = len(runs)
        names = ", ".join(model.runs[n].file for n in runs)
        shown = [k for k in keys if k in floor and not _slice_of(k, "holdup_slice")]
        slices = [100 * floor[k] for k in keys if k in floor and _slice_of(k, "holdup_slice")]
        values = ", ".join(f"{k} {_floor_value(k, floor[k])}" for k in shown)
        if slices:
            values += f", a slice {min(slices):.1f}-{max(slices):.1f} %"
        parts.append(f"{what}, t(0.975, {m}) = {stdtrit(m, 0.5 + LEVEL / 2):.2f} times that of {names}: {values}")
    return (
        "The least half-widths a prediction keeps, each the root mean square error of the runs named, each predicted "
        "without it (`workflows.prediction.predict.floors`): " + "; ".join(parts) + "."
    )


def _floor_value(key: str, half: float) -> str:
    return f"{half:.3g}" if key in ABSOLUTE_KEYS else f"{100 * half:.1f} %"


def _twin_verdicts(result: Check) -> str:
    """The verdict a second DEM run gets (:func:`twin_rows`): what the law's is measured
    against."""
    if not result.twins:
        return ""
    judged = Check(result.twins, result.seed_sd, result.seed_pairs)
    runs = judged.runs()
    parts = []
    for run in runs:
        rows, ok = judged.of_run(run), judged.verdict(run)[0]
        missed = [r.key for r in rows if not r.inside_widened]
        parts.append(
            f"{run}: {len(rows) - len(missed)}/{len(rows)}"
            + (f" (missed {', '.join(missed)})" if missed else "")
            + ("" if ok else ", not predicted")
        )
    good = sum(judged.verdict(run)[0] for run in runs)
    return (
        " A second DEM run judged the same way (each replicate with its twin's values and intervals taken as its "
        "prediction; a library pair judged by the scatter of the other pairs, a run the library does not hold by "
        f"every pair's) is a prediction the verdict accepts on {good} of {len(runs)}: " + "; ".join(parts) + "."
    )


#: the correction forms :func:`alternatives` compares (the constant alone is the law's mean
#: error)
CORRECTION_ALTERNATIVES = (
    (),
    ("speed",),
    ("speed", "length", "feed"),
    ("speed", "speed2", "length", "feed"),
    ("speed", "length", "gap", "feed"),
    ("speed", "speed2", "length", "gap", "feed"),
    ("speed", "speed2", "length", "gap", "feed", "feed2"),
    ("speed", "speed2", "length", "length2", "gap", "feed"),
    ("speed", "feed", "last"),
    ("speed", "length", "feed", "last"),
    ("speed", "length", "gap", "feed", "last"),
    ("speed", "speed2", "length", "feed", "last"),
)


def alternatives(model: LibraryModel, forms: Sequence[Sequence[str]] = CORRECTION_ALTERNATIVES) -> str:
    """A markdown table of :func:`check` with each correction form of ``forms``: what the
    model's form was chosen from (the laws are not refitted: only the line changes)."""
    chosen = tuple(model.calibration.covariates) if model.calibration is not None else ()
    head = ["| correction covariates | coverage, interpolated | extrapolated | all |"]
    head[0] += "".join(f" median half-width {key}, interpolated [%] |" for key in USEFUL_HALF_WIDTH)
    head[0] += " runs the law predicts |"
    head.append("|" + " --- |" * (5 + len(USEFUL_HALF_WIDTH)))
    for form in dict.fromkeys([tuple(f) for f in forms] + [chosen]):
        result = check(recalibrated(model, form))
        name = ", ".join(form) or "none (the mean error)"
        mark = " (chosen)" if form == chosen else ""
        widths = "".join(f" {100 * result.median_half_width(key):.1f} |" for key in USEFUL_HALF_WIDTH)
        good = sum(result.verdict(run)[0] for run in result.runs())
        head.append(
            f"| {name}{mark} | {_percent(result.coverage(True))} | {_percent(result.coverage(False))} | "
            f"{_percent(result.coverage(None))} |{widths} {good}/{len(result.runs())} |"
        )
    return (
        "## The correction's form\n\nEach form checked like the tables above (every run left out); "
        "the targets are half-widths of "
        + ", ".join(f"{100 * v:g} % ({k})" for k, v in USEFUL_HALF_WIDTH.items())
        + " and a coverage of at least 90 %.\n\n"
        + "\n".join(head)
    )


def _source_rows(
    head: str, sources: Sequence[tuple[str, LibraryModel, bool]], keep, widths: Sequence[str]
) -> list[str]:
    """The rows of a table comparing ``sources`` (label, calibrated model, chosen) on the
    rows of the quantities ``keep`` accepts, checked like :func:`check`: coverage, the
    median half-widths of ``widths`` and the interval score."""
    rows = [
        f"| {head} | coverage, interpolated | extrapolated | all | "
        + "".join(f"median half-width {k}, interpolated [%] | " for k in widths)
        + "interval score [log] |",
        "|" + " --- |" * (5 + len(widths)),
    ]
    for label, m, chosen in sources:
        result = check(m)
        kept = tuple(r for r in result.rows if keep(r.key))
        part = Check(kept, result.seed_sd, result.seed_pairs)
        half = "".join(f"{100 * part.median_half_width(k):.1f} | " for k in widths)
        rows.append(
            f"| {label}{' (chosen)' if chosen else ''} | {_percent(part.coverage(True))} | "
            f"{_percent(part.coverage(False))} | {_percent(part.coverage(None))} | {half}{interval_score(kept):.4f} |"
        )
    return rows


def slice_sources(found: Sources) -> str:
    """A markdown table of the slices' hold-ups checked like :func:`check` from each
    source :func:`calibrated` chose between (:func:`slice_scores`): the zone law and the
    correction's lines, and which the library's predictions take."""
    if found.zone is None or found.lines is None:
        sources = [("a correction line per slice", found.chosen, True)]
    else:
        zone_chosen = found.chosen.calibration.profile is not None
        sources = [
            ("the zone law of the bed (`workflows/prediction/profile.py`)", found.zone, zone_chosen),
            ("a correction line per slice", found.lines, not zone_chosen),
        ]
    rows = _source_rows("slices from", sources, lambda key: _slice_of(key, "holdup_slice"), ["holdup_slice"])
    return (
        "## The slices' hold-ups\n\nEvery run's slices predicted without it, from each source, scaled to the "
        "predicted hold-up; the predictions take the one of the lower interval score (the mean width of the 95 % "
        "intervals on the log scale plus 40 times any miss).\n\n" + "\n".join(rows)
    )


def layout_sources(found: Sources) -> str:
    """A markdown table of the slices' hold-ups checked like :func:`check` from the zone law
    with and without its misses at the layouts the library has run, and which the library's
    predictions take; empty where the zone law has none."""
    if found.layouts is None:
        return ""
    # the zone law kept (or, where the slices took the lines, the one they were chosen over)
    zone = found.zone if found.zone is not None else found.chosen
    used = found.chosen.calibration.profile is not None
    with_chosen = zone.calibration.profile is not None and zone.calibration.profile.layouts is not None
    sources = [
        ("the zone law with its layouts' misses of the shares", found.layouts[0], used and with_chosen),
        ("the zone law alone", found.layouts[1], used and not with_chosen),
    ]
    rows = _source_rows("slices from", sources, lambda key: _slice_of(key, "holdup_slice"), ["holdup_slice"])
    return (
        "## The layouts the library has run\n\nEvery run's slices predicted without it by the zone law, on the "
        "law's chain as fitted, with and without what the zone law misses of each slice's share at the layouts "
        "(length and blade stations) the other runs share with it (`workflows/prediction/profile.py`, "
        "`LayoutShares`; a run whose layout no other run has keeps the law alone); the predictions take the one "
        "of the lower interval score.\n\n" + "\n".join(rows)
    )


def alone_sources(found: Sources) -> str:
    """A markdown table of the quantities of :data:`MIXING_KEYS` scored on every run left
    out from the law corrected and from its correction's line alone
    (:func:`line_alone_scores`), and which the library's predictions take; empty without
    scores."""
    if not found.alone:
        return ""
    rows = [
        "| quantity | interval score, the law corrected [log] | the line alone | predicted from |",
        "| --- | --- | --- | --- |",
    ]
    for key, (law, alone) in found.alone.items():
        taken = "the line alone" if key in found.chosen.calibration.direct else "the law corrected"
        rows.append(f"| {key} | {law:.4f} | {alone:.4f} | {taken} |")
    return (
        "## The outlet's mixing: the law or the line alone\n\nEvery run's outlet mixing indices predicted without "
        "it from the law corrected by its line, and from that line alone fitted to the DEM's values (the law's "
        "value not used); each takes the lower interval score.\n\n" + "\n".join(rows)
    )


def chain_sources(found: Sources) -> str:
    """A markdown table of every quantity but the slices checked like :func:`check` from
    the law's chain as fitted and timed by the zone law (:func:`chain_scores`), and which
    the library's predictions take; empty when ``found`` holds no such pair."""
    if found.fitted is None or found.timed is None:
        return ""
    timed_chosen = found.chosen.calibration.timed
    sources = [
        ("the law's chain as fitted", found.fitted, not timed_chosen),
        ("the chain timed by the zone law (`workflows.prediction.predict.timed`)", found.timed, timed_chosen),
    ]
    widths = [k for k in HEADLINE if k in found.chosen.calibration.whole]
    rows = _source_rows("quantities from", sources, lambda key: not _slice_of(key, "holdup_slice"), widths)
    return (
        "## The chain's time scale\n\nEvery run's quantities but the slices predicted without it, from the law's "
        "chain as fitted and from that chain with each slice's rates scaled so that it holds the zone law's "
        "hold-up (where particles go is the law's, how long they stay the bed's); the predictions take the one of "
        "the lower interval score.\n\n" + "\n".join(rows)
    )


def _law_misses(model: LibraryModel, key: str = "holdup") -> str:
    """How far the law alone is from the DEM's ``key`` at the library's runs, fitted with
    them and left out: what the correction has to make up."""
    calibration = model.calibration
    if calibration is None or key not in calibration.whole:
        return ""
    held = [(n, r.dem[key].value) for n, r in enumerate(model.runs) if key in r.dem]
    ranges = []
    for law in (lambda n: calibration.whole[key][n], lambda n: calibration.left_out[key][n][n]):
        misses = [dem / law(n) - 1 for n, dem in held if law(n) > 0]
        ranges.append(f"{min(misses):+.1%} to {max(misses):+.1%}" if misses else "-")
    law = "the law's chain timed by the zone law" if calibration.timed else "the law"
    return (
        f" Before the correction {law} misses the runs' {key} (DEM / law - 1) by {ranges[0]} fitted with them, "
        f"{ranges[1]} each left out."
    )


def _mean_scores(model: LibraryModel, result: Check) -> str:
    """The mean held-out log-likelihood of the library's runs, interpolated and
    extrapolated: what the law's form is chosen by."""
    if not model.left_out_scores or model.calibration is None:
        return ""
    scores = np.asarray(model.left_out_scores, dtype=float)
    inside = np.asarray(model.calibration.inside, dtype=bool)
    parts = [
        f"{scores[mask].mean():.5f} {label}"
        for mask, label in ((inside, "interpolated"), (~inside, "extrapolated"))
        if mask.any()
    ]
    return f" Mean held-out log-likelihood [nats/particle-step]: {', '.join(parts)}."


def _verdicts(result: Check) -> str:
    """How many runs the law predicts (:meth:`Check.verdict`), and on how many the
    headline quantities alone are inside the DEM's widened interval."""
    runs = result.runs()
    if not runs:
        return ""
    predicted = sum(result.verdict(run)[0] for run in runs)
    headline = sum(result.headline_inside(run) for run in runs)
    return (
        f" The law predicts {predicted} of {len(runs)} runs (the {len(HEADLINE)} headline quantities, "
        f"{', '.join(HEADLINE)}, and all but {MAY_MISS} of the others inside the DEM's interval widened by the seed "
        f"scatter); the headline quantities alone are inside it on {headline} of {len(runs)}."
    )


def _ck(test: tuple[float, float] | None) -> str:
    return "-" if test is None else f"{test[0]:.3f}, {test[1]:.1f}"


def _percent(value: float) -> str:
    return "-" if not math.isfinite(value) else f"{value:.1%}"


def _share(rows: list[CheckedQuantity]) -> str:
    rows = [r for r in rows if math.isfinite(r.low)]
    return f"{sum(r.covered for r in rows)}/{len(rows)}" if rows else "-"


def _rms_error(rows: list[CheckedQuantity]) -> str:
    """The root mean square of the rows' errors on their scale: % for a log quantity."""
    errors = [residual(r.key, r.dem, r.value) for r in rows]
    errors = [e for e in errors if math.isfinite(e)]
    if not errors:
        return "-"
    rms = math.sqrt(float(np.mean(np.square(errors))))
    return f"{rms:.4f}" if rows[0].key in ABSOLUTE_KEYS else f"{100 * rms:.1f} %"


def _half(rows: list[CheckedQuantity]) -> str:
    values = [r.relative_half_width for r in rows if math.isfinite(r.low)]
    return f"{100 * float(np.median(values)):.1f}" if values else "-"


def restricted(model: LibraryModel, runs: Sequence[int]) -> LibraryModel:
    """``model`` (calibrated) as if it held only the runs of index ``runs``, in that
    order: their entries, laws left out and calibration values. No law is refitted: the
    whole library's law and each law left out keep every other run they were fitted to,
    so :func:`check` of the result judges the correction's design, not the law's. Its
    slices take the correction's lines: the zone law is the whole library's (refitting it
    to every subset is :func:`calibrated`'s work); so is the time scale of a chain timed by
    it, whose values the result keeps."""
    keep = list(runs)
    cal = model.calibration
    if cal is None:
        raise ConfigError("the library model has no calibration: make it with `pbmdem library fit`")
    scores = [model.left_out_scores[n] for n in keep] if model.left_out_scores else []
    sub = replace(
        model,
        runs=tuple(model.runs[n] for n in keep),
        left_out=tuple(model.left_out[n] for n in keep),
        transverse_left_out=tuple(model.transverse_left_out[n] for n in keep),
        left_out_scores=tuple(scores),
        ck=tuple(model.ck[n] for n in keep) if model.ck else (),
        calibration=None,
    )
    inside = [not _others(sub, n).extrapolated for n in range(len(keep))]
    calibration = Calibration(
        {key: [values[n] for n in keep] for key, values in cal.whole.items()},
        {key: [[rows[m][n] for n in keep] for m in keep] for key, rows in cal.left_out.items()},
        inside,
        cal.covariates,
        timed=cal.timed,
        direct=cal.direct,
    )
    return replace(sub, calibration=calibration)
