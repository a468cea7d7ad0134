"""Research on DEM runs (``pbmdem study ...``): why the transport model is what it is.
They import the product; the product never imports them."""

import argparse
from collections.abc import Iterable
from pathlib import Path

from coupling.errors import ConfigError
from coupling.files import distinct_inputs
from workflows.shipped import LIBRARY_MODEL, REDUCED_RUN, VALIDATION_DIR

#: the baseline's blender length [m]: the blade layout most of a library's runs share
BASELINE_LENGTH_M = 0.33


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


def add_library_arguments(parser: argparse.ArgumentParser, out: Path) -> None:
    """``--library`` (a library model, by default the shipped one) and ``--out``, for a
    study of a library's law."""
    parser.add_argument("--library", default=str(LIBRARY_MODEL), help="a library model (default: the shipped one)")
    parser.add_argument("--out", default=str(out), help=f"output folder (default: {out})")


def write_page(out: str | Path, stem: str, text: str, record: dict) -> None:
    """Print a study's page ``text`` and write it, with its ``record``, as ``stem``.md and
    ``stem``.json in the folder ``out`` (``--out``)."""
    from coupling.files import writable_directory
    from coupling.jsonable import write_json

    print(text)
    folder = writable_directory(out, "--out")
    (folder / f"{stem}.md").write_text(text)
    written = write_json(folder / f"{stem}.json", record)
    print(f"wrote {folder / f'{stem}.md'} and {written}")


def calibrated_library(path: str | Path):
    """The library model at ``path``, refused (ConfigError naming it) without the
    calibration every study of its law reads."""
    from workflows.prediction.library import load_model

    model = load_model(path)
    if model.calibration is None:
        raise ConfigError(f"{path}: the library model has no calibration; make it with `pbmdem library fit`")
    return model


def distinct_runs(paths: Iterable[str | Path], what: str = "--results") -> list[Path]:
    """The results files of a study over runs, refused (ConfigError naming both) when one
    run is given twice, as a path, a link or a copy: it would be counted twice and pooled
    intervals would come out narrower than the runs give (:func:`coupling.files.distinct_inputs`)."""
    return distinct_inputs(paths, what, ConfigError)
