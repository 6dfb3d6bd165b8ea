"""Closed surfaces and shapes: check and tetrahedralise triangle surfaces, build solids (gmsh).

NumPy, outside jit, run once per body. The pieces:

- ``read_surface(source)``: a closed triangle surface (STL, OBJ, PLY, or any meshio format,
  or a ``meshio.Mesh``) as points and triangles, duplicate points merged.
- ``check_surface(points, triangles)``: a surface that is open, not manifold, inconsistently
  oriented, degenerate or self-intersecting (``self_intersections``) refused by name;
  ``enclosed_volume``: the volume inside a closed surface.
- ``tetrahedralise(points, triangles, spacing)``: a closed, manifold, non-self-intersecting
  triangle surface (checked here) meshed into tetrahedra by Gmsh at the requested spacing.
- ``half_ellipsoid``, ``lobe``, ``cylinder``: shapes built with Gmsh's OpenCASCADE kernel at
  run time, as ``meshio.Mesh`` with named physical groups (write them with ``meshio.write``);
  each can conform to given segments (``embed_segments``: e.g. a needle track, vertices along
  it) and be made mirror-symmetric (``symmetric``: half meshed, then ``mirrored``).

A spacing is refused before any meshing when it is too coarse for the shape or would make
more than ``max_cells`` tetrahedra; a mesh that misses more than 5% of its shape's volume is
refused after. Gmsh runs through ``mesh.gmsh_session()``; the meshes are
read, checked and measured by ``mesh``.
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

from .mesh import (MAX_TETRAHEDRA, connectivity, finite_points, gmsh_session, gmsh_to_meshio, read_mesh,
                   simplex_volumes, source_name, volume_mesh)

if TYPE_CHECKING:
    import meshio   # imported where used: it costs a second of every ``import jaxrkpm``

# tetrahedra per spacing^3 of volume at a uniform gmsh size (unit cube at spacings 0.2, 0.1,
# 0.05: 6.4, 5.0, 4.7; cylinder: 6.1, 5.1); the estimate takes the upper end
TETRAHEDRA_PER_CUBE = 6.5


# ======================================================================== surfaces
def read_surface(source):
    """A closed triangle surface (STL, OBJ, PLY, or any meshio format; or a meshio.Mesh) as
    points (V, 3) and triangles (T, 3), duplicate points merged (STL repeats them)."""
    mesh = read_mesh(source)
    tris = [np.asarray(b.data) for b in mesh.cells if b.type == "triangle"]
    if not tris:
        raise ValueError(f"the surface {source_name(source)} has no triangles (cell types: "
                         f"{sorted({b.type for b in mesh.cells})})")
    P = finite_points(mesh.points, source_name(source))
    if P.shape[1] != 3:
        raise ValueError(f"the surface {source_name(source)} must have 3D points, got {P.shape[1]} coordinates")
    T = np.concatenate([connectivity(b, len(P), source_name(source)) for b in mesh.cells if b.type == "triangle"])
    if not len(T):
        raise ValueError(f"the surface {source_name(source)} has no triangles: its triangle blocks are empty")
    used, T = np.unique(T, return_inverse=True)
    P, T = P[used], T.reshape(-1, 3)
    P, merged = np.unique(P, axis=0, return_inverse=True)
    return P, merged.ravel()[T]


def check_surface(points: np.ndarray, triangles: np.ndarray, name: str = "surface"):
    """Raise a ValueError naming the defect unless the triangles form a closed, manifold,
    consistently oriented surface without degenerate or self-intersecting triangles."""
    P, T = points, triangles
    area = np.linalg.norm(np.cross(P[T[:, 1]] - P[T[:, 0]], P[T[:, 2]] - P[T[:, 0]]), axis=1) / 2
    if np.any(area <= 1e-14 * area.max()):
        t = int(np.argmin(area))
        raise ValueError(f"the surface {name} has degenerate (zero-area) triangles, e.g. triangle {t}")
    directed = T[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2)
    edges, counts = np.unique(np.sort(directed, 1), axis=0, return_counts=True)
    if np.any(counts == 1):
        e = edges[counts == 1]
        raise ValueError(f"the surface {name} is not closed: {len(e)} edges belong to one triangle "
                         f"only, e.g. the edge {P[e[0, 0]].tolist()} - {P[e[0, 1]].tolist()}")
    if np.any(counts > 2):
        e = edges[np.argmax(counts)]
        raise ValueError(f"the surface {name} is not manifold: the edge {P[e[0]].tolist()} - "
                         f"{P[e[1]].tolist()} belongs to {counts.max()} triangles")
    _, dcounts = np.unique(directed, axis=0, return_counts=True)
    if np.any(dcounts > 1):
        raise ValueError(f"the surface {name} is not consistently oriented: neighbouring "
                         "triangles run through a shared edge in the same direction")
    hits = self_intersections(P, T)
    if len(hits):
        i, j = hits[0]
        raise ValueError(f"the surface {name} intersects itself: {len(hits)} pairs of triangles "
                         f"cross, e.g. triangles {i} and {j} near {P[T[i]].mean(0).tolist()}")


def self_intersections(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(K, 2) pairs of triangles that share no vertex and cross (an edge of one pierces the
    other; candidates from a KD-tree of centroids). Coplanar overlaps are not detected."""
    P, T = points, triangles
    V = P[T]                                                    # (T, 3, 3)
    centroid = V.mean(1)
    reach = 2 * np.linalg.norm(V - centroid[:, None], axis=2).max()
    pairs = cKDTree(centroid).query_pairs(reach, output_type="ndarray")
    if not len(pairs):
        return pairs
    i, j = pairs[:, 0], pairs[:, 1]
    apart = ~np.any(T[i][:, :, None] == T[j][:, None, :], axis=(1, 2))
    lo, hi = V.min(1), V.max(1)
    overlap = np.all((lo[i] <= hi[j]) & (lo[j] <= hi[i]), axis=1)
    pairs = pairs[apart & overlap]
    if not len(pairs):
        return pairs
    hit = _edges_pierce(V[pairs[:, 0]], V[pairs[:, 1]]) | _edges_pierce(V[pairs[:, 1]], V[pairs[:, 0]])
    return pairs[hit]


def _edges_pierce(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """(K,) whether an edge of triangle A (K, 3, 3) crosses triangle B (K, 3, 3)
    (Moller-Trumbore on the three edge segments)."""
    out = np.zeros(len(A), bool)
    e1, e2 = B[:, 1] - B[:, 0], B[:, 2] - B[:, 0]
    scale = np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1)
    for k in range(3):
        p, q = A[:, k], A[:, (k + 1) % 3]
        dirn = q - p
        h = np.cross(dirn, e2)
        det = np.sum(e1 * h, 1)
        ok = np.abs(det) > 1e-12 * scale * np.linalg.norm(dirn, axis=1)   # not parallel
        f = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        s = p - B[:, 0]
        u = f * np.sum(s * h, 1)
        qv = np.cross(s, e1)
        v = f * np.sum(dirn * qv, 1)
        t = f * np.sum(e2 * qv, 1)
        out |= ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t >= 0) & (t <= 1)
    return out


def enclosed_volume(points: np.ndarray, triangles: np.ndarray) -> float:
    """Volume inside a closed, consistently oriented triangle surface (divergence theorem)."""
    V = points[triangles]
    return abs(float(np.einsum("ti,ti->t", V[:, 0], np.cross(V[:, 1], V[:, 2])).sum() / 6))


def _check_spacing(spacing, extent: np.ndarray, name: str, volume: float | None = None,
                   max_cells: int = MAX_TETRAHEDRA) -> float:
    """The spacing as a float, refused before any meshing when it is not a positive number,
    too coarse for the shape's thinnest extent, or so fine that gmsh would make more than
    ``max_cells`` tetrahedra (estimated from ``volume``, default the bounding box's)."""
    if isinstance(spacing, (bool, np.bool_)) or not isinstance(spacing, (int, float, np.integer, np.floating)):
        raise TypeError(f"spacing must be a positive number, got {spacing!r} ({type(spacing).__name__})")
    if not (np.isfinite(spacing) and spacing > 0):
        raise ValueError(f"spacing must be positive and finite, got {spacing}")
    spacing = float(spacing)
    if spacing > extent.min() / 2:
        raise ValueError(f"spacing {spacing:g} is too coarse for {name}: it is only "
                         f"{extent.min():.3g} thick; use a spacing below {extent.min() / 4:.3g}")
    volume = float(np.prod(extent)) if volume is None else float(volume)
    estimate = TETRAHEDRA_PER_CUBE * volume / spacing ** 3
    if estimate > max_cells:
        finest = (TETRAHEDRA_PER_CUBE * volume / max_cells) ** (1 / 3)
        raise ValueError(f"spacing {spacing:g} is too fine for {name}: gmsh would make about {estimate:.2g} "
                         f"tetrahedra (volume {volume:.4g} / spacing^3 x {TETRAHEDRA_PER_CUBE}), more than the "
                         f"bound of {max_cells:,} (max_cells); use a spacing of at least {finest:.3g}")
    return spacing


def _check_volume(mesh: meshio.Mesh, expected: float, spacing: float, name: str, tolerance: float = 0.05):
    """Refuse a mesh whose tetrahedra miss more than ``tolerance`` of the shape's volume: its
    spacing was too coarse for the shape's curvature."""
    vm = volume_mesh(mesh, 3)
    got = float(simplex_volumes(vm.points, vm.cells).sum())
    if abs(got - expected) > tolerance * expected:
        raise ValueError(f"spacing {spacing:g} is too coarse for {name}: its tetrahedra hold "
                         f"{got:.4g} of the volume {expected:.4g} ({100 * abs(got / expected - 1):.0f}% "
                         f"off); use a smaller spacing")


def _generate(gmsh, spacing: float, name: str, finest: float | None = None) -> meshio.Mesh:
    """Tetrahedralise the current model at ``spacing`` (``finest``: the smallest size a
    background field may ask for, default ``spacing``)."""
    gmsh.option.setNumber("Mesh.MeshSizeMin", spacing if finest is None else min(finest, spacing))
    gmsh.option.setNumber("Mesh.MeshSizeMax", spacing)
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
    try:
        gmsh.model.mesh.generate(3)
    except Exception as err:
        raise ValueError(f"gmsh could not tetrahedralise {name} at spacing {spacing:g}: {err}") from err
    return gmsh_to_meshio(gmsh)


def tetrahedralise(points, triangles, spacing: float, name: str = "surface",
                   max_cells: int = MAX_TETRAHEDRA) -> meshio.Mesh:
    """Tetrahedra filling a closed triangle surface (points (V, 3), triangles (T, 3)) at the
    given spacing, by Gmsh: the triangles become a discrete surface, re-parametrised
    (classifySurfaces / createGeometry), remeshed at ``spacing`` and filled. Physical
    groups: "volume" (the tetrahedra) and "surface". A spacing that would make more than
    ``max_cells`` tetrahedra is refused before meshing (the estimate is in the message)."""
    import meshio

    P = finite_points(points, name)
    if P.shape[1] != 3:
        raise ValueError(f"the surface {name} must have 3D points, got {P.shape[1]} coordinates")
    T = connectivity(meshio.CellBlock("triangle", np.asarray(triangles)), len(P), name)
    check_surface(P, T, name)
    spacing = _check_spacing(spacing, np.ptp(P, axis=0), name, enclosed_volume(P, T), max_cells)
    with gmsh_session("surface") as gmsh:
        s = gmsh.model.addDiscreteEntity(2)
        gmsh.model.mesh.addNodes(2, s, np.arange(1, len(P) + 1), P.ravel())
        gmsh.model.mesh.addElementsByType(s, 2, [], (T + 1).ravel())
        try:   # patches split at 40 deg creases; each patch re-parametrised for remeshing
            gmsh.model.mesh.classifySurfaces(math.radians(40), True, True, math.pi)
            gmsh.model.mesh.createGeometry()
        except Exception as err:
            raise ValueError(f"gmsh could not re-parametrise the surface {name}: {err}") from err
        surfaces = [t for _, t in gmsh.model.getEntities(2)]
        loop = gmsh.model.geo.addSurfaceLoop(surfaces)
        volume = gmsh.model.geo.addVolume([loop])
        gmsh.model.geo.synchronize()
        gmsh.model.addPhysicalGroup(3, [volume], name="volume")
        gmsh.model.addPhysicalGroup(2, surfaces, name="surface")
        mesh = _generate(gmsh, spacing, name)
    _check_volume(mesh, enclosed_volume(P, T), spacing, name)
    return mesh


# ======================================================================== shapes
AXES = {"x": 0, "y": 1, "z": 2}


def _occ_shape(build, spacing: float, name: str, embed_segments=(), segment_spacing=None,
               symmetric: str | None = None) -> meshio.Mesh:
    """Mesh an OpenCASCADE solid: ``build(occ)`` makes it and returns (volume tag,
    classify, centre), ``classify(centre of mass)`` names each boundary surface's physical
    group. ``embed_segments``: segments the mesh conforms to (``_embed_segments``).
    ``symmetric`` ("x", "y" or "z"): only the half on the positive side of the plane through
    ``centre`` normal to that axis is meshed, then mirrored (``mirrored``), so the mesh has
    the solid's mirror symmetry exactly (a symmetric load gives a symmetric answer)."""
    segments = _segments(embed_segments)
    if symmetric is not None and symmetric not in AXES:
        raise ValueError(f"symmetric must be one of {list(AXES)} or None, got {symmetric!r}")
    with gmsh_session(name) as gmsh:
        occ = gmsh.model.occ
        volume, classify, centre = build(occ)
        occ.synchronize()
        xmin, ymin, zmin, xmax, ymax, zmax = gmsh.model.getBoundingBox(3, volume)
        extent = np.array([xmax - xmin, ymax - ymin, zmax - zmin])
        expected = occ.getMass(3, volume)
        spacing = _check_spacing(spacing, extent, name, expected)
        plane = None if symmetric is None else (AXES[symmetric], float(centre[AXES[symmetric]]))
        _check_inside(gmsh, volume, segments, name, plane)
        if plane is not None:
            corner = np.array([xmin, ymin, zmin]) - extent
            size = 3 * extent
            size[plane[0]] = plane[1] - corner[plane[0]]
            out, _ = occ.cut([(3, volume)], [(3, occ.addBox(*corner, *size))])
            occ.synchronize()
            volume = out[0][1]
        finest = None
        if len(segments):
            finest = spacing if segment_spacing is None else _positive([segment_spacing], 1, "segment_spacing")[0]
            volume = _embed_segments(gmsh, volume, segments, spacing, finest, name)
        gmsh.model.addPhysicalGroup(3, [volume], name="volume")
        surfaces = [t for _, t in gmsh.model.getBoundary([(3, volume)], oriented=False)]
        groups = {}
        for s in surfaces:
            if plane is not None:
                box = np.reshape(gmsh.model.getBoundingBox(2, s), (2, 3))[:, plane[0]]   # padded by OCC
                centre_of_mass = occ.getCenterOfMass(2, s)[plane[0]]
                if np.ptp(box) < 1e-4 * extent.max() and abs(centre_of_mass - plane[1]) < 1e-9 * extent.max():
                    continue                          # the cut face: inside the mirrored solid
            groups.setdefault(classify(np.array(occ.getCenterOfMass(2, s))), []).append(s)
        for group, tags in groups.items():
            gmsh.model.addPhysicalGroup(2, tags, name=group)
        mesh = _generate(gmsh, spacing, name, finest)
    if plane is not None:
        mesh = mirrored(mesh, *plane)
    _check_volume(mesh, expected, spacing, name)
    return mesh


def mirrored(source, axis: int, offset: float = 0.0) -> meshio.Mesh:
    """A mesh lying on one side of the plane x[axis] = offset joined with its mirror image:
    the vertices on the plane shared, the mirrored cells' orientation restored, every named
    group (cell sets, Gmsh physical and geometrical data, point sets) holding both halves."""
    import meshio

    mesh = read_mesh(source)
    P = np.asarray(mesh.points, float)
    side = P[:, axis] - offset
    scale = np.ptp(P, axis=0).max()
    if np.any(side > 1e-9 * scale) and np.any(side < -1e-9 * scale):
        raise ValueError(f"the mesh lies on both sides of the plane x[{axis}] = {offset}: nothing to mirror")
    on_plane = np.abs(side) <= 1e-9 * scale
    image = np.arange(len(P))
    image[~on_plane] = len(P) + np.arange(int((~on_plane).sum()))
    Q = P[~on_plane].copy()
    Q[:, axis] = 2 * offset - Q[:, axis]
    cells = []
    for block in mesh.cells:
        data = np.asarray(block.data)
        flip = image[data]
        if data.shape[1] > 1 and block.dim > 0:
            flip = flip[:, [1, 0, *range(2, data.shape[1])]]   # mirrored: swap two vertices back
        cells.append(meshio.CellBlock(block.type, np.concatenate([data, flip])))
    sizes = [len(b.data) for b in mesh.cells]
    cell_data = {k: [np.concatenate([x, x]) for x in v] for k, v in mesh.cell_data.items()}
    cell_sets = {k: [None if ids is None else np.concatenate([ids, np.asarray(ids) + n]) for ids, n in zip(v, sizes)]
                 for k, v in mesh.cell_sets.items()}
    point_data = {k: np.concatenate([v, np.asarray(v)[~on_plane]]) for k, v in mesh.point_data.items()}
    point_sets = {k: np.union1d(v, image[np.asarray(v)]) for k, v in mesh.point_sets.items()}
    return meshio.Mesh(np.concatenate([P, Q]), cells, point_data=point_data, cell_data=cell_data,
                       field_data=dict(mesh.field_data), cell_sets=cell_sets, point_sets=point_sets)


def _segments(embed_segments) -> np.ndarray:
    """(S, 2, 3) segment end points from a sequence of (a, b) pairs, checked."""
    seg = np.asarray(embed_segments if embed_segments is not None else (), float)
    if seg.size == 0:
        return np.zeros((0, 2, 3))
    if seg.ndim == 2 and seg.shape == (2, 3):
        seg = seg[None]
    if seg.ndim != 3 or seg.shape[1:] != (2, 3) or not np.isfinite(seg).all():
        raise ValueError(f"embed_segments must be a list of (a, b) pairs of 3D points, got shape {seg.shape}")
    if np.any(np.linalg.norm(seg[:, 1] - seg[:, 0], axis=1) == 0):
        raise ValueError("embed_segments holds a segment of zero length (a == b)")
    return seg


def _check_inside(gmsh, volume: int, segments: np.ndarray, name: str, plane=None):
    """Raise unless every segment lies in the solid (its ends may touch the surface) and, for
    a mirrored mesh, on the meshed side of the mirror plane (axis, offset) or in it."""
    for k, (a, b) in enumerate(segments):
        inside = [gmsh.model.isInside(3, volume, list(a + t * (b - a))) for t in np.linspace(0.02, 0.98, 25)]
        if not all(inside):
            raise ValueError(f"embed_segments[{k}] {a.tolist()} -> {b.tolist()} leaves {name}: every "
                             "segment must lie inside the solid (its ends may touch the surface)")
        if plane is not None and min(a[plane[0]], b[plane[0]]) < plane[1] - 1e-12:
            raise ValueError(f"embed_segments[{k}] {a.tolist()} -> {b.tolist()} crosses to the mirrored "
                             f"half of {name}: give segments on the side x[{plane[0]}] >= {plane[1]} "
                             "(their mirror images are not embedded)")


def _embed_segments(gmsh, volume: int, segments: np.ndarray, spacing: float, finest: float, name: str) -> int:
    """Make the mesh of ``volume`` conform to the segments (mesh vertices along each, at
    ``finest`` spacing; the size grows back to ``spacing`` within one ``spacing`` of them):
    the segments fragment the solid (OpenCASCADE), which embeds them in it. Returns the
    volume's tag after the fragment. Each segment must lie in the solid (its ends may touch
    the surface)."""
    occ = gmsh.model.occ
    lines = [(1, occ.addLine(occ.addPoint(*a), occ.addPoint(*b))) for a, b in segments]
    out, _ = occ.fragment([(3, volume)], lines)
    occ.synchronize()
    volumes = [t for d, t in out if d == 3]
    curves = [t for d, t in out if d == 1]
    if len(volumes) != 1:
        raise ValueError(f"embedding the segments split {name} into {len(volumes)} pieces")
    field = gmsh.model.mesh.field
    distance = field.add("Distance")
    field.setNumbers(distance, "CurvesList", curves)
    field.setNumber(distance, "Sampling", 200)
    threshold = field.add("Threshold")
    field.setNumber(threshold, "InField", distance)
    field.setNumber(threshold, "SizeMin", finest)
    field.setNumber(threshold, "SizeMax", spacing)
    field.setNumber(threshold, "DistMin", 0.5 * finest)
    field.setNumber(threshold, "DistMax", spacing)
    field.setAsBackgroundMesh(threshold)
    return volumes[0]


def half_ellipsoid(radii, spacing: float, center=(0.0, 0.0, 0.0), embed_segments=(),
                   segment_spacing: float | None = None, symmetric: str | None = None) -> meshio.Mesh:
    """The upper half (z >= center z) of the ellipsoid with semi-axes ``radii`` (3,): a
    breast-like phantom on a flat base. Physical groups "volume", "base" (the flat face at
    z = center z) and "skin" (the curved surface).

    Every shape builder takes ``embed_segments`` (a list of (a, b) 3D point pairs inside the
    solid, e.g. a needle track): the mesh conforms to them, with vertices along each at
    ``segment_spacing`` (default ``spacing``), its size growing back to ``spacing`` within one
    ``spacing`` of them; and ``symmetric`` ("x", "y" or "z", for the cylinder "x" or "y",
    for the lobe "z"): the mesh mirror-symmetric about the shape's symmetry plane normal to
    that axis (half meshed, then mirrored; a segment lying in the mirror plane must not touch
    the surface: gmsh cannot mesh that face then, so start it just inside)."""
    r = _positive(radii, 3, "radii")
    c = np.asarray(center, float)

    def build(occ):
        ball = occ.addSphere(*c, 1.0)
        occ.dilate([(3, ball)], *c, *r)
        below = occ.addBox(*(c - 2 * r), *(4 * r[0], 4 * r[1], 2 * r[2]))
        out, _ = occ.cut([(3, ball)], [(3, below)])
        return out[0][1], lambda cm: "base" if abs(cm[2] - c[2]) < 1e-9 * r[2] else "skin", c

    if symmetric == "z":
        raise ValueError("the half-ellipsoid has no mirror plane normal to z: symmetric must be 'x' or 'y'")
    return _occ_shape(build, spacing, "the half-ellipsoid", embed_segments, segment_spacing, symmetric)


def cylinder(radius: float, height: float, spacing: float, center=(0.0, 0.0, 0.0), embed_segments=(),
             segment_spacing: float | None = None, symmetric: str | None = None) -> meshio.Mesh:
    """The cylinder of ``radius`` along z from the base ``center`` up to ``height``.
    Physical groups "volume", "bottom", "top" and "side". ``embed_segments``,
    ``segment_spacing``, ``symmetric``: as ``half_ellipsoid``."""
    radius, height = _positive([radius, height], 2, "radius and height")
    c = np.asarray(center, float)

    def classify(cm):
        if abs(cm[2] - c[2]) < 1e-9 * height:
            return "bottom"
        return "top" if abs(cm[2] - c[2] - height) < 1e-9 * height else "side"

    if symmetric == "z":
        raise ValueError("mirroring the cylinder about a plane normal to z is not offered: symmetric must be 'x' or 'y'")
    return _occ_shape(lambda occ: (occ.addCylinder(*c, 0, 0, height, radius), classify, c),
                      spacing, "the cylinder", embed_segments, segment_spacing, symmetric)


def lobe(length: float, width: float, thickness: float, spacing: float, embed_segments=(),
         segment_spacing: float | None = None, symmetric: str | None = None) -> meshio.Mesh:
    """A lobe-shaped organ: two flattened ellipsoids fused along x (a large lobe of
    ``length`` x ``width`` x ``thickness`` and a smaller one overlapping its right end),
    centred at the origin. Physical groups "volume" and "surface". ``embed_segments``,
    ``segment_spacing``, ``symmetric``: as ``half_ellipsoid``."""
    L, W, H = _positive([length, width, thickness], 3, "length, width and thickness")

    def build(occ):
        big = occ.addSphere(-0.15 * L, 0, 0, 1.0)
        occ.dilate([(3, big)], -0.15 * L, 0, 0, 0.35 * L, 0.5 * W, 0.5 * H)
        small = occ.addSphere(0.25 * L, 0.1 * W, 0, 1.0)
        occ.dilate([(3, small)], 0.25 * L, 0.1 * W, 0, 0.25 * L, 0.35 * W, 0.35 * H)
        out, _ = occ.fuse([(3, big)], [(3, small)])
        return out[0][1], lambda cm: "surface", np.zeros(3)

    if symmetric in ("x", "y"):
        raise ValueError(f"the lobe has no mirror plane normal to {symmetric}: symmetric must be 'z' or None")
    return _occ_shape(build, spacing, "the lobe", embed_segments, segment_spacing, symmetric)


def _positive(values, n, what) -> np.ndarray:
    v = np.asarray(values, float).ravel()
    if v.shape != (n,) or not np.all(np.isfinite(v) & (v > 0)):
        raise ValueError(f"{what} must be {n} positive numbers, got {values}")
    return v
