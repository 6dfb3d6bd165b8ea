"""A follower pressure on a part of the boundary, as a conservative term.

The load of an inflated cavity or a pressed membrane: a pressure p acts on the deformed
boundary, along its normal, t = -p n (n the body's outward normal: p > 0 pushes into the
body), so the load turns and grows with the surface it acts on. Its potential is

    Pi = -load p (V - V_0),    V = -(1/d) int x . n da  over the deformed loaded boundary,

V the volume (2D: area) that the loaded boundary encloses on its outer side (a cavity's
volume; for the whole outer surface minus the body's). V comes from the deformed facets by the
divergence theorem: each facet of the loaded part is cut into simplices t (segments;
triangles, a box face's quad into four around its centre) whose corners x = X + u(X) move with
the RK displacement field, and V = -sum_t det[x_t1 - c, ..., x_td - c] / d! (c the part's
centroid; the simplices ordered along the body's outward normal). So, as the derivatives of one
function of the corners:

- the load on the body, -dPi/dx, is -load p n a on each deformed simplex, shared equally by its
  corners (half of a segment's to each end, a third of a triangle's to each corner), and
  carried to the particles by their shape functions at the corners;
- the tangent is the Hessian of -load p V: symmetric, from each simplex's d x d corner
  Hessian (autodiff, cheap) spread over the particle pairs of its corners' neighbours.

Exact where the loaded part is closed (a cavity, the whole surface), or where its rim is held:
the rim's corners at essential particles, where u = g exactly (eq 3.22), so they do not move
with the unknowns. A follower pressure on an open part with a free rim has no potential (its
work depends on the path, and V's derivative at the rim depends on c): such a part is refused.
At a held rim, where the pressure's load is not V's derivative, the reactions take the rim's
share of p n a itself (``reaction_correction``), so the supports carry the whole load.

``Model(..., terms=[Pressure(where, p)])`` adds one; ``p`` is a parameter of the solve
(``solve(params={"pressure": p})``, differentiable) and the load scale ``loads`` scales it.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from math import factorial
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from scipy.spatial import cKDTree

from .materials import det
from .term import Context, Pairs, Term, TermSpec, boolean_mask, static, term, window_plan


def _volume_change(Y, U):
    """det[Y + U] - det[Y] for corner rows Y, U (..., d, d), as sum_k det[Y_<k, U_k, (Y + U)_>k]
    (the determinant is linear in each row): no cancellation of the reference volume."""
    dim = Y.shape[-1]
    y = Y + U
    total = 0.0
    for k in range(dim):
        rows = [Y[..., i, :] for i in range(k)] + [U[..., k, :]] + [y[..., i, :] for i in range(k + 1, dim)]
        total = total + det(jnp.stack(rows, -2))
    return total


def _area_normals(c):
    """n a of each simplex (T, d) from its corners (T, d, d): (e_y, -e_x) for a segment e, half
    the cross product of a triangle's edges."""
    if c.shape[-1] == 2:
        e = c[:, 1] - c[:, 0]
        return jnp.stack([e[:, 1], -e[:, 0]], 1)
    return 0.5 * jnp.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0])


@term
class PressureTerm(Term):
    """Pi = load p sum_t (det[y_t] - det[Y_t]) / d! over the simplices t of the loaded boundary
    (see the module docstring).

    Y (S, d)            the surface points (facet corners, box-face centres) relative to the
                        part's centroid, reference configuration
    idx, psi (S, Ks)    their neighbours and shape functions
    simplices (T, d)    corners of each simplex, ordered so that det[Y_t] / d! is the signed
                        volume with the body's outward normal
    rows (T, Kt)        the particles whose shape functions reach a simplex's corners
    spsi (T, d, Kt)     each corner's shape functions laid out on its simplex's row
    p                   () the pressure: a parameter
    unit                () |nodal load| of p = 1 on the reference boundary (the force scale)
    pair_id (T, Kt, Kt)  the pattern's index of the pair (rows[t, k], rows[t, m])
    rim (S,)            1 at the surface points on the rim of an open part (None: closed)
    block_budget        doubles of (window, Kt, Kt, d, d) local blocks held at once
    """

    Y: jax.Array
    idx: jax.Array
    psi: jax.Array
    simplices: jax.Array
    rows: jax.Array
    spsi: jax.Array
    p: jax.Array
    unit: jax.Array
    pair_id: jax.Array = None
    rim: jax.Array = None
    name: str = static("pressure")
    block_budget: int = static(2**18)

    def _displacements(self, d):
        """u at the surface points (S, d)."""
        return jnp.einsum("sk,ski->si", self.psi, d[self.idx])

    def _corners(self, d):
        """Reference and displacement of every simplex's corners: (T, d, d) each."""
        return self.Y[self.simplices], self._displacements(d)[self.simplices]

    def _energy_at(self, u, load):
        """The energy from the surface points' displacements u (S, d)."""
        Y = self.Y[self.simplices]
        return load * self.p / factorial(Y.shape[-1]) * jnp.sum(_volume_change(Y, u[self.simplices]))

    def energy(self, d, load, aux=None):
        return self._energy_at(self._displacements(d), load), None

    def reaction_correction(self, d, load):
        """At the rim of an open part: the rim's share of the pressure load minus V's derivative
        there (see the module docstring), as (N, d) on the particles; None for a closed part."""
        if self.rim is None:
            return None
        u = self._displacements(d)
        dim = u.shape[-1]
        share = load * self.p / dim * _area_normals(self.Y[self.simplices] + u[self.simplices])   # -load on each corner
        own = jnp.zeros_like(u).at[self.simplices.reshape(-1)].add(jnp.repeat(share, dim, axis=0))
        wrong = jax.grad(self._energy_at)(u, load)
        gap = self.rim[:, None] * (own - wrong)
        return jnp.zeros_like(d).at[self.idx].add(self.psi[..., None] * gap[:, None, :])

    def blocks(self, d, load, pairs: Pairs):
        Y, U = self._corners(d)
        dim = Y.shape[-1]
        H = jax.vmap(jax.hessian(_volume_change, argnums=1))(Y, U) * (load * self.p / factorial(dim))
        T, _, Kt = self.spsi.shape

        def window_sum(acc, H, spsi, pid):
            B = jnp.einsum("tak,taibj,tbm->tkmij", spsi, H, spsi)      # (T, Kt, Kt, d, d)
            return acc + jax.ops.segment_sum(B.reshape(-1, dim, dim), pid.reshape(-1), num_segments=pairs.count)

        zero = jnp.zeros((pairs.count, dim, dim), d.dtype)
        windows, size = window_plan(T, Kt * Kt * dim * dim, self.block_budget)
        if windows == 1:
            return window_sum(zero, H, self.spsi, self.pair_id)

        def body(i, acc):
            # the last window is shifted back to end at T; its simplices already summed add zero
            start = jnp.minimum(i * size, T - size)
            seen = start + jnp.arange(size) < i * size

            def window(x):
                return jax.lax.dynamic_slice_in_dim(x, start, size)

            Hw = jnp.where(seen[:, None, None, None, None], 0.0, window(H))
            return window_sum(acc, Hw, window(self.spsi), window(self.pair_id))

        return jax.lax.fori_loop(0, windows, body, zero)

    def force_scale(self, aux):
        """|p| x |the nodal load of a unit pressure on the reference boundary|: like the dead
        loads' |f|, at load scale 1."""
        return jnp.abs(self.p) * self.unit

    # -------------------------------------------------------------- parameters
    @property
    def params(self) -> dict:
        return {"p": self.p}

    def with_params(self, params: dict) -> "PressureTerm":
        return replace(self, p=params["p"])

    def check_params(self, value) -> dict:
        try:
            p = jnp.asarray(value, jnp.float64)
        except (TypeError, ValueError):
            raise ValueError(f"params[{self.name!r}] must be a pressure (a number), got {value!r}") from None
        if p.shape != ():
            raise ValueError(f"params[{self.name!r}] must be a pressure (a number), got shape {p.shape}")
        if not isinstance(p, jax.core.Tracer) and not np.isfinite(float(p)):
            raise ValueError(f"params[{self.name!r}] is not finite: {float(p)}")
        return {"p": p}

    # ----------------------------------------------------------- host side
    def lists(self) -> np.ndarray:
        return np.asarray(self.rows)

    def placed(self, ids) -> "PressureTerm":
        return replace(self, pair_id=jnp.asarray(ids, jnp.int32))

    def loaded(self) -> bool:
        return isinstance(self.p, jax.core.Tracer) or float(self.p) != 0.0


@dataclass(frozen=True)
class Pressure(TermSpec):
    """A follower pressure ``p`` on the boundary facets whose centres satisfy ``where``
    (X (M, d) -> (M,) bool), e.g. a cavity's wall: ``Pressure(lambda X: np.hypot(*X.T) < 1.5,
    p=0.1)``. p > 0 pushes into the body (a gas in a cavity inflates it); it is force per unit
    deformed area (2D: per unit length and thickness). ``name`` keys it in
    ``Model.solve(params={name: p})``. The loaded part must be closed, or its rim held by
    essential sets (see jaxrkpm.mechanics.pressure)."""

    where: Callable
    p: float = 1.0
    name: str = "pressure"

    def __post_init__(self):
        if not callable(self.where):
            raise ValueError(f"Pressure.where must be a predicate X (M, d) -> (M,) bool, got {self.where!r}")
        if isinstance(self.p, (bool, np.bool_)) or not isinstance(self.p, (int, float, np.integer, np.floating)) \
                or not np.isfinite(self.p):
            raise ValueError(f"Pressure.p must be a finite number, got {self.p!r}")
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"Pressure.name must be a non-empty string, got {self.name!r}")

    def build(self, ctx: Context) -> PressureTerm:
        body = ctx.body
        facets, normals = body.boundary_facets()
        mask = boolean_mask(self.where(facets.mean(1)), f"pressure {self.name!r}: where")
        if mask.shape != (len(facets),):
            raise ValueError(f"pressure {self.name!r}: where must return ({len(facets)},) booleans "
                             f"(one per boundary facet centre), got shape {mask.shape}")
        if not mask.any():
            raise ValueError(f"pressure {self.name!r}: where selects no boundary facet")
        facets, normals = facets[mask], normals[mask]
        points, corners = _corner_points(facets, 1e-9 * body.spacing)
        rim = _check_rim(corners, points, body.X[ctx.sets.bnd], 1e-9 * body.spacing, self.name)
        centroid = points.mean(0)
        points, simplices = _simplices(points, corners, normals)
        sf = body.shape_functions(points, ctx.a, gradients=False, support_factor=ctx.support)
        rows, spsi = _simplex_rows(sf.idx, sf.psi, simplices)
        unit = np.linalg.norm(_unit_load(points, simplices, sf.idx, sf.psi, body.n))
        return PressureTerm(Y=jnp.asarray(points - centroid), idx=jnp.asarray(sf.idx, jnp.int32),
                            psi=jnp.asarray(sf.psi),
                            simplices=jnp.asarray(simplices, jnp.int32), rows=jnp.asarray(rows, jnp.int32),
                            spsi=jnp.asarray(spsi), p=jnp.asarray(float(self.p)), unit=jnp.asarray(unit),
                            rim=None if len(rim) == 0 else jnp.zeros(len(points)).at[rim].set(1.0), name=self.name)


def _corner_points(facets, tol):
    """The distinct facet corners (V, d) and each facet's corners as indices into them (M, nv)
    (corners closer than ``tol`` are one)."""
    M, nv, dim = facets.shape
    flat = facets.reshape(-1, dim)
    near = cKDTree(flat).query_ball_point(flat, tol)
    rep = np.array([min(n) for n in near])
    first, inverse = np.unique(rep, return_inverse=True)
    return flat[first], inverse.reshape(M, nv)


def _check_rim(corners, points, held, tol, name):
    """The rim's corners (indices into ``points``) of the loaded part, checked: the rim is where
    a facet edge (2D: a corner) belongs to one loaded facet only; each rim corner must sit on
    an essential particle (an open part with a free rim is refused)."""
    nv = corners.shape[1]
    if nv == 2:
        ends = corners.reshape(-1)
    else:
        edges = np.sort(np.stack([corners, np.roll(corners, -1, axis=1)], -1).reshape(-1, 2), axis=1)
        uniq, count = np.unique(edges, axis=0, return_counts=True)
        ends = uniq[count == 1].reshape(-1)
        if np.any(count > 2):
            raise ValueError(f"pressure {name!r}: the loaded facets are not a manifold surface "
                             "(an edge shared by more than two of them)")
    ids, count = np.unique(ends, return_counts=True)
    rim = ids[count == 1] if nv == 2 else ids
    if nv == 2 and np.any(count > 2):
        raise ValueError(f"pressure {name!r}: the loaded facets are not a manifold curve "
                         "(a corner shared by more than two of them)")
    if len(rim) == 0:
        return rim
    dist = cKDTree(held).query(points[rim])[0] if len(held) else np.full(len(rim), np.inf)
    free = rim[dist > tol]
    if len(free):
        raise ValueError(f"pressure {name!r}: the loaded boundary part is open and {len(free)} corner(s) of "
                         f"its rim are not held by an essential set (e.g. at {points[free[0]].tolist()}). "
                         "A follower pressure on an open surface with a free rim has no potential (its "
                         "work depends on the path); load a closed part of the boundary (a cavity, the "
                         "whole surface), hold the rim with an essential set, or use a dead traction "
                         "(Model(tractions=...))")
    return rim


def _simplices(points, corners, normals):
    """(surface points, simplices (T, d)) with every simplex ordered so that its normal is the
    facet's outward one; a quad becomes four triangles around its centre (a new point)."""
    M, nv = corners.shape
    dim = points.shape[1]
    if nv == 4:
        centres = points[corners].mean(1)
        c = len(points) + np.arange(M)
        points = np.concatenate([points, centres])
        tris = np.stack([np.stack([corners[:, k], corners[:, (k + 1) % 4], c], 1) for k in range(4)], 1)
        corners, normals = tris.reshape(-1, 3), np.repeat(normals, 4, axis=0)
    simplices = corners.copy()
    P = points[simplices]
    if dim == 2:
        t = P[:, 1] - P[:, 0]
        flip = t[:, 1] * normals[:, 0] - t[:, 0] * normals[:, 1] < 0      # (t_y, -t_x) . n
        simplices[flip] = simplices[flip][:, ::-1]
    else:
        flip = np.einsum("md,md->m", np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]), normals) < 0
        simplices[flip] = simplices[flip][:, [0, 2, 1]]
    return points, simplices


def _unit_load(points, simplices, idx, psi, n):
    """The nodal load (n, d) of a unit pressure on the reference boundary (NumPy, at build):
    each simplex's n a / d on each of its corners, carried to the particles by the shape
    functions there (the force scale's unit; its sign does not matter)."""
    c = points[simplices]
    dim = c.shape[-1]
    if dim == 2:
        e = c[:, 1] - c[:, 0]
        na = np.stack([e[:, 1], -e[:, 0]], 1)
    else:
        na = 0.5 * np.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0])
    f = np.zeros((n, dim))
    for a in range(dim):
        s = simplices[:, a]
        np.add.at(f, idx[s], psi[s][..., None] * (na / dim)[:, None, :])
    return f


def _simplex_rows(idx, psi, simplices):
    """Each simplex's particles (T, Kt): the union of its corners' neighbour lists (padded by
    repeating the last), and each corner's shape functions laid out on that row (T, d, Kt)."""
    T, dim = simplices.shape
    lists = [np.unique(idx[s]) for s in simplices]
    Kt = max(len(r) for r in lists)
    rows = np.stack([np.pad(r, (0, Kt - len(r)), mode="edge") for r in lists])
    spsi = np.zeros((T, dim, Kt))
    for t, (s, r) in enumerate(zip(simplices, lists)):
        for a in range(dim):
            np.add.at(spsi[t, a], np.searchsorted(r, idx[s[a]]), psi[s[a]])
    return rows, spsi
