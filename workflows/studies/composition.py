"""``pbmdem study composition``: is the DEM's outlet segregated, or is its RSD sampling?

The outlet RSD is a mean over the steady dumps of the RSD across the last slice's
compartments at that dump's counts. Three numbers on one DEM results file with per-dump counts
(or compartment sequences) tell segregation from sampling:

* the DEM's outlet RSD and its random-mixture floor (both from the dumps);
* the RSD of a random mixture at the DEM's own counts: at every steady dump, the A
  particles then in the last slice dealt at random over its compartments (multivariate
  hypergeometric), everything else as in the DEM;
* the time-averaged A fraction of each outlet compartment (segregation by feed side
  would show as a tilt across y: A is fed on +y, B on -y).

and, for every PBM rate mode, its outlet RSD sampled at the DEM's mean counts (the
basis before per-dump counts were kept) and at the DEM's counts dump by dump (the
agreement table's). Writes ``composition.json`` and prints a table.
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from coupling.errors import ConfigError
from coupling.intervals import Interval
from coupling.jsonable import write_json
from coupling.metrics import rsd
from workflows.analysis.agreement import agreement_rows, pbm_steady, run_modes
from workflows.pipeline.results import load_results, pbm_config_for, rtd_pulse
from workflows.shipped import REDUCED_RUN

HELP = "the outlet's composition: segregation or sampling (DEM RSD against a random mixture at its own counts)"
OUT = Path("results/composition")
#: random deals per steady dump
DEALS = 20


@dataclass(frozen=True)
class CompositionStudy:
    """What :func:`composition_study` measures (module docstring)."""

    dem_rsd: Interval
    dem_floor: float
    random_mixture_rsd: float
    a_fraction_by_compartment: tuple[float, ...]
    mean_particles_by_compartment: tuple[float, ...]
    pbm_at_mean_counts: dict[str, float]
    pbm_at_dump_counts: dict[str, float]
    steady_dumps: int


def random_mixture_at(counts_a: np.ndarray, totals: np.ndarray, deals: int, rng: np.random.Generator) -> float:
    """Mean outlet RSD when, at each dump (row), the A particles of the row are dealt at
    random over its compartments of ``totals`` particles (``deals`` deals per dump)."""
    values = []
    for a, n in zip(counts_a.sum(axis=1), totals):
        for _ in range(deals):
            dealt = rng.multivariate_hypergeometric(n, a)
            values.append(rsd(dealt.astype(float), (n - dealt).astype(float)))
    values = np.asarray(values)
    return float(values[np.isfinite(values)].mean())


def composition_study(results_path: str | Path, seed: int = 0) -> CompositionStudy:
    results, config = load_results(results_path)
    summary = results.summary
    if summary.steady_time is None or "rsd_outlet" not in summary.steady:
        raise ConfigError(f"{results_path}: the DEM run reached no steady state, so it has no steady outlet RSD")
    outlet = results.steady_outlet_counts()
    if outlet is None:
        raise ConfigError(
            f"{results_path}: neither per-dump counts nor compartment sequences on the table's grid; "
            "post-process the run again"
        )
    a, totals = outlet[:, 0].astype(np.int64), outlet.sum(axis=1).astype(np.int64)
    series = results.timeseries[results.timeseries["t_s"] > summary.steady_time]
    steady = summary.steady["rsd_outlet"]
    pooled = a.sum(axis=0) / np.maximum(totals.sum(axis=0), 1)
    pbm_config = pbm_config_for(config, results.table, rtd_pulse(summary))
    modes = run_modes(results.table, pbm_config, config.steady_state, summary)
    at_dumps = agreement_rows(summary, results.particles, modes, outlet)
    row = next(r for r in at_dumps if r.key == "rsd_outlet")
    return CompositionStudy(
        dem_rsd=Interval(float(steady["value"]), float(steady["low"]), float(steady["high"])),
        dem_floor=float(series["rsd_outlet_floor"].mean()),
        random_mixture_rsd=random_mixture_at(a, totals, DEALS, np.random.default_rng(seed)),
        a_fraction_by_compartment=tuple(float(v) for v in pooled),
        mean_particles_by_compartment=tuple(float(v) for v in totals.mean(axis=0)),
        pbm_at_mean_counts={
            mode: float(pbm_steady(m.result, summary.steady)["rsd_outlet"]) for mode, m in modes.items()
        },
        pbm_at_dump_counts={mode: float(row.value(mode)) for mode in modes},
        steady_dumps=len(outlet),
    )


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--results",
        default=str(REDUCED_RUN),
        help="DEM results file with per-dump counts or sequences (default: %(default)s)",
    )
    parser.add_argument("--out", default=str(OUT), help="output folder (default: %(default)s)")


def run(args: argparse.Namespace) -> int:
    started = time.perf_counter()
    study = composition_study(args.results)
    low, high = study.dem_rsd.low, study.dem_rsd.high

    def mark(v: float) -> str:
        return "✓" if math.isfinite(v) and low <= v <= high else "✗"

    print(f"DEM outlet RSD {study.dem_rsd.estimate:.3f} [{low:.3f}, {high:.3f}] over {study.steady_dumps} steady dumps")
    print(
        f"its random-mixture floor {study.dem_floor:.3f}; a random mixture at the DEM's own counts {study.random_mixture_rsd:.3f}"
    )
    print(
        "time-averaged A fraction per outlet compartment (-y ... +y):",
        " ".join(f"{v:.2f}" for v in study.a_fraction_by_compartment),
    )
    print("mean particles per outlet compartment:", " ".join(f"{v:.1f}" for v in study.mean_particles_by_compartment))
    print("| PBM rates | sampled at the DEM's mean counts | at its counts dump by dump |\n| --- | --- | --- |")
    for mode, at_dumps in study.pbm_at_dump_counts.items():
        at_means = study.pbm_at_mean_counts[mode]
        print(f"| {mode} | {at_means:.3f} {mark(at_means)} | {at_dumps:.3f} {mark(at_dumps)} |")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    record = {"results": str(args.results), **asdict(study), "wall_time_s": time.perf_counter() - started}
    record["dem_rsd"] = study.dem_rsd._asdict()
    print(f"wrote {write_json(out / 'composition.json', record)}")
    return 0
