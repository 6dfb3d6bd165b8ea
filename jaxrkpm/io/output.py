"""Mesh output for ParaView / PyVista: a solution as a ``.vtu`` unstructured grid (written with
meshio) and a run as a ``.pvd`` time series of such files.

A meshfree body has no mesh, so the cells here are for viewing only (:func:`body_cells`):
the body's own simplices when it came from a mesh (``Body.cells``), the lattice's quads /
hexahedra for a grid body, else a Delaunay triangulation of the particles keeping the
simplices whose centroid lies in the body (polygon bodies). The points are the particles'
reference positions (or the deformed ones, ``deformed=True``); the point data are the RK
fields evaluated at the particles (:func:`point_fields`): displacement, Cauchy stress, its
von Mises value, det F, the particle volumes and one 0/1 mask per essential set. Vectors and
tensors of 2D bodies are padded with zeros to 3 components / 3x3 (VTK's vectors are 3D, so
ParaView's *Warp By Vector* works on ``displacement``).

Why ``.pvd`` for series (not meshio's XDMF ``TimeSeriesWriter``): every frame stays a
self-contained ``.vtu`` that meshio, ParaView and PyVista open on its own; frames may carry
deformed points (XDMF time series share one geometry); and the index is a few lines of XML
with no HDF5 dependency.
"""
from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from pathlib import Path

import meshio
import numpy as np
from scipy.spatial import Delaunay

from ..discretise.mesh import simplex_volumes

# meshio cell type of the viewing cells, by (dimension, vertices per cell)
CELL_TYPES = {(2, 3): "triangle", (2, 4): "quad", (3, 4): "tetra", (3, 8): "hexahedron"}
# outward faces of a cell, by meshio type, for the VTK vertex order (positive orientation)
FACES = {
    "tetra": [(0, 2, 1), (0, 1, 3), (1, 2, 3), (0, 3, 2)],
    "hexahedron": [(0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (2, 3, 7, 6), (0, 4, 7, 3), (1, 2, 6, 5)],
}


# --------------------------------------------------------------------------- cells
def body_cells(body) -> tuple[str, np.ndarray]:
    """Viewing cells of a body: (meshio cell type, (C, k) particle indices), positively oriented.

    ``body.cells`` (mesh bodies: triangles / tetrahedra) when set; quads / hexahedra for a
    full lattice (``Body.grid``); else a Delaunay triangulation of the particles, keeping the
    non-degenerate simplices whose centroid lies inside the body (``Body.polygon``,
    ``Body.points``: the concave parts of a polygon stay empty)."""
    X, d = np.asarray(body.X, float), body.dim
    if body.cells is not None:
        cells = np.asarray(body.cells)
        if cells.ndim != 2 or cells.shape[1] != d + 1:
            raise ValueError(f"body.cells must be ({d + 1})-vertex simplices, shape (C, {d + 1}), "
                             f"got {cells.shape}")
        if cells.size and (cells.min() < 0 or cells.max() >= body.n):
            raise ValueError(f"body.cells index particles outside 0..{body.n - 1}")
        return CELL_TYPES[d, d + 1], _oriented(X, cells.astype(np.int64))
    lattice = _lattice_cells(X, body.spacing)
    if lattice is not None:
        return CELL_TYPES[d, 2 ** d], lattice
    simplices = Delaunay(X).simplices.astype(np.int64)
    size = np.abs(simplex_volumes(X, simplices))
    keep = (size > 1e-9 * body.spacing ** d) & body.contains(X[simplices].mean(axis=1))
    return CELL_TYPES[d, d + 1], _oriented(X, simplices[keep])


def _lattice_cells(X, h):
    """Quads (2D) / hexahedra (3D) of particles on a full lattice of spacing h, in VTK vertex
    order; None when X is not one (any particle order is accepted)."""
    I = np.rint((X - X.min(axis=0)) / h)
    if not np.allclose(X - X.min(axis=0), I * h, atol=1e-9 * h):
        return None
    I = I.astype(np.int64)
    shape = tuple(int(s) for s in I.max(axis=0) + 1)
    if int(np.prod(shape)) != len(X):
        return None
    at = np.full(shape, -1, dtype=np.int64)          # lattice index -> particle
    at[tuple(I.T)] = np.arange(len(X))
    if (at < 0).any():                               # a duplicate left a lattice site empty
        return None
    corners = [(0, 0), (1, 0), (1, 1), (0, 1)]      # counter-clockwise, then the top face
    if X.shape[1] == 3:
        corners = [c + (0,) for c in corners] + [c + (1,) for c in corners]
    n = [s - 1 for s in shape]
    cells = [at[tuple(slice(o, o + m) for o, m in zip(c, n))].ravel() for c in corners]
    return np.stack(cells, axis=1)


def _oriented(X, simplices):
    """Simplices with two vertices swapped where their orientation is negative."""
    out = simplices.copy()
    neg = simplex_volumes(X, simplices) < 0
    out[neg, 1], out[neg, 2] = simplices[neg, 2], simplices[neg, 1]
    return out


def surface_faces(cell_type: str, cells) -> np.ndarray:
    """Boundary faces of 3D cells (faces that belong to one cell only), oriented outward:
    (M, 3) triangles of tetrahedra or (M, 4) quads of hexahedra."""
    if cell_type not in FACES:
        raise ValueError(f"surface_faces takes 3D cells {list(FACES)}, got {cell_type!r}")
    cells = np.asarray(cells)
    faces = np.concatenate([cells[:, list(f)] for f in FACES[cell_type]])
    _, inverse, counts = np.unique(np.sort(faces, axis=1), axis=0, return_inverse=True,
                                   return_counts=True)
    return faces[counts[inverse.ravel()] == 1]


# --------------------------------------------------------------------------- fields
def von_mises(s33) -> np.ndarray:
    """von Mises equivalent stress of (N, 3, 3) tensors: sqrt(3/2 dev:dev)."""
    s33 = np.asarray(s33, float)
    dev = s33 - np.trace(s33, axis1=1, axis2=2)[:, None, None] * np.eye(3) / 3.0
    return np.sqrt(1.5 * np.einsum("nij,nij->n", dev, dev))


def _pad(a, shape):
    out = np.zeros((a.shape[0],) + shape)
    out[(slice(None),) + tuple(slice(0, s) for s in a.shape[1:])] = a
    return out


def point_fields(model, sol) -> dict:
    """The point data of a solution at the particles: ``displacement`` (N, 3),
    ``cauchy_stress`` (N, 9) (row-major 3x3), ``von_mises`` (N,) of it, ``det_F`` (N,) (area
    ratio in 2D), ``volume`` (N,) and ``set_<name>`` (N,) 0/1 for each essential set. A 2D
    stress is padded with zeros out of plane (von Mises of the plane-stress state)."""
    X = np.asarray(model.body.X)
    n = len(X)
    u = np.asarray(model.particle_displacements(sol))
    sigma = _pad(np.asarray(model.stress(sol, X, kind="cauchy")), (3, 3))
    F = np.asarray(model.deformation_gradient(sol, X))
    fields = {"displacement": _pad(u, (3,)), "cauchy_stress": sigma.reshape(n, 9),
              "von_mises": von_mises(sigma), "det_F": np.linalg.det(F),
              "volume": np.asarray(model.body.volumes, float)}
    for name in model.set_names:
        mask = np.zeros(n, np.uint8)
        mask[model.set_indices(name)] = 1
        fields[f"set_{name}"] = mask
    return fields


# --------------------------------------------------------------------------- writers
def _check_suffix(path, suffix: str, what: str) -> Path:
    path = Path(os.fspath(path))
    if path.suffix != suffix:
        raise ValueError(f"path {str(path)!r} must end with {suffix!r} ({what})")
    return path


def write_vtu(path, points, cells, point_data: dict | None = None) -> Path:
    """Write points (N, 2|3), cells ``(meshio type, (C, k) indices)`` and point data arrays
    with N rows ((N,), (N, k); (N, a, b) is flattened row-major) to the ``.vtu`` ``path``
    (binary, zlib). Returns the path."""
    path = _check_suffix(path, ".vtu", "a VTK XML unstructured grid")
    P = np.asarray(points, float)
    if P.ndim != 2 or P.shape[1] not in (2, 3):
        raise ValueError(f"points must have shape (N, 2) or (N, 3), got {P.shape}")
    n = len(P)
    kind, conn = cells
    conn = np.asarray(conn)
    if kind not in CELL_TYPES.values() or conn.ndim != 2 or \
            conn.shape[1] != {"triangle": 3, "quad": 4, "tetra": 4, "hexahedron": 8}[kind]:
        raise ValueError(f"cells must be (type, (C, k) indices) with type in "
                         f"{list(CELL_TYPES.values())} and k its vertex count, got {kind!r}, {conn.shape}")
    if conn.size and (conn.min() < 0 or conn.max() >= n):
        raise ValueError(f"cells index points outside 0..{n - 1}")
    data = {}
    for name, a in (point_data or {}).items():
        a = np.asarray(a)
        if a.ndim == 0 or a.shape[0] != n:
            raise ValueError(f"point data {name!r} has shape {a.shape}; it needs one row per point ({n})")
        data[name] = a.reshape(n, -1) if a.ndim > 2 else a
    meshio.write(path, meshio.Mesh(_pad(P, (3,)), [(kind, conn)], point_data=data), file_format="vtu")
    return path


def write_solution(path, model, sol, *, deformed: bool = False) -> Path:
    """Write a solution to the ``.vtu`` ``path``: the viewing cells of the model's body
    (:func:`body_cells`), its particles at their reference positions (``deformed=True``: at
    X + u) and :func:`point_fields`. Returns the path."""
    path = _check_suffix(path, ".vtu", "a VTK XML unstructured grid")
    fields = point_fields(model, sol)
    X = np.asarray(model.body.X, float)
    points = X + fields["displacement"][:, :X.shape[1]] if deformed else X
    return write_vtu(path, points, body_cells(model.body), fields)


def write_series(path, model, solutions, times, *, deformed: bool = False) -> Path:
    """Write solutions as a ParaView time series: ``path`` (``.pvd``, the index) and one
    ``.vtu`` per frame in the folder next to it named after it (``run.pvd`` ->
    ``run/frame_0000.vtu``, ...; the index refers to them by relative paths). ``times``
    (strictly increasing, one per solution) are the frames' time values, e.g. control steps.
    Returns the index path."""
    path = _check_suffix(path, ".pvd", "a ParaView collection of .vtu frames")
    solutions = list(solutions)
    t = np.asarray(times, float)
    if t.shape != (len(solutions),):
        raise ValueError(f"times must have one value per solution ({len(solutions)}), got shape {t.shape}")
    if not solutions:
        raise ValueError("solutions is empty: a series needs at least one frame")
    if not (np.all(np.isfinite(t)) and np.all(np.diff(t) > 0)):
        raise ValueError(f"times must be finite and strictly increasing, got {t.tolist()}")
    folder = path.with_suffix("")
    folder.mkdir(parents=True, exist_ok=True)
    root = ET.Element("VTKFile", type="Collection", version="0.1", byte_order="LittleEndian")
    collection = ET.SubElement(root, "Collection")
    for k, (sol, tk) in enumerate(zip(solutions, t)):
        frame = write_solution(folder / f"frame_{k:04d}.vtu", model, sol, deformed=deformed)
        ET.SubElement(collection, "DataSet", timestep=repr(float(tk)), group="", part="0",
                      file=frame.relative_to(path.parent).as_posix())
    ET.indent(root)
    ET.ElementTree(root).write(path, xml_declaration=True, encoding="utf-8")
    return path


def read_series(path) -> list[tuple[float, Path]]:
    """The frames of a ``.pvd`` index: [(time, absolute .vtu path)] in file order."""
    path = _check_suffix(path, ".pvd", "a ParaView collection of .vtu frames")
    root = ET.parse(path).getroot()
    if root.get("type") != "Collection":
        raise ValueError(f"{path}: not a VTK collection file (type={root.get('type')!r})")
    return [(float(ds.get("timestep")), path.parent / ds.get("file"))
            for ds in root.iter("DataSet")]
