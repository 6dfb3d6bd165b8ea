"""Small planar-polygon toolkit (NumPy, build time only): orientation, point location,
clipping, Voronoi cells clipped to a domain, triangulation."""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def _cross(u, v):
    """z-component of the 2D cross product (broadcasts)."""
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def signed_area(P: np.ndarray) -> float:
    x, y = P[:, 0], P[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))


def area(P: np.ndarray) -> float:
    return abs(signed_area(P))


def centroid(P: np.ndarray) -> np.ndarray:
    x, y = P[:, 0], P[:, 1]
    cr = x * np.roll(y, -1) - np.roll(x, -1) * y
    a = 0.5 * cr.sum()
    return np.array([((x + np.roll(x, -1)) * cr).sum(), ((y + np.roll(y, -1)) * cr).sum()]) / (6 * a)


def as_ccw(V: np.ndarray) -> np.ndarray:
    """Validated counter-clockwise copy of a simple polygon's vertices (V, 2)."""
    V = np.asarray(V, float)
    if V.ndim != 2 or V.shape[1] != 2 or len(V) < 3:
        raise ValueError(f"polygon vertices must have shape (V>=3, 2), got {V.shape}")
    if not np.all(np.isfinite(V)):
        raise ValueError("polygon vertices contain non-finite values")
    if np.allclose(V[0], V[-1]):
        V = V[:-1]
    a = signed_area(V)
    if abs(a) < 1e-14:
        raise ValueError("polygon has zero area")
    return V if a > 0 else V[::-1].copy()


def contains(V: np.ndarray, P: np.ndarray) -> np.ndarray:
    """(P,) bool, even-odd rule (points exactly on the boundary may go either way)."""
    P = np.atleast_2d(P)
    x, y = P[:, 0:1], P[:, 1:2]
    a, b = V, np.roll(V, -1, axis=0)
    cond = (a[:, 1] > y) != (b[:, 1] > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        xint = a[:, 0] + (y - a[:, 1]) * (b[:, 0] - a[:, 0]) / (b[:, 1] - a[:, 1])
    return (np.sum(cond & (x < xint), axis=1) % 2) == 1


def distance_to_boundary(V: np.ndarray, P: np.ndarray) -> np.ndarray:
    """(P,) distance from each point to the nearest polygon edge."""
    P = np.atleast_2d(P)[:, None, :]
    a, b = V[None], np.roll(V, -1, axis=0)[None]
    ab = b - a
    t = np.clip(np.sum((P - a) * ab, -1) / np.sum(ab * ab, -1), 0.0, 1.0)
    return np.min(np.linalg.norm(P - (a + t[..., None] * ab), axis=-1), axis=1)


def clip_halfplane(P: np.ndarray, n: np.ndarray, c: float) -> np.ndarray:
    """Sutherland-Hodgman: the part of polygon P where n.x <= c (P may be non-convex)."""
    if len(P) == 0:
        return P
    s = P @ n - c
    out = []
    for i in range(len(P)):
        j = (i + 1) % len(P)
        if s[i] <= 0:
            out.append(P[i])
        if (s[i] < 0 < s[j]) or (s[j] < 0 < s[i]):
            t = s[i] / (s[i] - s[j])
            out.append(P[i] + t * (P[j] - P[i]))
    return np.array(out).reshape(-1, 2)


def clip_convex(P: np.ndarray, C: np.ndarray) -> np.ndarray:
    """The part of polygon P inside the convex counter-clockwise polygon C."""
    for a, b in zip(C, np.roll(C, -1, axis=0)):
        e = b - a
        n = np.array([e[1], -e[0]])  # outward normal of a ccw edge
        P = clip_halfplane(P, n, float(n @ a))
        if len(P) < 3:
            return np.zeros((0, 2))
    return P


def voronoi_cells(X: np.ndarray, V: np.ndarray, k: int = 24) -> list[np.ndarray]:
    """Voronoi cell of every particle intersected with the domain polygon V.

    Each cell is the domain clipped by the bisector half-planes of the k nearest
    particles (enough for the quasi-uniform particle sets built here; the cell areas are
    checked to sum to the domain area)."""
    k = min(k, len(X) - 1)
    _, nbr = cKDTree(X).query(X, k=k + 1)
    cells = []
    for i, row in enumerate(nbr):
        cell = V
        for j in row[1:]:
            n = X[j] - X[i]
            cell = clip_halfplane(cell, n, float(n @ (X[i] + X[j]) / 2))
        cells.append(_drop_degenerate(cell))
    total = sum(area(c) for c in cells if len(c) >= 3)
    if abs(total - area(V)) > 1e-9 * area(V):
        raise ValueError(f"Voronoi cells cover {total} of the domain area {area(V)}: "
                         "the particle distribution is too irregular for the neighbour search")
    return cells


def voronoi_areas(X: np.ndarray, V: np.ndarray) -> np.ndarray:
    return np.array([area(c) if len(c) >= 3 else 0.0 for c in voronoi_cells(X, V)])


def _drop_degenerate(P: np.ndarray, tol: float = 1e-13) -> np.ndarray:
    """Remove repeated and collinear vertices (clipping produces them)."""
    changed = True
    while changed and len(P) >= 3:
        changed = False
        for i in range(len(P)):
            a, b, c = P[i - 1], P[i], P[(i + 1) % len(P)]
            scale = max(np.abs(P).max(), 1.0)
            if np.linalg.norm(b - a) < tol * scale or abs(_cross(b - a, c - b)) < tol * scale**2:
                P = np.delete(P, i, axis=0)
                changed = True
                break
    return P if len(P) >= 3 else np.zeros((0, 2))


def triangulate(P: np.ndarray) -> np.ndarray:
    """Ear-clipping triangulation of a simple polygon: (T, 3, 2) counter-clockwise triangles."""
    P = _drop_degenerate(as_ccw(P))
    idx = list(range(len(P)))
    tris = []
    guard = 0
    while len(idx) > 3 and guard < 10 * len(P) ** 2:
        guard += 1
        for k in range(len(idx)):
            i, j, l = idx[k - 1], idx[k], idx[(k + 1) % len(idx)]
            a, b, c = P[i], P[j], P[l]
            if _cross(b - a, c - b) <= 0:
                continue  # reflex vertex
            others = [P[m] for m in idx if m not in (i, j, l)]
            if others and _any_in_triangle(np.array(others), a, b, c):
                continue
            tris.append([a, b, c])
            idx.pop(k)
            break
        else:
            raise ValueError("polygon could not be triangulated (self-intersecting?)")
    tris.append([P[m] for m in idx])
    return np.array(tris)


def _any_in_triangle(Q, a, b, c) -> bool:
    def side(p, q):
        return _cross(q - p, Q - p)
    s1, s2, s3 = side(a, b), side(b, c), side(c, a)
    return bool(np.any((s1 > 0) & (s2 > 0) & (s3 > 0)))
