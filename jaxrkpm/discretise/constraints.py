"""The essential boundary conditions as a transformation (thesis eqs 3.22-3.31), in one place.

Particles are split into the essential set Lambda_b and the rest; the boundary coefficients
follow from the free ones and the prescribed values g so that u^h(X_b) = g exactly:

    d_b = (D^b)^-1 (g - D^nb d_nb),   D^b_ij = Psi_{b_j}(X_{b_i}),  D^nb_ij = Psi_{nb_j}(X_{b_i}).

A ``Roller`` set holds only some components of its particles' displacement (a symmetry
plane, a roller support): the same transformation written per held direction n,
n . u^h(X_b) = n . g_b, with the coefficients of held particles in a frame whose first axes
span their held directions (``mechanics.constraint.HeldComponents``).

``EssentialSets`` names and validates the sets; ``Transformation`` holds (D^b)^-1 and the
rows of D^nb; ``EliminationLayout`` lays out T = [I; -A], A = (D^b)^-1 D^nb, by independent
components for the dense tangent; ``HostElimination`` applies T and T^T on the host (sparse
LU of the constraint matrix) for the sparse and Krylov solvers.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.sparse.csgraph import connected_components

from .body import Body


@dataclass(frozen=True)
class Roller:
    """An essential set that holds only some displacement components of its particles
    (``Model(essential={name: Roller(...)})``): a symmetry plane or a roller support.

    particles   particle indices or a boolean mask (as a plain essential set)
    components  the held axes: an int or a sequence of them (e.g. 0: u_x held, the others free)
    normal      instead of ``components``: the held direction(s), (d,) or (k, d), for a plane
                not aligned with the axes (its normal component is held)

    The prescribed value of the set is a displacement as for any set; only its component along
    the held directions acts (zero: a symmetry plane). A particle may lie in several rollers
    (the edge of two symmetry planes) if their held directions are independent."""

    particles: object
    components: object = None
    normal: object = None

    def directions(self, dim: int, name: str) -> np.ndarray:
        """The held unit directions (k, dim), orthonormal."""
        if (self.components is None) == (self.normal is None):
            raise ValueError(f"Roller {name!r}: give either components=... (held axes) or normal=... "
                             "(held direction), not both or neither")
        if self.components is not None:
            return self._axes(dim, name)
        return self._normals(dim, name)

    def _axes(self, dim: int, name: str) -> np.ndarray:
        """The unit vectors of the held ``components``."""
        comps = np.atleast_1d(np.asarray(self.components))
        if comps.size == 0 or comps.ndim != 1 or not np.issubdtype(comps.dtype, np.integer):
            raise ValueError(f"Roller {name!r}: components must be axis indices in 0..{dim - 1}, "
                             f"got {self.components!r}")
        if comps.min() < 0 or comps.max() >= dim or len(np.unique(comps)) != len(comps):
            raise ValueError(f"Roller {name!r}: components must be distinct axis indices in "
                             f"0..{dim - 1} (a {dim}D body), got {self.components!r}")
        return np.eye(dim)[np.sort(comps)]

    def _normals(self, dim: int, name: str) -> np.ndarray:
        """Orthonormal rows spanning the held ``normal`` directions, each turned along its own."""
        try:
            n = np.atleast_2d(np.asarray(self.normal, float))
        except (TypeError, ValueError):
            raise ValueError(f"Roller {name!r}: normal must be numbers of shape ({dim},), "
                             f"got {self.normal!r}") from None
        if n.ndim != 2 or n.shape[1] != dim or not np.all(np.isfinite(n)) or len(n) > dim:
            raise ValueError(f"Roller {name!r}: normal must be finite, shape ({dim},) or (k, {dim}), "
                             f"got {self.normal!r}")
        sv = np.linalg.svd(n, compute_uv=False)
        if sv.min() < 1e-9 * max(sv.max(), 1e-300):
            raise ValueError(f"Roller {name!r}: the normal is zero or its directions are not independent: "
                             f"{self.normal!r}")
        q = np.linalg.qr(n.T)[0].T                  # orthonormal rows spanning the same directions
        return q * np.sign(np.sum(q * n, 1))[:, None]


@dataclass(frozen=True)
class EssentialSets:
    """Validated named particle sets, concatenated in ``bnd`` (a particle appears once per set
    that holds it: only ``Roller`` sets may share particles). ``free``: the particles with a
    displacement component that no set holds (the unknowns' rows)."""

    names: tuple
    slices: dict   # name -> slice into bnd
    bnd: np.ndarray   # (Nb,) particle indices
    free: np.ndarray  # (Nf,) particle indices
    directions: dict = None   # name -> held unit directions (k, d) of a Roller set; None: all

    @property
    def partial(self) -> bool:
        """Whether a set holds only some components (a ``Roller``)."""
        return any(v is not None for v in (self.directions or {}).values())

    def held(self, dim: int) -> list:
        """Per entry of ``bnd``, its held unit directions (k, dim)."""
        out = []
        for name in self.names:
            sl = self.slices[name]
            D = (self.directions or {}).get(name)
            out.extend([np.eye(dim) if D is None else D] * (sl.stop - sl.start))
        return out

    @staticmethod
    def build(body: Body, essential: dict) -> "EssentialSets":
        if not isinstance(essential, dict):
            raise ValueError("essential must be a dict: name -> particle indices")
        seen = {}   # particle -> the last set that holds it
        held = np.zeros(body.n, np.int64)   # held components per particle
        directions = {}
        parts, slices, start = [], {}, 0
        for name, idx in essential.items():
            if not isinstance(name, str):
                raise ValueError(f"essential set names must be strings, got {name!r}")
            directions[name] = None
            if isinstance(idx, Roller):
                directions[name] = idx.directions(body.dim, name)
                idx = idx.particles
            idx = _set_indices(body, name, idx)
            _claim(body, seen, directions, name, idx)
            held[idx] += body.dim if directions[name] is None else len(directions[name])
            parts.append(idx)
            slices[name] = slice(start, start + len(idx))
            start += len(idx)
        bnd = np.concatenate(parts) if parts else np.zeros(0, np.int64)
        return EssentialSets(tuple(essential), slices, bnd, _free(body, held), directions)


def _set_indices(body: Body, name: str, idx) -> np.ndarray:
    """The particle indices (int64, distinct, in range) of the set ``name``: indices or a
    boolean mask over the particles."""
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
    return idx


def _claim(body: Body, seen: dict, directions: dict, name: str, idx: np.ndarray) -> None:
    """Record ``name`` as a holder of its particles in ``seen``; only Roller sets may share."""
    for i in idx:
        other = seen.get(int(i))
        if other is not None and (directions[other] is None or directions[name] is None):
            raise ValueError(f"essential sets {other!r} and {name!r} overlap "
                             f"(particle {int(i)} at {body.X[i].tolist()}); only Roller sets "
                             "may share particles")
        seen[int(i)] = name


def _free(body: Body, held: np.ndarray) -> np.ndarray:
    """The particles with a component that no set holds, given the held count per particle."""
    if np.any(held > body.dim):
        i = int(np.argmax(held))
        raise ValueError(f"particle {i} at {body.X[i].tolist()} is held in {held[i]} directions by "
                         f"rollers, more than its {body.dim} components")
    free = np.flatnonzero(held < body.dim)
    if len(free) == 0:
        raise ValueError("every particle is in an essential set: nothing left to solve for")
    return free


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


class EliminationLayout(NamedTuple):
    """The essential particles' elimination from K_ff, split into independent components
    (``elimination_layout``): arrays (C, ...) zero-padded to the largest component, so the
    layouts of different essential partitions stack (a padded entry adds zero)."""

    A: np.ndarray      # (C, R, M) A = (D^b)^-1 D^nb on a component's R essential particles
    #                    (rows) and the M free ones it couples them to (columns)
    cols: np.ndarray   # (C, M) those free particles (positions in free)
    free: np.ndarray   # (C, F) the free particles that share a tangent pair with the rows
    fb: np.ndarray     # (3, P) per particle pair (free i, essential j): component, position
    #                    in ``free``, row (component C: not such a pair)
    bb: np.ndarray     # (3, P) per pair (essential, essential): component, both rows


def elimination_layout(A, pair_i, pair_j, free, bnd) -> EliminationLayout:
    """Host-side layout of the elimination T^T K T (T = [I; -A]) by components: essential
    particles linked by a tangent pair or by a free particle that A couples to both. Why:
    A couples each essential particle only to the free ones near its own piece of boundary
    (a cube's two clamped faces are two blocks of A, half of it zero), so the products and
    scatters of one component involve only its free rows and coupled columns, not the dense
    Kfb A (``experiments/bench_cube3d.py``). No essential particles: C = 0."""
    A = np.asarray(A, float)
    Nb, Nf = A.shape
    pair_i, pair_j = np.asarray(pair_i, np.int64), np.asarray(pair_j, np.int64)
    N = int(max(pair_i.max(), pair_j.max(), np.max(free, initial=-1), np.max(bnd, initial=-1))) + 1
    pos = np.full(N, -1, np.int64)
    pos[np.asarray(free, np.int64)] = np.arange(Nf)
    is_free = np.zeros(N, bool)
    is_free[np.asarray(free, np.int64)] = True
    pos[np.asarray(bnd, np.int64)] = np.arange(Nb)
    P = len(pair_i)
    bb_pair = ~is_free[pair_i] & ~is_free[pair_j]
    fb_pair = is_free[pair_i] & ~is_free[pair_j]
    nz = sp.csr_matrix(A != 0, dtype=float)
    links = (nz @ nz.T) + sp.csr_matrix((np.ones(bb_pair.sum()), (pos[pair_i[bb_pair]], pos[pair_j[bb_pair]])),
                                         shape=(Nb, Nb))
    C, label = connected_components(links, directed=False) if Nb else (0, np.zeros(0, np.int64))
    rows = [np.flatnonzero(label == c) for c in range(C)]
    cols = [np.flatnonzero(np.any(A[r] != 0, axis=0)) for r in rows]
    fb_c = label[pos[pair_j[fb_pair]]]
    free_of = [np.unique(pos[pair_i[fb_pair][fb_c == c]]) for c in range(C)]

    def padded(parts, ndim):   # (C, largest shape) with zeros after each part
        shape = np.max([np.shape(x) for x in parts], axis=0) if parts else (0,) * ndim
        out = np.zeros((len(parts), *shape), parts[0].dtype if parts else float)
        for c, x in enumerate(parts):
            out[(c, *map(slice, np.shape(x)))] = x
        return out

    local = np.zeros(Nb, np.int64)   # an essential particle's position within its component
    for r in rows:
        local[r] = np.arange(len(r))
    fb = np.stack([np.full(P, C), np.zeros(P, np.int64), np.zeros(P, np.int64)])
    f_local = np.zeros(P, np.int64)
    for c in range(C):
        here = np.flatnonzero(fb_pair)[fb_c == c]
        f_local[here] = np.searchsorted(free_of[c], pos[pair_i[here]])
    fb[:, fb_pair] = [fb_c, f_local[fb_pair], local[pos[pair_j[fb_pair]]]]
    bb = np.stack([np.full(P, C), np.zeros(P, np.int64), np.zeros(P, np.int64)])
    bi, bj = pos[pair_i[bb_pair]], pos[pair_j[bb_pair]]
    bb[:, bb_pair] = [label[bi], local[bi], local[bj]]
    A_c = [A[np.ix_(r, k)] for r, k in zip(rows, cols)]
    return EliminationLayout(padded(A_c, 2), padded(cols, 1).astype(np.int32), padded(free_of, 1).astype(np.int32),
                             fb.astype(np.int32), bb.astype(np.int32))


class HostElimination:
    """The thesis transformation T = [I; -A] on the host, with A = (C_b)^-1 C_f applied through
    a sparse LU of C_b (A itself is dense per essential set): all coefficients dd = T v from
    the free ones v, and T^T y. So K_ff v = T^T K T v needs only K (the sparse and Krylov
    solvers' products)."""

    def __init__(self, C, free_dofs: np.ndarray, bnd_dofs: np.ndarray):
        C = sp.csr_matrix(C)
        self.n_dof = C.shape[1]
        self.free_dofs, self.bnd_dofs = free_dofs, bnd_dofs
        self.Cf = C[:, free_dofs].tocsr()
        self.Cf_T = self.Cf.T.tocsr()
        self.Cb_lu = spla.splu(C[:, bnd_dofs].tocsc()) if C.shape[0] else None

    def expand(self, v):
        """T v: (n_dof,) all coefficients from the free ones v (n_free,)."""
        full = np.zeros(self.n_dof)
        full[self.free_dofs] = v
        if self.Cb_lu is not None:
            full[self.bnd_dofs] = -self.Cb_lu.solve(self.Cf @ v)
        return full

    def reduce(self, y):
        """T^T y (n_free,) for y (n_dof,)."""
        out = y[self.free_dofs]
        if self.Cb_lu is not None:
            out = out - self.Cf_T @ self.Cb_lu.solve(y[self.bnd_dofs], trans="T")
        return out
