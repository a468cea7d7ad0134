"""``pbmdem predict [--config C.toml] [--set PATH=VALUE ...] [--library FILE] [--out DIR]
[--extrapolate]``: an operating point predicted from a DEM library's law, without a DEM run,
every quantity with its 95 % prediction interval (:mod:`workflows.products.predict`). Without
``--config`` the point is the validation preset, the shipped library's baseline, so a point
one setting away from it is ``--set dem.operation.impeller_rpm=225``."""

from __future__ import annotations

import argparse
import math

HELP = "predict an operating point from the DEM library's law, no DEM run, with 95 percent prediction intervals"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--config",
        default=None,
        help="the configuration (TOML) of the point to predict (default: the validation preset, the shipped library's "
        "baseline)",
    )
    parser.add_argument(
        "--set",
        dest="settings",
        action="append",
        default=[],
        metavar="PATH=VALUE",
        help="change one setting of the configuration, e.g. dem.operation.impeller_rpm=225 (repeatable)",
    )
    parser.add_argument(
        "--library",
        default=None,
        help="a library model (library.json, or its folder) made by `pbmdem library fit` (default: the shipped one)",
    )
    parser.add_argument("--out", default="results/predict", help="output folder (default: %(default)s)")
    parser.add_argument(
        "--extrapolate",
        action="store_true",
        help="predict a point outside the library's domain: labelled, its intervals widened",
    )
    parser.add_argument("--no-figures", action="store_true", help="skip the figure and the HTML page")


def run(args: argparse.Namespace) -> int:
    if args.no_figures:
        return _run(args, None)
    from coupling.forked import Prepared
    from workflows.report import PREDICTION_FIGURES

    # forked first, so that matplotlib is imported on the other core while this process
    # imports and predicts; it draws the figure while this one writes the rest
    with Prepared(PREDICTION_FIGURES) as drawer:
        return _run(args, drawer)


def _run(args: argparse.Namespace, drawer) -> int:
    from workflows.config import preset_path
    from workflows.products.predict import run_predict

    config = args.config if args.config is not None else preset_path("validation")
    output = run_predict(
        config, args.library, args.out, args.extrapolate, not args.no_figures, drawer, settings=args.settings
    )
    prediction = output.prediction
    if prediction.extrapolated:
        print(f"EXTRAPOLATED: {'; '.join(prediction.outside)}")
    if prediction.new_layout:
        print("a blade layout no library run has: each interval at least the library's error at such a layout")
    print(f"{'quantity':32s} {'predicted':>11s}  95 % prediction interval")
    for q in prediction.quantities:
        interval = "-" if not math.isfinite(q.low) else f"[{q.low:.4g}, {q.high:.4g}]"
        print(f"{q.key:32s} {q.value:11.4g}  {interval}")
    d = output.dynamics
    print(f"{'VRR, feeder A white noise':32s} {d.vrr.value:11.4g}  [{d.vrr.low:.4g}, {d.vrr.high:.4g}]")
    delay = d.mean_delay_s
    print(f"{'step A x2: mean delay [s]':32s} {delay.value:11.4g}  [{delay.low:.4g}, {delay.high:.4g}]")
    for what, path in output.files.items():
        print(f"wrote {what}: {path}")
    print(f"({output.wall_time_s:.2f} s)")
    return 0
