"""Implicit differentiation of equilibria (here and only here): the one linearised solve
K_ff x = rhs behind every derivative, the differentiable solve (a custom JVP around the load
path), responses to prescribed directions and point Jacobians.
"""
from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from .linalg.refinement import preconditioned_cg
from .path import LoadPath
from .results import Limits, Solution, reached_equilibrium


def _zero_tangent(x):
    x = jnp.asarray(x)
    if jnp.issubdtype(x.dtype, jnp.integer) or x.dtype == jnp.bool_:
        return np.zeros(x.shape, dtype=jax.dtypes.float0)
    return jnp.zeros_like(x)


def sensitivity(problem, linear, u, g, load, rhs, state=None, refine: float = 0.0, guess=None,
                max_refine: int = 20):
    """x = K_ff^-1 rhs at the equilibrium (u, g, load), rhs (Nf, d) or (Nf, d, m): the one
    linearised solve behind every implicit derivative (the solve's JVP, ``response``,
    Jacobians). ``state``: a factorisation of K_ff there by ``linear`` to reuse (default:
    factorise now).

    ``refine`` > 0: ``state`` factorises a nearby, earlier tangent (a factorisation kept across
    control steps): conjugate gradients with the exact product, preconditioned by that
    factorisation (``preconditioned_cg``), until |rhs - K x| <= refine |rhs| per column (at
    most ``max_refine`` iterations, each m Hessian-vector products), so the result is
    K_ff^-1 rhs of this state to that relative residual. CG, not the stationary refinement
    x += solve(rhs - K x): that contracts only by the kept factorisation's chord factor per
    step and needed several times the iterations (``experiments/bench_cube3d.py``'s kept
    loop). ``guess`` (rhs's shape): where CG starts (e.g. the solution at the previous control
    step; the result meets the same residual test). 0: ``state`` factorises this very tangent.

    A custom linear solve: the matrix-vector product is the exact Hessian-vector product of
    the energy, the solve uses the factorisation, and symmetry makes it transposable (so
    reverse mode works too)."""
    if state is None:
        state = linear.state_at(problem, u, g, load)

    def hvp(v):
        return jax.jvp(lambda x: problem.residual(x, g, load), (u,), (v,))[1]

    # several right-hand sides (Nf, d, m) are one block: the product column by column
    matvec = hvp if rhs.ndim == u.ndim else jax.vmap(hvp, in_axes=-1, out_axes=-1)

    def solve(mv, b):
        if not refine:
            return linear.solve(state, b)
        x0 = None if guess is None else jax.lax.stop_gradient(guess)
        return preconditioned_cg(mv, partial(linear.solve, state), b, refine, max_refine,
                                 columns=b.ndim > u.ndim, loop=jax.lax.while_loop, x0=x0)[0]

    return jax.lax.custom_linear_solve(matvec, rhs, solve=solve, symmetric=True)


@partial(jax.custom_jvp, nondiff_argnums=(0,))
def solve_path_diff(driver: LoadPath, problem, lim: Limits, u0, g0, g1, l0, l1, state0=None, params0=None):
    """``driver.solve`` differentiable in (g1, l1, the problem's parameters) by the implicit
    function theorem at the converged state: K_ff du = -(dr/dg dg + dr/dl dl + dr/dp dp). No
    Newton iteration is differentiated; the path start (u0, g0, l0, the parameters ``params0``
    there) and ``state0`` only select the equilibrium branch and where Newton starts."""
    return driver.solve(problem, lim, u0, g0, g1, l0, l1, state0, params0)


@solve_path_diff.defjvp
def _solve_path_jvp(driver, primals, tangents):
    problem, lim, u0, g0, g1, l0, l1, state0, params0 = primals
    dproblem, _, _, _, dg1, _, dl1, _, _ = tangents
    sol = solve_path_diff(driver, problem, lim, u0, g0, g1, l0, l1, state0, params0)
    # a failed solve has no derivative: NaN, never the finite derivative of the kept state
    # (a factor, not a select, so the tangent stays linear and reverse mode transposes it)
    valid = jnp.where(reached_equilibrium(sol.status), 1.0, jnp.nan)
    dg, dl = sol.t * valid * dg1, sol.t * valid * dl1
    _, dr = jax.jvp(lambda g, l, p: problem.replace(params=p).residual(sol.u, g, l),
                    (sol.g, sol.load, problem.params), (dg, dl, dproblem.params))
    du = -sensitivity(problem, driver.linear, sol.u, sol.g, sol.load, dr) * valid
    dsol = Solution(du, dg, dl, *jax.tree.map(_zero_tangent, tuple(sol[3:])))
    return sol, dsol


solve_path_jit = jax.jit(solve_path_diff, static_argnames=("driver",))


def response(problem, linear, u, g, load, dG, state=None, refine: float = 0.0, guess=None):
    """Implicit sensitivity of the free coefficients to m prescribed directions dG (m, Nb, d):
    K_ff du = -K_fg dG with one factorisation (``state``, or a new one; ``refine`` and
    ``guess``, a response (m, Nf, d) to start from: see ``sensitivity``). Returns (m, Nf, d)."""
    dr = jax.vmap(lambda dg: jax.jvp(lambda x: problem.residual(u, x, load), (g,), (dg,))[1])(dG)   # (m, Nf, d)
    return _responses(problem, linear, u, g, load, dr, state, refine, guess)


def parameter_response(problem, linear, u, g, load, name: str, key: str, state=None, refine: float = 0.0,
                       guess=None):
    """Implicit sensitivity of the free coefficients to each component of the parameter
    ``problem.params[name][key]`` (m components, flattened), the rest held: K_ff du = -dr/dp
    with one factorisation (``state``, ``refine``, ``guess``: see ``response``). Returns
    (m, Nf, d)."""
    p0 = jnp.asarray(problem.term(name).params[key])

    def residual(p):
        return problem.replace(params={name: {key: p.reshape(p0.shape)}}).residual(u, g, load)

    flat = p0.ravel()
    dr = jax.vmap(lambda e: jax.jvp(residual, (flat,), (e,))[1])(jnp.eye(flat.size, dtype=flat.dtype))
    return _responses(problem, linear, u, g, load, dr, state, refine, guess)


def _responses(problem, linear, u, g, load, dr, state, refine, guess):
    """-K_ff^-1 dr for the m right-hand sides dr (m, Nf, d), as one block: (m, Nf, d)."""
    x0 = None if guess is None else -jnp.moveaxis(guess, 0, -1)
    du = -sensitivity(problem, linear, u, g, load, jnp.moveaxis(dr, 0, -1), state, refine, x0)   # (Nf, d, m)
    return jnp.moveaxis(du, -1, 0)


def point_jacobian(problem, idx, psi, u, g, du, dG):
    """d(displacement at points)/d(direction) from the responses du (m, Nf, d) to the
    directions dG (m, Nb, d): (P, d, m) (the point values are linear in (u, g))."""
    dU = jax.vmap(lambda a, b: jax.jvp(lambda x, y: problem.point_values(idx, psi, x, y), (u, g), (a, b))[1])(du, dG)
    return jnp.moveaxis(dU, 0, -1)


@partial(jax.jit, static_argnames=("linear", "refine"))
def implicit_jacobian(problem, linear, u, g, load, dG, idx, psi, state=None, refine: float = 0.0):
    """d(displacement at points)/d(direction) for the m directions dG: (P, d, m) (``state``,
    ``refine``: see ``sensitivity``)."""
    du = response(problem, linear, u, g, load, dG, state, refine)
    return point_jacobian(problem, idx, psi, u, g, du, dG)
