"""Volume meshes for bodies: read (meshio), validate, refine (gmsh), and the simplex helpers.

NumPy, outside jit, run once per body. The pieces:

- ``read_mesh(source)``: any format meshio reads (VTU/VTK, Gmsh .msh, Abaqus .inp, Medit .mesh,
  ...) or a ``meshio.Mesh`` as it is.
- ``volume_mesh(source, dim)``: the tetrahedra (3D) or triangles (2D) of a mesh, checked
  before any geometry (finite coordinates, at least one cell, integer connectivity within
  the points) and then as geometry (zero-volume cells, coincident vertices, faces shared by
  more than two cells, cells folded over a neighbour), each cell reordered to a positive
  orientation (the vertex order of a reference mesh is a convention: qhull and scikit-fem
  mix both), with its named vertex sets (tags) from cell sets, point sets and Gmsh physical
  groups. What was repaired (cells reordered, points no cell uses dropped) is said in one
  log line (logger ``jaxrkpm.discretise.mesh``) and in ``VolumeMesh.report``.
- ``refine_mesh(source, times)``: every cell split uniformly by Gmsh, named groups carried.
- simplex helpers the body and the integration share: ``simplex_volumes``,
  ``vertex_volumes``, ``boundary_faces``, ``facet_normals``, ``mean_edge_length``,
  ``Locator`` (point in mesh).

Gmsh keeps global state: every use goes through ``gmsh_session()`` (one at a time, any
thread).
"""
from __future__ import annotations

import contextlib
import io
import logging
import math
import os
import tempfile
import threading
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

if TYPE_CHECKING:
    import meshio   # imported where used: it costs a second of every ``import jaxrkpm``

SIMPLEX = {2: "triangle", 3: "tetra"}          # body dimension -> meshio cell type
# second-order simplices are used through their corner nodes (straight-sided cells)
CORNERS = {"triangle": 3, "triangle6": 3, "triangle7": 3, "tetra": 4, "tetra10": 4}
# the default bound (``max_cells``) on the tetrahedra a refinement may make or a spacing may
# ask gmsh for (``surface``): a million make a body past what a 3D solve on one machine does,
# and a finer spacing only meshes for minutes before that shows: refused before meshing
MAX_TETRAHEDRA = 1_000_000
_GMSH_LOCK = threading.RLock()
log = logging.getLogger(__name__)


# ======================================================================== gmsh state
@contextmanager
def gmsh_session(name: str = "jaxrkpm"):
    """Gmsh initialised for one job, quiet, and cleaned up after (finalised if it was not
    running before; else only the model added here is removed). Safe outside the main
    thread (no SIGINT handler) and serialised by a lock: gmsh has one global state."""
    import gmsh

    with _GMSH_LOCK:
        owner = not gmsh.isInitialized()
        if owner:
            gmsh.initialize(readConfigFiles=False, interruptible=False)
        try:
            gmsh.option.setNumber("General.Terminal", 0)
            gmsh.model.add(name)
            yield gmsh
        finally:
            if owner:
                gmsh.finalize()
            else:
                gmsh.model.remove()


def gmsh_to_meshio(gmsh) -> meshio.Mesh:
    """The current gmsh mesh through a temporary .msh file, read by meshio (cell sets and
    ``gmsh:physical`` data carry the physical group names)."""
    import meshio

    fd, path = tempfile.mkstemp(suffix=".msh")
    os.close(fd)
    try:
        gmsh.write(path)
        mesh = meshio.read(path)
    finally:
        os.unlink(path)
    mesh.cell_sets.pop("gmsh:bounding_entities", None)   # gmsh bookkeeping, not a tag
    return mesh


# ======================================================================== reading
def read_mesh(source) -> meshio.Mesh:
    """A ``meshio.Mesh`` from a path (any format meshio reads) or the mesh itself."""
    import meshio

    if isinstance(source, meshio.Mesh):
        return source
    if not isinstance(source, (str, os.PathLike)):
        raise ValueError(f"a mesh must be a file path or a meshio.Mesh, got {type(source).__name__}")
    path = Path(source)
    if not path.is_file():
        raise ValueError(f"mesh file {str(path)!r} does not exist")
    said = io.StringIO()      # meshio prints its reasons, then may call sys.exit(1)
    try:
        # over: meshio tests an ASCII STL for the binary layout with a uint32 product that
        # overflows (a warning a user can do nothing about; the read is right)
        with contextlib.redirect_stdout(said), contextlib.redirect_stderr(said), np.errstate(over="ignore"):
            return meshio.read(path)
    except SystemExit:        # e.g. a text file named .vtu: meshio ends the process
        why = [line.strip() for line in said.getvalue().splitlines()
               if line.strip() and "Couldn't read file" not in line]   # its own reasons, if any
        raise ValueError(f"meshio cannot read {str(path)!r}: not a valid {path.suffix or 'mesh'} file"
                         + (f" ({'; '.join(why)})" if why else "")) from None
    except Exception as err:   # meshio raises ReadError, KeyError, ValueError by format
        raise ValueError(f"meshio cannot read {str(path)!r}: {err}") from err


def source_name(source) -> str:
    """How errors name a mesh source: its path, or "mesh" for a meshio.Mesh."""
    return repr(str(source)) if isinstance(source, (str, os.PathLike)) else "mesh"


@dataclass(frozen=True)
class VolumeMesh:
    """points (V, d); cells (C, d+1) simplices, positively oriented; tags name -> vertex
    indices (sorted); report: what loading repaired ("reoriented": cells whose vertex order
    was reversed, "dropped": indices of the source's points that no cell uses, removed, so
    the particles are the remaining points in their order)."""

    points: np.ndarray
    cells: np.ndarray
    tags: dict
    report: dict = None

    @property
    def dim(self) -> int:
        return self.points.shape[1]


def volume_mesh(source, dim: int | None = None, drop_degenerate: bool = False, flat: float = 1e-10) -> VolumeMesh:
    """The simplices of a mesh (tetrahedra for ``dim`` 3, triangles for 2; default: 3 if
    the mesh has tetrahedra), validated, each positively oriented, unused vertices dropped,
    with its tags. Raises a ValueError naming the defect: non-finite coordinates, no cells,
    connectivity that is not integer or indexes past the points (a -1 included), zero-volume
    cells, coincident vertices, a face of more than two cells, cells folded over each other.
    ``drop_degenerate``: zero-volume cells (the slivers of scipy's ``Delaunay`` on points of
    a lattice) are dropped instead of refused, and counted (``report["degenerate"]`` and the
    log line); they add nothing to the body's volume, and the faces they leave unmatched
    inside the body are not boundary (:func:`boundary_faces`). ``flat``: a cell whose
    measure is below this fraction of the mean is degenerate (zero volume)."""
    if not isinstance(drop_degenerate, (bool, np.bool_)):
        raise ValueError(f"drop_degenerate must be True or False, got {drop_degenerate!r}")
    mesh = read_mesh(source)
    name = source_name(source)
    dim, points, cells = _simplices(mesh, name, dim)
    degenerate = 0
    if drop_degenerate:
        cells, degenerate = _without_flat(points, cells, name, dim, flat)
    used, cells = np.unique(cells, return_inverse=True)
    cells = cells.reshape(-1, dim + 1)
    dropped = np.setdiff1d(np.arange(len(mesh.points)), used)
    points = points[used]
    cells, reoriented = _checked_cells(points, cells, flat)
    tags = _kept_tags(mesh, used)
    report = {"reoriented": reoriented, "dropped": dropped, "degenerate": degenerate}
    _say(name, SIMPLEX[dim], len(cells), reoriented, dropped, mesh, degenerate)
    return VolumeMesh(points, cells, tags, report)


def _simplices(mesh: meshio.Mesh, name: str, dim: int | None):
    """(dim, points (V, dim), cells (C, dim+1)) of the mesh's simplex blocks (the corners of
    second-order ones), checked as numbers; ``dim`` None: 3 if the mesh has tetrahedra."""
    kinds = {b.type for b in mesh.cells}
    if dim is None:
        dim = 3 if kinds & {"tetra", "tetra10"} else 2
    if dim not in SIMPLEX:
        raise ValueError(f"dim must be 2 or 3, got {dim}")
    wanted = [t for t in CORNERS if CORNERS[t] == dim + 1]
    blocks = [i for i, b in enumerate(mesh.cells) if b.type in wanted]
    if not blocks:
        raise ValueError(_no_simplices(dim, kinds))
    points = finite_points(mesh.points, name)
    cells = np.concatenate([connectivity(mesh.cells[i], len(points), name)[:, :dim + 1] for i in blocks])
    if not len(cells):
        raise ValueError(f"the mesh {name} has no {SIMPLEX[dim]} cells: its {SIMPLEX[dim]} blocks are empty")
    return dim, _coordinates(points, dim), cells


def _no_simplices(dim: int, kinds: set) -> str:
    what = ("is a 2D or surface mesh (triangles, no tetrahedra)" if dim == 3 and "triangle" in kinds
            else f"has {', '.join(sorted(kinds)) or 'no'} cells")
    return f"a {dim}D body needs {SIMPLEX[dim]} cells, but the mesh {what}"


def _without_flat(points, cells, name: str, dim: int, tolerance: float):
    """(the cells of nonzero volume, how many were dropped)."""
    vol = np.abs(simplex_volumes(points, cells))
    flat = vol <= tolerance * vol.mean()
    if flat.all():
        raise ValueError(f"every {SIMPLEX[dim]} cell of the mesh {name} has zero volume: it has no body")
    return cells[~flat], int(flat.sum())


def _kept_tags(mesh: meshio.Mesh, used: np.ndarray) -> dict:
    """The mesh's tags renumbered to the ``used`` points (sorted source indices); a tag left
    without a point is dropped."""
    renumber = -np.ones(len(mesh.points), np.int64)
    renumber[used] = np.arange(len(used))
    tags = {}
    for tag, vertices in _vertex_tags(mesh).items():
        kept = renumber[vertices]
        kept = np.unique(kept[kept >= 0])
        if kept.size:
            tags[tag] = kept
    return tags


def _say(name, kind, n_cells, reoriented, dropped, mesh, degenerate=0):
    """One log line for what loading repaired: INFO for reordered cells (a convention) and
    for the mid-edge nodes of second-order cells; WARNING where points that no cell at all
    uses were dropped (the file holds stray points: particle indices differ from its own)."""
    notes = []
    if degenerate:
        notes.append(f"{degenerate} zero-volume {kind} cells were dropped (drop_degenerate=True); "
                     f"{n_cells} remain")
    if reoriented:
        notes.append(f"{reoriented} of {n_cells} {kind} cells had the opposite vertex order and were "
                     "reordered (orientation is a convention of the mesher)")
    stray = dropped
    if len(dropped):
        listed = np.unique(np.concatenate([np.asarray(b.data, np.int64).ravel() for b in mesh.cells]
                                          or [np.zeros(0, np.int64)]))
        stray = np.setdiff1d(dropped, listed)
        notes.append(f"{len(dropped)} of {len(mesh.points)} points are no {kind} vertex and were dropped"
                     + (f" ({len(stray)} belong to no cell at all, e.g. point {int(stray[0])}; the "
                        "particles are the remaining points in their order)" if len(stray) else
                        " (mid-edge nodes or vertices of lower-dimensional cells)"))
    if notes:
        log.log(logging.WARNING if len(stray) else logging.INFO, "mesh %s: %s", name, "; ".join(notes))


def finite_points(points, name) -> np.ndarray:
    """The mesh points as a float (V, 2|3) array; a ValueError for non-numbers or non-finite
    coordinates (before any geometry: NaN makes every later check meaningless)."""
    try:
        P = np.asarray(points, float)
    except (TypeError, ValueError):
        raise ValueError(f"the points of mesh {name} are not numbers") from None
    if P.ndim != 2 or P.shape[1] not in (2, 3):
        raise ValueError(f"the points of mesh {name} must have shape (V, 2) or (V, 3), got {P.shape}")
    bad = ~np.all(np.isfinite(P), axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f"mesh {name}: {int(bad.sum())} points have non-finite coordinates (NaN or inf), "
                         f"e.g. point {i} at {P[i].tolist()}")
    return P


def connectivity(block, n_points: int, name) -> np.ndarray:
    """A cell block's vertex indices as int64 (C, k), checked: integers (a float index would
    be truncated), each in 0..n_points-1 (a -1, a padding or missing vertex, would index the
    last point)."""
    data = np.asarray(block.data)
    if data.ndim != 2:
        raise ValueError(f"mesh {name}: the {block.type} connectivity must be a (cells, vertices) table, "
                         f"got shape {data.shape}")
    if data.dtype.kind not in "iu":
        flat = data.ravel()
        try:
            frac = np.flatnonzero(np.asarray(flat, float) % 1 != 0)
        except (TypeError, ValueError):
            frac = np.zeros(0, int)
        detail = (f": cell {int(frac[0]) // data.shape[1]} holds {flat[frac[0]]!r}" if len(frac) else "")
        raise ValueError(f"mesh {name}: the {block.type} connectivity must be integer vertex indices, "
                         f"got {data.dtype}{detail}")
    data = data.astype(np.int64)
    bad = np.flatnonzero(np.any((data < 0) | (data >= n_points), axis=1))
    if len(bad):
        c = int(bad[0])
        raise ValueError(f"mesh {name}: {len(bad)} {block.type} cells index past the {n_points} points "
                         f"(valid 0..{n_points - 1}), e.g. cell {c} with vertices {data[c].tolist()}"
                         + (" (a negative index: a missing vertex)" if data[c].min() < 0 else ""))
    return data


def _coordinates(points: np.ndarray, dim: int) -> np.ndarray:
    """Mesh points as (V, dim): a 2D mesh may come with a constant third coordinate."""
    if points.shape[1] == dim:
        return points
    if dim == 3:
        raise ValueError(f"a 3D body needs 3D points, the mesh has {points.shape[1]} coordinates")
    extent = np.ptp(points[:, :2], axis=0).max()
    if np.ptp(points[:, 2:], axis=0).max() > 1e-12 * extent:
        raise ValueError("the triangles do not lie in a plane z = const: a surface mesh, not a "
                         "2D body (use Body.from_surface for a closed surface)")
    return points[:, :2]


def simplex_volumes(points: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """(C,) signed measures of the simplices (positive for a positive vertex order)."""
    V = points[cells]
    E = V[:, 1:] - V[:, :1]                       # (C, d, d) edge vectors from vertex 0
    return np.linalg.det(E) / math.factorial(points.shape[1])


def _checked_cells(points, cells, tolerance: float):
    """(cells with positive volumes, how many were reordered). Each negatively oriented cell
    has two vertices swapped: in a reference mesh the vertex order is a convention (qhull
    and scikit-fem mix both), not a deformation. Errors: coincident vertices, zero-volume
    cells, faces of more than two cells, and cells folded over a neighbour (the two cells of
    an interior face on the same side of it: a tangled mesh, which reordering cannot mend)."""
    d = points.shape[1]
    extent = np.ptp(points, axis=0).max()
    pairs = cKDTree(points).query_pairs(1e-12 * extent, output_type="ndarray")
    if len(pairs):
        i, j = pairs[0]
        raise ValueError(f"mesh vertices {i} and {j} coincide at {points[i].tolist()} ({len(pairs)} "
                         "such pairs): the cells do not share them, so the mesh is not conforming; "
                         "merge duplicate nodes first")
    vol = simplex_volumes(points, cells)
    name = SIMPLEX[d]
    flat = np.abs(vol) <= tolerance * np.abs(vol).mean()
    if flat.any():
        c = int(np.flatnonzero(flat)[0])
        raise ValueError(f"{int(flat.sum())} of {len(cells)} {name} cells are zero-volume, e.g. cell {c} with "
                         f"vertices {cells[c].tolist()} (volume {vol[c]:.3g}): slivers, as scipy's Delaunay makes "
                         "of points on a lattice; Body.from_mesh(..., drop_degenerate=True) drops them (they add "
                         "no volume), or use a mesher that makes none")
    negative = vol < 0
    cells = cells.copy()
    cells[negative] = cells[negative][:, [1, 0, *range(2, d + 1)]]
    _, face_id, counts = face_counts(cells)            # raises on a face of more than two cells
    _check_folds(points, cells, face_id, counts)
    return cells, int(negative.sum())


def _check_folds(points, cells, face_id, counts):
    """Raise if the two cells of an interior face lie on the same side of it (one folded over
    the other: they overlap). With every cell positively oriented, the face seen from its two
    cells has opposite orientations exactly when they lie on opposite sides."""
    d = points.shape[1]
    cell, local = np.nonzero(counts[face_id] == 2)
    if not len(cell):
        return
    order = np.argsort(face_id[cell, local], kind="stable")
    cell, local = cell[order].reshape(-1, 2).T, local[order].reshape(-1, 2).T
    F = np.sort(_faces(cells)[cell[0], local[0]], axis=1)         # the shared face, one vertex order
    base = points[F]                                               # (M, d, d)
    side = [np.linalg.det(np.concatenate([base[:, 1:] - base[:, :1],
                                          (points[cells[c, l]] - base[:, 0])[:, None]], axis=1))
            for c, l in ((cell[0], local[0]), (cell[1], local[1]))]
    folded = np.flatnonzero(side[0] * side[1] > 0)
    if len(folded):
        k = int(folded[0])
        raise ValueError(f"{len(folded)} interior faces have both their {SIMPLEX[d]} cells on the same side "
                         f"(the cells overlap: a tangled mesh), e.g. cells {int(cell[0, k])} and "
                         f"{int(cell[1, k])} across the face with vertices {F[k].tolist()}")


# ------------------------------------------------------------------------ tags
def _cell_groups(mesh: meshio.Mesh) -> dict:
    """name -> {block: cell ids} of every named cell group: cell sets, Gmsh physical groups
    (names in field_data), cell data written by meshio from cell sets (key "a-b-c", values
    0, 1, 2); if the mesh has no names at all, integer cell labels (Medit refs, unnamed
    physical ids) as "<label><value>", e.g. "ref3"."""
    groups = {}
    _add_cell_sets(groups, mesh)
    _add_physical_groups(groups, mesh)
    labels = _integer_labels(mesh)
    _add_named_labels(groups, labels)
    if not groups and not mesh.point_sets:
        _add_unnamed_labels(groups, labels)
    return groups


def _add_group(groups: dict, name: str, block: int, ids) -> None:
    """Merge the cells ``ids`` of ``block`` into the group ``name`` (nothing for no ids)."""
    ids = np.asarray(ids, np.int64).ravel()
    if ids.size:
        per_block = groups.setdefault(name, {})
        per_block[block] = np.union1d(per_block.get(block, ids[:0]), ids)


def _add_cell_sets(groups: dict, mesh: meshio.Mesh) -> None:
    """The mesh's cell sets but gmsh's bookkeeping ones."""
    for name, per_block in mesh.cell_sets.items():
        if not name.startswith("gmsh:"):
            for b, ids in enumerate(per_block):
                if ids is not None:
                    _add_group(groups, name, b, ids)


def _add_physical_groups(groups: dict, mesh: meshio.Mesh) -> None:
    """Gmsh physical groups named in ``field_data`` (name -> (tag, dimension))."""
    physical = mesh.cell_data.get("gmsh:physical")
    if physical is None or not mesh.field_data:
        return
    for name, (tag, dim) in ((k, np.asarray(v).ravel()[:2]) for k, v in mesh.field_data.items()):
        for b, data in enumerate(physical):
            if mesh.cells[b].dim == dim:
                _add_group(groups, name, b, np.flatnonzero(np.asarray(data) == tag))


def _integer_labels(mesh: meshio.Mesh) -> dict:
    """key -> per block (C,) integer labels: the cell data that may name groups."""
    return {k: [np.asarray(x).ravel() for x in v] for k, v in mesh.cell_data.items()
            if k != "gmsh:geometrical" and all(np.asarray(x).dtype.kind in "iu" for x in v)}


def _add_named_labels(groups: dict, labels: dict) -> None:
    """meshio's ``cell_sets_to_data``: key "a-b-c", values 0, 1, 2 for the sets a, b, c."""
    for key, data in labels.items():
        names = list(dict.fromkeys(key.split("-")))
        values = np.unique(np.concatenate(data))
        values = values[values >= 0]
        if ":" not in key and len(names) == len(values):
            for name, value in zip(names, values):
                for b, x in enumerate(data):
                    _add_group(groups, name, b, np.flatnonzero(x == value))


def _add_unnamed_labels(groups: dict, labels: dict) -> None:
    """Each value of each label as the group "<label><value>" (e.g. "ref3")."""
    for key, data in labels.items():
        for b, x in enumerate(data):
            for value in np.unique(x[x >= 0]):
                _add_group(groups, f"{key.split(':')[-1]}{value}", b, np.flatnonzero(x == value))


def _vertex_tags(mesh: meshio.Mesh) -> dict:
    """name -> vertex indices of the named cell groups (``_cell_groups``) and point sets."""
    tags = {name: np.unique(np.concatenate([np.asarray(mesh.cells[b].data)[ids].ravel()
                                            for b, ids in per_block.items()]))
            for name, per_block in _cell_groups(mesh).items()}
    for name, ids in mesh.point_sets.items():
        tags[name] = np.union1d(tags.get(name, np.zeros(0, np.int64)), np.asarray(ids, np.int64))
    return {k: v.astype(np.int64) for k, v in tags.items()}


GMSH_TYPE = {1: 1, 2: 2, 3: 4}   # simplex dimension -> gmsh element type: line, triangle, tetrahedron


def refine_mesh(source, times: int = 1, max_cells: int = MAX_TETRAHEDRA) -> meshio.Mesh:
    """The mesh with every simplex split uniformly ``times`` times by Gmsh (tetrahedra into
    8, triangles into 4; new vertices at the edge midpoints, so a curved surface keeps its
    chords), its named cell groups carried along as physical groups. Point sets cannot be
    carried (a new vertex belongs to no listed point): such a mesh is refused. A refinement
    that would make more than ``max_cells`` simplices is refused before meshing."""
    if not (isinstance(times, (int, np.integer)) and times >= 0):
        raise ValueError(f"refine must be a whole number of refinements >= 0, got {times!r}")
    mesh = read_mesh(source)
    if times == 0:
        return mesh
    if mesh.point_sets:
        raise ValueError(f"refine cannot carry the point sets {sorted(mesh.point_sets)} to the new "
                         "vertices: tag cells instead (cell sets / physical groups)")
    dim = 3 if {b.type for b in mesh.cells} & {"tetra", "tetra10"} else 2
    blocks = [b for b, blk in enumerate(mesh.cells) if CORNERS.get(blk.type) == dim + 1]
    sizes = [len(mesh.cells[b].data) for b in blocks]
    _check_refined_size(sum(sizes), dim, times, max_cells)
    first = dict(zip(blocks, np.cumsum([0] + sizes[:-1])))
    simplices = np.concatenate([np.asarray(mesh.cells[b].data)[:, :dim + 1] for b in blocks])
    groups = _cell_groups(mesh)
    owner = _owners(groups, first, len(simplices))
    with gmsh_session("refine") as gmsh:
        _add_simplices(gmsh, mesh, dim, simplices, owner)
        _add_physical(gmsh, mesh, dim, simplices, groups, owner, first)
        gmsh.option.setNumber("Mesh.SaveAll", 1)     # also the simplices in no group
        for _ in range(times):
            gmsh.model.mesh.refine()
        return gmsh_to_meshio(gmsh)


def _check_refined_size(cells: int, dim: int, times: int, max_cells: int) -> None:
    made = cells * float(2 ** dim) ** times
    if made > max_cells:
        raise ValueError(f"refine={times} would split the {cells:,} cells into {made:.3g} (x{2 ** dim} each "
                         f"time), more than the bound of {max_cells:,}: refine fewer times")


def _owners(groups: dict, first: dict, n: int) -> np.ndarray:
    """(n,) the group (its position in ``groups``) of each simplex, the first that lists it;
    -1: none. Gmsh holds each simplex in one entity."""
    owner = np.full(n, -1)
    for g, per_block in enumerate(groups.values()):
        for b, ids in per_block.items():
            if b in first:
                mine = first[b] + ids
                owner[mine[owner[mine] < 0]] = g
    return owner


def _discrete_entity(gmsh, d: int, cells: np.ndarray) -> int:
    """A new discrete entity of dimension ``d`` holding the simplices ``cells``; its tag."""
    tag = gmsh.model.addDiscreteEntity(d)
    gmsh.model.mesh.addElementsByType(tag, GMSH_TYPE[d], [], (cells[:, :d + 1] + 1).ravel())
    return tag


def _add_simplices(gmsh, mesh: meshio.Mesh, dim: int, simplices: np.ndarray, owner: np.ndarray) -> None:
    """Every node, and the simplices of no group, into one entity."""
    holder = gmsh.model.addDiscreteEntity(dim)
    xyz = np.zeros((len(mesh.points), 3))
    xyz[:, :mesh.points.shape[1]] = mesh.points
    gmsh.model.mesh.addNodes(dim, holder, np.arange(1, len(xyz) + 1), xyz.ravel())
    if np.any(owner < 0):
        gmsh.model.mesh.addElementsByType(holder, GMSH_TYPE[dim], [], (simplices[owner < 0] + 1).ravel())


def _add_physical(gmsh, mesh: meshio.Mesh, dim: int, simplices: np.ndarray, groups: dict, owner: np.ndarray,
                  first: dict) -> None:
    """Each group as a physical group: its simplices, and its lower-dimensional cells (a
    tagged face or edge) as entities of their own."""
    for g, (name, per_block) in enumerate(groups.items()):
        entities = {dim: [_discrete_entity(gmsh, dim, simplices[owner == g])]} if np.any(owner == g) else {}
        for b, ids in per_block.items():
            d = mesh.cells[b].dim
            if b not in first and d in GMSH_TYPE and d < dim:
                entities.setdefault(d, []).append(_discrete_entity(gmsh, d, np.asarray(mesh.cells[b].data)[ids]))
        for d, tags in entities.items():
            gmsh.model.addPhysicalGroup(d, tags, name=name)


# ======================================================================== topology
def _faces(cells: np.ndarray) -> np.ndarray:
    """(C, d+1, d): the face of every cell opposite each of its vertices."""
    n = cells.shape[1]
    return cells[:, [[j for j in range(n) if j != k] for k in range(n)]]


def face_counts(cells: np.ndarray):
    """Unique faces (F, d) (sorted vertex indices), for each (cell, local face) its face
    id (C, d+1), and how many cells hold each face (F,). Raises on a face of > 2 cells."""
    F = np.sort(_faces(cells), axis=2)
    d = cells.shape[1] - 1
    uniq, inv, counts = np.unique(F.reshape(-1, d), axis=0, return_inverse=True, return_counts=True)
    if counts.max() > 2:
        f = int(np.argmax(counts))
        raise ValueError(f"the face with vertices {uniq[f].tolist()} belongs to {counts[f]} cells "
                         "(overlapping cells or a non-manifold mesh)")
    return uniq, inv.reshape(cells.shape), counts


def boundary_faces(points: np.ndarray, cells: np.ndarray):
    """Faces on the mesh surface: vertex indices (M, d) ordered so that the normal points
    out (3D: (b - a) x (c - a); 2D: the tangent b - a rotated by -90 deg), the cell (M,) and
    local face (M,) (the face opposite that local vertex) each comes from."""
    _, face_id, counts = face_counts(cells)
    cell, local = np.nonzero(counts[face_id] == 1)
    F = _faces(cells)[cell, local]
    opposite = points[cells[cell, local]]
    a = points[F[:, 0]]
    if points.shape[1] == 3:
        n = np.cross(points[F[:, 1]] - a, points[F[:, 2]] - a)
    else:
        t = points[F[:, 1]] - a
        n = np.stack([t[:, 1], -t[:, 0]], 1)
    inward = np.sum(n * (opposite - a), 1) > 0
    F[inward] = F[inward][:, ::-1] if points.shape[1] == 2 else F[inward][:, [0, 2, 1]]
    n[inward] *= -1
    inside = _faces_inside(points, cells, F, n)
    return F[~inside], cell[~inside], local[~inside]


def _faces_inside(points, cells, F, n) -> np.ndarray:
    """(M,) whether each unmatched face has body on its outer side too: the faces a dropped
    zero-volume cell left between two cells that triangulate the same plane differently
    (a point just outside the face lies in another cell). None in a conforming mesh."""
    d = points.shape[1]
    centre = points[F].mean(axis=1)
    size = np.linalg.norm(n, axis=1, keepdims=True)
    scale = mean_edge_length(points, cells)
    probe = centre + 1e-6 * scale * n / np.maximum(size, 1e-300)
    k = min(16, len(cells))
    tree = cKDTree(points[cells].mean(axis=1))
    inside = np.zeros(len(probe), bool)
    for start in range(0, len(probe), 4096):         # bounded memory on large surfaces
        p = probe[start:start + 4096]
        _, near = tree.query(p, k=k)
        near = np.asarray(near).reshape(len(p), k)
        V = points[cells[near]]                                  # (m, k, d+1, d)
        T = np.swapaxes(V[:, :, 1:] - V[:, :, :1], -1, -2)       # (m, k, d, d) edge vectors as columns
        ok = np.abs(np.linalg.det(T)) > 0
        T[~ok] = np.eye(d)
        lam = np.linalg.solve(T, (p[:, None, :] - V[:, :, 0])[..., None])[..., 0]
        bary = np.concatenate([1 - lam.sum(-1, keepdims=True), lam], -1)
        inside[start:start + 4096] = np.any(ok & np.all(bary > -1e-9, axis=-1), axis=1)
    return inside


def facet_normals(V: np.ndarray):
    """Unit normals (M, d) and measures (M,) (areas in 3D, lengths in 2D) of facets given by
    their vertex coordinates V (M, d, d), normals by the vertex order (``boundary_faces``)."""
    t = V[:, 1] - V[:, 0]
    if V.shape[2] == 3:
        n = np.cross(t, V[:, 2] - V[:, 0])
        size = np.linalg.norm(n, axis=1)
        return n / size[:, None], size / 2
    size = np.linalg.norm(t, axis=1)
    return np.stack([t[:, 1], -t[:, 0]], 1) / size[:, None], size


def vertex_volumes(points: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """(V,) each vertex's share of its cells: 1/(d+1) of each adjacent simplex (its median
    dual cell); they sum to the mesh volume."""
    vol = np.abs(simplex_volumes(points, cells))
    out = np.zeros(len(points))
    np.add.at(out, cells, np.repeat(vol[:, None] / cells.shape[1], cells.shape[1], 1))
    return out


def mean_edge_length(points: np.ndarray, cells: np.ndarray) -> float:
    """Mean length of the mesh's (unique) edges: a body's nominal particle spacing."""
    n = cells.shape[1]
    E = np.sort(cells[:, [[i, j] for i in range(n) for j in range(i + 1, n)]].reshape(-1, 2), 1)
    E = np.unique(E, axis=0)
    return float(np.linalg.norm(points[E[:, 1]] - points[E[:, 0]], axis=1).mean())


class Locator:
    """Point location in a simplex mesh: the cell holding each point (KD-tree of cell
    centroids, then barycentric coordinates of the nearby cells)."""

    def __init__(self, points: np.ndarray, cells: np.ndarray):
        V = points[cells]
        self.cells = cells
        self.origin = V[:, 0]
        self.inverse = np.linalg.inv(np.swapaxes(V[:, 1:] - V[:, :1], 1, 2))   # (C, d, d)
        centroid = V.mean(1)
        self.radius = float(np.linalg.norm(V - centroid[:, None], axis=2).max())
        self.tree = cKDTree(centroid)

    def barycentric(self, cell: np.ndarray, P: np.ndarray) -> np.ndarray:
        """(P, d+1) barycentric coordinates of the points P in the cells ``cell``."""
        lam = np.einsum("pij,pj->pi", self.inverse[cell], P - self.origin[cell])
        return np.concatenate([1 - lam.sum(1, keepdims=True), lam], 1)

    def locate(self, P: np.ndarray, tol: float = 1e-10) -> np.ndarray:
        """(P,) index of a cell holding each point (barycentric coordinates >= -tol), -1 if
        none."""
        P = np.atleast_2d(np.asarray(P, float))
        lists = self.tree.query_ball_point(P, self.radius * (1 + 1e-9))
        counts = np.array([len(l) for l in lists])
        point = np.repeat(np.arange(len(P)), counts)
        cell = np.fromiter((c for l in lists for c in l), np.int64, counts.sum())
        out = -np.ones(len(P), np.int64)
        if len(cell):
            inside = self.barycentric(cell, P[point]).min(1) >= -tol
            out[point[inside]] = cell[inside]
        return out
