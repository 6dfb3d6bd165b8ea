"""The discrete problem of a model, as one public, jit-friendly object.

``model.problem(params)`` returns a ``Problem``: the model's arrays (``Ops``), its material
parameters (``Params``) and its static solver settings (``Config``). It is a pytree whose
leaves are the arrays and whose static part is the Config, so it can be passed into
``jax.jit``, ``vmap``-ed over stacked arrays, and differentiated in its parameters::

    prob = model.problem()
    r = jax.jit(lambda p, u, g: p.residual(u, g))(prob, u, g)
    K = prob.tangent(u, g)                  # dense K_ff
    state = prob.factorise(u, g)            # the linear solver's factorisation (explicit state)
    J = prob.jacobian(sol, dG, idx, psi, state=state)

Unknowns are the free RK coefficients u (Nf, d); g (Nb, d) are the prescribed values of the
essential particles and ``load`` the scale of the dead loads.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from ..mechanics import assembly as A
from . import implicit, newton as N
from .config import Config
from .results import Limits, Solution
from ..mechanics.assembly import Ops, Params


@jax.tree_util.register_pytree_node_class
class Problem:
    """Energy, residual, tangent, linear solves, Newton and implicit derivatives of one
    discrete problem (see the module docstring)."""

    def __init__(self, ops: Ops, params: Params, config: Config):
        self.ops, self.params, self.config = ops, params, config

    def tree_flatten(self):
        return (self.ops, self.params), self.config

    @classmethod
    def tree_unflatten(cls, config, children):
        return cls(*children, config)

    def replace(self, **kw) -> "Problem":
        """A copy with other ``ops``, ``params`` or ``config``."""
        return Problem(kw.pop("ops", self.ops), kw.pop("params", self.params), kw.pop("config", self.config))

    def with_config(self, **settings) -> "Problem":
        """A copy with other solver settings (Config fields)."""
        return self.replace(config=dataclasses.replace(self.config, **settings))

    # ------------------------------------------------------------------ the discrete model
    def coefficients(self, u, g):
        """Full RK coefficients (N, d): free ones u, essential ones by eq 3.22."""
        return A.coefficients(self.ops, u, g)

    def energy(self, u, g, load=1.0):
        """Total potential energy Pi(u; g, load)."""
        return A.energy(self.ops, self.params, self.config.W, u, g, load)[0]

    def min_det_f(self, u, g):
        """Smallest det F over the integration points."""
        return A.energy(self.ops, self.params, self.config.W, u, g, 0.0)[1]

    def residual(self, u, g, load=1.0):
        """r = dPi/du (Nf, d)."""
        return A.residual(self.ops, self.params, self.config.W, u, g, load)

    def force_scale(self, u, g):
        """The size of the terms summed into the residual (the convergence test's scale)."""
        wP = A.energy_residual_stress(self.ops, self.params, self.config.W, u, g, 1.0)[3]
        return A.stress_force_scale(self.ops, wP)

    def roundoff_floor(self, u, g):
        """The residual norm below which |r| carries no information at (u, g) (the convergence
        test's floor; see jaxrkpm.mechanics.assembly.force_scales)."""
        return A.force_scales(self.ops, self.params, self.config.W, self.coefficients(u, g))[1]

    def tangent_blocks(self, u, g):
        """The tangent in the full coefficients as (P, d, d) particle-pair blocks."""
        return A.pair_blocks(self.ops, self.params, self.config.W, self.coefficients(u, g))

    def tangent(self, u, g):
        """K_ff = dr/du, dense (Nf*d, Nf*d) whatever the linear solver (small problems)."""
        return A.dense_tangent(self.ops, self.tangent_blocks(u, g))

    def point_values(self, idx, psi, u, g):
        """Displacement (P, d) at points with precomputed (P, K) shape functions."""
        return A.point_values(self.ops, idx, psi, u, g)

    # ----------------------------------------------------------------------- linear solves
    def factorise(self, u, g):
        """The linear solver's factorisation of K_ff at (u, g): explicit state for
        ``solve_linear``, ``stability``, ``newton(..., state=...)`` and the derivatives."""
        return N.linear_state(self.ops, self.params, self.config, u, g)

    def solve_linear(self, state, rhs):
        """K_ff x = rhs with a factorisation from ``factorise``; rhs (Nf, d) or (Nf, d, m)."""
        return self.config.linear.solve(state, rhs)

    def stability(self, state):
        """The jaxrkpm.solvers.linalg.base.Stability code of a factorisation."""
        return self.config.linear.stability(state)

    # ------------------------------------------------------------------------- nonlinear
    def newton(self, u, g0, g1, l0=1.0, l1=1.0, *, max_iter=25, state=None, chord=False, floor=None):
        """One Newton solve from the equilibrium at (g0, l0) to (g1, l1): (u, status code,
        iterations, |r|, linear state); ``g0`` None: ``u`` is already an iterate at g1 (no
        predictor). ``chord=True`` reuses the factorisation ``state``
        for every step (no assembly); ``floor``: the round-off floor of the residual test
        (``roundoff_floor`` of a nearby state; default: computed in the solve); see
        jaxrkpm.solvers.newton.newton."""
        if state is None:
            if chord:
                raise ValueError("a chord solve needs the factorisation to reuse (state=...)")
            state = self.config.linear.empty(self.ops, jnp.result_type(u))
        return N.newton(self.ops, self.params, self.config, max_iter, u, g0, g1,
                        jnp.asarray(l0, jnp.float64), jnp.asarray(l1, jnp.float64), state, chord, floor)

    def solve(self, limits: Limits, u0, g0, g1, l0, l1, state=None) -> Solution:
        """Adaptive load stepping from the equilibrium (u0, g0, l0) to (g1, l1),
        differentiable in g1, l1 and the parameters (implicit function theorem). ``state``:
        a factorisation of K_ff at that start (``factorise``), which the first step reuses
        where the solver keeps states (see ``jaxrkpm.solvers.path.solve_path``)."""
        return implicit.solve_path_diff(self.ops, self.params, self.config, limits, u0, g0, g1, l0, l1, state)

    # ------------------------------------------------------------- implicit derivatives
    def sensitivity(self, sol: Solution, rhs, state=None):
        """K_ff^-1 rhs at the equilibrium ``sol`` (differentiable, transposable)."""
        return implicit.sensitivity(self.ops, self.params, self.config, sol.u, sol.g, sol.load, rhs, state)

    def response(self, sol: Solution, dG, state=None, refine: float = 0.0, guess=None):
        """du (m, Nf, d) of the free coefficients for m prescribed directions dG (m, Nb, d)
        (``guess``: a response to start the refinement from; see ``jaxrkpm.solvers.implicit.sensitivity``)."""
        return implicit.response(self.ops, self.params, self.config, sol.u, sol.g, sol.load, dG, state, refine, guess)

    def jacobian(self, sol: Solution, dG, idx, psi, state=None, refine: float = 0.0, du=None):
        """d(displacement at points)/d(direction) (P, d, m) for the directions dG (m, Nb, d)
        at points with shape functions (idx, psi), from one factorisation (``state``;
        ``refine`` > 0, the relative residual to refine to, where it factorises an earlier,
        nearby state: see ``jaxrkpm.solvers.implicit.sensitivity``), or from their ``response`` ``du``
        where it is already known."""
        if du is None:
            du = self.response(sol, dG, state, refine)
        return implicit.point_jacobian(self.ops, idx, psi, sol.u, sol.g, du, dG)
