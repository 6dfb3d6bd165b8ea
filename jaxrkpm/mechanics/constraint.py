"""The essential boundary conditions inside jit: the map from the unknowns to the full RK
coefficients, d = T(u, g) (thesis eq 3.22), and the reduction of a tangent through it.

Not a term of the energy: the essential constraint contributes no energy of its own; every
term's energy is evaluated at d = T(u, g), and the tangent in the unknowns is T^T K T. So the
Problem holds it beside its terms (``Problem.constraint``), not in their sum.
"""
from __future__ import annotations

from dataclasses import replace
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..discretise.constraints import EssentialSets, Transformation, elimination_layout
from .term import Pairs, static, term


@term
class Essential:
    """d = T(u, g): free coefficients from u (Nf, d), the essential ones by eq 3.22,
    d_b = (D^b)^-1 (g - D^nb d_nb), so that u^h(X_b) = g exactly.

    free (Nf,), bnd (Nb,)   free and essential particle indices
    Dbinv (Nb, Nb)          (D^b)^-1
    nb_idx, nb_psi (Nb, Kb)  neighbours of the essential particles, Psi_J(X_b) (zero for
                            essential J)
    elim                    ``EliminationLayout``: (D^b)^-1 D^nb by independent component,
                            for the dense K_ff
    n, dim                  particles and dimension (static)
    """

    free: jax.Array
    bnd: jax.Array
    Dbinv: jax.Array
    nb_idx: jax.Array
    nb_psi: jax.Array
    elim: Any
    n: int = static(0)
    dim: int = static(0)

    def coefficients(self, u, g):
        """Full RK coefficients (N, d): free ones from u, essential ones by eq 3.22."""
        # the free and the essential particles are distinct: said, so that the derivatives of
        # these scatters are plain gathers (JAX otherwise tracks which of the duplicates won
        # with an integer scatter and gather of its own in every residual)
        d = jnp.zeros((self.n, self.dim), u.dtype).at[self.free].set(u, unique_indices=True)
        s = jnp.einsum("bk,bki->bi", self.nb_psi, d[self.nb_idx])
        return d.at[self.bnd].set(self.Dbinv @ (g - s), unique_indices=True)

    def point_values(self, idx, psi, u, g):
        """Displacement at points with precomputed (P, K) shape functions: (P, d)."""
        d = self.coefficients(u, g)
        return jnp.einsum("pk,pki->pi", psi, d[idx])

    def reactions(self, r_d):
        """dPi/dg (Nb, d) from the energy's gradient in the full coefficients r_d (N, d): the
        generalized force each essential particle's constraint exerts on the body."""
        return self.Dbinv.T @ r_d[self.bnd]

    def dense_tangent(self, blocks, pairs: Pairs):
        """K_ff = T^T K T with T = [I; -A] (the thesis transformation), dense (Nf*d, Nf*d), from
        the (P, d, d) pair blocks of K.

        The free-free pair blocks are scattered straight into K_ff's (particle, d, particle, d)
        layout (no full (N d)^2 matrix, transpose or row/column gathers), and the essential
        particles are eliminated one component at a time (``elimination_layout``):
        K_ff -= K_fb A + (K_fb A)^T, K_ff += A^T K_bb A on each component's rows and columns
        only (``experiments/bench_cube3d.py``). A pair of the other orientation is dropped
        (K_bf = K_fb^T: every term's tangent is symmetric)."""
        N, dim = self.n, blocks.shape[-1]
        Nf = self.free.shape[0]
        pos = jnp.full(N, Nf, jnp.int32).at[self.free].set(jnp.arange(Nf, dtype=jnp.int32))
        i, j = pos[pairs.i], pos[pairs.j]          # Nf (out of range, dropped): essential
        Kff = jnp.zeros((Nf, dim, Nf, dim), blocks.dtype).at[i, :, j, :].add(blocks, mode="drop")
        e = self.elim
        C, F, R = e.free.shape[0], e.free.shape[1], e.A.shape[1]
        if C:
            Kfb = jnp.zeros((C, F, dim, R, dim), blocks.dtype).at[e.fb[0], e.fb[1], :, e.fb[2], :].add(blocks, mode="drop")
            Kbb = jnp.zeros((C, R, dim, R, dim), blocks.dtype).at[e.bb[0], e.bb[1], :, e.bb[2], :].add(blocks, mode="drop")
            X = jnp.einsum("cfaRb,cRm->cfmab", Kfb, e.A)                     # (C, F, M, d, d)
            rows, cols = e.free[:, :, None], e.cols[:, None, :]
            Kff = Kff.at[rows, :, cols, :].add(-X)
            Kff = Kff.at[e.cols[:, :, None], :, e.free[:, None, :], :].add(-X.transpose(0, 2, 1, 4, 3))
            corr = jnp.einsum("cRm,cRaSb,cSn->cmnab", e.A, Kbb, e.A)          # (C, M, M, d, d)
            Kff = Kff.at[e.cols[:, :, None], :, cols, :].add(corr)
        n = Nf * dim
        return Kff.reshape(n, n)


def essential(sets: EssentialSets, trans: Transformation | None, n: int, dim: int,
              pair_i: np.ndarray, pair_j: np.ndarray) -> Essential:
    """The ``Essential`` constraint of ``sets`` (``trans``: their ``Transformation``, None
    where there are no essential particles) over n particles in ``dim`` dimensions, its
    elimination laid out over the tangent's pattern (pair_i, pair_j)."""
    Nf = len(sets.free)
    if trans is not None:
        A = trans.coupling(sets, n)
        Dbinv, nb_idx, nb_psi = trans.Dbinv, trans.nb_idx, trans.nb_psi
    else:
        A = np.zeros((0, Nf))
        Dbinv, nb_idx, nb_psi = np.zeros((0, 0)), np.zeros((0, 1), np.int64), np.zeros((0, 1))
    return Essential(free=jnp.asarray(sets.free, jnp.int32), bnd=jnp.asarray(sets.bnd, jnp.int32),
                     Dbinv=jnp.asarray(Dbinv), nb_idx=jnp.asarray(nb_idx, jnp.int32), nb_psi=jnp.asarray(nb_psi),
                     elim=jax.tree.map(jnp.asarray, elimination_layout(A, pair_i, pair_j, sets.free, sets.bnd)),
                     n=n, dim=dim)



@term
class HeldComponents:
    """d = T(u, g) where some sets hold only some components (``Roller``): the transformation
    of eq 3.22 written per held direction n, n . u^h(X_b) = n . g_b.

    Every held particle h gets an orthonormal frame Q_h whose first k_h rows span its held
    directions; its coefficient is d_h = Q_h^T c_h with the local components c_h: the first k_h
    follow from the constraints, the others are unknowns (u's row of h, where h is free; its
    first k_h entries are placeholders that no energy sees, given a unit stiffness in K_ff).
    With x the held local components of all held particles, C_h x = n . g - C_f d_f, so
    x = C_h^-1 (n . g - C_f d_f).

    free (Nf,), bnd (Nb,)    the unknowns' particles and the sets' entries (as ``Essential``)
    held (H,), frames (H, d, d), keep (H, d)   held particles, their frames, their free local
                             components (1) and held ones (0)
    c_entry (C,), c_n (C, d), c_idx, c_psi (C, K)   per constraint: its entry of bnd, its
                             direction, and the shape functions at its particle
    slot (2, C)              the held local component (held row, component) of each column of
    Cinv (C, C)              C_h^-1
    T (H, d, M, d), cols (M,)   the linear map from the unknowns' rows ``cols`` to the held
                             particles' coefficients (for K_ff = T^T K T)
    dummy (D,)               the placeholders' positions in the flat unknowns
    """

    free: jax.Array
    bnd: jax.Array
    held: jax.Array
    frames: jax.Array
    keep: jax.Array
    c_entry: jax.Array
    c_n: jax.Array
    c_idx: jax.Array
    c_psi: jax.Array
    slot: jax.Array
    Cinv: jax.Array
    T: jax.Array
    cols: jax.Array
    dummy: jax.Array
    n: int = static(0)
    dim: int = static(0)

    def _local(self, u):
        """All coefficients from u with the held particles' held local components zeroed, and
        those particles' local components (H, d)."""
        d = jnp.zeros((self.n, self.dim), u.dtype).at[self.free].set(u, unique_indices=True)
        loc = d[self.held] * self.keep
        return d.at[self.held].set(jnp.einsum("hmi,hm->hi", self.frames, loc), unique_indices=True), loc

    def coefficients(self, u, g):
        """Full RK coefficients (N, d) with every held component n . u^h(X_b) = n . g_b."""
        d, loc = self._local(u)
        s = jnp.einsum("ck,cki,ci->c", self.c_psi, d[self.c_idx], self.c_n)
        x = self.Cinv @ (jnp.einsum("ci,ci->c", g[self.c_entry], self.c_n) - s)
        loc = loc.at[self.slot[0], self.slot[1]].set(x, unique_indices=True)
        return d.at[self.held].set(jnp.einsum("hmi,hm->hi", self.frames, loc), unique_indices=True)

    def point_values(self, idx, psi, u, g):
        """Displacement at points with precomputed (P, K) shape functions: (P, d)."""
        d = self.coefficients(u, g)
        return jnp.einsum("pk,pki->pi", psi, d[idx])

    def reactions(self, r_d):
        """dPi/dg (Nb, d) from the energy's gradient in the full coefficients r_d (N, d): each
        entry's reaction, along its held directions only."""
        u0 = jnp.zeros((self.free.shape[0], self.dim), r_d.dtype)
        g0 = jnp.zeros((self.bnd.shape[0], self.dim), r_d.dtype)
        return jax.vjp(lambda g: self.coefficients(u0, g), g0)[1](r_d)[0]

    def dense_tangent(self, blocks, pairs: Pairs):
        """K_ff = T^T K T dense (Nf d, Nf d) from the (P, d, d) pair blocks of K: the free-free
        blocks of the particles no set holds scattered as they are, the held particles' through
        T (``T``, ``cols``)."""
        N, dim = self.n, blocks.shape[-1]
        Nf, H = self.free.shape[0], self.held.shape[0]
        is_held = jnp.zeros(N, bool).at[self.held].set(True)
        pu = jnp.full(N, Nf, jnp.int32).at[self.free].set(jnp.arange(Nf, dtype=jnp.int32))
        pu = jnp.where(is_held, Nf, pu)             # rows of u of the particles no set holds
        ph = jnp.full(N, H, jnp.int32).at[self.held].set(jnp.arange(H, dtype=jnp.int32))
        Kff = jnp.zeros((Nf, dim, Nf, dim), blocks.dtype).at[pu[pairs.i], :, pu[pairs.j], :].add(blocks, mode="drop")
        Kuh = jnp.zeros((Nf, dim, H, dim), blocks.dtype).at[pu[pairs.i], :, ph[pairs.j], :].add(blocks, mode="drop")
        Khh = jnp.zeros((H, dim, H, dim), blocks.dtype).at[ph[pairs.i], :, ph[pairs.j], :].add(blocks, mode="drop")
        X = jnp.einsum("fahb,hbmc->famc", Kuh, self.T)                  # (Nf, d, M, d)
        Kff = Kff.at[:, :, self.cols, :].add(X)
        Kff = Kff.at[self.cols, :, :, :].add(jnp.transpose(X, (2, 3, 0, 1)))
        corr = jnp.einsum("hamc,hagb,gbne->mcne", self.T, Khh, self.T)   # (M, d, M, d)
        Kff = Kff.at[self.cols[:, None], :, self.cols[None, :], :].add(jnp.transpose(corr, (0, 2, 1, 3)))
        n = Nf * dim
        K = Kff.reshape(n, n)
        # the placeholders: a unit stiffness at the scale of the others keeps K_ff regular
        scale = jnp.mean(jnp.abs(jnp.diagonal(K)))
        return K.at[self.dummy, self.dummy].add(scale)


def held_components(body, sets: EssentialSets, a: float, support, n: int, dim: int) -> HeldComponents:
    """The ``HeldComponents`` constraint of ``sets`` (some of them ``Roller``) over the n
    particles of ``body`` (kernel dilation ``a``)."""
    entries = sets.held(dim)
    held, where = np.unique(sets.bnd, return_inverse=True)
    H = len(held)
    dirs = [[] for _ in range(H)]
    for e, h in enumerate(where):
        dirs[h].extend(entries[e])
    frames = np.zeros((H, dim, dim))
    k = np.zeros(H, np.int64)
    for h, D in enumerate(dirs):
        D = np.asarray(D)
        sv = np.linalg.svd(D, compute_uv=False)
        if len(D) > dim or sv.min() < 1e-6:
            raise ValueError(f"particle {int(held[h])} at {body.X[held[h]].tolist()} is held by sets with "
                             "directions that are not independent (two rollers holding the same direction)")
        q = np.linalg.qr(D.T, mode="complete")[0].T    # first len(D) rows span the held directions
        frames[h], k[h] = q, len(D)
    keep = (np.arange(dim)[None] >= k[:, None]).astype(float)
    # one constraint per entry and held direction
    c_entry = np.concatenate([np.full(len(entries[e]), e) for e in range(len(entries))]).astype(np.int64)
    c_n = np.concatenate(entries)
    sf = body.shape_functions(body.X[held], a, gradients=False, support_factor=support)
    c_idx, c_psi = sf.idx[where[c_entry]], sf.psi[where[c_entry]]
    slot = np.stack([np.repeat(np.arange(H), k), np.concatenate([np.arange(m) for m in k])])
    hpos = -np.ones(n, np.int64)
    hpos[held] = np.arange(H)
    # C_h[c, (h, m)] = Psi_h(X_c) n_c . Q_h[m] over the held particles h near X_c
    col_of = -np.ones((H, dim), np.int64)
    col_of[slot[0], slot[1]] = np.arange(slot.shape[1])
    Ch = np.zeros((len(c_entry), len(c_entry)))
    for kk in range(c_idx.shape[1]):
        h = hpos[c_idx[:, kk]]
        on = (h >= 0) & (c_psi[:, kk] != 0)
        for m in range(dim):
            cols = col_of[h[on], m]
            use = cols >= 0
            rows = np.flatnonzero(on)[use]
            np.add.at(Ch, (rows, cols[use]), c_psi[rows, kk] * np.einsum("ci,ci->c", c_n[rows], frames[h[on][use], m]))
    cond = np.linalg.cond(Ch)
    if not np.isfinite(cond) or cond > 1e12:
        raise ValueError(f"the held-components matrix (eq 3.30 per direction) is singular (condition {cond:.3g}); "
                         "essential particles too close together for the support")
    Nf = len(sets.free)
    fpos = -np.ones(n, np.int64)
    fpos[sets.free] = np.arange(Nf)
    held_free = fpos[held] >= 0
    dummy = (fpos[held][held_free][:, None] * dim + np.arange(dim)[None])[keep[held_free] == 0]
    # the unknowns' rows that reach a held coefficient: the free particles near the held ones
    near = fpos[np.unique(c_idx[c_psi != 0])]
    cols = np.unique(np.concatenate([near[near >= 0], fpos[held][held_free]])).astype(np.int64)
    out = HeldComponents(free=jnp.asarray(sets.free, jnp.int32), bnd=jnp.asarray(sets.bnd, jnp.int32),
                         held=jnp.asarray(held, jnp.int32), frames=jnp.asarray(frames), keep=jnp.asarray(keep),
                         c_entry=jnp.asarray(c_entry, jnp.int32), c_n=jnp.asarray(c_n),
                         c_idx=jnp.asarray(c_idx, jnp.int32), c_psi=jnp.asarray(c_psi),
                         slot=jnp.asarray(slot, jnp.int32), Cinv=jnp.asarray(np.linalg.inv(Ch)),
                         T=jnp.zeros((H, dim, len(cols), dim)), cols=jnp.asarray(cols, jnp.int32),
                         dummy=jnp.asarray(dummy, jnp.int32), n=n, dim=dim)
    # T: the (linear) map from the unknowns' rows ``cols`` to the held coefficients
    g0 = jnp.zeros((len(sets.bnd), dim))

    def held_of(v):
        return out.coefficients(jnp.zeros((Nf, dim)).at[out.cols].set(v), g0)[out.held]

    T = jax.jacfwd(held_of)(jnp.zeros((len(cols), dim)))
    return replace(out, T=T)
