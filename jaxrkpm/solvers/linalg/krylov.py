"""The Krylov linear solver: CG on K_ff preconditioned by algebraic multigrid
(``multigrid``), on the host.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from . import multigrid as krylov
from .base import LinearSolver, LinearStats, Stability
from .host import host_callback


# ------------------------------------------------------------------------------ krylov
class KrylovState(NamedTuple):
    handle: jax.Array      # () int64 key of the host multigrid hierarchy (0: none)
    pre_blocks: jax.Array  # (P, d, d) the tangent the hierarchy was built from (to build it again)
    blocks: jax.Array      # (P, d, d) the tangent K_ff is made of (the matrix solved)
    outcome: jax.Array     # () int64 krylov.KrylovStatus of the last CG solve
    work: LinearStats      # the host work of the call that made this state (``LinearSolver.work``)


@dataclass(frozen=True, eq=False)
class KrylovSolver(LinearSolver):
    """Newton-Krylov for large systems: CG on K_ff = T^T K T with the assembled tangent,
    preconditioned by an algebraic multigrid hierarchy built rarely (``jaxrkpm.solvers.linalg.multigrid``), on
    the host through jax.pure_callback (CPU). No factorisation: stability is inferred from CG
    (converged without negative curvature: STABLE; negative curvature met: UNSTABLE; not
    converged: FAILED, which ends the Newton attempt with Status.LINEAR_SOLVE)."""

    system: Any           # jaxrkpm.solvers.linalg.multigrid.KrylovSystem
    name: str = "krylov"

    @property
    def tight_rtol(self) -> float:
        """CG's relative residual where ``newton_solve`` is given no other."""
        return self.system.rtol

    @property
    def _pool(self):
        return krylov.pool(self.system)

    def init(self, problem, blocks) -> KrylovState:
        i64 = jax.ShapeDtypeStruct((), jnp.int64)
        h, st, work = host_callback(self._pool.init, (i64, i64, LinearStats.shape_dtypes()), blocks)
        return KrylovState(h, blocks, blocks, st, work)

    def empty(self, problem, dtype) -> KrylovState:
        P, d = problem.n_pairs, problem.dim
        z = jnp.zeros((P, d, d), dtype)
        return KrylovState(jnp.zeros((), jnp.int64), z, z, jnp.asarray(krylov.KrylovStatus.NONE, jnp.int64),
                           LinearStats.of())

    def work(self, state: KrylovState) -> LinearStats:
        return state.work

    def solve(self, state: KrylovState, rhs):
        """K_ff x = rhs to the system's rtol (NaN where CG does not converge)."""
        return host_callback(self._pool.solve, jax.ShapeDtypeStruct(rhs.shape, rhs.dtype),
                                 state.handle, state.pre_blocks, state.blocks, rhs)

    def stability(self, state: KrylovState):
        o = state.outcome
        return jnp.where(o == krylov.KrylovStatus.CONVERGED, Stability.STABLE,
                         jnp.where(o == krylov.KrylovStatus.NEGATIVE_CURVATURE, Stability.UNSTABLE,
                                   jnp.where(o == krylov.KrylovStatus.MAX_ITERATIONS, Stability.FAILED,
                                             Stability.UNKNOWN)))

    def negative_eigenvalues(self, state: KrylovState):
        """0 where CG inferred K_ff positive definite, else -1 (CG does not count them)."""
        return jnp.where(state.outcome == krylov.KrylovStatus.CONVERGED, 0, -1).astype(jnp.int64)

    def newton_solve(self, state: KrylovState, problem, blocks, rhs, rtol=None):
        """CG with the current tangent to ``rtol`` (the inexact-Newton forcing term; default
        the system's rtol), preconditioned by the kept hierarchy (rebuilt when CG slows)."""
        rtol = jnp.asarray(self.system.rtol if rtol is None else rtol, rhs.dtype)
        i64 = jax.ShapeDtypeStruct((), jnp.int64)
        out = (jax.ShapeDtypeStruct(rhs.shape, rhs.dtype), i64, i64, jax.ShapeDtypeStruct((), jnp.bool_),
               LinearStats.shape_dtypes())
        x, h, st, rebuilt, work = host_callback(self._pool.newton_solve, out, state.handle, state.pre_blocks,
                                                blocks, rhs, rtol)
        new = KrylovState(h, jnp.where(rebuilt, blocks, state.pre_blocks), blocks, st, work)
        return x, new, self.stability(new)
