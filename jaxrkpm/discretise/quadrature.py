"""Integration tables, computed once (total Lagrangian): points, weights, neighbour
indices, Psi and grad Psi. Gauss quadrature on background cells independent of the
particles (thesis Fig. 3.3); boundary facets for tractions."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import roots_jacobi

from . import mesh
from . import polygons
from .body import Body
from .pairs import padded_groups


@dataclass(frozen=True)
class Table:
    """points (Q, d), weights (Q,), idx (Q, K), psi (Q, K), dpsi (Q, K, d);
    normals (Q, d) for boundary tables (outward, reference configuration), else None."""

    points: np.ndarray
    weights: np.ndarray
    idx: np.ndarray
    psi: np.ndarray
    dpsi: np.ndarray
    normals: np.ndarray | None = None

    def subset(self, keep: np.ndarray) -> "Table":
        return Table(self.points[keep], self.weights[keep], self.idx[keep], self.psi[keep],
                     self.dpsi[keep], None if self.normals is None else self.normals[keep])


def gauss_1d(order: int):
    """Gauss-Legendre rule with ``order`` points on [0, 1]: points (order,), weights (order,)."""
    x, w = np.polynomial.legendre.leggauss(order)
    return (x + 1) / 2, w / 2  # on [0, 1]


def tensor_rule(order: int, d: int):
    """Tensor-product Gauss rule on the unit cube [0, 1]^d: points (order^d, d), weights."""
    x, w = gauss_1d(order)
    pts = np.stack(np.meshgrid(*([x] * d), indexing="ij"), -1).reshape(-1, d)
    wts = np.prod(np.stack(np.meshgrid(*([w] * d), indexing="ij"), -1).reshape(-1, d), axis=1)
    return pts, wts  # on the unit cube


def segment_rule(a: np.ndarray, b: np.ndarray, order: int):
    """Gauss rule on the segment a -> b in R^d: points (order, d), weights (order,)."""
    x, w = gauss_1d(order)
    return a + x[:, None] * (b - a), w * np.linalg.norm(b - a)


def triangle_rule(a: np.ndarray, b: np.ndarray, c: np.ndarray, order: int):
    """Collapsed (Duffy) Gauss rule on the planar triangle (a, b, c) in R^2 or R^3:
    order^2 points (order^2, d) and weights, exact for polynomials of degree 2*order - 2."""
    x, w = gauss_1d(order)
    s, t = np.meshgrid(x, x, indexing="ij")
    s, t = s.ravel(), t.ravel()
    ws = np.outer(w, w).ravel()
    # (s, t) in the unit square -> barycentric (1-s, s(1-t), st); Jacobian s
    pts = a + np.outer(s * (1 - t), b - a) + np.outer(s * t, c - a)
    e1, e2 = b - a, c - a
    jac = abs(polygons.cross2(e1, e2)) if len(a) == 2 else np.linalg.norm(np.cross(e1, e2))
    return pts, ws * s * jac


def simplex_rule(order: int, d: int):
    """Collapsed (Stroud conical product) Gauss rule on the d-simplex, d = 1, 2, 3, with
    ``order`` points per direction: barycentric coordinates (order^d, d+1) and weights
    (order^d,) as fractions of the simplex measure (they sum to 1). Gauss-Jacobi points
    absorb the collapse's Jacobian, so the rule is exact for polynomials of total degree
    2 * order - 1 (as ``order`` Gauss-Legendre points per direction on a box)."""
    if d not in (1, 2, 3):
        raise ValueError(f"simplex rules are for d = 1, 2, 3, got {d}")
    if order < 1:
        raise ValueError(f"Gauss order must be >= 1, got {order}")
    axes = []
    for k in range(d):   # collapsed direction k carries the weight s^(d-1-k) on [0, 1]
        x, w = roots_jacobi(order, 0.0, float(d - 1 - k))
        axes.append(((x + 1) / 2, w / w.sum()))
    grids = np.meshgrid(*[x for x, _ in axes], indexing="ij")
    wts = np.prod(np.meshgrid(*[w for _, w in axes], indexing="ij"), axis=0).ravel()
    s = [g.ravel() for g in grids]
    # barycentric coordinates: peel one coordinate per collapsed direction
    lam, rest = [], np.ones_like(s[0])
    for k in range(d):
        lam.append(rest * (1 - s[k]))
        rest = rest * s[k]
    lam.append(rest)
    return np.stack(lam, 1), wts


def mesh_gauss_points(body: Body, order: int = 2):
    """Gauss points (C * order^d, d) and weights on the cells of a mesh body
    (``simplex_rule``: exact for degree 2 * order - 1 on every cell)."""
    lam, w = simplex_rule(order, body.dim)
    vol = np.abs(mesh.simplex_volumes(body.X, body.cells))
    pts = np.einsum("qk,ckd->cqd", lam, body.X[body.cells]).reshape(-1, body.dim)
    return pts, (vol[:, None] * w[None]).ravel()


def gauss_points(body: Body, order: int = 2, cell_size: float | None = None):
    """Gauss points and weights over the domain on a background grid of cells.

    Cells are squares/cubes of ``cell_size`` (default: the particle spacing) covering the
    bounding box; in a polygon, cells crossing the boundary are cut to the domain and the
    cut piece is triangulated. A mesh body is integrated on its own cells instead
    (``mesh_gauss_points``; ``cell_size`` does not apply)."""
    if order < 1:
        raise ValueError(f"Gauss order must be >= 1, got {order}")
    if body.cells is not None:
        if cell_size is not None:
            raise ValueError("cell_size does not apply to a mesh body: it is integrated on its cells")
        return mesh_gauss_points(body, order)
    h = body.spacing if cell_size is None else float(cell_size)
    if not h > 0:
        raise ValueError(f"cell_size must be positive, got {cell_size}")
    d = body.dim
    span = body.upper - body.lower
    n = np.maximum(1, np.ceil(span / h - 1e-9).astype(int))
    sizes = span / n
    ref_pts, ref_w = tensor_rule(order, d)
    corners = np.stack(np.meshgrid(*[np.arange(k) for k in n], indexing="ij"), -1).reshape(-1, d)
    corners = body.lower + corners * sizes
    if body.is_box:
        pts = (corners[:, None, :] + ref_pts[None] * sizes).reshape(-1, d)
        w = np.tile(ref_w * np.prod(sizes), len(corners))
        return pts, w
    all_p, all_w = [], []
    V = body.vertices
    cell_area = float(np.prod(sizes))
    for c in corners:
        box = np.array([c, c + [sizes[0], 0], c + sizes, c + [0, sizes[1]]])
        piece = polygons.clip_convex(V, box)
        if len(piece) < 3:
            continue
        A = polygons.area(piece)
        if A < 1e-14 * cell_area:
            continue
        if abs(A - cell_area) < 1e-12 * cell_area:
            all_p.append(c + ref_pts * sizes)
            all_w.append(ref_w * cell_area)
            continue
        for tri in polygons.triangulate(piece):
            p, w = triangle_rule(*tri, order)
            all_p.append(p)
            all_w.append(w)
    return np.concatenate(all_p), np.concatenate(all_w)


def boundary_points(body: Body, order: int = 2):
    """Gauss points on the domain boundary: points (B, d), weights (B,) (length / area),
    outward normals (B, d): ``order`` points per direction on each of the body's
    ``boundary_facets`` (segments, box quads, or mesh surface triangles)."""
    x, w = gauss_1d(order)
    facets, normals = body.boundary_facets()
    if body.dim == 2:
        a, b = facets[:, 0], facets[:, 1]
        L = np.linalg.norm(b - a, axis=1)
        pts = (a[:, None] + x[None, :, None] * (b - a)[:, None]).reshape(-1, 2)
        wts = (L[:, None] * w[None]).ravel()
        nrm = np.repeat(normals, order, axis=0)
        return pts, wts, nrm
    if facets.shape[1] == 3:                       # triangles of a mesh surface
        lam, wl = simplex_rule(order, 2)
        pts = np.einsum("qk,mkd->mqd", lam, facets).reshape(-1, 3)
        areas = np.linalg.norm(np.cross(facets[:, 1] - facets[:, 0], facets[:, 2] - facets[:, 0]), axis=1) / 2
        return pts, (areas[:, None] * wl[None]).ravel(), np.repeat(normals, len(wl), axis=0)
    uv, wuv = tensor_rule(order, 2)
    q0, q1, q3 = facets[:, 0], facets[:, 1], facets[:, 3]
    e1, e2 = q1 - q0, q3 - q0
    pts = (q0[:, None] + uv[None, :, :1] * e1[:, None] + uv[None, :, 1:] * e2[:, None]).reshape(-1, 3)
    areas = np.linalg.norm(np.cross(e1, e2), axis=1)
    wts = (areas[:, None] * wuv[None]).ravel()
    nrm = np.repeat(normals, len(uv), axis=0)
    return pts, wts, nrm


def table(body: Body, points, weights, a: float, normals=None, support_factor=None,
          groups=None) -> Table:
    """The Table of given points and weights (``groups`` (Q,): points that share one
    neighbour list, e.g. the Gauss points of one mesh cell)."""
    sf = body.shape_functions(points, a, support_factor=support_factor, groups=groups)
    return Table(np.asarray(points), np.asarray(weights), sf.idx, sf.psi, sf.dpsi, normals)


def gauss_table(body: Body, a: float, order: int = 2, cell_size: float | None = None,
                support_factor=None) -> Table:
    """The integration Table for ``Model(integration="gauss")``: ``gauss_points`` with their
    shape functions; on a mesh body the Gauss points of a cell share one neighbour list
    (the model sums their tangent contributions per cell before the scatter)."""
    pts, wts = gauss_points(body, order, cell_size)
    groups = None
    if body.cells is not None:
        groups = np.repeat(np.arange(len(body.cells)), len(wts) // len(body.cells))
    return table(body, pts, wts, a, support_factor=support_factor, groups=groups)


def dilatation_patches(body: Body, table: Table, integration: str = "gauss",
                       cell_size: float | None = None) -> np.ndarray:
    """The patch (Q,) of every integration point over which the anti-locking formulation
    averages the volume change (``jaxrkpm.mechanics.strain.mean_dilatation``): the background
    cell of ``cell_size`` (default: the spacing) that holds the point, for Gauss points and for
    the cells and sub-cells of MSCNI. That is one volumetric constraint per cell of about one
    particle, the count of the mean-dilatation element Q1/P0: patches of two spacings are too
    soft, and folding MSCNI's sub-cells into their own particle's cell alone leaves it stiffer
    (``experiments/cook_membrane.py``). On a mesh body, whose small cells crowd unevenly into
    background cells (a patch's cost grows with the square of its points), the patch is the
    nearest particle instead: the same count, one constraint a particle. SCNI keeps a patch
    per point: nodal integration already has one volumetric constraint per particle, and fewer
    make it soft."""
    if integration == "scni":
        return np.arange(len(table.points))
    if body.cells is not None:
        return np.asarray(body.nearest(table.points), np.int64).reshape(-1)
    h = body.spacing if cell_size is None else float(cell_size)
    span = body.upper - body.lower
    n = np.maximum(1, np.ceil(span / h - 1e-9).astype(int))
    cell = np.clip(np.floor((table.points - body.lower) / (span / n)).astype(np.int64), 0, n - 1)
    return np.ravel_multi_index(tuple(cell.T), tuple(n))


def patched(table: Table, patch_of: np.ndarray) -> tuple[Table, np.ndarray]:
    """``table`` with every point's neighbour list widened to the union of its patch's lists
    (the added entries carry psi = dpsi = 0, so every field it gives is unchanged), and the
    patches as groups (G, S) of point indices padded with Q: a patch's points then share one
    list, so a term that couples them keeps its tangent within that list's pairs."""
    Q, K = table.idx.shape
    patch_of = np.asarray(patch_of, np.int64)
    if patch_of.shape != (Q,):
        raise ValueError(f"patch_of must have one patch per point, shape ({Q},), got {patch_of.shape}")
    _, patch_of = np.unique(patch_of, return_inverse=True)
    N = int(table.idx.max()) + 1
    keys = np.unique(patch_of[:, None] * N + table.idx.astype(np.int64))
    owner, member = keys // N, keys % N
    counts = np.bincount(owner)
    start = np.r_[0, np.cumsum(counts)[:-1]]
    Ku = int(counts.max())
    slot = np.arange(len(keys)) - np.repeat(start, counts)
    lists = np.repeat(member[start + counts - 1][:, None], Ku, 1)     # padding: the list's last entry
    lists[owner, slot] = member
    # where each (point, entry) lands in its patch's list
    pos = np.searchsorted(keys, patch_of[:, None] * N + table.idx) - start[patch_of][:, None]
    rows = np.repeat(np.arange(Q), K)
    psi = np.zeros((Q, Ku))
    dpsi = np.zeros((Q, Ku, table.dpsi.shape[-1]))
    np.add.at(psi, (rows, pos.ravel()), table.psi.ravel())
    np.add.at(dpsi, (rows, pos.ravel()), table.dpsi.reshape(Q * K, -1))
    idx = lists[patch_of].astype(table.idx.dtype)
    return (Table(table.points, table.weights, idx, psi, dpsi, table.normals),
            padded_groups(patch_of, np.bincount(patch_of)))
