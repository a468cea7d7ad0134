"""``pbmdem design``: the smallest blender and the impeller speeds that meet a spec, from a
table library of DEM runs."""

from __future__ import annotations

import argparse

from workflows.pipeline.log import stderr_log

HELP = "the smallest blender and the impeller speeds that meet a spec, from a table library of DEM runs"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    spec = parser.add_argument_group("the spec (at least one of --ca-within, --rsd-max, --mrt-min, --mrt-max)")
    spec.add_argument(
        "--ca-within",
        type=float,
        default=None,
        metavar="X",
        help="outlet C_A within +-X (absolute fraction) for --coverage standard deviations",
    )
    spec.add_argument("--coverage", type=float, default=3.0, help="standard deviations within --ca-within (default 3)")
    spec.add_argument("--rsd-max", type=float, default=None, help="largest relative SD of the outlet C_A")
    spec.add_argument("--mrt-min", type=float, default=None, help="shortest mean residence time [s]")
    spec.add_argument("--mrt-max", type=float, default=None, help="longest mean residence time [s]")
    feeder = parser.add_argument_group("the feeder noise the composition criteria are judged under")
    feeder.add_argument("--noise-sigma", type=float, default=0.0, help="relative SD of the feeder's rate")
    feeder.add_argument("--noise-tau", type=float, default=0.0, help="its correlation time [s] (0: white)")
    feeder.add_argument("--noise-band", type=float, default=0.5, help="its bandwidth [Hz] (default 0.5)")
    feeder.add_argument("--noise-feeder", choices=("A", "B"), default="A", help="the noisy feeder (default A)")
    space = parser.add_argument_group("the design space (refused outside the library's)")
    space.add_argument("--rpm-min", type=float, default=None, help="default: the library's lowest speed")
    space.add_argument("--rpm-max", type=float, default=None, help="default: the library's highest speed")
    space.add_argument("--length-min", type=float, default=None, help="smallest length factor (default 0.5)")
    space.add_argument("--length-max", type=float, default=None, help="largest length factor (default 2.0)")
    parser.add_argument(
        "--library", default=None, help="directory of DEM results files (default: the shipped validation campaign)"
    )
    parser.add_argument(
        "--rates",
        choices=("measured", "velocity", "phases"),
        default="measured",
        help="PBM transfer rates (default measured: the mode whose residence times follow the DEM across "
        "speeds; phases needs a library whose results carry the phase model)",
    )
    parser.add_argument("--out", default="results/design", help="where design.json and feasible.png go")


def run(args: argparse.Namespace) -> int:
    from coupling.forked import Prepared
    from workflows.report import DESIGN_FIGURES

    # forked first, so that matplotlib is imported on the other core while this process
    # imports and reads the library; it draws the figure at the end
    with Prepared(DESIGN_FIGURES) as figures:
        return _run(args, figures)


def _run(args: argparse.Namespace, figures) -> int:
    from pbm.design import design_spec
    from workflows.products.design import answer_lines, run_design, throughput_lines
    from workflows.shipped import VALIDATION_DIR

    given = {
        "ca_tolerance": args.ca_within,
        "coverage_sigmas": args.coverage,
        "rsd_max": args.rsd_max,
        "mrt_min_s": args.mrt_min,
        "mrt_max_s": args.mrt_max,
        "noise_sigma": args.noise_sigma,
        "noise_tau_s": args.noise_tau,
        "noise_band_hz": args.noise_band,
        "noise_feeder": args.noise_feeder,
        "rpm_min": args.rpm_min,
        "rpm_max": args.rpm_max,
        "length_factor_min": args.length_min,
        "length_factor_max": args.length_max,
    }
    spec = design_spec(**{k: v for k, v in given.items() if v is not None})
    result, throughput, out = run_design(
        spec, args.out, args.library or VALIDATION_DIR, args.rates, log=stderr_log, figures=figures
    )
    print("\n".join(answer_lines(result) + throughput_lines(throughput)))
    print(f"design.json and feasible.png: {out}")
    return 0 if result.best is not None else 1
