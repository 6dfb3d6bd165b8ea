"""The body's strain energy as a term: gather -> F -> E -> W -> scatter, inside jit.

``StrainEnergy`` holds the volume integration table (points by group, weights, shape function
gradients), the material's parameters at the integration points and its strain energy density
W (static). Its energy is sum_q w_q W(E(F_q)); its tangent blocks are assembled from dP/dF by
group of points that share a neighbour list; its share of the force scale comes from the
stress that the residual's backward pass computes anyway (``aux``).
"""
from __future__ import annotations

from dataclasses import replace
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from ..discretise.pairs import point_groups
from ..discretise.quadrature import patched
from .materials import Material, det, green_lagrange
from .term import Context, Pairs, Term, static, term, window_plan


def deformation_gradients(idx, dpsi, d):
    """F = I + sum_K d_K (x) grad Psi_K at each point: (Q, d, d)."""
    return jnp.eye(d.shape[1]) + jnp.einsum("qkj,qki->qij", dpsi, d[idx])


def _point_energy(W):
    def psi(F, p):
        return W(green_lagrange(F), p)
    return psi


def mean_dilatation(F, w):
    """F-bar over one patch of points (S, d, d) with weights w (S,): (J̄ / J)^(1/d) F, J̄ the
    w-weighted mean of J = det F. The deviatoric part of F is the point's own, its volume change
    the patch's, so a patch carries one volumetric constraint instead of one per point; under
    an affine field every J equals J̄ and F-bar is F (the patch test is untouched)."""
    J = det(F)
    Jbar = jnp.sum(w * J) / jnp.sum(w)
    return ((Jbar / J) ** (1.0 / F.shape[-1]))[:, None, None] * F


def _per_group(f, axes):
    """f(F, p) of one point, mapped over (G, S) points."""
    return jax.vmap(jax.vmap(f, in_axes=(0, axes)), in_axes=(0, axes))


def material_tangent(W, F, p, axes):
    """dP/dF at every point, (Q, d, d, d, d) with [q, i, j, k, l] = dP_ij / dF_kl: the stress
    linearised once and applied to the d^2 unit directions (jax.hessian of the point energy,
    the same numbers, vmaps those directions into (Q, d^2, ...) arrays that XLA:CPU pads and
    copies; ``experiments/bench_cube3d_large.py`` times the assembly)."""
    stress = jax.vmap(jax.grad(_point_energy(W)), in_axes=(0, axes))
    _, lin = jax.linearize(lambda G: stress(G, p), F)
    dim = F.shape[-1]
    unit = jnp.eye(dim * dim, dtype=F.dtype).reshape(dim * dim, dim, dim)
    return jnp.stack([lin(jnp.broadcast_to(e, F.shape)) for e in unit], -1).reshape(F.shape + (dim, dim))


@term
class StrainEnergy(Term):
    """sum_q w_q W(E(F_q), p_q) over the volume integration points.

    idx (Q, K), dpsi (Q, K, d), w (Q,)   the integration table
    groups (G, S)   points sharing one neighbour list (padded with Q)
    pair_id (G, K, K)   the pattern's index of the pair (idx[q, k], idx[q, m]) of each group
    point, tensors  the material's parameters: name -> (Q,) values at the points; name ->
                    global arrays (e.g. Fung's A and C)
    W               the strain energy density W(E, p) (static)
    n               particles (static)
    block_budget    doubles of (chunk, K, K, d, d) local tangent blocks held at once: small
                    enough that a chunk's blocks stay in cache between the GEMM that writes
                    them and the scatter that sums them (``experiments/bench_cube3d_large.py``)
    patches         True: the groups are dilatation patches (``dilatation_patches``) and every
                    point's energy is taken at F-bar (``mean_dilatation``) over its group, the
                    anti-locking formulation; the tangent blocks are then the Hessian of each
                    patch's energy in its points' F (``experiments/bench_anti_locking.py``)
    half_part       neighbours per part of a group's list when only one triangle of its
                    (K, K) blocks is formed (K >= 2 half_part): a group's blocks are symmetric,
                    so of the parts' (a, b) products only a <= b are formed and the transposes
                    come from one gather over the pairs (``experiments/bench_cube3d_large.py``)
    """

    idx: jax.Array
    dpsi: jax.Array
    w: jax.Array
    groups: jax.Array
    point: dict
    tensors: dict
    pair_id: jax.Array = None
    W: Callable = static()
    n: int = static(0)
    name: str = static("strain")
    block_budget: int = static(2**18)
    half_part: int = static(16)
    patches: bool = static(False)

    # --------------------------------------------------------------- by group
    def _merged(self):
        return {**self.point, **self.tensors}, {**{k: 0 for k in self.point}, **{k: None for k in self.tensors}}

    def by_group(self, x):
        """Per-point values x (Q, ...) laid out by integration-point group (G, S, ...); the
        padding slots (index Q) hold zeros."""
        return jnp.concatenate([x, jnp.zeros((1,) + x.shape[1:], x.dtype)])[self.groups]

    def _group_params(self):
        """The material parameters by group (padding slots: the first point's values, so W
        stays finite there; their weight is zero) and their vmap axes."""
        p, axes = self._merged()
        slot = jnp.minimum(self.groups, self.w.shape[0] - 1)
        return {k: v[slot] if axes[k] == 0 else v for k, v in p.items()}, axes

    def group_gradients(self, d):
        """F at the integration points by group: (G, S, d, d), F = I in the padding slots.

        The points of a group share one neighbour list, so the coefficients are gathered once
        per group, and the residual's transpose (the scatter back onto the particles) sums a
        group's points before it scatters (``experiments/bench_cube3d.py``)."""
        rep = self.idx[self.groups[:, 0]]                    # (G, K): the group's neighbour list
        return jnp.eye(d.shape[1]) + jnp.einsum("gskj,gki->gsij", self.by_group(self.dpsi), d[rep])

    def _group_sum_scatter(self, contrib, like):
        """sum over a group's points of contrib (G, S, K, d), scattered onto the particles of
        the group's neighbour list: (N, d)."""
        rep = self.idx[self.groups[:, 0]]
        return jnp.zeros_like(like).at[rep].add(contrib.sum(1))

    # ------------------------------------------------------------------ energy
    def energy(self, d, load, aux=None):
        """(sum_q w_q W_q, min det F). ``aux`` (G, S, d, d), added to F at the integration
        points by group, is zero in value: the energy's gradient with respect to it is the
        stress w P there, which the backward pass of the residual computes anyway (so the
        force scale needs no second pass through the material)."""
        F = self.group_gradients(d) + (0.0 if aux is None else aux)
        p, axes = self._group_params()
        det_F = jnp.where(self.groups < self.w.shape[0], det(F), jnp.inf)   # padding: not a point
        if self.patches:
            return jnp.sum(jax.vmap(self._patch_energy(axes), in_axes=(0, 0, axes))(F, self.by_group(self.w), p)), \
                jnp.min(det_F)
        Wq = _per_group(_point_energy(self.W), axes)(F, p)
        return jnp.sum(self.by_group(self.w) * Wq), jnp.min(det_F)

    def _patch_energy(self, axes):
        """The energy of one patch, sum_s w_s W(F-bar_s), from its points' F (S, d, d), weights
        (S,) and parameters (the padding slots: F = I, w = 0)."""
        psi = jax.vmap(_point_energy(self.W), in_axes=(0, axes))

        def energy(F, w, p):
            return jnp.sum(w * psi(mean_dilatation(F, w), p))
        return energy

    def aux_zeros(self, u):
        """Zeros of the shape of the stress by group (G, S, d, d), in u's dtype."""
        return jnp.zeros(self.groups.shape + (u.shape[-1],) * 2, u.dtype)

    # ------------------------------------------------------------- force scale
    def _weighted(self, X):
        """w X for per-point (G, S, ...) tensors X (zero in the padding slots)."""
        return self.by_group(self.w).reshape(self.groups.shape + (1,) * (X.ndim - 2)) * X

    def _scatter_norm(self, wX):
        """|| sum_q |grad Psi| |w X| || for weighted per-point (G, S, d, d) tensors w X: the size of
        the terms summed onto the particles."""
        contrib = jnp.einsum("gskj,gsij->gski", jnp.abs(self.by_group(self.dpsi)), jnp.abs(wX))
        return jnp.linalg.norm(self._group_sum_scatter(contrib, jnp.zeros((self.n, wX.shape[-1]), wX.dtype)))

    def force_scale(self, aux):
        """|| sum_q |grad Psi| |w P| || from the weighted stress w P (G, S, d, d), the aux of
        ``energy``: the size of the terms this term sums into the residual."""
        return self._scatter_norm(aux)

    def force_scales(self, d):
        """(``force_scale``, stiffness scale) at d from one pass (a jvp of the stress along F
        gives P and dP/dF : F together, where two passes would cost twice).

        The stiffness scale is || sum_q w |grad Psi| |dP/dF : F| || (dP/dF : F is the stress change
        of a unit relative stretch): times machine epsilon, the force that rounding the strain
        E = (F^T F - I)/2 to machine precision produces, below which |r| carries no information
        (the convergence test's round-off floor, ``jaxrkpm.solvers.newton.Tolerance``)."""
        F = self.group_gradients(d)
        p, axes = self._group_params()
        if self.patches:   # the weighted stress of a patch and its change, from the patch's energy
            stress = jax.grad(self._patch_energy(axes))
            P, dP = jax.vmap(lambda F, w, p: jax.jvp(lambda G: stress(G, w, p), (F,), (F,)),
                             in_axes=(0, 0, axes))(F, self.by_group(self.w), p)
            return self._scatter_norm(P), self._scatter_norm(dP)

        def stress_and_stiffness(F, p):
            return jax.jvp(lambda G: jax.grad(_point_energy(self.W))(G, p), (F,), (F,))

        P, dP = _per_group(stress_and_stiffness, axes)(F, p)
        return self._scatter_norm(self._weighted(P)), self._scatter_norm(self._weighted(dP))

    # ------------------------------------------------------------------ tangent
    def blocks(self, d, load, pairs: Pairs):
        """Tangent in the full coefficients as (P, d, d) blocks over the particle pairs:
        K_IJ = sum_q w_q grad Psi_I . dP/dF . grad Psi_J (dP/dF by autodiff of W); with
        ``patches``, the Hessian of the F-bar energy (``_patch_tangent``)."""
        if self.patches:
            C, rank = self._patch_tangent(d)
            return self._assembled(self.dpsi, C, pairs, rank)
        F = deformation_gradients(self.idx, self.dpsi, d)
        p, axes = self._merged()
        return self._assembled(self.dpsi * self.w[:, None, None], material_tangent(self.W, F, p, axes), pairs)

    def _patch_tangent(self, d):
        """The F-bar energy's Hessian in the points' F, as a per-point tangent and a rank-3
        patch term: E(F) = Ẽ(F, J̄(F)) with Ẽ = sum_s w_s W(F̄_s(F_s, J̄)) and J̄ = sum_s w_s J_s /
        sum_s w_s couples the points of a patch only through the scalar J̄, so

            d2E/dF_s dF_t = δ_st (Ẽ_FsFs + Ẽ_J̄ d2J̄/dF_s2) + a_s ⊗ b_t + b_s ⊗ a_t + c b_s ⊗ b_t

        with a_s = Ẽ_FsJ̄, b_s = dJ̄/dF_s, c = Ẽ_J̄J̄: the per-point part assembles as the plain
        tangent does and the coupling as three outer products of (K, d) vectors per patch, the
        cost of a plain assembly (``experiments/bench_anti_locking.py``), where the patch's full
        Hessian (S d^2)^2 by autodiff cost S d^2 passes. Returns the per-point tangent (Q, d, d, d, d)
        (weights included) and (a (Q, d, d), b (Q, d, d), c (G,))."""
        F = self.group_gradients(d)
        p, axes = self._group_params()
        w = self.by_group(self.w)
        dim = F.shape[-1]
        psi = _point_energy(self.W)
        grads = jax.grad(lambda Fs, Jb, ps: psi((Jb / det(Fs)) ** (1.0 / dim) * Fs, ps), argnums=(0, 1))
        unit = jnp.eye(dim * dim, dtype=F.dtype).reshape(dim * dim, dim, dim)

        def point(Fs, Jb, ps):
            # one linearisation of (dW/dF, dW/dJ̄) at fixed J̄ along the d^2 unit directions of F and
            # along J̄; one of dJ/dF for its curvature
            (_, e), lin = jax.linearize(lambda G, j: grads(G, j, ps), Fs, Jb)
            A = jnp.stack([lin(u, jnp.zeros_like(Jb))[0] for u in unit], -1).reshape((dim,) * 4)
            a, f = lin(jnp.zeros_like(Fs), jnp.ones_like(Jb))
            cof, lin_det = jax.linearize(jax.grad(det), Fs)
            HJ = jnp.stack([lin_det(u) for u in unit], -1).reshape((dim,) * 4)
            return A, a, e, f, cof, HJ

        sw = jnp.sum(w, 1)
        Jb = jnp.broadcast_to((jnp.sum(w * det(F), 1) / sw)[:, None], w.shape)
        A, a, e, f, cof, HJ = jax.vmap(jax.vmap(point, in_axes=(0, 0, axes)), in_axes=(0, 0, axes))(F, Jb, p)
        gJ = jnp.sum(w * e, 1)                                         # Ẽ_J̄ (G,)
        share = w / sw[:, None]                                        # dJ̄/dJ_s
        tangent = w[..., None, None, None, None] * A + (gJ[:, None] * share)[..., None, None, None, None] * HJ
        return self._points(tangent), (self._points(w[..., None, None] * a),
                                       self._points(share[..., None, None] * cof), jnp.sum(w * f, 1))

    def _points(self, x):
        """Per-group values x (G, S, ...) as per-point values (Q, ...) (the padding dropped)."""
        Q = self.w.shape[0]
        return jnp.zeros((Q + 1,) + x.shape[2:], x.dtype).at[self.groups].set(x)[:Q]

    def _assembled(self, wdpsi, C, pairs: Pairs, rank=None):
        """The pair sums of sum_q wdpsi_q . C_q . dpsi_q, and with ``rank`` = (a, b, c) the
        patch terms alpha (x) beta + beta (x) alpha + c beta (x) beta (alpha = sum_s dpsi_s . a_s,
        beta = sum_s dpsi_s . b_s over each group: ``_patch_tangent``).

        Integration points with the same neighbour list (the Gauss points of one background
        cell) are summed together as one batched matrix product before the scatter into the
        pair sums, so the scatter runs once per group, not once per point. Large tables are
        swept in windows of groups (a loop that accumulates the pair sums) so the (G, K, K, d, d)
        local blocks never exist all at once. Long lists (K >= 2 half_part) form one triangle
        of each group's blocks: the pair sums U then hold each pair's blocks in one of its two
        orders, and K_IJ = U_IJ + U_JI^T (I != J); the patch terms are symmetric in the same
        way, so they join the triangle."""
        Q, K, dim = self.dpsi.shape
        n_pairs = pairs.count
        G = self.groups.shape[0]
        n_parts = max(1, K // self.half_part)
        half = n_parts >= 2
        cut = np.linspace(0, K, n_parts + 1).astype(int)
        parts = [slice(a, b) for a, b in zip(cut[:-1], cut[1:])]
        # within a diagonal product (a, a) both orders of a pair are formed: the (m, k), m > k,
        # are sent past the last pair (a scatter drops them)
        below = np.tril(np.ones((K, K), bool), -1)

        def ext(x):  # index Q is the padding of the groups: a zero row
            return jnp.concatenate([x, jnp.zeros((1,) + x.shape[1:], x.dtype)])

        wdpsi, C, dpsi = ext(wdpsi), ext(C), ext(self.dpsi)
        if rank is not None:
            a_pt, b_pt, c_grp = ext(rank[0]), ext(rank[1]), rank[2]

        def chunk_sum(acc, grp, pid, c_chunk):
            # K_km[a, b] = sum_(s, l) Y[(s, l), (k, a, b)] dpsi[s, m, l] with Y = w dpsi . C: one
            # batched GEMM per group and pair of parts, laid out (group, m, (k, a, b)) so that
            # its output rows are already the (d, d) blocks of the pairs (k, m) (pid transposed
            # to match); summed into acc in place (a scatter-add into the carried sums)
            c, s = grp.shape
            D = dpsi[grp]
            Y = jnp.einsum("cskj,csajbl->cslkab", wdpsi[grp], C[grp]).reshape(c, s * dim, K, dim * dim)
            B = D.transpose(0, 1, 3, 2).reshape(c, s * dim, K)
            if rank is not None:   # (group, m, k, a, b) like the GEMM's output
                al = jnp.einsum("cskj,csaj->cka", D, a_pt[grp])
                be = jnp.einsum("cskj,csaj->cka", D, b_pt[grp])
                R = (jnp.einsum("cka,cmb->cmkab", al, be) + jnp.einsum("cka,cmb->cmkab", be, al)
                     + c_chunk[:, None, None, None, None] * jnp.einsum("cka,cmb->cmkab", be, be))
            pid = pid.transpose(0, 2, 1)
            blocks, ids = [], []
            for a, rows in enumerate(parts):
                for cols in parts[a:]:
                    blk = jnp.einsum("cxm,cxn->cmn", B[:, :, rows], Y[:, :, cols].reshape(c, s * dim, -1))
                    if rank is not None:
                        blk = blk + R[:, rows, cols].reshape(blk.shape)
                    blocks.append(blk)
                    ij = pid[:, rows, cols]
                    if half and rows == cols:
                        ij = jnp.where(below[rows, cols], n_pairs, ij)
                    ids.append(ij.reshape(-1))
            blocks = jnp.concatenate([b.reshape(-1, dim, dim) for b in blocks])
            return acc + jax.ops.segment_sum(blocks, jnp.concatenate(ids), num_segments=n_pairs)

        zero = jnp.zeros((n_pairs, dim, dim), C.dtype)
        # windows of equal size: the last one, shifted back to end at G, recomputes up to a
        # whole window of groups already summed (their padding row Q adds nothing)
        windows, chunk = window_plan(G, K * K * dim * dim * (1 if rank is None else 2), self.block_budget)
        if windows == 1:
            U = chunk_sum(zero, self.groups, self.pair_id, None if rank is None else c_grp)
        else:
            def body(i, acc):
                # a window of ``chunk`` groups sliced in place (padding the (G, K, K) pair-id
                # table to whole chunks would copy it, the largest table of a 3D body); the last
                # window is shifted back to end at G, and its groups already summed point at
                # the zero padding row Q instead (so their patch vectors are zero too)
                start = jnp.minimum(i * chunk, G - chunk)
                grp = jax.lax.dynamic_slice_in_dim(self.groups, start, chunk)
                seen = (start + jnp.arange(chunk) < i * chunk)
                pid = jax.lax.dynamic_slice_in_dim(self.pair_id, start, chunk)
                c_chunk = None if rank is None else jax.lax.dynamic_slice_in_dim(c_grp, start, chunk)
                return chunk_sum(acc, jnp.where(seen[:, None], Q, grp), pid, c_chunk)

            U = jax.lax.fori_loop(0, windows, body, zero)
        if half:
            U = U + jnp.where((pairs.i == pairs.j)[:, None, None], 0.0, jnp.swapaxes(U[pairs.t], -1, -2))
        return U

    # -------------------------------------------------------------- parameters
    @property
    def params(self) -> dict:
        return {"point": self.point, "tensors": self.tensors}

    def with_params(self, params: dict) -> "StrainEnergy":
        return replace(self, point=params["point"], tensors=params["tensors"])

    # ----------------------------------------------------------- host side
    def lists(self) -> np.ndarray:
        """Each group's neighbour list (G, K): per point it would be Q K^2 pair keys."""
        return np.asarray(self.idx)[np.asarray(self.groups)[:, 0]]

    def placed(self, ids) -> "StrainEnergy":
        return replace(self, pair_id=jnp.asarray(ids, jnp.int32))


def needs_anti_locking(material: Material, point: dict, lame_ratio: float = 9.0) -> bool:
    """Whether ``material`` (its parameters at the points) is nearly incompressible: an energy
    with a volumetric-deviatoric split (``Material.split``), or one written with Lame constants
    whose lam / mu reaches ``lame_ratio`` somewhere (9: Poisson's ratio 0.45, from which such an
    energy locks)."""
    if material.split:
        return True
    if "lam" in point and "mu" in point:
        return bool(np.any(np.asarray(point["lam"]) >= lame_ratio * np.asarray(point["mu"])))
    return False


def strain_energy(ctx: Context, material: Material, anti_locking: bool | None = None,
                  patch_of: np.ndarray | None = None) -> StrainEnergy:
    """The strain energy term of ``material`` over ``ctx.volume``, the material's parameters
    evaluated at the points and its energy checked there. Its integration points are grouped
    by neighbour list (``point_groups``), or, with ``anti_locking`` (None: where
    ``needs_anti_locking``), by the dilatation patches ``patch_of`` (Q,)
    (``jaxrkpm.discretise.quadrature.dilatation_patches``), each point's energy taken at F-bar."""
    table = ctx.volume
    d = ctx.body.dim
    point = {k: jnp.asarray(v) for k, v in material.point_params(table.points).items()}
    tensors = {k: jnp.asarray(v) for k, v in material.global_params(d).items()}
    material.check_energy(d, {k: v[0] for k, v in point.items()})
    on = needs_anti_locking(material, point) if anti_locking is None else bool(anti_locking)
    if on and patch_of is None:
        raise ValueError("anti-locking needs the dilatation patches of the integration points (patch_of)")
    if on:
        table, groups = patched(table, patch_of)
    else:
        groups = point_groups(table.idx.astype(np.int64))
    return StrainEnergy(idx=jnp.asarray(table.idx, jnp.int32), dpsi=jnp.asarray(table.dpsi),
                        w=jnp.asarray(table.weights), groups=jnp.asarray(groups, jnp.int32), point=point,
                        tensors=tensors, W=material.W, n=ctx.body.n, patches=on)
