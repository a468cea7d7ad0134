"""Blender geometry as pure functions: a :class:`~dem.config.DemConfig` in, triangle meshes out.

Frame (``coupling/DEFINITIONS.md``): x axial, 0 at the closed inlet end wall, ``L`` at the
outlet; the impeller axis is the x axis (y = z = 0); z is vertical, gravity along -z.

What is built, and why
----------------------
* **Barrel**: a cylinder of radius ``D/2`` about the x axis. The deck uses LIGGGHTS'
  ``wall/gran ... primitive xcylinder`` (measured faster than an STL barrel);
  :func:`barrel_mesh` exists for viewing only. The inlet end wall is the primitive plane
  ``x = 0`` (again an STL only for viewing).
* **Impeller** (one STL, ``meshes/impeller.stl``): a closed cylindrical shaft from ``x = 0``
  to ``x = L`` plus ``blade_stations`` stations of flat, zero-thickness rectangular paddles.
  A paddle lies in the plane spanned by its radial direction ``e_r`` and the chord direction
  ``cos(p) e_x - s sin(p) e_theta`` (``p`` = ``blade_pitch_deg``, ``s`` = +1 for a forward
  (F) blade, -1 for a backward (B) one). With the positive rotation the deck applies
  (right-handed about +x), the leading face of an F paddle has a normal with a +x component,
  so it pushes powder towards the outlet; B paddles push it back. The paddle root is buried
  inside the shaft (at half the shaft radius) so no gap opens between shaft and paddle;
  the paddle's radial length is chosen so that its *outermost corners* sit exactly at
  ``D/2 - blade_tip_clearance_m`` (a flat paddle's tip edge is a chord, so its corners are
  the point of closest approach to the wall).
* **Weir** (``meshes/weir.stl``): a zero-thickness circular-segment plate in the plane
  ``x = L`` covering the barrel's cross-section below ``z = -D/2 + weir_height_m``. Its arc
  reaches 1 mm beyond the barrel radius so that no particle can slip between weir and wall.
  Above the weir the outlet end is open: powder spills over it.
* **Discharge face** (``meshes/discharge.stl``): a planar square covering the whole
  cross-section at ``x = L + discharge_offset_m``. It is not a wall: ``fix massflow/mesh``
  counts and deletes particles whose centre crosses it. A particle centre can only get past
  ``x = L`` by going over the weir, so every crossing is a discharge.
* **Simulation box**: ``x`` from ``-inlet_margin_m`` (default ``-box_margin_m``) to
  ``L + outlet_length_m``, ``y`` and
  ``z`` within ``D/2 + box_margin_m``.
* **Feed zones**: two boxes above the first axial compartment, upstream of the first blade,
  A on the +y side and B on the -y side (mirror images).

Validation (:func:`validate_geometry`) happens before any mesh is returned or written, and
raises :class:`~coupling.errors.GeometryError` naming the value and its valid range: positive
sizes, blade tips clearing the wall by more than the largest particle, blades within the
barrel, feed zones inside the barrel and clear of the blades' swept volume, and LIGGGHTS'
own mesh checks (no duplicate or degenerate triangles, no angle below 0.5 deg, at most 5
edge neighbours per element, every node inside the simulation box).

This module is longer than most: each surface, the checks that make it acceptable to
LIGGGHTS, and its STL text belong together, so that changing a surface shows at once what
it must still satisfy.
"""

from __future__ import annotations

import io
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from coupling.errors import GeometryError
from dem.config import DemConfig, GeometryConfig

if TYPE_CHECKING:
    import meshio

# LIGGGHTS 3.8.0's mesh/surface checks (SurfaceMesh / TriMesh): these are the limits it applies.
MIN_TRIANGLE_ANGLE_DEG = 0.5
MAX_EDGE_NEIGHBOURS = 5
#: Coordinates are rounded to this many decimals (1 nm) so that STL text is reproducible.
COORD_DECIMALS = 9
WEIR_OVERLAP_M = 0.001


@dataclass(frozen=True)
class TriMesh:
    """A triangle surface: ``points`` (n, 3) in m, ``triangles`` (m, 3) indices into points."""

    name: str
    points: np.ndarray
    triangles: np.ndarray

    @property
    def corners(self) -> np.ndarray:
        """(m, 3, 3) coordinates of each triangle's corners [m]."""
        return self.points[self.triangles]

    def to_meshio(self) -> meshio.Mesh:
        return _meshio().Mesh(self.points, [("triangle", self.triangles)])


@dataclass(frozen=True)
class Box:
    """An axis-aligned box [m]."""

    xmin: float
    xmax: float
    ymin: float
    ymax: float
    zmin: float
    zmax: float

    def contains(self, points: np.ndarray, margin: float = 0.0) -> np.ndarray:
        p = np.asarray(points)
        return (
            (p[:, 0] > self.xmin + margin)
            & (p[:, 0] < self.xmax - margin)
            & (p[:, 1] > self.ymin + margin)
            & (p[:, 1] < self.ymax - margin)
            & (p[:, 2] > self.zmin + margin)
            & (p[:, 2] < self.zmax - margin)
        )

    @property
    def corners(self) -> np.ndarray:
        xs, ys, zs = (self.xmin, self.xmax), (self.ymin, self.ymax), (self.zmin, self.zmax)
        return np.array([[x, y, z] for x in xs for y in ys for z in zs])


@dataclass(frozen=True)
class BladeStation:
    """One axial station of paddles: centre ``x_m``, ``orientation`` 'F' or 'B', azimuths [deg]."""

    x_m: float
    orientation: str
    azimuths_deg: tuple[float, ...]


@dataclass(frozen=True)
class Geometry:
    """The validated, assembled blender."""

    meshes: dict[str, TriMesh]  # name -> mesh; keys of DECK_MESHES are used by the deck
    box: Box
    feed_zones: dict[str, Box]  # "A", "B"
    stations: tuple[BladeStation, ...]
    discharge_x_m: float
    view_meshes: dict[str, TriMesh] = field(default_factory=dict)  # barrel, inlet wall


# --------------------------------------------------------------------------------------
# derived dimensions
# --------------------------------------------------------------------------------------


def blade_axial_half_extent_m(g: GeometryConfig) -> float:
    """Half the axial extent of a pitched paddle [m]."""
    return 0.5 * g.blade_chord_m * math.cos(math.radians(g.blade_pitch_deg))


def blade_tangential_half_extent_m(g: GeometryConfig) -> float:
    return 0.5 * g.blade_chord_m * math.sin(math.radians(g.blade_pitch_deg))


def blade_root_radius_m(g: GeometryConfig) -> float:
    """Paddles start inside the shaft (half its radius) so no shaft-paddle gap opens."""
    return 0.5 * g.shaft_radius_m


def blade_stations(g: GeometryConfig) -> tuple[BladeStation, ...]:
    """Axial stations, evenly spaced, orientation cycling through ``blade_pattern``."""
    if g.blade_stations == 1:
        xs = [g.first_blade_x_m]
    else:
        xs = np.linspace(g.first_blade_x_m, g.last_blade_x_m, g.blade_stations).tolist()
    stations = []
    for s, x in enumerate(xs):
        base = s * g.blade_azimuth_step_deg
        az = tuple((base + b * 360.0 / g.blades_per_station) % 360.0 for b in range(g.blades_per_station))
        stations.append(BladeStation(float(x), g.blade_pattern[s % len(g.blade_pattern)], az))
    return tuple(stations)


def swept_volumes(g: GeometryConfig) -> list[tuple[float, float, float, float]]:
    """Annuli swept by the paddles: (x_min, x_max, r_min, r_max) per station [m]."""
    half = blade_axial_half_extent_m(g)
    return [(st.x_m - half, st.x_m + half, 0.0, g.blade_tip_radius_m) for st in blade_stations(g)]


def feed_zones(g: GeometryConfig) -> dict[str, Box]:
    """Feed boxes: A on +y, B on -y, ``feed_depth_m`` tall, centred at ``feed_height_m``."""
    z0, z1 = g.feed_height_m - g.feed_depth_m / 2, g.feed_height_m + g.feed_depth_m / 2
    return {
        "A": Box(g.feed_x_min_m, g.feed_x_max_m, g.feed_y_inner_m, g.feed_y_outer_m, z0, z1),
        "B": Box(g.feed_x_min_m, g.feed_x_max_m, -g.feed_y_outer_m, -g.feed_y_inner_m, z0, z1),
    }


def simulation_box(g: GeometryConfig) -> Box:
    r = g.radius_m + g.box_margin_m
    upstream = g.inlet_margin_m if g.inlet_margin_m is not None else g.box_margin_m
    return Box(-upstream, g.length_m + g.outlet_length_m, -r, r, -r, r)


def discharge_x_m(g: GeometryConfig) -> float:
    return g.length_m + g.discharge_offset_m


# --------------------------------------------------------------------------------------
# meshes
# --------------------------------------------------------------------------------------


def _n_around(g: GeometryConfig, radius: float, minimum: int = 12) -> int:
    """Segments around a circle of this radius, chords no longer than the mesh resolution."""
    return max(minimum, math.ceil(2 * math.pi * radius / g.mesh_resolution_m))


def _cylinder(name: str, radius: float, x0: float, x1: float, n_theta: int, n_x: int, caps: bool) -> TriMesh:
    theta = np.linspace(0, 2 * np.pi, n_theta, endpoint=False)
    xs = np.linspace(x0, x1, n_x + 1)
    ring = np.stack([np.cos(theta), np.sin(theta)], axis=1) * radius
    pts = [[x, y, z] for x in xs for y, z in ring]
    tris = []
    for i in range(n_x):
        for k in range(n_theta):
            a, b = i * n_theta + k, i * n_theta + (k + 1) % n_theta
            c, d = a + n_theta, b + n_theta
            tris += [[a, b, d], [a, d, c]]
    if caps:
        for x, base, flip in ((x0, 0, True), (x1, n_x * n_theta, False)):
            centre = len(pts)
            pts.append([x, 0.0, 0.0])
            for k in range(n_theta):
                a, b = base + k, base + (k + 1) % n_theta
                tris.append([centre, b, a] if flip else [centre, a, b])
    return TriMesh(name, np.round(np.array(pts, float), COORD_DECIMALS), np.array(tris, dtype=np.int64))


def shaft_mesh(g: GeometryConfig) -> TriMesh:
    """Closed cylinder of radius ``shaft_radius_m`` from the inlet wall to the weir plane.

    Deliberately coarse (an octagon by default): LIGGGHTS re-bins every triangle of a moving
    mesh each step, and that per-step cost was measured to dominate small runs (smoke: ~35 us
    per step for 350 triangles). The shaft only has to keep powder off the axis."""
    n_theta = _n_around(g, g.shaft_radius_m, minimum=8)
    n_x = max(1, math.ceil(g.length_m / g.mesh_resolution_m))
    return _cylinder("shaft", g.shaft_radius_m, 0.0, g.length_m, n_theta, n_x, caps=True)


def blade_meshes(g: GeometryConfig) -> TriMesh:
    """Every paddle, two triangles each (see the module docstring for the orientation)."""
    p = math.radians(g.blade_pitch_deg)
    half_chord = g.blade_chord_m / 2
    r_root = blade_root_radius_m(g)
    # corners of the tip edge at exactly the tip radius
    r_tip_mid = math.sqrt(g.blade_tip_radius_m**2 - (half_chord * math.sin(p)) ** 2)
    pts, tris = [], []
    for st in blade_stations(g):
        sign = 1.0 if st.orientation == "F" else -1.0
        for az in st.azimuths_deg:
            phi = math.radians(az)
            e_r = np.array([0.0, math.cos(phi), math.sin(phi)])
            e_t = np.array([0.0, -math.sin(phi), math.cos(phi)])
            e_c = math.cos(p) * np.array([1.0, 0.0, 0.0]) - sign * math.sin(p) * e_t
            centre = np.array([st.x_m, 0.0, 0.0])
            base = len(pts)
            for r, c in (
                (r_root, -half_chord),
                (r_root, half_chord),
                (r_tip_mid, half_chord),
                (r_tip_mid, -half_chord),
            ):
                pts.append(centre + r * e_r + c * e_c)
            tris += [[base, base + 1, base + 2], [base, base + 2, base + 3]]
    return TriMesh("blades", np.round(np.array(pts), COORD_DECIMALS), np.array(tris, dtype=np.int64))


def merge_meshes(name: str, *meshes: TriMesh) -> TriMesh:
    pts, tris, offset = [], [], 0
    for m in meshes:
        pts.append(m.points)
        tris.append(m.triangles + offset)
        offset += len(m.points)
    return TriMesh(name, np.concatenate(pts), np.concatenate(tris))


def impeller_mesh(g: GeometryConfig) -> TriMesh:
    """Shaft + paddles, the surface that ``move/mesh rotate`` turns."""
    return merge_meshes("impeller", shaft_mesh(g), blade_meshes(g))


def weir_mesh(g: GeometryConfig) -> TriMesh:
    """Circular-segment plate at x = L below the weir crest, fanned from the crest's centre."""
    r_out = g.radius_m + WEIR_OVERLAP_M
    z_top = -g.radius_m + g.weir_height_m
    half_angle = math.acos(-z_top / r_out)  # from -z towards the chord ends
    n_arc = max(8, math.ceil(2 * half_angle * r_out / g.mesh_resolution_m))
    ang = np.linspace(-half_angle, half_angle, n_arc + 1)
    arc = np.stack([np.full_like(ang, g.length_m), r_out * np.sin(ang), -r_out * np.cos(ang)], axis=1)
    centre = np.array([[g.length_m, 0.0, z_top]])
    pts = np.concatenate([centre, arc])
    tris = np.array([[0, k + 1, k + 2] for k in range(n_arc)], dtype=np.int64)
    return TriMesh("weir", np.round(pts, COORD_DECIMALS), tris)


def _plane_x(name: str, x: float, half: float, n: int) -> TriMesh:
    s = np.linspace(-half, half, n + 1)
    pts = np.array([[x, y, z] for y in s for z in s])
    tris = []
    for i in range(n):
        for j in range(n):
            a, b, c, d = i * (n + 1) + j, i * (n + 1) + j + 1, (i + 1) * (n + 1) + j, (i + 1) * (n + 1) + j + 1
            tris += [[a, c, d], [a, d, b]]
    return TriMesh(name, np.round(pts, COORD_DECIMALS), np.array(tris, dtype=np.int64))


def discharge_mesh(g: GeometryConfig) -> TriMesh:
    """Planar counting face past the weir (not a wall), covering the whole cross-section."""
    half = g.radius_m + WEIR_OVERLAP_M
    n = max(2, math.ceil(2 * half / (4 * g.mesh_resolution_m)))
    return _plane_x("discharge", discharge_x_m(g), half, n)


def barrel_mesh(g: GeometryConfig) -> TriMesh:
    """Open barrel, for viewing only (the deck uses the primitive xcylinder)."""
    n_theta = _n_around(g, g.radius_m)
    n_x = max(1, math.ceil(g.length_m / (2 * g.mesh_resolution_m)))
    return _cylinder("barrel", g.radius_m, 0.0, g.length_m, n_theta, n_x, caps=False)


def inlet_wall_mesh(g: GeometryConfig) -> TriMesh:
    """Inlet end disc, for viewing only (the deck uses the primitive plane x = 0)."""
    n_theta = _n_around(g, g.radius_m)
    theta = np.linspace(0, 2 * np.pi, n_theta, endpoint=False)
    pts = np.concatenate(
        [[[0.0, 0.0, 0.0]], np.stack([0 * theta, g.radius_m * np.cos(theta), g.radius_m * np.sin(theta)], 1)]
    )
    tris = np.array([[0, 1 + k, 1 + (k + 1) % n_theta] for k in range(n_theta)], dtype=np.int64)
    return TriMesh("inlet_wall", pts, tris)


# --------------------------------------------------------------------------------------
# checks
# --------------------------------------------------------------------------------------


def triangle_angles_deg(mesh: TriMesh) -> np.ndarray:
    """(m, 3) interior angles of each triangle [deg]; nan for a degenerate triangle."""
    c = mesh.corners
    out = np.empty((len(c), 3))
    for k in range(3):
        u = c[:, (k + 1) % 3] - c[:, k]
        v = c[:, (k + 2) % 3] - c[:, k]
        nu, nv = np.linalg.norm(u, axis=1), np.linalg.norm(v, axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            cosang = np.einsum("ij,ij->i", u, v) / (nu * nv)
        out[:, k] = np.degrees(np.arccos(np.clip(cosang, -1, 1)))
    return out


def edge_neighbour_counts(mesh: TriMesh, decimals: int = COORD_DECIMALS) -> np.ndarray:
    """Number of other triangles sharing an edge with each triangle (coordinates matched,
    as LIGGGHTS matches nodes by position, not by index)."""
    keys = [tuple(p) for p in np.round(mesh.points, decimals)]
    node_id: dict[tuple, int] = {}
    ids = np.array([node_id.setdefault(k, len(node_id)) for k in keys])
    tri = ids[mesh.triangles]
    edges: dict[tuple[int, int], list[int]] = {}
    for t, (a, b, c) in enumerate(tri):
        for e in ((a, b), (b, c), (c, a)):
            edges.setdefault(tuple(sorted(e)), []).append(t)
    counts = np.zeros(len(tri), dtype=int)
    for members in edges.values():
        for t in members:
            counts[t] += len(members) - 1
    return counts


def check_mesh(mesh: TriMesh, box: Box) -> None:
    """LIGGGHTS' mesh/surface checks, raised as :class:`GeometryError` before anything is written."""
    if len(mesh.triangles) == 0:
        raise GeometryError(f"mesh {mesh.name!r} has no triangles")
    if not np.all(np.isfinite(mesh.points)):
        raise GeometryError(f"mesh {mesh.name!r} has non-finite coordinates")
    c = mesh.corners
    area = 0.5 * np.linalg.norm(np.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0]), axis=1)
    scale = max(float(np.ptp(mesh.points, axis=0).max()), 1e-12)
    bad = np.flatnonzero(area <= 1e-12 * scale**2)
    if bad.size:
        raise GeometryError(
            f"mesh {mesh.name!r}: triangle {bad[0]} is degenerate (area {area[bad[0]]:.3g} m2; must be > 0)"
        )
    angles = triangle_angles_deg(mesh)
    worst = int(np.nanargmin(angles.min(axis=1)))
    if angles[worst].min() < MIN_TRIANGLE_ANGLE_DEG:
        raise GeometryError(
            f"mesh {mesh.name!r}: triangle {worst} has an angle of {angles[worst].min():.3g} deg; "
            f"LIGGGHTS needs every angle >= {MIN_TRIANGLE_ANGLE_DEG} deg (refine mesh_resolution_m or change the dimension)"
        )
    rounded = np.round(c, COORD_DECIMALS)
    keys = {}
    for t, tri in enumerate(rounded):
        key = tuple(sorted(map(tuple, tri)))
        if key in keys:
            raise GeometryError(f"mesh {mesh.name!r}: triangles {keys[key]} and {t} are duplicates")
        keys[key] = t
    counts = edge_neighbour_counts(mesh)
    if counts.max() > MAX_EDGE_NEIGHBOURS:
        t = int(counts.argmax())
        raise GeometryError(
            f"mesh {mesh.name!r}: triangle {t} has {counts[t]} edge neighbours; LIGGGHTS allows at most {MAX_EDGE_NEIGHBOURS}"
        )
    inside = box.contains(mesh.points)
    if not inside.all():
        p = mesh.points[np.flatnonzero(~inside)[0]]
        raise GeometryError(
            f"mesh {mesh.name!r}: node {tuple(np.round(p, 6))} m lies outside the simulation box "
            f"x [{box.xmin}, {box.xmax}], y [{box.ymin}, {box.ymax}], z [{box.zmin}, {box.zmax}] m"
        )


def _overlap(a0: float, a1: float, b0: float, b1: float) -> bool:
    return a0 < b1 and b0 < a1


def _box_radial_range(b: Box) -> tuple[float, float]:
    """Smallest and largest distance from the x axis of any point of the box [m]."""
    ny = 0.0 if b.ymin <= 0 <= b.ymax else min(abs(b.ymin), abs(b.ymax))
    nz = 0.0 if b.zmin <= 0 <= b.zmax else min(abs(b.zmin), abs(b.zmax))
    fy, fz = max(abs(b.ymin), abs(b.ymax)), max(abs(b.zmin), abs(b.zmax))
    return math.hypot(ny, nz), math.hypot(fy, fz)


def validate_geometry(config: DemConfig) -> None:
    """Every geometric precondition of a runnable deck; raises :class:`GeometryError`."""
    g, p = config.geometry, config.particles
    for name in (
        "length_m",
        "diameter_m",
        "shaft_radius_m",
        "blade_chord_m",
        "blade_tip_clearance_m",
        "weir_height_m",
        "outlet_length_m",
        "mesh_resolution_m",
        "box_margin_m",
        "discharge_offset_m",
    ):
        value = getattr(g, name)
        if not value > 0:
            raise GeometryError(f"geometry.{name} = {value}: must be > 0")
    if g.blade_tip_clearance_m <= p.max_diameter_m:
        raise GeometryError(
            f"geometry.blade_tip_clearance_m = {g.blade_tip_clearance_m} m: blade tips must clear the wall by more "
            f"than the largest particle diameter {p.max_diameter_m:.4g} m (valid: > {p.max_diameter_m:.4g} and < "
            f"{g.radius_m - g.shaft_radius_m:.4g} m), or particles are pinched between blade and wall"
        )
    half_t = blade_tangential_half_extent_m(g)
    if g.blade_tip_radius_m <= math.hypot(g.shaft_radius_m, half_t):
        raise GeometryError(
            f"geometry.blade_tip_clearance_m = {g.blade_tip_clearance_m} m leaves no paddle outside the shaft: "
            f"tip radius {g.blade_tip_radius_m:.4g} m must exceed {math.hypot(g.shaft_radius_m, half_t):.4g} m"
        )
    half = blade_axial_half_extent_m(g)
    st = blade_stations(g)
    if st[0].x_m - half <= 0 or st[-1].x_m + half >= g.length_m:
        raise GeometryError(
            f"blades span x [{st[0].x_m - half:.4g}, {st[-1].x_m + half:.4g}] m; they must stay inside (0, "
            f"{g.length_m}) m (move first_blade_x_m / last_blade_x_m or shorten blade_chord_m)"
        )
    if g.discharge_offset_m >= g.outlet_length_m:
        raise GeometryError(
            f"geometry.discharge_offset_m = {g.discharge_offset_m} m must be below outlet_length_m = {g.outlet_length_m} m"
        )
    if g.weir_height_m >= g.radius_m - g.shaft_radius_m:
        raise GeometryError(
            f"geometry.weir_height_m = {g.weir_height_m} m: must be in (0, {g.radius_m - g.shaft_radius_m:.4g}) m "
            "(the crest must stay below the shaft)"
        )
    box = simulation_box(g)
    for comp, zone in feed_zones(g).items():
        r_near, r_far = _box_radial_range(zone)
        if r_far >= g.radius_m - p.max_diameter_m / 2:
            raise GeometryError(
                f"feed zone {comp} reaches {r_far:.4g} m from the axis; it must stay inside the barrel "
                f"(< {g.radius_m - p.max_diameter_m / 2:.4g} m): reduce feed_y_outer_m, feed_height_m or feed_depth_m"
            )
        if zone.zmax - zone.zmin <= p.max_diameter_m or zone.xmax - zone.xmin <= p.max_diameter_m:
            raise GeometryError(
                f"feed zone {comp} ({zone.xmax - zone.xmin:.4g} x {zone.ymax - zone.ymin:.4g} x "
                f"{zone.zmax - zone.zmin:.4g} m) must be larger than the largest particle ({p.max_diameter_m:.4g} m)"
            )
        if zone.xmin < p.max_diameter_m / 2:
            raise GeometryError(
                f"geometry.feed_x_min_m = {g.feed_x_min_m} m: must be >= half the largest particle "
                f"({p.max_diameter_m / 2:.4g} m) so inserted particles do not overlap the inlet wall"
            )
        for k, (x0, x1, _r0, r1) in enumerate(swept_volumes(g)):
            if _overlap(zone.xmin, zone.xmax, x0, x1) and r_near < r1:
                raise GeometryError(
                    f"feed zone {comp} (x [{zone.xmin}, {zone.xmax}] m) intersects the volume swept by blade station "
                    f"{k} (x [{x0:.4g}, {x1:.4g}] m, r < {r1:.4g} m): feed_x_max_m must be < {x0:.4g} m"
                )
    for mesh in deck_meshes(g).values():
        check_mesh(mesh, box)


#: Meshes the deck loads, by file stem (``meshes/<name>.stl``).
DECK_MESHES = ("impeller", "weir", "discharge")


def deck_meshes(g: GeometryConfig) -> dict[str, TriMesh]:
    return {"impeller": impeller_mesh(g), "weir": weir_mesh(g), "discharge": discharge_mesh(g)}


def build_geometry(config: DemConfig) -> Geometry:
    """Validate, then assemble the blender. Raises :class:`GeometryError` on any violation."""
    validate_geometry(config)
    g = config.geometry
    return Geometry(
        meshes=deck_meshes(g),
        box=simulation_box(g),
        feed_zones=feed_zones(g),
        stations=blade_stations(g),
        discharge_x_m=discharge_x_m(g),
        view_meshes={"barrel": barrel_mesh(g), "inlet_wall": inlet_wall_mesh(g)},
    )


# --------------------------------------------------------------------------------------
# STL
# --------------------------------------------------------------------------------------


def _meshio():
    """meshio, imported where a mesh is written or read: the geometry's boxes (the feed
    zones a PBM configuration needs) should not pay its import."""
    import meshio

    return meshio


def stl_text(mesh: TriMesh) -> str:
    """ASCII STL of a mesh, written by meshio (in memory)."""
    buf = io.StringIO()
    _meshio().stl.write(buf, mesh.to_meshio(), binary=False)
    return buf.getvalue()


def write_stl(mesh: TriMesh, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    _meshio().write(path, mesh.to_meshio(), file_format="stl", binary=False)
    return path


def read_stl(path: str | Path, name: str | None = None) -> TriMesh:
    """Read an STL (meshio merges coincident nodes)."""
    with warnings.catch_warnings():
        # meshio sniffs ASCII-vs-binary by reading the first bytes of an ASCII file as a
        # uint32 triangle count and multiplying it: a harmless overflow warning.
        warnings.simplefilter("ignore", RuntimeWarning)
        m = _meshio().read(path, file_format="stl")
    return TriMesh(name or Path(path).stem, np.asarray(m.points, float), np.asarray(m.get_cells_type("triangle")))
