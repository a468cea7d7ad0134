"""``pbmdem library fit [--results FILE...] [--out DIR]``: the law of a DEM library, its
laws with each run left out, the intervals calibrated on them and checked
(:mod:`workflows.products.predict`). ``pbmdem library check --results FILE...``: DEM runs
the library does not hold, predicted by its law and judged against their DEM.
``pbmdem library suggest``: the next DEM run that most narrows the intervals, as a
configuration. ``pbmdem library add RESULTS.h5...``: the library refitted with more runs.
``pbmdem library build CONFIG...`` / ``status``: the DEM runs of configurations into a
library folder (a Slurm job array, or here in turn) and their state."""

from __future__ import annotations

import argparse

HELP = "a DEM library's law: fit it, calibrate its prediction intervals on each run left out"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from workflows.prediction.covariates import AXIAL_SLICES, REFERENCE_FEED_PER_S, REFERENCE_RPM, REFERENCE_SLICE_M
    from workflows.prediction.library import (
        CORRECTION_TERMS,
        COVARIATES,
        DEFAULT_CORRECTION,
        DEFAULT_COVARIATES,
        FIT_ITERATIONS,
        LEFT_OUT_ITERATIONS,
        LIBRARY_PHASES,
    )

    sub = parser.add_subparsers(dest="library_command", required=True, metavar="LIBRARY_COMMAND")
    fit = sub.add_parser("fit", help="fit the law of a library of DEM results and calibrate its intervals")
    fit.add_argument(
        "--results",
        nargs="+",
        default=None,
        metavar="FILE",
        help="DEM results files with compartment sequences (default: the shipped campaign and library)",
    )
    fit.add_argument("--out", default="results/library", help="output folder (default: %(default)s)")
    fit.add_argument("--phases", type=int, default=LIBRARY_PHASES, help="phases K (default: %(default)s)")
    fit.add_argument(
        "--covariates",
        default=",".join(DEFAULT_COVARIATES),
        help=f"comma-separated, from {', '.join(COVARIATES)} (default: %(default)s)",
    )
    fit.add_argument(
        "--iterations", type=int, default=FIT_ITERATIONS, help="EM iterations of the whole fit (default: %(default)s)"
    )
    fit.add_argument(
        "--left-out-iterations",
        type=int,
        default=LEFT_OUT_ITERATIONS,
        help="EM iterations of each fit with one run left out, from the whole fit (default: %(default)s)",
    )
    fit.add_argument(
        "--correction",
        default=",".join(DEFAULT_CORRECTION),
        help=f"the correction line's covariates, comma-separated, from {', '.join(CORRECTION_TERMS)}; "
        "'none' for the law's mean error alone (default: %(default)s)",
    )
    _jobs_argument(fit)
    fit.set_defaults(func=fit_command)

    check = sub.add_parser("check", help="predict DEM runs the library does not hold and judge each against its DEM")
    check.add_argument("--results", nargs="+", required=True, metavar="FILE", help="DEM results files to judge")
    check.add_argument(
        "--library", default=None, help="a library model (library.json or its folder; default: the shipped one)"
    )
    check.add_argument("--extrapolate", action="store_true", help="judge runs outside the library's domain too")
    check.add_argument("--out", default=None, help="write check.json and check.md into this folder")
    check.set_defaults(func=check_command)

    build = sub.add_parser("build", help="run the DEM of configuration files into a library folder (a Slurm job array)")
    build.add_argument("configs", nargs="+", metavar="CONFIG", help="configuration files (TOML), one run each")
    build.add_argument(
        "--scheduler",
        choices=("slurm", "local"),
        default="slurm",
        help="slurm: one job array (sbatch), returns at once, follow it with `library status`; "
        "local: each run here in turn (default: %(default)s)",
    )
    build.add_argument(
        "--library",
        default="results/library",
        help="the library's folder, where finished results land as dem-<key>.h5 (default: %(default)s)",
    )
    build.add_argument("--runs-dir", default="runs", help="the runs and their cache (default: %(default)s)")
    build.add_argument("--np", type=int, default=None, help="MPI ranks per run (default: the configs' dem.run.np)")
    build.add_argument("--partition", default=None, help="Slurm partition")
    build.set_defaults(func=build_command)

    status = sub.add_parser("status", help="the state of each run of a library build (sacct); add finished results")
    status.add_argument(
        "--library", default="results/library", help="the library's folder of the build (default: %(default)s)"
    )
    status.add_argument(
        "--resubmit-failed",
        action="store_true",
        help="submit the failed runs again as one job array; each resumes from its restart files",
    )
    status.set_defaults(func=status_command)

    suggest = sub.add_parser(
        "suggest", help="the next DEM run that most narrows the prediction intervals, as a configuration"
    )
    suggest.add_argument(
        "--library", default=None, help="a library model (library.json or its folder; default: the shipped one)"
    )
    suggest.add_argument(
        "--region",
        default=None,
        help="where the intervals matter, e.g. speed=200:300,length=0.33:0.41,feed=60:110 (rpm, m, particles/s; "
        "default: the library's whole domain)",
    )
    suggest.add_argument(
        "--extend",
        type=float,
        default=0.0,
        help="candidates also beyond the domain's edges, by this fraction of each axis' width (default: %(default)s)",
    )
    suggest.add_argument(
        "--base",
        default=None,
        help="configuration to build the run from (default: the configuration of the library's run nearest its "
        f"reference point, {REFERENCE_RPM:g} rpm, {REFERENCE_SLICE_M * AXIAL_SLICES:g} m, "
        f"{REFERENCE_FEED_PER_S:g} particles/s)",
    )
    suggest.add_argument("--top", type=int, default=5, help="candidates to list (default: %(default)s)")
    suggest.add_argument(
        "--out", default="results/suggest", help="folder of suggest.toml, .json and .md (default: %(default)s)"
    )
    suggest.set_defaults(func=suggest_command)

    add = sub.add_parser("add", help="add DEM results to a library and refit it (its cached fits reused)")
    add.add_argument("results", nargs="+", metavar="RESULTS.h5", help="DEM results files with compartment sequences")
    add.add_argument(
        "--library",
        default="results/library",
        help="the library's folder, made by `library fit` (default: %(default)s)",
    )
    _jobs_argument(add)
    add.set_defaults(func=add_command)


def _jobs_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--jobs",
        type=int,
        default=1,
        help="processes for the fits with one run left out, each as long as a few EM minutes; "
        "up to the cores free (default: %(default)s)",
    )


def fit_command(args: argparse.Namespace) -> int:
    from workflows.prediction import calibration
    from workflows.prediction.library import FitSettings
    from workflows.products.library import library_fit
    from workflows.shipped import library_runs

    names = tuple(n.strip() for n in args.covariates.split(",") if n.strip())
    correction = tuple(n.strip() for n in args.correction.split(",") if n.strip() and n.strip() != "none")
    settings = FitSettings(args.phases, names, args.iterations, args.left_out_iterations, correction=correction)
    output = library_fit(list(args.results or library_runs()), args.out, settings, jobs=args.jobs)
    print(calibration.markdown(output.model, output.check))
    for what, path in output.files.items():
        print(f"wrote {what}: {path}")
    return 0


def check_command(args: argparse.Namespace) -> int:
    from workflows.products.library import library_check

    output = library_check(args.results, args.library, args.extrapolate, args.out)
    print(output.text)
    for what, path in output.files.items():
        print(f"wrote {what}: {path}")
    return 0


def build_command(args: argparse.Namespace) -> int:
    from workflows.pipeline.log import stderr_log
    from workflows.products.library_build import build_library, status_table

    states = build_library(
        args.configs, args.library, args.scheduler, args.runs_dir, args.np, args.partition, log=stderr_log
    )
    print(status_table(states))
    if args.scheduler == "slurm":  # a local build has run to its end here
        print(f"follow it with: pbmdem library status --library {args.library}")
    return 0


def status_command(args: argparse.Namespace) -> int:
    from workflows.pipeline.log import stderr_log
    from workflows.products.library_build import library_status, status_table

    print(status_table(library_status(args.library, resubmit_failed=args.resubmit_failed, log=stderr_log)))
    return 0


def suggest_command(args: argparse.Namespace) -> int:
    from coupling.errors import ConfigError
    from workflows.products.library import library_suggest

    if args.top < 1:
        raise ConfigError(f"--top {args.top}: list at least 1 candidate")
    output = library_suggest(args.library, args.out, args.region, args.extend, args.base, args.top)
    for n, s in enumerate(output.suggestions, 1):
        notes = ["outside the domain"] if s.outside_domain else []
        notes += [f"the correction gains {', '.join(s.gains)}"] if s.gains else []
        print(
            f"{n}. {s.speed:.4g} rpm, {s.length:.4g} m, {s.feed:.4g} particles/s: criterion {s.criterion_now:.3g} -> "
            f"{s.criterion_after:.3g} ({-s.relative_reduction:+.1%})" + (f" ({'; '.join(notes)})" if notes else "")
        )
    for what, path in output.files.items():
        print(f"wrote {what}: {path}")
    return 0


def add_command(args: argparse.Namespace) -> int:
    from workflows.prediction import calibration
    from workflows.products.library import library_add

    output = library_add(args.results, args.library, jobs=args.jobs)
    print(calibration.markdown(output.model, output.check))
    print(f"added {len(output.added)} run(s): {', '.join(p.name for p in output.added)}")
    for what, path in output.files.items():
        print(f"wrote {what}: {path}")
    return 0
