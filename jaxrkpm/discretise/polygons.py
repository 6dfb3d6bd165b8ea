"""Small planar-polygon toolkit (NumPy, outside jit): orientation, point location,
point-to-segment distance (any dimension), clipping (optionally carrying edge labels),
Voronoi cells clipped to a domain, triangulation."""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def cross2(u, v):
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
    V = _vertices(V)
    a = signed_area(V)
    if abs(a) < 1e-14:
        raise ValueError("polygon has zero area")
    return V if a > 0 else V[::-1].copy()


def _vertices(V) -> np.ndarray:
    """(V, 2) float vertices, finite, without a repeated closing vertex."""
    try:
        V = np.asarray(V, float)
    except (TypeError, ValueError):
        raise ValueError("polygon vertices must be a (V, 2) array of numbers") from None
    if V.ndim != 2 or V.shape[1] != 2 or len(V) < 3:
        raise ValueError(f"polygon vertices must have shape (V>=3, 2), got {V.shape}")
    if not np.all(np.isfinite(V)):
        raise ValueError("polygon vertices contain non-finite values")
    if np.allclose(V[0], V[-1]):
        V = V[:-1]
    return V


def simple_ccw(V) -> np.ndarray:
    """``as_ccw`` for a domain outline, which must also be a SIMPLE polygon: no vertex
    listed twice and no two edges that cross or touch (both break the clipped Voronoi
    volumes and the inside test, with errors that name neither)."""
    V = _vertices(V)
    scale = max(float(np.abs(V).max()), 1.0)
    tol = 1e-12 * scale
    n = len(V)
    for i in range(n):
        same = np.flatnonzero(np.linalg.norm(V[i + 1:] - V[i], axis=1) <= tol)
        if len(same):
            raise ValueError(f"polygon vertex {i + 1 + int(same[0])} repeats vertex {i} "
                             f"({V[i].tolist()}): list every corner once")
    a, b = V, np.roll(V, -1, axis=0)
    for i in range(n - 2):
        j = np.arange(i + 2, n - 1 if i == 0 else n)   # edges not adjacent to edge i
        meet = _segments_meet(a[i], b[i], a[j], b[j], tol) if len(j) else np.zeros(0, bool)
        if meet.any():
            k = int(j[meet][0])
            raise ValueError(f"polygon is self-intersecting: edge {i} ({a[i].tolist()} -> "
                             f"{b[i].tolist()}) meets edge {k} ({a[k].tolist()} -> {b[k].tolist()}); "
                             "give the outline of a simple polygon")
    return as_ccw(V)


def _segments_meet(p, q, A, B, tol):
    """(m,) bool: segment p -> q touches or crosses each segment A[k] -> B[k] (``tol``: a
    length below which coordinates count as equal)."""
    area_tol = tol * max(float(np.linalg.norm(q - p)), 1.0)

    def side(x):   # orientation sign, zero within the tolerance
        return np.where(np.abs(x) <= area_tol, 0.0, np.sign(x))
    d1, d2 = side(cross2(q - p, A - p)), side(cross2(q - p, B - p))
    d3, d4 = side(cross2(B - A, p - A)), side(cross2(B - A, q - A))
    # collinear pieces pass the sign test without meeting: their boxes must overlap too
    overlap = np.all(np.maximum(np.minimum(A, B), np.minimum(p, q))
                     <= np.minimum(np.maximum(A, B), np.maximum(p, q)) + tol, axis=1)
    return (d1 * d2 <= 0) & (d3 * d4 <= 0) & overlap


def contains(V: np.ndarray, P: np.ndarray) -> np.ndarray:
    """(P,) bool, even-odd rule (points exactly on the boundary may go either way)."""
    P = np.atleast_2d(P)
    x, y = P[:, 0:1], P[:, 1:2]
    a, b = V, np.roll(V, -1, axis=0)
    cond = (a[:, 1] > y) != (b[:, 1] > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        xint = a[:, 0] + (y - a[:, 1]) * (b[:, 0] - a[:, 0]) / (b[:, 1] - a[:, 1])
    return (np.sum(cond & (x < xint), axis=1) % 2) == 1


def distance_to_segment(P: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance from points P (..., d) to the segments a -> b (..., d), any dimension d,
    broadcasting over the leading axes: |P - (a + t (b - a))| with t the projection of P
    onto the segment's line clamped to [0, 1] (t = 0 on a zero-length segment)."""
    ab = b - a
    den = np.sum(ab * ab, -1)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.clip(np.sum((P - a) * ab, -1) / den, 0.0, 1.0)
    t = np.where(den > 0, t, 0.0)
    return np.linalg.norm(P - (a + t[..., None] * ab), axis=-1)


def distance_to_boundary(V: np.ndarray, P: np.ndarray) -> np.ndarray:
    """(P,) distance from each point to the nearest polygon edge."""
    P = np.atleast_2d(P)[:, None, :]
    return np.min(distance_to_segment(P, V[None], np.roll(V, -1, axis=0)[None]), axis=1)


def clip_halfplane(P: np.ndarray, n: np.ndarray, c: float, labels: np.ndarray | None = None,
                   label: int = -1):
    """Sutherland-Hodgman: the part of polygon P where n.x <= c (P may be non-convex).

    With edge ``labels`` (m,) (edge k runs P[k] -> P[k+1]) returns (polygon, labels) of the
    clipped polygon, the new edge along the clip line labelled ``label``."""
    m = len(P)
    if m == 0 and labels is None:
        return P
    L = np.zeros(m, np.int64) if labels is None else labels
    s = P @ n - c
    out, out_l = [], []
    for i in range(m):
        j = (i + 1) % m
        if s[i] <= 0:
            out.append(P[i])
            out_l.append(L[i] if (s[j] <= 0 or s[i] < 0) else label)
            if s[i] < 0 < s[j]:
                out.append(P[i] + s[i] / (s[i] - s[j]) * (P[j] - P[i]))
                out_l.append(label)
        elif s[j] < 0:
            out.append(P[i] + s[i] / (s[i] - s[j]) * (P[j] - P[i]))
            out_l.append(L[i])
    out = np.array(out).reshape(-1, 2)
    return out if labels is None else (out, np.array(out_l, dtype=np.int64))


def clip_convex(P: np.ndarray, C: np.ndarray) -> np.ndarray:
    """The part of polygon P inside the convex counter-clockwise polygon C."""
    for a, b in zip(C, np.roll(C, -1, axis=0)):
        e = b - a
        n = np.array([e[1], -e[0]])  # outward normal of a ccw edge
        P = clip_halfplane(P, n, float(n @ a))
        if len(P) < 3:
            return np.zeros((0, 2))
    return P


def voronoi_cells(X: np.ndarray, V: np.ndarray, k: int = 24, labelled: bool = False,
                  tol: float = 0.0) -> list:
    """Voronoi cell of every particle intersected with the domain polygon V.

    Each cell is the domain clipped by the bisector half-planes of the k nearest
    particles (enough for the quasi-uniform particle sets built here; the cell areas are
    checked to sum to the domain area). A cell is a counter-clockwise vertex array (m, 2)
    without repeated or collinear vertices, (0, 2) if empty. With ``labelled`` a cell is
    (vertices (m, 2), labels (m,)): the label of edge k (vertex k -> k+1) is the particle
    across it, -1 on the domain boundary; edges shorter than ``tol`` are dropped and
    collinear edges merged only where they carry the same label."""
    k = min(k, len(X) - 1)
    _, nbr = cKDTree(X).query(X, k=k + 1)
    cells = []
    for i, row in enumerate(nbr):
        cell, lab = V, -np.ones(len(V), np.int64)
        for j in row[1:]:
            n = X[j] - X[i]
            cell, lab = clip_halfplane(cell, n, float(n @ (X[i] + X[j]) / 2), lab, int(j))
            if len(cell) < 3:
                break
        cells.append(_clean_labelled(cell, lab, tol) if labelled else _drop_degenerate(cell))
    total = sum(area(P) for P in ([c for c, _ in cells] if labelled else cells) if len(P) >= 3)
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
            if np.linalg.norm(b - a) < tol * scale or abs(cross2(b - a, c - b)) < tol * scale**2:
                P = np.delete(P, i, axis=0)
                changed = True
                break
    return P if len(P) >= 3 else np.zeros((0, 2))


def _clean_labelled(P, L, tol):
    """Drop zero-length edges and merge collinear consecutive edges with the same label."""
    P, L = [p for p in P], [int(x) for x in L]
    changed = True
    while changed and len(P) >= 3:
        changed = False
        m = len(P)
        for k in range(m):
            k1 = (k + 1) % m
            if np.linalg.norm(P[k1] - P[k]) < tol:
                L[k] = L[k1]           # edge k vanishes: vertex k takes the next edge
                del P[k1], L[k1]
                changed = True
                break
            a, b, c = P[k - 1], P[k], P[k1]
            if L[k - 1] == L[k] and abs(cross2(b - a, c - b)) < tol * np.linalg.norm(c - a) \
                    and np.dot(b - a, c - b) > 0:
                del P[k], L[k]
                changed = True
                break
    if len(P) < 3:
        return np.zeros((0, 2)), np.zeros(0, np.int64)
    return np.array(P), np.array(L, np.int64)


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
            if cross2(b - a, c - b) <= 0:
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
        return cross2(q - p, Q - p)
    s1, s2, s3 = side(a, b), side(b, c), side(c, a)
    return bool(np.any((s1 > 0) & (s2 > 0) & (s3 > 0)))
