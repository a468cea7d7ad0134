"""A PNG of the assembled blender, rendered without a display.

pyvista/VTK render off screen first (``pv.OFF_SCREEN = True``). VTK 9.3+ wheels fall back
to EGL/OSMesa when there is no X server (measured here: works on this headless Debian machine,
after a "bad X server connection" warning on stderr). If that fails, or the image comes back
blank, ``pyvista.start_xvfb()`` is tried when an ``Xvfb`` binary exists, and last matplotlib's
Agg backend draws the triangles with ``mpl_toolkits.mplot3d``. The first backend that
produces a non-blank image wins; :func:`render_geometry` returns which one it was. The
pyvista attempt (with its Xvfb retry) runs in a child process, because a VTK that cannot
create any context may abort instead of raising. pyvista is optional (``pip install
'pbmdem[render]'``): without it ``"auto"`` goes straight to matplotlib.
"""

from __future__ import annotations

import importlib.util
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from coupling.errors import MissingExtraError
from dem.config import DemConfig
from dem.geometry import Geometry, TriMesh, build_geometry

COLOURS = {
    "impeller": "#4a6fa5",
    "weir": "#c0392b",
    "discharge": "#f1c40f",
    "barrel": "#bbbbbb",
    "inlet_wall": "#888888",
    "feed_A": "#27ae60",
    "feed_B": "#8e44ad",
}
OPACITY = {"barrel": 0.15, "inlet_wall": 0.3, "discharge": 0.35}


def _image_is_blank(img: np.ndarray) -> bool:
    return img is None or img.size == 0 or float(np.asarray(img, float).std()) < 1.0


def _feed_box_mesh(name: str, box) -> TriMesh:
    c = box.corners  # ordered x-major, then y, then z
    faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    tris = [[a, b, cc] for a, b, cc, d in faces] + [[a, cc, d] for a, b, cc, d in faces]
    return TriMesh(name, c, np.array(tris))


def _all_meshes(geo: Geometry) -> dict[str, TriMesh]:
    out = dict(geo.view_meshes)
    out.update(geo.meshes)
    for comp, box in geo.feed_zones.items():
        out[f"feed_{comp}"] = _feed_box_mesh(f"feed_{comp}", box)
    return out


def pyvista_installed() -> bool:
    """Whether pyvista can be imported, found without importing it (the child process does)."""
    return importlib.util.find_spec("pyvista") is not None


def _render_pyvista(meshes: dict[str, TriMesh], path: Path, size: tuple[int, int]) -> None:
    import pyvista as pv

    pv.OFF_SCREEN = True
    plotter = pv.Plotter(off_screen=True, window_size=list(size))
    try:
        for name, m in meshes.items():
            faces = np.hstack([np.full((len(m.triangles), 1), 3), m.triangles]).ravel()
            plotter.add_mesh(
                pv.PolyData(m.points, faces),
                color=COLOURS.get(name, "#777777"),
                opacity=OPACITY.get(name, 1.0),
                show_edges=name == "impeller",
            )
        plotter.set_background("white")
        plotter.camera_position = [(0.45, -0.35, 0.30), (0.165, 0.0, 0.0), (0.0, 0.0, 1.0)]
        img = plotter.screenshot(str(path), return_img=True)
    finally:
        plotter.close()
    if _image_is_blank(img):
        raise RuntimeError("pyvista produced a blank image")


def _render_matplotlib(meshes: dict[str, TriMesh], path: Path, size: tuple[int, int]) -> None:
    from matplotlib.figure import Figure
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    fig = Figure(figsize=(size[0] / 100, size[1] / 100), dpi=100)
    ax = fig.add_subplot(projection="3d")
    for name, m in meshes.items():
        ax.add_collection3d(
            Poly3DCollection(
                m.corners, facecolor=COLOURS.get(name, "#777777"), alpha=OPACITY.get(name, 0.9), edgecolor="none"
            )
        )
    pts = np.concatenate([m.points for m in meshes.values()])
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    ax.set_xlim(lo[0], hi[0]), ax.set_ylim(lo[1], hi[1]), ax.set_zlim(lo[2], hi[2])
    ax.set_box_aspect(hi - lo)
    ax.set_xlabel("x [m]"), ax.set_ylabel("y [m]"), ax.set_zlabel("z [m]")
    fig.savefig(path)


def _render_pyvista_isolated(meshes: dict[str, TriMesh], path: Path, size: tuple[int, int]) -> None:
    """Run the pyvista renderer in a child process: a VTK without a usable offscreen
    context can abort the process (not raise), which must not take the caller down."""
    with tempfile.TemporaryDirectory() as tmp:
        npz = Path(tmp) / "meshes.npz"
        arrays = {}
        for name, m in meshes.items():
            arrays[f"{name}__points"] = m.points
            arrays[f"{name}__triangles"] = m.triangles
        np.savez(npz, **arrays)
        proc = subprocess.run(
            [sys.executable, "-m", "dem.render", str(npz), str(path), str(size[0]), str(size[1])],
            capture_output=True,
            text=True,
            timeout=300,
        )
        if proc.returncode != 0 or not path.is_file():
            raise RuntimeError(f"pyvista renderer failed (exit {proc.returncode}): {proc.stderr[-500:]}")


def _load_npz(npz: Path) -> dict[str, TriMesh]:
    data = np.load(npz)
    names = sorted({k.rsplit("__", 1)[0] for k in data.files})
    return {n: TriMesh(n, data[f"{n}__points"], data[f"{n}__triangles"]) for n in names}


def render_geometry(
    config: DemConfig, path: str | Path, size: tuple[int, int] = (1200, 700), backend: str = "auto"
) -> str:
    """Render the blender (impeller, weir, discharge face, barrel, feed zones) to a PNG.

    ``backend`` is ``"auto"``, ``"pyvista"`` or ``"matplotlib"``; returns the one used.
    pyvista runs in a child process (see :func:`_render_pyvista_isolated`); ``"auto"``
    skips it when it is not installed, ``"pyvista"`` then raises :class:`MissingExtraError`.
    """
    if backend == "pyvista" and not pyvista_installed():
        raise MissingExtraError("pyvista", "render", "the pyvista renderer")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    meshes = _all_meshes(build_geometry(config))
    if backend in ("auto", "pyvista") and pyvista_installed():
        try:
            _render_pyvista_isolated(meshes, path, size)
            return "pyvista"
        except Exception:
            if backend == "pyvista":
                raise
    _render_matplotlib(meshes, path, size)
    return "matplotlib"


if __name__ == "__main__":  # child process of _render_pyvista_isolated
    _npz, _png, _w, _h = sys.argv[1:5]
    _meshes = _load_npz(Path(_npz))
    try:
        _render_pyvista(_meshes, Path(_png), (int(_w), int(_h)))
    except Exception:
        if not shutil.which("Xvfb"):
            raise
        import pyvista as pv

        pv.start_xvfb()
        _render_pyvista(_meshes, Path(_png), (int(_w), int(_h)))
