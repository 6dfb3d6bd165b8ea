"""Stabilized conforming nodal integration (SCNI, Chen et al. 2001/2002; thesis section 3.6).

Each particle L owns a smoothing cell Omega_L (its Voronoi cell clipped to the domain in 2D,
the box of half-spacing around it on a 3D grid). The gradient used at L is the smoothed one

    b_I(X_L) = (1/A_L) oint_{dOmega_L} Psi_I n dGamma,

evaluated on the cell facets. Every facet is evaluated ONCE and enters its two cells with
opposite signs, so interior facets cancel exactly and the integration constraint

    sum_L A_L b_I(X_L) = oint_Gamma Psi_I n dGamma          (every particle I)

holds to round-off: that is what makes nodal integration pass the patch test.

Mesh bodies (``Body.from_mesh``, 2D or 3D): the cells are the median-dual cells, each
particle's 1/(d+1) share of every adjacent simplex (their measures are the particles'
volumes). Inside a tetrahedron every edge (i, j) gives two triangles (edge midpoint, the
centroid of a face holding the edge, the tetrahedron's centroid) separating i's share from
j's (a triangle gives one segment, edge midpoint to centroid); each is evaluated once and
used with +n for i and -n for j. A surface face splits into its vertices' shares.

Boundary facets. With ``boundary="nodal"`` (default) Psi_I on a domain-boundary facet is
replaced by its piecewise-linear (2D) / bilinear (3D) interpolant between the boundary
particles (on a mesh body: the P1 interpolant on each surface face). The boundary term of
the constraint is then a combination of Psi_I(X_b) at
boundary particles, which the nodal essential BCs of the transformation method (eq 3.22)
can balance exactly: the affine patch test passes to round-off. ``boundary="gauss"``
integrates Psi_I itself on the boundary facets (more accurate gradients near the boundary,
patch test to O(h)). Both are exact for linear fields (sum_I b_I X_I^T = I).

Stabilisation (``stab`` = beta > 0; Model(integration="mscni") uses beta = 0.5). Nodal
integration under-integrates fields whose gradient oscillates inside a cell but whose cell
average is small (Puso, Chen, Zywicz & Elmer 2008). With the default support (2.01 h) plain
SCNI has no spurious zero-energy mode (only the rigid ones), but such modes carry too little
energy (the more so at a smaller support; experiments/scni_modes.py measures how much), and
they soften the response to strong compression. Each cell is split into sub-cells (the
triangles / pyramids from the cell centroid to each facet); their smoothed gradients b^s come
from the same shared-facet machinery and satisfy the integration constraint on their own. The
energy is the blend

    Pi = sum_L [(1 - beta) A_L W(F_L) + beta sum_{s in L} A_s W(F_s)],

i.e. the table simply gets the sub-cell rows with weights beta A_s. Since
sum_s A_s (F_s - F_L) = 0, expanding about F_L gives

    sum_s A_s W(F_s) = A_L W(F_L) + 1/2 sum_s A_s dF_s : C(F_L) : dF_s + O(dF^3),  dF_s = F_s - F_L,

so the stabilisation is Puso's modified-SCNI penalty on the sub-cell gradient jumps with the
current material tangent C, parameter beta; but it is written with true deformation
gradients only: frame-invariant, non-negative for a non-negative W, and it lives in the same
gather -> F -> W pipeline (no code change in the solver). beta = 1 is pure sub-cell smoothing.
On a mesh body the sub-cells are each particle's piece of each adjacent simplex (the dual
facets inside the simplex bound two pieces; a face shared by two simplices separates the
particle's two pieces there).
"""
from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np
import scipy.sparse as sp

from . import mesh
from . import polygons
from .body import Body
from .quadrature import Table, segment_rule, simplex_rule, tensor_rule, triangle_rule

# integration name accepted by Model -> (stabilisation beta, boundary rule)
SCHEMES = {
    "scni": (0.0, "nodal"),     # Chen et al. 2001 SCNI: one smoothed point per particle
    "mscni": (0.5, "nodal"),    # + sub-cell stabilisation (modified SCNI, see above)
}


def _rot(t):
    """Outward normal of a counter-clockwise edge with tangent t (2D): t rotated by -90 deg."""
    return np.stack([t[..., 1], -t[..., 0]], -1)


# ================================================================== facet bookkeeping
class _Builder:
    """Rows (cells and sub-cells) and facets: each facet's quadrature points are added once,
    with the list of (row, sign) that use them."""

    def __init__(self, d):
        self.d = d
        self.row_pts, self.row_level, self.row_owner = [], [], []
        self.pts, self.wts, self.nrm, self.bnd = [], [], [], []
        self.inc_row, self.inc_pt, self.inc_sign = [], [], []
        self.face = []     # per facet point: the mesh surface face it lies on, else -1
        self.mesh_faces = None   # (M, d) surface faces of a mesh body, indexed by ``face``
        self.npts = 0

    def row(self, point, level, owner):
        self.row_pts.append(np.asarray(point, float))
        self.row_level.append(level)
        self.row_owner.append(owner)
        return len(self.row_pts) - 1

    def facet(self, pts, wts, normal, uses, boundary=False):
        g = len(pts)
        ids = np.arange(self.npts, self.npts + g)
        self.pts.append(pts)
        self.wts.append(wts)
        self.nrm.append(np.broadcast_to(normal, (g, self.d)))
        self.bnd.append(np.full(g, boundary))
        self.face.append(np.full(g, -1))
        for r, s in uses:
            self.inc_row.append(np.full(g, r))
            self.inc_pt.append(ids)
            self.inc_sign.append(np.full(g, float(s)))
        self.npts += g

    def rows(self, points, level, owners):
        """Many rows at once: points (R, d), owners (R,); returns their row indices (R,)."""
        start = len(self.row_pts)
        self.row_pts.extend(np.asarray(points, float))
        self.row_level.extend([level] * len(points))
        self.row_owner.extend(np.asarray(owners).tolist())
        return start + np.arange(len(points))

    def facets(self, pts, wts, normals, rows, signs, boundary=False, face=None):
        """Many facets at once: points (F, g, d), weights (F, g), normals (F, d); facet f is
        used by rows[f, u] with sign signs[u] (rows (F, U), -1: no use); ``face`` (F,) the
        mesh surface face of each (boundary) facet."""
        F, g = wts.shape
        ids = self.npts + np.arange(F * g).reshape(F, g)
        self.pts.append(pts.reshape(-1, self.d))
        self.wts.append(wts.ravel())
        self.nrm.append(np.repeat(normals, g, axis=0))
        self.bnd.append(np.full(F * g, boundary))
        self.face.append(np.full(F * g, -1) if face is None else np.repeat(face, g))
        for u in range(rows.shape[1]):
            use = rows[:, u] >= 0
            self.inc_row.append(np.repeat(rows[use, u], g))
            self.inc_pt.append(ids[use].ravel())
            self.inc_sign.append(np.full(use.sum() * g, float(signs[u])))
        self.npts += F * g


def _rect_rule(lo, hi, ax, val, order):
    """Tensor Gauss rule on the axis-aligned rectangle {x_ax = val} x [lo, hi] (3D)."""
    uv, w = tensor_rule(order, 2)
    a1, a2 = [i for i in range(3) if i != ax]
    pts = np.zeros((len(uv), 3))
    pts[:, ax] = val
    pts[:, a1] = lo[a1] + uv[:, 0] * (hi[a1] - lo[a1])
    pts[:, a2] = lo[a2] + uv[:, 1] * (hi[a2] - lo[a2])
    return pts, w * (hi[a1] - lo[a1]) * (hi[a2] - lo[a2])


def _build_2d(body: Body, order, stabilised):
    h = body.spacing
    V = body.vertices
    cells = polygons.voronoi_cells(body.X, V, labelled=True, tol=1e-11 * h)
    N = body.n
    B = _Builder(2)
    for i in range(N):
        B.row(body.X[i], 0, i)
    sub, cent = _fan_rows(B, cells, stabilised, h)
    for i, (P, L) in enumerate(cells):
        _cell_edges(B, cells, sub, i, order)
        if sub[i] is not None and sub[i][0] != sub[i][-1]:
            _spokes(B, P, cent[i], sub[i], order)
    return B


def _fan_rows(B: _Builder, cells, stabilised, h):
    """The sub-cell rows of every 2D cell: fan triangles (centroid, v_k, v_k+1); a cell whose
    fan is not positive (non-convex cell) keeps a single sub-cell equal to itself. Returns
    sub[i][k] (the row of the sub-cell holding edge k of cell i; None: not stabilised) and
    each cell's centroid."""
    sub = []
    cent = []
    for i, (P, L) in enumerate(cells):
        if not stabilised or len(P) < 3:
            sub.append(None)
            cent.append(None)
            continue
        c = polygons.centroid(P)
        tri_area = 0.5 * polygons.cross2(P - c, np.roll(P, -1, axis=0) - c)
        if np.all(tri_area > 1e-12 * h * h):
            sub.append([B.row((c + P[k] + P[(k + 1) % len(P)]) / 3, 1, i) for k in range(len(P))])
        else:
            r = B.row(polygons.centroid(P), 1, i)
            sub.append([r] * len(P))
        cent.append(c)
    return sub, cent


def _sub_row_near(cells, sub, j, p):
    """Sub-cell of cell j whose outer edge is nearest to the point p."""
    P = cells[j][0]
    return sub[j][int(np.argmin(polygons.distance_to_segment(p, P, np.roll(P, -1, axis=0))))]


def _cell_edges(B: _Builder, cells, sub, i, order):
    """The edges of 2D cell i that no earlier cell evaluated, each used by both cells (and
    their sub-cells)."""
    P, L = cells[i]
    m = len(P)
    for k in range(m):
        a, b, j = P[k], P[(k + 1) % m], int(L[k])
        if j >= 0 and j < i:
            continue                        # evaluated by cell j
        pts, w = segment_rule(a, b, order)
        n = _rot(b - a) / np.linalg.norm(b - a)
        uses = [(i, 1)]
        if sub[i] is not None:
            uses.append((sub[i][k], 1))
        if j >= 0:
            uses.append((j, -1))
            if sub[j] is not None:
                uses.append((_sub_row_near(cells, sub, j, 0.5 * (a + b)), -1))
        B.facet(pts, w, n, uses, boundary=j < 0)


def _spokes(B: _Builder, P, c, rows, order):
    """The spokes c -> v_k of a fanned cell, between its fan triangles k-1 and k."""
    for k in range(len(P)):
        pts, w = segment_rule(c, P[k], order)
        n = _rot(P[k] - c) / np.linalg.norm(P[k] - c)
        B.facet(pts, w, n, [(rows[k], 1), (rows[k - 1], -1)])


def _lattice(body: Body):
    h = body.spacing
    ijk = np.rint((body.X - body.lower) / h).astype(np.int64)
    shape = tuple(ijk.max(0) + 1)
    if (not body.is_box or np.abs(body.lower + ijk * h - body.X).max() > 1e-9 * h
            or np.prod(shape) != body.n or len(np.unique(ijk, axis=0)) != body.n):
        raise ValueError("SCNI in 3D needs a regular grid body (Body.grid with 3 entries)")
    lookup = -np.ones(shape, np.int64)
    lookup[tuple(ijk.T)] = np.arange(body.n)
    return ijk, shape, lookup


_BOX_FACES = [(ax, s) for ax in range(3) for s in (-1, 1)]   # a 3D cell's faces: (axis, side)


def _build_3d(body: Body, order, stabilised):
    h = body.spacing
    ijk, shape, lookup = _lattice(body)
    lo = np.maximum(body.X - h / 2, body.lower)
    hi = np.minimum(body.X + h / 2, body.upper)
    N = body.n
    B = _Builder(3)
    for i in range(N):
        B.row(body.X[i], 0, i)
    sub = _pyramid_rows(B, lo, hi) if stabilised else None
    for i in range(N):
        for f, (ax, s) in enumerate(_BOX_FACES):
            nb = ijk[i].copy()
            nb[ax] += s
            inside = 0 <= nb[ax] < shape[ax]
            j = int(lookup[tuple(nb)]) if inside else -1
            if j >= 0 and j < i:
                continue
            _box_face(B, lo[i], hi[i], i, j, f, sub, order)
        if sub is not None:
            _pyramid_facets(B, lo[i], hi[i], sub[i], order)
    return B


def _pyramid_rows(B: _Builder, lo, hi):
    """(N, 6) the rows of each box cell's six pyramids (centre to a face), at their centroids."""
    sub = np.zeros((len(lo), 6), np.int64)
    for i in range(len(lo)):
        c = 0.5 * (lo[i] + hi[i])
        for f, (ax, s) in enumerate(_BOX_FACES):
            fc = c.copy()
            fc[ax] = hi[i, ax] if s > 0 else lo[i, ax]
            sub[i, f] = B.row(c + 0.75 * (fc - c), 1, i)   # pyramid centroid
    return sub


def _box_face(B: _Builder, lo, hi, i, j, f, sub, order):
    """Face f of box cell i (lo, hi), shared with cell j (-1: on the boundary)."""
    ax, s = _BOX_FACES[f]
    val = hi[ax] if s > 0 else lo[ax]
    pts, w = _rect_rule(lo, hi, ax, val, order)
    n = np.zeros(3)
    n[ax] = s
    uses = [(i, 1)]
    if sub is not None:
        uses.append((sub[i, f], 1))
    if j >= 0:
        uses.append((j, -1))
        if sub is not None:
            uses.append((sub[j, _BOX_FACES.index((ax, -s))], -1))
    B.facet(pts, w, n, uses, boundary=j < 0)


def _pyramid_facets(B: _Builder, lo, hi, rows, order):
    """The 12 triangles (centre, box edge) between the pyramids ``rows`` (6,) of one box cell."""
    c = 0.5 * (lo + hi)
    for f1, (ax1, s1) in enumerate(_BOX_FACES):
        for f2, (ax2, s2) in enumerate(_BOX_FACES):
            if ax2 <= ax1:
                continue
            ax3 = 3 - ax1 - ax2
            e0 = c.copy()
            e0[ax1] = hi[ax1] if s1 > 0 else lo[ax1]
            e0[ax2] = hi[ax2] if s2 > 0 else lo[ax2]
            e1 = e0.copy()
            e0[ax3], e1[ax3] = lo[ax3], hi[ax3]
            pts, w = triangle_rule(c, e0, e1, order)
            n = np.cross(e0 - c, e1 - c)
            n /= np.linalg.norm(n)
            fc2 = c.copy()
            fc2[ax2] = e0[ax2]
            if n @ (fc2 - c) < 0:        # orient out of pyramid f1, into pyramid f2
                n = -n
            B.facet(pts, w, n, [(rows[f1], 1), (rows[f2], -1)])


# ============================================================ mesh bodies: median dual
# barycentric coordinate of a simplex vertex at the centroid of its median-dual piece: the
# mean of the largest of d+1 uniform barycentric coordinates, H_{d+1} / (d+1)
_PIECE_OWN = {2: 11 / 18, 3: 25 / 48}


def _facet_rule(S, order, towards):
    """Gauss points (F, g, d), weights (F, g) and unit normals (F, d) on facet simplices
    S (F, d, d) (segments in 2D, triangles in 3D), normals turned along ``towards`` (F, d)."""
    lam, w = simplex_rule(order, S.shape[2] - 1)
    n, size = mesh.facet_normals(S)
    n = np.where(np.sum(n * towards, 1, keepdims=True) < 0, -n, n)
    return np.einsum("gk,fkd->fgd", lam, S), size[:, None] * w[None], n


def _face_shares(V, fc):
    """Each face vertex's share of a face: face vertices V (M, d, d), centroids fc (M, d) ->
    per vertex j a list of facet simplices (M, d, d) (3D: two triangles vertex - edge
    midpoint - face centroid; 2D: the half edge vertex - midpoint)."""
    d = V.shape[1]
    shares = []
    for j in range(d):
        p = V[:, j]
        mids = [(p + V[:, k]) / 2 for k in range(d) if k != j]
        if d == 2:
            shares.append([np.stack([p, mids[0]], 1)])
        else:
            shares.append([np.stack([p, mids[0], fc], 1), np.stack([p, fc, mids[1]], 1)])
    return shares


def _build_mesh(body: Body, order, stabilised):
    """Median-dual smoothing cells of a mesh body (see the module docstring)."""
    X, cells = body.X, body.cells
    C, n = cells.shape
    d = n - 1
    B = _Builder(d)
    B.rows(X, 0, np.arange(body.n))
    V = X[cells]                                            # (C, n, d)
    g = V.mean(1)
    sub = None
    if stabilised:                                          # (C, n): row of vertex k's piece of cell c
        lam = np.full((n, n), (1 - _PIECE_OWN[d]) / d)
        np.fill_diagonal(lam, _PIECE_OWN[d])
        sub = B.rows(np.einsum("kj,cjd->ckd", lam, V).reshape(-1, d), 1, cells.ravel()).reshape(C, n)
    signs = (1, -1, 1, -1)
    for a, b in combinations(range(n), 2):                  # dual facets inside the cells
        m = (V[:, a] + V[:, b]) / 2
        if d == 2:
            pieces = [np.stack([m, g], 1)]
        else:
            pieces = [np.stack([m, (V[:, a] + V[:, b] + V[:, k]) / 3, g], 1)
                      for k in range(n) if k not in (a, b)]
        rows = [cells[:, a], cells[:, b]] + ([sub[:, a], sub[:, b]] if stabilised else [])
        for S in pieces:
            B.facets(*_facet_rule(S, order, V[:, b] - V[:, a]), np.stack(rows, 1), signs)

    faces, fcell, flocal = mesh.boundary_faces(X, cells)    # surface: each vertex's share
    fV = X[faces]
    outward = mesh.facet_normals(fV)[0]
    local = np.argmax(cells[fcell][:, None, :] == faces[:, :, None], axis=2)   # (M, d)
    for j, share in enumerate(_face_shares(fV, fV.mean(1))):
        rows = [faces[:, j]] + ([sub[fcell, local[:, j]]] if stabilised else [])
        for S in share:
            B.facets(*_facet_rule(S, order, outward), np.stack(rows, 1), (1, 1), boundary=True,
                     face=np.arange(len(faces)))
    B.mesh_faces = faces
    if stabilised:                                          # interior faces between two pieces
        _, face_id, counts = mesh.face_counts(cells)
        shared = np.flatnonzero(counts[face_id.ravel()] == 2)
        shared = shared[np.argsort(face_id.ravel()[shared], kind="stable")].reshape(-1, 2)
        c1, k1 = np.divmod(shared[:, 0], n)
        c2 = shared[:, 1] // n
        F = cells[c1][np.arange(n)[None] != k1[:, None]].reshape(-1, d)   # the face, as in c1
        fV = X[F]
        fc = fV.mean(1)
        towards = fc - X[cells[c1, k1]]                     # out of c1, into c2
        l1 = np.argmax(cells[c1][:, None, :] == F[:, :, None], axis=2)
        l2 = np.argmax(cells[c2][:, None, :] == F[:, :, None], axis=2)
        for j, share in enumerate(_face_shares(fV, fc)):
            rows = np.stack([sub[c1, l1[:, j]], sub[c2, l2[:, j]]], 1)
            for S in share:
                B.facets(*_facet_rule(S, order, towards), rows, signs)
    return B


def _boundary_stencils_mesh(X, faces, face_of_point, P):
    """P1 interpolation on the mesh surface face holding each boundary point P (G, d): the
    face's vertices (G, d) and the point's barycentric coordinates there (G, d)."""
    idx = faces[face_of_point]
    V = X[idx]
    E = V[:, 1:] - V[:, :1]                                 # (G, d-1, d)
    lam = np.linalg.solve(E @ np.swapaxes(E, 1, 2), np.einsum("gkd,gd->gk", E, P - V[:, 0])[..., None])[..., 0]
    return idx, np.concatenate([1 - lam.sum(1, keepdims=True), lam], 1)


# ===================================================== nodal (interpolated) boundary rule
def _lagrange_window(t_nodes, t, degree):
    """For sorted node parameters (m,) and points t (G,): the (G, p+1) indices of the p+1
    nodes nearest each point (a window bracketing it) and the Lagrange weights there."""
    p = min(degree, len(t_nodes) - 1)
    k = np.clip(np.searchsorted(t_nodes, t, side="right") - 1, 0, len(t_nodes) - 2)
    first = np.clip(k - (p - 1) // 2, 0, len(t_nodes) - 1 - p)
    win = first[:, None] + np.arange(p + 1)[None]
    tn = t_nodes[win]                                          # (G, p+1)
    w = np.ones_like(tn)
    for j in range(p + 1):
        for m in range(p + 1):
            if m != j:
                w[:, j] *= (t - tn[:, m]) / (tn[:, j] - tn[:, m])
    return win, w


def _boundary_stencils_2d(body: Body, P, degree):
    """For boundary points P (G, 2): the boundary particles on the point's polygon edge that
    interpolate it (Lagrange, ``degree``) and their weights: (G, S) indices, (G, S) weights."""
    V = body.vertices
    tol = 1e-9 * body.spacing
    S = degree + 1
    idx = np.zeros((len(P), S), np.int64)
    wts = np.zeros((len(P), S))
    done = np.zeros(len(P), bool)
    for a, b in zip(V, np.roll(V, -1, axis=0)):
        ab = b - a
        sel = (~done) & (polygons.distance_to_segment(P, a, b) < tol)
        if not sel.any():
            continue
        on = np.flatnonzero(polygons.distance_to_segment(body.X, a, b) < tol)
        t_on = (body.X[on] - a) @ ab / (ab @ ab)
        order = np.argsort(t_on)
        on, t_on = on[order], t_on[order]
        if len(on) < 2 or t_on[0] > 1e-9 or t_on[-1] < 1 - 1e-9:
            raise ValueError("SCNI boundary='nodal' needs boundary particles at every polygon vertex "
                             "(use boundary='gauss')")
        win, w = _lagrange_window(t_on, (P[sel] - a) @ ab / (ab @ ab), degree)
        idx[sel, :win.shape[1]] = on[win]
        wts[sel, :win.shape[1]] = w
        done |= sel
    if not done.all():
        raise ValueError("SCNI: a boundary facet point lies on no polygon edge")
    return idx, wts


def _boundary_stencils_3d(body: Body, P, degree):
    """Tensor-product Lagrange interpolation between the grid particles of the box face
    holding each point."""
    h = body.spacing
    ijk, shape, lookup = _lattice(body)
    tol = 1e-9 * h
    S = (degree + 1) ** 2
    idx = np.zeros((len(P), S), np.int64)
    wts = np.zeros((len(P), S))
    done = np.zeros(len(P), bool)
    for ax in range(3):
        for s, val in ((0, body.lower[ax]), (shape[ax] - 1, body.upper[ax])):
            sel = (~done) & (np.abs(P[:, ax] - val) < tol)
            if not sel.any():
                continue
            a1, a2 = [i for i in range(3) if i != ax]
            u = (P[sel] - body.lower) / h
            w1i, w1 = _lagrange_window(np.arange(shape[a1], dtype=float), u[:, a1], degree)
            w2i, w2 = _lagrange_window(np.arange(shape[a2], dtype=float), u[:, a2], degree)
            q = np.zeros((sel.sum(), w1i.shape[1], w2i.shape[1], 3), np.int64)
            q[..., ax] = s
            q[..., a1] = w1i[:, :, None]
            q[..., a2] = w2i[:, None, :]
            m = w1i.shape[1] * w2i.shape[1]
            idx[sel, :m] = lookup[tuple(np.moveaxis(q, -1, 0))].reshape(-1, m)
            wts[sel, :m] = (w1[:, :, None] * w2[:, None, :]).reshape(-1, m)
            done |= sel
    if not done.all():
        raise ValueError("SCNI: a boundary facet point lies on no face of the box")
    return idx, wts


# ========================================================================== assembly
@dataclass(frozen=True)
class Smoothing:
    """The SCNI integration of a body.

    table      the integration Table the Model consumes: rows 0..N-1 are the particles' cells
               (points X_L, weights (1 - beta) A_L), then the sub-cells when stabilised
               (points at their centroids, weights beta A_s); idx/psi/dpsi over the union of
               the particles touching each row's facets (padding: index 0, psi = dpsi = 0)
    areas      (R,) measure of every row's cell / sub-cell (cells first: areas[:N] = A_L)
    level      (R,) 0 for particle cells, 1 for sub-cells; owner (R,) the particle of each row
    boundary_integral (N, d) oint_Gamma Psi_I n dGamma with the same boundary rule: the
               right-hand side of the integration constraint
    boundary   that boundary rule as a Table: its points, weights, outward normals and the
               shape-function rows it integrates (the interpolated Psi of the 'nodal' rule),
               so that a boundary load summed over it is exactly what the cells' stresses
               balance (sum_q w_q psi_q n_q = boundary_integral); dpsi is not set (zeros)
    """

    table: Table
    areas: np.ndarray
    level: np.ndarray
    owner: np.ndarray
    beta: float
    boundary_integral: np.ndarray
    boundary: Table


def build(body: Body, a: float, stab: float = 0.5, boundary: str = "nodal",
          order: int = 2, support_factor=None, nodal_degree: int = 1) -> Smoothing:
    """Smoothing cells, shared-facet quadrature and the SCNI Table of ``body`` for the RK
    dilation ``a``. ``stab`` = beta in [0, 1] (0: plain SCNI), ``order`` Gauss points per
    facet direction, ``boundary`` 'nodal' | 'gauss' (see the module docstring);
    ``nodal_degree``: the Lagrange degree of the 'nodal' rule's boundary interpolant on grid
    and polygon bodies (a mesh body's is P1 on its surface faces)."""
    _check_options(stab, boundary, order)
    d, N = body.dim, body.n
    Bd = _facets(body, order, stab > 0)

    pts = np.concatenate(Bd.pts)
    wts = np.concatenate(Bd.wts)
    nrm = np.concatenate(Bd.nrm)
    isb = np.concatenate(Bd.bnd)
    inc_row = np.concatenate(Bd.inc_row)
    inc_pt = np.concatenate(Bd.inc_pt)
    inc_sign = np.concatenate(Bd.inc_sign)
    row_pts = np.array(Bd.row_pts)
    level = np.array(Bd.row_level)
    owner = np.array(Bd.row_owner)
    R = len(row_pts)

    def sf(P):
        return body.shape_functions(P, a, gradients=False, support_factor=support_factor)

    ent_pt, ent_I, ent_v = _facet_psi(body, Bd, pts, isb, boundary, sf, nodal_degree)
    areas = _row_areas(body, R, level, owner, inc_row, inc_pt, inc_sign, pts, wts, nrm)

    # (row, particle) -> oint Psi n as sparse products: incidences (R, points) x Psi at the
    # facet points (points, N), one product per normal component
    Psi = sp.csr_matrix((ent_v, (ent_pt, ent_I)), shape=(len(pts), N))
    A = sp.csr_matrix((inc_sign * wts[inc_pt], (inc_row, inc_pt)), shape=(R, len(pts)))
    G = [(A @ sp.diags(nrm[:, k]) @ Psi).tocoo() for k in range(d)]

    # boundary integral oint_Gamma Psi_I n (the constraint's right-hand side)
    bint = np.stack([Psi.T @ np.where(isb, wts * nrm[:, k], 0.0) for k in range(d)], 1)
    bnd = _padded_rows(Psi[isb], pts[isb], wts[isb], nrm[isb])

    idx, psi, dpsi = _row_pattern(G, sf(row_pts), areas, N)
    weights = np.where(level == 0, (1.0 - stab) * areas, stab * areas)
    keep = weights > 0            # beta = 1: the cell rows carry no weight
    tab = Table(row_pts[keep], weights[keep], idx[keep], psi[keep], dpsi[keep])
    return Smoothing(tab, areas, level, owner, float(stab), bint, bnd)


def _check_options(stab, boundary, order) -> None:
    if not 0.0 <= stab <= 1.0:
        raise ValueError(f"SCNI stabilisation beta must lie in [0, 1], got {stab}")
    if boundary not in ("nodal", "gauss"):
        raise ValueError(f"SCNI boundary rule must be 'nodal' or 'gauss', got {boundary!r}")
    if order < 1:
        raise ValueError(f"facet Gauss order must be >= 1, got {order}")


def _facets(body: Body, order, stabilised) -> _Builder:
    """The rows and facets of the body's smoothing cells: a mesh body's median dual, a 2D
    body's clipped Voronoi cells, a 3D grid's boxes."""
    if body.cells is not None:
        return _build_mesh(body, order, stabilised)
    if body.dim == 2:
        if body.vertices is None:
            raise ValueError("SCNI in 2D needs the domain polygon (Body.grid or Body.polygon)")
        return _build_2d(body, order, stabilised)
    return _build_3d(body, order, stabilised)


def _facet_psi(body: Body, Bd: _Builder, pts, isb, boundary, sf, degree):
    """Psi at every facet point as sparse entries (point, particle, value): the shape
    functions themselves, but on the boundary under the 'nodal' rule their interpolant
    between the boundary particles."""
    inner = np.flatnonzero(~isb) if boundary == "nodal" else np.arange(len(pts))
    s_in = sf(pts[inner])
    ent_pt = [np.repeat(inner, s_in.idx.shape[1])]
    ent_I = [s_in.idx.ravel()]
    ent_v = [s_in.psi.ravel()]
    if boundary == "nodal" and isb.any():
        bpts = np.flatnonzero(isb)
        st_idx, st_w = _boundary_stencils(body, Bd, pts, bpts, degree)
        nodes = np.unique(st_idx)
        s_nodes = sf(body.X[nodes])
        where = np.searchsorted(nodes, st_idx)            # (Gb, S) rows of s_nodes
        Kn = s_nodes.idx.shape[1]
        ent_pt.append(np.repeat(bpts, st_idx.shape[1] * Kn))
        ent_I.append(s_nodes.idx[where].ravel())
        ent_v.append((st_w[..., None] * s_nodes.psi[where]).ravel())
    return map(np.concatenate, (ent_pt, ent_I, ent_v))


def _boundary_stencils(body: Body, Bd: _Builder, pts, bpts, degree):
    """The boundary particles interpolating each boundary facet point pts[bpts], and their
    weights (the 'nodal' rule)."""
    if body.cells is not None:
        return _boundary_stencils_mesh(body.X, Bd.mesh_faces, np.concatenate(Bd.face)[bpts], pts[bpts])
    return (_boundary_stencils_2d if body.dim == 2 else _boundary_stencils_3d)(body, pts[bpts], degree)


def _row_areas(body: Body, R, level, owner, inc_row, inc_pt, inc_sign, pts, wts, nrm) -> np.ndarray:
    """(R,) each row's measure from its facets (divergence theorem, exact for linear
    integrands), checked positive and the cells' sum against the body's measure."""
    d = body.dim
    areas = np.zeros(R)
    np.add.at(areas, inc_row, inc_sign * wts[inc_pt] * np.sum(pts[inc_pt] * nrm[inc_pt], 1) / d)
    if np.any(areas <= 0):
        r = int(np.argmin(areas))
        raise ValueError(f"SCNI: smoothing cell {r} (particle {owner[r]}) has measure {areas[r]:.3g}")
    total = areas[level == 0].sum()
    if abs(total - body.measure) > 1e-9 * body.measure:
        raise ValueError(f"SCNI cells cover {total} of the domain measure {body.measure}")
    return areas


def _row_pattern(G, s_row, areas, N):
    """The table's (idx, psi, dpsi), (R, K[, d]): per row the union of the particles of its
    smoothed gradient (the sparse G, one per component, over its area) and of the shape
    functions at its point ``s_row``, padded (index 0, values 0)."""
    R, d = len(areas), len(G)
    key_g = np.concatenate([g.row.astype(np.int64) * N + g.col for g in G])
    key_p = (np.arange(R)[:, None] * N + s_row.idx).ravel()
    uniq, inv = np.unique(np.concatenate([key_g, key_p]), return_inverse=True)
    grad = np.zeros((len(uniq), d))
    pos = 0
    for k, g in enumerate(G):
        np.add.at(grad[:, k], inv[pos:pos + g.nnz], g.data)
        pos += g.nnz
    val = np.zeros(len(uniq))
    np.add.at(val, inv[len(key_g):], s_row.psi.ravel())
    rows, parts = uniq // N, uniq % N
    grad /= areas[rows][:, None]
    counts = np.bincount(rows, minlength=R)
    K = int(counts.max())
    slot = np.arange(len(uniq)) - np.repeat(np.cumsum(counts) - counts, counts)
    idx = np.zeros((R, K), np.int32)
    psi = np.zeros((R, K))
    dpsi = np.zeros((R, K, d))
    idx[rows, slot] = parts
    psi[rows, slot] = val
    dpsi[rows, slot] = grad
    return idx, psi, dpsi


def _padded_rows(Psi, points, weights, normals) -> Table:
    """The boundary Table of sparse shape-function rows Psi (B, N) at ``points``: each row's
    nonzeros padded to the longest (index 0, psi 0)."""
    Psi = sp.csr_matrix(Psi)
    Psi.sum_duplicates()
    counts = np.diff(Psi.indptr)
    K = max(1, int(counts.max(initial=0)))
    rows = np.repeat(np.arange(Psi.shape[0]), counts)
    slot = np.arange(Psi.nnz) - np.repeat(Psi.indptr[:-1], counts)
    idx = np.zeros((Psi.shape[0], K), np.int32)
    psi = np.zeros((Psi.shape[0], K))
    idx[rows, slot] = Psi.indices
    psi[rows, slot] = Psi.data
    return Table(points, weights, idx, psi, np.zeros((*idx.shape, points.shape[1])), normals)


def smoothing(body: Body, a: float, scheme: str = "scni", order: int = 2, support_factor=None) -> Smoothing:
    """The Smoothing of ``Model(integration=scheme)`` (its ``table`` is the volume rule)."""
    if scheme not in SCHEMES:
        raise ValueError(f"unknown SCNI scheme {scheme!r}: choose one of {list(SCHEMES)}")
    stab, bnd = SCHEMES[scheme]
    return build(body, a, stab, bnd, order, support_factor)

