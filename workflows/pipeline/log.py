"""How the pipeline reports progress: a :data:`Log` is any callable taking one line. The
command line's is :func:`stderr_log`; library calls default to silence. A module of its own
so that a command can name its log without importing the pipeline's stages."""

from __future__ import annotations

import sys
from collections.abc import Callable

Log = Callable[[str], None]


def quiet(message: str) -> None:
    """The log that says nothing."""


def stderr_log(message: str) -> None:
    """The command line's log: one line per message on stderr."""
    print(f"pbmdem: {message}", file=sys.stderr, flush=True)
