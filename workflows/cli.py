"""The ``pbmdem`` command line: ``pbmdem config``, ``pbmdem compare``, ``pbmdem validate``,
``pbmdem design``, ``pbmdem pbm ...`` (:mod:`workflows.cli_pbm`) and ``pbmdem dem ...``
(:mod:`workflows.cli_dem`).

Every command parses its arguments and makes one library call; library code raises, and
only :func:`main` turns a project error into one line on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from coupling.errors import ConfigError, PbmDemError, error_line
from workflows.config import add_config_arguments, dump_toml, preset_names, resolve_config
from workflows.pipeline import stderr_log


def build_parser() -> argparse.ArgumentParser:
    from workflows import cli_dem, cli_pbm

    parser = argparse.ArgumentParser(
        prog="pbmdem", description="Hybrid DEM-PBM pipeline for continuous powder blenders (Sen et al. 2013).")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    config = sub.add_parser("config", help="list presets, print or validate a configuration")
    config.add_argument("--preset", help="preset name")
    config.add_argument("--config", help="TOML configuration file to validate and print")
    config.add_argument("--list", action="store_true", help="list the preset names")
    config.set_defaults(func=config_command)

    compare = sub.add_parser(
        "compare", help="DEM (or its cached / shipped results) -> velocity tables -> PBM -> side-by-side report")
    add_config_arguments(compare)
    compare.add_argument("--np", type=int, default=None, help="MPI ranks for LIGGGHTS (default: the config's)")
    compare.add_argument("--fresh", action="store_true", help="ignore cached and shipped DEM results: run LIGGGHTS again")
    compare.add_argument("--resume", action="store_true", help="resume an interrupted DEM run from its restart file")
    compare.add_argument("--results-dir", default="results", help="where <preset>-<hash>/report.html goes")
    compare.add_argument("--runs-dir", default="runs", help="root of the DEM run directories and cache")
    compare.add_argument("--noise-members", type=int, default=200, help="realisations per noise level")
    compare.add_argument("--no-paraview", action="store_true", help="skip the ParaView (VTK) files")
    compare.add_argument("--no-progress", action="store_true", help="no progress bar")
    compare.set_defaults(func=compare_command)

    validate = sub.add_parser(
        "validate", help="the validation campaign: DEM runs with one factor changed, predicted by PBMs built without them")
    validate.add_argument("--out", default="results/validation", help="where report.html goes")
    validate.add_argument("--runs-dir", default="runs/validation", help="the campaign's DEM runs and their cache")
    validate.add_argument("--np", type=int, default=None, help="MPI ranks per run (default: the preset's)")
    validate.add_argument("--fresh", action="store_true", help="ignore cached and shipped results: rerun every DEM run")
    validate.set_defaults(func=validate_command)

    design = sub.add_parser(
        "design", help="the smallest blender and the impeller speeds that meet a spec, from a table library of DEM runs")
    spec = design.add_argument_group("the spec (at least one of --ca-within, --rsd-max, --mrt-min, --mrt-max)")
    spec.add_argument("--ca-within", type=float, default=None, metavar="X",
                      help="outlet C_A within +-X (absolute fraction) for --coverage standard deviations")
    spec.add_argument("--coverage", type=float, default=3.0, help="standard deviations within --ca-within (default 3)")
    spec.add_argument("--rsd-max", type=float, default=None, help="largest relative SD of the outlet C_A")
    spec.add_argument("--mrt-min", type=float, default=None, help="shortest mean residence time [s]")
    spec.add_argument("--mrt-max", type=float, default=None, help="longest mean residence time [s]")
    feeder = design.add_argument_group("the feeder noise the composition criteria are judged under")
    feeder.add_argument("--noise-sigma", type=float, default=0.0, help="relative SD of the feeder's rate")
    feeder.add_argument("--noise-tau", type=float, default=0.0, help="its correlation time [s] (0: white)")
    feeder.add_argument("--noise-band", type=float, default=0.5, help="its bandwidth [Hz] (default 0.5)")
    feeder.add_argument("--noise-feeder", choices=("A", "B"), default="A", help="the noisy feeder (default A)")
    space = design.add_argument_group("the design space (refused outside the library's)")
    space.add_argument("--rpm-min", type=float, default=None, help="default: the library's lowest speed")
    space.add_argument("--rpm-max", type=float, default=None, help="default: the library's highest speed")
    space.add_argument("--length-min", type=float, default=None, help="smallest length factor (default 0.5)")
    space.add_argument("--length-max", type=float, default=None, help="largest length factor (default 2.0)")
    design.add_argument("--library", default=None,
                        help="directory of DEM results files (default: the shipped validation campaign)")
    design.add_argument("--rates", choices=("measured", "velocity"), default="measured",
                        help="PBM transfer rates (default measured: the mode whose residence times follow the DEM "
                             "across speeds)")
    design.add_argument("--out", default="results/design", help="where design.json and feasible.png go")
    design.set_defaults(func=design_command)

    cli_pbm.register(sub)
    cli_dem.register(sub)
    return parser


def config_command(args: argparse.Namespace) -> int:
    if args.list:
        print("\n".join(preset_names()))
        return 0
    print(dump_toml(resolve_config(args.preset, args.config)), end="")
    return 0


def compare_command(args: argparse.Namespace) -> int:
    from workflows.compare import full_comparison

    if args.noise_members < 1:
        raise ConfigError(f"--noise-members must be >= 1, got {args.noise_members}")
    report = full_comparison(
        resolve_config(args.preset, args.config), results_root=Path(args.results_dir), runs_root=Path(args.runs_dir),
        np_ranks=args.np, fresh=args.fresh, resume=args.resume, noise_members=args.noise_members,
        paraview=not args.no_paraview, progress=not args.no_progress, log=stderr_log)
    print(f"report: {report}")
    return 0


def validate_command(args: argparse.Namespace) -> int:
    from workflows.validation import validation_report

    page = validation_report(args.out, args.runs_dir, fresh=args.fresh, nprocs=args.np, log=stderr_log)
    print(f"report: {page}")
    return 0


def design_command(args: argparse.Namespace) -> int:
    from pbm.design import design_spec
    from workflows.design import REFERENCE_DIR, answer_lines, run_design

    given = {"ca_tolerance": args.ca_within, "coverage_sigmas": args.coverage, "rsd_max": args.rsd_max,
             "mrt_min_s": args.mrt_min, "mrt_max_s": args.mrt_max, "noise_sigma": args.noise_sigma,
             "noise_tau_s": args.noise_tau, "noise_band_hz": args.noise_band, "noise_feeder": args.noise_feeder,
             "rpm_min": args.rpm_min, "rpm_max": args.rpm_max, "length_factor_min": args.length_min,
             "length_factor_max": args.length_max}
    spec = design_spec(**{k: v for k, v in given.items() if v is not None})
    result, out = run_design(spec, args.out, args.library or REFERENCE_DIR, args.rates, log=stderr_log)
    print("\n".join(answer_lines(result)))
    print(f"design.json and feasible.png: {out}")
    return 0 if result.best is not None else 1


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (PbmDemError, OSError) as exc:  # OSError: the file system said no (a path, the disk, a permission)
        print(f"pbmdem: error: {error_line(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("pbmdem: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
