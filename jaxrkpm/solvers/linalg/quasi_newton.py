"""A kept factorisation improved by secant pairs (L-BFGS with the factorisation as H_0).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from .base import LinearSolver
from .dense import DenseSolver


# ------------------------------------------------------------------------ quasi-Newton
class QuasiNewtonState(NamedTuple):
    base: Any         # the wrapped solver's factorisation (of K_ff at some earlier state)
    S: jax.Array      # (m, n) steps s_k of the secant pairs (newest last)
    Y: jax.Array      # (m, n) residual changes y_k = r(u + s_k) - r(u) at one load
    count: jax.Array  # () pairs held (<= m)


@dataclass(frozen=True)
class QuasiNewton(LinearSolver):
    """A kept factorisation of K_ff made better by secant pairs: L-BFGS (Nocedal & Wright,
    Algorithm 7.4, the two-loop recursion) with the factorisation's inverse as the initial
    inverse Hessian H_0. So chord corrections with a factorisation of an earlier state
    converge superlinearly, and the factorisation serves many more control steps before it
    must be made again; the approximation H stays symmetric (and positive definite where
    the base is and every pair has s.y > 0), so it also serves the implicit Jacobian's
    transposable solve.

    ``update(state, s, y)`` adds the pair (s, y) (the oldest one drops out once ``memory``
    are held; pairs with too little curvature s.y are skipped); ``init`` factorises anew
    and forgets the pairs. Stability and inertia are the base factorisation's."""

    base: Any = DenseSolver(inverse=True)
    memory: int = 8
    name = "quasi-newton"
    tight_rtol = None     # its solves are direct (the base's and the two-loop recursion)

    def _fresh(self, base_state, problem, dtype) -> QuasiNewtonState:
        n = problem.n_free * problem.dim
        z = jnp.zeros((self.memory, n), dtype)
        return QuasiNewtonState(base_state, z, z, jnp.zeros((), jnp.int32))

    def init(self, problem, blocks) -> QuasiNewtonState:
        return self._fresh(self.base.init(problem, blocks), problem, blocks.dtype)

    def empty(self, problem, dtype) -> QuasiNewtonState:
        return self._fresh(self.base.empty(problem, dtype), problem, dtype)

    def solve(self, state: QuasiNewtonState, rhs):
        n = state.S.shape[1]
        q = rhs.reshape(n, -1)
        sy = jnp.sum(state.S * state.Y, axis=1)
        held = jnp.arange(self.memory) >= self.memory - state.count    # newest pairs at the end
        rho = jnp.where(held, 1.0 / jnp.where(held, sy, 1.0), 0.0)

        def backward(q, k):          # newest to oldest
            a = rho[k] * (state.S[k] @ q)
            return q - state.Y[k][:, None] * a[None], a

        q, alpha = jax.lax.scan(backward, q, jnp.arange(self.memory)[::-1])
        x = self.base.solve(state.base, q.reshape(rhs.shape)).reshape(n, -1)

        def forward(x, ka):          # oldest to newest
            k, a = ka
            b = rho[k] * (state.Y[k] @ x)
            return x + state.S[k][:, None] * (a - b)[None], None

        x, _ = jax.lax.scan(forward, x, (jnp.arange(self.memory), alpha[::-1]))
        return x.reshape(rhs.shape)

    def update(self, state: QuasiNewtonState, s, y, accept=True) -> QuasiNewtonState:
        """With the secant pair (s, y) added (y = r(u + s) - r(u) at one load) where
        ``accept``, unless its curvature s.y is not clearly positive (then H would lose
        positive definiteness). A select, not a lax.cond: a cond over the whole state made
        XLA copy the factorisation at every correction."""
        s, y = s.reshape(-1), y.reshape(-1)
        good = accept & (jnp.sum(s * y) > 1e-12 * jnp.linalg.norm(s) * jnp.linalg.norm(y))
        S = jnp.where(good, jnp.roll(state.S, -1, axis=0).at[-1].set(s), state.S)
        Y = jnp.where(good, jnp.roll(state.Y, -1, axis=0).at[-1].set(y), state.Y)
        return QuasiNewtonState(state.base, S, Y, jnp.minimum(state.count + good, self.memory))

    def work(self, state: QuasiNewtonState):
        return self.base.work(state.base)

    def stability(self, state: QuasiNewtonState):
        return self.base.stability(state.base)

    def negative_eigenvalues(self, state: QuasiNewtonState):
        return self.base.negative_eigenvalues(state.base)

    def newton_solve(self, state, problem, blocks, rhs, rtol=None):
        """A Newton step with the current tangent: a new factorisation, no pairs."""
        x, base, stab = self.base.newton_solve(state.base, problem, blocks, rhs, rtol)
        return x, self._fresh(base, problem, blocks.dtype), stab


def secant(linear: LinearSolver, memory: int = 8) -> LinearSolver:
    """The solver whose kept factorisation learns from the secant pairs of later corrections
    (a control loop's quasi-Newton chords): L-BFGS on a kept dense inverse where ``linear``
    serves modified Newton as it is, else ``linear`` itself."""
    return QuasiNewton(DenseSolver(inverse=True), memory) if linear.modified_newton else linear
