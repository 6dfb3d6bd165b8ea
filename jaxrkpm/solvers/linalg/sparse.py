"""The sparse linear solver: the saddle-point form of the essential transformation,
factorised on the host (PARDISO or SuperLU, ``factorisations``), called through host callbacks.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from . import factorisations as sparse
from .base import LinearSolver, LinearStats, Stability
from .host import host_callback


# ------------------------------------------------------------------------------ sparse
class SparseState(NamedTuple):
    handle: jax.Array   # () int64 key of the host factorisation (0: none)
    inertia: jax.Array  # () int64 negative eigenvalues of K_ff; sparse.UNKNOWN/FAILED/NONE
    blocks: jax.Array   # (P, d, d) the tangent it factorises (to make it again if evicted)
    work: LinearStats   # the host work of the call that made this state (``LinearSolver.work``)


def _sparse_stability(inertia):
    return jnp.where(inertia == 0, Stability.STABLE,
                     jnp.where(inertia > 0, Stability.UNSTABLE, Stability.UNKNOWN))


@dataclass(frozen=True, eq=False)
class SparseSolver(LinearSolver):
    """Sparse path for large systems: the saddle-point form of the same transformation,

        [K  C^T] [dd]   [r]
        [C   0 ] [l ] = [0],   C dd = 0  <=>  dd = T du_f,

    whose free part solves T^T K T du_f = r exactly, on the host (jax.pure_callback, so it
    runs inside jit and while-loops): symmetric indefinite factorisations (PARDISO or
    SuperLU), reused as conjugate-gradient preconditioners while they work (see
    jaxrkpm.solvers.linalg.factorisations). ``system`` is immutable; the factorisations are addressed by the
    handles in the state."""

    system: Any           # jaxrkpm.solvers.linalg.factorisations.SaddlePointSystem
    name: str = "sparse"

    @property
    def tight_rtol(self) -> float:
        """CG's relative residual where ``newton_solve`` is given no other (None for the
        direct solvers, whose solves are exact)."""
        return self.system.cg_rtol

    @property
    def _pool(self):
        return sparse.pool(self.system)

    def init(self, problem, blocks) -> SparseState:
        i64 = jax.ShapeDtypeStruct((), jnp.int64)
        h, neg, work = host_callback(self._pool.init, (i64, i64, LinearStats.shape_dtypes()), blocks)
        return SparseState(h, neg, blocks, work)

    def empty(self, problem, dtype) -> SparseState:
        P, d = problem.n_pairs, problem.dim
        return SparseState(jnp.zeros((), jnp.int64), jnp.asarray(sparse.NONE, jnp.int64),
                           jnp.zeros((P, d, d), dtype), LinearStats.of())

    def work(self, state: SparseState) -> LinearStats:
        return state.work

    def solve(self, state: SparseState, rhs):
        return host_callback(self._pool.solve, jax.ShapeDtypeStruct(rhs.shape, rhs.dtype),
                                 state.handle, state.blocks, rhs)

    def stability(self, state: SparseState):
        return _sparse_stability(state.inertia)

    def negative_eigenvalues(self, state: SparseState):
        """Number of negative eigenvalues of K_ff: the factorisation's inertia (-1: unknown)."""
        return jnp.maximum(state.inertia, -1).astype(jnp.int64)

    def newton_solve(self, state: SparseState, problem, blocks, rhs, rtol=None):
        """CG with the current tangent preconditioned by the held factorisation while it is
        positive definite and CG converges (to ``rtol``, default the system's tight cg_rtol;
        no negative curvature met counts as stable), else a new factorisation."""
        rtol = jnp.asarray(self.system.cg_rtol if rtol is None else rtol, rhs.dtype)
        i64 = jax.ShapeDtypeStruct((), jnp.int64)
        out = (jax.ShapeDtypeStruct(rhs.shape, rhs.dtype), i64, i64, jax.ShapeDtypeStruct((), jnp.bool_),
               LinearStats.shape_dtypes())
        x, h, neg, reused, work = host_callback(self._pool.newton_solve, out, state.handle, state.inertia,
                                                state.blocks, blocks, rhs, rtol)
        new = SparseState(h, neg, jnp.where(reused, state.blocks, blocks), work)
        return x, new, self.stability(new)
