"""Arc-length continuation of a Model's equilibrium path (the driver is
:mod:`jaxrkpm.solvers.continuation`), and point loads for it.
"""
from __future__ import annotations

import math
from typing import Mapping

import jax.numpy as jnp
import numpy as np

from ..solvers.continuation import ArcLength, ArcLengthPath, ArcPath, EquilibriumPath, arc_step, start_point
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
    says why the path stopped, every accepted point is kept; ``stats`` its linear work)."""
    _check_model(model)
    ds, ds_max, psi = _check_lengths(ds, ds_max, psi)
    lim = Limits.of(steps, max_iter, max_cuts)   # the solve's limits, checked the same way
    _check_path_options(target_iterations, direction, load_max)
    start = model.initial() if initial is None else model.check_solution(initial, "initial")
    if not Status.of(start.status).equilibrium:
        raise ValueError(f"initial must be an equilibrium, but its status is {Status.of(start.status).name}")
    problem = _driven_problem(model, params, load_pattern)
    dg = model.prescribed(prescribed)
    if not (problem.loaded() or np.any(np.asarray(dg))):
        raise ValueError("nothing drives the path: the model has no dead load (tractions, body force) "
                         "and no pressure, and neither load_pattern nor prescribed is given")
    probes = _probes(model, points)   # checked (inside the body, finite) before the path, not after it
    newton = model.solver(**options).newton   # the options checked as a solve's
    # the compiled step and start looked up here, at the call: a caller may wrap them
    driver = ArcLengthPath(ArcLength(newton.linear, newton.tolerance), attempt=arc_step, first=start_point)
    # explicit dtypes: a weakly typed Python scalar would compile arc_step a second time
    args = ArcPath(dg, jnp.asarray(psi, jnp.float64), lim.max_iter, direction, ds, ds_max, steps, max_cuts,
                   target_iterations, load_max, probes)
    return driver.solve(problem, args, start)


def _check_model(model):
    if not isinstance(model, Model):
        raise TypeError(f"model must be a jaxrkpm Model, got {type(model).__name__}")
    if model.unconstrained:
        raise ValueError("unconstrained: the model has no essential set and no springs, so it has "
                         "rigid-body modes and no path is unique; hold part of it or add Springs")


def _check_lengths(ds, ds_max, psi):
    """(ds, ds_max, psi) checked, ds_max 4 ds by default."""
    ds = _check_positive("ds", ds)
    ds_max = 4.0 * ds if ds_max is None else _check_positive("ds_max", ds_max)
    if ds_max < ds:
        raise ValueError(f"ds_max ({ds_max}) must be at least ds ({ds})")
    return ds, ds_max, _check_positive("psi", psi, allow_zero=True)


def _check_path_options(target_iterations, direction, load_max):
    if isinstance(target_iterations, bool) or not isinstance(target_iterations, int) or target_iterations < 1:
        raise ValueError(f"target_iterations must be a positive int, got {target_iterations!r}")
    if direction not in (1, -1):
        raise ValueError(f"direction must be +1 (load factor increasing first) or -1, got {direction!r}")
    if load_max is not None and not (isinstance(load_max, (int, float)) and math.isfinite(load_max)):
        raise ValueError(f"load_max must be a finite number (or None: no target), got {load_max!r}")


def _driven_problem(model, params, load_pattern):
    """The model's problem with ``params``, its dead loads replaced by ``load_pattern`` where
    given (checked)."""
    problem = model.problem(params)
    if load_pattern is None:
        return problem
    f_ext = problem.load_pattern
    f = np.asarray(load_pattern, float)
    if f.shape != f_ext.shape or not np.all(np.isfinite(f)):
        raise ValueError(f"load_pattern must be finite nodal loads of shape {f_ext.shape} "
                         f"(e.g. from jaxrkpm.point_load), got shape {f.shape}")
    return problem.with_load_pattern(f)


def _probes(model, points):
    """(idx, psi) of the probe points' shape functions, or None without points."""
    if points is None:
        return None
    sf = model.shape_functions(model.body.check_inside(points, "probe point"), gradients=False)
    return jnp.asarray(sf.idx), jnp.asarray(sf.psi)
