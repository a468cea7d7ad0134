"""ParaView output: compartment cells carry the value of the right (i, j), series are readable
by meshio and, when the ``render`` extra is installed, by VTK itself."""

import re

import meshio
import numpy as np
import pytest

from coupling.tables import make_table
from workflows.report.paraview import (
    COMPARTMENT_FIELDS,
    impeller_at,
    particle_cloud,
    save,
    write_compartment_series,
)

NX, NY = 4, 3
X_EDGES, Y_EDGES = np.linspace(0, 0.33, NX + 1), np.linspace(-0.05, 0.05, NY + 1)


def _table():
    ii, jj = np.meshgrid(np.arange(NX), np.arange(NY), indexing="ij")
    vx = 0.01 * np.stack([10 * ii + jj, 100 + 10 * ii + jj]).astype(float)  # value encodes (k, i, j) [m/s]
    return make_table([0.0, 5.0], X_EDGES, Y_EDGES, vx, 0, 0, 0, count_A=1, count_B=3)


def _ij(centre):
    return np.searchsorted(X_EDGES, centre[0]) - 1, np.searchsorted(Y_EDGES, centre[1]) - 1


def test_compartment_cells_match_their_ij(tmp_path):
    pvd = write_compartment_series(_table(), tmp_path, height_m=0.1)
    listed = re.findall(r'timestep="([^"]+)" group="" part="0" file="([^"]+)"', pvd.read_text())
    assert listed == [("0", "compartments_0000.vtu"), ("5", "compartments_0001.vtu")]
    grid = meshio.read(tmp_path / "compartments_0001.vtu")
    (block,) = grid.cells
    assert block.type == "hexahedron" and block.data.shape == (NX * NY, 8)
    assert len(grid.points) == (NX + 1) * (NY + 1) * 2
    assert sorted(grid.cell_data) == sorted(COMPARTMENT_FIELDS)
    np.testing.assert_allclose(np.unique(grid.points[:, 2]), [-0.05, 0.05])  # the vessel's height, one cell
    for cell, corners in enumerate(block.data):
        i, j = _ij(grid.points[corners].mean(axis=0))
        assert grid.cell_data["vx_pos"][0][cell] == pytest.approx(0.01 * (100 + 10 * i + j))
    np.testing.assert_allclose(grid.cell_data["fraction_A"][0], 0.25)


def test_particles_and_impeller_rotation(tmp_path):
    cloud = particle_cloud([1, 2], [1, 2], [[0, 0, 0], [1, 0, 0]], [[0, 3, 4], [0, 0, 0]], [1e-3, 2e-3])
    back = meshio.read(save(cloud, tmp_path / "p.vtu"))
    np.testing.assert_allclose(back.point_data["speed"], [5, 0])
    np.testing.assert_array_equal(back.point_data["id"], [1, 2])
    assert back.point_data["velocity"].shape == (2, 3) and back.cells[0].type == "vertex"
    blade = meshio.Mesh(np.array([[0.1, 0.0, 0.04]]), [("vertex", np.array([[0]]))])
    # A quarter turn at 250 rpm takes 0.06 s; right-hand rotation about +x maps +z to -y.
    turned = impeller_at(blade, rpm=250, time_s=0.06)
    np.testing.assert_allclose(turned.points[0], [0.1, -0.04, 0.0], atol=1e-12)


def test_vtk_reads_the_same_cells(tmp_path):
    pv = pytest.importorskip("pyvista", reason="pyvista is optional: pip install 'pbmdem[render]'")
    write_compartment_series(_table(), tmp_path, height_m=0.1)
    grid = pv.read(tmp_path / "compartments_0001.vtu")
    # VTK's own geometry of the hexahedra: the corners in its order, every volume positive
    volumes = grid.compute_cell_sizes()["Volume"]
    np.testing.assert_allclose(volumes, np.diff(X_EDGES)[0] * np.diff(Y_EDGES)[0] * 0.1)
    for cell, centre in enumerate(grid.cell_centers().points):
        i, j = _ij(centre)
        assert grid.cell_data["vx_pos"][cell] == pytest.approx(0.01 * (100 + 10 * i + j))
