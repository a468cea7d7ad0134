"""What a PBM run and a feed-noise ensemble cost in memory, estimated before they start.

The exact solver (:mod:`pbm.solver`) keeps a dense m x m generator and step operators per
velocity window (m = S K + 3: S = NX x NY compartments, K hidden phases in the "phases" rate
mode, else 1, and the accumulators), and the
ensemble keeps per member its feed factors and its output series. Both grow without bound
with the grid or the member count; :func:`check_pbm_memory` and
:func:`check_ensemble_memory` refuse, with the estimate, what the machine cannot hold
(``nx = 100000``: 80 GB per matrix; ``--noise-members 100000000``: terabytes).
"""

from __future__ import annotations

import math

from coupling.errors import ConfigError
from coupling.resources import format_bytes, require_memory

__all__ = ["check_ensemble_memory", "check_pbm_memory", "ensemble_bytes", "pbm_bytes", "phase_bytes", "table_bytes"]


def table_bytes(nx: int, ny: int, n_windows: int, with_rates: bool = True) -> float:
    """A velocity table's arrays: 7 fields (+4 rates) of K x NX x NY float64."""
    return 8.0 * (11 if with_rates else 7) * int(n_windows) * int(nx) * int(ny)


def phase_bytes(nx: int, ny: int, n_phases: int) -> float:
    """A phase model's arrays: rates (K, 4, NX, NY) and switching (K, K, NX, NY) float64."""
    return 8.0 * int(n_phases) * (4 + int(n_phases)) * int(nx) * int(ny)


def pbm_bytes(nx: int, ny: int, n_windows: int, n_phases: int = 1) -> float:
    """Peak memory of the exact PBM solver: per generator a dense one and about three
    cached step operators of m x m (m = S K + 3 with K = ``n_phases``), plus the table
    (filled copy included) and the matrix-exponential temporaries (~8 m x m). The phase
    model is one generator for every window (:func:`pbm.solver.table_schedule`), so
    ``n_phases`` > 1 counts one window of operators, and the model's own arrays."""
    m = int(nx) * int(ny) * int(n_phases) + 3
    dense = 8.0 * m * m
    generators = 1 if int(n_phases) > 1 else int(n_windows)
    extra = phase_bytes(nx, ny, n_phases) if int(n_phases) > 1 else 0.0
    return generators * 4 * dense + 8 * dense + 2 * table_bytes(nx, ny, n_windows) + extra


def check_pbm_memory(
    nx: int, ny: int, n_windows: int, available_bytes: float | None = None, n_phases: int = 1
) -> float:
    """Refuse (ResourceLimitError) a PBM on a grid, or with a number of hidden phases
    ``n_phases``, the machine cannot hold; the estimate."""
    estimate = pbm_bytes(nx, ny, n_windows, n_phases)
    m = int(nx) * int(ny) * int(n_phases) + 3
    phases = f" with {n_phases} phases each ({m - 3} populations)" if int(n_phases) > 1 else ""
    require_memory(
        estimate,
        f"the PBM on {nx} x {ny} compartments{phases} over {n_windows} velocity windows",
        f"one dense {m} x {m} operator is {format_bytes(8.0 * m**2)}; "
        + ("use a phase model with fewer phases or a coarser grid" if phases else "use a coarser grid"),
        available=available_bytes,
    )
    return estimate


def ensemble_bytes(members: int, t_end_s: float, noise_interval_s: float, output_interval_s: float, nx: int) -> float:
    """Peak memory of :func:`pbm.ensemble.noise_ensemble` per its arrays: per member the
    feed factors and fed amounts (4 per noise interval), the C_A and RSD series and their
    repeated copies (6 per output), the slice RSDs (2 NX), twice for the band statistics'
    sorted copies."""
    n_noise = max(1, math.ceil(t_end_s / noise_interval_s))
    n_out = max(1, math.ceil(t_end_s / output_interval_s))
    return 2 * 8.0 * int(members) * (4 * n_noise + 6 * n_out + 2 * int(nx))


def check_ensemble_memory(
    members: int,
    t_end_s: float,
    noise_interval_s: float,
    output_interval_s: float,
    nx: int,
    available_bytes: float | None = None,
) -> float:
    """Refuse a member count that is not an integer >= 1 (ConfigError) or that the machine
    cannot hold (ResourceLimitError, with the estimate and the largest count that fits);
    else the estimate [bytes]."""
    if isinstance(members, bool) or not isinstance(members, int) and not float(members).is_integer() or members < 1:
        raise ConfigError(f"the number of noise members must be an integer >= 1, got {members!r}")
    for name, value in (
        ("t_end_s", t_end_s),
        ("noise_interval_s", noise_interval_s),
        ("output_interval_s", output_interval_s),
    ):
        if not (math.isfinite(value) and value > 0):
            raise ConfigError(f"{name} must be a finite number > 0, got {value}")
    estimate = ensemble_bytes(int(members), t_end_s, noise_interval_s, output_interval_s, nx)
    per_member = estimate / int(members)
    from coupling.resources import MEMORY_FRACTION, available_memory_bytes

    available = available_memory_bytes() if available_bytes is None else float(available_bytes)
    fits = int(MEMORY_FRACTION * available // per_member)
    require_memory(
        estimate,
        f"a feed-noise ensemble of {int(members)} members over {t_end_s:g} s",
        f"{format_bytes(per_member)} per member: at most {fits} members fit",
        available=available,
    )
    return estimate
