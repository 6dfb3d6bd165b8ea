"""Implicit differentiation of equilibria: the one linearised solve K_ff x = rhs behind every
derivative, the differentiable solve (a custom JVP), responses and point Jacobians.
"""
from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from ..mechanics.assembly import point_values, residual
from .config import Config
from .linalg.refinement import preconditioned_cg
from .newton import linear_state
from .path import solve_path
from .results import Solution, reached_equilibrium


# ------------------------------------------------------------ implicit differentiation
def _zero_tangent(x):
    x = jnp.asarray(x)
    if jnp.issubdtype(x.dtype, jnp.integer) or x.dtype == jnp.bool_:
        return np.zeros(x.shape, dtype=jax.dtypes.float0)
    return jnp.zeros_like(x)

REFINE_MAX = 20   # CG preconditioned by a kept factorisation: at most this many iterations


def sensitivity(ops, params, cfg: Config, u, g, load, rhs, state=None, refine: float = 0.0, guess=None):
    """x = K_ff^-1 rhs at the equilibrium (u, g, load), rhs (Nf, d) or (Nf, d, m): the one
    linearised solve behind every implicit derivative (solve's JVP, ``response``, Jacobians).
    ``state``: a factorisation of K_ff there to reuse (default: factorise now).
    ``refine`` > 0: ``state`` factorises a nearby, earlier tangent (a factorisation kept across
    control steps): conjugate gradients with the exact product, preconditioned by that
    factorisation (``jaxrkpm.solvers.linalg.refinement.preconditioned_cg``), until |rhs - K x| <= refine |rhs|
    per column (at most REFINE_MAX iterations), so the result is K_ff^-1 rhs of this state to
    that relative residual. Why CG, not the stationary refinement x += solve(rhs - K x): that
    contracts by the kept factorisation's chord factor per step, and needed 25 corrections
    where CG took 9 (10^3 cube, a factorisation 10 control steps old; 0.49 s against 0.23 s).
    ``guess`` (rhs's shape): where CG starts (e.g. the solution at the previous control step;
    the result meets the same residual test). 0: ``state`` factorises this very tangent (no
    refinement).

    A custom linear solve: the matrix-vector product is the exact Hessian-vector product of
    the energy, the solve uses the factorisation, and symmetry makes it transposable (so
    reverse mode works too)."""
    if state is None:
        state = linear_state(ops, params, cfg, u, g)

    def hvp(v):
        return jax.jvp(lambda x: residual(ops, params, cfg.W, x, g, load), (u,), (v,))[1]

    # several right-hand sides (Nf, d, m) are one block: the product column by column
    matvec = hvp if rhs.ndim == u.ndim else jax.vmap(hvp, in_axes=-1, out_axes=-1)

    def solve(mv, b):
        if not refine:
            return cfg.linear.solve(state, b)
        x0 = None if guess is None else jax.lax.stop_gradient(guess)
        return preconditioned_cg(mv, partial(cfg.linear.solve, state), b, refine, REFINE_MAX,
                                 columns=b.ndim > u.ndim, loop=jax.lax.while_loop, x0=x0)[0]

    return jax.lax.custom_linear_solve(matvec, rhs, solve=solve, symmetric=True)


@partial(jax.custom_jvp, nondiff_argnums=(2,))
def solve_path_diff(ops, params, cfg, lim, u0, g0, g1, l0, l1, state0=None):
    """``solve_path`` differentiable in (g1, l1, params) by the implicit function theorem at
    the converged state: K_ff du = -(dr/dg dg + dr/dl dl + dr/dp dp). No Newton iteration is
    differentiated; the path start (u0, g0, l0) and ``state0`` only select the equilibrium
    branch and where Newton starts."""
    return solve_path(ops, params, cfg, lim, u0, g0, g1, l0, l1, state0)


@solve_path_diff.defjvp
def _solve_path_jvp(cfg, primals, tangents):
    ops, params, lim, u0, g0, g1, l0, l1, state0 = primals
    _, dparams, _, _, _, dg1, _, dl1, _ = tangents
    sol = solve_path_diff(ops, params, cfg, lim, u0, g0, g1, l0, l1, state0)
    # a failed solve has no derivative: NaN, never the finite derivative of the kept state
    # (a factor, not a select, so the tangent stays linear and reverse mode transposes it)
    valid = jnp.where(reached_equilibrium(sol.status), 1.0, jnp.nan)
    dg, dl = sol.t * valid * dg1, sol.t * valid * dl1
    _, dr = jax.jvp(lambda g, l, p: residual(ops, p, cfg.W, sol.u, g, l),
                    (sol.g, sol.load, params), (dg, dl, dparams))
    du = -sensitivity(ops, params, cfg, sol.u, sol.g, sol.load, dr) * valid
    dsol = Solution(du, dg, dl, *jax.tree.map(_zero_tangent, tuple(sol[3:])))
    return sol, dsol


solve_path_jit = jax.jit(solve_path_diff, static_argnames=("cfg",))


def response(ops, params, cfg: Config, u, g, load, dG, state=None, refine: float = 0.0, guess=None):
    """Implicit sensitivity of the free coefficients to m prescribed directions dG (m, Nb, d):
    K_ff du = -K_fg dG with one factorisation (``state``, or a new one; ``refine`` and
    ``guess``, a response (m, Nf, d) to start from: see ``sensitivity``). Returns (m, Nf, d)."""
    dr = jax.vmap(lambda dg: jax.jvp(lambda x: residual(ops, params, cfg.W, u, x, load),
                                     (g,), (dg,))[1])(dG)                      # (m, Nf, d)
    x0 = None if guess is None else -jnp.moveaxis(guess, 0, -1)
    du = -sensitivity(ops, params, cfg, u, g, load, jnp.moveaxis(dr, 0, -1), state, refine, x0)   # (Nf, d, m)
    return jnp.moveaxis(du, -1, 0)


def point_jacobian(ops, idx, psi, u, g, du, dG):
    """d(displacement at points)/d(direction) from the responses du (m, Nf, d) to the
    directions dG (m, Nb, d): (P, d, m) (the point values are linear in (u, g))."""
    dU = jax.vmap(lambda a, b: jax.jvp(lambda x, y: point_values(ops, idx, psi, x, y), (u, g), (a, b))[1])(du, dG)
    return jnp.moveaxis(dU, 0, -1)


@partial(jax.jit, static_argnames=("cfg",))
def implicit_jacobian(ops, params, cfg: Config, u, g, load, dG, idx, psi, state=None):
    """d(displacement at points)/d(direction) for the m directions dG: (P, d, m)."""
    du = response(ops, params, cfg, u, g, load, dG, state)
    return point_jacobian(ops, idx, psi, u, g, du, dG)
