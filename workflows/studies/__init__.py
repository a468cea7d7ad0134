"""Research on DEM runs (``pbmdem study ...``): why the transport model is what it is.
They import the product; the product never imports them."""

import argparse

from workflows.shipped import REDUCED_RUN, VALIDATION_DIR


def add_runs_arguments(parser: argparse.ArgumentParser, needs: str, out: str) -> None:
    """``--results`` (many results files; by default the shipped reduced run and the
    validation campaign) and ``--out``, for a study run over runs; ``needs`` says what each
    file must carry."""
    parser.add_argument(
        "--results",
        nargs="+",
        default=[str(REDUCED_RUN), *sorted(str(p) for p in VALIDATION_DIR.glob("dem-*.h5"))],
        metavar="FILE",
        help=f"DEM results files with {needs} (default: the shipped reduced run and the validation campaign)",
    )
    parser.add_argument("--out", default=out, help="output folder (default: %(default)s)")
