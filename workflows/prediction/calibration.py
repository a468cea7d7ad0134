"""The prediction intervals' calibration, and the check that they hold on runs left out.

Each run of a library is predicted by the law fitted without it
(:attr:`~workflows.prediction.library.LibraryModel.left_out`): its errors, one per run and
quantity, are the :class:`~workflows.prediction.library.Calibration` that
:func:`workflows.prediction.predict.predict` builds its intervals from (:func:`calibrated`).

Whether those intervals hold is then measured without using the run judged
(:func:`check`): run i's prediction by the law without it, its bias and spread from the
errors of the other runs only, its jackknife spread at its own point; the DEM's value
inside that interval or not. Beside it, the DEM's scatter between seeds, from the
library's replicate pairs (two runs at one operating point, :func:`seed_scatter`), and
whether each prediction lies inside the DEM's interval widened by that scatter.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from workflows.prediction.library import (
    ABSOLUTE_KEYS,
    Calibration,
    LibraryModel,
    quantity_keys,
)
from workflows.prediction.predict import PointValues, corrected, jackknife, point_values, residual

#: the headline quantities and the half-widths the issue asks of them, as fractions of the
#: value (slices: every slice)
USEFUL_HALF_WIDTH = {
    "mean_residence_time_s": 0.04,
    "holdup": 0.04,
    "rtd_variance_s2": 0.15,
    "holdup_slice": 0.08,
}


def left_out_values(model: LibraryModel) -> list[PointValues]:
    """Each run's quantities from the law fitted without it, at its operating point."""
    return [
        point_values(law, transverse, entry.point, model.interval_s)
        for law, transverse, entry in zip(model.left_out, model.transverse_left_out, model.runs)
    ]


def calibrated(model: LibraryModel) -> LibraryModel:
    """``model`` with its :class:`Calibration`: each run's errors left out."""
    predicted = left_out_values(model)
    residuals = {
        key: [
            residual(key, entry.dem[key].value, values.values[key]) if key in entry.dem else math.nan
            for entry, values in zip(model.runs, predicted)
        ]
        for key in quantity_keys()
    }
    return replace(model, calibration=Calibration(residuals))


def seed_scatter(model: LibraryModel) -> tuple[dict[str, float], list[tuple[str, str]]]:
    """Per quantity, the DEM's standard deviation between seeds on the quantity's scale,
    from every pair of library runs at one operating point (half the mean square of their
    differences); and the pairs. Empty without a pair."""
    pairs = []
    for a in range(len(model.runs)):
        for b in range(a + 1, len(model.runs)):
            if not model.runs[a].point.differences(model.runs[b].point):
                pairs.append((a, b))
    out = {}
    for key in quantity_keys():
        diffs = []
        for a, b in pairs:
            ea, eb = model.runs[a].dem.get(key), model.runs[b].dem.get(key)
            if ea is not None and eb is not None:
                diffs.append(residual(key, ea.value, eb.value))
        diffs = [d for d in diffs if math.isfinite(d)]
        if diffs:
            out[key] = math.sqrt(float(np.mean(np.square(diffs))) / 2)
    return out, [(model.runs[a].file, model.runs[b].file) for a, b in pairs]


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

    @property
    def covered(self) -> bool:
        """The DEM's value lies inside the prediction interval."""
        return self.low <= self.dem <= self.high

    @property
    def inside_widened(self) -> bool:
        """The prediction lies inside the DEM's interval widened by the seed scatter (in
        quadrature with its half-width)."""
        half = (self.dem_high - self.dem_low) / 2
        seed = 1.96 * self.seed_sd * (1.0 if self.key in ABSOLUTE_KEYS else abs(self.dem))
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
        }


@dataclass(frozen=True)
class Check:
    rows: tuple[CheckedQuantity, ...]
    seed_sd: dict[str, float]
    seed_pairs: tuple[tuple[str, str], ...]

    @property
    def coverage(self) -> float:
        rows = [r for r in self.rows if math.isfinite(r.low)]
        return sum(r.covered for r in rows) / len(rows) if rows else math.nan

    def runs(self) -> list[str]:
        return list(dict.fromkeys(r.run for r in self.rows))

    def of_run(self, run: str) -> list[CheckedQuantity]:
        return [r for r in self.rows if r.run == run]

    def median_half_width(self, key: str) -> float:
        values = [r.relative_half_width for r in self.rows if r.key == key or r.key.startswith(key + "_")]
        return float(np.median(values)) if values else math.nan

    def record(self) -> dict[str, Any]:
        return {
            "coverage": self.coverage,
            "rows": [r.record() for r in self.rows],
            "seed_sd": self.seed_sd,
            "seed_pairs": [list(p) for p in self.seed_pairs],
            "median_relative_half_width": {key: self.median_half_width(key) for key in USEFUL_HALF_WIDTH},
        }


def check(model: LibraryModel) -> Check:
    """Every run predicted without it, its interval calibrated without it (module
    docstring). ``model`` must carry its calibration."""
    calibration = model.calibration if model.calibration is not None else calibrated(model).calibration
    predicted = left_out_values(model)
    scatter, pairs = seed_scatter(model)
    rows = []
    for n, (entry, values) in enumerate(zip(model.runs, predicted)):
        at_point = [
            point_values(law, transverse, entry.point, model.interval_s).values
            for law, transverse in zip(model.left_out, model.transverse_left_out)
        ]
        for key in quantity_keys():
            dem = entry.dem.get(key)
            if dem is None:
                continue
            spread = math.sqrt(jackknife(at_point, key))
            centre, low, high = corrected(key, values.values[key], calibration.error(key, leave=n), spread)
            rows.append(
                CheckedQuantity(
                    entry.file,
                    key,
                    float(dem.value),
                    float(dem.low),
                    float(dem.high),
                    centre,
                    low,
                    high,
                    scatter.get(key, 0.0),
                )
            )
    return Check(tuple(rows), scatter, tuple(pairs))


def markdown(model: LibraryModel, result: Check) -> str:
    """The check as tables: per run, the quantities covered and inside the widened DEM
    interval; per quantity, the coverage and the median relative half-width."""
    keys = quantity_keys()
    n_keys = len(keys)
    point = {r.file: r.point for r in model.runs}
    lines = [
        f"Each run predicted by the law fitted without it ({len(model.runs)} runs, {n_keys} quantities each); "
        f"interval calibrated without it. Coverage of the 95 % intervals: {result.coverage:.1%}.",
        "",
        f"| run | rpm | feed [/s] | length [m] | DEM inside the prediction interval (of {n_keys}) | "
        "prediction inside the DEM interval widened by seed scatter | missed |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for run in result.runs():
        rows = result.of_run(run)
        p = point[run]
        missed = ", ".join(r.key for r in rows if not r.covered) or "-"
        lines.append(
            f"| {run} | {p.impeller_rpm:g} | {p.feed_rate_total_per_s:g} | {p.length_m:g} | "
            f"{sum(r.covered for r in rows)} | {sum(r.inside_widened for r in rows)} | {missed} |"
        )
    lines += [
        "",
        "| quantity | coverage | median half-width [% of value] | seed scatter sd |",
        "| --- | --- | --- | --- |",
    ]
    for key in keys:
        rows = [r for r in result.rows if r.key == key]
        if not rows:
            continue
        cover = sum(r.covered for r in rows) / len(rows)
        half = float(np.median([r.relative_half_width for r in rows]))
        seed = result.seed_sd.get(key, math.nan)
        scale = "" if key in ABSOLUTE_KEYS else " (log)"
        lines.append(f"| {key} | {cover:.0%} | {100 * half:.1f} | {seed:.3g}{scale} |")
    if result.seed_pairs:
        lines += ["", "Seed pairs: " + "; ".join(f"{a} and {b}" for a, b in result.seed_pairs)]
    return "\n".join(lines)
