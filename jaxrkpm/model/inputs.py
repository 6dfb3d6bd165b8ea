"""What a user hands a model, checked and put into its shapes: prescribed values, Solutions,
parameter overrides and moved springs. Functions over the model (its public attributes).
"""
from __future__ import annotations

from typing import Mapping

import jax
import jax.numpy as jnp
import numpy as np

from ..mechanics.loads import SpringTerm, spring_psi
from ..mechanics.strain import StrainEnergy
from ..solvers.results import Critical, Solution


def is_concrete(x) -> bool:
    """Whether x has a value here (not a tracer of jit, vmap or a derivative)."""
    return not isinstance(x, jax.core.Tracer)


def concrete(x):
    """x as a NumPy array, or None where its value is not known (inside jit or vmap). Under
    jax.jacfwd / jax.grad outside jit the value is known: the tracer carries it."""
    while isinstance(x, jax.core.Tracer):
        value = getattr(x, "to_concrete_value", lambda: None)()
        if value is None:
            return None
        x = value
    return np.asarray(x)


def unconstrained(model) -> bool:
    """No essential set and no springs: the body may translate and rotate freely. Such a model
    is fine for its tangent (its rigid-body modes) and energy; a solve is refused."""
    return len(model.sets.bnd) == 0 and not np.any(np.asarray(model.problem().term_of(SpringTerm).k) > 0)


def check_constrained(model) -> None:
    if model.unconstrained:
        raise ValueError("unconstrained: rigid-body modes. The model has no essential set and no "
                         "springs, so it can translate and rotate freely and no solve has a unique "
                         "equilibrium; hold part of it (essential={'wall': body.select(...)}) or "
                         "add Springs")


def check_set(model, name: str) -> None:
    if name not in model.sets.slices:
        raise ValueError(f"unknown essential set {name!r}; this model has {list(model.sets.names)}")


def check_g(model, g, what: str = "g"):
    """All prescribed values (Nb, d) as a float array: the right shape for THIS model (a g of
    another model is named, not a broadcasting error) and finite."""
    shape = (len(model.sets.bnd), model.dim)
    try:
        g = jnp.asarray(g, jnp.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be a {shape} array of prescribed values") from None
    if g.shape != shape:
        raise ValueError(f"{what} has shape {g.shape}, but this model has {shape[0]} essential "
                         f"particles in {shape[1]}D: shape {shape} (from model.prescribed(...) of "
                         "this model)")
    if is_concrete(g) and not np.all(np.isfinite(np.asarray(g))):
        raise ValueError(f"{what} has non-finite prescribed values (NaN/inf) at essential "
                         f"particles {np.flatnonzero(~np.isfinite(np.asarray(g)).all(1))[:5].tolist()}")
    return g


def check_solution(model, sol, what: str = "solution") -> Solution:
    """``sol`` if it is a Solution of this model's shapes (u (Nf, d), g (Nb, d)); a ValueError
    naming the mismatch for one of another model (or not a Solution)."""
    if not isinstance(sol, Solution):
        raise TypeError(f"{what} must be a jaxrkpm Solution (from model.solve), got {type(sol).__name__}")
    want_u, want_g = (len(model.sets.free), model.dim), (len(model.sets.bnd), model.dim)
    if jnp.shape(sol.u) != want_u or jnp.shape(sol.g) != want_g:
        raise ValueError(f"{what} does not belong to this model: its u, g have shapes "
                         f"{jnp.shape(sol.u)}, {jnp.shape(sol.g)}; this model's are {want_u}, "
                         f"{want_g} (a Solution of another model, or a batched one: index it)")
    return sol


def initial(model) -> Solution:
    """The undeformed, unloaded equilibrium."""
    z = jnp.zeros((), jnp.int32)
    f = jnp.zeros((), jnp.float64)  # not weak-typed: the same jit signature as a solve's output
    u = jnp.zeros((len(model.sets.free), model.dim))
    return Solution(u, jnp.zeros((len(model.sets.bnd), model.dim)), f, z, f + 1.0, z, z, z, f, z, Critical.empty(u))


def set_values(model, name: str, v):
    """The prescribed values of set ``name`` (n_set, d) from (d,) (rigid) or (n_set, d)."""
    check_set(model, name)
    d, sl = model.dim, model.sets.slices[name]
    n = sl.stop - sl.start
    try:
        v = jnp.asarray(v, dtype=jnp.float64)
    except (TypeError, ValueError):
        raise ValueError(f"prescribed value for {name!r} must be numbers of shape ({d},) (rigid) "
                         f"or ({n}, {d}) (per particle), got {v!r}") from None
    if v.shape == (d,):
        v = jnp.broadcast_to(v, (n, d))
    elif v.shape != (n, d):
        raise ValueError(f"prescribed value for {name!r} must have shape ({d},) (rigid) "
                         f"or ({n}, {d}) (per particle), got {v.shape}")
    if is_concrete(v) and not np.all(np.isfinite(np.asarray(v))):
        raise ValueError(f"prescribed value for {name!r} is not finite")
    return v


def prescribed(model, values: Mapping | None = None, base=None):
    """(Nb, d) prescribed displacements from name -> (d,) rigid translation or (n_set, d); sets
    not named keep ``base`` (default: zero)."""
    g = jnp.zeros((len(model.sets.bnd), model.dim)) if base is None else check_g(model, base, "base")
    if values is not None and not isinstance(values, Mapping):
        raise TypeError(f"prescribed values must be a dict set name -> value, got {type(values).__name__}")
    for name, v in (values or {}).items():
        v = set_values(model, name, v)
        g = g.at[model.sets.slices[name]].set(v)
    return g


def point_parameter(model, name: str, v, Q: int):
    """A material parameter's override (Q,): a scalar, (Q,) values, or a field X -> (Q,) at
    the volume's integration points; finite, and of the material's sign."""
    if callable(v):
        v = np.asarray(v(model.volume.points), float)
    v = jnp.asarray(v, jnp.float64)
    if v.ndim == 0:
        v = jnp.broadcast_to(v, (Q,))
    if v.shape != (Q,):
        raise ValueError(f"parameter {name!r} must be a scalar or ({Q},) values, got {v.shape}")
    if is_concrete(v):
        arr = np.asarray(v)
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"parameter {name!r} is not finite")
        model.material.check_sign(name, arr)
    return v


def params_with(model, overrides: Mapping | None = None) -> dict:
    """The problem's parameters (term name -> its parameters, ``Problem.params``) with
    overrides: a material parameter's name -> scalar, (Q,) array, or field X -> (Q,); a
    term's name (e.g. "springs", a pressure's) -> its value (see the term)."""
    problem = model.problem()
    if not overrides:
        return problem.params
    if not isinstance(overrides, Mapping):
        raise TypeError(f"params must be a dict name -> value, got {type(overrides).__name__}")
    params = dict(problem.params)
    strain = problem.term_of(StrainEnergy)
    point, tensors = dict(strain.point), dict(strain.tensors)
    terms = {t.name: t for t in problem.terms if t is not strain}
    for k, v in overrides.items():
        if k in point:
            point[k] = point_parameter(model, k, v, strain.w.shape[0])
        elif k in tensors:
            tensors[k] = jnp.asarray(v, jnp.float64)
        elif k in terms:
            params[k] = terms[k].check_params(v)
        else:
            raise ValueError(f"unknown material parameter {k!r}; {model.material.name} has "
                             f"{sorted(point) + sorted(tensors)}, and the model's terms {sorted(terms)}")
    params[strain.name] = {"point": point, "tensors": tensors}
    return params


def springs_at(model, points, stiffness=None) -> dict:
    """The parameters of the model's springs moved to ``points`` (S, d) (and, optionally, new
    stiffnesses): JAX, so a solve is differentiable in both. The points must stay where the
    particles of the spring region cover them."""
    springs = model.problem().term_of(SpringTerm)
    S = springs.idx.shape[0]
    if S == 0:
        raise ValueError("this model has no springs (Model(..., springs=Springs(...)))")
    points = jnp.asarray(points, jnp.float64)
    if points.shape != (S, model.dim):
        raise ValueError(f"spring points must have shape ({S}, {model.dim}), got {points.shape}")
    psi = spring_psi(model.body, model.a, points, np.asarray(springs.idx))
    if is_concrete(psi) and not np.allclose(np.asarray(psi).sum(1), 1.0, atol=1e-8):
        raise ValueError("a spring point left its region (its shape functions no longer sum "
                         "to 1): widen Springs(region=...)")
    k = springs.k if stiffness is None else jnp.broadcast_to(jnp.asarray(stiffness, jnp.float64), (S,))
    return {"psi": psi, "k": k}
