"""Reference geometry: particles, volumes, named sets and the domain boundary.

Everything here is NumPy and runs once, outside jit (total Lagrangian: the reference
configuration never changes).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import Callable

import numpy as np
from scipy.spatial import cKDTree

from . import mesh
from . import polygons
from . import rk
from . import surface


def _check_spacing(spacing) -> float:
    """The particle spacing as a float; a clear error for a string, NaN, inf or <= 0."""
    if isinstance(spacing, (bool, np.bool_)) or not isinstance(spacing, (int, float, np.integer, np.floating)):
        raise TypeError(f"spacing must be a positive number, got {spacing!r} ({type(spacing).__name__})")
    if not (np.isfinite(spacing) and spacing > 0):
        raise ValueError(f"spacing must be positive and finite, got {spacing}")
    return float(spacing)


def _check_origin(origin, d: int) -> np.ndarray:
    origin = np.asarray(origin, float)
    if origin.shape != (d,):
        raise ValueError(f"origin must have shape ({d},), got {origin.shape}")
    if not np.all(np.isfinite(origin)):
        raise ValueError(f"origin must be finite, got {origin.tolist()}")
    return origin


@dataclass(frozen=True, eq=False)
class Body:
    """A body in its reference configuration.

    X        (N, d)  particle positions
    volumes  (N,)    particle volumes (areas in 2D); they sum to the domain measure
    spacing          nominal particle spacing h (the kernel support is a multiple of it)
    lower, upper (d,) bounding box of the domain
    vertices (V, 2)  counter-clockwise domain polygon (2D only; a box gives 4 corners)
    cells    (C, d+1) simplices (triangles / tetrahedra, particle indices) of a body built
             from a mesh; None for grid and polygon bodies
    tags     name -> particle indices: named sets that came with the body (mesh physical
             groups / tags); empty for grid and polygon bodies

    A mesh body (``from_mesh``, ``from_surface``) has its particles at the mesh vertices,
    volumes = each vertex's share of its cells, spacing = the mean edge length, and no
    ``vertices`` polygon (its boundary is the mesh surface).
    """

    X: np.ndarray
    volumes: np.ndarray
    spacing: float
    lower: np.ndarray
    upper: np.ndarray
    vertices: np.ndarray | None = None
    is_box: bool = True
    _tree: cKDTree = field(default=None, repr=False)
    cells: np.ndarray | None = None
    tags: dict = field(default_factory=dict)

    def __repr__(self) -> str:
        # a summary, not the arrays: printing a body of thousands of particles stays one line
        box = " x ".join(f"[{lo:.4g}, {hi:.4g}]" for lo, hi in zip(np.ravel(self.lower), np.ravel(self.upper)))
        kind = "mesh" if self.cells is not None else ("box" if self.is_box else "polygon")
        cells = "" if self.cells is None else f", {len(self.cells)} cells"
        tags = f", tags {sorted(self.tags)}" if self.tags else ""
        return f"Body({self.dim}D {kind}, {self.n} particles{cells}, spacing {self.spacing:.4g}, {box}{tags})"

    @property
    def dim(self) -> int:
        return self.X.shape[1]

    @property
    def n(self) -> int:
        return self.X.shape[0]

    @property
    def measure(self) -> float:
        """Domain area (2D) or volume (3D)."""
        if self.cells is not None:
            return float(np.abs(mesh.simplex_volumes(self.X, self.cells)).sum())
        if self.vertices is not None and not self.is_box:
            return polygons.area(self.vertices)
        return float(np.prod(self.upper - self.lower))

    # ------------------------------------------------------------------ builders
    @staticmethod
    def grid(shape, spacing: float, origin=None) -> "Body":
        """Regular lattice of particles, ``shape`` = (nx, ny) or (nx, ny, nz)."""
        if any(isinstance(s, (bool, np.bool_)) or not isinstance(s, (int, np.integer)) for s in shape):
            # int(2.7) would silently build a 2-particle row
            raise TypeError(f"grid shape must be whole particle counts (ints), got {tuple(shape)}")
        shape = tuple(int(s) for s in shape)
        if len(shape) not in (2, 3):
            raise ValueError(f"grid shape must have 2 or 3 entries, got {shape}")
        if min(shape) < 2:
            raise ValueError(f"grid shape needs at least 2 particles per direction, got {shape}")
        spacing = _check_spacing(spacing)
        d = len(shape)
        origin = np.zeros(d) if origin is None else _check_origin(origin, d)
        axes = [origin[i] + spacing * np.arange(shape[i]) for i in range(d)]
        X = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, d)
        # Trapezoid weights per axis: boundary particles own half a cell.
        w1 = []
        for s in shape:
            w = np.full(s, spacing)
            w[[0, -1]] = spacing / 2
            w1.append(w)
        vol = np.prod(np.stack(np.meshgrid(*w1, indexing="ij"), -1).reshape(-1, d), axis=1)
        lower, upper = origin, origin + spacing * (np.array(shape) - 1)
        verts = None
        if d == 2:
            verts = np.array([[lower[0], lower[1]], [upper[0], lower[1]],
                              [upper[0], upper[1]], [lower[0], upper[1]]])
        return Body(X, vol, float(spacing), lower, upper, verts, True, cKDTree(X))

    @staticmethod
    def polygon(vertices, spacing: float, origin=None) -> "Body":
        """2D body bounded by a simple polygon.

        Particles: lattice points (anchored at ``origin``, default the first vertex) that lie
        inside the polygon and at least spacing/3 from its boundary, plus particles placed on
        every edge at (at most) ``spacing``. Volumes are the particles' Voronoi cells clipped to
        the polygon, so they sum to its area.
        """
        V = polygons.simple_ccw(vertices)
        spacing = _check_spacing(spacing)
        origin = V[0] if origin is None else _check_origin(origin, 2)
        edge_pts = []
        for a, b in zip(V, np.roll(V, -1, axis=0)):
            m = max(1, int(np.ceil(np.linalg.norm(b - a) / spacing - 1e-9)))
            t = np.arange(m)[:, None] / m
            edge_pts.append(a + t * (b - a))
        edge_pts = np.concatenate(edge_pts)
        lo, hi = V.min(0), V.max(0)
        i0 = np.floor((lo - origin) / spacing).astype(int)
        i1 = np.ceil((hi - origin) / spacing).astype(int)
        gx = origin[0] + spacing * np.arange(i0[0], i1[0] + 1)
        gy = origin[1] + spacing * np.arange(i0[1], i1[1] + 1)
        L = np.stack(np.meshgrid(gx, gy, indexing="ij"), -1).reshape(-1, 2)
        inside = polygons.contains(V, L) & (polygons.distance_to_boundary(V, L) > spacing / 3)
        X = np.concatenate([edge_pts, L[inside]])
        vol = polygons.voronoi_areas(X, V)
        return Body(X, vol, float(spacing), lo, hi, V, False, cKDTree(X))

    @staticmethod
    def points(X, vertices, spacing: float) -> "Body":
        """2D body from given particle positions (N, 2) in the polygon ``vertices``: for a
        layout that must match a reference (e.g. the thesis' lattice phantom). Volumes are
        Voronoi cells clipped to the polygon; every particle must lie in the closed polygon."""
        X = np.asarray(X, float)
        if X.ndim != 2 or X.shape[1] != 2:
            raise ValueError(f"particle positions must have shape (N, 2), got {X.shape}")
        if not np.all(np.isfinite(X)):
            raise ValueError("particle positions contain non-finite coordinates")
        spacing = _check_spacing(spacing)
        V = polygons.simple_ccw(vertices)
        outside = ~(polygons.contains(V, X) | (polygons.distance_to_boundary(V, X) <= 1e-9 * spacing))
        if outside.any():
            i = int(np.flatnonzero(outside)[0])
            raise ValueError(f"particle {i} at {X[i].tolist()} is outside the polygon")
        vol = polygons.voronoi_areas(X, V)
        return Body(X, vol, float(spacing), V.min(0), V.max(0), V, False, cKDTree(X))

    @staticmethod
    def from_mesh(source, dim: int | None = None, refine: int = 0, drop_degenerate: bool = False) -> "Body":
        """Body from a tetrahedral (3D) or triangular (2D) volume mesh: a path to any file
        meshio reads (VTU/VTK, Gmsh .msh, Abaqus .inp, Medit .mesh, ...) or a meshio.Mesh
        (e.g. from ``jaxrkpm.half_ellipsoid``). ``dim`` 3 or 2 (default: 3 if the mesh
        has tetrahedra). Particles at the mesh vertices; volumes are each vertex's share
        of its cells (summing to the mesh volume); ``tags`` from the mesh's named groups
        (cell sets, point sets, Gmsh physical groups); spacing = mean edge length.
        ``refine`` > 0 first splits every cell uniformly that many times (Gmsh,
        ``jaxrkpm.refine_mesh``: particles at the edge midpoints too, tags carried). The
        mesh is checked before any geometry (finite coordinates, at least one cell, integer
        connectivity within the points), then as geometry (zero-volume cells, coincident
        vertices, faces of more than two cells, cells folded over a neighbour), each
        failure a ValueError naming it; cells with the opposite vertex order are reordered
        (a mesher's convention: scipy's Delaunay and scikit-fem mix both) and points that
        no cell uses dropped, said in one line of the ``jaxrkpm.discretise.mesh`` logger.
        ``drop_degenerate``: zero-volume cells (the slivers scipy's ``Delaunay`` makes of
        points on a lattice), which are refused by default, are dropped, and their number
        said in that line."""
        vm = mesh.volume_mesh(mesh.refine_mesh(source, refine) if refine else source, dim, drop_degenerate)
        X = vm.points
        return Body(X, mesh.vertex_volumes(X, vm.cells), mesh.mean_edge_length(X, vm.cells),
                    X.min(0), X.max(0), None, False, cKDTree(X), vm.cells, vm.tags)

    @staticmethod
    def from_surface(source, spacing: float, max_cells: int = mesh.MAX_TETRAHEDRA) -> "Body":
        """3D body inside a closed triangle surface (STL, OBJ, PLY or any meshio format, or a
        meshio.Mesh), tetrahedralised by Gmsh at ``spacing`` (``jaxrkpm.tetrahedralise``).
        A surface that is open, not manifold, inconsistently oriented or self-intersecting
        or has non-finite points, a spacing too coarse for it, or one so fine that Gmsh would
        make more than ``max_cells`` tetrahedra (estimated before meshing), raises a
        ValueError naming the problem; a spacing that is not a number, a TypeError. Tags:
        "volume" (every particle) and "surface"."""
        spacing = _check_spacing(spacing)
        if isinstance(max_cells, (bool, np.bool_)) or not isinstance(max_cells, (int, np.integer)) or max_cells < 1:
            raise ValueError(f"max_cells must be a positive int, got {max_cells!r}")
        points, triangles = surface.read_surface(source)
        return Body.from_mesh(surface.tetrahedralise(points, triangles, spacing, mesh.source_name(source),
                                                     int(max_cells)))

    @cached_property
    def _mesh_boundary(self):
        """Surface faces (M, d) of a mesh body, outward ordered (``mesh.boundary_faces``)."""
        return mesh.boundary_faces(self.X, self.cells)[0]

    @cached_property
    def _locator(self) -> mesh.Locator:
        return mesh.Locator(self.X, self.cells)

    # ------------------------------------------------------------------ queries
    def select(self, predicate: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
        """Indices of the particles where ``predicate(X) -> (N,) bool`` is true."""
        mask = np.asarray(predicate(self.X), bool)
        if mask.shape != (self.n,):
            raise ValueError(f"predicate must return a ({self.n},) boolean array, got shape {mask.shape}")
        return np.flatnonzero(mask)

    def tagged(self, name: str) -> np.ndarray:
        """Indices of the particles of the named set ``name`` that came with the body (a
        mesh tag / physical group)."""
        if name not in self.tags:
            have = sorted(self.tags) or "none (only mesh bodies carry tags)"
            raise ValueError(f"the body has no tag {name!r}; its tags: {have}")
        return np.asarray(self.tags[name])

    def surface_particles(self) -> np.ndarray:
        """Indices of the particles on the domain boundary (mesh surface vertices, box
        faces, polygon edges)."""
        tol = 1e-9 * self.spacing
        if self.cells is not None:
            return np.unique(self._mesh_boundary)
        if self.is_box:
            return self.select(lambda X: np.any((X <= self.lower + tol) | (X >= self.upper - tol), 1))
        return self.select(lambda X: polygons.distance_to_boundary(self.vertices, X) <= tol)

    def surface_near(self, point, radius: float) -> np.ndarray:
        """Surface particles within ``radius`` of ``point`` (d,): e.g. a paddle's contact
        patch."""
        p = self._point(point, "point")
        r = self._radius(radius)
        S = self.surface_particles()
        return S[np.linalg.norm(self.X[S] - p, axis=1) <= r]

    def near_segment(self, a, b, radius: float) -> np.ndarray:
        """Particles within ``radius`` of the segment a -> b (each (d,)): e.g. a needle
        track."""
        a, b = self._point(a, "segment start a"), self._point(b, "segment end b")
        r = self._radius(radius)
        return np.flatnonzero(polygons.distance_to_segment(self.X, a, b) <= r)

    def _point(self, p, what):
        p = np.asarray(p, float)
        if p.shape != (self.dim,) or not np.all(np.isfinite(p)):
            raise ValueError(f"{what} must be {self.dim} finite coordinates, got {p.tolist()}")
        return p

    @staticmethod
    def _radius(radius):
        if not (np.isfinite(radius) and radius > 0):
            raise ValueError(f"radius must be positive and finite, got {radius}")
        return float(radius)

    def nearest(self, points, k: int = 1) -> np.ndarray:
        """Indices of the k particles nearest to each point: (P,) or (P, k)."""
        _, idx = self._tree.query(np.atleast_2d(points), k=k)
        return idx

    def neighbours(self, points, radius: float, capacity: int | None = None) -> rk.Neighbours:
        """Padded lists of the particles within the box-shaped window of half-width
        ``radius`` around each point (``rk.neighbours`` on this body's KD-tree)."""
        return rk.neighbours(self._tree, points, radius, capacity)

    def shape_functions(self, points, a: float, *, gradients: bool = True,
                        support_factor: float | None = None,
                        capacity: int | None = None, groups=None) -> rk.ShapeFunctions:
        """RK shape functions of this body's particles with dilation ``a`` at ``points``
        (``rk.shape_functions``; ``support_factor`` only names the support in errors;
        ``groups`` (P,): points that share one neighbour list)."""
        return rk.shape_functions(self.X, self.volumes, self._tree, points, a,
                                  capacity=capacity, gradients=gradients,
                                  support_factor=support_factor, groups=groups)

    def contains(self, points, tol: float | None = None) -> np.ndarray:
        """(P,) bool: points inside the closed domain (with a small tolerance)."""
        P = np.atleast_2d(np.asarray(points, float))
        tol = 1e-9 * self.spacing if tol is None else tol
        if self.cells is not None:      # barycentric tolerance ~ distance / spacing
            return self._locator.locate(P, tol / self.spacing) >= 0
        if self.is_box:
            return np.all((P >= self.lower - tol) & (P <= self.upper + tol), axis=1)
        return polygons.contains(self.vertices, P) | (polygons.distance_to_boundary(self.vertices, P) <= tol)

    def check_inside(self, points, what: str = "point") -> np.ndarray:
        try:
            P = np.atleast_2d(np.asarray(points, float))
        except (TypeError, ValueError):
            raise ValueError(f"{what}s must be a (P, {self.dim}) array of numbers") from None
        if P.ndim != 2 or P.shape[1] != self.dim:
            raise ValueError(f"{what}s must have shape (P, {self.dim}), got {np.shape(points)}")
        if P.shape[0] == 0:
            raise ValueError(f"no {what}s given (shape {P.shape}): pass at least one (P >= 1)")
        if not np.all(np.isfinite(P)):
            raise ValueError(f"{what}s contain non-finite coordinates")
        out = ~self.contains(P)
        if out.any():
            i = int(np.flatnonzero(out)[0])
            raise ValueError(f"{what} {i} at {P[i].tolist()} is outside the body "
                             f"(bounding box {self.lower.tolist()} .. {self.upper.tolist()})")
        return P

    def boundary_facets(self, n_per_edge: float | None = None):
        """Boundary pieces of size <= spacing: 2D segments (M, 2, 2) with outward normals (M, 2);
        3D quads (M, 4, 3) with outward normals (M, 3). Counter-clockwise ordering in 2D.
        A mesh body gives its own surface: triangles (M, 3, 3) in 3D, edges (M, 2, 2) in 2D
        (``n_per_edge`` does not apply)."""
        if self.cells is not None:
            faces = self._mesh_boundary
            return self.X[faces], mesh.facet_normals(self.X[faces])[0]
        h = self.spacing if n_per_edge is None else n_per_edge
        if self.dim == 2:
            segs = []
            V = self.vertices
            for a, b in zip(V, np.roll(V, -1, axis=0)):
                m = max(1, int(np.ceil(np.linalg.norm(b - a) / h - 1e-9)))
                t = np.arange(m + 1)[:, None] / m
                p = a + t * (b - a)
                segs.append(np.stack([p[:-1], p[1:]], 1))
            segs = np.concatenate(segs)
            tang = segs[:, 1] - segs[:, 0]
            normal = np.stack([tang[:, 1], -tang[:, 0]], 1)
            normal /= np.linalg.norm(normal, axis=1, keepdims=True)
            return segs, normal
        quads, normals = [], []
        lo, hi = self.lower, self.upper
        for ax in range(3):
            a1, a2 = [i for i in range(3) if i != ax]
            n1 = max(1, int(np.ceil((hi[a1] - lo[a1]) / h - 1e-9)))
            n2 = max(1, int(np.ceil((hi[a2] - lo[a2]) / h - 1e-9)))
            s1 = np.linspace(lo[a1], hi[a1], n1 + 1)
            s2 = np.linspace(lo[a2], hi[a2], n2 + 1)
            for side, val in ((-1, lo[ax]), (1, hi[ax])):
                for i in range(n1):
                    for j in range(n2):
                        q = np.zeros((4, 3))
                        q[:, ax] = val
                        q[:, a1] = [s1[i], s1[i + 1], s1[i + 1], s1[i]]
                        q[:, a2] = [s2[j], s2[j], s2[j + 1], s2[j + 1]]
                        nrm = np.zeros(3)
                        nrm[ax] = side
                        quads.append(q)
                        normals.append(nrm)
        return np.array(quads), np.array(normals)
