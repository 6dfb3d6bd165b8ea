"""Solves that improve on an approximate inverse of K: iterative refinement of a solve made in
lower precision, and conjugate gradients preconditioned by the factorisation of a nearby
matrix. The one rule of each, shared by the solvers inside jit and on the host (PARDISO):
both work on JAX and NumPy arrays alike."""
from __future__ import annotations

from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np

from ..iterate import python_loop


def refine(apply, matvec, b, steps: int):
    """x ~ K^-1 b from ``apply`` (an approximate K^-1, e.g. a single-precision factorisation)
    and ``matvec`` (the exact K x): x = apply(b), then ``steps`` times x += apply(b - K x)."""
    x = apply(b)
    for _ in range(steps):
        x = x + apply(b - matvec(x))
    return x


class CGState(NamedTuple):
    iteration: Any   # () iterations done
    x: Any           # the iterate
    r: Any           # the residual b - K x
    p: Any           # the search direction
    rz: Any          # r . z (z the preconditioned residual), per column
    live: Any        # columns still iterating
    curved: Any      # columns that met no direction of non-positive curvature


def preconditioned_cg(matvec, precondition, b, rtol: float, maxiter: int, *, columns: bool = False,
                      loop=python_loop, x0=None):
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
    if x0 is not None:
        # a zero right-hand side's solution is zero, which CG from a guess never meets within rtol x 0
        x0 = xp.where(goal > 0, x0, 0.0)
    x = xp.zeros_like(b) if x0 is None else x0
    r = b if x0 is None else b - matvec(x0)
    z = precondition(r)
    rz = dot(r, z)
    start = CGState(0, x, r, z, rz, xp.sqrt(dot(r, r)) > goal, xp.ones_like(goal, dtype=bool))

    def cond(s):
        return (s.iteration < maxiter) & xp.any(s.live)

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
        return CGState(k + 1, x, r, p, rz_new, live, curved)

    s = loop(cond, body, start)
    return s.x, s.iteration, s.curved & ~s.live
