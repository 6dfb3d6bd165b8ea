"""Dead loads and springs.

Natural boundary conditions: dead loads (body force per reference volume, traction h0 per
reference area, eq 3.9) integrated once into a constant nodal force vector. ``Springs``:
zero-length springs that hold material points (elastic supports, penalty paddles).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..discretise.body import Body
from ..discretise.quadrature import Table


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
