"""Terms: the pieces of the total potential energy, each a small pytree, and what they share.

The Problem (:mod:`jaxrkpm.mechanics.problem`) sums the contributions of its terms, all in the
full RK coefficients d (N, d) at the load scale ``load``::

    Pi(d; load)  = sum_t  term.energy(d, load)[0]
    K(d; load)   = sum_t  term.blocks(d, load, pairs)    # (P, d, d) particle-pair blocks
    force scale  = sum_t  term.force_scale(aux)          # the convergence test's scale

and reaches d from the unknowns through its constraint (``constraint.Essential``, the
transformation d = T(u, g) of eq 3.22), which is not a term: it adds no energy, it is the
map every energy is evaluated through, and the tangent's reduction K_ff = T^T K T is its job.

A term is a frozen dataclass registered as a pytree (``@term``): its arrays (tables built once,
and its parameters) are the leaves, its knobs are ``static()`` fields (hashable aux data: a
different value compiles a different program, never a patched module global). Its
parameters (``params``, a dict) are what a solve is differentiable in (``Model.solve(params=
{term.name: ...})``). Nothing mutable is static; geometry is NumPy and built once, outside
jit, by the term's builder (a ``TermSpec``'s ``build``).

Writing a new term, e.g. zero-length springs of one stiffness k that hold material points
(the shape of every term; :mod:`jaxrkpm.mechanics.pressure` is a worked one)::

    from dataclasses import dataclass, replace

    import jax
    import jax.numpy as jnp
    import numpy as np

    from jaxrkpm.internal import Term, TermSpec, static, term

    @term
    class Tether(Term):
        idx: jax.Array            # (S, K) particles that reach the tethered points
        psi: jax.Array            # (S, K) their shape functions there
        k: jax.Array              # () stiffness: a parameter
        pair_id: jax.Array = None  # (S, K, K) the pairs of idx's rows (set by ``placed``)
        name: str = static("tether")

        def energy(self, d, load, aux=None):
            u = jnp.einsum("sk,ski->si", self.psi, d[self.idx])
            return 0.5 * self.k * jnp.sum(u * u), None          # (value, no det F)

        def lists(self):
            return np.asarray(self.idx)

        def placed(self, ids):
            return replace(self, pair_id=jnp.asarray(ids))

        def blocks(self, d, load, pairs):                       # or omit: no tangent blocks
            kk = self.k * jnp.einsum("sk,sm->skm", self.psi, self.psi)
            s = jax.ops.segment_sum(kk.ravel(), self.pair_id.ravel(), num_segments=pairs.count)
            return s[:, None, None] * jnp.eye(d.shape[1])

        @property
        def params(self):
            return {"k": self.k}

        def with_params(self, params):
            return replace(self, k=params["k"])

    @dataclass(frozen=True)
    class TetherSpec(TermSpec):                                  # what the user passes
        points: np.ndarray
        k: float = 1.0
        name: str = "tether"

        def build(self, ctx):                                   # NumPy, once
            sf = ctx.body.shape_functions(self.points, ctx.a, gradients=False,
                                          support_factor=ctx.support)
            return Tether(jnp.asarray(sf.idx), jnp.asarray(sf.psi), jnp.asarray(self.k), name=self.name)

and ``Model(..., terms=[TetherSpec(points)])`` adds it, ``solve(params={"tether": {"k": k}})``
overrides its parameter (``Term.check_params``); export the spec in ``jaxrkpm/__init__.pyi``.
A term whose tangent blocks are cheap to get by autodiff may form them so (the pressure's
per-facet Hessians are); the energy's gradient, the residual, is always autodiff.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any, ClassVar, Mapping, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..discretise.body import Body
from ..discretise.constraints import EssentialSets
from ..discretise.pairs import pair_pattern
from ..discretise.quadrature import Table


def static(default: Any = None):
    """A static field of a term: pytree aux data (hashable, part of the compiled program's
    key), e.g. a knob or a name."""
    return field(default=default, metadata={"static": True})


def term(cls):
    """Class decorator: a frozen dataclass registered as a pytree, its ``static()`` fields
    aux data and the rest leaves. Compared by identity (its leaves are arrays)."""
    cls = dataclass(frozen=True, eq=False)(cls)
    meta = [f.name for f in fields(cls) if f.metadata.get("static")]
    data = [f.name for f in fields(cls) if not f.metadata.get("static")]
    return jax.tree_util.register_dataclass(cls, data_fields=data, meta_fields=meta)


class Pairs(NamedTuple):
    """The tangent's pattern: the particle pairs (i, j) whose blocks any term fills (both
    orders of every pair), sorted; ``t`` the index of each pair's transpose (j, i)."""

    i: jax.Array   # (P,)
    j: jax.Array   # (P,)
    t: jax.Array   # (P,)

    @property
    def count(self) -> int:
        return self.i.shape[-1]



def boolean_mask(values, what: str) -> np.ndarray:
    """A predicate's answer, checked to be booleans: numbers would be cast (non-zero = True),
    loading the wrong part of the boundary without a word. ``what`` names the predicate."""
    arr = np.asarray(values)
    if arr.dtype != np.bool_:
        raise ValueError(f"{what} must return booleans, got {arr.dtype} values (a number is not a side: "
                         "return a comparison, e.g. X[:, 0] > 0.5)")
    return arr

@dataclass(frozen=True)
class Context:
    """What a term's builder may use (host side, NumPy): the body, its kernel dilation ``a``
    (= ``support`` x spacing), the volume and boundary integration tables, the essential
    sets, and ``balanced``: the boundary rule that the volume rule's stresses balance exactly
    (SCNI's boundary integral, with its interpolated shape functions; for Gauss integration
    the surface table itself), for terms that must pass the patch test with a boundary load."""

    body: Body
    a: float
    support: float
    volume: Table
    surface: Table
    sets: EssentialSets
    balanced: Table | None = None


class Term:
    """A contribution to the total potential energy (see the module docstring). Defaults:
    no tangent blocks, no parameters, no share of the force scale."""

    name: str
    # True: the energy is linear in d by construction (a dead load): it has no tangent blocks
    # and the build does not check that (a class attribute, not a field)
    linear: ClassVar[bool] = False
    # False: the tangent changes by orders of magnitude within a load step (a contact barrier),
    # so a kept factorisation contracts slowly and eager solves take full Newton steps instead
    # of modified Newton (``experiments/bench_contact.py`` counts the iterations)
    modified_newton: ClassVar[bool] = True

    # ------------------------------------------------------------------ inside jit
    def energy(self, d, load, aux=None):
        """(energy at the full coefficients d (N, d) and load scale ``load``, the smallest
        det F the term sees or None). ``aux``: this term's entry of ``aux_zeros`` (zero in
        value), whose gradient is the aux the force scale reads."""
        raise NotImplementedError

    def aux_zeros(self, u):
        """Zeros that ``energy`` adds where the gradient with respect to them is wanted
        (the strain energy's stress), in u's dtype; None: no aux."""
        return None

    def blocks(self, d, load, pairs: Pairs):
        """The energy's Hessian in d at load scale ``load`` as (P, d, d) blocks over ``pairs``;
        None: none (the term is linear in d)."""
        return None

    def force_scale(self, aux):
        """This term's share of the convergence test's force scale (the size of what it adds
        to the residual), from its aux; None: nothing."""
        return None

    def force_scales(self, d):
        """(force scale share, stiffness scale share) at d without aux (either None)."""
        return self.force_scale(None), None

    def reaction_correction(self, d, load):
        """What the reactions add to the energy's gradient (N, d) where the term's load is not
        that gradient at held points (a follower pressure at the held rim of an open surface);
        None: nothing. The residual never sees it: held points do not move with the unknowns."""
        return None

    # ------------------------------------------------------------- parameters
    @property
    def params(self) -> dict:
        """The parameters a solve is differentiable in."""
        return {}

    def with_params(self, params: dict) -> "Term":
        return self

    def check_params(self, value) -> dict:
        """``params`` from a user's override ``Model.solve(params={name: value})``, checked:
        by default a dict of the same names and shapes as ``params``."""
        ref = self.params
        if not ref:
            raise ValueError(f"the {self.name!r} term has no parameters to override")
        if not (isinstance(value, Mapping) and set(value) == set(ref)
                and all(jnp.shape(value[k]) == jnp.shape(ref[k]) for k in ref)):
            raise ValueError(f"params[{self.name!r}] must be a dict of " + ", ".join(
                f"{k!r} (shape {jnp.shape(v)})" for k, v in ref.items()))
        return dict(value)

    # --------------------------------------------------------- host side, at build
    def lists(self) -> np.ndarray | None:
        """(R, K) particle lists: the tangent pattern holds every pair within a row (NumPy,
        at build). None: the term adds no blocks."""
        return None

    def placed(self, ids: np.ndarray) -> "Term":
        """The term with the pair ids (R, K, K) of its lists' rows in the pattern."""
        return self

    def loaded(self) -> bool:
        """Whether the load scale drives a nonzero load of this term (at build values)."""
        return False


class TermSpec:
    """What a user passes to ``Model(..., terms=[...])``: a description (NumPy, parameters,
    a ``name`` that keys its parameters) whose ``build(ctx: Context)`` returns the Term."""

    name: str

    def build(self, ctx: Context) -> Term:
        raise NotImplementedError


def window_plan(n: int, per_item: int, budget: int) -> tuple[int, int]:
    """(windows, size): ``n`` items swept in windows of equal size holding at most ``budget``
    doubles at ``per_item`` each (at least one item a window). The last window is shifted
    back to end at n, so it may cover up to a whole window of items already summed."""
    windows = -(-n // max(1, budget // per_item))
    return windows, -(-n // windows)


def on_pattern(terms, n: int, dim: int) -> tuple:
    """The pair pattern of ``terms`` over n particles (every pair within a row of any term's
    ``lists``) and the terms placed on it: (Pairs, terms, pair_i, pair_j (NumPy, for the
    host-side linear systems)). A term without lists must be linear in d (its Hessian, the
    blocks it does not give, is zero: checked at a random state, so a new term that forgets
    its blocks is refused instead of leaving the tangent short; a term that declares itself
    ``linear`` is taken at its word, sparing every model build the check's eager compiles)."""
    lists = [t.lists() for t in terms]
    rng = np.random.default_rng(0)
    for t, rows in zip(terms, lists):
        if rows is not None and type(t).blocks is Term.blocks:
            raise TypeError(f"term {t.name!r} has lists but no blocks: its tangent would be missing")
        if rows is None and t.linear:
            continue
        d, v = (jnp.asarray(rng.standard_normal((n, dim))) for _ in range(2))
        if rows is None and np.any(np.asarray(jax.jvp(jax.grad(lambda x, t=t: t.energy(x, 1.0)[0]), (d,), (v,))[1])):
            raise TypeError(f"term {t.name!r} has no tangent blocks (lists() is None) but its energy is "
                            "not linear in d: give it lists, placed and blocks")
    pair_i, pair_j, pair_t, ids = pair_pattern([rows for rows in lists if rows is not None], n)
    ids = iter(ids)
    placed = tuple(t if rows is None else t.placed(next(ids)) for t, rows in zip(terms, lists))
    pairs = Pairs(*(jnp.asarray(x, jnp.int32) for x in (pair_i, pair_j, pair_t)))
    return pairs, placed, pair_i, pair_j
