"""Point Jacobians of a model's solutions: J = d(displacement at points)/d(prescribed values of
a driven set), implicit (one linearised solve) or by finite differences (re-solves).
Functions over (model, solution).
"""
from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ..solvers.implicit import implicit_jacobian
from ..solvers.results import Solution
from .inputs import check_set, check_solution
from .post import point_values
from .solving import kept_linear

METHODS = ("implicit", "fd")
SCHEMES = ("forward", "central")


def directions(model, name: str, rigid: bool = True):
    """Unit prescribed-value directions (m, Nb, d) that drive set ``name``: d rigid
    translations, or one per particle and component (m = n_set * d)."""
    check_set(model, name)
    sl = model.sets.slices[name]
    Nb, d = len(model.sets.bnd), model.dim
    if rigid:
        G = np.zeros((d, Nb, d))
        for a in range(d):
            G[a, sl, a] = 1.0
        return jnp.asarray(G)
    n = sl.stop - sl.start
    G = np.zeros((n * d, Nb, d))
    for i in range(n):
        for a in range(d):
            G[i * d + a, sl.start + i, a] = 1.0
    return jnp.asarray(G)


def implicit(model, sol: Solution, idx, psi, G, params=None, rtol: float = 1e-12):
    """(P d, m): K_ff du = -K_fg dG at the converged state: with a factorisation of K_ff there,
    or, where the Solution kept its solve's last factorisation, CG preconditioned by it to the
    relative residual ``rtol``."""
    if not (isinstance(rtol, (int, float)) and 0 < rtol < 1):
        raise ValueError(f"rtol must be a number in (0, 1), got {rtol!r}")
    problem = model.problem(params)
    kept = kept_linear(model.linear, sol, problem)
    J = implicit_jacobian(problem, model.linear, sol.u, sol.g, sol.load, G, idx, psi, kept,
                          refine=0.0 if kept is None else float(rtol))
    return J.reshape(idx.shape[0] * model.dim, -1)


def finite_differences(model, sol: Solution, idx, psi, G, params=None, eps: float = 1e-6,
                       scheme: str = "central"):
    """(P d, m) by the thesis' Algorithm 4: perturb each direction by eps, re-solve from the
    converged state (``sol`` itself is never modified)."""
    if not (np.isfinite(eps) and eps > 0):
        raise ValueError(f"eps must be positive, got {eps}")

    def at(g):
        s = model.solve_g(g, initial=sol, params=params, loads=sol.load)
        return point_values(model.constraint, idx, psi, s.u, s.g).ravel()

    base = point_values(model.constraint, idx, psi, sol.u, sol.g).ravel()
    if scheme == "forward":
        cols = [(at(sol.g + eps * dg) - base) / eps for dg in G]
    else:
        cols = [(at(sol.g + eps * dg) - at(sol.g - eps * dg)) / (2 * eps) for dg in G]
    return jnp.stack(cols, axis=1)


def jacobian(model, sol: Solution, driven: str, points, method: str = "implicit", eps: float = 1e-6,
             scheme: str = "central", rigid: bool = True, params=None, rtol: float = 1e-12):
    """J = d(displacement at points)/d(displacement of the driven set): (P*d, m), m = d for a
    rigidly driven set (else n_set*d); see ``Model.jacobian``."""
    if method not in METHODS:
        raise ValueError(f"unknown Jacobian method {method!r}: choose 'implicit' or 'fd'")
    if scheme not in SCHEMES:
        raise ValueError(f"unknown difference scheme {scheme!r}: choose 'forward' or 'central'")
    check_solution(model, sol)
    idx, psi = model.point_tables(points)
    G = directions(model, driven, rigid)
    if method == "implicit":
        return implicit(model, sol, idx, psi, G, params, rtol)
    return finite_differences(model, sol, idx, psi, G, params, eps, scheme)
