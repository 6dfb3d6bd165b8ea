"""Stabilized conforming nodal integration (SCNI, Chen et al. 2001/2002; thesis section 3.6).

Each particle L owns a smoothing cell Omega_L (its Voronoi cell clipped to the domain in 2D,
the box of half-spacing around it on a 3D grid). The gradient used at L is the smoothed one

    b_I(X_L) = (1/A_L) oint_{dOmega_L} Psi_I n dGamma,

evaluated on the cell facets. Every facet is evaluated ONCE and enters its two cells with
opposite signs, so interior facets cancel exactly and the integration constraint

    sum_L A_L b_I(X_L) = oint_Gamma Psi_I n dGamma          (every particle I)

holds to round-off: that is what makes nodal integration pass the patch test.

Boundary facets. With ``boundary="nodal"`` (default) Psi_I on a domain-boundary facet is
replaced by its piecewise-linear (2D) / bilinear (3D) interpolant between the boundary
particles. The boundary term of the constraint is then a combination of Psi_I(X_b) at
boundary particles, which the nodal essential BCs of the transformation method (eq 3.22)
can balance exactly: the affine patch test passes to round-off. ``boundary="gauss"``
integrates Psi_I itself on the boundary facets (more accurate gradients near the boundary,
patch test to O(h)). Both are exact for linear fields (sum_I b_I X_I^T = I).

Stabilisation (``stab`` = beta > 0; Model(integration="mscni") uses beta = 0.5). Nodal
integration under-integrates fields whose gradient oscillates inside a cell but whose cell
average is small (Puso, Chen, Zywicz & Elmer 2008). With the default support (2.01 h) plain
SCNI has no spurious zero-energy mode (only the rigid ones), but such modes carry up to ~7x
too little energy (~25x at support 1.5 h; experiments/scni_modes.py), and they soften the
response to strong compression. Each cell is split into sub-cells (the triangles / pyramids
from the cell centroid to each facet); their smoothed gradients b^s come from the same
shared-facet machinery and satisfy the integration constraint on their own. The energy is
the blend

    Pi = sum_L [(1 - beta) A_L W(F_L) + beta sum_{s in L} A_s W(F_s)],

i.e. the table simply gets the sub-cell rows with weights beta A_s. Since
sum_s A_s (F_s - F_L) = 0, expanding about F_L gives

    sum_s A_s W(F_s) = A_L W(F_L) + 1/2 sum_s A_s dF_s : C(F_L) : dF_s + O(dF^3),  dF_s = F_s - F_L,

so the stabilisation is Puso's modified-SCNI penalty on the sub-cell gradient jumps with the
current material tangent C, parameter beta; but it is written with true deformation
gradients only: frame-invariant, non-negative for a non-negative W, and it lives in the same
gather -> F -> W pipeline (no code change in the solver). beta = 1 is pure sub-cell smoothing.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import polygons
from .geometry import Body
from .integration import Table, segment_rule, tensor_rule, triangle_rule

# integration name accepted by Model -> (stabilisation beta, boundary rule)
SCHEMES = {
    "scni": (0.0, "nodal"),     # Chen et al. 2001 SCNI: one smoothed point per particle
    "mscni": (0.5, "nodal"),    # + sub-cell stabilisation (modified SCNI, see above)
}
DEFAULT_STAB = 0.5
NODAL_DEGREE = 1   # Lagrange degree of the boundary interpolant of the 'nodal' rule


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
        for r, s in uses:
            self.inc_row.append(np.full(g, r))
            self.inc_pt.append(ids)
            self.inc_sign.append(np.full(g, float(s)))
        self.npts += g


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
    # sub-cells: fan triangles (centroid, v_k, v_k+1); a cell whose fan is not positive
    # (non-convex cell) keeps a single sub-cell equal to itself
    sub = []   # sub[i][k] -> row of the sub-cell holding edge k of cell i
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

    def sub_row_near(j, p):
        """Sub-cell of cell j whose outer edge is nearest to the point p."""
        P = cells[j][0]
        return sub[j][int(np.argmin(polygons.distance_to_segment(p, P, np.roll(P, -1, axis=0))))]

    for i, (P, L) in enumerate(cells):
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
                    uses.append((sub_row_near(j, 0.5 * (a + b)), -1))
            B.facet(pts, w, n, uses, boundary=j < 0)
        if sub[i] is not None and sub[i][0] != sub[i][-1]:
            c = cent[i]
            for k in range(m):                  # spokes c -> v_k between triangles k-1 and k
                pts, w = segment_rule(c, P[k], order)
                n = _rot(P[k] - c) / np.linalg.norm(P[k] - c)
                B.facet(pts, w, n, [(sub[i][k], 1), (sub[i][k - 1], -1)])
    return B


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


def _build_3d(body: Body, order, stabilised):
    h = body.spacing
    ijk, shape, lookup = _lattice(body)
    lo = np.maximum(body.X - h / 2, body.lower)
    hi = np.minimum(body.X + h / 2, body.upper)
    N = body.n
    B = _Builder(3)
    for i in range(N):
        B.row(body.X[i], 0, i)
    faces = [(ax, s) for ax in range(3) for s in (-1, 1)]
    sub = None
    if stabilised:
        sub = np.zeros((N, 6), np.int64)
        for i in range(N):
            c = 0.5 * (lo[i] + hi[i])
            for f, (ax, s) in enumerate(faces):
                fc = c.copy()
                fc[ax] = hi[i, ax] if s > 0 else lo[i, ax]
                sub[i, f] = B.row(c + 0.75 * (fc - c), 1, i)   # pyramid centroid
    for i in range(N):
        for f, (ax, s) in enumerate(faces):
            val = hi[i, ax] if s > 0 else lo[i, ax]
            nb = ijk[i].copy()
            nb[ax] += s
            inside = 0 <= nb[ax] < shape[ax]
            j = int(lookup[tuple(nb)]) if inside else -1
            if j >= 0 and j < i:
                continue
            pts, w = _rect_rule(lo[i], hi[i], ax, val, order)
            n = np.zeros(3)
            n[ax] = s
            uses = [(i, 1)]
            if sub is not None:
                uses.append((sub[i, f], 1))
            if j >= 0:
                uses.append((j, -1))
                if sub is not None:
                    uses.append((sub[j, faces.index((ax, -s))], -1))
            B.facet(pts, w, n, uses, boundary=j < 0)
        if sub is not None:                      # 12 triangles (centre, box edge) per cell
            c = 0.5 * (lo[i] + hi[i])
            for f1, (ax1, s1) in enumerate(faces):
                for f2, (ax2, s2) in enumerate(faces):
                    if ax2 <= ax1:
                        continue
                    ax3 = 3 - ax1 - ax2
                    e0 = c.copy()
                    e0[ax1] = hi[i, ax1] if s1 > 0 else lo[i, ax1]
                    e0[ax2] = hi[i, ax2] if s2 > 0 else lo[i, ax2]
                    e1 = e0.copy()
                    e0[ax3], e1[ax3] = lo[i, ax3], hi[i, ax3]
                    pts, w = triangle_rule(c, e0, e1, order)
                    n = np.cross(e0 - c, e1 - c)
                    n /= np.linalg.norm(n)
                    fc2 = c.copy()
                    fc2[ax2] = e0[ax2]
                    if n @ (fc2 - c) < 0:        # orient out of pyramid f1, into pyramid f2
                        n = -n
                    B.facet(pts, w, n, [(sub[i, f1], 1), (sub[i, f2], -1)])
    return B


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
    """

    table: Table
    areas: np.ndarray
    level: np.ndarray
    owner: np.ndarray
    beta: float
    boundary_integral: np.ndarray


def build(body: Body, a: float, stab: float = DEFAULT_STAB, boundary: str = "nodal",
          order: int = 2, support_factor=None) -> Smoothing:
    """Smoothing cells, shared-facet quadrature and the SCNI Table of ``body`` for the RK
    dilation ``a``. ``stab`` = beta in [0, 1] (0: plain SCNI), ``order`` Gauss points per
    facet direction, ``boundary`` 'nodal' | 'gauss' (see the module docstring)."""
    if not 0.0 <= stab <= 1.0:
        raise ValueError(f"SCNI stabilisation beta must lie in [0, 1], got {stab}")
    if boundary not in ("nodal", "gauss"):
        raise ValueError(f"SCNI boundary rule must be 'nodal' or 'gauss', got {boundary!r}")
    if order < 1:
        raise ValueError(f"facet Gauss order must be >= 1, got {order}")
    d, N = body.dim, body.n
    if d == 2:
        if body.vertices is None:
            raise ValueError("SCNI in 2D needs the domain polygon (Body.grid or Body.polygon)")
        Bd = _build_2d(body, order, stab > 0)
    else:
        Bd = _build_3d(body, order, stab > 0)

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

    # Psi at every facet point as sparse rows (point, particle, value)
    inner = np.flatnonzero(~isb) if boundary == "nodal" else np.arange(len(pts))
    s_in = sf(pts[inner])
    ent_pt = [np.repeat(inner, s_in.idx.shape[1])]
    ent_I = [s_in.idx.ravel()]
    ent_v = [s_in.psi.ravel()]
    if boundary == "nodal" and isb.any():
        bpts = np.flatnonzero(isb)
        st_idx, st_w = (_boundary_stencils_2d if d == 2 else _boundary_stencils_3d)(
            body, pts[bpts], NODAL_DEGREE)
        nodes = np.unique(st_idx)
        s_nodes = sf(body.X[nodes])
        where = np.searchsorted(nodes, st_idx)            # (Gb, S) rows of s_nodes
        Kn = s_nodes.idx.shape[1]
        ent_pt.append(np.repeat(bpts, st_idx.shape[1] * Kn))
        ent_I.append(s_nodes.idx[where].ravel())
        ent_v.append((st_w[..., None] * s_nodes.psi[where]).ravel())
    ent_pt, ent_I, ent_v = map(np.concatenate, (ent_pt, ent_I, ent_v))

    # row measures from the same facets (divergence theorem, exact for linear integrands)
    areas = np.zeros(R)
    np.add.at(areas, inc_row, inc_sign * wts[inc_pt] * np.sum(pts[inc_pt] * nrm[inc_pt], 1) / d)
    if np.any(areas <= 0):
        r = int(np.argmin(areas))
        raise ValueError(f"SCNI: smoothing cell {r} (particle {owner[r]}) has measure {areas[r]:.3g}")
    total = areas[level == 0].sum()
    if abs(total - body.measure) > 1e-9 * body.measure:
        raise ValueError(f"SCNI cells cover {total} of the domain measure {body.measure}")

    # (row, particle) -> oint Psi n: expand incidences x facet-point entries
    order_pt = np.argsort(ent_pt, kind="stable")
    ent_pt, ent_I, ent_v = ent_pt[order_pt], ent_I[order_pt], ent_v[order_pt]
    start = np.searchsorted(ent_pt, np.arange(len(pts)))
    count = np.searchsorted(ent_pt, np.arange(len(pts)), side="right") - start
    c_inc = count[inc_pt]
    rep_row = np.repeat(inc_row, c_inc)
    offs = np.arange(c_inc.sum()) - np.repeat(np.cumsum(c_inc) - c_inc, c_inc)
    e = np.repeat(start[inc_pt], c_inc) + offs
    coef = np.repeat(inc_sign * wts[inc_pt], c_inc)[:, None] * ent_v[e][:, None] * nrm[np.repeat(inc_pt, c_inc)]
    key_g = rep_row * N + ent_I[e]

    # boundary integral oint_Gamma Psi_I n (the constraint's right-hand side)
    bsel = isb[ent_pt]
    bint = np.zeros((N, d))
    np.add.at(bint, ent_I[bsel], (wts[ent_pt[bsel]] * ent_v[bsel])[:, None] * nrm[ent_pt[bsel]])

    # shape values at the row points
    s_row = sf(row_pts)
    key_p = (np.arange(R)[:, None] * N + s_row.idx).ravel()
    keys = np.concatenate([key_g, key_p])
    uniq, inv = np.unique(keys, return_inverse=True)
    grad = np.zeros((len(uniq), d))
    np.add.at(grad, inv[:len(key_g)], coef)
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

    weights = np.where(level == 0, (1.0 - stab) * areas, stab * areas)
    keep = weights > 0            # beta = 1: the cell rows carry no weight
    tab = Table(row_pts[keep], weights[keep], idx[keep], psi[keep], dpsi[keep])
    return Smoothing(tab, areas, level, owner, float(stab), bint)


def table(body: Body, a: float, scheme: str = "scni", order: int = 2, support_factor=None) -> Table:
    """The integration Table for ``Model(integration=scheme)``."""
    if scheme not in SCHEMES:
        raise ValueError(f"unknown SCNI scheme {scheme!r}: choose one of {list(SCHEMES)}")
    stab, bnd = SCHEMES[scheme]
    return build(body, a, stab, bnd, order, support_factor).table
