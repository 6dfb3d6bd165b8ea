"""The essential boundary conditions inside jit: the map from the unknowns to the full RK
coefficients, d = T(u, g) (thesis eq 3.22), and the reduction of a tangent through it.

Not a term of the energy: the essential constraint contributes no energy of its own; every
term's energy is evaluated at d = T(u, g), and the tangent in the unknowns is T^T K T. So the
Problem holds it beside its terms (``Problem.constraint``), not in their sum.
"""
from __future__ import annotations

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

