"""A model's discrete problem, assembled once from its discretisation: the built-in terms
(strain energy, springs, dead loads), the user's terms, their tangent pattern and the
essential constraint, summed into a ``Problem``.
"""
from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from ..discretise.discretisation import Discretisation
from .constraint import essential, held_components
from .loads import DeadLoad, SpringTerm, Springs, dead_load, spring_term
from .materials import Material
from .problem import Problem
from .strain import StrainEnergy, strain_energy
from .term import Context, TermSpec, on_pattern

BUILT_IN = (StrainEnergy, SpringTerm, DeadLoad)   # the terms every model has, found by type


class Assembled(NamedTuple):
    """The problem and its tangent's pair pattern (NumPy, for the host-side linear systems)."""

    problem: Problem
    pair_i: np.ndarray
    pair_j: np.ndarray


def context(disc: Discretisation) -> Context:
    """What a term's builder may use, from the discretisation."""
    return Context(disc.body, disc.a, disc.support, disc.volume, disc.surface, disc.sets, disc.balanced)


def check_options(material, anti_locking, terms) -> None:
    """The options of ``assemble`` that can be checked before anything is built."""
    if not isinstance(material, Material):
        raise ValueError(f"material must be a jaxrkpm Material, got {type(material).__name__}")
    if anti_locking not in (None, True, False):
        raise ValueError(f"anti_locking must be None (where the material needs it), True or False, "
                         f"got {anti_locking!r}")
    if isinstance(terms, TermSpec) or not isinstance(terms, (list, tuple)):
        raise TypeError(f"terms must be a list of term specifications (e.g. [jaxrkpm.Pressure(...)]), "
                        f"got {type(terms).__name__}")
    for spec in terms:
        if not isinstance(spec, TermSpec):
            raise TypeError(f"each of terms must be a term specification (e.g. jaxrkpm.Pressure), "
                            f"got {type(spec).__name__}")


def user_terms(specs, ctx: Context, taken) -> list:
    """The terms built from ``Model(terms=...)``: each spec's name must be free (not a
    material parameter's, not another term's: it keys the term's parameters)."""
    taken, out = set(taken), []
    for spec in specs:
        if not isinstance(spec.name, str) or spec.name in taken:
            raise ValueError(f"term name {spec.name!r} is taken (by a term or a material parameter): "
                             f"give it another name=...")
        taken.add(spec.name)
        out.append(spec.build(ctx))
    return out


def assemble(disc: Discretisation, material: Material, anti_locking: bool | None = None,
             springs: Springs | None = None, body_force=None, tractions=(), terms=()) -> Assembled:
    """The ``Problem`` of ``material`` on ``disc`` with its loads and further terms (the options
    as ``Model``'s), and the pair pattern of its tangent."""
    check_options(material, anti_locking, terms)
    ctx = context(disc)
    body, d = disc.body, disc.body.dim
    strain = strain_energy(ctx, material, anti_locking, disc.patches)
    built = [strain, spring_term(ctx, springs), dead_load(ctx, body_force, tractions)]
    built += user_terms(terms, ctx, {t.name for t in built} | {*strain.point, *strain.tensors})
    pairs, built, pair_i, pair_j = on_pattern(tuple(built), body.n, d)
    if disc.sets.partial:
        constraint = held_components(body, disc.sets, disc.a, disc.support, body.n, d)
    else:
        constraint = essential(disc.sets, disc.trans, body.n, d, pair_i, pair_j)
    return Assembled(Problem(constraint, pairs, built, jnp.asarray(body.spacing)), pair_i, pair_j)
