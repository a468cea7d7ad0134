"""Memory and time up front: refuse a problem the machine cannot hold before starting it.

An input that scales a dense array (a grid of 1e5 compartments, 1e8 ensemble members)
would otherwise end in a memory traceback, or with the kernel killing the process
without a word, after minutes of work. The stage that knows its arrays estimates their
size (:mod:`dem.resources`, :mod:`pbm.resources`); :func:`require_memory` compares the
estimate with what this machine has and raises
:class:`~coupling.errors.ResourceLimitError` with the estimate, the limit and the fix.
"""

from __future__ import annotations

import os
from pathlib import Path

from coupling.errors import ResourceLimitError

__all__ = ["MEMORY_FRACTION", "available_memory_bytes", "format_bytes", "require_memory", "require_time"]

#: Share of the available memory one estimate may claim: the estimates count the big arrays,
#: not the interpreter, the libraries or the temporaries of a vector operation.
MEMORY_FRACTION = 0.8


def format_bytes(n: float) -> str:
    """``n`` bytes in the largest binary unit that keeps it >= 1 (e.g. '22.0 GiB')."""
    value = float(n)
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if abs(value) < 1024 or unit == "PiB":
            return f"{value:.1f} {unit}" if unit != "B" else f"{value:.0f} B"
        value /= 1024
    return f"{value:.1f} PiB"


def _cgroup_limit() -> float | None:
    """Memory left under this process's cgroup (v2 memory.max - memory.current), if limited."""
    try:
        text = Path("/proc/self/cgroup").read_text()
    except OSError:
        return None
    for line in text.splitlines():
        parts = line.split(":", 2)
        if len(parts) == 3 and parts[0] == "0":
            base = Path("/sys/fs/cgroup") / parts[2].lstrip("/")
            try:
                limit = (base / "memory.max").read_text().strip()
                current = float((base / "memory.current").read_text().strip())
            except (OSError, ValueError):
                return None
            if limit == "max":
                return None
            try:
                return max(0.0, float(limit) - current)
            except ValueError:
                return None
    return None


def available_memory_bytes() -> float:
    """Memory this process can still use [bytes]: the kernel's MemAvailable, or less when a
    cgroup limits the process. ``PBMDEM_MEMORY_BYTES`` overrides it (tests, batch jobs
    that know their share)."""
    override = os.environ.get("PBMDEM_MEMORY_BYTES")
    if override:
        try:
            return float(override)
        except ValueError:
            pass
    available = None
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                available = float(line.split()[1]) * 1024
                break
    except (OSError, ValueError, IndexError):
        available = None
    if available is None:
        try:
            available = float(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
        except (ValueError, OSError, AttributeError):
            available = float("inf")
    limit = _cgroup_limit()
    return min(available, limit) if limit is not None else available


def require_memory(estimate_bytes: float, what: str, fix: str, available: float | None = None) -> None:
    """Raise ResourceLimitError when ``estimate_bytes`` exceeds :data:`MEMORY_FRACTION` of the
    available memory: one line naming ``what`` needs it, the estimate, what is available
    and ``fix`` (what the user can change)."""
    available = available_memory_bytes() if available is None else float(available)
    if not estimate_bytes <= MEMORY_FRACTION * available:
        raise ResourceLimitError(
            f"{what} needs about {format_bytes(estimate_bytes)} of memory; this machine has "
            f"{format_bytes(available)} available (at most {MEMORY_FRACTION:.0%} of it is used): {fix}"
        )


def require_time(estimate_s: float, limit_s: float, what: str, fix: str) -> None:
    """Raise ResourceLimitError when ``estimate_s`` exceeds ``limit_s``: one line with both."""
    if not estimate_s <= limit_s:
        raise ResourceLimitError(f"{what} would take about {_duration(estimate_s)} (limit {_duration(limit_s)}): {fix}")


def _duration(seconds: float) -> str:
    if seconds != seconds or seconds == float("inf"):
        return "forever"
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.0f} min"
    if seconds < 3 * 86400:
        return f"{seconds / 3600:.1f} h"
    return f"{seconds / 86400:.3g} days"
