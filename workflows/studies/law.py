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

The covariates (``--covariates``) are :mod:`workflows.prediction.library`'s; the default
is all of them. On the 13 shipped runs with the six first (500 EM iterations a fit, about
4 minutes here), the four first alone leave the 150-rpm run's steady hold-up 16 % high (a
law log-linear in speed cannot bend between 150 and 350 rpm); with the squares every run
is within 4.3 %. The EM is not converged at 1e-7 nats per particle-step after 500
iterations; from 150 to 500 the hold-ups moved by at most 1.4 %. ``pbmdem library fit``
fits the same law for ``pbmdem predict`` and judges every quantity, not only these two.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from coupling.errors import ConfigError
from coupling.files import writable_directory
from coupling.jsonable import write_json
from dem.phases.chain import steady_occupancy
from dem.phases.law import PhaseLaw, fit_law
from dem.summary import Estimate
from workflows.prediction.library import COVARIATES, DEFAULT_COVARIATES, LibraryRun, library_run
from workflows.shipped import library_runs
from workflows.studies import distinct_runs

HELP = "one phase chain for a DEM library, its rates laws of speed, length, position and feed; each run left out"
OUT = Path("results/law")


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
    resolved = [p.resolve() for p in distinct_runs(paths)]
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
        default=library_runs(),
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
