"""``pbmdem design``: the shortest blender and the largest feed that meet a spec with a
given probability, from the DEM library's law (:mod:`workflows.products.design`). Exit code
0 with an answer; 1 when no point searched meets the spec (the files still written, the most
likely point named); 2 for a bad spec or input, as every command."""

from __future__ import annotations

import argparse

HELP = "the shortest blender and the largest feed that meet a spec, from the DEM library's law, with probabilities"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    spec = parser.add_argument_group(
        "the spec (at least one of --ca-within, --rsd-max, --mrt-min, --mrt-max, --holdup-min, --holdup-max)"
    )
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
    spec.add_argument("--holdup-min", type=float, default=None, help="least hold-up [particles]")
    spec.add_argument("--holdup-max", type=float, default=None, help="largest hold-up [particles]")
    spec.add_argument(
        "--confidence", type=float, default=0.95, help="least P(spec met) of an answer (default %(default)s)"
    )
    feeder = parser.add_argument_group("the feeder noise the composition criteria are judged under")
    feeder.add_argument("--noise-sigma", type=float, default=0.0, help="relative SD of the feeder's rate")
    feeder.add_argument("--noise-tau", type=float, default=0.0, help="its correlation time [s] (0: white)")
    feeder.add_argument("--noise-band", type=float, default=0.5, help="its bandwidth [Hz] (default 0.5)")
    feeder.add_argument("--noise-feeder", choices=("A", "B"), default="A", help="the noisy feeder (default A)")
    space = parser.add_argument_group("the space searched (default: the library's domain; refused outside it)")
    space.add_argument("--rpm-min", type=float, default=None)
    space.add_argument("--rpm-max", type=float, default=None)
    space.add_argument("--length-min", type=float, default=None, help="shortest blender [m]")
    space.add_argument("--length-max", type=float, default=None, help="longest blender [m]")
    space.add_argument("--feed-min", type=float, default=None, help="lowest total feed [particles/s]")
    space.add_argument("--feed-max", type=float, default=None, help="highest total feed [particles/s]")
    parser.add_argument(
        "--library",
        default=None,
        help="a library model (library.json, or its folder) made by `pbmdem library fit` (default: the shipped one)",
    )
    parser.add_argument(
        "--extrapolate",
        action="store_true",
        help="search beyond the library's domain: labelled, the intervals widened",
    )
    parser.add_argument("--out", default="results/design", help="where design.json, feasible.png, report.html go")


def run(args: argparse.Namespace) -> int:
    from coupling.forked import Prepared
    from workflows.report import DESIGN_FIGURES

    # forked first, so that matplotlib is imported on the other core while this process
    # imports and searches; it draws the figure at the end
    with Prepared(DESIGN_FIGURES) as figures:
        return _run(args, figures)


#: each field of the design spec and the argument that gives it
FIELDS = {
    "ca_tolerance": "ca_within",
    "coverage_sigmas": "coverage",
    "rsd_max": "rsd_max",
    "mrt_min_s": "mrt_min",
    "mrt_max_s": "mrt_max",
    "holdup_min": "holdup_min",
    "holdup_max": "holdup_max",
    "confidence": "confidence",
    "noise_sigma": "noise_sigma",
    "noise_tau_s": "noise_tau",
    "noise_band_hz": "noise_band",
    "noise_feeder": "noise_feeder",
    "rpm_min": "rpm_min",
    "rpm_max": "rpm_max",
    "length_min_m": "length_min",
    "length_max_m": "length_max",
    "feed_min_per_s": "feed_min",
    "feed_max_per_s": "feed_max",
}
#: the spec's fields as a user gave them (a refusal names the flag, not the field)
FLAGS = {name: "--" + dest.replace("_", "-") for name, dest in FIELDS.items()}


def _run(args: argparse.Namespace, figures) -> int:
    from workflows.prediction.design import design_spec
    from workflows.products.design import answer_lines, run_design

    given = {name: getattr(args, dest) for name, dest in FIELDS.items()}
    spec = design_spec(FLAGS, **{k: v for k, v in given.items() if v is not None})
    output = run_design(spec, args.out, args.library, args.extrapolate, figures=figures)
    print("\n".join(answer_lines(output.result)))
    # no wall time: the output is compared between commits (`pbmdem bench same-numbers`)
    print(f"design.json, feasible.png, report.html: {output.files['design'].parent}")
    return 0 if output.result.shortest is not None else 1
