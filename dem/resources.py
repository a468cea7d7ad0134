"""What post-processing a DEM configuration costs, estimated before the dumps are read.

The streaming pass is flat in the number of snapshots, but three things grow with the
grid (S = NX x NY compartments, K velocity windows of the run):

* the transition counts between dumps, dense (S+1) x (S+1) per window (int64), kept for
  every window and copied once into the (K, S+1, S+1) array the rates are fitted to;
* the maximum-likelihood rate fit (:mod:`dem.rates`): one dense matrix exponential and its
  Frechet derivative of (S+1) x (S+1) per evaluation, a few hundred evaluations per window;
* the per-snapshot compartment counts (2 x S floats per dump) and the window sums
  (7 x S per window).

:func:`check_postprocess_resources` refuses, with the estimate, a grid whose arrays would
not fit in memory (``tables.nx = 100000``: 8 TB of transition counts) or whose rate fit
would not finish (``tables.nx = 200``: hours per window, whatever the number of dumps).
"""

from __future__ import annotations

import math
import os

from coupling.resources import format_bytes, require_memory, require_time
from dem.config import DemConfig

__all__ = ["MAX_RATE_FIT_S", "PostprocessCost", "check_postprocess_resources", "postprocess_cost"]

#: Wall time of one window's rate fit on the 10 x 10 grid (101 states) [s]: the DEM's own
#: windows (reduced preset, ~1.1e5 transitions, 300-500 evaluations) took 1.5-3 s on the
#: shared 2-core development machine (dem.rates); the upper value is used. One evaluation
#: is dense (S+1)^3 work, so the time scales as ((S+1) / 101)^3 (measured 0.14 -> 0.86 s
#: from 101 to 201 states: x6.1 against x7.9 cubic, so the scaling is conservative).
FIT_SECONDS_10X10 = 3.0
FIT_STATES_10X10 = 101
#: Longest rate fit accepted for one post-processing [s] (4 h; the 20 x 10 grid of the
#: paper's 52 windows is estimated at 21 min). ``PBMDEM_MAX_RATE_FIT_HOURS`` overrides it.
MAX_RATE_FIT_S = 4 * 3600.0


class PostprocessCost:
    """Estimated peak memory [bytes] and rate-fit time [s] of post-processing a run."""

    def __init__(self, n_states: int, n_windows: int, n_snapshots: int) -> None:
        self.n_states = int(n_states)  # S + 1 (compartments + discharged)
        self.n_windows = int(n_windows)
        self.n_snapshots = int(n_snapshots)
        dense = float(self.n_states) ** 2 * 8  # one (S+1)^2 int64 or float64 array
        s = self.n_states - 1
        # counts per window (dict) + their (K, S+1, S+1) copy + ~12 dense matrices of the fit
        # (generator, expm, Frechet pair, gradient, scratch) + a per-snapshot bincount
        self.transition_bytes = 2 * self.n_windows * dense
        self.fit_bytes = 12 * dense
        self.array_bytes = 8.0 * s * (7 * self.n_windows + 4 * self.n_snapshots)
        self.memory_bytes = self.transition_bytes + self.fit_bytes + self.array_bytes + dense
        self.fit_seconds = self.n_windows * FIT_SECONDS_10X10 * (self.n_states / FIT_STATES_10X10) ** 3


def postprocess_cost(config: DemConfig, n_snapshots: int | None = None) -> PostprocessCost:
    """The cost of post-processing the dumps of ``config``'s run: K = ceil(duration /
    window_s) windows, ``n_snapshots`` dumps (default duration / dump interval + 1)."""
    tables, operation = config.tables, config.operation
    n_windows = max(1, math.ceil(float(operation.duration_s) / float(tables.window_s) - 1e-9))
    if n_snapshots is None:
        n_snapshots = math.ceil(float(operation.duration_s) / float(config.numerics.dump_interval_s)) + 1
    return PostprocessCost(int(tables.nx) * int(tables.ny) + 1, n_windows, n_snapshots)


def _fit_limit_s() -> float:
    text = os.environ.get("PBMDEM_MAX_RATE_FIT_HOURS")
    try:
        return float(text) * 3600.0 if text else MAX_RATE_FIT_S
    except ValueError:
        return MAX_RATE_FIT_S


def check_postprocess_resources(
    config: DemConfig, n_snapshots: int | None = None, available_bytes: float | None = None
) -> PostprocessCost:
    """Refuse (ResourceLimitError, one line with the estimate) a grid whose post-processing
    would not fit in memory or whose measured-rate fit would not finish; else the estimate."""
    cost = postprocess_cost(config, n_snapshots)
    nx, ny = int(config.tables.nx), int(config.tables.ny)
    grid = f"tables.nx x tables.ny = {nx} x {ny} ({nx * ny} compartments) over {cost.n_windows} velocity windows"
    require_memory(
        cost.memory_bytes,
        f"post-processing with {grid}",
        f"the transition counts alone are {format_bytes(cost.transition_bytes)}; use a coarser grid",
        available=available_bytes,
    )
    require_time(
        cost.fit_seconds,
        _fit_limit_s(),
        f"the measured-rate fit of {grid}",
        f"{FIT_SECONDS_10X10:g} s per window at 10 x 10, x ((S+1)/101)^3 for S compartments; use a coarser "
        "grid (or raise PBMDEM_MAX_RATE_FIT_HOURS)",
    )
    return cost
