"""Do stable states exist where a solve stopped? An independent, host-side check by exact
trust-region minimisation of a model's discrete energy (scipy's ``trust-exact``: the dense
Hessian K_ff, its eigen-decomposition in the subproblem, negative curvature used), for small
dense models.

A load-controlled solve that stops (MAX_ITERATIONS, LINE_SEARCH, or UNSTABLE_TANGENT with no
stable state found by the branch switch) may have met a Newton globalisation failure, or the
end of the stable path. ``stable_beyond`` tells them apart: it minimises the energy at
prescribed values a little further along the path, each minimisation from the last stable
minimum, and reports the first that does not end on an equilibrium with K_ff positive
definite (and how: ``collapse`` where the minimisation ran into det F = 0 at an integration
point, the energy still falling there). Every trial point with det F <= 0 is refused (infinite
energy), so a minimum it reports is an admissible, stable equilibrium.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from scipy.optimize import minimize

_ENERGY = jax.jit(lambda prob, u, g: prob.energy(u, g))
_RESIDUAL = jax.jit(lambda prob, u, g: prob.residual(u, g))
_TANGENT = jax.jit(lambda prob, u, g: prob.tangent(u, g))
_SCALE = jax.jit(lambda prob, u, g: prob.force_scale(prob.energy_residual(u, g)[3]))


def minimise(prob, u, g, radius: float, max_iter: int = 1000):
    """A local minimum of the energy of ``prob`` (a ``Model.problem()``, small) at the prescribed
    values g from u, by exact trust-region Newton with trust radius at most ``radius`` (in
    coefficient units, |du|): every step stays within it, so the minimisation follows the
    energy downhill and stops in the first minimum it meets instead of jumping out of a
    shallow basin (unbounded, from a state just before a stable equilibrium near the end of
    the 9x9 square's stable path, it overshot into the collapse).
    Every iterate keeps det F > 0. Returns a dict:
    u (Nf, d), energy, min_detF, residual |r|, force_scale (the convergence test's), the three
    lowest eigenvalues of K_ff, iterations."""
    shape = np.shape(u)
    g = jnp.asarray(g)
    last = {}

    def at(x):
        return jnp.asarray(x.reshape(shape))

    def admissible(x):
        e, det = (float(v) for v in _ENERGY(prob, at(x), g))
        return det > 0 and np.isfinite(e), e

    def fun(x):
        ok, e = admissible(x)
        return e if ok else np.inf

    # at a refused (inverted) trial point: the last admissible values (the step is rejected)
    def jac(x):
        if admissible(x)[0]:
            last["r"] = np.asarray(_RESIDUAL(prob, at(x), g)).ravel()
        return last["r"]

    def hess(x):
        if admissible(x)[0]:
            K = np.asarray(_TANGENT(prob, at(x), g))
            last["K"] = 0.5 * (K + K.T)
        return last["K"]

    x0 = np.asarray(u, float).ravel()
    if not admissible(x0)[0]:
        raise ValueError("minimise: u inverts the material at g (det F <= 0 at an integration point); "
                         "start from a state closer to g (smaller increments)")
    res = minimize(fun, x0, jac=jac, hess=hess, method="trust-exact",
                   options={"maxiter": int(max_iter), "gtol": 1e-9, "initial_trust_radius": 0.5 * radius,
                            "max_trust_radius": radius})
    e, det = (float(v) for v in _ENERGY(prob, at(res.x), g))
    return {"u": res.x.reshape(shape), "energy": e, "min_detF": det,
            "residual": float(np.linalg.norm(jac(res.x))), "force_scale": float(_SCALE(prob, at(res.x), g)),
            "lowest_eigenvalues": np.linalg.eigvalsh(hess(res.x))[:3].tolist(), "iterations": int(res.nit)}


def stable_beyond(prob, sol, g_end, fraction: float = 0.1, rtol: float = 1e-6, max_iter: int = 1000,
                  radius: float = 0.02, collapse: float = 1e-6) -> dict:
    """Stable states past the (stable) equilibrium ``sol`` of the problem ``prob`` on the
    straight path of prescribed values from sol.g to ``g_end`` (Nb, d): energy minima
    (``minimise``) at s = fraction, 2 fraction, ... of that path, each from the last. Stops at
    the first that is not an equilibrium (|r| <= rtol x the force scale) with K_ff positive
    definite. Trust radius: ``radius`` particle spacings. Returns a dict: ``reached`` (the
    largest s with a stable minimum, 0 if none), ``full`` (s = 1 reached), and at the first
    failure (``failed_at`` s): min_detF, residual, force_scale, lowest_eigenvalues, iterations,
    ``collapse`` (min_detF below ``collapse``: the minimisation ran into det F = 0)."""
    if not 0 < fraction <= 1:
        raise ValueError(f"fraction must lie in (0, 1] (a share of the path per minimisation), got {fraction}")
    g0, g1 = np.asarray(sol.g, float), np.asarray(g_end, float)
    u, s, out = np.asarray(sol.u, float), 0.0, {}
    while s < 1 - 1e-12:
        s1 = min(1.0, s + fraction)
        m = minimise(prob, u, g0 + s1 * (g1 - g0), radius * float(prob.spacing), max_iter)
        if not (m["residual"] <= rtol * m["force_scale"] and m["lowest_eigenvalues"][0] > 0):
            out = {"failed_at": s1, **{k: v for k, v in m.items() if k not in ("u", "energy")},
                   "collapse": bool(m["min_detF"] < collapse)}
            break
        u, s = m["u"], s1
    return {"reached": s, "full": s >= 1 - 1e-12, **out}
