"""The compartment model: transfer rates from a velocity table, the feed, the generator.

State layout. Compartment (i, j) -- i axial from the inlet, j along y from y = -D/2 -- is
entry ``c = i * NY + j`` of a population vector ``N`` (particles). Every species (A, B,
the passive tracer, every ensemble member) obeys the same linear operator, so the solver
propagates them together as the columns of one matrix. Below the NX*NY populations the
state carries three accumulator rows, shared by all columns:

* ``OUT`` (row n):   discharged particles, dOUT/dt = sum over the last slice of forward rate x N
* ``INT1`` (row n+1): time integral of the hold-up, dINT1/dt = sum(N)         [particle s]
* ``INT2`` (row n+2): time integral of INT1,        dINT2/dt = INT1           [particle s^2]

so that time-averaged outflow rates and the first two moments of the residence-time
distribution come out of the same exact propagation, with no quadrature error.

Rates (``coupling/DEFINITIONS.md``, "PBM rates"): particles in (i, j) leave to (i+1, j) at
vx_pos/dx_i, to (i-1, j) at vx_neg/dx_i, to (i, j+1) at vy_pos/dy_j and to (i, j-1) at
vy_neg/dy_j [1/s per particle], with the leaving compartment's velocities (mode "velocity");
or at the table's measured rate_x_pos, rate_x_neg, rate_y_pos, rate_y_neg (mode "measured").
The mode only chooses the four rate arrays; one generator builder serves both. The last
slice's forward flux is the outflow; there is no flux through the inlet wall nor through
the side walls.

Mode "phases" (transport with memory, :mod:`coupling.phases`): every compartment carries K
hidden mobility phases, so the populations are the NX*NY*K entries ``c * K + h`` (then the
same three accumulators), moved by the generator of the table's time-invariant phase model
(schema 3); the feed enters the inlet compartments in the model's entry phases
(:func:`feed_distribution`), and :func:`n_populations` / :func:`collapse_phases` give the
callers the per-compartment view. With K = 1 it is the "measured" chain of those rates.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from coupling.compartments import inlet_weights
from coupling.errors import ConfigError, TableError
from coupling.tables import RATE_NAMES, VELOCITY_NAMES, VelocityTable

N_ACCUMULATORS = 3
# Where the per-particle transfer rates come from: "velocity" = v/dx (the paper's eq. 4),
# "measured" = the table's rate_* fields (transitions counted by the DEM post-processing),
# "phases" = the table's hidden-phase model (schema 3, fitted to the particles' sequences).
RATE_MODES = ("velocity", "measured", "phases")


def fill_missing_velocities(table: VelocityTable) -> tuple[VelocityTable, np.ndarray]:
    """Give every compartment-window without enough samples a velocity, by a fixed rule.

    A compartment-window is missing when ``table.valid`` is False (fewer than
    ``min_samples`` particle-snapshots); its stored velocities (0 by the schema) are never
    read as measurements. For each velocity field (vx_pos, vx_neg, vy_pos, vy_neg), in order:

    1. the same compartment's value in the nearest window in time where it is valid
       (a tie between an earlier and a later window takes the earlier one: the flow that
       particles have actually seen);
    2. if the compartment is valid in no window: the mean of the valid compartments of the
       same axial slice in the same window;
    3. else the mean of the valid compartments of the nearest axial slice that has any in
       that window (a tie averages both sides);
    4. else (the window has no valid compartment at all) the table-wide mean of all valid
       compartment-windows.

    Returns ``(filled_table, filled_mask)``: the filled table (``n_samples`` unchanged, so
    provenance survives) and the (K, NX, NY) bool mask of filled entries. Raises
    TableError when no compartment-window at all is valid: there is nothing to fill from.
    """
    valid = table.valid
    if valid.all():
        return table, np.zeros_like(valid)
    if not valid.any():
        raise TableError(
            f"no compartment-window of the velocity table has n_samples >= min_samples = {table.min_samples}; "
            "the table carries no velocity information"
        )
    fields = {name: getattr(table, name) for name in VELOCITY_NAMES}
    return table.replace(**_fill_by_rule(table.t, valid, fields)), ~valid


def fill_missing_rates(table: VelocityTable) -> tuple[VelocityTable, np.ndarray]:
    """Give every unmeasured (NaN) rate of a table with rates a value, by the rule of
    :func:`fill_missing_velocities`, applied to each rate field with its own NaNs as the
    missing entries (one rate can be measured where another is not).

    Returns ``(filled_table, filled_mask)``, the mask (K, NX, NY) True where any of the four
    rates was filled. Raises ConfigError for a table without rates and TableError when a
    rate field has no measured entry at all.
    """
    require_rates(table, "measured")
    filled, mask = {}, np.zeros((table.n_windows, table.nx, table.ny), dtype=bool)
    for name in RATE_NAMES:
        values = getattr(table, name)
        valid = ~np.isnan(values)
        if not valid.any():
            raise TableError(f"dataset '{name}' is NaN (not measured) everywhere; there is no rate to fill from")
        if not valid.all():
            filled.update(_fill_by_rule(table.t, valid, {name: values}))
            mask |= ~valid
    return (table.replace(**filled) if filled else table), mask


def _fill_by_rule(times: np.ndarray, valid: np.ndarray, fields: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The fill rule of :func:`fill_missing_velocities` for (K, NX, NY) ``fields`` that share
    the mask ``valid`` (which has at least one True): filled copies of the fields."""
    k_count, nx = valid.shape[:2]
    filled = {name: values.copy() for name, values in fields.items()}

    # Rule 1: nearest valid window of the same compartment. For each (k, i, j) find the
    # last valid window at or before k and the first at or after k, then pick the closer.
    idx = np.arange(k_count)[:, None, None]
    last_before = np.where(valid, idx, -1)
    last_before = np.maximum.accumulate(last_before, axis=0)
    first_after = np.where(valid, idx, k_count)
    first_after = np.minimum.accumulate(first_after[::-1], axis=0)[::-1]
    has_before = last_before >= 0
    has_after = first_after < k_count
    t_k = np.broadcast_to(times[:, None, None], valid.shape)
    gap_before = np.where(has_before, t_k - times[np.clip(last_before, 0, None)], np.inf)
    gap_after = np.where(has_after, times[np.clip(first_after, None, k_count - 1)] - t_k, np.inf)
    source = np.where(gap_before <= gap_after, last_before, first_after)
    rule1 = ~valid & (has_before | has_after)
    kk, ii, jj = np.nonzero(rule1)
    for name in fields:
        filled[name][kk, ii, jj] = filled[name][source[kk, ii, jj], ii, jj]

    # Rules 2-4 for compartments that are valid in no window at all.
    never_valid = ~valid.any(axis=0)
    if never_valid.any():
        all_valid_mean = {name: values[valid].mean() for name, values in fields.items()}
        for k in range(k_count):
            slice_has = valid[k].any(axis=1)  # (NX,)
            for i, j in zip(*np.nonzero(never_valid)):
                if not slice_has.any():
                    for name in fields:
                        filled[name][k, i, j] = all_valid_mean[name]
                    continue
                distance = np.abs(np.arange(nx) - i).astype(float)
                distance[~slice_has] = np.inf
                slices = np.nonzero(distance == distance.min())[0]
                for name, values in fields.items():
                    filled[name][k, i, j] = np.mean([values[k][s][valid[k, s]].mean() for s in slices])
    return filled


def supported_modes(table: VelocityTable) -> tuple[str, ...]:
    """The rate modes ``table`` can drive: the velocities always, the measured rates and
    the hidden-phase model when it carries them."""
    return tuple(
        mode
        for mode in RATE_MODES
        if mode == "velocity" or (mode == "measured" and table.has_rates) or (mode == "phases" and table.has_phases)
    )


def require_rates(table: VelocityTable, rates: str) -> None:
    """Raise ConfigError unless ``rates`` is a known mode that this table can drive."""
    if rates not in RATE_MODES:
        raise ConfigError(f"unknown rate mode rates = {rates!r}; valid: {', '.join(map(repr, RATE_MODES))}")
    if rates == "measured" and not table.has_rates:
        raise ConfigError(
            "rates = 'measured' needs the velocity table's measured transition rates, but this table has no "
            f"measured rates ({', '.join(RATE_NAMES)}): use a schema-2 table from a DEM run with transition "
            "tracking, or rates = 'velocity'"
        )
    if rates == "phases" and not table.has_phases:
        raise ConfigError(
            "rates = 'phases' needs the velocity table's hidden-phase transport model (schema 3, fitted by "
            "dem.phases from the DEM's compartment sequences), but this table has none: fit one, or use "
            "rates = 'measured' or 'velocity'"
        )


def n_phases(table: VelocityTable, rates: str) -> int:
    """Phases per compartment of mode ``rates``: the phase model's K, else 1."""
    return table.phases.n_phases if rates == "phases" else 1


def n_populations(table: VelocityTable, rates: str) -> int:
    """Population entries of the state vector: NX*NY compartments times the phases."""
    return table.nx * table.ny * n_phases(table, rates)


def collapse_phases(populations: np.ndarray, k: int, axis: int = 0) -> np.ndarray:
    """Sum the K phases of each compartment: ``axis`` of length NX*NY*K -> NX*NY."""
    if k == 1:
        return populations
    populations = np.moveaxis(np.asarray(populations), axis, -1)
    collapsed = populations.reshape(*populations.shape[:-1], -1, k).sum(axis=-1)
    return np.moveaxis(collapsed, -1, axis)


def filled_table(table: VelocityTable, rates: str) -> tuple[VelocityTable, np.ndarray]:
    """The table with the fields that mode ``rates`` reads filled where missing, and the
    (K, NX, NY) mask of the compartment-windows filled: velocities for "velocity"
    (:func:`fill_missing_velocities`), measured rates for "measured" (:func:`fill_missing_rates`)."""
    require_rates(table, rates)
    if rates == "phases":  # the phase model is complete: nothing to fill
        return table, np.zeros((table.n_windows, table.nx, table.ny), dtype=bool)
    return fill_missing_velocities(table) if rates == "velocity" else fill_missing_rates(table)


def default_feed_weights(y_edges: np.ndarray, side: int) -> np.ndarray:
    """Weights of a feeder over the NY inlet compartments: the width share on one side.

    ``side`` = +1 for y > 0 (feeder A), -1 for y < 0 (feeder B). A compartment straddling
    y = 0 (odd NY) gets the fraction of its width on that side, so the two default feeds
    stay mirror images of each other. Normalised to sum 1.
    """
    zone = (0.0, y_edges[-1]) if side > 0 else (y_edges[0], 0.0)
    try:
        return np.asarray(inlet_weights(y_edges, *zone))
    except ConfigError:
        raise ConfigError(
            f"the transverse edges {y_edges[0]:.4g}..{y_edges[-1]:.4g} m do not extend to y "
            f"{'> 0' if side > 0 else '< 0'}; give feed_weights_{'a' if side > 0 else 'b'} explicitly"
        ) from None


def feed_distribution(table: VelocityTable, weights_a, weights_b, rates: str = "velocity") -> np.ndarray:
    """(n, 2) matrix: how one particle/s of feed A (column 0) and B (column 1) enters.

    Each column sums to 1. ``weights_a`` / ``weights_b`` are NY relative weights over the
    first axial slice, NX * NY over the whole grid (flat index i * NY + j: a feed zone that
    spans slices), or None for the default halves of the first slice. Raises ConfigError
    when a weight list has neither length. With ``rates`` = "phases"
    n is NX*NY*K: each compartment's share is split over the phases by the model's
    entry-phase distribution of that feeder.
    """
    if rates == "phases":
        require_rates(table, rates)
        plain = feed_distribution(table, weights_a, weights_b)
        entry = table.phases.entry  # (2, K): feeder A, feeder B
        return np.stack([(plain[:, f, None] * entry[f][None, :]).ravel() for f in (0, 1)], axis=1)
    ny = table.ny
    columns = []
    for name, weights, side in (("feed_weights_a", weights_a, +1), ("feed_weights_b", weights_b, -1)):
        if weights is None:
            w = default_feed_weights(table.y_edges, side)
        else:
            w = np.asarray(weights, dtype=float)
            if w.shape not in ((ny,), (table.nx * ny,)):
                raise ConfigError(
                    f"{name} has {w.size} entries; the velocity table needs NY = {ny} (the first slice) or "
                    f"NX * NY = {table.nx * ny} (every compartment)"
                )
            w = w / w.sum()
        column = np.zeros(table.nx * ny)
        column[: w.size] = w
        columns.append(column)
    return np.stack(columns, axis=1)


def transfer_rates(table: VelocityTable, k, rates: str = "velocity") -> dict[str, np.ndarray]:
    """Per-particle rates [1/s] of window ``k``, each (NX, NY), walls already closed.

    ``k`` may also be an index array or slice: the rates then carry a leading window axis.
    Keys: ``forward`` (to i+1; for the last slice: the outflow), ``backward`` (to i-1),
    ``up`` (to j+1), ``down`` (to j-1). ``rates`` (:data:`RATE_MODES`) says where they come
    from: "velocity" = vx_pos/dx, vx_neg/dx, vy_pos/dy, vy_neg/dy; "measured" = the table's
    rate_x_pos, rate_x_neg, rate_y_pos, rate_y_neg, filled beforehand
    (:func:`fill_missing_rates`; a NaN left raises TableError). Rates through the inlet wall
    and the side walls are set to 0 here, so that the velocities recorded there by DEM
    (particles bouncing off a wall) never move particles out of the domain.
    """
    require_rates(table, rates)
    if rates == "velocity":
        dx = table.dx[:, None]
        dy = table.dy[None, :]
        forward = table.vx_pos[k] / dx
        backward = table.vx_neg[k] / dx
        up = table.vy_pos[k] / dy
        down = table.vy_neg[k] / dy
    else:
        # Copies: the wall entries are zeroed below, and the table's arrays are its own.
        forward, backward, up, down = (np.array(getattr(table, name)[k], dtype=float) for name in RATE_NAMES)
        if any(np.isnan(r).any() for r in (forward, backward, up, down)):
            raise TableError(
                f"window(s) {k} of the table hold unmeasured (NaN) rates; fill them first with "
                "pbm.model.fill_missing_rates"
            )
    backward[..., 0, :] = 0.0
    up[..., :, -1] = 0.0
    down[..., :, 0] = 0.0
    return {"forward": forward, "backward": backward, "up": up, "down": down}


def _phase_triplets(table: VelocityTable, k):
    """:func:`generator_triplets` of mode "phases": the phase model's generator (the same
    in every window) transposed to the column convention, with the accumulators."""
    require_rates(table, "phases")
    q = table.phases.generator()  # row = from, last state discharged
    n = q.shape[0] - 1
    src, dst = np.nonzero(q[:n])  # off-diagonal moves, the discharge and the diagonal
    rows = np.where(dst == n, n, dst)
    cols = src
    values = q[src, dst]
    # accumulators: INT1 gathers every population, INT2 integrates INT1
    rows = np.concatenate([rows, np.full(n, n + 1), [n + 2]])
    cols = np.concatenate([cols, np.arange(n), [n + 1]])
    values = np.concatenate([values, np.ones(n), [1.0]])
    lead = np.shape(np.arange(table.n_windows)[k])
    return rows, cols, np.broadcast_to(values, (*lead, values.size)).copy(), n + N_ACCUMULATORS


def generator_triplets(table: VelocityTable, k, rates: str):
    """Row, column and value arrays of the generator entries; values carry the leading
    window axis of ``k`` (if any), rows and columns are the same for every window."""
    if rates == "phases":
        return _phase_triplets(table, k)
    nx, ny = table.nx, table.ny
    n = nx * ny
    r = transfer_rates(table, k, rates)
    lead = r["forward"].shape[:-2]
    c = np.arange(n).reshape(nx, ny)
    rows, cols, vals = [], [], []

    def add(src, dst, rate):
        rows.append(np.broadcast_to(dst, src.shape).ravel())
        cols.append(np.ravel(src))
        vals.append(np.broadcast_to(rate, (*lead, *np.shape(src))).reshape(*lead, -1))

    add(c[:-1, :], c[1:, :], r["forward"][..., :-1, :])
    add(c[1:, :], c[:-1, :], r["backward"][..., 1:, :])
    add(c[:, :-1], c[:, 1:], r["up"][..., :, :-1])
    add(c[:, 1:], c[:, :-1], r["down"][..., :, 1:])
    leaving = r["forward"] + r["backward"] + r["up"] + r["down"]
    add(c, c, -leaving)
    # Accumulators: discharged particles, and the two time integrals of the hold-up.
    add(c[-1, :], np.full(ny, n), r["forward"][..., -1, :])
    add(c, np.full((nx, ny), n + 1), np.ones((nx, ny)))
    add(np.array([n + 1]), np.array([n + 2]), np.ones(1))
    return np.concatenate(rows), np.concatenate(cols), np.concatenate(vals, axis=-1), n + N_ACCUMULATORS


def generator_matrix(table: VelocityTable, k, rates: str = "velocity") -> np.ndarray:
    """Dense (n+3, n+3) generator of window ``k``: dz/dt = G z for the augmented state,
    with the transfer rates of mode ``rates`` (:func:`transfer_rates`).

    With an index array ``k`` of windows: the stack (len(k), n+3, n+3), built at once.
    """
    return dense_generator(*generator_triplets(table, k, rates))


def dense_generator(rows: np.ndarray, cols: np.ndarray, vals: np.ndarray, m: int) -> np.ndarray:
    """The dense generator(s) of triplets; ``vals`` may carry leading window axes."""
    g = np.zeros((*vals.shape[:-1], m, m))
    # Every (destination, source) pair occurs once (the stencil's neighbours, the
    # diagonal and the accumulator rows are distinct), so plain assignment is exact.
    g[..., rows, cols] = vals
    return g


def generator_sparse(table: VelocityTable, k: int, rates: str = "velocity") -> sp.csr_matrix:
    """The same generator as a sparse CSR matrix (for the BDF Jacobian)."""
    rows, cols, vals, m = generator_triplets(table, k, rates)
    return sp.csr_matrix((vals, (rows, cols)), shape=(m, m))
