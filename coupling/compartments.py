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


def inlet_weights(y_edges: np.ndarray, zone_y_min_m: float, zone_y_max_m: float) -> list[float]:
    """Shares of a feed zone's particles landing in each y compartment of the first slice:
    the overlap of each compartment with the zone's y range [y_min, y_max], normalised.

    The DEM feeder inserts particles uniformly over its zone and they fall nearly straight
    down onto the bed, so the overlap in y is what each inlet compartment receives.
    """
    lo = np.maximum(y_edges[:-1], zone_y_min_m)
    hi = np.minimum(y_edges[1:], zone_y_max_m)
    overlap = np.clip(hi - lo, 0.0, None)
    if overlap.sum() <= 0:
        raise ConfigError(
            f"feed zone y in [{zone_y_min_m}, {zone_y_max_m}] m lies outside the compartments "
            f"[{y_edges[0]}, {y_edges[-1]}] m"
        )
    return [float(w) for w in overlap / overlap.sum()]


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
    y_share = np.asarray(inlet_weights(y_edges, *zone_y_m))
    lo = np.maximum(x_edges[:-1], zone_x_m[0])
    hi = np.minimum(x_edges[1:], zone_x_m[1])
    x_overlap = np.clip(hi - lo, 0.0, None)
    if x_overlap.sum() <= 0:
        raise ConfigError(
            f"feed zone x in [{zone_x_m[0]}, {zone_x_m[1]}] m lies outside the compartments "
            f"[{x_edges[0]}, {x_edges[-1]}] m"
        )
    x_share = x_overlap / x_overlap.sum()
    if np.count_nonzero(x_share) == 1 and x_share[0] > 0:
        return [float(w) for w in y_share]
    return [float(w) for w in np.outer(x_share, y_share).ravel()]
