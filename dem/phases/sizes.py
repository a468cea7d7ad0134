"""Size classes and their dead zones: particles keep their size and the sizes move at
different speeds, so where the records carry the diameters each size class gets a chain of
its own (:func:`dem.phases.table_with_phases`): the classes (:func:`size_classes`, merged
until each is large enough: :func:`kinds_by_size`), the Little's-law residence time that
bounds a class's dead zone (:func:`little_residence_time`) and the hold of the zone to it
(:func:`zone_held_to_little`).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy.optimize import brentq

from coupling.phases import PhaseTransport
from dem.phases.chain import mean_residence_time
from dem.phases.data import PhaseData, first_compartments, first_seen_in
from dem.tracking import CompartmentSequences

#: Particles keep their size, and sizes move at different speeds: on a fresh validation
#: run at 300 rpm and feed x1.25 (sizes 5.48 / 6.00 / 6.52 mm) the pooled mean residence
#: times were 19.9, 15.9 and 12.4 s and 1.15 %, 0.19 % and 0 % stayed beyond the horizon
#: (``pbmdem study sizes``). A chain for every size learns that as a phase particles can
#: leave, and its pooled mean came out 1.8 % high (16.31 s against 16.02 [15.78, 16.26]);
#: a chain per size class, fed in the classes' shares, gave 16.25 s, 143.7 s^2, the
#: hold-up and the RTD overlap, all inside. So where the records carry the diameters, each size class with at
#: least this many particles entering in the fit window gets its own chain
#: (:func:`table_with_phases`); a smaller class joins its neighbour in size.
MIN_KIND_PARTICLES = 300
#: ... and at least this share of them: a class of 1 % (the tails of the reduced preset's
#: five classes) adds as many states to every solve as the middle one for 1 % of the
#: particles; joined to its neighbour, the reduced comparison runs on 9 phases, not 15.
MIN_KIND_SHARE = 0.05
#: more distinct diameters than this are grouped into QUANTILE_CLASSES classes of equal counts
MAX_CLASSES = 8
QUANTILE_CLASSES = 5
#: diameters closer than this are one class [m] (the dumps print radii to ~6 digits)
SAME_DIAMETER_M = 1e-7


def size_classes(diameters: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(class of each particle, -1 where the diameter is unknown; mean diameter of each
    class [m], ascending). Distinct diameters are the classes; more than
    :data:`MAX_CLASSES` of them (a continuous distribution) are grouped into
    :data:`QUANTILE_CLASSES` classes of about equal counts. Raises ValueError when no
    diameter is known."""
    d = np.asarray(diameters, dtype=float)
    known = np.isfinite(d) & (d > 0)
    if not known.any():
        raise ValueError("no particle has a known diameter")
    labels = np.full(d.size, -1, np.int64)
    distinct = np.unique(np.round(d[known] / SAME_DIAMETER_M))
    if distinct.size <= MAX_CLASSES:
        labels[known] = np.searchsorted(distinct, np.round(d[known] / SAME_DIAMETER_M))
    else:
        edges = np.quantile(d[known], np.linspace(0, 1, QUANTILE_CLASSES + 1)[1:-1])
        labels[known] = np.searchsorted(edges, d[known], side="right")
    n = int(labels.max()) + 1
    centres = np.array([d[labels == c].mean() if np.any(labels == c) else math.nan for c in range(n)])
    return labels, centres


def little_residence_time(sequences: CompartmentSequences, window: tuple[float, float]) -> float:
    """Little's law over ``window`` = (t0, t1] [s]: the particle-seconds spent inside over
    its dumps (each dump standing for one dump interval) per particle first seen in it [s].
    Raises ValueError when no particle entered in the window."""
    t = sequences.snapshot_t
    tol = 1e-6 * sequences.interval_s
    dumps = np.flatnonzero((t > window[0] + tol) & (t <= window[1] + tol))
    entering = int(first_seen_in(sequences, window).sum())
    if not dumps.size or not entering:
        raise ValueError(f"no particle entered in {window} s: Little's law needs an inflow")
    inside_until = sequences.start + sequences.lengths - sequences.discharged  # one past the last dump inside
    change = np.zeros(t.size + 1)
    np.add.at(change, sequences.start, 1.0)
    np.add.at(change, inside_until, -1.0)
    count = np.cumsum(change)[:-1]
    return float(count[dumps].sum() * sequences.interval_s / entering)


def zone_held_to_little(model: PhaseTransport, data: PhaseData, residence_s: float) -> PhaseTransport:
    """``model`` (its phase 0 a dead zone, :attr:`dem.phases.PhaseSettings.stagnant_exit_max_per_s`) with the
    rates into the zone scaled by the one factor that makes its mean residence time from
    where ``data``'s particles entered (:func:`first_compartments`) ``residence_s`` (the
    sequences' :func:`little_residence_time`), or leaves it as fitted where even that is
    short of it: the zone only shrinks (its size is what the likelihood saw at most; in a
    class that hardly parks, the largest, a grown zone would be a tail the DEM lacks), and
    there is none when the moving phases alone stay longer. The likelihood sizes the zone
    by the exchange it sees inside the window and leaves the hold-up free: with the zone
    left at most once per 2 residence times, the reduced run's steady hold-up came out 2265
    against the DEM's 2250 [2238, 2263], and 2248 once held (:data:`dem.phases.ZONE_RESIDENCES`). The
    factor is kept in the model's attributes (``zone_entry_scale``)."""
    entering = first_compartments(data)

    def with_scale(c: float) -> PhaseTransport:
        switching = model.switching.copy()
        switching[1:, 0] *= c
        return dataclasses.replace(model, switching=switching)

    def excess(c: float) -> float:
        return mean_residence_time(with_scale(c), entering) - residence_s

    if excess(1.0) <= 0:
        scale = 1.0
    elif excess(0.0) >= 0:
        scale = 0.0
    else:
        scale = float(brentq(excess, 0.0, 1.0, xtol=1e-6))
    held = with_scale(scale)
    return dataclasses.replace(held, attrs={**held.attrs, "zone_entry_scale": scale})


def kinds_by_size(
    sequences: CompartmentSequences,
    diameters: np.ndarray,
    window: tuple[float, float],
    minimum: int = MIN_KIND_PARTICLES,
    min_share: float = MIN_KIND_SHARE,
) -> list[np.ndarray]:
    """The sequences' rows of each size class (:func:`size_classes` of ``diameters``, one
    per sequence, NaN unknown), a class with fewer than ``minimum`` particles first seen in
    ``window`` = (t0, t1], or less than ``min_share`` of them, merged into its neighbour in
    size (the smaller of the two) until none is; smallest size first. Particles of unknown
    size are in none."""
    labels, _centres = size_classes(diameters)
    entering = first_seen_in(sequences, window)
    groups = [np.flatnonzero(labels == c) for c in range(int(labels.max()) + 1)]
    groups = [g for g in groups if g.size]
    count = lambda g: int(entering[g].sum())  # noqa: E731
    least = max(minimum, min_share * sum(count(g) for g in groups))
    while len(groups) > 1 and min(count(g) for g in groups) < least:
        small = min(range(len(groups)), key=lambda c: count(groups[c]))
        neighbours = [c for c in (small - 1, small + 1) if 0 <= c < len(groups)]
        other = min(neighbours, key=lambda c: count(groups[c]))
        a, b = sorted((small, other))
        groups[a : b + 1] = [np.sort(np.concatenate([groups[a], groups[b]]))]
    return groups
