"""A library of three shipped runs fitted with few EM iterations: the files, refusals and
round trips of ``pbmdem library`` and ``predict``, not the law's accuracy."""

from pathlib import Path

from workflows.cli.main import main
from workflows.shipped import VALIDATION_DIR

#: 150, 350 and 250 rpm at the baseline's length and feed
SPEEDS = [VALIDATION_DIR / f"dem-{h}.h5" for h in ("57ed37b232c5816c", "5c3093abd07ae686", "aa093a229dfd2ce4")]


def fit_small_library(out: Path) -> Path:
    args = ["library", "fit", "--results", *map(str, SPEEDS), "--out", str(out)]
    assert main([*args, "--iterations", "3", "--left-out-iterations", "2"]) == 0
    return out
