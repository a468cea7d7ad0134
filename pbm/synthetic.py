"""A seeded synthetic velocity table of DEM-like magnitudes, to try and benchmark the PBM
without a DEM run. Not physics: only the orders of magnitude are DEM-like.
"""

from __future__ import annotations

import numpy as np

from coupling.errors import ConfigError
from coupling.tables import VelocityTable, make_table


def synthetic_table(
    nx: int = 10,
    ny: int = 10,
    n_windows: int = 52,
    window_s: float = 5.0,
    length_m: float = 0.330,
    diameter_m: float = 0.100,
    seed: int = 2013,
    min_samples: int = 20,
) -> VelocityTable:
    """Paper-like table: NX x NY compartments over L x D, ``n_windows`` windows of ``window_s``.

    Velocities per compartment-window, uniform random [m/s]: vx_pos 0.03-0.05,
    vx_neg 0.01-0.03 (net forward drift, back-mixing), vy_pos and vy_neg 0.05-0.3.
    Samples mimic a filling blender: in window k the slices beyond ``2 + 2 k`` have no
    particles yet (n_samples 0, so the PBM's fill rule is exercised), the others 50-500
    samples; counts of A and B follow the samples (A on the y > 0 side early on).
    """
    for name, value in (("nx", nx), ("ny", ny), ("n_windows", n_windows)):
        if isinstance(value, bool) or int(value) != value or value < 1:
            raise ConfigError(f"{name} must be an integer >= 1, got {value!r}")
    if not window_s > 0:
        raise ConfigError(f"window_s must be > 0 s, got {window_s}")
    rng = np.random.default_rng(seed)
    shape = (n_windows, nx, ny)
    t = window_s * np.arange(n_windows)
    n_samples = rng.integers(50, 500, size=shape)
    reached = 2 + 2 * np.arange(n_windows)
    n_samples[np.arange(nx)[None, :] >= reached[:, None]] = 0
    y_centres = (np.arange(ny) + 0.5) / ny - 0.5
    share_a = np.broadcast_to(0.5 + 0.4 * np.sign(y_centres) * np.exp(-np.arange(n_windows) / 4)[:, None, None],
                              shape)
    per_snapshot = n_samples / 50.0
    return make_table(
        t=t,
        x_edges=np.linspace(0.0, length_m, nx + 1),
        y_edges=np.linspace(-diameter_m / 2, diameter_m / 2, ny + 1),
        vx_pos=rng.uniform(0.03, 0.05, shape),
        vx_neg=rng.uniform(0.01, 0.03, shape),
        vy_pos=rng.uniform(0.05, 0.3, shape),
        vy_neg=rng.uniform(0.05, 0.3, shape),
        count_A=per_snapshot * share_a,
        count_B=per_snapshot * (1 - share_a),
        n_samples=n_samples,
        window_s=window_s,
        min_samples=min_samples,
        attrs={"preset": "synthetic", "synthetic_seed": seed, "input_hash": f"synthetic-{seed}"},
    )
