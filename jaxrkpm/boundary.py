"""Boundary conditions.

Essential: the thesis' transformation (eqs 3.22-3.31). Particles are split into the
essential set Lambda_b and the rest; the boundary coefficients follow from the free ones
and the prescribed values g so that u^h(X_b) = g exactly:

    d_b = (D^b)^-1 (g - D^nb d_nb),   D^b_ij = Psi_{b_j}(X_{b_i}),  D^nb_ij = Psi_{nb_j}(X_{b_i}).

Natural: dead loads (body force per reference volume, traction h0 per reference area,
eq 3.9) integrated once into a constant nodal force vector.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .geometry import Body
from .integration import Table


@dataclass(frozen=True)
class EssentialSets:
    """Validated, non-overlapping named particle sets, concatenated in ``bnd``."""

    names: tuple
    slices: dict   # name -> slice into bnd
    bnd: np.ndarray   # (Nb,) particle indices
    free: np.ndarray  # (Nf,) particle indices

    @staticmethod
    def build(body: Body, essential: dict) -> "EssentialSets":
        if not isinstance(essential, dict):
            raise ValueError("essential must be a dict: name -> particle indices")
        seen = {}
        parts, slices, start = [], {}, 0
        for name, idx in essential.items():
            if not isinstance(name, str):
                raise ValueError(f"essential set names must be strings, got {name!r}")
            try:
                idx = np.asarray(idx)
            except (TypeError, ValueError):
                raise ValueError(f"essential set {name!r} must be particle indices or a boolean mask") from None
            if idx.dtype == bool:
                if idx.shape != (body.n,):
                    raise ValueError(f"essential set {name!r}: boolean mask must have shape ({body.n},)")
                idx = np.flatnonzero(idx)
            if idx.size == 0:
                raise ValueError(f"essential set {name!r} is empty (check the selection predicate)")
            if not np.issubdtype(idx.dtype, np.integer):
                # astype(int) would truncate 1.7 to 1 and hold the wrong particle
                raise TypeError(f"essential set {name!r} must hold integer particle indices (or a "
                                f"boolean mask), got {idx.dtype} values such as {idx.ravel()[0]!r}; "
                                "use body.select(...) or an int array")
            idx = idx.astype(np.int64).ravel()
            if idx.min() < 0 or idx.max() >= body.n:
                raise ValueError(f"essential set {name!r} has indices outside 0..{body.n - 1}")
            if len(np.unique(idx)) != len(idx):
                raise ValueError(f"essential set {name!r} lists a particle twice")
            for i in idx:
                if int(i) in seen:
                    raise ValueError(f"essential sets {seen[int(i)]!r} and {name!r} overlap "
                                     f"(particle {int(i)} at {body.X[i].tolist()})")
                seen[int(i)] = name
            parts.append(idx)
            slices[name] = slice(start, start + len(idx))
            start += len(idx)
        bnd = np.concatenate(parts) if parts else np.zeros(0, np.int64)
        free = np.setdiff1d(np.arange(body.n), bnd)
        if len(free) == 0:
            raise ValueError("every particle is in an essential set: nothing left to solve for")
        return EssentialSets(tuple(essential), slices, bnd, free)


@dataclass(frozen=True)
class Transformation:
    """Arrays of the boundary transformation, for use inside jit.

    Dbinv (Nb, Nb): (D^b)^-1; nb_idx (Nb, K), nb_psi (Nb, K): Psi_J(X_b) over the
    neighbours of each boundary particle, zeroed where J is itself a boundary particle
    (that part is D^b); rows (Nb, K), rows_psi: the full rows of [D^nb D^b] (the constraint
    u^h(X_b) = g used by the sparse saddle-point solver)."""

    Dbinv: np.ndarray
    nb_idx: np.ndarray
    nb_psi: np.ndarray
    rows_psi: np.ndarray

    @staticmethod
    def build(body: Body, sets: EssentialSets, a: float, support_factor=None) -> "Transformation":
        sf = body.shape_functions(body.X[sets.bnd], a, gradients=False,
                                  support_factor=support_factor)
        pos = -np.ones(body.n, np.int64)
        pos[sets.bnd] = np.arange(len(sets.bnd))
        Nb = len(sets.bnd)
        Db = np.zeros((Nb, Nb))
        is_b = pos[sf.idx] >= 0
        rows = np.repeat(np.arange(Nb), sf.idx.shape[1]).reshape(sf.idx.shape)
        np.add.at(Db, (rows[is_b], pos[sf.idx][is_b]), sf.psi[is_b])
        cond = np.linalg.cond(Db)
        if not np.isfinite(cond) or cond > 1e12:
            raise ValueError(f"the boundary matrix D^b (eq 3.30) is singular (condition {cond:.3g}); "
                             "essential particles too close together for the support")
        nb_psi = np.where(is_b, 0.0, sf.psi)
        return Transformation(np.linalg.inv(Db), sf.idx, nb_psi, sf.psi)

    def coupling(self, sets: EssentialSets, n: int) -> np.ndarray:
        """A = (D^b)^-1 D^nb as a dense (Nb, Nf) matrix: d_b = Dbinv g - A d_nb."""
        Dnb = np.zeros((len(sets.bnd), n))
        rows = np.repeat(np.arange(len(sets.bnd)), self.nb_idx.shape[1]).reshape(self.nb_idx.shape)
        np.add.at(Dnb, (rows, self.nb_idx), self.nb_psi)
        return self.Dbinv @ Dnb[:, sets.free]


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
