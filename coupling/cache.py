"""Keys for runs and caches: a hash of the inputs names the directory or file (signac's
recipe), so a changed input can never be served a stale result."""

from __future__ import annotations

import hashlib
import json
from typing import Any


def stable_hash(data: Any, length: int = 16) -> str:
    """Hash of JSON-serialisable data, independent of dict key order."""
    text = json.dumps(data, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:length]
