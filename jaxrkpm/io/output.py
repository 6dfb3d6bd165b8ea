"""Mesh output for ParaView / PyVista: a solution as a ``.vtu`` unstructured grid (written with
meshio) and a run as a ``.pvd`` time series of such files.

A meshfree body has no mesh, so the cells here are for viewing only (:func:`body_cells`):
the body's own simplices when it came from a mesh (``Body.cells``), the lattice's quads /
hexahedra for a grid body, else a Delaunay triangulation of the particles keeping the
simplices whose centroid lies in the body (polygon bodies). The points are the particles'
reference positions (or the deformed ones, ``deformed=True``); the point data are the RK
fields evaluated at the particles (:func:`point_fields`): displacement, Cauchy stress, its
von Mises value, det F, the particle volumes, one 0/1 mask per essential set and, per rigid
tool (``jaxrkpm.Contact``), its contact state (:func:`contact_fields`). Vectors and
tensors of 2D bodies are padded with zeros to 3 components / 3x3 (VTK's vectors are 3D, so
ParaView's *Warp By Vector* works on ``displacement``).

Every ``.vtu`` of a solution carries the solve's outcome as VTK field data (``solve_status``:
the ``jaxrkpm.Status`` code, ``converged``: 1 or 0, ``t``: the fraction of the increment
reached, ``load``): a failed solve's last converged state is written, and says so. Fields that
are not finite are refused (a NaN field views as a blank body). A series is validated whole
before its first frame is written and lands atomically (:func:`write_series`).

Why ``.pvd`` for series (not meshio's XDMF ``TimeSeriesWriter``): every frame stays a
self-contained ``.vtu`` that meshio, ParaView and PyVista open on its own; frames may carry
deformed points (XDMF time series share one geometry); and the index is a few lines of XML
with no HDF5 dependency.
"""
from __future__ import annotations

import os
import shutil
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path, PurePosixPath

import meshio
import numpy as np
from scipy.spatial import Delaunay

from ..discretise.mesh import simplex_volumes
from ..mechanics.contact import ContactTerm
from ..solvers.results import Status

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


def point_fields(model, sol, params=None) -> dict:
    """The point data of a solution at the particles: ``displacement`` (N, 3),
    ``cauchy_stress`` (N, 9) (row-major 3x3), ``von_mises`` (N,) of it, ``det_F`` (N,) (area
    ratio in 2D), ``volume`` (N,), ``set_<name>`` (N,) 0/1 for each essential set and, where
    there are essential sets, ``reaction`` (N, 3), the force the sets exert on each particle
    (``Model.reactions``, under ``params``, the solve's). A 2D
    stress is padded with zeros out of plane (von Mises of the plane-stress state)."""
    X = np.asarray(model.body.X)
    n = len(X)
    u = np.asarray(model.particle_displacements(sol))
    sigma = _pad(np.asarray(model.stress(sol, X, kind="cauchy")), (3, 3))
    F = np.asarray(model.deformation_gradient(sol, X))
    with np.errstate(invalid="ignore"):     # a non-finite F: the writer names the field and refuses it
        det_F = np.linalg.det(F)
    fields = {"displacement": _pad(u, (3,)), "cauchy_stress": sigma.reshape(n, 9),
              "von_mises": von_mises(sigma), "det_F": det_F,
              "volume": np.asarray(model.body.volumes, float)}
    for name in model.set_names:
        mask = np.zeros(n, np.uint8)
        mask[model.set_indices(name)] = 1
        fields[f"set_{name}"] = mask
    if model.set_names:   # a roller's reaction lies along its held directions only
        R = np.zeros((n, model.dim))
        np.add.at(R, np.concatenate([model.set_indices(k) for k in model.set_names]),
                  np.asarray(model.reactions(sol, params)))
        fields["reaction"] = _pad(R, (3,))
    return fields


def contact_fields(model, sol, params=None) -> tuple[dict, dict]:
    """(point data, field data) of every rigid tool of the model (``jaxrkpm.Contact`` terms)
    at the solution ``sol`` solved with ``params`` (the tools' poses). Each contact point
    (a boundary quadrature point) is given to its nearest particle, so that a particle shows
    the contact on its share of the boundary: ``contact_<tool>_force`` (N, 3) the sum of its
    points' forces (their sum over the particles is the tool's force on the body),
    ``contact_<tool>_pressure`` (N,) their weighted mean pressure, ``contact_<tool>_active``
    (N,) 0/1 any of them within the barrier's range, and ``contact_<tool>_gap`` (N,) the
    particle's own deformed position's signed distance from the tool. Field data per tool:
    ``contact_<tool>_resultant``, ``_normal``, ``_tangential`` (3,) its force on the body and
    that split, ``_active`` (the count of active contact points) and ``_min_gap`` (the
    smallest contact point gap: negative would be penetration)."""
    problem = model.problem(params)
    tools = [t for t in problem.terms if isinstance(t, ContactTerm)]
    point, field = {}, {}
    if not tools:
        return point, field
    X = np.asarray(model.body.X, float)
    n = len(X)
    d = model.coefficients(sol)
    load = np.asarray(sol.load, float)
    x = X + np.asarray(model.particle_displacements(sol))
    for t in tools:
        res = t.results(d, load)
        owner = np.asarray(model.body.nearest(np.asarray(t.X)), np.int64).reshape(-1)
        w = np.asarray(t.w)
        force = np.zeros((n, X.shape[1]))
        np.add.at(force, owner, np.asarray(res.point_force))
        wsum = np.bincount(owner, w, n)
        pw = np.bincount(owner, w * np.asarray(res.pressure), n)
        key = f"contact_{t.name}"
        point[f"{key}_force"] = _pad(force, (3,))
        point[f"{key}_pressure"] = np.divide(pw, wsum, out=np.zeros(n), where=wsum > 0)
        point[f"{key}_active"] = (np.bincount(owner, np.asarray(res.active, float), n) > 0).astype(np.uint8)
        point[f"{key}_gap"] = np.asarray(t.gaps(x, load))
        for part, value in (("resultant", res.force), ("normal", res.normal), ("tangential", res.tangential)):
            field[f"{key}_{part}"] = _pad(np.asarray(value, float)[None], (3,))[0]
        field[f"{key}_active"] = np.array([int(np.sum(res.active))], np.int32)
        field[f"{key}_min_gap"] = np.array([float(res.min_gap)])
    return point, field


def solve_record(sol) -> dict:
    """The field data of a solution's file: ``solve_status`` (the ``jaxrkpm.Status`` code),
    ``converged`` (1: an equilibrium was reached, 0: the solve failed and this is its last
    converged state), ``t`` (the fraction of the increment reached) and ``load``."""
    code = int(np.asarray(sol.status))
    converged = Status.of(code).equilibrium
    return {"solve_status": np.array([code], np.int32), "converged": np.array([int(converged)], np.uint8),
            "t": np.array([float(np.asarray(sol.t))]), "load": np.array([float(np.asarray(sol.load))])}


def _checked(model, sol, what: str = "solution", params=None):
    """(point fields, field data) of one solve of ``model`` (with ``params``: the rigid tools'
    poses); a ValueError for a Solution of another model or a batch, or for fields that are
    not finite (named, with a particle)."""
    if np.ndim(getattr(sol, "status", None)) != 0:
        raise ValueError(f"{what} is a batch of {np.size(sol.status)} solves (status shape "
                         f"{np.shape(sol.status)}): write one at a time (index the batch)")
    model.check_solution(sol, what)
    fields = point_fields(model, sol, params)
    touch, record = contact_fields(model, sol, params)
    fields.update(touch)
    bad = {k: np.flatnonzero(~np.all(np.isfinite(np.asarray(v, float).reshape(len(v), -1)), axis=1))
           for k, v in fields.items()}
    bad = {k: v for k, v in bad.items() if len(v)}
    if bad:
        k, idx = next(iter(bad.items()))
        raise ValueError(f"{what} has non-finite fields ({', '.join(f'{f}: {len(i)} particles' for f, i in bad.items())}; "
                         f"e.g. {k} at particle {int(idx[0])}): nothing written (status "
                         f"{int(np.asarray(sol.status))}; a failed solve keeps its last converged state, "
                         "which is finite: this state was not made by a solve of this model)")
    return fields, {**solve_record(sol), **record}


# --------------------------------------------------------------------------- writers
def _check_suffix(path, suffix: str, what: str) -> Path:
    path = Path(os.fspath(path))
    if path.suffix != suffix:
        raise ValueError(f"path {str(path)!r} must end with {suffix!r} ({what})")
    return path


def write_vtu(path, points, cells, point_data: dict | None = None, field_data: dict | None = None) -> Path:
    """Write points (N, 2|3), cells ``(meshio type, (C, k) indices)`` and point data arrays
    with N rows ((N,), (N, k); (N, a, b) is flattened row-major) to the ``.vtu`` ``path``
    (binary, zlib); ``field_data``: name -> a small numeric array, written as the grid's VTK
    FieldData. Returns the path."""
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
    data = _point_data(point_data or {}, n)
    meshio.write(path, meshio.Mesh(_pad(P, (3,)), [(kind, conn)], point_data=data), file_format="vtu")
    if field_data:
        _add_field_data(path, field_data)
    return path


def _point_data(point_data: dict, n: int) -> dict:
    """The arrays with one row per point, a tensor's rows flattened row-major."""
    data = {}
    for name, a in point_data.items():
        a = np.asarray(a)
        if a.ndim == 0 or a.shape[0] != n:
            raise ValueError(f"point data {name!r} has shape {a.shape}; it needs one row per point ({n})")
        data[name] = a.reshape(n, -1) if a.ndim > 2 else a
    return data


VTK_TYPES = {"i": "Int32", "u": "UInt8", "f": "Float64"}


def _add_field_data(path: Path, field_data: dict):
    """Insert a VTK ``<FieldData>`` block (ASCII arrays) into the .vtu at ``path`` (meshio's
    VTU writer does not write field data; its reader and VTK's read it)."""
    tree = ET.parse(path)
    grid = tree.getroot().find("UnstructuredGrid")
    block = ET.Element("FieldData")
    for name, value in field_data.items():
        a = np.atleast_1d(np.asarray(value))
        kind = VTK_TYPES[a.dtype.kind]
        array = ET.SubElement(block, "DataArray", type=kind, Name=name, NumberOfTuples=str(a.size), format="ascii")
        array.text = " ".join(repr(float(x)) if kind == "Float64" else str(int(x)) for x in a.ravel())
    grid.insert(0, block)
    tree.write(path, xml_declaration=True, encoding="utf-8")


def write_solution(path, model, sol, *, deformed: bool = False, params=None) -> Path:
    """Write a solution to the ``.vtu`` ``path``: the viewing cells of the model's body
    (:func:`body_cells`), its particles at their reference positions (``deformed=True``: at
    X + u), :func:`point_fields`, the rigid tools' contact (:func:`contact_fields`, at the
    poses in ``params``, the solve's), and the solve's outcome as field data
    (:func:`solve_record`: a failed solve's last converged state is marked ``converged`` 0).
    A Solution of another model, a batch, or fields that are not finite raise a ValueError
    and write nothing. Returns the path."""
    path = _check_suffix(path, ".vtu", "a VTK XML unstructured grid")
    fields, record = _checked(model, sol, params=params)
    return _write_checked(path, model, fields, record, deformed)


def _write_checked(path, model, fields, record, deformed):
    X = np.asarray(model.body.X, float)
    points = X + fields["displacement"][:, :X.shape[1]] if deformed else X
    return write_vtu(path, points, body_cells(model.body), fields, record)


def write_series(path, model, solutions, times, *, deformed: bool = False, params=None) -> Path:
    """Write solutions as a ParaView time series: ``path`` (``.pvd``, the index) and one
    ``.vtu`` per frame in the folder next to it named after it (``run.pvd`` ->
    ``run/frame_0000.vtu``, ...; the index refers to them by relative paths). ``times``
    (strictly increasing, one per solution) are the frames' time values, e.g. control steps.
    ``params``: the solves' parameters (the rigid tools' poses), one dict for all frames or a
    list of one per solution.

    Every solution is checked (of this model, finite fields) before anything is written, and
    the series is written into a temporary folder beside ``path`` that then replaces the old
    folder and index: a bad frame leaves an earlier series at ``path`` as it was, never an
    index mixing old and new frames. Returns the index path."""
    path = _check_suffix(path, ".pvd", "a ParaView collection of .vtu frames")
    solutions = list(solutions)
    t = _series_times(times, len(solutions))
    params = _per_frame(params, len(solutions))
    frames = [_checked(model, sol, f"solutions[{k}]", p) for k, (sol, p) in enumerate(zip(solutions, params))]
    folder = path.with_suffix("")
    if path.is_dir() or (folder.exists() and not folder.is_dir()):
        raise ValueError(f"cannot write the series {str(path)!r}: {str(path if path.is_dir() else folder)!r} "
                         "is in the way (a folder for the index, or a file for the frames' folder)")
    path.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{path.stem}.", dir=path.parent))
    try:
        _stage_series(staging, folder.name, model, frames, t, deformed)
        old = staging / "old"
        if folder.exists():
            folder.rename(old)                       # the earlier frames, out of the way
        (staging / "frames").rename(folder)
        os.replace(staging / "index.pvd", path)      # the index last: it names only new frames
    except BaseException:
        if (staging / "old").exists() and not folder.exists():
            (staging / "old").rename(folder)         # put the earlier series back
        raise
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return path


def _series_times(times, n: int) -> np.ndarray:
    """The frames' times as floats, one per solution (at least one), finite and increasing."""
    t = np.asarray(times, float)
    if t.shape != (n,):
        raise ValueError(f"times must have one value per solution ({n}), got shape {t.shape}")
    if not n:
        raise ValueError("solutions is empty: a series needs at least one frame")
    if not (np.all(np.isfinite(t)) and np.all(np.diff(t) > 0)):
        raise ValueError(f"times must be finite and strictly increasing, got {t.tolist()}")
    return t


def _per_frame(params, n: int) -> list:
    """``params`` as one entry per frame: a list of n as it is, anything else repeated."""
    if not isinstance(params, (list, tuple)):
        return [params] * n
    if len(params) != n:
        raise ValueError(f"params must be one dict or a list of one per solution ({n}), "
                         f"got a list of {len(params)}")
    return params


def _stage_series(staging: Path, name: str, model, frames, t, deformed) -> None:
    """The frames into ``staging``/frames and their index, naming them under the folder
    ``name``, into ``staging``/index.pvd."""
    root = ET.Element("VTKFile", type="Collection", version="0.1", byte_order="LittleEndian")
    collection = ET.SubElement(root, "Collection")
    (staging / "frames").mkdir()
    for k, ((fields, record), tk) in enumerate(zip(frames, t)):
        _write_checked(staging / "frames" / f"frame_{k:04d}.vtu", model, fields, record, deformed)
        ET.SubElement(collection, "DataSet", timestep=repr(float(tk)), group="", part="0",
                      file=f"{name}/frame_{k:04d}.vtu")
    ET.indent(root)
    ET.ElementTree(root).write(staging / "index.pvd", xml_declaration=True, encoding="utf-8")


def read_series(path) -> list[tuple[float, Path]]:
    """The frames of a ``.pvd`` index: [(time, absolute .vtu path)] in file order. A file
    that is not a VTK collection, a frame without a finite time, or a frame path that is
    absolute or leaves the index's folder (``../``) raises a ValueError naming it."""
    path = _check_suffix(path, ".pvd", "a ParaView collection of .vtu frames")
    if not path.is_file():
        raise ValueError(f"series index {str(path)!r} does not exist")
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as err:
        raise ValueError(f"{str(path)!r} is not a ParaView collection: not XML ({err})") from None
    if root.tag != "VTKFile" or root.get("type") != "Collection":
        raise ValueError(f"{str(path)!r} is not a VTK collection file (<{root.tag} type={root.get('type')!r}>)")
    frames = []
    for k, ds in enumerate(root.iter("DataSet")):
        step, name = ds.get("timestep"), ds.get("file")
        try:
            time = float(step)
        except (TypeError, ValueError):
            time = None
        if time is None or not np.isfinite(time):
            raise ValueError(f"{str(path)!r}: frame {k} has no finite time (timestep={step!r})")
        rel = PurePosixPath(name or "")
        if not name or rel.is_absolute() or Path(name).is_absolute() or ".." in rel.parts:
            raise ValueError(f"{str(path)!r}: frame {k} file={name!r} must be a path relative to the index's "
                             "folder and inside it (no absolute path, no '..')")
        frames.append((time, path.parent / rel))
    return frames
