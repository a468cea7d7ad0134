"""Is a dumped particle centre where the vessel lets it be?

The barrel is a cylinder of radius R = D / 2 about the x axis from the inlet wall (x = 0)
to the weir (x = L); past the weir the outlet region runs to the simulation box's end
(L + ``outlet_length_m``). A centre lies at least one particle radius inside a wall, so a
centre beyond the wall by more than the largest particle diameter (the tolerance: contact
overlap and the dump's rounding stay far below it) was not contained by the vessel --
walls leaking in an exploded simulation, or a corrupted field. The dump reader already
refuses positions far outside the box; these are inside the box but outside the vessel,
and are counted (a warning in the results), not refused.
"""

from __future__ import annotations

import numpy as np

from dem.config import DemConfig

__all__ = ["outside_vessel"]


def outside_vessel(x: np.ndarray, y: np.ndarray, z: np.ndarray | None, config: DemConfig) -> np.ndarray:
    """Boolean mask of the particle centres outside the vessel (module docstring); ``z``
    None (not dumped) checks the axial extent and |y| only."""
    g = config.geometry
    tol = float(config.particles.max_diameter_m)
    length, radius = float(g.length_m), float(g.radius_m)
    outside = (x < -tol) | (x > length + float(g.outlet_length_m) + tol)
    in_barrel = x <= length
    if z is None:
        outside |= in_barrel & (np.abs(y) > radius + tol)
    else:
        outside |= in_barrel & (y * y + z * z > (radius + tol) ** 2)
    return outside
