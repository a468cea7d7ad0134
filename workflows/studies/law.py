"""``pbmdem study law``: one phase chain for a library of DEM runs, its rates laws of the
operating point, judged on every run it was fitted to and on every run left out of it.

A per-run phase model reproduces its own run and is no function of speed, feed or length.
:mod:`dem.phases.law` fits one chain to every particle of every run at once, each rate
exp(x . beta) of its compartment's covariates x; this study builds x from each run's
operating point (:class:`coupling.operating.OperatingPoint`), fits the law to the library,
and for each run compares the law's steady hold-up and Little's-law mean residence time
(the chain's steady occupancy under the run's feed) with the DEM's intervals, fitted with
the run (``self``) and without it (``held out``, the law refitted to the other runs: a
prediction of an operating point the fit never saw). It needs only what the results store
(the compartment sequences). Writes ``law.json`` and prints a table.

The covariates (``--covariates``, the constant always first):

* ``speed``: log(impeller speed / :data:`REFERENCE_RPM`);
* ``length``: log(slice length / :data:`REFERENCE_SLICE_M`): a longer blender on the same
  number of slices has longer slices, crossed more slowly;
* ``position``: the slice's centre from inlet (-0.5) to weir (+0.5);
* ``feed``: log(total feed rate / :data:`REFERENCE_FEED_PER_S`), the same in every slice
  of a run (a proxy of the fill: the bed deepens with the feed);
* ``speed2``, ``position2``: the squares of ``speed`` and ``position`` (a law curved in
  speed; the inlet wall and the weir at both ends of the slices).

The default covariates are all six. On the 13 shipped runs (500 EM iterations a fit, about
4 minutes here), the four first alone leave the 150-rpm run's steady hold-up 16 % high (a
law log-linear in speed cannot bend between 150 and 350 rpm); with the squares every run
is within 4.3 %. The EM is not converged at 1e-7 nats per particle-step after 500
iterations; from 150 to 500 the hold-ups moved by at most 1.4 %.
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from coupling.errors import ConfigError
from coupling.files import writable_directory
from coupling.jsonable import write_json
from coupling.operating import OperatingPoint
from dem.phases.chain import steady_occupancy
from dem.phases.data import first_compartments, prepare, steady_window
from dem.phases.law import LawRun, PhaseLaw, fit_law
from dem.phases.settings import PHASE_LAG_S, PhaseSettings
from dem.summary import Estimate
from workflows.pipeline.results import load_results, run_operating_point
from workflows.shipped import REFERENCE_DIR, VALIDATION_DIR

HELP = "one phase chain for a DEM library, its rates laws of speed, length, position and feed; each run left out"
OUT = Path("results/law")
#: the library's baseline: the validation preset's speed, slice length (0.33 m over 10
#: slices) and total feed [rpm, m, particles/s]
REFERENCE_RPM = 250.0
REFERENCE_SLICE_M = 0.033
REFERENCE_FEED_PER_S = 73.7
COVARIATES = ("speed", "length", "position", "feed", "speed2", "position2")
DEFAULT_COVARIATES = ("speed", "length", "position", "feed", "speed2", "position2")
#: the axial grid the law is fitted on (the product's phase model is axial)
AXIAL_SLICES = 10
LIBRARY_DIR = REFERENCE_DIR / "library"


def covariate_columns(point: OperatingPoint, nx: int, names: tuple[str, ...]) -> np.ndarray:
    """(NX, 1 + len(names)) covariates of the ``nx`` axial slices of a run at ``point``
    (module docstring), the constant first."""
    position = (np.arange(nx) + 0.5) / nx - 0.5
    feed = point.feed_rate_a_per_s + point.feed_rate_b_per_s
    values = {
        "speed": np.full(nx, math.log(point.impeller_rpm / REFERENCE_RPM)),
        "length": np.full(nx, math.log(point.length_m / nx / REFERENCE_SLICE_M)),
        "position": position,
        "feed": np.full(nx, math.log(feed / REFERENCE_FEED_PER_S)),
        "speed2": np.full(nx, math.log(point.impeller_rpm / REFERENCE_RPM) ** 2),
        "position2": position**2,
    }
    return np.column_stack([np.ones(nx)] + [values[name] for name in names])


@dataclass(frozen=True)
class LibraryRun:
    """One run of the library: its law data, operating point, the DEM's steady hold-up
    and Little's-law mean residence time with their intervals, and the feed's inlet
    distribution over the slices (2, NX) [particles/s]."""

    name: str
    law_run: LawRun
    point: OperatingPoint
    holdup: Estimate
    little_s: Estimate
    entering: np.ndarray


def library_run(path: str | Path, names: tuple[str, ...], lag_s: float = PHASE_LAG_S) -> LibraryRun:
    """:class:`LibraryRun` of the results file ``path``: its particles that entered in the
    steady window (and those inside then), on :data:`AXIAL_SLICES` slices. Raises
    ConfigError naming the file when it has no sequences or no steady state."""
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
    feed = point.feed_rate_a_per_s + point.feed_rate_b_per_s
    entering = first_compartments(data)[:2]
    entering = entering / max(entering.sum(), 1e-300) * feed
    name = f"{Path(path).name} ({point.impeller_rpm:g} rpm, {feed:g} /s, {point.length_m:g} m)"
    law_run = LawRun(data, covariate_columns(point, AXIAL_SLICES, names), name)
    return LibraryRun(
        name,
        law_run,
        point,
        Estimate.from_record(summary.steady["holdup"]),
        Estimate.from_record(summary.steady["little_mean_residence_time_s"]),
        entering,
    )


def steady_holdup(law: PhaseLaw, run: LibraryRun) -> float:
    """The law's steady hold-up at ``run``'s operating point under its feed [particles]."""
    model = law.run_chain(run.law_run)
    return float(steady_occupancy(model, run.entering).sum())


@dataclass(frozen=True)
class Judged:
    """The law's steady hold-up of one run against the DEM's, and its Little's-law mean
    residence time; ``fitted_with``: whether the run was among those the law was fitted to."""

    run: str
    fitted_with: bool
    holdup: float
    dem_holdup: Estimate
    mean_s: float
    dem_little_s: Estimate

    @property
    def holdup_error(self) -> float:
        return self.holdup / self.dem_holdup.value - 1.0

    @property
    def inside(self) -> bool:
        return self.dem_holdup.low <= self.holdup <= self.dem_holdup.high


def judged(law: PhaseLaw, run: LibraryRun, fitted_with: bool) -> Judged:
    holdup = steady_holdup(law, run)
    return Judged(run.name, fitted_with, holdup, run.holdup, holdup / run.entering.sum(), run.little_s)


@dataclass(frozen=True)
class LawStudy:
    covariates: tuple[str, ...]
    n_phases: int
    law: PhaseLaw
    self_judged: tuple[Judged, ...]
    held_out: tuple[Judged, ...]
    held_out_log_likelihood_per_step: tuple[float, ...]
    wall_time_s: float

    def record(self) -> dict:
        law = self.law
        return {
            "covariates": list(self.covariates),
            "n_phases": self.n_phases,
            "n_parameters": law.n_parameters,
            "log_likelihood_per_step": law.log_likelihood / max(law.n_steps, 1),
            "converged": law.converged,
            "iterations": law.iterations,
            "coefficients": {key: value.tolist() for key, value in sorted(law.coefficients.items())},
            "entry": law.entry.tolist(),
            "self": [_judged_record(j) for j in self.self_judged],
            "held_out": [_judged_record(j) for j in self.held_out],
            "held_out_log_likelihood_per_step": list(self.held_out_log_likelihood_per_step),
            "wall_time_s": self.wall_time_s,
        }


def _judged_record(j: Judged) -> dict:
    return {**asdict(j), "holdup_error": j.holdup_error, "inside": j.inside}


def law_study(
    paths: list[str],
    names: tuple[str, ...],
    n_phases: int,
    held_out: list[str] | None,
    max_iterations: int,
    tol: float,
) -> LawStudy:
    """Fit the law to every run of ``paths`` and judge it on each; refit without each run
    of ``held_out`` (default: every run) and judge it on that run."""
    started = time.perf_counter()
    unknown = sorted(set(names) - set(COVARIATES))
    if unknown:
        raise ConfigError(f"covariates {unknown} unknown; valid: {', '.join(COVARIATES)}")
    resolved = [Path(p).resolve() for p in paths]
    left = resolved if held_out is None else [Path(p).resolve() for p in held_out]
    strangers = [str(p) for p in left if p not in resolved]
    if strangers:
        raise ConfigError(f"--held-out {', '.join(strangers)}: not among the runs fitted (--results)")
    runs = [library_run(path, names) for path in paths]
    if len(runs) < 2:
        raise ConfigError(f"a law needs at least 2 runs to fit and judge, got {len(runs)}")
    columns = ("1", *names)
    law = fit_law([r.law_run for r in runs], n_phases, columns, max_iterations, tol)
    self_judged = tuple(judged(law, run, True) for run in runs)
    out, scores = [], []
    for n, (path, run) in enumerate(zip(resolved, runs)):
        if path not in left:
            continue
        rest = [r.law_run for m, r in enumerate(runs) if m != n]
        without = fit_law(rest, n_phases, columns, max_iterations, tol)
        out.append(judged(without, run, False))
        scores.append(without.score(run.law_run) / max(run.law_run.data.n_steps, 1))
        print(f"  left out {run.name}: {out[-1].holdup_error:+.1%}", flush=True)
    return LawStudy(names, n_phases, law, self_judged, tuple(out), tuple(scores), time.perf_counter() - started)


def markdown(study: LawStudy) -> str:
    lines = [
        "| run | fitted with it | law hold-up | DEM hold-up [95 %] | error | law mean [s] | DEM Little [s] |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]
    for j in study.self_judged + study.held_out:
        d, m = j.dem_holdup, j.dem_little_s
        lines.append(
            f"| {j.run} | {'yes' if j.fitted_with else 'no'} | {j.holdup:.0f} {'✓' if j.inside else '✗'} | "
            f"{d.value:.0f} [{d.low:.0f}, {d.high:.0f}] | {j.holdup_error:+.1%} | {j.mean_s:.2f} | {m.value:.2f} |"
        )
    law = study.law
    lines.append(
        f"\n{law.n_parameters} parameters, {law.iterations} EM iterations ({'converged' if law.converged else 'not converged'}), "
        f"{study.wall_time_s:.0f} s"
    )
    return "\n".join(lines)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--results",
        nargs="+",
        default=[
            *sorted(str(p) for p in VALIDATION_DIR.glob("dem-*.h5")),
            *sorted(str(p) for p in LIBRARY_DIR.glob("dem-*.h5")),
        ],
        metavar="FILE",
        help="DEM results files with compartment sequences (default: the validation campaign and the library)",
    )
    parser.add_argument(
        "--covariates",
        default=",".join(DEFAULT_COVARIATES),
        help=f"comma-separated, from {', '.join(COVARIATES)} (default: %(default)s)",
    )
    parser.add_argument("--phases", type=int, default=3, help="phases K (default: %(default)s)")
    parser.add_argument(
        "--held-out", nargs="*", default=None, metavar="FILE", help="runs to leave out (default: every run)"
    )
    parser.add_argument("--max-iterations", type=int, default=500, help="EM iterations per fit (default: %(default)s)")
    parser.add_argument(
        "--tol", type=float, default=1e-7, help="EM stopping gain [nats per particle-step] (default: %(default)s)"
    )
    parser.add_argument("--out", default=str(OUT), help="output folder (default: %(default)s)")


def run(args: argparse.Namespace) -> int:
    names = tuple(n.strip() for n in args.covariates.split(",") if n.strip())
    if args.max_iterations < 1:
        raise ConfigError(f"--max-iterations must be >= 1, got {args.max_iterations}")
    study = law_study(list(args.results), names, args.phases, args.held_out, args.max_iterations, args.tol)
    print(markdown(study))
    out = writable_directory(args.out, "--out")
    print(f"wrote {write_json(out / 'law.json', study.record())}")
    return 0
