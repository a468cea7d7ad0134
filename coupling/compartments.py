"""The compartment grid both sides share: its edges, where a particle belongs, and which
compartments a feed zone feeds.

Frame: x axial, 0 at the inlet wall and L at the weir; y across the diameter, centred on
the impeller axis; z up. Compartment (i, j) has i = 0..NX-1 from the inlet and
j = 0..NY-1 from y = -D/2; each spans the full height of the vessel.
"""

from __future__ import annotations

import numpy as np

from coupling.errors import ConfigError


def grid_edges(length_m: float, diameter_m: float, nx: int, ny: int) -> tuple[np.ndarray, np.ndarray]:
    """Uniform ``(x_edges, y_edges)`` [m] over x in [0, L] and y in [-D/2, D/2]."""
    return np.linspace(0.0, length_m, nx + 1), np.linspace(-diameter_m / 2, diameter_m / 2, ny + 1)


def bin_particles(x, y, length_m: float, diameter_m: float, nx: int, ny: int) -> tuple[np.ndarray, np.ndarray]:
    """``(inside, cell)`` for particle centres at ``x``, ``y`` [m] on the uniform grid of
    :func:`grid_edges`.

    ``inside``: bool mask of the particles with 0 <= x <= L (in the blender; x = L belongs
    to the last slice). ``cell``: the flat compartment index i * NY + j of each particle
    inside. y is clipped into the outer compartments: the barrel is round, so only rounding
    puts a centre beyond +-D/2.
    """
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    inside = (x >= 0) & (x <= length_m)
    i = np.minimum((x[inside] / (length_m / nx)).astype(np.int64), nx - 1)
    j = np.clip(np.floor((y[inside] + diameter_m / 2) / (diameter_m / ny)).astype(np.int64), 0, ny - 1)
    return inside, i * ny + j


def _overlap_shares(edges: np.ndarray, zone_min_m: float, zone_max_m: float, axis: str) -> np.ndarray:
    """Each compartment's overlap with [zone_min, zone_max] along one axis, normalised."""
    overlap = np.clip(np.minimum(edges[1:], zone_max_m) - np.maximum(edges[:-1], zone_min_m), 0.0, None)
    if overlap.sum() <= 0:
        raise ConfigError(
            f"feed zone {axis} in [{zone_min_m}, {zone_max_m}] m lies outside the compartments "
            f"[{edges[0]}, {edges[-1]}] m"
        )
    return overlap / overlap.sum()


def inlet_weights(y_edges: np.ndarray, zone_y_min_m: float, zone_y_max_m: float) -> list[float]:
    """Shares of a feed zone's particles landing in each y compartment of the first slice:
    the overlap of each compartment with the zone's y range [y_min, y_max], normalised.

    The DEM feeder inserts particles uniformly over its zone and they fall nearly straight
    down onto the bed, so the overlap in y is what each inlet compartment receives.
    """
    return [float(w) for w in _overlap_shares(y_edges, zone_y_min_m, zone_y_max_m, "y")]


def feed_zone_weights(
    x_edges: np.ndarray, y_edges: np.ndarray, zone_x_m: tuple[float, float], zone_y_m: tuple[float, float]
) -> list[float]:
    """Shares of a feed zone's particles landing in each compartment: the overlap of each
    compartment with the zone's rectangle in x and y, normalised. NY weights of the first
    slice when the zone lies inside it, else NX * NY (flat index i * NY + j).

    The particles fall nearly straight down from where they are inserted, so a zone wider
    than the first slice feeds the next one too: at 20 slices of the reduced blender most
    particles are first seen in the second slice, and feeding them all into the first adds
    half a slice to every path.
    """
    y_share = _overlap_shares(y_edges, *zone_y_m, "y")
    x_share = _overlap_shares(x_edges, *zone_x_m, "x")
    if np.count_nonzero(x_share) == 1 and x_share[0] > 0:
        return [float(w) for w in y_share]
    return [float(w) for w in np.outer(x_share, y_share).ravel()]
