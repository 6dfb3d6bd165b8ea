"""Reproducing-kernel shape functions (thesis eqs 3.16-3.21), NumPy, build time only.

Psi_I(X) = H(0)^T M(X)^-1 H((X - X_I)/a) Phi_a(X - X_I) V_I with a linear basis H and the
cubic-spline tensor-product window of eq 3.21. Values and gradients are evaluated over
padded neighbour lists (a KD-tree query in the max-norm, since the window is a box).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree



def kernel(x: np.ndarray, xp=np) -> np.ndarray:
    """Cubic spline of eq 3.21 (support |x| <= 1); ``xp``: numpy or jax.numpy."""
    r = xp.abs(x)
    return xp.where(r <= 0.5, 2 / 3 - 4 * r**2 + 4 * r**3,
                    xp.where(r < 1.0, 4 / 3 - 4 * r + 4 * r**2 - 4 / 3 * r**3, 0.0))


def kernel_derivative(x: np.ndarray) -> np.ndarray:
    r = np.abs(x)
    dr = np.where(r <= 0.5, -8 * r + 12 * r**2, np.where(r <= 1.0, -4 + 8 * r - 4 * r**2, 0.0))
    return dr * np.sign(x)


@dataclass(frozen=True)
class Neighbours:
    """Padded neighbour lists: idx (P, K) particle indices (padding repeats the point's
    last neighbour, so a padded entry pairs no particles that are not neighbours already:
    padding with particle 0 made every particle a tangent pair of particle 0, a dense row
    and column in the sparse pattern, and linked distant essential sets), mask (P, K) true
    where the entry is a real neighbour."""

    idx: np.ndarray
    mask: np.ndarray


def neighbours(tree: cKDTree, points: np.ndarray, radius: float,
               capacity: int | None = None, groups: np.ndarray | None = None) -> Neighbours:
    """Particles whose (box-shaped) window covers each point. ``capacity`` fixes K; a point
    with more neighbours than that raises instead of being silently truncated. ``groups``
    (P,) ints: points of one group (the Gauss points of one mesh cell) get the union of
    their lists, so they share one neighbour list (extra entries have zero kernel weight)."""
    lists = tree.query_ball_point(points, r=radius * (1 - 1e-12), p=np.inf)
    if groups is not None:
        lists = _group_union(lists, np.asarray(groups))
    counts = np.array([len(l) for l in lists])
    K = int(counts.max()) if capacity is None else int(capacity)
    if counts.max() > K:
        i = int(np.argmax(counts))
        raise ValueError(f"neighbour capacity {K} overflows at point {i} {points[i].tolist()} "
                         f"which has {counts[i]} neighbours; raise the capacity")
    idx = np.zeros((len(points), K), dtype=np.int32)
    mask = np.zeros((len(points), K), dtype=bool)
    for p, l in enumerate(lists):
        l = sorted(l)
        idx[p, :len(l)] = l
        idx[p, len(l):] = l[-1] if len(l) else 0
        mask[p, :len(l)] = True
    return Neighbours(idx, mask)


def _group_union(lists, groups):
    """Per point, the union of the lists of all points in its group."""
    counts = np.array([len(l) for l in lists])
    group = np.repeat(groups, counts)
    part = np.fromiter((i for l in lists for i in l), np.int64, counts.sum())
    n = int(part.max()) + 1 if len(part) else 1
    keys = np.unique(group.astype(np.int64) * n + part)
    g_of, members = keys // n, keys % n
    starts = np.searchsorted(g_of, groups)
    ends = np.searchsorted(g_of, groups, side="right")
    return [members[a:b] for a, b in zip(starts, ends)]


@dataclass(frozen=True)
class ShapeFunctions:
    """Shape function values and gradients at P points over K padded neighbours.

    idx (P, K) int, psi (P, K), dpsi (P, K, d); padded entries have psi = dpsi = 0."""

    idx: np.ndarray
    psi: np.ndarray
    dpsi: np.ndarray


def shape_functions(X: np.ndarray, volumes: np.ndarray, tree: cKDTree, points: np.ndarray,
                    a: float, capacity: int | None = None, gradients: bool = True,
                    support_factor: float | None = None,
                    groups: np.ndarray | None = None, chunk: int = 8192) -> ShapeFunctions:
    """RK shape functions of the particles (X, volumes) with dilation ``a`` at ``points``
    (``groups``: points sharing one neighbour list, see ``neighbours``), ``chunk`` points at
    a time (it bounds the (chunk, K, d, d+1) temporaries)."""
    points = np.atleast_2d(np.asarray(points, float))
    nb = neighbours(tree, points, a, capacity, groups)
    P, K = nb.idx.shape
    d = X.shape[1]
    psi = np.zeros((P, K))
    dpsi = np.zeros((P, K, d))
    for s in range(0, P, chunk):
        sl = slice(s, s + chunk)
        out = _evaluate(X, volumes, points[sl], nb.idx[sl], nb.mask[sl], a, gradients,
                        support_factor, s)
        psi[sl] = out[0]
        if gradients:
            dpsi[sl] = out[1]
    return ShapeFunctions(nb.idx, psi, dpsi)


def _evaluate(X, volumes, pts, idx, mask, a, gradients, support_factor, offset):
    d = X.shape[1]
    R = (pts[:, None, :] - X[idx]) / a                       # (P, K, d)
    k1 = kernel(R)                                             # (P, K, d)
    phi = np.prod(k1, axis=-1) / a**d * volumes[idx] * mask   # Phi_a * V_I, (P, K)
    H = np.concatenate([np.ones(R.shape[:-1] + (1,)), R], axis=-1)  # H((X - X_I)/a), eq 3.19
    M = np.einsum("pk,pka,pkb->pab", phi, H, H)
    _check_moment_matrix(M, pts, mask, a, support_factor, offset)
    Minv = np.linalg.inv(M)
    b = Minv[:, :, 0]                                          # M^-1 H(0), (P, d+1)
    bH = np.einsum("pa,pka->pk", b, H)
    psi = bH * phi
    if not gradients:
        return (psi,)
    # d/dX_j of each factor (R depends on X with dR/dX = 1/a)
    dk1 = kernel_derivative(R) / a                             # (P, K, d)
    dphi = np.empty(R.shape)
    for j in range(d):
        others = np.prod(np.delete(k1, j, axis=-1), axis=-1)
        dphi[..., j] = dk1[..., j] * others
    dphi *= (volumes[idx] * mask / a**d)[..., None]            # (P, K, d)
    dH = np.zeros(R.shape[:-1] + (d, d + 1))                   # dH/dX_j = e_j / a
    for j in range(d):
        dH[..., j, j + 1] = 1.0 / a
    dM = (np.einsum("pk,pkja,pkb->pjab", phi, dH, H)
          + np.einsum("pk,pka,pkjb->pjab", phi, H, dH)
          + np.einsum("pkj,pka,pkb->pjab", dphi, H, H))        # (P, d, d+1, d+1)
    db = -np.einsum("pab,pjbc,pc->pja", Minv, dM, b)           # (P, d, d+1)
    dpsi = (np.einsum("pja,pka->pkj", db, H) * phi[..., None]
            + np.einsum("pa,pkja->pkj", b, dH) * phi[..., None]
            + bH[..., None] * dphi)
    return psi, dpsi


def _check_moment_matrix(M, pts, mask, a, support_factor, offset):
    n_real = mask.sum(1)
    d = pts.shape[1]
    with np.errstate(all="ignore"):
        cond = np.linalg.cond(M)
    bad = (n_real < d + 1) | ~np.isfinite(cond) | (cond > 1e12)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        hint = (f"support factor {support_factor:g}" if support_factor else f"dilation a={a:g}")
        raise ValueError(
            f"moment matrix is singular at point {offset + i} {pts[i].tolist()} "
            f"({int(n_real[i])} particles cover it, condition number {cond[i]:.3g}): "
            f"the {hint} is too small for a linear basis (or the point is outside the body); "
            f"use a larger support (e.g. 2.01 x spacing or more)")


def psi_jax(X, volumes, idx, points, a):
    """The same shape function values in JAX, differentiable in ``points`` (P, d), over a
    fixed candidate list ``idx`` (P, K) of real particles (particles outside a point's window
    get zero): for points that move inside a differentiated computation (spring supports).
    Everything else evaluates shape functions once, with NumPy, at build time."""
    import jax.numpy as jnp

    X, volumes, idx = jnp.asarray(X), jnp.asarray(volumes), jnp.asarray(idx)
    d = X.shape[1]
    R = (points[:, None, :] - X[idx]) / a
    phi = jnp.prod(kernel(R, jnp), axis=-1) / a**d * volumes[idx]
    H = jnp.concatenate([jnp.ones(R.shape[:-1] + (1,)), R], axis=-1)
    M = jnp.einsum("pk,pka,pkb->pab", phi, H, H)
    b = jnp.linalg.solve(M, jnp.broadcast_to(jnp.eye(d + 1)[0], M.shape[:-1])[..., None])[..., 0]
    return jnp.einsum("pa,pka->pk", b, H) * phi
