"""Post-processing of a model's solutions: coefficients, displacements, deformation gradients,
stresses, reactions and energy at a Solution. Functions over (model, solution).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..mechanics.materials import det, green_lagrange, pk2
from ..mechanics.strain import StrainEnergy, deformation_gradients
from ..solvers.results import Solution
from .inputs import check_set, check_solution, params_with

STRESSES = ("pk2", "pk1", "cauchy")

# Each post-processing step is one compiled program: run eagerly, JAX compiles every
# operation of the residual's backward pass on its own, which costs a cold process more than
# the program does (``experiments/bench_peer.py``'s first_post_s); FD evaluates point values
# per re-solve
point_values = jax.jit(lambda constraint, idx, psi, u, g: constraint.point_values(idx, psi, u, g))
_coefficients = jax.jit(lambda constraint, u, g: constraint.coefficients(u, g))
_reactions = jax.jit(lambda problem, u, g, load: problem.reactions(u, g, load))
_energy = jax.jit(lambda problem, d, load: problem.energy_full(d, load)[0])


@jax.jit
def _gradients(idx, dpsi, constraint, u, g):
    return deformation_gradients(idx, dpsi, constraint.coefficients(u, g))


class PointTables:
    """Device arrays (idx, psi) of a model's shape functions at point sets, cached per set: a
    repeated ``displacement`` or ``jacobian`` at the same points would otherwise re-evaluate
    the RK shape functions (a KD-tree query and moment matrices in NumPy) each call, a large
    share of a needle-loop increment (``experiments/bench_sweep.py``)."""

    def __init__(self, shape_functions, size: int = 64):
        self.shape_functions, self.size, self.cache = shape_functions, size, {}

    def __call__(self, points):
        X = np.asarray(points, np.float64)
        key = (X.shape, X.tobytes())
        if key not in self.cache:
            sf = self.shape_functions(X, gradients=False)
            if len(self.cache) >= self.size:
                self.cache.clear()
            self.cache[key] = (jnp.asarray(sf.idx), jnp.asarray(sf.psi))
        return self.cache[key]


def coefficients(model, sol: Solution):
    """(N, d) RK coefficients of a solution (essential ones by eq 3.22)."""
    check_solution(model, sol)
    return _coefficients(model.constraint, sol.u, sol.g)


def displacement(model, sol: Solution, points):
    """u(X) at reference points (P, d)."""
    check_solution(model, sol)
    idx, psi = model.point_tables(points)
    return point_values(model.constraint, idx, psi, sol.u, sol.g)


def deformation_gradient(model, sol: Solution, points):
    """F at reference points (P, d, d)."""
    check_solution(model, sol)
    sf = model.shape_functions(points)
    return _gradients(jnp.asarray(sf.idx), jnp.asarray(sf.dpsi), model.constraint, sol.u, sol.g)


def material_parameters(model, points, params=None) -> tuple[dict, dict]:
    """The material's parameters at ``points`` (name -> (P,), with the scalar overrides of
    ``params``) and its global tensors (with those of ``params``)."""
    tensors = params_with(model, params)[model.problem().term_of(StrainEnergy).name]["tensors"]
    prm = {k: jnp.asarray(v) for k, v in model.material.point_params(points).items()}
    if params:
        prm.update({k: jnp.broadcast_to(jnp.asarray(v), (len(points),)) for k, v in params.items()
                    if k in prm and not callable(v) and jnp.ndim(v) == 0})
    return prm, tensors


def stress(model, sol: Solution, points, kind: str = "cauchy", params=None):
    """Stress at points (P, d, d): 'pk2' (S), 'pk1' (P = F S) or 'cauchy' (eq 3.5)."""
    if kind not in STRESSES:
        raise ValueError(f"unknown stress kind {kind!r}: choose 'pk2', 'pk1' or 'cauchy'")
    P = model.body.check_inside(points)
    F = deformation_gradient(model, sol, P)
    prm, tensors = material_parameters(model, P, params)
    axes = {**{k: 0 for k in prm}, **{k: None for k in tensors}}
    S = jax.vmap(lambda E, p: pk2(model.material.W, E, p), in_axes=(0, axes))(green_lagrange(F), {**prm, **tensors})
    if kind == "pk2":
        return S
    if kind == "pk1":
        return F @ S
    return F @ S @ jnp.swapaxes(F, -1, -2) / det(F)[:, None, None]


def reactions(model, sol: Solution, params=None):
    """(Nb, d) generalized reaction at each essential particle: dPi/dg, the force the
    constraint exerts on the body (exact discrete reaction from the residual)."""
    check_solution(model, sol)
    return _reactions(model.problem(params), sol.u, sol.g, sol.load)


def reaction(model, sol: Solution, name: str, params=None):
    """(d,) resultant force exerted on the body by the essential set ``name``."""
    check_set(model, name)
    return jnp.sum(reactions(model, sol, params)[model.sets.slices[name]], axis=0)


def energy(model, sol: Solution, params=None):
    """The total potential energy at a solution."""
    return _energy(model.problem(params), coefficients(model, sol), sol.load)
