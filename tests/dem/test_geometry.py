"""Blender geometry: LIGGGHTS' mesh checks, clearances, feed zones, STL round trip, rendering."""

import math

import numpy as np
import pytest

from coupling.errors import ConfigError, GeometryError
from dem.config import DemConfig, GeometryConfig
from dem.geometry import (
    MIN_TRIANGLE_ANGLE_DEG,
    TriMesh,
    blade_axial_half_extent_m,
    blade_meshes,
    blade_stations,
    build_geometry,
    check_mesh,
    edge_neighbour_counts,
    read_stl,
    simulation_box,
    stl_text,
    triangle_angles_deg,
    write_stl,
)
from workflows.config import config_from_dict, load_preset

PRESETS = ["paper", "reduced", "smoke"]


@pytest.mark.parametrize("name", PRESETS)
def test_preset_meshes_pass_liggghts_checks(name):
    geo = build_geometry(load_preset(name).dem)
    for mesh in geo.meshes.values():
        check_mesh(mesh, geo.box)  # raises on failure
        assert triangle_angles_deg(mesh).min() >= MIN_TRIANGLE_ANGLE_DEG
        assert edge_neighbour_counts(mesh).max() <= 5


@pytest.mark.parametrize("name", PRESETS)
def test_blade_tips_clear_the_wall_by_more_than_the_largest_particle(name):
    dem = load_preset(name).dem
    blades = blade_meshes(dem.geometry)
    r = np.hypot(blades.points[:, 1], blades.points[:, 2])
    clearance = dem.geometry.radius_m - r.max()
    assert clearance == pytest.approx(dem.geometry.blade_tip_clearance_m, abs=1e-8)
    assert clearance > dem.particles.max_diameter_m


def test_blades_alternate_and_sit_between_feed_and_weir():
    g = GeometryConfig()
    st = blade_stations(g)
    assert [s.orientation for s in st[:4]] == ["F", "B", "F", "B"]
    half = blade_axial_half_extent_m(g)
    assert st[0].x_m - half > g.feed_x_max_m
    assert st[-1].x_m + half < g.length_m
    blades = blade_meshes(g)
    assert blades.points[:, 0].min() == pytest.approx(st[0].x_m - half, abs=1e-9)


def test_forward_blade_leading_face_pushes_towards_outlet():
    # One F paddle at azimuth 0 (pointing +y): it moves along +z under positive rotation
    # about +x; the normal of its leading face must have a +x component.
    g = GeometryConfig(
        blade_stations=1, first_blade_x_m=0.1, last_blade_x_m=0.1, blades_per_station=1, blade_pattern="F"
    )
    c = blade_meshes(g).corners[0]
    n = np.cross(c[1] - c[0], c[2] - c[0])
    n = n if n[2] > 0 else -n  # leading face: the side moving into the powder (+z here)
    assert n[0] > 0


def test_every_node_inside_the_box_and_box_contains_the_barrel():
    dem = load_preset("smoke").dem
    geo = build_geometry(dem)
    r = dem.geometry.radius_m
    assert geo.box.ymin < -r and geo.box.ymax > r and geo.box.zmin < -r and geo.box.zmax > r
    assert geo.box.xmin < 0 and geo.box.xmax > geo.discharge_x_m
    assert geo.discharge_x_m > dem.geometry.length_m


def test_stl_round_trip(tmp_path):
    geo = build_geometry(load_preset("smoke").dem)
    for name, mesh in geo.meshes.items():
        path = write_stl(mesh, tmp_path / f"{name}.stl")
        assert path.read_text().startswith("solid")
        back = read_stl(path)
        assert len(back.triangles) == len(mesh.triangles)
        np.testing.assert_allclose(
            np.sort(back.corners.reshape(-1, 3), axis=0), np.sort(mesh.corners.reshape(-1, 3), axis=0), atol=1e-9
        )
        check_mesh(back, geo.box)
        assert stl_text(mesh) == path.read_text()


def _tri(*pts):
    return TriMesh("t", np.array(pts, float), np.arange(len(pts)).reshape(-1, 3))


def test_mesh_checks_reject_bad_triangles():
    box = simulation_box(GeometryConfig())
    good = [(0.1, 0, 0), (0.11, 0, 0), (0.1, 0.01, 0)]
    check_mesh(_tri(*good), box)
    with pytest.raises(GeometryError, match="degenerate"):
        check_mesh(_tri((0.1, 0, 0), (0.11, 0, 0), (0.12, 0, 0)), box)
    with pytest.raises(GeometryError, match="angle of .* deg"):
        check_mesh(_tri((0.1, 0, 0), (0.2, 0, 0), (0.1, 0.0005, 0)), box)
    with pytest.raises(GeometryError, match="duplicates"):
        check_mesh(_tri(*good, *good[::-1]), box)
    with pytest.raises(GeometryError, match="outside the simulation box"):
        check_mesh(_tri((0.1, 0, 0), (0.11, 0, 0), (0.1, 0.2, 0)), box)
    # a "book" of 7 triangles sharing one edge: 6 neighbours each
    pts, tris = [(0.1, 0, 0), (0.12, 0, 0)], []
    for k in range(7):
        a = 2 * math.pi * k / 7
        pts.append((0.11, 0.01 * math.cos(a), 0.01 * math.sin(a)))
        tris.append([0, 1, 2 + k])
    with pytest.raises(GeometryError, match="7|6 edge neighbours"):
        check_mesh(TriMesh("book", np.array(pts), np.array(tris)), box)


def _geometry_error(**geometry):
    """Build a config bypassing pydantic's own checks, so the geometry layer is what refuses."""
    g = GeometryConfig.model_construct(**{**GeometryConfig().model_dump(), **geometry})
    dem = DemConfig.model_construct(**{**dict(DemConfig()), "geometry": g})
    with pytest.raises(GeometryError) as info:
        build_geometry(dem)
    return str(info.value)


@pytest.mark.parametrize(
    "geometry, fragment",
    [
        ({"length_m": 0.0}, "length_m = 0.0"),
        ({"shaft_radius_m": -0.01}, "shaft_radius_m = -0.01"),
        ({"blade_chord_m": 0.0}, "blade_chord_m = 0.0"),
        ({"blade_tip_clearance_m": 0.0001}, "blade_tip_clearance_m = 0.0001"),
        ({"blade_tip_clearance_m": 0.045}, "no paddle outside the shaft"),
        ({"weir_height_m": 0.045}, "weir_height_m = 0.045"),
        ({"feed_x_max_m": 0.05}, "intersects the volume swept by blade station 0"),
        ({"feed_height_m": 0.045}, "inside the barrel"),
        ({"last_blade_x_m": 0.325}, "must stay inside"),
    ],
)
def test_geometry_errors_name_the_value(geometry, fragment):
    assert fragment in _geometry_error(**geometry)


def test_config_layer_refuses_blades_touching_the_wall():
    with pytest.raises(ConfigError, match="pinched"):
        config_from_dict({"dem": {"geometry": {"blade_tip_clearance_m": 0.002}}})


def test_render_png_is_not_blank(tmp_path):
    from matplotlib.image import imread

    from dem.render import render_geometry

    dem = load_preset("smoke").dem
    for backend in ("auto", "matplotlib"):
        path = tmp_path / f"geo_{backend}.png"
        used = render_geometry(dem, path, size=(400, 300), backend=backend)
        assert used in ("pyvista", "matplotlib")
        img = imread(path)
        assert img.shape[0] > 100 and img.shape[1] > 100
        assert float(np.asarray(img[..., :3]).std()) > 0.01
