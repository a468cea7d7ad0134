"""pyvista is an optional extra (``pip install 'pbmdem[render]'``): without it every module
imports and no VTK is loaded, the geometry picture is drawn by matplotlib, asking for the
pyvista picture is one line naming the extra, and the ParaView files are written all the
same (through meshio, a required dependency).

Absence is simulated with ``sys.modules["pyvista"] = None``, which makes ``import pyvista``
raise ImportError (CI installs the extra, so the pyvista paths are tested elsewhere)."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from coupling.errors import MissingExtraError
from coupling.tables import make_table
from workflows.config import load_preset

ROOT = Path(__file__).resolve().parents[1]

EVERY_MODULE_WITHOUT_PYVISTA = """
import importlib, pkgutil, sys
sys.modules["pyvista"] = None
for package in ("coupling", "dem", "pbm", "workflows"):
    for info in pkgutil.walk_packages(importlib.import_module(package).__path__, package + "."):
        if not info.name.endswith("__main__"):
            importlib.import_module(info.name)
assert not [name for name in sys.modules if name.startswith("vtk")]
"""


@pytest.fixture
def no_pyvista(monkeypatch):
    monkeypatch.setitem(sys.modules, "pyvista", None)


def test_every_module_imports_without_pyvista():
    # a fresh interpreter: in this one the modules are imported already
    proc = subprocess.run(
        [sys.executable, "-c", EVERY_MODULE_WITHOUT_PYVISTA], cwd=ROOT, capture_output=True, text=True
    )
    assert proc.returncode == 0, proc.stderr[-2000:]


def test_the_picture_falls_back_to_matplotlib(no_pyvista, tmp_path):
    from matplotlib.image import imread

    from dem.render import render_geometry

    path = tmp_path / "geometry.png"
    assert render_geometry(load_preset("smoke").dem, path, size=(400, 300)) == "matplotlib"
    assert float(np.asarray(imread(path)[..., :3]).std()) > 0.01


def test_asking_for_the_pyvista_picture_names_the_extra(no_pyvista, tmp_path):
    from dem.render import render_geometry

    with pytest.raises(
        MissingExtraError, match=r"^the pyvista renderer needs pyvista.*pip install 'pbmdem\[render\]'$"
    ):
        render_geometry(load_preset("smoke").dem, tmp_path / "geometry.png", backend="pyvista")
    assert not (tmp_path / "geometry.png").exists()


def _table():
    edges = np.linspace(0, 0.3, 4), np.linspace(-0.05, 0.05, 3)
    return make_table([0.0, 5.0], *edges, np.zeros((2, 3, 2)), 0, 0, 0, count_A=1, count_B=1)


def _run_with_two_dumps(run_dir: Path, config) -> None:
    """A run directory holding two dumps of three particles, as LIGGGHTS writes them."""
    from dem import deck
    from dem.dumps import format_snapshot

    (run_dir / "dumps").mkdir(parents=True)
    rows = np.array(
        [
            [1, 1, 0.01, 0.01, 0, 0.1, 0, 0, 0.003],
            [2, 2, 0.2, -0.01, 0, 0.1, 0, 0, 0.003],
            [3, 1, 0.1, 0, 0.01, 0, 0, 0, 0.003],
        ]
    )
    for step in (1000, 2000):
        (run_dir / "dumps" / f"dump.{step}.txt").write_bytes(format_snapshot(step, deck.DUMP_COLUMNS, rows))


def test_compare_writes_the_paraview_files_without_pyvista(no_pyvista, tmp_path):
    from types import SimpleNamespace

    import meshio

    from dem.geometry import build_geometry
    from workflows.products.compare import write_paraview
    from workflows.report.paraview import COMPARTMENT_FIELDS

    config = load_preset("smoke")
    run_dir = tmp_path / "run"
    _run_with_two_dumps(run_dir, config)
    lines = []
    dem = SimpleNamespace(table=_table(), provenance={"run_dir": str(run_dir)})
    write_paraview(config, dem, tmp_path / "paraview", lines.append)
    assert lines == []
    out = tmp_path / "paraview"
    assert {p.name for p in out.glob("*.pvd")} == {"compartments.pvd", "particles.pvd", "impeller.pvd"}
    for k in (0, 1):
        grid = meshio.read(out / f"compartments_{k:04d}.vtu")
        assert len(grid.points) == 4 * 3 * 2 and grid.cells[0].type == "hexahedron" and len(grid.cells[0].data) == 6
        assert sorted(grid.cell_data) == sorted(COMPARTMENT_FIELDS)
        cloud = meshio.read(out / f"particles_{k:04d}.vtu")
        assert len(cloud.points) == 3 and len(cloud.cells[0].data) == 3
        assert sorted(cloud.point_data) == ["id", "radius", "speed", "type", "velocity"]
    meshes = build_geometry(config.dem).meshes
    impeller, weir = meshio.read(out / "impeller_0001.vtu"), meshio.read(out / "weir.vtu")
    assert len(impeller.points) == len(meshes["impeller"].points) and impeller.cells[0].type == "triangle"
    assert len(impeller.cells[0].data) == len(meshes["impeller"].triangles)
    assert len(weir.cells[0].data) == len(meshes["weir"].triangles)
    assert "pyvista" not in sys.modules or sys.modules["pyvista"] is None


def test_dem_deck_png_without_pyvista(no_pyvista, tmp_path, capsys):
    from workflows.cli.main import main

    assert main(["dem", "deck", "--preset", "smoke", "--out", str(tmp_path / "run"), "--png"]) in (0, None)
    assert next((tmp_path / "run").rglob("geometry.png")).stat().st_size > 1000
