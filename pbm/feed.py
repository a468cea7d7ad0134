"""The PBM's feed from the table's operating point (:class:`coupling.operating.OperatingPoint`).

A :class:`pbm.config.PbmConfig` whose feed rates or feed weights are None takes them from
the velocity table: each feeder's rate as the DEM ran it, and its zone mapped onto the
table's compartments by overlap in x and y (:func:`coupling.compartments.feed_zone_weights`).
A rate the user gives that differs from the table's is used, and named
(:class:`FeedOverride`): a PBM fed at another rate than the DEM it was measured from
describes another process, which may be the point (a prediction at a new feed), but never
silently.

A table that records no operating point (a synthetic table, a file written before tables
recorded it and read without its configuration) leaves a None rate at the paper's
:data:`PAPER_FEED_RATE_PER_S` and None weights at the first slice's halves
(:func:`pbm.model.default_feed_weights`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from coupling.compartments import feed_zone_weights
from coupling.operating import OperatingPoint
from coupling.tables import VelocityTable
from pbm.config import PbmConfig

#: Each feeder's rate of the paper (1990 particles/s in all) [particles/s]: a None rate on a
#: table without an operating point.
PAPER_FEED_RATE_PER_S = 995.0
FEED_RATE_FIELDS = {"A": "feed_rate_a_per_s", "B": "feed_rate_b_per_s"}
FEED_WEIGHT_FIELDS = {"A": "feed_weights_a", "B": "feed_weights_b"}


@dataclass(frozen=True)
class FeedOverride:
    """A feed rate the configuration gives that differs from the table's operating point."""

    field: str
    value_per_s: float
    table_per_s: float

    @property
    def message(self) -> str:
        return f"{self.field} = {self.value_per_s:g} overrides the table's {self.table_per_s:g} /s"


def feed_at(point: OperatingPoint, x_edges: np.ndarray, y_edges: np.ndarray) -> dict[str, Any]:
    """The PbmConfig feed fields of ``point`` on a grid of compartment edges [m]: both
    rates [particles/s] and both feeders' weights (their zones' overlap shares)."""
    out: dict[str, Any] = {}
    for feeder, zone in point.feed_zones.items():
        out[FEED_RATE_FIELDS[feeder]] = point.feed_rate_per_s(feeder)
        out[FEED_WEIGHT_FIELDS[feeder]] = feed_zone_weights(x_edges, y_edges, zone.x_range_m, zone.y_range_m)
    return out


def feed_overrides(config: PbmConfig, point: OperatingPoint) -> tuple[FeedOverride, ...]:
    """The rates ``config`` gives that differ from ``point``'s (relative 1e-9: the same
    number written twice, e.g. 127.36 / 2 and 63.68, is no override)."""
    out = []
    for feeder, name in FEED_RATE_FIELDS.items():
        given, measured = getattr(config, name), point.feed_rate_per_s(feeder)
        if given is not None and not math.isclose(given, measured, rel_tol=1e-9, abs_tol=0.0):
            out.append(FeedOverride(name, float(given), measured))
    return tuple(out)


def resolve_feed(config: PbmConfig | None, table: VelocityTable) -> tuple[PbmConfig, tuple[FeedOverride, ...]]:
    """``config`` (default :class:`PbmConfig`) with every None feed field taken from the
    table's operating point (module docstring), and the given rates that contradict it."""
    config = config or PbmConfig()
    point = table.operating_point
    if point is None:
        missing = {name: PAPER_FEED_RATE_PER_S for name in FEED_RATE_FIELDS.values() if getattr(config, name) is None}
        return (config.model_copy(update=missing) if missing else config), ()
    derived = feed_at(point, table.x_edges, table.y_edges)
    updates = {name: value for name, value in derived.items() if getattr(config, name) is None}
    return (config.model_copy(update=updates) if updates else config), feed_overrides(config, point)
