"""ParaView-ready output: particle snapshots, impeller at the snapshot's angle, compartment
fields over time. Each series is a set of VTK XML unstructured-grid files (``.vtu``) plus a
``.pvd`` collection that ParaView opens as one time-dependent dataset.

Written through meshio, a required dependency that needs no VTK: the compartments are
hexahedra (one per compartment, one cell high), the surfaces triangles, the particles
points with one vertex cell each. pyvista (the optional ``render`` extra) is needed only
for the 3D picture of the geometry (:mod:`dem.render`), not for these files.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from xml.sax.saxutils import quoteattr

import meshio
import numpy as np

from coupling.tables import VelocityTable

#: the compartment fields, one value per cell (units: counts [particles], velocities [m/s])
COMPARTMENT_FIELDS = ("count_A", "count_B", "fraction_A", "vx_pos", "vx_neg", "vy_pos", "vy_neg", "n_samples", "valid")


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


def save(mesh: meshio.Mesh, path: Path) -> Path:
    """``mesh`` as a VTK XML unstructured grid (binary, zlib-compressed)."""
    meshio.write(path, mesh, file_format="vtu")
    return path


def compartment_grid(table: VelocityTable, k: int, height_m: float) -> meshio.Mesh:
    """Window ``k`` of ``table`` as NX * NY hexahedra spanning z in [-height/2, height/2]
    [m], with the fields of :data:`COMPARTMENT_FIELDS` as cell data.

    Compartments span the full height of the vessel, hence one cell in z. Cells are
    numbered with x fastest, (i, j) -> i + NX * j, as VTK numbers a rectilinear grid's."""
    nx, ny = table.nx, table.ny
    half = height_m / 2
    # points with x fastest, then y, then z: point (i, j, l) -> i + (NX+1) * (j + (NY+1) * l)
    xs, ys, zs = np.meshgrid(table.x_edges, table.y_edges, [-half, half], indexing="ij")
    points = np.column_stack([xs.ravel(order="F"), ys.ravel(order="F"), zs.ravel(order="F")])
    i, j = (index.ravel(order="F") for index in np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij"))

    def corner(di: np.ndarray | int, dj: np.ndarray | int, level: int) -> np.ndarray:
        return (i + di) + (nx + 1) * ((j + dj) + (ny + 1) * level)

    # VTK's hexahedron: the lower face counter-clockwise seen from +z, then the upper one
    hexahedra = np.column_stack(
        [corner(di, dj, level) for level in (0, 1) for di, dj in ((0, 0), (1, 0), (1, 1), (0, 1))]
    )

    def cells(values: np.ndarray) -> np.ndarray:
        return np.asarray(values).ravel(order="F")

    count_a, count_b = table.count_A[k], table.count_B[k]
    total = count_a + count_b
    fraction_a = np.divide(count_a, total, out=np.full_like(total, np.nan), where=total > 0)
    fields = {
        "count_A": count_a,
        "count_B": count_b,
        "fraction_A": fraction_a,
        "vx_pos": table.vx_pos[k],
        "vx_neg": table.vx_neg[k],
        "vy_pos": table.vy_pos[k],
        "vy_neg": table.vy_neg[k],
        "n_samples": table.n_samples[k],
        "valid": table.valid[k].astype(np.uint8),
    }
    return meshio.Mesh(
        points, [("hexahedron", hexahedra)], cell_data={name: [cells(fields[name])] for name in COMPARTMENT_FIELDS}
    )


def write_compartment_series(table: VelocityTable, out_dir: Path, height_m: float) -> Path:
    """One ``.vtu`` per velocity window plus ``compartments.pvd``; returns the collection."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    entries = []
    for k, t in enumerate(table.t):
        name = f"compartments_{k:04d}.vtu"
        save(compartment_grid(table, k, height_m), out_dir / name)
        entries.append((float(t), name))
    return write_pvd(out_dir / "compartments.pvd", entries)


def particle_cloud(ids, types, positions, velocities, radii) -> meshio.Mesh:
    """Particles as points [m], one vertex cell each (what ParaView draws), with id, type,
    velocity (vector) [m/s], speed [m/s] and radius [m]."""
    points = np.asarray(positions, dtype=float).reshape(-1, 3)
    velocities = np.asarray(velocities, dtype=float).reshape(-1, 3)
    return meshio.Mesh(
        points,
        [("vertex", np.arange(len(points)).reshape(-1, 1))],
        point_data={
            "id": np.asarray(ids, dtype=np.int64),
            "type": np.asarray(types, dtype=np.int32),
            "velocity": velocities,
            "speed": np.linalg.norm(velocities, axis=1),
            "radius": np.asarray(radii, dtype=float),
        },
    )


def impeller_at(impeller: meshio.Mesh, rpm: float, time_s: float) -> meshio.Mesh:
    """The impeller turned to its angle at ``time_s``: the deck's ``move/mesh rotate`` turns it
    about +x (right-hand rule) from angle 0 at t = 0."""
    angle = np.deg2rad((360.0 * rpm / 60.0 * time_s) % 360.0)
    c, s = np.cos(angle), np.sin(angle)
    rotation = np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    return meshio.Mesh(impeller.points @ rotation.T, impeller.cells, point_data=impeller.point_data)


def write_particle_series(dem_config, run_dir: Path, out_dir: Path, max_snapshots: int = 60) -> list[Path]:
    """Particle snapshots of a run (at most ``max_snapshots``, evenly spread) as ``.vtu`` with
    the impeller at each snapshot's angle and the weir; one ``.pvd`` collection per series.

    Returns the collection files. Reads the dumps of ``run_dir`` through ``dem.dumps``."""
    from dem import deck
    from dem.dumps import dump_paths, iter_snapshots
    from dem.geometry import build_geometry

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = dump_paths(str(Path(run_dir) / deck.DUMP_GLOB))
    chosen = [paths[i] for i in np.unique(np.linspace(0, len(paths) - 1, min(max_snapshots, len(paths))).astype(int))]
    geometry = build_geometry(dem_config)
    impeller = geometry.meshes["impeller"].to_meshio()
    save(geometry.meshes["weir"].to_meshio(), out_dir / "weir.vtu")
    dt = dem_config.timestep_s
    rpm = dem_config.operation.impeller_rpm
    particles, impellers = [], []
    k = 0
    for snap in iter_snapshots(chosen, columns=deck.DUMP_COLUMNS):
        if snap.n == 0:  # before the first insertion: nothing to draw
            continue
        t = snap.time_s(dt)
        positions = np.column_stack([snap["x"], snap["y"], snap["z"]])
        velocities = np.column_stack([snap["vx"], snap["vy"], snap["vz"]])
        name = f"particles_{k:04d}.vtu"
        save(particle_cloud(snap["id"], snap["type"], positions, velocities, snap["radius"]), out_dir / name)
        particles.append((t, name))
        name = f"impeller_{k:04d}.vtu"
        save(impeller_at(impeller, rpm, t), out_dir / name)
        impellers.append((t, name))
        k += 1
    return [write_pvd(out_dir / "particles.pvd", particles), write_pvd(out_dir / "impeller.pvd", impellers)]
