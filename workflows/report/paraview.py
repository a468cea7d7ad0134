"""ParaView-ready output: particle snapshots, impeller at the snapshot's angle, compartment
fields over time. Each series is a set of VTK XML files plus a ``.pvd`` collection that
ParaView opens as one time-dependent dataset.

Written through pyvista, an optional dependency (``pip install 'pbmdem[render]'``): it is
imported when a file is made, and its absence is a one-line :class:`MissingExtraError`.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING
from xml.sax.saxutils import quoteattr

import numpy as np

from coupling.errors import MissingExtraError
from coupling.tables import VelocityTable

if TYPE_CHECKING:
    import pyvista as pv


def _pyvista():
    """The pyvista module, or MissingExtraError naming the extra that installs it."""
    try:
        import pyvista
    except ModuleNotFoundError as exc:
        if exc.name != "pyvista":  # pyvista is there, something it needs is not: say that
            raise
        raise MissingExtraError("pyvista", "render", "the ParaView output") from None
    return pyvista


def write_pvd(path: Path, entries: Iterable[tuple[float, str]]) -> Path:
    """A ParaView collection file listing (time [s], file name relative to ``path``)."""
    rows = "\n".join(
        f'    <DataSet timestep="{t:.9g}" group="" part="0" file={quoteattr(name)}/>' for t, name in entries
    )
    path.write_text(
        '<?xml version="1.0"?>\n<VTKFile type="Collection" version="0.1">\n  <Collection>\n'
        f"{rows}\n  </Collection>\n</VTKFile>\n"
    )
    return path


def compartment_grid(table: VelocityTable, k: int, height_m: float) -> pv.RectilinearGrid:
    """Window ``k`` of ``table`` as a one-cell-high rectilinear grid with cell data.

    Compartments span the full height of the vessel, hence one cell in z."""
    pv = _pyvista()
    half = height_m / 2
    grid = pv.RectilinearGrid(table.x_edges, table.y_edges, np.array([-half, half]))

    # VTK numbers cells with x fastest: (i, j) -> i + NX * j, i.e. Fortran order of (NX, NY).
    def cells(values: np.ndarray) -> np.ndarray:
        return np.asarray(values).ravel(order="F")

    count_a, count_b = table.count_A[k], table.count_B[k]
    total = count_a + count_b
    fraction_a = np.divide(count_a, total, out=np.full_like(total, np.nan), where=total > 0)
    for name, values in (
        ("count_A", count_a),
        ("count_B", count_b),
        ("fraction_A", fraction_a),
        ("vx_pos", table.vx_pos[k]),
        ("vx_neg", table.vx_neg[k]),
        ("vy_pos", table.vy_pos[k]),
        ("vy_neg", table.vy_neg[k]),
        ("n_samples", table.n_samples[k]),
        ("valid", table.valid[k].astype(np.uint8)),
    ):
        grid.cell_data[name] = cells(values)
    return grid


def write_compartment_series(table: VelocityTable, out_dir: Path, height_m: float) -> Path:
    """One ``.vtr`` per velocity window plus ``compartments.pvd``; returns the collection."""
    _pyvista()  # before the directory: without pyvista, say so and write nothing
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    entries = []
    for k, t in enumerate(table.t):
        name = f"compartments_{k:04d}.vtr"
        compartment_grid(table, k, height_m).save(out_dir / name)
        entries.append((float(t), name))
    return write_pvd(out_dir / "compartments.pvd", entries)


def particle_cloud(ids, types, positions, velocities, radii) -> pv.PolyData:
    """Particles as points with id, type, velocity (vector), speed and radius."""
    cloud = _pyvista().PolyData(np.asarray(positions, dtype=float).reshape(-1, 3))
    cloud.point_data["id"] = np.asarray(ids, dtype=np.int64)
    cloud.point_data["type"] = np.asarray(types, dtype=np.int32)
    velocities = np.asarray(velocities, dtype=float).reshape(-1, 3)
    cloud.point_data["velocity"] = velocities
    cloud.point_data["speed"] = np.linalg.norm(velocities, axis=1)
    cloud.point_data["radius"] = np.asarray(radii, dtype=float)
    return cloud


def impeller_at(impeller: pv.PolyData, rpm: float, time_s: float) -> pv.PolyData:
    """The impeller turned to its angle at ``time_s``: the deck's ``move/mesh rotate`` turns it
    about +x (right-hand rule) from angle 0 at t = 0."""
    angle_deg = (360.0 * rpm / 60.0 * time_s) % 360.0
    return impeller.rotate_x(angle_deg, point=(0.0, 0.0, 0.0), inplace=False)


def _polydata(mesh) -> pv.PolyData:
    """A ``dem.geometry.TriMesh`` as pyvista surface."""
    faces = np.hstack([np.full((len(mesh.triangles), 1), 3), mesh.triangles]).ravel()
    return _pyvista().PolyData(np.asarray(mesh.points, dtype=float), faces)


def write_particle_series(dem_config, run_dir: Path, out_dir: Path, max_snapshots: int = 60) -> list[Path]:
    """Particle snapshots of a run (at most ``max_snapshots``, evenly spread) as ``.vtp`` with
    the impeller at each snapshot's angle and the weir; one ``.pvd`` collection per series.

    Returns the collection files. Reads the dumps of ``run_dir`` through ``dem.dumps``."""
    _pyvista()  # before any file: without pyvista, say so and write nothing
    from dem import deck
    from dem.dumps import dump_paths, iter_snapshots
    from dem.geometry import build_geometry

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = dump_paths(str(Path(run_dir) / deck.DUMP_GLOB))
    chosen = [paths[i] for i in np.unique(np.linspace(0, len(paths) - 1, min(max_snapshots, len(paths))).astype(int))]
    geometry = build_geometry(dem_config)
    impeller = _polydata(geometry.meshes["impeller"])
    _polydata(geometry.meshes["weir"]).save(out_dir / "weir.vtp")
    dt = dem_config.timestep_s
    rpm = dem_config.operation.impeller_rpm
    particles, impellers = [], []
    k = 0
    for snap in iter_snapshots(chosen, columns=deck.DUMP_COLUMNS):
        if snap.n == 0:  # before the first insertion: VTK has no empty point clouds
            continue
        t = snap.time_s(dt)
        positions = np.column_stack([snap["x"], snap["y"], snap["z"]])
        velocities = np.column_stack([snap["vx"], snap["vy"], snap["vz"]])
        name = f"particles_{k:04d}.vtp"
        particle_cloud(snap["id"], snap["type"], positions, velocities, snap["radius"]).save(out_dir / name)
        particles.append((t, name))
        name = f"impeller_{k:04d}.vtp"
        impeller_at(impeller, rpm, t).save(out_dir / name)
        impellers.append((t, name))
        k += 1
    return [write_pvd(out_dir / "particles.pvd", particles), write_pvd(out_dir / "impeller.pvd", impellers)]
