"""Newton-Krylov linear solves for large systems: conjugate gradients on K_ff = T^T K T,
preconditioned by a smoothed-aggregation algebraic multigrid hierarchy (pyamg) that is
built rarely and reused across Newton iterations and load steps.

Why: a sparse direct factorisation of a 3D RKPM tangent fills heavily (the kernels reach
two spacings, so every particle couples to ~300 others: 7e7 factor entries at a 20^3 cube)
and its cost grows as n^2 in 3D; CG with an AMG V-cycle costs a few matrix-vector products
per iteration, and a hierarchy built at one state keeps preconditioning the tangents of
nearby states. No factorisation of K_ff is ever formed.

* The matrix. K is the (N d, N d) tangent in the full coefficients, as a block-sparse (BSR)
  matrix whose blocks are exactly the assembled (P, d, d) pair blocks (the pairs are sorted
  by (i, j): no pattern map is built). K_ff v = T^T K T v goes through the host-side
  transformation (``jaxrkpm.discretise.constraints.HostElimination``), as in the sparse path.
* The preconditioner. AMG of K restricted to the free particles (K_nn: the essential
  particles' coupling through (D^b)^-1 is left out: it is dense per set and only touches the
  particles near the held faces), with the rigid-body modes evaluated at the free particles
  as the near-nullspace (the linear RK basis reproduces them exactly in the coefficients).
  It is rebuilt from the current tangent only when CG needs more than ``growth`` x the
  iterations per decade of residual reduction that it needed just after it was built, or
  does not converge.
* Outcomes. A CG solve converges (to ``rtol`` on the true residual |K_ff x - b| / |b|),
  meets negative curvature (p.K_ff p <= 0: a certificate that K_ff is not positive
  definite) or runs out of iterations (``KrylovStatus``). The Newton step reports the last
  as ``Stability.FAILED``, which ends the Newton attempt with ``Status.LINEAR_SOLVE`` (the
  load step is cut, as for any failure); a ``solve`` that does not converge returns NaN.
  Stability: positive definite is inferred where CG converged without meeting negative
  curvature (as the sparse path infers it for its CG solves): not a proof.

Runs on the host (``jax.pure_callback``), so it is for CPU; on a GPU the dense path runs
without a callback.
"""
from __future__ import annotations

import copy
import threading

import numpy as np
import scipy.sparse as sp

from ...base.outcome import Outcome
from ...discretise.constraints import HostElimination
from .factorisations import HostWork, block_matrix, block_pattern, kff, pooled


class KrylovStatus(Outcome):
    """Outcome of one CG solve (an int code inside jit)."""

    CONVERGED = 0, "CG reached its tolerance on the true residual"
    MAX_ITERATIONS = 1, "CG did not reach its tolerance within maxiter iterations"
    NEGATIVE_CURVATURE = 2, "CG met a direction p with p.K_ff p <= 0: K_ff is not positive definite"
    NONE = 3, "no solve yet (a fresh state)"


def rigid_modes(X: np.ndarray) -> np.ndarray:
    """The rigid-body modes at the points X (n, d) as (n d, m) columns (m = 3 in 2D, 6 in 3D):
    translations and infinitesimal rotations about the centroid, in coefficient order
    (point-major). The linear RK basis reproduces them exactly."""
    n, d = X.shape
    Y = X - X.mean(0)
    cols = [np.tile(np.eye(d)[k], n) for k in range(d)]
    for a, b in ([(0, 1)] if d == 2 else [(0, 1), (1, 2), (0, 2)]):
        r = np.zeros((n, d))
        r[:, a], r[:, b] = -Y[:, b], Y[:, a]
        cols.append(r.ravel())
    return np.stack(cols, 1)


class KrylovSystem:
    """The host-side pieces, immutable once built (part of the static solver configuration):
    the BSR pattern of K from the sorted particle pairs, the free-free part the hierarchy is
    built on, the transformation T and the near-nullspace.

    Its work is reported per call in ``LinearStats`` (``factorisations``: hierarchies built,
    ``cg_solves`` and ``cg_iterations``: CG's, ``factorise_s``: set-up seconds, ``cg_s``, and
    ``matrix_s``: the matrix made from the blocks)."""

    drop = 0.01                 # pair blocks weaker than this (relative) are left out of the hierarchy
    curvature_roundoff = 1e-10  # p.Kp below this x |p| |Kp| in magnitude is round-off, not curvature

    def __init__(self, X: np.ndarray, pair_i: np.ndarray, pair_j: np.ndarray, C, free: np.ndarray,
                 bnd: np.ndarray, rtol: float = 1e-10, maxiter: int = 500, growth: float = 2.0):
        import pyamg  # noqa: F401  (a clear ImportError now, not inside a callback)

        N, d = X.shape
        self._options(rtol, maxiter, growth)
        pair_i, pair_j = np.asarray(pair_i, np.int64), np.asarray(pair_j, np.int64)
        self.N, self.d = N, d
        self.indptr, self.indices = block_pattern(pair_i, pair_j, N)
        free = np.asarray(free, np.int64)
        pos = -np.ones(N, np.int64)
        pos[free] = np.arange(len(free))
        keep = (pos[pair_i] >= 0) & (pos[pair_j] >= 0)
        self.keep_ff = np.flatnonzero(keep)                     # pairs of two free particles
        self.indptr_ff = np.searchsorted(pos[pair_i[keep]], np.arange(len(free) + 1)).astype(np.int32)
        self.indices_ff = pos[pair_j[keep]].astype(np.int32)
        self.rows_ff = pos[pair_i[keep]].astype(np.int32)
        self.free_dofs = (free[:, None] * d + np.arange(d)).ravel()
        bnd_dofs = (np.asarray(bnd, np.int64)[:, None] * d + np.arange(d)).ravel()
        self.elimination = HostElimination(C, self.free_dofs, bnd_dofs)
        self.B = rigid_modes(X[free])
        for a in (self.indptr, self.indices, self.keep_ff, self.indptr_ff, self.indices_ff, self.rows_ff,
                  self.free_dofs, self.B):
            a.setflags(write=False)

    def _options(self, rtol, maxiter, growth):
        if not (isinstance(rtol, float) and 0 < rtol < 1):
            raise ValueError(f"rtol must be a number in (0, 1) (CG's relative residual), got {rtol!r}")
        if not (isinstance(maxiter, (int, np.integer)) and maxiter > 0):
            raise ValueError(f"maxiter must be a positive integer (CG iterations), got {maxiter!r}")
        if not (isinstance(growth, (int, float)) and growth >= 1):
            raise ValueError(f"growth must be a number >= 1 (iterations per decade, relative to a "
                             f"fresh hierarchy's, beyond which it is rebuilt), got {growth!r}")
        self.rtol, self.maxiter, self.growth = float(rtol), int(maxiter), float(growth)

    def replace(self, **options) -> "KrylovSystem":
        """A copy with other ``rtol``, ``maxiter`` or ``growth`` (the arrays are shared)."""
        unknown = set(options) - {"rtol", "maxiter", "growth"}
        if unknown:
            raise ValueError(f"unknown option(s) {sorted(unknown)}: choose rtol, maxiter, growth")
        other = copy.copy(self)
        merged = {"rtol": self.rtol, "maxiter": self.maxiter, "growth": self.growth, **options}
        other._options(merged["rtol"], merged["maxiter"], merged["growth"])
        return other

    @property
    def n_free(self) -> int:
        return len(self.free_dofs)

    def matrix(self, blocks, work: HostWork | None = None) -> sp.bsr_matrix:
        """K (N d, N d): the pair blocks as they are (no copy of the data); ``work`` (of this
        method and the others) the call's ledger, where one counts."""
        with HostWork.of(work).timed("matrix_s"):
            return block_matrix(blocks, self.indptr, self.indices)

    def hierarchy(self, blocks, work: HostWork | None = None):
        """A smoothed-aggregation AMG hierarchy of K_nn (free particles) for ``blocks``, with
        the pair blocks weaker than ``drop`` x sqrt(|K_ii| |K_jj|) (Frobenius norms) left out: an
        RKPM particle couples to ~300 others, most of them weakly; measured at a 14^3 cube,
        dropping below 0.02 keeps 28% of the blocks, CG needs the same 30 iterations (to
        1e-10) and a V-cycle costs a third (0.05 dropped too much: CG did not converge).
        Every kept block counts as a strong connection for the aggregation (theta = 0: the
        dropping already chose them): larger aggregates and a lower operator complexity, with
        fewer CG iterations at ``drop`` = 0.01 than at 0.02 or 0.005
        (``experiments/bench_cube3d_large.py --solver krylov``)."""
        work = HostWork.of(work)
        with work.timed("factorise_s"):
            ml = self._hierarchy(blocks)
        work.add(factorisations=1)
        return ml

    def _hierarchy(self, blocks):
        import pyamg
        data = np.asarray(blocks, np.float64)[self.keep_ff]
        size = np.sqrt(np.einsum("pab,pab->p", data, data))
        diag = np.zeros(len(self.indptr_ff) - 1)
        on = self.rows_ff == self.indices_ff
        diag[self.rows_ff[on]] = size[on]
        strong = size >= self.drop * np.sqrt(diag[self.rows_ff] * diag[self.indices_ff])
        indptr = np.searchsorted(self.rows_ff[strong], np.arange(len(diag) + 1))
        Knn = sp.bsr_matrix((data[strong], self.indices_ff[strong], indptr), shape=(self.n_free,) * 2)
        ml = pyamg.smoothed_aggregation_solver(Knn, B=self.B, symmetry="symmetric", max_coarse=500,
                                               strength=("symmetric", {"theta": 0.0}))
        return ml

    def cg(self, ml, K, b, x0=None, rtol=None, work: HostWork | None = None):
        """CG on K_ff x = b (one column) preconditioned by one V-cycle of ``ml``: (x, status,
        iterations, iterations per decade of residual reduction). Converged on the true
        residual |b - K_ff x| <= rtol |b| (checked again whenever the recursive one says so)."""
        if np.linalg.norm(b) == 0:
            return np.zeros_like(b), KrylovStatus.CONVERGED, 0, 0.0
        work = HostWork.of(work)
        with work.timed("cg_s"):
            x, status, it, rate = self._cg(ml, K, b, x0, rtol)
        work.add(cg_solves=1, cg_iterations=it)
        return x, status, it, rate

    def _cg(self, ml, K, b, x0, rtol):
        rtol = self.rtol if rtol is None else rtol
        A = kff(self.elimination, K)
        M = ml.aspreconditioner(cycle="V")
        bn = np.linalg.norm(b)
        x = np.zeros_like(b) if x0 is None else np.array(x0, np.float64)
        status, it = KrylovStatus.MAX_ITERATIONS, 0
        r = b - A(x) if x0 is not None else b.copy()
        z = M @ r
        p = z.copy()
        rz = r @ z
        while it < self.maxiter:
            it += 1
            Ap = A(p)
            pAp = p @ Ap
            if not pAp > 0:
                # negative curvature only where it is resolved: a CG that stagnates at its
                # attainable accuracy meets p.Kp ~ 0 from round-off, which says nothing of K_ff
                resolved = pAp < -self.curvature_roundoff * np.linalg.norm(p) * np.linalg.norm(Ap)
                status = KrylovStatus.NEGATIVE_CURVATURE if resolved else KrylovStatus.MAX_ITERATIONS
                break
            a = rz / pAp
            x += a * p
            r -= a * Ap
            if np.linalg.norm(r) <= rtol * bn:
                r = b - A(x)     # the recursive residual drifts: confirm on the true one
                if np.linalg.norm(r) <= rtol * bn:
                    status = KrylovStatus.CONVERGED
                    break
                z = M @ r        # restart from the true residual
                p = z.copy()
                rz = r @ z
                continue
            z = M @ r
            rz, rz_old = r @ z, rz
            p = z + (rz / rz_old) * p
        reduction = max(np.linalg.norm(r) / bn, 1e-300)
        return x, status, it, it / max(-np.log10(reduction), 1e-3)


class KrylovPool:
    """The hierarchies of one KrylovSystem, addressed by handle (a memo, as
    ``sparse.FactorPool``: a handle comes with the blocks it was built from, so an evicted
    hierarchy is built again and results never depend on the call history). Each slot also
    keeps the iterations per decade CG needed just after the hierarchy was built."""

    def __init__(self, system: KrylovSystem, size: int = 2):
        self.system, self.size = system, size
        self.slots: dict[int, list] = {}         # handle -> [hierarchy, iterations per decade]
        self.next = 1
        self.lock = threading.Lock()

    def _get(self, handle: int, blocks, work: HostWork):
        if handle not in self.slots:
            work.add(refactorisations=1)
            self._store(handle, self.system.hierarchy(blocks, work))
        self.slots[handle] = self.slots.pop(handle)           # most recently used last
        return self.slots[handle]

    def _store(self, handle, ml):
        while len(self.slots) >= self.size:
            self.slots.pop(next(iter(self.slots)))
        self.slots[handle] = [ml, None]

    def _new(self, blocks, work: HostWork) -> int:
        h = self.next
        self.next += 1
        self._store(h, self.system.hierarchy(blocks, work))
        return h

    def _solve_columns(self, slot, K, b, rtol, work: HostWork):
        """Every column of b (n, m): (x, worst status, largest iterations per decade)."""
        xs, status, rate = [], KrylovStatus.CONVERGED, 0.0
        for j in range(b.shape[1]):
            x, st, _, per = self.system.cg(slot[0], K, b[:, j], rtol=rtol, work=work)
            xs.append(x)
            rate = max(rate, per)
            if st != KrylovStatus.CONVERGED:
                status = st
                break
        if slot[1] is None and status == KrylovStatus.CONVERGED:
            slot[1] = rate
        return np.stack(xs + [np.zeros_like(b[:, 0])] * (b.shape[1] - len(xs)), 1), status, rate

    def init(self, blocks):
        """A hierarchy for ``blocks`` and a probe solve K_ff x = K_ff 1 (its outcome says
        whether CG converges and meets no negative curvature): (handle, status, LinearStats of
        the call)."""
        work = HostWork()
        with self.lock:
            h = self._new(blocks, work)
            K = self.system.matrix(blocks, work)
            b = kff(self.system.elimination, K)(np.ones(self.system.n_free))
            _, st, _ = self._solve_columns(self.slots[h], K, b[:, None], None, work)
            return np.int64(h), np.int64(st), work.stats()

    def solve(self, handle, pre_blocks, blocks, rhs):
        """x (rhs.shape) with K_ff x = rhs for ``blocks``, NaN where CG did not converge."""
        rhs = np.asarray(rhs, np.float64)
        work = HostWork()   # a solve returns no state to carry it: its work stays uncounted
        with self.lock:
            slot = self._get(int(handle), pre_blocks, work)
            b = rhs.reshape(self.system.n_free, -1)
            x, st, _ = self._solve_columns(slot, self.system.matrix(blocks, work), b, None, work)
            if st != KrylovStatus.CONVERGED:
                return np.full(rhs.shape, np.nan)
            return x.reshape(rhs.shape)

    def newton_solve(self, handle, pre_blocks, blocks, rhs, rtol):
        """A Newton step with the current tangent ``blocks``: CG with the kept hierarchy; a
        new one (from ``blocks``) where none is held, where CG did not converge (then CG goes
        again with the new one) or where it needed more than ``growth`` x the
        iterations per decade of its first solve. Returns (x, handle, status, rebuilt) and
        the call's LinearStats."""
        rhs = np.asarray(rhs, np.float64)
        b = rhs.reshape(self.system.n_free, -1)
        work = HostWork()
        with self.lock:
            x, h, st, rebuilt = self._newton_solve(int(handle), pre_blocks, blocks, b, float(rtol), work)
        return x.reshape(rhs.shape), np.int64(h), np.int64(st), np.bool_(rebuilt), work.stats()

    def _newton_solve(self, h, pre_blocks, blocks, b, rtol, work):
        K = self.system.matrix(blocks, work)
        rebuilt = False
        if h <= 0:
            h, rebuilt = self._new(blocks, work), True
        slot = self._get(h, pre_blocks, work)
        x, st, rate = self._solve_columns(slot, K, b, rtol, work)
        if st == KrylovStatus.NEGATIVE_CURVATURE:
            return x, h, st, rebuilt
        slow = slot[1] is not None and rate > self.system.growth * slot[1]
        if st != KrylovStatus.CONVERGED or (slow and not rebuilt):
            h, rebuilt = self._new(blocks, work), True
            if st != KrylovStatus.CONVERGED:
                x, st, _ = self._solve_columns(self.slots[h], K, b, rtol, work)
        return x, h, st, rebuilt

    def clear(self):
        with self.lock:
            self.slots.clear()


pool = pooled(KrylovPool)   # the hierarchy pool of a KrylovSystem
