"""``pbmdem study error-structure``: whether what the law misses, each run left out,
follows the operating point.

Every run of the library predicted without it (:func:`workflows.prediction.calibration.check`)
misses the DEM by an error on each quantity's scale (the log of DEM / prediction, or the
difference for the absolute quantities). Were those errors a smooth function of the
operating point, the runs nearest a point would tell its error, and a correction that
interpolates them would take it off. Each run's error is therefore kriged from the other
runs' errors: a zero-mean Gaussian process over (log speed, log length, log feed), each
over the library's range, with a squared-exponential kernel of length ``ell`` and a
signal-to-noise variance ratio ``ratio`` (the kriging weights need only the ratio). The
page gives, per quantity, the root mean square error as predicted and after kriging with
each (ell, ratio) of a grid, and the least of them: the grid is chosen on the same runs,
so that column is the kriging at its most favourable. Beside it, each slice's mean error
over the runs of the baseline's length and over the others: a miss the blade layout
carries whatever the speed and the feed. Writes ``error-structure.md`` and ``.json``.
"""

from __future__ import annotations

import argparse
import math
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from workflows.prediction.calibration import check
from workflows.prediction.covariates import run_covariates
from workflows.prediction.library import LibraryModel, quantity_keys
from workflows.prediction.predict import DOMAIN_AXES, residual
from workflows.studies import BASELINE_LENGTH_M, add_library_arguments, calibrated_library, write_page

HELP = "whether the law's errors, every run left out, follow the operating point (kriged from the other runs)"
OUT = Path("results/error-structure")
#: the kernel's length scales, in widths of the library's ranges, and signal-to-noise ratios
LENGTHS = (0.1, 0.2, 0.3, 0.5, 1.0)
RATIOS = (0.25, 1.0, 4.0, 16.0)


def scaled_points(model: LibraryModel) -> np.ndarray:
    """(runs, 3) each run's log speed, log length and log feed over the library's range."""
    x = np.array([[run_covariates(r.point)[a] for a in DOMAIN_AXES] for r in model.runs])
    width = x.max(axis=0) - x.min(axis=0)
    return x / np.where(width > 1e-12, width, 1.0)


def kriged_errors(x: np.ndarray, errors: np.ndarray, ell: float, ratio: float) -> np.ndarray:
    """Each run's error less its kriging from the other runs' (module docstring); NaN
    errors are neither kriged nor used."""
    out = np.full(errors.shape, math.nan)
    for n in np.flatnonzero(np.isfinite(errors)):
        use = np.isfinite(errors) & (np.arange(errors.size) != n)
        if not use.any():
            continue
        d2 = np.sum((x[use][:, None, :] - x[use][None, :, :]) ** 2, axis=2)
        k = ratio * np.exp(-d2 / (2 * ell**2)) + np.eye(int(use.sum()))
        k_star = ratio * np.exp(-np.sum((x[use] - x[n]) ** 2, axis=1) / (2 * ell**2))
        out[n] = errors[n] - k_star @ np.linalg.solve(k, errors[use])
    return out


def _rms(values: np.ndarray) -> float:
    values = values[np.isfinite(values)]
    return float(np.sqrt(np.mean(values**2))) if values.size else math.nan


def error_table(model: LibraryModel) -> dict[str, dict]:
    """Per quantity: the held-out errors' root mean square as predicted, after kriging at
    each (ell, ratio) of :data:`LENGTHS` x :data:`RATIOS`, and the least of those."""
    result = check(model)
    runs = [r.file for r in model.runs]
    x = scaled_points(model)
    out = {}
    for key in quantity_keys():
        by_run = {r.run: residual(key, r.dem, r.value) for r in result.rows if r.key == key}
        errors = np.array([by_run.get(run, math.nan) for run in runs])
        kriged = {(ell, ratio): _rms(kriged_errors(x, errors, ell, ratio)) for ell in LENGTHS for ratio in RATIOS}
        # the least defined one (NaN where the runs give no error to krige)
        best = min(kriged, key=lambda k: (not math.isfinite(kriged[k]), kriged[k]))
        out[key] = {
            "rms": _rms(errors),
            "kriged": {f"{ell:g}/{ratio:g}": v for (ell, ratio), v in kriged.items()},
            "best": {"ell": best[0], "ratio": best[1], "rms": kriged[best]},
            "errors": dict(zip(runs, errors.tolist())),
        }
    return out


def slice_bias(model: LibraryModel, table: dict[str, dict]) -> dict[str, tuple[float, float]]:
    """Per slice, its mean held-out error over the runs of the baseline's length and over
    the others."""
    baseline = {r.file for r in model.runs if abs(r.point.length_m - BASELINE_LENGTH_M) < 1e-9}
    out = {}
    for key, row in table.items():
        if key.startswith("holdup_slice_"):
            errors = row["errors"]
            base = [e for run, e in errors.items() if run in baseline and math.isfinite(e)]
            other = [e for run, e in errors.items() if run not in baseline and math.isfinite(e)]
            out[key] = (float(np.mean(base)) if base else math.nan, float(np.mean(other)) if other else math.nan)
    return out


def _percent(value: float) -> str:
    return f"{100 * value:+.1f} %" if math.isfinite(value) else "-"


def markdown(table: dict[str, dict], bias: dict[str, tuple[float, float]], library: str, runs: Sequence) -> str:
    columns = [f"{ell:g}/{ratio:g}" for ell in LENGTHS for ratio in RATIOS]
    lines = [
        "# What the law misses, each run left out: does it follow the operating point?",
        "",
        f"Made by `pbmdem study error-structure --library {library}` from its {len(runs)} runs. Root mean square "
        "of the held-out errors (log DEM / prediction; the difference for C_A and the Lacey index) as predicted, "
        "and after kriging each run's error from the other runs' over (log speed, log length, log feed) "
        "(`workflows/studies/error_structure.py`): columns ell/ratio, the kernel's length in widths of the "
        "library's ranges and its signal-to-noise ratio. The last column is the least over the grid, chosen on "
        "these same runs.",
        "",
        "| quantity | as predicted | " + " | ".join(columns) + " | least (ell/ratio) |",
        "|" + " --- |" * (len(columns) + 3),
    ]
    for key, row in table.items():
        best = row["best"]
        cells = " | ".join(f"{row['kriged'][c]:.4f}" for c in columns)
        lines.append(f"| {key} | {row['rms']:.4f} | {cells} | {best['rms']:.4f} ({best['ell']:g}/{best['ratio']:g}) |")
    lines += [
        "",
        f"Each slice's mean held-out error (log DEM / prediction) over the runs {BASELINE_LENGTH_M:g} m long and "
        "over the others:",
        "",
        f"| slice | runs of {BASELINE_LENGTH_M:g} m | other lengths |",
        "| --- | --- | --- |",
    ]
    lines += [f"| {key} | {_percent(a)} | {_percent(b)} |" for key, (a, b) in bias.items()]
    return "\n".join(lines) + "\n"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_library_arguments(parser, OUT)


def run(args: argparse.Namespace) -> int:
    model = calibrated_library(args.library)
    table = error_table(model)
    bias = slice_bias(model, table)
    text = markdown(table, bias, os.path.relpath(args.library), model.runs)
    write_page(args.out, "error-structure", text, {"quantities": table, "slice_bias": bias})
    return 0
