"""A seeded synthetic velocity table of DEM-like magnitudes, to try and benchmark the PBM
without a DEM run. Not physics: only the orders of magnitude are DEM-like.
"""

from __future__ import annotations

import math

import numpy as np

from coupling.errors import ConfigError
from coupling.resources import require_memory
from coupling.tables import MAX_TIME_S, VelocityTable, make_table
from pbm.resources import table_bytes


def _integer(name: str, value, low: int, high: int | None = None) -> int:
    valid = f"an integer >= {low}" + (f" and <= {high}" if high is not None else "")
    if isinstance(value, bool) or not isinstance(value, (int, np.integer, float)):
        raise ConfigError(f"{name} must be {valid}, got {value!r}")
    if isinstance(value, float) and not (math.isfinite(value) and value.is_integer()):
        raise ConfigError(f"{name} must be {valid}, got {value!r}")
    if value < low or (high is not None and value > high):
        raise ConfigError(f"{name} must be {valid}, got {value!r}")
    return int(value)


def check_synthetic_arguments(
    nx,
    ny,
    n_windows,
    window_s,
    length_m=0.330,
    diameter_m=0.100,
    seed=2013,
    min_samples=20,
    available_bytes: float | None = None,
) -> None:
    """Refuse, naming the argument and what is valid, what :func:`synthetic_table` cannot
    make: grid and window counts that are not integers >= 1, or whose table would not fit in
    memory (``--windows 1e8``: 10^8 x 100 compartments x 11 arrays); a window that is not a
    finite time > 0 or whose windows run past 1e9 s; a seed that is not an integer in
    [0, 2**63) (numpy's generators refuse negative seeds); sizes that are not finite > 0."""
    nx = _integer("nx", nx, 1)
    ny = _integer("ny", ny, 1)
    n_windows = _integer("n_windows (--windows)", n_windows, 1)
    _integer("seed", seed, 0, 2**63 - 1)
    _integer("min_samples", min_samples, 1)
    for name, value in (("window_s", window_s), ("length_m", length_m), ("diameter_m", diameter_m)):
        if (
            isinstance(value, bool)
            or not isinstance(value, (int, float, np.number))
            or not (math.isfinite(value) and value > 0)
        ):
            raise ConfigError(f"{name} must be a finite number > 0, got {value!r}")
    if n_windows * float(window_s) > MAX_TIME_S:
        raise ConfigError(
            f"{n_windows} windows of {window_s:g} s run to {n_windows * float(window_s):.3g} s; "
            f"a table's times must stay within {MAX_TIME_S:g} s"
        )
    require_memory(
        table_bytes(nx, ny, n_windows) * 3,
        f"a synthetic table of {n_windows} windows x {nx} x {ny} compartments",
        "use fewer windows or a coarser grid",
        available=available_bytes,
    )


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
    Arguments are checked first (:func:`check_synthetic_arguments`: ConfigError or
    ResourceLimitError naming the argument).
    """
    check_synthetic_arguments(nx, ny, n_windows, window_s, length_m, diameter_m, seed, min_samples)
    rng = np.random.default_rng(seed)
    shape = (n_windows, nx, ny)
    t = window_s * np.arange(n_windows)
    n_samples = rng.integers(50, 500, size=shape)
    reached = 2 + 2 * np.arange(n_windows)
    n_samples[np.arange(nx)[None, :] >= reached[:, None]] = 0
    y_centres = (np.arange(ny) + 0.5) / ny - 0.5
    share_a = np.broadcast_to(0.5 + 0.4 * np.sign(y_centres) * np.exp(-np.arange(n_windows) / 4)[:, None, None], shape)
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
