"""Host-side sparse linear algebra of the Newton solver (large systems).

The constrained tangent system is the saddle-point form of the thesis transformation,

    [K  C^T] [dd]   [r]
    [C   0 ] [l ] = [0],      C dd = 0  <=>  dd = T du_f,

whose free part solves K_ff du_f = T^T K T du_f = r exactly. C = [D^nb D^b] (x) I has sparse
LU factors (D^b is banded) while T (through (D^b)^-1) is dense per essential set, so the
saddle-point matrix is factorised instead of K_ff. Everything structural is done once:

* a geometric nested-dissection ordering of the particles (each essential particle's
  multipliers right after its own coefficients, so the factorisation needs no pivoting:
  every multiplier pivot is preceded by the coefficient pivot it constrains);
* the CSC pattern of the permuted saddle-point matrix and the position of every tangent
  block entry in it: each Newton iteration only writes the data array.

Factorisations are reused: the last positive definite factorisation preconditions a
conjugate-gradient solve of K_ff x = r (matrix-vector products with the current K and T);
only when CG stalls or meets negative curvature is the current matrix factorised again.
The factorisation's pivots give the inertia: the number of negative pivots minus the
number of constraints is the number of negative eigenvalues of K_ff (Haynsworth).
"""
from __future__ import annotations

import threading

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla


def nested_dissection(X: np.ndarray, indptr: np.ndarray, indices: np.ndarray, leaf: int = 64) -> np.ndarray:
    """Fill-reducing order of n nodes with coordinates X (n, dim) and the symmetric
    adjacency (indptr, indices) (CSR): recursive median bisection along the longest extent;
    the nodes of the upper half adjacent to the lower half form the separator, numbered last."""
    n = X.shape[0]
    mark = np.zeros(n, bool)
    parts = []

    def rec(nodes):
        if len(nodes) <= leaf:
            parts.append(nodes)
            return
        x = X[nodes]
        ax = int(np.argmax(x.max(0) - x.min(0)))
        lower = x[:, ax] < np.median(x[:, ax])
        if lower.all() or not lower.any():
            parts.append(nodes)
            return
        lo, hi = nodes[lower], nodes[~lower]
        mark[lo] = True
        starts, stops = indptr[hi], indptr[hi + 1]
        lens = stops - starts
        flat = np.repeat(starts - np.cumsum(np.r_[0, lens[:-1]]), lens) + np.arange(lens.sum())
        owner = np.repeat(np.arange(len(hi)), lens)
        touch = np.zeros(len(hi), bool)
        touch[owner[mark[indices[flat]]]] = True
        mark[lo] = False
        rec(lo)
        rec(hi[~touch])
        parts.append(hi[touch])

    rec(np.arange(n))
    return np.concatenate(parts)


class SaddlePointSystem:
    """The permuted saddle-point pattern, its data map, and the factorisation cache."""

    cg_rtol = 1e-11     # relative residual of the preconditioned CG solves
    cg_maxiter = 40     # beyond this the current matrix is factorised instead
    cg_maxiter_sparsified = 400  # with the sparsified (3D) preconditioner
    stencil = 2.0       # 3D preconditioner: pairs within this many spacings are kept

    def __init__(self, X: np.ndarray, rows: np.ndarray, cols: np.ndarray, C, free_dofs: np.ndarray,
                 bnd: np.ndarray, dim: int):
        N = X.shape[0]
        d = dim
        n_dof = N * d
        C = sp.csr_matrix(C)
        nc = C.shape[0]
        self.n_dof, self.nc, self.n = n_dof, nc, n_dof + nc
        self.free_dofs = np.asarray(free_dofs, np.int64)
        self.bnd_dofs = (np.asarray(bnd, np.int64)[:, None] * d + np.arange(d)).ravel()

        self._X, self._d, self._bnd = X, d, np.asarray(bnd, np.int64)
        self.inv = self._ordering(rows, cols)
        Ccoo = C.tocoo()
        self._c_entries = (np.concatenate([Ccoo.row + n_dof, Ccoo.col]),
                           np.concatenate([Ccoo.col, Ccoo.row + n_dof]),
                           np.concatenate([Ccoo.data, Ccoo.data]))
        self.indices, self.indptr, self.pos_K, self.template = self._pattern(rows, cols, self.inv)

        # 3D: the exact factorisation fills too much (a 20^3 grid: ~2.6e8 factor entries,
        # minutes per factorisation), so CG is preconditioned by the factorisation of a
        # sparsified tangent instead: pairs beyond ``stencil`` spacings (Chebyshev distance)
        # are dropped and each dropped entry's magnitude is added to its row's diagonal, so
        # the preconditioner dominates K (P - K is positive semidefinite: P is positive
        # definite wherever K is).
        self.sparsified = dim == 3
        if self.sparsified:
            dist = np.abs(X[rows // d] - X[cols // d]).max(1)
            h = np.min(dist[dist > 0]) if np.any(dist > 0) else 1.0
            keep = dist <= self.stencil * h * (1 + 1e-9)
            self.keep, self.drop_rows = np.flatnonzero(keep), rows[~keep]
            self.drop = np.flatnonzero(~keep)
            # its own ordering: separators of the sparser graph are thinner (a 14^3 grid:
            # 26.5 -> 16.7 million factor entries, factorisation 8.7 -> 6.1 s)
            kr, kc = rows[keep], cols[keep]
            self.p_inv = self._ordering(kr, kc)
            (self.p_indices, self.p_indptr, self.p_pos_K,
             self.p_template) = self._pattern(kr, kc, self.p_inv)
            diag = np.flatnonzero(kr == kc)
            self.p_diag_pos = self.p_pos_K[diag]
            self.p_diag_row = kr[diag]

        self.Cf = C[:, self.free_dofs].tocsr()
        self.Cf_T = self.Cf.T.tocsr()
        self.Cb_lu = spla.splu(C[:, self.bnd_dofs].tocsc()) if nc else None
        self._lu = None           # last positive definite factorisation (a preconditioner)
        self._lock = threading.Lock()
        self.stats = {"factorisations": 0, "cg_solves": 0, "cg_iterations": 0}

    # ----------------------------------------------------------------------- pieces
    def _ordering(self, rows, cols):
        """old -> new dof positions: nested dissection of the particle graph of the K
        entries (rows, cols) (block order: d*d entries a pair), each particle's dofs followed
        (essential particles) by its multipliers."""
        X, d, bnd = self._X, self._d, self._bnd
        N, n_dof = X.shape[0], self.n_dof
        pi, pj = rows[::d * d] // d, cols[::d * d] // d
        G = sp.csr_matrix((np.ones(len(pi), np.int8), (pi, pj)), shape=(N, N))
        order = nested_dissection(X, G.indptr, G.indices)
        is_b = np.zeros(N, bool)
        is_b[bnd] = True
        bpos = -np.ones(N, np.int64)
        bpos[bnd] = np.arange(len(bnd))
        per = d + d * is_b[order]
        node = np.repeat(order, per)
        k = np.arange(per.sum()) - np.repeat(np.cumsum(per) - per, per)
        perm = np.where(k < d, node * d + k, n_dof + bpos[node] * d + (k - d))   # new -> old
        inv = np.empty_like(perm)
        inv[perm] = np.arange(len(perm))
        return inv

    def _pattern(self, rows, cols, inv):
        """CSC pattern (permuted by inv) of the saddle-point matrix with K entries (rows, cols):
        indices, indptr, the data position of each K entry, and the data with C filled in."""
        cr, cc, cv = self._c_entries
        rn = inv[np.concatenate([rows, cr])]
        cn = inv[np.concatenate([cols, cc])]
        key = cn.astype(np.int64) * self.n + rn
        srt = np.argsort(key, kind="stable")
        if np.any(np.diff(key[srt]) == 0):
            raise ValueError("duplicate entries in the tangent pattern")
        pos = np.empty_like(srt)
        pos[srt] = np.arange(len(srt))
        indices = rn[srt].astype(np.int32)
        indptr = np.searchsorted(cn[srt], np.arange(self.n + 1)).astype(np.int32)
        template = np.zeros(len(srt))
        template[pos[len(rows):]] = cv
        return indices, indptr, pos[:len(rows)], template

    def preconditioner_matrix(self, blocks) -> sp.csc_matrix:
        """The sparsified, diagonally compensated saddle-point matrix (3D)."""
        b = np.asarray(blocks, np.float64).ravel()
        data = self.p_template.copy()
        data[self.p_pos_K] = b[self.keep]
        add = np.bincount(self.drop_rows, np.abs(b[self.drop]), minlength=self.n_dof)
        data[self.p_diag_pos] += add[self.p_diag_row]
        return sp.csc_matrix((data, self.p_indices, self.p_indptr), shape=(self.n, self.n))

    def matrix(self, blocks) -> sp.csc_matrix:
        data = self.template.copy()
        data[self.pos_K] = np.asarray(blocks, np.float64).ravel()
        return sp.csc_matrix((data, self.indices, self.indptr), shape=(self.n, self.n))

    def _factorise(self, A, inv=None):
        inv = self.inv if inv is None else inv
        lu = spla.splu(A, permc_spec="NATURAL", diag_pivot_thresh=0.0,
                       options=dict(SymmetricMode=True))
        self.stats["factorisations"] += 1
        if np.array_equal(lu.perm_r, lu.perm_c):       # symmetric (static) pivoting: inertia
            neg = int(np.count_nonzero(lu.U.diagonal() < 0)) - self.nc
        else:                                           # pivoting happened: inertia unknown
            neg = 0
        return (lu, inv), neg

    def _direct(self, lu, b):
        lu, inv = lu
        B = np.zeros((self.n, b.shape[1]))
        B[inv[self.free_dofs]] = b
        return lu.solve(B)[inv[self.free_dofs]]

    def _matvec(self, A, v):
        """K_ff v = T^T K T v with the current K (A is symmetric: CSC = CSR of itself)."""
        dd = np.zeros(self.n)
        full = np.zeros(self.n_dof)
        full[self.free_dofs] = v
        if self.nc:
            full[self.bnd_dofs] = -self.Cb_lu.solve(self.Cf @ v)
        dd[self.inv[:self.n_dof]] = full
        y = (A.T @ dd)[self.inv[:self.n_dof]]   # A.T of a CSC is a CSR view: a fast product
        out = y[self.free_dofs]
        if self.nc:
            out = out - self.Cf_T @ self.Cb_lu.solve(y[self.bnd_dofs], trans="T")
        return out

    def _pcg(self, A, lu, b, maxiter, rtol):
        """CG on K_ff x = b preconditioned by a previous factorisation, to the relative
        residual rtol; returns x, or None when it stalls or meets negative curvature."""
        bn = np.linalg.norm(b)
        x = np.zeros_like(b)
        if bn == 0:
            return x
        r = b.copy()
        z = self._direct(lu, r[:, None])[:, 0]
        p = z.copy()
        rz = r @ z
        for it in range(1, maxiter + 1):
            Ap = self._matvec(A, p)
            pAp = p @ Ap
            if not pAp > 0:
                return None
            a = rz / pAp
            x += a * p
            r -= a * Ap
            if np.linalg.norm(r) <= rtol * bn:
                self.stats["cg_iterations"] += it
                return x
            z = self._direct(lu, r[:, None])[:, 0]
            rz, rz_old = r @ z, rz
            p = z + (rz / rz_old) * p
        return None

    # ----------------------------------------------------------------------- solve
    def solve(self, blocks, rhs, rtol=None):
        """x (rhs.shape) with K_ff x = rhs (iterative solves to the relative residual rtol,
        default cg_rtol), and whether K_ff looked positive definite."""
        rtol = self.cg_rtol if rtol is None else float(rtol)
        rhs = np.asarray(rhs, np.float64)
        b = rhs.reshape(len(self.free_dofs), -1)
        with self._lock:
            A = self.matrix(blocks)
            maxiter = self.cg_maxiter_sparsified if self.sparsified else self.cg_maxiter
            if self._lu is not None:
                x = self._pcg_all(A, self._lu, b, maxiter, rtol)
                if x is not None:
                    self.stats["cg_solves"] += 1
                    return x.reshape(rhs.shape), np.bool_(True)
            if not self.sparsified:
                lu, neg = self._factorise(A)
                x = self._direct(lu, b)
                self._lu = lu if neg == 0 else None
                return x.reshape(rhs.shape), np.bool_(neg == 0)
            lu, neg = self._factorise(self.preconditioner_matrix(blocks), self.p_inv)
            self._lu = lu if neg == 0 else None   # P - K >= 0: P indefinite => K_ff indefinite
            x = self._pcg_all(A, lu, b, maxiter, rtol) if neg == 0 else None
            if x is not None:
                self.stats["cg_solves"] += 1
                return x.reshape(rhs.shape), np.bool_(True)
            # negative curvature (K_ff indefinite) or no convergence: GMRES on the same operator
            op = spla.LinearOperator((len(self.free_dofs),) * 2, matvec=lambda v: self._matvec(A, v))
            M = spla.LinearOperator(op.shape, matvec=lambda v: self._direct(lu, v.reshape(-1, 1))[:, 0])
            cols = [spla.gmres(op, b[:, j], M=M, rtol=rtol, restart=200, maxiter=5)[0]
                    for j in range(b.shape[1])]
            return np.stack(cols, 1).reshape(rhs.shape), np.bool_(False)

    def _pcg_all(self, A, lu, b, maxiter, rtol):
        cols = []
        for j in range(b.shape[1]):
            xj = self._pcg(A, lu, b[:, j], maxiter, rtol)
            if xj is None:
                return None
            cols.append(xj)
        return np.stack(cols, 1)

    def reset(self):
        """Forget the cached factorisation and zero the statistics."""
        with self._lock:
            self._lu = None
            self.stats = dict.fromkeys(self.stats, 0)
