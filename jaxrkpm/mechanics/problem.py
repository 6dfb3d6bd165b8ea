"""The discrete problem of a model as one jit-friendly pytree: what the solvers ask of the
mechanics.

``model.problem(params)`` returns a ``Problem``: the essential constraint (the map d = T(u, g)
from the unknowns to the full RK coefficients, ``constraint.Essential``), the tangent's pair
pattern and the terms of the total potential energy (``term.Term``: the strain energy, the
springs, the dead loads, and whatever else the model was given, e.g. a follower pressure),
whose contributions it sums. It can be passed into ``jax.jit``, ``vmap``-ed over stacked arrays
and differentiated in its parameters (``params``: each term's, by name)::

    prob = model.problem()
    r = jax.jit(lambda p, u, g: p.residual(u, g))(prob, u, g)
    K = prob.tangent(u, g)                  # dense K_ff (small problems)

Unknowns are the free RK coefficients u (Nf, d); g (Nb, d) are the prescribed values of the
essential particles and ``load`` the load scale (of the dead loads and pressures). The solvers
(:mod:`jaxrkpm.solvers`) see the mechanics only through these methods.
"""
from __future__ import annotations

from dataclasses import replace

import jax
import jax.numpy as jnp

from .constraint import Essential
from .loads import DeadLoad
from .term import Pairs, Term


def _summed(values):
    """The sum of the values that are not None, in order (None if all are)."""
    total = None
    for v in values:
        if v is not None:
            total = v if total is None else total + v
    return total


@jax.tree_util.register_pytree_node_class
class Problem:
    """Energy, residual and tangent of one discrete problem (see the module docstring).

    constraint  ``Essential``: d = T(u, g)
    pairs       ``Pairs``: the tangent's particle-pair pattern, shared by the terms' blocks
    terms       the terms of the energy, a tuple of ``Term`` with distinct names
    spacing     () the particle spacing (a length scale)"""

    def __init__(self, constraint: Essential, pairs: Pairs, terms: tuple, spacing):
        self.constraint, self.pairs, self.terms, self.spacing = constraint, pairs, tuple(terms), spacing

    def tree_flatten(self):
        return (self.constraint, self.pairs, self.terms, self.spacing), None

    @classmethod
    def tree_unflatten(cls, _, children):
        return cls(*children)

    def replace(self, **kw) -> "Problem":
        """A copy with another ``constraint``, ``pairs``, ``terms``, ``spacing`` or ``params``
        (name -> a term's parameters: those named are replaced)."""
        terms = kw.pop("terms", self.terms)
        if "params" in kw:
            params = kw.pop("params")
            terms = tuple(t.with_params(params[t.name]) if t.name in params else t for t in terms)
        out = Problem(kw.pop("constraint", self.constraint), kw.pop("pairs", self.pairs), terms,
                      kw.pop("spacing", self.spacing))
        if kw:
            raise TypeError(f"Problem.replace got unknown fields {sorted(kw)}")
        return out

    def term(self, name: str) -> Term:
        """The term called ``name``."""
        for t in self.terms:
            if t.name == name:
                return t
        raise KeyError(f"no term {name!r}; this problem has {[t.name for t in self.terms]}")

    def term_of(self, kind: type) -> Term:
        """The first term of type ``kind`` (a built-in one: ``StrainEnergy``, ``SpringTerm``,
        ``DeadLoad``), whatever its name."""
        for t in self.terms:
            if isinstance(t, kind):
                return t
        raise KeyError(f"no {kind.__name__} term; this problem has {[type(t).__name__ for t in self.terms]}")

    @property
    def params(self) -> dict:
        """The parameters the problem is differentiable in: term name -> its parameters."""
        return {t.name: t.params for t in self.terms}

    @property
    def load_pattern(self):
        """(N, d) the dead loads at load scale 1."""
        return self.term_of(DeadLoad).f

    def with_load_pattern(self, f_ext) -> "Problem":
        """The same problem with the dead load (N, d) at load scale 1 replaced by ``f_ext``."""
        f = jnp.asarray(f_ext)
        return self.replace(terms=tuple(replace(t, f=f) if isinstance(t, DeadLoad) else t for t in self.terms))

    def loaded(self) -> bool:
        """Whether the load scale drives anything (a nonzero dead load or pressure; host side)."""
        return any(t.loaded() for t in self.terms)

    # ------------------------------------------------------------------------ sizes
    @property
    def dim(self) -> int:
        return self.constraint.dim

    @property
    def n_free(self) -> int:
        """Free particles Nf (the unknowns are (Nf, d))."""
        return self.constraint.free.shape[-1]

    @property
    def n_pairs(self) -> int:
        """Particle pairs of the tangent's pattern (its (P, d, d) blocks)."""
        return self.pairs.count

    # -------------------------------------------------------------- the discrete model
    def coefficients(self, u, g):
        """Full RK coefficients (N, d): free ones u, essential ones by eq 3.22."""
        return self.constraint.coefficients(u, g)

    def energy_full(self, d, load=1.0, aux=None):
        """(Pi, smallest det F) in the full coefficients d (N, d): the terms' energies summed.
        ``aux``: a ``no_aux``-shaped zero per term (see ``Term.energy``)."""
        aux = (None,) * len(self.terms) if aux is None else aux
        values, dets = zip(*(t.energy(d, load, a) for t, a in zip(self.terms, aux)))
        dets = [x for x in dets if x is not None]
        det_min = dets[0] if dets else jnp.asarray(jnp.inf, d.dtype)
        for x in dets[1:]:
            det_min = jnp.minimum(det_min, x)
        return _summed(values), det_min

    def energy(self, u, g, load=1.0):
        """(total potential energy Pi(u; g, load), smallest det F over the integration points)."""
        return self.energy_full(self.coefficients(u, g), load)

    def residual(self, u, g, load=1.0):
        """r = dPi/du (Nf, d)."""
        return jax.grad(lambda v: self.energy(v, g, load)[0])(u)

    def energy_residual(self, u, g, load=1.0):
        """(Pi, min det F, r, aux) in one pass; ``aux`` (per term: the strain energy's weighted
        stresses) gives the force scale of the convergence test without a second pass
        (``force_scale``)."""
        (Pi, det_min), (r, aux) = jax.value_and_grad(
            lambda x, e: self.energy_full(self.coefficients(x, g), load, e),
            argnums=(0, 1), has_aux=True)(u, self.no_aux(u))
        return Pi, det_min, r, aux

    def no_aux(self, u):
        """``energy_residual``'s aux where no residual was evaluated (zeros)."""
        return tuple(t.aux_zeros(u) for t in self.terms)

    def force_scale(self, aux):
        """The size of the terms summed into the residual, from ``energy_residual``'s aux: each
        term's share, summed."""
        return _summed(t.force_scale(a) for t, a in zip(self.terms, aux))

    def force_scales(self, u, g):
        """(force scale, stiffness scale) at (u, g) in one pass: the stiffness scale times
        machine epsilon is the residual that rounding the strain produces (the convergence
        test's round-off floor: ``jaxrkpm.solvers.newton.Tolerance``)."""
        d = self.coefficients(u, g)
        force, stiffness = zip(*(t.force_scales(d) for t in self.terms))
        return _summed(force), _summed(stiffness)

    def tangent_blocks(self, u, g, load=1.0):
        """The tangent in the full coefficients as (P, d, d) particle-pair blocks at load scale
        ``load`` (a follower load's depends on it): the terms' blocks summed."""
        d = self.coefficients(u, g)
        return _summed(t.blocks(d, load, self.pairs) for t in self.terms)

    def dense_tangent(self, blocks):
        """K_ff = T^T K T dense (Nf d, Nf d) from pair blocks (T: the essential transformation)."""
        return self.constraint.dense_tangent(blocks, self.pairs)

    def tangent(self, u, g, load=1.0):
        """K_ff = dr/du at load scale ``load``, dense (Nf*d, Nf*d) (small problems)."""
        return self.dense_tangent(self.tangent_blocks(u, g, load))

    def point_values(self, idx, psi, u, g):
        """Displacement (P, d) at points with precomputed (P, K) shape functions."""
        return self.constraint.point_values(idx, psi, u, g)

    def reactions(self, u, g, load=1.0):
        """(Nb, d) dPi/dg: the generalized reaction at each essential particle (with the terms'
        ``reaction_correction`` where their load at held points is not dPi/dd)."""
        d = self.coefficients(u, g)
        r_d = jax.grad(lambda c: self.energy_full(c, load)[0])(d)
        extra = _summed(t.reaction_correction(d, load) for t in self.terms)
        return self.constraint.reactions(r_d if extra is None else r_d + extra)
