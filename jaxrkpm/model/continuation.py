"""Arc-length continuation of a Model's equilibrium path (the driver is
:mod:`jaxrkpm.solvers.continuation`), and point loads for it.
"""
from __future__ import annotations

from typing import Mapping

import jax
import jax.numpy as jnp
import numpy as np

import math
from functools import partial

from ..solvers.continuation import ArcLength, EquilibriumPath, PathStatus, arc_step, start_point
from ..solvers.results import Limits, Solution, Status
from .model import Model


def point_load(model, points, forces) -> np.ndarray:
    """The (N, d) nodal load of concentrated forces ``forces`` (P, d) at reference points
    ``points`` (P, d): f_K = sum_p Psi_K(X_p) F_p, the load work-conjugate to the
    displacements u(X_p) (the same force a prescribed u(X_p) has as its reaction). Pass it
    as ``arc_length(..., load_pattern=...)``."""
    X = np.atleast_2d(np.asarray(points, float))
    F = np.asarray(forces, float)
    if F.shape == (model.dim,):
        F = np.broadcast_to(F, X.shape)
    if F.shape != X.shape or not np.all(np.isfinite(F)):
        raise ValueError(f"forces must be finite, of shape ({model.dim},) or {X.shape} (one per point), "
                         f"got {F.shape}")
    sf = model.shape_functions(X, gradients=False)
    f = np.zeros((model.body.n, model.dim))
    np.add.at(f, np.asarray(sf.idx), np.asarray(sf.psi)[..., None] * F[:, None, :])
    return f


def _check_positive(name, v, allow_zero=False):
    ok = isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))
    if not (ok and math.isfinite(v) and (v >= 0 if allow_zero else v > 0)):
        raise ValueError(f"{name} must be a {'non-negative' if allow_zero else 'positive'} finite number, "
                         f"got {v!r}")
    return float(v)


def arc_length(model, ds: float, *, steps: int = 50, initial: Solution | None = None,
               load_max: float | None = None, load_pattern=None, prescribed: Mapping | None = None,
               direction: int = 1, psi: float = 0.0, ds_max: float | None = None,
               max_cuts: int = 8, max_iter: int = 12, target_iterations: int = 4,
               points=None, params=None, **options) -> EquilibriumPath:
    """Follow the equilibrium path of ``model`` by arc-length continuation (Crisfield).

    The path parameter lambda scales the dead loads (the model's tractions and body force,
    or ``load_pattern`` (N, d), e.g. from ``point_load``) and, optionally, drives the
    prescribed displacements along ``prescribed`` (set name -> (d,) or (n_set, d) direction
    per unit lambda, added to the start's values). It starts at ``initial`` (default:
    undeformed, lambda = 0) and takes at most ``steps`` steps of arc length ``ds`` (in the
    units of the RK coefficients; adapted to about ``target_iterations`` corrector iterations
    per step, never above ``ds_max``, default 4 ds; cut in half on a failed step at most
    ``max_cuts`` times in a row), stopping early once lambda >= ``load_max``. ``psi`` 0:
    cylindrical constraint; > 0: spherical (Riks), the load term weighted by psi^2 |q|^2.
    ``direction`` -1 starts with a decreasing load factor. ``points`` (P, d): reference
    points whose displacement is recorded per point (checked inside the body before the path
    is computed). ``options``: solver settings of ``Model.solve`` (the corrector takes
    ``rtol``). Returns an EquilibriumPath (never raises for a failed step: its status
    says why the path stopped, every accepted point is kept)."""
    if not isinstance(model, Model):
        raise TypeError(f"model must be a jaxrkpm Model, got {type(model).__name__}")
    if model.unconstrained:
        raise ValueError("unconstrained: the model has no essential set and no springs, so it has "
                         "rigid-body modes and no path is unique; hold part of it or add Springs")
    ds = _check_positive("ds", ds)
    ds_max = 4.0 * ds if ds_max is None else _check_positive("ds_max", ds_max)
    if ds_max < ds:
        raise ValueError(f"ds_max ({ds_max}) must be at least ds ({ds})")
    lim = Limits.of(steps, max_iter, max_cuts)   # the solve's limits, checked the same way
    if isinstance(target_iterations, bool) or not isinstance(target_iterations, int) or target_iterations < 1:
        raise ValueError(f"target_iterations must be a positive int, got {target_iterations!r}")
    psi = _check_positive("psi", psi, allow_zero=True)
    if direction not in (1, -1):
        raise ValueError(f"direction must be +1 (load factor increasing first) or -1, got {direction!r}")
    if load_max is not None and not (isinstance(load_max, (int, float)) and math.isfinite(load_max)):
        raise ValueError(f"load_max must be a finite number (or None: no target), got {load_max!r}")

    start = model.initial() if initial is None else model.check_solution(initial, "initial")
    if not Status.of(start.status).equilibrium:
        raise ValueError(f"initial must be an equilibrium, but its status is {Status.of(start.status).name}")
    problem = model.problem(params)
    f_ext = problem.load_pattern
    if load_pattern is not None:
        f = np.asarray(load_pattern, float)
        if f.shape != f_ext.shape or not np.all(np.isfinite(f)):
            raise ValueError(f"load_pattern must be finite nodal loads of shape {f_ext.shape} "
                             f"(e.g. from jaxrkpm.point_load), got shape {f.shape}")
        problem = problem.with_load_pattern(f)
    dg = model.prescribed(prescribed)
    if not (problem.loaded() or np.any(np.asarray(dg))):
        raise ValueError("nothing drives the path: the model has no dead load (tractions, body force) "
                         "and no pressure, and neither load_pattern nor prescribed is given")
    probes = None
    if points is not None:   # checked (inside the body, finite) before the path, not after it
        sf = model.shape_functions(model.body.check_inside(points, "probe point"), gradients=False)
        probes = jnp.asarray(sf.idx), jnp.asarray(sf.psi)
    newton = model.solver(**options).newton   # the options checked as a solve's
    arc = ArcLength(newton.linear, newton.tolerance)
    # explicit dtypes: a weakly typed Python scalar would compile arc_step a second time
    f64 = partial(jnp.asarray, dtype=jnp.float64)
    psi_a = f64(psi)

    u = jnp.asarray(start.u, jnp.float64)
    g = jnp.asarray(start.g, jnp.float64)
    lam = jnp.asarray(start.load, jnp.float64)
    state, stab, neg, rn0 = start_point(arc, problem, u, g, lam)
    rows = [(np.asarray(u), np.asarray(g), float(lam), float(rn0), int(stab), int(neg), 0.0, 0)]
    du_prev, dlam_prev = jnp.zeros_like(u), f64(direction)
    step_ds, cuts, status = ds, 0, PathStatus.COMPLETED
    try:
        for _ in range(steps):
            tries = 0
            while True:
                out = arc_step(arc, problem, lim.max_iter, u, g, dg, lam, state, du_prev, dlam_prev,
                               f64(step_ds), psi_a)
                code = int(out[3])
                if code == PathStatus.COMPLETED:
                    break
                if tries == max_cuts:
                    status = PathStatus.of(code)
                    break
                tries, cuts, step_ds = tries + 1, cuts + 1, step_ds / 2
            if status != PathStatus.COMPLETED:
                break
            u1, g1, lam1, _, its, rn, state, stab, neg = out
            du_prev, dlam_prev = u1 - u, lam1 - lam
            u, g, lam = u1, g1, lam1
            its = int(its)
            rows.append((np.asarray(u), np.asarray(g), float(lam), float(rn), int(stab), int(neg), step_ds, its))
            step_ds = min(step_ds * min(2.0, max(0.5, math.sqrt(target_iterations / max(its, 1)))), ds_max)
            if load_max is not None and float(lam) >= load_max:
                break
    except KeyboardInterrupt:
        status = PathStatus.INTERRUPTED

    U, G, L, R, ST, NEG, A, IT = (np.asarray(c) for c in zip(*rows))
    disp = None
    if probes is not None:
        idx, psi_p = probes
        # one point at a time: a compiled function of the path's length would recompile per length
        disp = np.stack([np.asarray(_point_values(problem, idx, psi_p, u_k, g_k)) for u_k, g_k in zip(U, G)])
    return EquilibriumPath(L, U, G, disp, R, ST, NEG, A, IT, cuts, PathStatus.of(status), start)


_point_values = jax.jit(lambda problem, idx, psi, u, g: problem.point_values(idx, psi, u, g))
