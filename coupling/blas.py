"""Run BLAS single-threaded inside hot loops of small matrices (the PBM, the rate fits),
and size the project's own thread pools to the cores that are free.

Why: the PBM multiplies ~100 x 100 matrices a few thousand times. Threading cannot speed
up products that small, but OpenBLAS's spinning worker threads can slow them down by two
orders of magnitude when the cores are busy -- measured here: a 260 s run took 8.7 s
instead of 0.06 s while LIGGGHTS occupied both cores, which is exactly the pipeline's
situation. This module finds the OpenBLAS libraries already loaded in the process (numpy's
and scipy's wheels bundle their own) and sets their thread count through their C API,
restoring it afterwards -- what threadpoolctl does, without the dependency. Where no
OpenBLAS is found (another BLAS, another OS) it does nothing.

The parallelism the PBM does use is over independent work it schedules itself (the
windows' exponentials, the columns of a march, blocks of ensemble members), on as many
threads as :func:`free_cores` finds idle: a thread more than the free cores only takes
time from LIGGGHTS or from its siblings. Results never depend on the thread count.
"""

from __future__ import annotations

import ctypes
import os
from contextlib import contextmanager
from functools import lru_cache

_PREFIXES = ("openblas", "scipy_openblas", "scipy_openblas64_")
_SUFFIXES = ("", "64_", "_64_")


@lru_cache(maxsize=1)
def _openblas_controls() -> tuple[tuple, ...]:
    controls = []
    try:
        with open("/proc/self/maps") as maps:
            paths = {line.split()[-1] for line in maps if "openblas" in line.lower() and ".so" in line}
    except OSError:
        return ()
    for path in sorted(paths):
        if not path.startswith("/"):
            continue
        try:
            # Already mapped: dlopen returns the loaded library, it loads nothing new.
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for prefix in _PREFIXES:
            for suffix in _SUFFIXES:
                setter = getattr(lib, f"{prefix}_set_num_threads{suffix}", None)
                getter = getattr(lib, f"{prefix}_get_num_threads{suffix}", None)
                if setter is not None and getter is not None:
                    getter.restype = ctypes.c_int
                    controls.append((setter, getter))
                    break
            else:
                continue
            break
    return tuple(controls)


@contextmanager
def single_threaded_blas():
    """Context manager: OpenBLAS uses one thread inside, its previous count after."""
    controls = _openblas_controls()
    previous = [getter() for _setter, getter in controls]
    for setter, _getter in controls:
        setter(1)
    try:
        yield
    finally:
        for (setter, _getter), count in zip(controls, previous):
            setter(count)


def free_cores(limit: int | None = None) -> int:
    """The cores no other task is running on now, between 1 and ``limit``.

    The CPUs this process may run on, minus the runnable tasks other than the calling
    thread (the fourth field of /proc/loadavg, "running/total", counts it too): unlike the
    load averages it is current, so a LIGGGHTS run started a second ago counts. Where
    /proc/loadavg does not exist, every CPU counts as free.
    """
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cpus = os.cpu_count() or 1
    try:
        with open("/proc/loadavg") as handle:
            running = int(handle.read().split()[3].split("/")[0])
    except (OSError, IndexError, ValueError):
        running = 1
    free = max(1, cpus - max(0, running - 1))
    return free if limit is None else max(1, min(free, limit))
