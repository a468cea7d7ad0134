"""ParaView output: compartment cells carry the value of the right (i, j), series are readable."""

import numpy as np
import pytest

from coupling.tables import make_table
from workflows.report.paraview import impeller_at, particle_cloud, write_compartment_series

# the `render` extra, which `make setup` installs; without it see tests/test_extras.py
pv = pytest.importorskip("pyvista", reason="pyvista is optional: pip install 'pbmdem[render]'")


def test_compartment_cells_match_their_ij(tmp_path):
    nx, ny = 4, 3
    x_edges, y_edges = np.linspace(0, 0.33, nx + 1), np.linspace(-0.05, 0.05, ny + 1)
    ii, jj = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    vx = 0.01 * np.stack([10 * ii + jj, 100 + 10 * ii + jj]).astype(float)  # value encodes (k, i, j) [m/s]
    table = make_table([0.0, 5.0], x_edges, y_edges, vx, 0, 0, 0, count_A=1, count_B=3)
    pvd = write_compartment_series(table, tmp_path, height_m=0.1)
    assert "compartments_0001.vtr" in pvd.read_text()
    grid = pv.read(tmp_path / "compartments_0001.vtr")
    centres = grid.cell_centers().points
    for cell, (x, y, _) in enumerate(centres):
        i, j = np.searchsorted(x_edges, x) - 1, np.searchsorted(y_edges, y) - 1
        assert grid.cell_data["vx_pos"][cell] == pytest.approx(0.01 * (100 + 10 * i + j))
    np.testing.assert_allclose(grid.cell_data["fraction_A"], 0.25)


def test_particles_and_impeller_rotation(tmp_path):
    cloud = particle_cloud([1, 2], [1, 2], [[0, 0, 0], [1, 0, 0]], [[0, 3, 4], [0, 0, 0]], [1e-3, 2e-3])
    cloud.save(tmp_path / "p.vtp")
    back = pv.read(tmp_path / "p.vtp")
    np.testing.assert_allclose(back.point_data["speed"], [5, 0])
    blade = pv.PolyData(np.array([[0.1, 0.0, 0.04]]))
    # A quarter turn at 250 rpm takes 0.06 s; right-hand rotation about +x maps +z to -y.
    turned = impeller_at(blade, rpm=250, time_s=0.06)
    np.testing.assert_allclose(turned.points[0], [0.1, -0.04, 0.0], atol=1e-12)
