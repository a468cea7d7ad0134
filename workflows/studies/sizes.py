"""``pbmdem study sizes``: how much of the particles' memory is their size?

The DEM feeds a size distribution (``dem.particles.diameter_sd_m``, discretised into
``size_classes``). A particle keeps its size for ever, so if the sizes move at different
speeds (the small ones sift into the slow bed, the large ones ride over it), part of the
"hidden mobility" the phase model learns is an attribute the particle never loses and the
chain is told nothing about. This study measures it on one DEM run:

* the DEM's pooled RTD of each size class: the particles of that class that entered in the
  run's entry window, the run's horizon, the same block bootstrap as the whole run's
  (:func:`dem.steady.pooled_rtd`), and the share still inside at the horizon;
* a phase model per size class (the product's fit, :func:`dem.phases.table_with_phases`,
  on that class's sequences alone) and their population (:func:`coupling.phases.population`:
  each class its own chain, the feed dealt over the classes by their shares): each class's
  pooled RTD, and the population's mean, variance and hold-up beside the run's own phase
  model (one chain for every size) and the DEM.

The diameters come from the per-particle records (``diameter_m``, recorded since the
post-processing reads the dumps' radius) or, for results made before, from the run's dumps
(``--run-dir``). Writes ``sizes.json`` and prints a table.
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from coupling.errors import ConfigError
from coupling.jsonable import write_json
from coupling.phases import population
from dem import phases
from dem.deck import DUMP_GLOB
from dem.dumps import iter_snapshots
from dem.steady import pooled_rtd as dem_pooled_rtd
from dem.summary import Estimate
from workflows.pipeline.results import load_results
from workflows.shipped import REDUCED_RUN
from workflows.studies.phases import Interval, dem_target, pbm_numbers

HELP = "the RTD by particle size: the DEM's per size class, and a phase model per class against one for all"
OUT = Path("results/sizes")
#: more distinct diameters than this are grouped into QUANTILE_CLASSES classes of equal counts
MAX_CLASSES = 8
QUANTILE_CLASSES = 5
#: diameters closer than this are one class [m] (the dumps print radii to ~6 digits)
SAME_DIAMETER_M = 1e-7


@dataclass(frozen=True)
class SizeClass:
    """One size class: its mean diameter [m], its share of the entry window's particles,
    the DEM's pooled RTD of its particles (mean [s], variance [s²], share beyond the
    horizon) and its own phase model's."""

    diameter_m: float
    share: float
    n_entered: int
    dem_mean_s: Estimate
    dem_variance_s2: Estimate
    dem_beyond: float
    model_mean_s: float
    model_variance_s2: float
    model_beyond: float


@dataclass(frozen=True)
class SizeStudy:
    """What :func:`size_study` measures (module docstring): the classes, and for the whole
    feed the DEM against one phase model for every size (``one_chain``, the run's own) and
    the population of per-class models (``by_size``), each as mean [s], variance [s²] and
    steady hold-up [particles]."""

    classes: tuple[SizeClass, ...]
    n_phases: int
    dem: dict[str, Interval]
    one_chain: dict[str, float]
    by_size: dict[str, float]
    fit_wall_s: float


def diameters_from_dumps(pattern: str | Path) -> dict[int, float]:
    """Each particle's diameter [m] at its first sight in the dumps of ``pattern`` (a glob
    or path; every snapshot must carry ``id`` and ``radius``)."""
    seen: dict[int, float] = {}
    for snap in iter_snapshots(str(pattern), columns=("id", "radius")):
        ids = snap["id"].astype(np.int64)
        for pid, radius in zip(ids.tolist(), snap["radius"].tolist()):
            seen.setdefault(pid, 2.0 * radius)
    return seen


def size_classes(diameters: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(class of each particle, -1 where the diameter is unknown; mean diameter of each
    class [m], ascending). Distinct diameters are the classes; more than
    :data:`MAX_CLASSES` of them (a continuous distribution) are grouped into
    :data:`QUANTILE_CLASSES` classes of about equal counts."""
    d = np.asarray(diameters, dtype=float)
    known = np.isfinite(d) & (d > 0)
    if not known.any():
        raise ValueError("no particle has a known diameter")
    labels = np.full(d.size, -1, np.int64)
    distinct = np.unique(np.round(d[known] / SAME_DIAMETER_M))
    if distinct.size <= MAX_CLASSES:
        labels[known] = np.searchsorted(distinct, np.round(d[known] / SAME_DIAMETER_M))
    else:
        edges = np.quantile(d[known], np.linspace(0, 1, QUANTILE_CLASSES + 1)[1:-1])
        labels[known] = np.searchsorted(edges, d[known], side="right")
    n = int(labels.max()) + 1
    centres = np.array([d[labels == c].mean() if np.any(labels == c) else math.nan for c in range(n)])
    return labels, centres


def _diameters(results, run_dir: str | Path | None, source: str) -> np.ndarray:
    """The diameter of each particle of the records [m], from the records or the dumps."""
    records = results.particles
    ids = records["id"].to_numpy(np.int64)
    if "diameter_m" in records and np.isfinite(records["diameter_m"].to_numpy(float)).any():
        return records["diameter_m"].to_numpy(float)
    if run_dir is None:
        raise ConfigError(
            f"{source} holds no particle diameters (made before they were recorded): give --run-dir, the run "
            "directory whose dumps carry them, or post-process the run again"
        )
    pattern = Path(run_dir) / DUMP_GLOB
    seen = diameters_from_dumps(pattern)
    if not seen:
        raise ConfigError(f"--run-dir {run_dir}: no dump in {pattern}")
    return np.array([seen.get(int(i), math.nan) for i in ids])


def size_study(results_path: str | Path, run_dir: str | Path | None = None, n_phases: int | None = None) -> SizeStudy:
    """:class:`SizeStudy` of the DEM results ``results_path`` (module docstring); K =
    ``n_phases`` per class, default the run's own phase model's."""
    results, config = load_results(results_path)
    summary, table, seq = results.summary, results.table, results.sequences
    if seq is None or table.phases is None:
        raise ConfigError(f"{results_path} holds no compartment sequences or phase model: post-process the run again")
    if summary.steady_time is None or not summary.has_pooled_rtd:
        raise ConfigError(f"{results_path}: the run has no steady state or no pooled RTD to split by size")
    k = n_phases or table.phases.n_phases
    diameters = _diameters(results, run_dir, str(results_path))
    labels, centres = size_classes(diameters)
    records = results.particles
    t_ss, t_end = float(summary.steady_time), float(seq.snapshot_t[-1])
    little = float(summary.steady["little_mean_residence_time_s"]["value"])
    target = dem_target(summary, str(results_path))
    t0, t1 = target.entry_window_s
    entry_t = records["entry_t_s"].to_numpy(float)
    in_window = (entry_t > t0) & (entry_t <= t1)
    label_by_id = dict(zip(records["id"].to_numpy(np.int64).tolist(), labels.tolist()))
    seq_labels = np.array([label_by_id.get(int(pid), -1) for pid in seq.ids.tolist()])
    wall0 = time.perf_counter()
    models, shares, rows = [], [], []
    for c, diameter in enumerate(centres):
        mine = labels == c
        share = float((mine & in_window).sum() / max(in_window.sum(), 1))
        members = np.flatnonzero(seq_labels == c)
        if share <= 0 or not members.size:
            continue
        fitted, _fit = phases.table_with_phases(table, seq.subset(members), t_ss, k)
        model = fitted.phases
        dem = dem_pooled_rtd(records[mine], t_ss, t_end, little, float(table.window_s))
        pbm = pbm_numbers(model, config, target)
        models.append(model)
        shares.append(share)
        rows.append(
            SizeClass(
                float(diameter),
                share,
                int(dem["n_entered"]),
                Estimate.from_record(dem["mean_residence_time_s"]),
                Estimate.from_record(dem["rtd_variance_s2"]),
                1.0 - float(dem["recovered_fraction"]["value"]),
                float(pbm["mean_s"]),
                float(pbm["variance_s2"]),
                1.0 - float(pbm["recovered_fraction"]),
            )
        )
    wall = time.perf_counter() - wall0
    whole = {
        name: pbm_numbers(m, config, target) for name, m in (("one", table.phases), ("by", population(models, shares)))
    }
    return SizeStudy(
        tuple(rows),
        k,
        {"mean_s": target.mean_s, "variance_s2": target.variance_s2, "holdup": target.holdup},
        {key: float(whole["one"][key]) for key in ("mean_s", "variance_s2", "holdup")},
        {key: float(whole["by"][key]) for key in ("mean_s", "variance_s2", "holdup")},
        wall,
    )


def markdown(study: SizeStudy) -> str:
    """The study's two tables: by size class, and for the whole feed."""
    lines = [
        f"| diameter [mm] | share | tracers | DEM mean [s] | DEM variance [s²] | DEM beyond H | "
        f"K = {study.n_phases} per class: mean / variance / beyond H |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for c in study.classes:
        m, v = c.dem_mean_s, c.dem_variance_s2
        lines.append(
            f"| {1e3 * c.diameter_m:.2f} | {c.share:.3f} | {c.n_entered} | {m.value:.2f} [{m.low:.2f}, {m.high:.2f}] | "
            f"{v.value:.0f} [{v.low:.0f}, {v.high:.0f}] | {c.dem_beyond:.2%} | "
            f"{c.model_mean_s:.2f} / {c.model_variance_s2:.0f} / {c.model_beyond:.2%} |"
        )
    lines += [
        "",
        "| whole feed | DEM [95 %] | one chain for every size | a chain per size class |",
        "| --- | --- | --- | --- |",
    ]
    for key, label, digits in (
        ("mean_s", "pooled mean [s]", 2),
        ("variance_s2", "pooled variance [s²]", 1),
        ("holdup", "steady hold-up", 0),
    ):
        dem = study.dem[key]
        marks = ["✓" if dem.inside(x[key]) else "✗" for x in (study.one_chain, study.by_size)]
        lines.append(
            f"| {label} | {dem.value:.{digits}f} [{dem.low:.{digits}f}, {dem.high:.{digits}f}] | "
            f"{study.one_chain[key]:.{digits}f} {marks[0]} | {study.by_size[key]:.{digits}f} {marks[1]} |"
        )
    return "\n".join(lines)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--results",
        default=str(REDUCED_RUN),
        help="DEM results file with compartment sequences and a phase model (default: %(default)s)",
    )
    parser.add_argument(
        "--run-dir",
        default=None,
        help="the run's directory, whose dumps give the diameters when the results file records none",
    )
    parser.add_argument("--k", type=int, default=None, help="phases per size class (default: the run's own model's)")
    parser.add_argument("--out", default=str(OUT), help="output folder (default: %(default)s)")


def run(args: argparse.Namespace) -> int:
    if args.k is not None and args.k < 1:
        raise ConfigError(f"--k {args.k}: expected a number of phases >= 1")
    started = time.perf_counter()
    study = size_study(args.results, args.run_dir, args.k)
    print(markdown(study))
    print(f"per-class fits {study.fit_wall_s:.0f} s")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    record = {"results": str(args.results), **asdict(study), "wall_time_s": time.perf_counter() - started}
    print(f"wrote {write_json(out / 'sizes.json', record)}")
    return 0
