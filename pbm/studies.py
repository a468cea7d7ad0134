"""Studies on a velocity table: the paper's blender length and diameter (Figs 3-4), the
compartment grid, the impeller speed (scaled, or interpolated between DEM runs at other
speeds). Each builds modified tables that feed the same :func:`pbm.simulate.simulate`.
"""

from __future__ import annotations

import numpy as np

from coupling import phases as phase_model
from coupling.errors import ConfigError
from coupling.metrics import SteadyStateRule
from coupling.operating import OperatingPoint
from coupling.tables import RATE_NAMES, VELOCITY_NAMES, VelocityTable
from pbm.model import fill_missing_rates, fill_missing_velocities
from pbm.simulate import simulate


def scale_blender(table: VelocityTable, length_factor: float = 1.0, diameter_factor: float = 1.0) -> VelocityTable:
    """The same velocities in a blender ``length_factor`` x longer and ``diameter_factor``
    x wider: the compartment edges are scaled, so every rate v/dx or v/dy changes by the
    inverse factor (a longer blender takes longer to cross, a wider one mixes radially
    more slowly). The edges' origin is kept (x = 0 at the inlet, y centred on the axis).
    """
    for name, value in (("length_factor", length_factor), ("diameter_factor", diameter_factor)):
        if not (np.isfinite(value) and value > 0):
            raise ConfigError(f"{name} must be a finite number > 0, got {value}")
    attrs = dict(table.attrs)
    attrs["geometry_scaling"] = {"length_factor": float(length_factor), "diameter_factor": float(diameter_factor)}
    rates = {}
    if table.has_rates:  # measured rates are per compartment: the same speeds over longer cells
        rates = {
            "rate_x_pos": table.rate_x_pos / length_factor,
            "rate_x_neg": table.rate_x_neg / length_factor,
            "rate_y_pos": table.rate_y_pos / diameter_factor,
            "rate_y_neg": table.rate_y_neg / diameter_factor,
        }
    if table.has_phases:  # the same, phase by phase; the phases' exchange keeps its pace
        rates["phases"] = phase_model.scaled(table.phases, 1 / length_factor, 1 / diameter_factor)
    point = table.operating_point
    return table.replace(
        x_edges=table.x_edges * length_factor,
        y_edges=table.y_edges * diameter_factor,
        attrs=attrs,
        operating_point=None if point is None else point.scaled(length_factor, diameter_factor),
        **rates,
    )


def scale_speed(table: VelocityTable, factor: float) -> VelocityTable:
    """Every velocity, measured rate and phase-model rate times ``factor``: the naive hypothesis that the
    flow follows the impeller speed (``factor`` = new rpm / old rpm) with an unchanged bed."""
    if not (np.isfinite(factor) and factor > 0):
        raise ConfigError(f"speed factor must be a finite number > 0, got {factor}")
    fields = {name: getattr(table, name) * factor for name in VELOCITY_NAMES}
    if table.has_rates:
        fields.update({name: getattr(table, name) * factor for name in RATE_NAMES})
    if table.has_phases:
        fields["phases"] = phase_model.scaled(table.phases, factor, factor, factor)
    attrs = {**table.attrs, "speed_scaling": float(factor)}
    if table.operating_point is not None:
        point = table.operating_point
        fields["operating_point"] = point.replace(impeller_rpm=point.impeller_rpm * factor)
    return table.replace(attrs=attrs, **fields)


def interpolate_tables(points, at: float) -> VelocityTable:
    """A table library's answer at an operating value ``at`` (e.g. an impeller speed):
    ``points`` are (value, table) pairs of DEM runs on the same grid and windows; the two
    that bracket ``at`` are interpolated linearly, field by field and window by window,
    after each has had its missing velocities (and rates) filled. Outside the library's
    range it raises ConfigError rather than extrapolate. Measured rates are kept only when
    both bracketing tables carry them."""
    points = sorted(((float(v), t) for v, t in points), key=lambda p: p[0])
    values = [v for v, _ in points]
    if len(points) < 2 or len(set(values)) != len(values):
        raise ConfigError(f"a table library needs >= 2 tables at distinct values, got values {values}")
    if not (values[0] <= at <= values[-1]):
        raise ConfigError(
            f"{at:g} lies outside the table library's range {values[0]:g}..{values[-1]:g}: "
            "a run there is needed (no extrapolation)"
        )
    hi = int(np.clip(np.searchsorted(values, at, side="left"), 1, len(points) - 1))
    (v0, t0), (v1, t1) = points[hi - 1], points[hi]
    same = (
        t1.t.shape == t0.t.shape
        and np.allclose(t1.t, t0.t)
        and t1.window_s == t0.window_s
        and t1.x_edges.shape == t0.x_edges.shape
        and np.allclose(t1.x_edges, t0.x_edges)
        and t1.y_edges.shape == t0.y_edges.shape
        and np.allclose(t1.y_edges, t0.y_edges)
    )
    if not same:
        raise ConfigError(f"the tables at {v0:g} and {v1:g} differ in grid or windows; a library needs one layout")
    w = (at - v0) / (v1 - v0)
    a, b = fill_missing_velocities(t0)[0], fill_missing_velocities(t1)[0]
    fields = {
        name: (1 - w) * getattr(a, name) + w * getattr(b, name) for name in (*VELOCITY_NAMES, "count_A", "count_B")
    }
    fields["n_samples"] = np.maximum(1, np.rint((1 - w) * a.n_samples + w * b.n_samples)).astype(np.int64)
    rates = {name: None for name in RATE_NAMES}
    if a.has_rates and b.has_rates:
        ra, rb = fill_missing_rates(a)[0], fill_missing_rates(b)[0]
        rates = {name: (1 - w) * getattr(ra, name) + w * getattr(rb, name) for name in RATE_NAMES}
    phases = None
    if a.has_phases and b.has_phases:
        phases = phase_model.blend(a.phases, b.phases, w)
    attrs = {**t0.attrs, "interpolated": {"at": float(at), "between": [v0, v1]}}
    point = _interpolated_point(t0.operating_point, t1.operating_point, at)
    return a.replace(min_samples=1, attrs=attrs, phases=phases, operating_point=point, **fields, **rates)


def _interpolated_point(p0: OperatingPoint | None, p1: OperatingPoint | None, at: float) -> OperatingPoint | None:
    """The operating point of a table interpolated at ``at``: a speed library's (the two
    points differ in the speed alone) at that speed, one point when both are it, else
    unknown (None)."""
    if p0 is None or p1 is None:
        return None
    differences = p0.differences(p1)
    if not differences:
        return p0
    return p0.replace(impeller_rpm=float(at)) if differences == ("impeller_rpm",) else None


def _overlap(old_edges: np.ndarray, new_edges: np.ndarray) -> np.ndarray:
    """(N_new, N_old) lengths of the overlap of each new interval with each old one."""
    lo = np.maximum(new_edges[:-1, None], old_edges[None, :-1])
    hi = np.minimum(new_edges[1:, None], old_edges[None, 1:])
    return np.clip(hi - lo, 0.0, None)


def regrid(
    table: VelocityTable, nx: int | None = None, ny: int | None = None, x_edges=None, y_edges=None
) -> VelocityTable:
    """The same flow on a finer or coarser compartment grid over the same vessel.

    New edges are ``x_edges`` / ``y_edges`` if given, else ``nx`` / ``ny`` uniform
    compartments over the old extent (unchanged axis if neither is given). They must span
    exactly the old extent (the operating point is kept: the same vessel).

    Rule (conservative, particle-flux weighted): first the table's missing
    compartment-windows are filled (:func:`pbm.model.fill_missing_velocities`). Particles
    are taken as spread uniformly inside each old compartment, so a new compartment
    receives from each old one the share ``overlap area / old area`` of its particles
    (``count_A + count_B``) and of its ``n_samples``. Each new velocity is then the ratio of
    sums over those particles, ``sum(share * N * v) / sum(share * N)`` -- what the DEM
    post-processing would have reported binning on the new grid, i.e. the new
    compartment's particle flux divided by its particles. New compartments without any
    counts weight by overlap area instead. Counts are conserved exactly; ``n_samples`` is the
    rounded share of the old samples, at least 1, because after filling every
    compartment-window carries a usable velocity (``min_samples`` of the result is 1).
    """
    new_x = _new_edges(table.x_edges, nx, x_edges, "x")
    new_y = _new_edges(table.y_edges, ny, y_edges, "y")
    if table.has_rates:
        # measured rates belong to the grid they were fitted on; refitting them on another
        # grid needs the DEM's moves between its compartments (bin the dumps at that NX)
        table = table.replace(rate_x_pos=None, rate_x_neg=None, rate_y_pos=None, rate_y_neg=None)
    table = table.replace(phases=None)  # the phase model too: refit from the sequences on that grid
    filled, _ = fill_missing_velocities(table)
    # Shares of each old compartment's content landing in each new one.
    sx = _overlap(table.x_edges, new_x) / table.dx[None, :]  # (NXn, NXo)
    sy = _overlap(table.y_edges, new_y) / table.dy[None, :]  # (NYn, NYo)

    def move(values: np.ndarray) -> np.ndarray:  # (K, NXo, NYo) -> (K, NXn, NYn), conservative
        return np.einsum("ai,kij,bj->kab", sx, values, sy)

    particles = table.count_A + table.count_B
    area = np.broadcast_to(table.dx[:, None] * table.dy[None, :], particles.shape)
    by_particles = move(particles)
    by_area = move(area)
    new_fields = {}
    for name in VELOCITY_NAMES:
        v = getattr(filled, name)
        with np.errstate(invalid="ignore", divide="ignore"):
            particle_mean = move(particles * v) / by_particles
        # Where the new compartment overlaps no particles at all, weight by area instead.
        new_fields[name] = np.where(by_particles > 0, particle_mean, move(area * v) / by_area)
    n_samples = np.maximum(1, np.rint(move(table.n_samples.astype(float)))).astype(np.int64)
    attrs = dict(table.attrs)
    attrs["regridded_from"] = [table.nx, table.ny]
    return table.replace(
        x_edges=new_x,
        y_edges=new_y,
        count_A=move(table.count_A),
        count_B=move(table.count_B),
        n_samples=n_samples,
        min_samples=1,
        attrs=attrs,
        **new_fields,
    )


def _new_edges(old: np.ndarray, count, edges, axis: str) -> np.ndarray:
    if edges is not None:
        if count is not None:
            raise ConfigError(f"give n{axis} or {axis}_edges, not both")
        edges = np.asarray(edges, dtype=float)
        if edges.ndim != 1 or edges.size < 2 or np.any(np.diff(edges) <= 0) or not np.all(np.isfinite(edges)):
            raise ConfigError(f"{axis}_edges must be finite and strictly increasing with >= 2 entries, got {edges}")
        if not (np.isclose(edges[0], old[0]) and np.isclose(edges[-1], old[-1])):
            raise ConfigError(
                f"{axis}_edges must span the table's extent {old[0]:.6g}..{old[-1]:.6g} m, got {edges[0]:.6g}..{edges[-1]:.6g}"
            )
        edges[0], edges[-1] = old[0], old[-1]
        return edges
    if count is None:
        return old.copy()
    if isinstance(count, bool) or int(count) != count or count < 1:
        raise ConfigError(f"n{axis} must be an integer >= 1, got {count!r}")
    return np.linspace(old[0], old[-1], int(count) + 1)


def geometry_study(
    table: VelocityTable,
    config=None,
    length_factors=(0.75, 1.0, 1.25),
    diameter_factors=(0.75, 1.0, 1.25),
    rtd_pulse_s: float | None = None,
    steady: SteadyStateRule = SteadyStateRule(),
) -> dict:
    """Paper Figs 3-4: the same velocities in longer/shorter and wider/narrower blenders.

    Returns ``{"length": {factor: PbmResult}, "diameter": {factor: PbmResult}}``, each run
    by :func:`pbm.simulate.simulate` on :func:`scale_blender`'s table (the other dimension
    kept). Plot with :func:`pbm.plots.plot_rsd_time_family` / ``plot_rsd_by_slice_family``.
    """

    def run(length_factor: float = 1.0, diameter_factor: float = 1.0):
        scaled = scale_blender(table, length_factor=length_factor, diameter_factor=diameter_factor)
        return simulate(scaled, config, rtd_pulse_s, steady=steady)

    return {
        "length": {float(f): run(length_factor=f) for f in length_factors},
        "diameter": {float(f): run(diameter_factor=f) for f in diameter_factors},
    }


def grid_study(
    table: VelocityTable,
    config=None,
    grids=((5, 5), (10, 10), (20, 20)),
    rtd_pulse_s: float | None = None,
    steady: SteadyStateRule = SteadyStateRule(),
) -> dict:
    """The paper's compartment-number study: ``{(nx, ny): PbmResult}`` on :func:`regrid`'s tables."""
    return {
        (int(nx), int(ny)): simulate(regrid(table, nx=nx, ny=ny), config, rtd_pulse_s, steady=steady)
        for nx, ny in grids
    }
