"""The discrete problem inside jit: gather -> F -> E -> W -> scatter.

All geometry arrives in ``Ops`` (built once by ``Model``). Unknowns are the free RK
coefficients u_f (Nf, d); prescribed values g (Nb, d) and the load scale are explicit,
differentiable inputs. The energy, its gradient (the residual) and the tangent as
particle-pair blocks; the force scale of the convergence test.
"""
from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .materials import det, green_lagrange


class Ops(NamedTuple):
    """Geometry and topology as arrays (no Python objects), passed into jit."""

    idx: jax.Array      # (Q, K) neighbour particles of each integration point
    dpsi: jax.Array     # (Q, K, d) shape function gradients
    w: jax.Array        # (Q,) integration weights
    free: jax.Array     # (Nf,) free particle indices
    bnd: jax.Array      # (Nb,) essential particle indices
    Dbinv: jax.Array    # (Nb, Nb) (D^b)^-1
    nb_idx: jax.Array   # (Nb, Kb) neighbours of the essential particles
    nb_psi: jax.Array   # (Nb, Kb) Psi_J(X_b), zero for essential J
    f_ext: jax.Array    # (N, d) nodal dead load at load scale 1
    pair_id: jax.Array  # (G, K, K) index of the particle pair (idx[q,k], idx[q,m]) for the q of group G
    pair_i: jax.Array   # (P,) first particle of each pair
    pair_j: jax.Array   # (P,)
    pair_t: jax.Array   # (P,) index of the transposed pair (pair_j, pair_i)
    elim: Any           # jaxrkpm.discretise.constraints.Elimination: (D^b)^-1 D^nb by boundary component
    spacing: jax.Array  # () particle spacing
    groups: jax.Array   # (G, S) integration points sharing one neighbour list (padded with Q)
    sp_idx: jax.Array   # (S, Ks) particles whose shape functions may reach each spring point
    sp_pair: jax.Array  # (S, Ks, Ks) index of the particle pair (sp_idx[s,k], sp_idx[s,m])


class Params(NamedTuple):
    point: dict   # name -> (Q,) values at the integration points
    tensors: dict  # name -> global arrays (e.g. Fung's A and C)
    springs: dict  # "psi" (S, Ks) shape functions at the spring points, "k" (S,) stiffnesses


# ------------------------------------------------------------------------ discrete model
def coefficients(ops: Ops, u, g):
    """Full RK coefficients (N, d): free ones from u, essential ones by eq 3.22."""
    N, dim = ops.f_ext.shape
    # the free and the essential particles are distinct: said, so that the derivatives of
    # these scatters are plain gathers (JAX otherwise tracks which of the duplicates won
    # with an integer scatter and gather of its own: 6 more kernels in every residual)
    d = jnp.zeros((N, dim), u.dtype).at[ops.free].set(u, unique_indices=True)
    s = jnp.einsum("bk,bki->bi", ops.nb_psi, d[ops.nb_idx])
    return d.at[ops.bnd].set(ops.Dbinv @ (g - s), unique_indices=True)


def deformation_gradients(idx, dpsi, d):
    """F = I + sum_K d_K (x) grad Psi_K at each point: (Q, d, d)."""
    return jnp.eye(d.shape[1]) + jnp.einsum("qkj,qki->qij", dpsi, d[idx])


def _point_energy(W):
    def psi(F, p):
        return W(green_lagrange(F), p)
    return psi


def _merged(params: Params):
    return {**params.point, **params.tensors}, {**{k: 0 for k in params.point},
                                                 **{k: None for k in params.tensors}}


def spring_energy(ops: Ops, params: Params, d):
    """Zero-length springs that hold material points to their reference positions:
    1/2 sum_s k_s |u(X_s)|^2 with u(X_s) = sum_K Psi_K(X_s) d_K (an elastic support, or a
    penalty paddle whose points X_s may move: they enter only through params.springs)."""
    sp = params.springs
    u = jnp.einsum("sk,ski->si", sp["psi"], d[ops.sp_idx])
    return 0.5 * jnp.sum(sp["k"][:, None] * u * u)


def by_group(ops: Ops, x):
    """Per-point values x (Q, ...) laid out by integration-point group (G, S, ...); the
    padding slots (index Q) hold zeros."""
    return jnp.concatenate([x, jnp.zeros((1,) + x.shape[1:], x.dtype)])[ops.groups]


def _group_params(ops: Ops, params: Params):
    """The material parameters by group (padding slots: the first point's values, so W
    stays finite there; their weight is zero) and their vmap axes."""
    p, axes = _merged(params)
    slot = jnp.minimum(ops.groups, ops.w.shape[0] - 1)
    return {k: v[slot] if axes[k] == 0 else v for k, v in p.items()}, axes


def group_gradients(ops: Ops, d):
    """F at the integration points by group: (G, S, d, d), F = I in the padding slots.

    The points of a group share one neighbour list, so the coefficients are gathered once
    per group, and the residual's transpose (the scatter back onto the particles) sums a
    group's points before it scatters: at the 10^3 Gauss cube (8 points a cell) the energy
    with its gradient took ~3x less time than point by point (same run, interleaved)."""
    rep = ops.idx[ops.groups[:, 0]]                    # (G, K): the group's neighbour list
    return jnp.eye(d.shape[1]) + jnp.einsum("gskj,gki->gsij", by_group(ops, ops.dpsi), d[rep])


def _per_group(f, axes):
    """f(F, p) of one point, mapped over (G, S) points."""
    return jax.vmap(jax.vmap(f, in_axes=(0, axes)), in_axes=(0, axes))


def _group_sum_scatter(ops: Ops, contrib, like):
    """sum over a group's points of contrib (G, S, K, d), scattered onto the particles of
    the group's neighbour list: (N, d)."""
    rep = ops.idx[ops.groups[:, 0]]
    return jnp.zeros_like(like).at[rep].add(contrib.sum(1))


def energy_full(ops: Ops, params: Params, W, d, load, dF=0.0):
    """Total potential energy in the full coefficients; aux: min det F.

    ``dF`` (G, S, d, d), added to F at the integration points by group, is zero in value: the
    energy's gradient with respect to it is the stress w P there (``energy_residual_stress``), which
    the backward pass of the residual computes anyway."""
    F = group_gradients(ops, d) + dF
    p, axes = _group_params(ops, params)
    Wq = _per_group(_point_energy(W), axes)(F, p)
    det_F = jnp.where(ops.groups < ops.w.shape[0], det(F), jnp.inf)   # padding: not a point
    return (jnp.sum(by_group(ops, ops.w) * Wq) + spring_energy(ops, params, d) - load * jnp.sum(ops.f_ext * d),
            jnp.min(det_F))


def energy(ops, params, W, u, g, load, dF=0.0):
    return energy_full(ops, params, W, coefficients(ops, u, g), load, dF)


def residual(ops, params, W, u, g, load):
    """r_f = dPi/du_f (Nf, d)."""
    return jax.grad(lambda v: energy(ops, params, W, v, g, load)[0])(u)


def energy_residual_stress(ops, params, W, u, g, load):
    """(Pi, min det F, r_f, w P) in one pass: the energy, its gradient and the weighted first
    Piola stress at the integration points by group (G, S, d, d), the gradient with respect
    to ``energy_full``'s dF (so the force scale needs no second pass through the material:
    at the 9x9 box that pass cost ~2x the residual)."""
    (Pi, det_min), (r, wP) = jax.value_and_grad(lambda x, e: energy(ops, params, W, x, g, load, e),
                                                argnums=(0, 1), has_aux=True)(u, zero_stress(ops, u))
    return Pi, det_min, r, wP


def zero_stress(ops: Ops, u):
    """Zeros of the shape of the stress by group (G, S, d, d), in u's dtype."""
    return jnp.zeros(ops.groups.shape + (u.shape[-1],) * 2, u.dtype)


def _weighted(ops: Ops, X):
    """w X for per-point (G, S, ...) tensors X (zero in the padding slots)."""
    return by_group(ops, ops.w).reshape(ops.groups.shape + (1,) * (X.ndim - 2)) * X


def _scatter_norm(ops: Ops, wX):
    """|| sum_q |grad Psi| |w X| || for weighted per-point (G, S, d, d) tensors w X: the size of
    the terms summed onto the particles."""
    contrib = jnp.einsum("gskj,gsij->gski", jnp.abs(by_group(ops, ops.dpsi)), jnp.abs(wX))
    return jnp.linalg.norm(_group_sum_scatter(ops, contrib, jnp.zeros(ops.f_ext.shape, wX.dtype)))


def stress_force_scale(ops, wP):
    """|| sum_q |grad Psi| |w P| || + |f_ext| from the weighted stress w P (G, S, d, d): the
    size of the terms summed into the residual."""
    return _scatter_norm(ops, wP) + jnp.linalg.norm(ops.f_ext)


def force_scales(ops, params, W, d):
    """(``stress_force_scale``, stiffness scale) at d from one pass (a jvp of the stress
    along F gives P and dP/dF : F together, where two passes would cost twice).

    The stiffness scale is || sum_q w |grad Psi| |dP/dF : F| || (dP/dF : F is the stress change
    of a unit relative stretch): times machine epsilon, the force that rounding the strain
    E = (F^T F - I)/2 to machine precision produces, below which |r| carries no information
    (the convergence test's round-off floor, ``jaxrkpm.solvers.newton.Tolerance``)."""
    F = group_gradients(ops, d)
    p, axes = _group_params(ops, params)

    def stress_and_stiffness(F, p):
        return jax.jvp(lambda G: jax.grad(_point_energy(W))(G, p), (F,), (F,))

    P, dP = _per_group(stress_and_stiffness, axes)(F, p)
    return stress_force_scale(ops, _weighted(ops, P)), _scatter_norm(ops, _weighted(ops, dP))


# doubles of (chunk, K, K, d, d) local tangent blocks held at once by pair_blocks (public: a
# test sweeps a small table in several windows by lowering it). Small enough that a chunk's
# blocks stay in cache between the GEMM that writes them and the scatter that sums them
# (2 MB): at the 10^3 cube (K = 64, 7 groups a chunk) the pair blocks took 2-5x less time
# than with the whole table at once (2^25; same run, interleaved, load average 7)
BLOCK_BUDGET = 2**18

# neighbours per part of a group's list when only one triangle of its (K, K) blocks is
# computed (public: a test sets it beyond K to compare with the whole square). A group's
# blocks are symmetric, K_mk = K_km^T, so of the parts' (a, b) products only a <= b are
# formed: with K = 64 in 4 parts, 10 of 16, and the transposes come from one gather over
# the pairs. Measured at the 20^3 cube (K = 64, same run, quiet): 1.36-1.40 -> 1.00-1.09 s
# (2 parts: 1.14-1.25 s; 8 parts: 1.00-1.12 s)
HALF_PART = 16


def material_tangent(W, F, p, axes):
    """dP/dF at every point, (Q, d, d, d, d) with [q, i, j, k, l] = dP_ij / dF_kl: the stress
    linearised once and applied to the d^2 unit directions. jax.hessian of the point energy
    (the same numbers) vmaps those directions into (Q, d^2, ...) arrays that XLA:CPU pads
    and copies: measured at 54,872 points (20^3 cube), 270 ms against 117 ms."""
    stress = jax.vmap(jax.grad(_point_energy(W)), in_axes=(0, axes))
    _, lin = jax.linearize(lambda G: stress(G, p), F)
    dim = F.shape[-1]
    unit = jnp.eye(dim * dim, dtype=F.dtype).reshape(dim * dim, dim, dim)
    return jnp.stack([lin(jnp.broadcast_to(e, F.shape)) for e in unit], -1).reshape(F.shape + (dim, dim))


def pair_blocks(ops, params, W, d):
    """Tangent in the full coefficients as (P, d, d) blocks over the particle pairs:
    K_IJ = sum_q w_q grad Psi_I . dP/dF . grad Psi_J (dP/dF by autodiff of W).

    Integration points with the same neighbour list (the Gauss points of one background
    cell) are summed together as one batched matrix product before the scatter into the
    pair sums, so the scatter runs once per group, not once per point. Large tables are
    swept in chunks of groups (a scan that accumulates the pair sums) so the (G, K, K, d, d)
    local blocks never exist all at once. Long lists (K >= 2 HALF_PART) form one triangle
    of each group's blocks: the pair sums U then hold each pair's blocks in one of its two
    orders, and K_IJ = U_IJ + U_JI^T (I != J)."""
    F = deformation_gradients(ops.idx, ops.dpsi, d)
    p, axes = _merged(params)
    C = material_tangent(W, F, p, axes)   # (Q, d, d, d, d)
    Q, K, dim = ops.dpsi.shape
    n_pairs = ops.pair_i.shape[0]
    G = ops.groups.shape[0]
    n_parts = max(1, K // HALF_PART)
    half = n_parts >= 2
    cut = np.linspace(0, K, n_parts + 1).astype(int)
    parts = [slice(a, b) for a, b in zip(cut[:-1], cut[1:])]
    # within a diagonal product (a, a) both orders of a pair are formed: the (m, k), m > k,
    # are sent past the last pair (a scatter drops them)
    below = np.tril(np.ones((K, K), bool), -1)

    def ext(x):  # index Q is the padding of the groups: a zero row
        return jnp.concatenate([x, jnp.zeros((1,) + x.shape[1:], x.dtype)])

    wdpsi, C, dpsi = ext(ops.dpsi * ops.w[:, None, None]), ext(C), ext(ops.dpsi)

    def chunk_sum(acc, grp, pid):
        # K_km[a, b] = sum_(s, l) Y[(s, l), (k, a, b)] dpsi[s, m, l] with Y = w dpsi . C: one
        # batched GEMM per group and pair of parts, laid out (group, m, (k, a, b)) so that
        # its output rows are already the (d, d) blocks of the pairs (k, m) (pid transposed
        # to match); summed into acc in place (a scatter-add into the carried sums)
        c, s = grp.shape
        Y = jnp.einsum("cskj,csajbl->cslkab", wdpsi[grp], C[grp]).reshape(c, s * dim, K, dim * dim)
        B = dpsi[grp].transpose(0, 1, 3, 2).reshape(c, s * dim, K)
        pid = pid.transpose(0, 2, 1)
        blocks, ids = [], []
        for a, rows in enumerate(parts):
            for cols in parts[a:]:
                blocks.append(jnp.einsum("cxm,cxn->cmn", B[:, :, rows], Y[:, :, cols].reshape(c, s * dim, -1)))
                ij = pid[:, rows, cols]
                if half and rows == cols:
                    ij = jnp.where(below[rows, cols], n_pairs, ij)
                ids.append(ij.reshape(-1))
        blocks = jnp.concatenate([b.reshape(-1, dim, dim) for b in blocks])
        return acc + jax.ops.segment_sum(blocks, jnp.concatenate(ids), num_segments=n_pairs)

    zero = jnp.zeros((n_pairs, dim, dim), d.dtype)
    # windows of equal size: with ``chunk`` groups each the last window, shifted back to end
    # at G, recomputed up to a whole window of groups already summed (the needle phantom,
    # G = 106 in windows of 104: 1.86 ms against 0.80 ms in two windows of 53)
    windows = -(-G // max(1, BLOCK_BUDGET // (K * K * dim * dim)))
    chunk = -(-G // windows)
    if windows == 1:
        U = chunk_sum(zero, ops.groups, ops.pair_id)
    else:
        def body(i, acc):
            # a window of ``chunk`` groups sliced in place (padding the (G, K, K) pair-id
            # table to whole chunks would copy it: GBs for a 3D body); the last window is
            # shifted back to end at G, and its groups already summed point at the zero
            # padding row Q instead
            start = jnp.minimum(i * chunk, G - chunk)
            grp = jax.lax.dynamic_slice_in_dim(ops.groups, start, chunk)
            seen = (start + jnp.arange(chunk) < i * chunk)[:, None]
            pid = jax.lax.dynamic_slice_in_dim(ops.pair_id, start, chunk)
            return chunk_sum(acc, jnp.where(seen, Q, grp), pid)

        U = jax.lax.fori_loop(0, windows, body, zero)
    if half:
        U = U + jnp.where((ops.pair_i == ops.pair_j)[:, None, None], 0.0, jnp.swapaxes(U[ops.pair_t], -1, -2))
    return U + spring_blocks(ops, params, n_pairs, dim)


def spring_blocks(ops, params, n_pairs, dim):
    """The springs' tangent k_s Psi_K(X_s) Psi_M(X_s) I as (P, d, d) pair blocks."""
    sp = params.springs
    kk = jnp.einsum("s,sk,sm->skm", sp["k"], sp["psi"], sp["psi"])
    scal = jax.ops.segment_sum(kk.ravel(), ops.sp_pair.ravel(), num_segments=n_pairs)
    return scal[:, None, None] * jnp.eye(dim)


def dense_tangent(ops, blocks):
    """K_ff = T^T K T with T = [I; -A] (the thesis transformation), dense (Nf*d, Nf*d).

    The free-free pair blocks are scattered straight into K_ff's (particle, d, particle, d)
    layout (no full (N d)^2 matrix, transpose or row/column gathers: measured at the 10^3
    cube, ~20% less time), and the essential particles are eliminated one component at a
    time (``elimination_layout``): K_ff -= K_fb A + (K_fb A)^T, K_ff += A^T K_bb A on each
    component's rows and columns only. A pair of the other orientation is dropped (K_bf =
    K_fb^T)."""
    N, dim = ops.f_ext.shape
    Nf = ops.free.shape[0]
    pos = jnp.full(N, Nf, jnp.int32).at[ops.free].set(jnp.arange(Nf, dtype=jnp.int32))
    i, j = pos[ops.pair_i], pos[ops.pair_j]          # Nf (out of range, dropped): essential
    Kff = jnp.zeros((Nf, dim, Nf, dim), blocks.dtype).at[i, :, j, :].add(blocks, mode="drop")
    e = ops.elim
    C, F, R = e.free.shape[0], e.free.shape[1], e.A.shape[1]
    if C:
        Kfb = jnp.zeros((C, F, dim, R, dim), blocks.dtype).at[e.fb[0], e.fb[1], :, e.fb[2], :].add(blocks, mode="drop")
        Kbb = jnp.zeros((C, R, dim, R, dim), blocks.dtype).at[e.bb[0], e.bb[1], :, e.bb[2], :].add(blocks, mode="drop")
        X = jnp.einsum("cfaRb,cRm->cfmab", Kfb, e.A)                     # (C, F, M, d, d)
        rows, cols = e.free[:, :, None], e.cols[:, None, :]
        Kff = Kff.at[rows, :, cols, :].add(-X)
        Kff = Kff.at[e.cols[:, :, None], :, e.free[:, None, :], :].add(-X.transpose(0, 2, 1, 4, 3))
        corr = jnp.einsum("cRm,cRaSb,cSn->cmnab", e.A, Kbb, e.A)          # (C, M, M, d, d)
        Kff = Kff.at[e.cols[:, :, None], :, cols, :].add(corr)
    n = Nf * dim
    return Kff.reshape(n, n)


def point_values(ops, idx, psi, u, g):
    """Displacement at points with precomputed (P, K) shape functions: (P, d)."""
    d = coefficients(ops, u, g)
    return jnp.einsum("pk,pki->pi", psi, d[idx])
