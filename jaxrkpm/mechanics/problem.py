"""The discrete problem of a model as one jit-friendly pytree: what the solvers ask of the
mechanics.

``model.problem(params)`` returns a ``Problem``: the model's arrays (``Ops``), its parameters
(``Params``, differentiable) and its strain energy density (static). It can be passed into
``jax.jit``, ``vmap``-ed over stacked arrays and differentiated in its parameters::

    prob = model.problem()
    r = jax.jit(lambda p, u, g: p.residual(u, g))(prob, u, g)
    K = prob.tangent(u, g)                  # dense K_ff (small problems)

Unknowns are the free RK coefficients u (Nf, d); g (Nb, d) are the prescribed values of the
essential particles and ``load`` the scale of the dead loads. The solvers
(:mod:`jaxrkpm.solvers`) see the mechanics only through these methods.
"""
from __future__ import annotations

from typing import Callable

import jax
import jax.numpy as jnp

from . import assembly as A
from .assembly import Ops, Params


@jax.tree_util.register_pytree_node_class
class Problem:
    """Energy, residual and tangent of one discrete problem (see the module docstring)."""

    def __init__(self, ops: Ops, params: Params, W: Callable):
        self.ops, self.params, self.W = ops, params, W

    def tree_flatten(self):
        return (self.ops, self.params), self.W

    @classmethod
    def tree_unflatten(cls, W, children):
        return cls(*children, W)

    def replace(self, **kw) -> "Problem":
        """A copy with other ``ops``, ``params`` or ``W``."""
        return Problem(kw.pop("ops", self.ops), kw.pop("params", self.params), kw.pop("W", self.W))

    def with_load_pattern(self, f_ext) -> "Problem":
        """The same problem with the dead load (N, d) at load scale 1 replaced by ``f_ext``."""
        return self.replace(ops=self.ops._replace(f_ext=jnp.asarray(f_ext)))

    # ------------------------------------------------------------------------ sizes
    @property
    def dim(self) -> int:
        return self.ops.f_ext.shape[-1]

    @property
    def n_free(self) -> int:
        """Free particles Nf (the unknowns are (Nf, d))."""
        return self.ops.free.shape[-1]

    @property
    def spacing(self):
        """() the particle spacing (a length scale)."""
        return self.ops.spacing

    @property
    def n_pairs(self) -> int:
        """Particle pairs of the tangent's pattern (its (P, d, d) blocks)."""
        return self.ops.pair_i.shape[-1]

    # -------------------------------------------------------------- the discrete model
    def coefficients(self, u, g):
        """Full RK coefficients (N, d): free ones u, essential ones by eq 3.22."""
        return A.coefficients(self.ops, u, g)

    def energy(self, u, g, load=1.0):
        """(total potential energy Pi(u; g, load), smallest det F over the integration points)."""
        return A.energy(self.ops, self.params, self.W, u, g, load)

    def residual(self, u, g, load=1.0):
        """r = dPi/du (Nf, d)."""
        return A.residual(self.ops, self.params, self.W, u, g, load)

    def energy_residual(self, u, g, load=1.0):
        """(Pi, min det F, r, aux) in one pass; ``aux`` (the weighted stresses) gives the force
        scale of the convergence test without a second pass (``force_scale``)."""
        return A.energy_residual_stress(self.ops, self.params, self.W, u, g, load)

    def no_aux(self, u):
        """``energy_residual``'s aux where no residual was evaluated (zeros)."""
        return A.zero_stress(self.ops, u)

    def force_scale(self, aux):
        """The size of the terms summed into the residual, from ``energy_residual``'s aux."""
        return A.stress_force_scale(self.ops, aux)

    def force_scales(self, u, g):
        """(force scale, stiffness scale) at (u, g) in one pass: the stiffness scale times
        machine epsilon is the residual that rounding the strain produces (the convergence
        test's round-off floor: ``jaxrkpm.solvers.newton.Tolerance``)."""
        return A.force_scales(self.ops, self.params, self.W, self.coefficients(u, g))

    def tangent_blocks(self, u, g):
        """The tangent in the full coefficients as (P, d, d) particle-pair blocks."""
        return A.pair_blocks(self.ops, self.params, self.W, self.coefficients(u, g))

    def dense_tangent(self, blocks):
        """K_ff = T^T K T dense (Nf d, Nf d) from pair blocks (T: the essential transformation)."""
        return A.dense_tangent(self.ops, blocks)

    def tangent(self, u, g):
        """K_ff = dr/du, dense (Nf*d, Nf*d) (small problems)."""
        return self.dense_tangent(self.tangent_blocks(u, g))

    def point_values(self, idx, psi, u, g):
        """Displacement (P, d) at points with precomputed (P, K) shape functions."""
        return A.point_values(self.ops, idx, psi, u, g)
