"""The thread sizing: free_cores sees the tasks that run now."""

import multiprocessing
import os
import time

from coupling.blas import free_cores


def _spin(stop):
    while not stop.is_set():
        pass


def test_free_cores_is_one_when_every_core_is_busy():
    cpus = len(os.sched_getaffinity(0))
    assert 1 <= free_cores() <= cpus
    assert free_cores(limit=1) == 1
    stop = multiprocessing.Event()
    spinners = [multiprocessing.Process(target=_spin, args=(stop,), daemon=True) for _ in range(cpus)]
    for p in spinners:
        p.start()
    try:
        time.sleep(0.5)
        assert free_cores() == 1
    finally:
        stop.set()
        for p in spinners:
            p.join(5)
