"""``pbmdem study profile-forms``: which blade stations the slices' zone law gives a line
of their own.

The zone law (:mod:`workflows.prediction.profile`) puts every forward station's swept zone
on one line and every backward one's on another. The stations beside the inlet's pile,
or the one before the weir, may not behave like the rest. Each form (a set of stations
with swept zones of their own) is fitted to a library's runs with one run left out at a
time, at the whole library's swept half-width, and that run's slices predicted: the root
mean square of the log errors, the share of DEM values inside the law's own 95 %
intervals, and their median half-width, over the runs inside the others' domain and over
the runs at an end of a range (the intervals without the extrapolation floor and widening
``pbmdem predict`` adds there). The forms are fitted without the misses of the layouts
the library has run; a second table then takes the chosen form with those misses in each
set of terms of :data:`LAYOUT_FORMS` (:class:`~workflows.prediction.profile.LayoutShares`),
over the same groups and over the runs of the baseline's layout. Writes
``profile-forms.md`` and ``.json``.
"""

from __future__ import annotations

import argparse
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from workflows.prediction.calibration import slice_holdups
from workflows.prediction.library import LibraryModel
from workflows.prediction.profile import OWN_STATIONS, fit_profile, refit
from workflows.studies import BASELINE_LENGTH_M, add_library_arguments, calibrated_library, write_page

HELP = "the slices' zone law with swept zones of their own at other stations, every run left out"
OUT = Path("results/profile-forms")
#: the forms compared: stations counted from the inlet, negative from the weir
FORMS = ((), (0,), (0, 1), (0, 1, -1), (0, 1, 2), (0, 1, -2), (0, 1, -3))
#: the terms of the layouts' misses compared (None: the law alone)
LAYOUT_FORMS = (None, ("speed",), ("speed", "feed"), ("speed", "speed2"), ("speed", "feed", "speed2"))


@dataclass(frozen=True)
class FormCheck:
    """One form's runs left out: per group ("interpolated", "extrapolated", "baseline
    layout"), the root mean square log error, the coverage and the median relative
    half-width of the slices, and the root mean square log error of their shares of the bed."""

    own_stations: tuple[int, ...]
    half_width_m: float
    groups: dict[str, tuple[float, float, float, float]]
    layouts: tuple[str, ...] | None = None

    def record(self) -> dict:
        return {
            "own_stations": list(self.own_stations),
            "layouts": None if self.layouts is None else list(self.layouts),
            "half_width_m": self.half_width_m,
            "groups": {
                k: dict(zip(("rms_log_error", "coverage", "median_half_width", "rms_log_share_error"), v))
                for k, v in self.groups.items()
            },
        }


def form_check(model: LibraryModel, own_stations: tuple[int, ...], layouts: tuple[str, ...] | None = None) -> FormCheck:
    """Every run of ``model`` (calibrated) left out under the form ``own_stations``, with the
    misses of the layouts run in the terms ``layouts`` (None: without)."""
    held = slice_holdups(model)
    points = [e.point for e in model.runs]
    whole = fit_profile(points, held, model.blade_pattern, own_stations=own_stations, layouts=layouts)
    errors, covered, halves, shares = [], [], [], []
    for n in range(len(points)):
        law = refit(whole, [p for m, p in enumerate(points) if m != n], np.delete(held, n, axis=0))
        values, half = law.at(points[n])
        error = np.log(held[n] / values)
        errors.append(error)
        shares.append(error - np.log(np.nansum(held[n]) / np.sum(values[np.isfinite(held[n])])))
        covered.append(np.abs(error) <= half)
        halves.append(np.sinh(half))  # (high - low) / 2 / value on the log scale's bounds
    errors, covered, halves, shares = map(np.array, (errors, covered, halves, shares))
    inside = np.array(model.calibration.inside)
    baseline = np.array([np.isclose(p.length_m, BASELINE_LENGTH_M) for p in points])
    groups = {}
    for name, rows in (("interpolated", inside), ("extrapolated", ~inside), ("baseline layout", baseline)):
        if rows.any():
            e, c, h, f = errors[rows], covered[rows], halves[rows], shares[rows]
            ok = np.isfinite(e)
            groups[name] = (
                float(np.sqrt(np.mean(e[ok] ** 2))),
                float(np.mean(c[ok])),
                float(np.median(h[ok])),
                float(np.sqrt(np.mean(f[ok] ** 2))),
            )
    return FormCheck(tuple(own_stations), whole.half_width_m, groups, layouts)


def markdown(rows: list[FormCheck], library: str) -> str:
    lines = [
        "# The slices' zone law: which stations get a swept zone of their own",
        "",
        f"Made by `pbmdem study profile-forms --library {library}`. Every run left out; stations counted from "
        "the inlet from 0, negative from the weir. The intervals are the law's own (without the extrapolation "
        "floor and widening `pbmdem predict` adds at an end of a range).",
        "",
        "| own stations | swept half-width [mm] | interpolated: rms log error | coverage | median half-width [%] "
        "| extrapolated: rms log error | coverage | median half-width [%] |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        name = ", ".join(map(str, r.own_stations)) or "none"
        lines.append(f"| {name} | {1000 * r.half_width_m:.0f} | " + _cells(r, ("interpolated", "extrapolated")))
    return "\n".join(lines) + "\n"


def _cells(row: FormCheck, groups: tuple[str, ...]) -> str:
    cells = []
    for group in groups:
        rms, cov, half, _ = row.groups.get(group, (np.nan,) * 4)
        cells += [f"{rms:.4f}", f"{100 * cov:.0f} %", f"{100 * half:.1f}"]
    return " | ".join(cells) + " |"


def layout_markdown(rows: list[FormCheck]) -> str:
    """The table of the chosen form with its layouts' misses in each set of terms."""
    groups = ("interpolated", "extrapolated", "baseline layout")
    lines = [
        "## The misses of the layouts the library has run",
        "",
        f"The form of own stations {', '.join(map(str, rows[0].own_stations)) or 'none'} with what it misses of "
        "each slice's share at the blade layouts (length and stations) the other runs share with the run left out, "
        "a line per slice in the terms given (`LayoutShares`); a run whose layout no other run has keeps the law "
        f"alone. Beside the two groups above, the runs of the baseline's {BASELINE_LENGTH_M:g} m layout. The misses "
        "move the shares and keep the law's total, and a prediction scales the slices to the predicted hold-up: "
        "so the root mean square log error of the slices' shares of the bed. Their intervals are checked as "
        "`pbmdem predict` gives them, the total's error with them, in `law/calibration.md`.",
        "",
        "| layouts' terms | " + " | ".join(f"{g}: rms log share error" for g in groups) + " |",
        "|" + " --- |" * (1 + len(groups)),
    ]
    for r in rows:
        name = "without (the law alone)" if r.layouts is None else ", ".join(r.layouts)
        cells = [f"{r.groups.get(g, (np.nan,) * 4)[3]:.4f}" for g in groups]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_library_arguments(parser, OUT)


def run(args: argparse.Namespace) -> int:
    model = calibrated_library(args.library)
    rows = [form_check(model, form) for form in FORMS]
    own = model.calibration.profile.own_stations if model.calibration.profile is not None else OWN_STATIONS
    layout_rows = [form_check(model, own, terms) for terms in LAYOUT_FORMS]
    text = markdown(rows, os.path.relpath(args.library)) + "\n" + layout_markdown(layout_rows)
    record = {"forms": [r.record() for r in rows], "layouts": [r.record() for r in layout_rows]}
    write_page(args.out, "profile-forms", text, record)
    return 0
