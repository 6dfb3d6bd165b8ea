"""Solves that improve on an approximate inverse of K: iterative refinement of a solve made in
lower precision, and conjugate gradients preconditioned by the factorisation of a nearby
matrix. The one rule of each, shared by the solvers inside jit and on the host (PARDISO):
both work on JAX and NumPy arrays alike."""
from __future__ import annotations

import jax.numpy as jnp
import numpy as np

# refinement steps: each cuts the residual by ~cond(K_ff) eps_single (1e-6 measured on the
# 10^3 cube), so two reach ~1e-12
REFINEMENTS = 2


def refine(apply, matvec, b, steps: int = REFINEMENTS):
    """x ~ K^-1 b from ``apply`` (an approximate K^-1, e.g. a single-precision factorisation)
    and ``matvec`` (the exact K x): x = apply(b), then ``steps`` times x += apply(b - K x)."""
    x = apply(b)
    for _ in range(steps):
        x = x + apply(b - matvec(x))
    return x


def _python_loop(cond, body, state):
    while cond(state):
        state = body(state)
    return state


def preconditioned_cg(matvec, precondition, b, rtol: float, maxiter: int, *, columns: bool = False,
                      loop=_python_loop, x0=None):
    """Conjugate gradients on K x = b (K symmetric positive definite) preconditioned by
    ``precondition`` (an approximate K^-1 that is symmetric positive definite, e.g. the
    factorisation of K at a nearby state), from x = ``x0`` (default 0: a guess, such as the
    solution of a nearby system, saves iterations), until |b - K x| <= rtol |b| or
    ``maxiter`` iterations. ``columns``: the last axis of b holds independent right-hand
    sides, each with its own step lengths and test (one product of K and of the
    preconditioner per iteration serves all). ``loop``: how to run the iterations, a
    Python while loop (NumPy, on the host) or ``jax.lax.while_loop`` (inside jit).

    Returns (x, iterations, ok) with ok per column: converged, not stopped by the cap or by
    a direction of non-positive curvature (K or the preconditioner not positive definite)."""
    xp = np if isinstance(b, np.ndarray) else jnp
    axes = tuple(range(b.ndim - 1)) if columns else None

    def dot(u, v):
        return xp.sum(u * v, axis=axes)

    goal = rtol * xp.sqrt(dot(b, b))
    x = xp.zeros_like(b) if x0 is None else x0
    r = b if x0 is None else b - matvec(x0)
    z = precondition(r)
    rz = dot(r, z)
    # state: iteration, x, r, p, r.z, live (columns still iterating), curved (no breakdown)
    start = (0, x, r, z, rz, xp.sqrt(dot(r, r)) > goal, xp.ones_like(goal, dtype=bool))

    def cond(s):
        return (s[0] < maxiter) & xp.any(s[5])

    def body(s):
        k, x, r, p, rz, live, curved = s
        Kp = matvec(p)
        pKp = dot(p, Kp)
        curved = curved & ~(live & ~(pKp > 0))
        live = live & curved
        a = xp.where(live, rz / xp.where(live, pKp, 1.0), 0.0)
        x, r = x + a * p, r - a * Kp
        z = precondition(r)
        rz_new = dot(r, z)
        live = live & (xp.sqrt(dot(r, r)) > goal)
        p = z + xp.where(live, rz_new / xp.where(rz != 0, rz, 1.0), 0.0) * p
        return k + 1, x, r, p, rz_new, live, curved

    k, x, r, _, _, live, curved = loop(cond, body, start)
    return x, k, curved & ~live
