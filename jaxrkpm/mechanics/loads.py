"""Dead loads and springs, as terms.

Natural boundary conditions: dead loads (body force per reference volume, traction h0 per
reference area, eq 3.9) integrated once into a constant nodal force vector, the ``DeadLoad``
term. ``Springs``: zero-length springs that hold material points (elastic supports, penalty
paddles), the ``SpringTerm``.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import jax
import jax.numpy as jnp
import numpy as np

from ..discretise.body import Body
from ..discretise.quadrature import Table
from ..discretise.rk import psi_jax
from .term import Context, Pairs, Term, static, term


def _evaluate_load(load, points: np.ndarray, dim: int, what: str) -> np.ndarray:
    if callable(load):
        v = np.asarray(load(points), float)
    else:
        v = np.broadcast_to(np.asarray(load, float), (len(points), dim))
    if v.shape != (len(points), dim):
        raise ValueError(f"{what} must give shape ({len(points)}, {dim}), got {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{what} has non-finite values")
    return v


def nodal_forces(body: Body, volume: Table, surface: Table | None,
                 body_force=None, tractions=()) -> np.ndarray:
    """Constant (N, d) nodal force vector f_I = int Psi_I b0 dV + int_Gh Psi_I h0 dA.

    ``body_force``: (d,) or callable X (Q, d) -> (Q, d), per unit reference volume.
    ``tractions``: sequence of (predicate, h0); predicate X (B, d) -> (B,) bool picks the
    boundary part, h0 is (d,) or callable X -> (B, d), per unit reference area."""
    d = body.dim
    f = np.zeros((body.n, d))
    if body_force is not None:
        b = _evaluate_load(body_force, volume.points, d, "body_force")
        np.add.at(f, volume.idx, volume.psi[..., None] * (volume.weights[:, None] * b)[:, None, :])
    for k, item in enumerate(tractions):
        try:
            predicate, h0 = item
        except (TypeError, ValueError):
            raise ValueError(f"traction {k} must be a (predicate, h0) pair") from None
        mask = np.asarray(predicate(surface.points), bool)
        if mask.shape != (len(surface.points),):
            raise ValueError(f"traction {k}: predicate must return ({len(surface.points)},) booleans")
        if not mask.any():
            raise ValueError(f"traction {k}: the predicate selects no boundary point")
        s = surface.subset(mask)
        h = _evaluate_load(h0, s.points, d, f"traction {k}")
        np.add.at(f, s.idx, s.psi[..., None] * (s.weights[:, None] * h)[:, None, :])
    return f


@dataclass(frozen=True)
class Springs:
    """Zero-length springs holding material points X_s to their reference positions: the
    energy 1/2 sum_s k_s |u(X_s)|^2 (an elastic support, or a penalty paddle).

    points     (S, d) reference positions
    stiffness  scalar or (S,) spring constants k_s >= 0 (force per displacement)
    region     particle indices that the points may reach when moved later
               (``Model.springs_at``); default: the particles whose windows cover them now

    The points and stiffnesses are parameters of the solve (``params={"springs": ...}``),
    so a solution is differentiable with respect to where the springs hold the body."""

    points: np.ndarray
    stiffness: object = 1.0
    region: object = None

    def stiffnesses(self) -> np.ndarray:
        P = np.atleast_2d(np.asarray(self.points, float))
        k = np.broadcast_to(np.asarray(self.stiffness, float), (len(P),)).copy()
        if not np.all(np.isfinite(k)) or np.any(k < 0):
            raise ValueError(f"spring stiffness must be finite and >= 0, got {self.stiffness}")
        return k


@term
class DeadLoad(Term):
    """The dead loads' potential -load f . d: f (N, d) the nodal force vector at load scale 1
    (``nodal_forces``; replaced by ``Problem.with_load_pattern``)."""

    f: jax.Array
    name: str = static("dead_load")
    linear = True

    def energy(self, d, load, aux=None):
        return -(load * jnp.sum(self.f * d)), None

    def force_scale(self, aux):
        """|f|: the dead loads at load scale 1."""
        return jnp.linalg.norm(self.f)

    def loaded(self) -> bool:
        return bool(np.any(np.asarray(self.f)))


def dead_load(ctx: Context, body_force=None, tractions=()) -> DeadLoad:
    """The ``DeadLoad`` of a body force and tractions (see ``nodal_forces``)."""
    rule = ctx.surface if ctx.balanced is None else ctx.balanced
    return DeadLoad(jnp.asarray(nodal_forces(ctx.body, ctx.volume, rule, body_force, tractions)))


@term
class SpringTerm(Term):
    """Zero-length springs: 1/2 sum_s k_s |u(X_s)|^2 with u(X_s) = sum_K Psi_K(X_s) d_K.

    idx (S, Ks)         the particles whose shape functions may reach each spring point
    psi (S, Ks), k (S,)  the shape functions at the spring points and the stiffnesses: the
                        parameters (the points X_s enter only through psi, so they may move,
                        ``Model.springs_at``)
    pair_id (S, Ks, Ks)  the pattern's index of the pair (idx[s, k], idx[s, m])

    They add no share of their own to the force scale: the spring forces balance the
    stresses they cause, which the strain energy's share measures."""

    idx: jax.Array
    psi: jax.Array
    k: jax.Array
    pair_id: jax.Array = None
    name: str = static("springs")

    def energy(self, d, load, aux=None):
        u = jnp.einsum("sk,ski->si", self.psi, d[self.idx])
        return 0.5 * jnp.sum(self.k[:, None] * u * u), None

    def blocks(self, d, load, pairs: Pairs):
        """k_s Psi_K(X_s) Psi_M(X_s) I as (P, d, d) pair blocks."""
        kk = jnp.einsum("s,sk,sm->skm", self.k, self.psi, self.psi)
        scal = jax.ops.segment_sum(kk.ravel(), self.pair_id.ravel(), num_segments=pairs.count)
        return scal[:, None, None] * jnp.eye(d.shape[1])

    @property
    def params(self) -> dict:
        return {"psi": self.psi, "k": self.k}

    def with_params(self, params: dict) -> "SpringTerm":
        return replace(self, psi=params["psi"], k=params["k"])

    def check_params(self, value) -> dict:
        ref = self.params
        if not (isinstance(value, dict) and set(value) == {"psi", "k"}
                and all(jnp.shape(value[n]) == jnp.shape(ref[n]) for n in ref)):
            raise ValueError('params["springs"] must come from model.springs_at(points, stiffness)')
        return value

    def lists(self) -> np.ndarray:
        return np.asarray(self.idx)

    def placed(self, ids) -> "SpringTerm":
        return replace(self, pair_id=jnp.asarray(ids, jnp.int32))


def spring_psi(body: Body, a: float, points, idx):
    """Psi (S, Ks) of the particles ``idx`` (S, Ks) at ``points`` (S, d), in JAX (so a solve
    is differentiable in where the springs hold the body)."""
    return psi_jax(body.X, body.volumes, idx, jnp.asarray(points, jnp.float64), a)


def spring_term(ctx: Context, springs: Springs | None) -> SpringTerm:
    """The ``SpringTerm`` of ``springs`` (None: no springs, an empty term). Every point's
    candidate list is the whole region (a moved point must find its neighbours there)."""
    if springs is None:
        return SpringTerm(jnp.zeros((0, 1), jnp.int32), jnp.zeros((0, 1)), jnp.zeros((0,)))
    if not isinstance(springs, Springs):
        raise ValueError(f"springs must be a jaxrkpm Springs, got {type(springs).__name__}")
    body = ctx.body
    P = body.check_inside(springs.points, "spring point")
    k = springs.stiffnesses()
    if springs.region is None:
        nb = body.neighbours(P, ctx.a)
        region = np.unique(nb.idx[nb.mask]).astype(np.int64)
    else:
        region = np.unique(np.asarray(springs.region, np.int64))
        if region.size == 0 or region.min() < 0 or region.max() >= body.n:
            raise ValueError(f"spring region must be particle indices in 0..{body.n - 1}")
    idx = np.tile(region, (len(P), 1))
    return SpringTerm(jnp.asarray(idx, jnp.int32), spring_psi(body, ctx.a, P, idx), jnp.asarray(k))
