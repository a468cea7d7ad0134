"""JSON for results: numpy values and paths turned into plain Python.

Two uses, one conversion. Files people read (``summary.json``) carry ``null`` where a
value is undefined (:func:`json_ready`); the cache keeps NaN and infinity exactly
(:func:`dumps_exact`: Python's json writes and reads them back as ``NaN``/``Infinity``).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np


def to_builtin(value: Any) -> Any:
    """A copy made of dicts, lists, str, int, float, bool and None (floats may be NaN/inf).
    Unknown objects become their ``str``."""
    if isinstance(value, dict):
        return {str(k): to_builtin(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [to_builtin(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, (str, int, float, bool)) or value is None:
        return value
    return str(value)  # paths and anything else


def json_ready(value: Any) -> Any:
    """:func:`to_builtin`, with NaN and infinities as None (JSON has neither)."""
    value = to_builtin(value)

    def clean(v: Any) -> Any:
        if isinstance(v, dict):
            return {k: clean(x) for k, x in v.items()}
        if isinstance(v, list):
            return [clean(x) for x in v]
        if isinstance(v, float) and not math.isfinite(v):
            return None
        return v

    return clean(value)


def dumps_exact(value: Any) -> str:
    """JSON text that :func:`json.loads` turns back into the same values, NaN included."""
    return json.dumps(to_builtin(value), sort_keys=True)


def write_json(path: str | Path, value: Any) -> Path:
    """The one JSON writer for files people read (``summary.json``, study and benchmark
    records): :func:`json_ready` values, sorted keys, the folder created, written whole or
    not at all (:func:`coupling.files.replace_file`); returns the path."""
    from coupling.files import replace_file

    path = Path(path)
    replace_file(path, json.dumps(json_ready(value), indent=2, sort_keys=True, allow_nan=False) + "\n", "JSON file")
    return path
