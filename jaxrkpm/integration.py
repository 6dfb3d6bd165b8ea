"""Integration tables, computed once (total Lagrangian): points, weights, neighbour
indices, Psi and grad Psi. Gauss quadrature on background cells independent of the
particles (thesis Fig. 3.3); boundary facets for tractions."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import polygons
from .geometry import Body


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


def gauss_points(body: Body, order: int = 2, cell_size: float | None = None):
    """Gauss points and weights over the domain on a background grid of cells.

    Cells are squares/cubes of ``cell_size`` (default: the particle spacing) covering the
    bounding box; in a polygon, cells crossing the boundary are cut to the domain and the
    cut piece is triangulated."""
    if order < 1:
        raise ValueError(f"Gauss order must be >= 1, got {order}")
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
    outward normals (B, d)."""
    x, w = gauss_1d(order)
    facets, normals = body.boundary_facets()
    if body.dim == 2:
        a, b = facets[:, 0], facets[:, 1]
        L = np.linalg.norm(b - a, axis=1)
        pts = (a[:, None] + x[None, :, None] * (b - a)[:, None]).reshape(-1, 2)
        wts = (L[:, None] * w[None]).ravel()
        nrm = np.repeat(normals, order, axis=0)
        return pts, wts, nrm
    uv, wuv = tensor_rule(order, 2)
    q0, q1, q3 = facets[:, 0], facets[:, 1], facets[:, 3]
    e1, e2 = q1 - q0, q3 - q0
    pts = (q0[:, None] + uv[None, :, :1] * e1[:, None] + uv[None, :, 1:] * e2[:, None]).reshape(-1, 3)
    areas = np.linalg.norm(np.cross(e1, e2), axis=1)
    wts = (areas[:, None] * wuv[None]).ravel()
    nrm = np.repeat(normals, len(uv), axis=0)
    return pts, wts, nrm


def table(body: Body, points, weights, a: float, normals=None, support_factor=None) -> Table:
    sf = body.shape_functions(points, a, support_factor=support_factor)
    return Table(np.asarray(points), np.asarray(weights), sf.idx, sf.psi, sf.dpsi, normals)
