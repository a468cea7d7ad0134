"""``pbmdem study sizes``: how much of the particles' memory is their size?

The DEM feeds a size distribution (``dem.particles.diameter_sd_m``, discretised into
``size_classes``). A particle keeps its size for ever, so if the sizes move at different
speeds (the small ones sift into the slow bed, the large ones ride over it), part of the
"hidden mobility" the phase model learns is an attribute the particle never loses and the
chain is told nothing about. This study measures it on one DEM run:

* the DEM's pooled RTD of each size class: the particles of that class that entered in the
  run's entry window, the run's horizon, the same block bootstrap as the whole run's
  (:func:`dem.steady.pooled_rtd`), and the share still inside at the horizon;
* the post-processing's phase model fitted both ways (:func:`dem.phases.table_with_phases`):
  one chain for every size, and a chain per size class with its dead zone (their population,
  :func:`coupling.phases.population`: each class its own chain, the feed dealt over the
  classes by their shares): each class's pooled RTD, and for the whole feed the mean,
  variance, hold-up and RTD overlap of both against the DEM.

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
from coupling.intervals import overlap_noise_band
from coupling.jsonable import write_json
from coupling.metrics import rtd_overlap
from dem import phases
from dem.deck import DUMP_GLOB
from dem.dumps import iter_snapshots
from dem.post import sequence_diameters
from workflows.analysis.agreement import dem_density
from workflows.analysis.memory import SizeRtd, rtd_by_size
from workflows.pipeline.results import load_results, pbm_config_for
from workflows.shipped import REDUCED_RUN
from workflows.studies.phases import Interval, dem_target, pbm_numbers

HELP = "the RTD by particle size: the DEM's per size class, and a phase model per class against one for all"
OUT = Path("results/sizes")
#: what the study compares for the whole feed
WHOLE = ("mean_s", "variance_s2", "holdup", "rtd_overlap", "overlap_noise_low")


@dataclass(frozen=True)
class SizeStudy:
    """What :func:`size_study` measures (module docstring): the classes, and for the whole
    feed the DEM against one phase model for every size (``one_chain``, the run's own) and
    the population of per-class models (``by_size``), each as mean [s], variance [s²] and
    steady hold-up [particles]; ``n_phases``: of each class's chain (K moving and, where
    there are classes, the dead zone: :func:`dem.phases.table_with_phases`)."""

    classes: tuple[SizeRtd, ...]
    n_phases: int
    dem: dict[str, Interval]
    one_chain: dict[str, float]
    by_size: dict[str, float]
    fit_wall_s: float
    #: each class's dead zone is left at most once per this many Little's-law residence
    #: times of the run; None: no zone
    zone_residences: float | None = phases.ZONE_RESIDENCES


def diameters_from_dumps(pattern: str | Path) -> dict[int, float]:
    """Each particle's diameter [m] at its first sight in the dumps of ``pattern`` (a glob
    or path; every snapshot must carry ``id`` and ``radius``)."""
    seen: dict[int, float] = {}
    for snap in iter_snapshots(str(pattern), columns=("id", "radius")):
        ids = snap["id"].astype(np.int64)
        for pid, radius in zip(ids.tolist(), snap["radius"].tolist()):
            seen.setdefault(pid, 2.0 * radius)
    return seen


def _diameters(results, run_dir: str | Path | None, source: str) -> np.ndarray:
    """The diameter of each particle of the sequences [m], from the records or the dumps."""
    known = sequence_diameters(results.sequences, results.particles)
    if known is not None and np.isfinite(known).any():
        return known
    if run_dir is None:
        raise ConfigError(
            f"{source} holds no particle diameters (made before they were recorded): give --run-dir, the run "
            "directory whose dumps carry them, or post-process the run again"
        )
    pattern = Path(run_dir) / DUMP_GLOB
    seen = diameters_from_dumps(pattern)
    if not seen:
        raise ConfigError(f"--run-dir {run_dir}: no dump in {pattern}")
    return np.array([seen.get(int(i), math.nan) for i in results.sequences.ids.tolist()])


def size_study(
    results_path: str | Path,
    run_dir: str | Path | None = None,
    n_phases: int | None = None,
    zone_residences: float | None = phases.ZONE_RESIDENCES,
) -> SizeStudy:
    """:class:`SizeStudy` of the DEM results ``results_path`` (module docstring); K =
    ``n_phases`` per class, default the run's own model's (:func:`dem.phases.moving_phases`);
    ``zone_residences`` bounds each class's dead zone as :func:`dem.phases.table_with_phases`
    does (:attr:`dem.phases.PhaseSettings.zone_residences`; None: no zone); every other
    setting is the product's."""
    results, config = load_results(results_path)
    summary, table, seq = results.summary, results.table, results.sequences
    if seq is None:
        raise ConfigError(f"{results_path} holds no compartment sequences: post-process the run again")
    target = dem_target(summary, str(results_path))
    k = n_phases or (phases.moving_phases(table.phases) if table.phases is not None else phases.PHASES)
    diameters = _diameters(results, run_dir, str(results_path))
    t_ss = float(summary.steady_time)
    wall0 = time.perf_counter()
    settings = phases.PhaseSettings(zone_residences=zone_residences)
    by_size, _fits = phases.table_with_phases(table.replace(phases=None), seq, t_ss, k, settings, diameters=diameters)
    one_chain, _fit = phases.table_with_phases(table.replace(phases=None), seq, t_ss, k)
    wall = time.perf_counter() - wall0
    records = results.particles
    pbm_config = pbm_config_for(config, table, None)
    rows = rtd_by_size(results, by_size, pbm_config, diameters)
    whole = {"one": pbm_numbers(one_chain.phases, config, target), "by": pbm_numbers(by_size.phases, config, target)}
    _edges, density, n = dem_density(records, summary.pooled_rtd)
    bin_s = float(summary.pooled_rtd.bin_s)
    for numbers in whole.values():
        e_pbm = numbers["density_per_s"]
        numbers["rtd_overlap"] = rtd_overlap(density, e_pbm[: density.size], bin_s)
        numbers["overlap_noise_low"] = overlap_noise_band(e_pbm, bin_s, n).low
    return SizeStudy(
        tuple(rows),
        phases.phases_per_kind(by_size.phases),
        {"mean_s": target.mean_s, "variance_s2": target.variance_s2, "holdup": target.holdup},
        {key: float(whole["one"][key]) for key in WHOLE},
        {key: float(whole["by"][key]) for key in WHOLE},
        wall,
        zone_residences,
    )


def markdown(study: SizeStudy) -> str:
    """The study's two tables: by size class, and for the whole feed."""
    zone = (
        "no zone" if study.zone_residences is None else f"zone left once per {study.zone_residences:g} residence times"
    )
    lines = [
        f"| diameter [mm] | share | tracers | DEM mean [s] | DEM variance [s²] | DEM beyond H | "
        f"{study.n_phases} phases per class ({zone}): mean / variance / beyond H |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for c in study.classes:
        m, v = c.dem_mean_s, c.dem_variance_s2
        lines.append(
            f"| {1e3 * c.diameter_m:.2f} | {c.share:.3f} | {c.n_entered} | {m.value:.2f} [{m.low:.2f}, {m.high:.2f}] | "
            f"{v.value:.0f} [{v.low:.0f}, {v.high:.0f}] | {c.dem_beyond:.2%} | "
            f"{c.pbm_mean_s:.2f} / {c.pbm_variance_s2:.0f} / {c.pbm_beyond:.2%} |"
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
    overlap = [
        f"{x['rtd_overlap']:.3f} {'✓' if x['rtd_overlap'] >= x['overlap_noise_low'] else '✗'} "
        f"(noise band ≥ {x['overlap_noise_low']:.3f})"
        for x in (study.one_chain, study.by_size)
    ]
    lines.append(f"| RTD overlap | | {overlap[0]} | {overlap[1]} |")
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
    parser.add_argument(
        "--zone",
        default=str(phases.ZONE_RESIDENCES),
        metavar="R",
        help="each class's dead zone is left at most once per R Little's-law residence times of the run, its "
        "entry then held to the class's Little's law; 'none' fits no zone (default: the product's, %(default)s)",
    )
    parser.add_argument("--out", default=str(OUT), help="output folder (default: %(default)s)")


def zone_argument(text: str) -> float | None:
    """``--zone``'s value: a positive number of residence times, or None for 'none'."""
    if text.strip().lower() == "none":
        return None
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise ConfigError(f"--zone {text}: expected a number of residence times > 0, or 'none' for no dead zone")
    return value


def run(args: argparse.Namespace) -> int:
    if args.k is not None and args.k < 1:
        raise ConfigError(f"--k {args.k}: expected a number of phases >= 1")
    started = time.perf_counter()
    study = size_study(args.results, args.run_dir, args.k, zone_argument(args.zone))
    print(markdown(study))
    print(f"per-class fits {study.fit_wall_s:.0f} s")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    record = {"results": str(args.results), **asdict(study), "wall_time_s": time.perf_counter() - started}
    print(f"wrote {write_json(out / 'sizes.json', record)}")
    return 0
