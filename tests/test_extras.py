"""pyvista is an optional extra (``pip install 'pbmdem[render]'``): without it every module
imports, the geometry picture is drawn by matplotlib, the ParaView writers refuse in one line
naming the extra, and ``compare`` leaves the ParaView files out with a line in its log.

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
    edges = np.linspace(0, 0.3, 3), np.linspace(-0.05, 0.05, 2)
    return make_table([0.0], *edges, np.zeros((1, 2, 1)), 0, 0, 0, count_A=1, count_B=1)


def test_the_paraview_writers_name_the_extra(no_pyvista, tmp_path):
    from workflows.report.paraview import particle_cloud, write_compartment_series

    with pytest.raises(MissingExtraError) as caught:
        write_compartment_series(_table(), tmp_path / "paraview", height_m=0.1)
    assert (
        str(caught.value) == "the ParaView output needs pyvista, which is not installed: pip install 'pbmdem[render]'"
    )
    assert not (tmp_path / "paraview").exists()
    with pytest.raises(MissingExtraError, match="pbmdem\\[render\\]"):
        particle_cloud([1], [1], [[0, 0, 0]], [[0, 0, 0]], [1e-3])


def test_compare_leaves_the_paraview_files_out_and_says_why(no_pyvista, tmp_path):
    from types import SimpleNamespace

    from workflows.products.compare import write_paraview

    lines = []
    dem = SimpleNamespace(table=_table(), provenance={})
    write_paraview(load_preset("smoke"), dem, tmp_path / "paraview", lines.append)
    assert lines == [
        "ParaView files not written: the ParaView output needs pyvista, which is not installed: "
        "pip install 'pbmdem[render]'"
    ]
    assert not (tmp_path / "paraview").exists()


def test_dem_deck_png_without_pyvista(no_pyvista, tmp_path, capsys):
    from workflows.cli.main import main

    assert main(["dem", "deck", "--preset", "smoke", "--out", str(tmp_path / "run"), "--png"]) in (0, None)
    assert next((tmp_path / "run").rglob("geometry.png")).stat().st_size > 1000
