"""Linear solvers of the Newton iteration, with explicit state (in the manner of lineax).

A solver is a static, immutable description (part of the jit configuration); everything that
changes between calls is its *state*, a pytree returned and passed explicitly:

    state = solver.init(ops, blocks)          # factorise the tangent given as pair blocks
    x = solver.solve(state, rhs)              # K_ff x = rhs with that factorisation
    solver.stability(state)                   # Stability: STABLE / UNSTABLE / UNKNOWN
    solver.negative_eigenvalues(state)        # inertia: negative eigenvalues of K_ff (-1: unknown)
    x, state, stab = solver.newton_solve(state, ops, blocks, rhs, rtol)
                                              # a Newton step with the current tangent, reusing
                                              # ``state`` where the solver can

``rhs`` is (Nf, d) or (Nf, d, m). One factorisation thus serves a Newton predictor, chord
corrections and implicit Jacobians (``jaxrkpm.solve.newton`` and ``sensitivity``), for the
dense and the sparse solver alike.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import krylov, sparse
from .refinement import REFINEMENTS, refine
from .outcome import Outcome

try:
    from jax.experimental.buffer_callback import buffer_callback
except ImportError:      # JAX before buffer_callback: host callbacks copy their operands
    buffer_callback = None


def host_callback(fn, result_shape_dtypes, *args):
    """``fn(*args)`` on the host inside jit (the sparse and Krylov solvers' factorisations
    and CG), one batch member at a time under vmap. ``fn`` gets read-only NumPy views of
    XLA's own operand buffers, valid during the call only: what it keeps beyond the call
    it must copy (the factorisations and multigrid hierarchies do).

    Why not jax.pure_callback: it copies every operand onto a new device array before the
    call, and a Newton step passes two tangents (the current one and the factorised one):
    at the 20^3 cube two 150 MB copies, 0.21 s a call against 13 us without them (same
    process); at the 30^3 cube 560 MB each. (pure_callback remains the fallback on JAX
    versions without buffer_callback.)"""
    if buffer_callback is None:
        return jax.pure_callback(fn, result_shape_dtypes, *args, vmap_method="sequential")

    def run(ctx, out, *buffers):
        views = []
        for b in buffers:
            v = np.asarray(b)
            v.flags.writeable = False
            views.append(v)
        results = fn(*views)
        for o, r in zip(jax.tree_util.tree_leaves(out), jax.tree_util.tree_leaves(results)):
            np.asarray(o)[...] = r

    return buffer_callback(run, result_shape_dtypes, vmap_method="sequential")(*args)


class Stability(Outcome):
    """What a factorisation says of K_ff (inside jit: the int code)."""

    STABLE = 0, "K_ff is positive definite (a stable equilibrium)"
    UNSTABLE = 1, "K_ff has negative eigenvalues (a limit or bifurcation point was passed)"
    UNKNOWN = 2, ("the factorisation could not tell the inertia of K_ff (pivots were perturbed "
                  "or permuted): stability is unknown")
    FAILED = 3, ("the iterative linear solve did not converge (jaxrkpm.krylov): the Newton "
                 "step is not trusted")


# ------------------------------------------------------------------------------- dense
class DenseState(NamedTuple):
    """A dense factorisation of K_ff. Its matrices are held flat (row-major by construction):
    held as (n, n) arrays inside a Newton or control loop, XLA gave the loop's carry LAPACK's
    column-major layout (they come out of, or feed, the factorisations), and every solve then
    copied them to the row-major layout of its products (10^3 cube, n = 2,400: a kept
    factorisation's solve 15 ms, 6.6 ms without the copies)."""
    K_flat: jax.Array     # (n * n,) K_ff
    spd: jax.Array        # () K_ff positive definite: L is usable (else solves use LU of K)
    Linv_flat: jax.Array  # (n * n,) L^-1 (``DenseSolver(inverse=True)``; K^-1 where K_ff is not
    #                       positive definite), else (0,)
    rows: tuple           # flat row blocks of L^T (``factor_blocks``), for ``triangular_pair``;
    #                       () with inverse=True
    Dinv: jax.Array       # (m, B, B) inverses of L's diagonal blocks (``blocked_inverses``; the
    #                       last one padded; m = 0 for a single block); (0, 0, 0) with inverse=True

    @property
    def K(self):
        return _square(self.K_flat)

    @property
    def Linv(self):
        return _square(self.Linv_flat)


def _square(flat):
    n = math.isqrt(flat.shape[0])
    return flat.reshape(n, n)


class Elimination(NamedTuple):
    """The essential particles' elimination from K_ff, split into independent components
    (``elimination_layout``): arrays (C, ...) zero-padded to the largest component, so the
    layouts of different essential partitions stack (a padded entry adds zero)."""

    A: jax.Array       # (C, R, M) A = (D^b)^-1 D^nb on a component's R essential particles
    #                    (rows) and the M free ones it couples them to (columns)
    cols: jax.Array    # (C, M) those free particles (positions in free)
    free: jax.Array    # (C, F) the free particles that share a tangent pair with the rows
    fb: jax.Array      # (3, P) per particle pair (free i, essential j): component, position
    #                    in ``free``, row (component C: not such a pair)
    bb: jax.Array      # (3, P) per pair (essential, essential): component, both rows


def elimination_layout(A, pair_i, pair_j, free, bnd) -> Elimination:
    """Host-side layout of the elimination T^T K T (T = [I; -A]) by components: essential
    particles linked by a tangent pair or by a free particle that A couples to both. Why:
    A couples each essential particle only to the free ones near its own piece of boundary
    (a cube's two clamped faces are two blocks of A, half of it zero), so the products and
    scatters of one component involve only its free rows and coupled columns (at the 10^3
    cube ~5x fewer flops than the dense Kfb A). No essential particles: C = 0."""
    import scipy.sparse as sps
    from scipy.sparse.csgraph import connected_components

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
    nz = sps.csr_matrix(A != 0, dtype=float)
    links = (nz @ nz.T) + sps.csr_matrix((np.ones(bb_pair.sum()), (pos[pair_i[bb_pair]], pos[pair_j[bb_pair]])),
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
    return Elimination(jnp.asarray(padded(A_c, 2)), jnp.asarray(padded(cols, 1), jnp.int32),
                       jnp.asarray(padded(free_of, 1), jnp.int32),
                       jnp.asarray(fb, jnp.int32), jnp.asarray(bb, jnp.int32))


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


TRIANGULAR_BLOCK = 256   # rows of L per block of the blocked triangular solves


def by_columns(f, b):
    """f(b) for b (n, k) as k calls on single columns (n <= TRIANGULAR_BLOCK; else f(b)).
    Why: XLA:CPU runs the products of a small matrix with a few columns slower than that
    many matrix-vector products, worst where the matrix is contracted over its rows (A^T b
    without a transposed copy): one thread, n = 138, k = 2, 13.2 us against 1.0 us a
    column; a kept L^-1's solve 14.1 us against 6.7 us by columns (the 2D box path's
    tracking, interleaved runs: 1.19 / 1.30 s -> 1.16 / 1.10 s). Not for large matrices,
    which each column would stream from memory again: at n = 2,400 (the 10^3 cube, three
    columns) the kept control loop took 0.18-0.20 s a step by columns against 0.16-0.18 s
    (runs interleaved)."""
    if b.shape[0] > TRIANGULAR_BLOCK or b.shape[1] == 1:
        return f(b)
    return jnp.concatenate([f(b[:, j:j + 1]) for j in range(b.shape[1])], axis=1)


def _block_edges(n):
    return list(range(0, n, TRIANGULAR_BLOCK)) + [n]


def factor_blocks(L):
    """The Cholesky factor L (n, n) as the row blocks of U = L^T (TRIANGULAR_BLOCK rows
    each, every one its own array, held flat as ``DenseState`` holds its matrices):
    U_i = L[:, a:c]^T, a column panel of L.

    Why separate arrays: a product with a slice of L taken inside jit ran ~8x slower than
    the same product with the slice held as an array (XLA:CPU, n = 2,400), so the blocks are
    cut once per factorisation instead of at every solve. Why column panels of L: LAPACK
    leaves L column-major, where a panel is contiguous and its transpose is row-major with
    no copy (row blocks of L were copied at every solve inside a loop: see ``DenseState``)."""
    edges = _block_edges(L.shape[0])
    return jax.lax.optimization_barrier(tuple(L[:, a:c].T.ravel() for a, c in zip(edges[:-1], edges[1:])))


def blocked_inverses(blocks):
    """Inverses of the diagonal blocks of L given as ``factor_blocks``: (m, B, B) with
    B = TRIANGULAR_BLOCK, L_ii^-1; the last block's in the top left corner of its slot (zeros
    elsewhere). Formed once per factorisation (m small triangular solves, ~n B^2 flops)."""
    B = TRIANGULAR_BLOCK
    if len(blocks) == 1:   # one block: solved with L itself (``triangular_pair``)
        return jnp.zeros((0, B, B), blocks[0].dtype)
    out = []
    n = math.isqrt(sum(Ui.size for Ui in blocks))
    for i, Ui in enumerate(blocks):
        Ui = Ui.reshape(-1, n)
        a, c = i * B, i * B + Ui.shape[0]
        inv = _lower_solve(Ui[:, a:c].T, jnp.eye(c - a, dtype=Ui.dtype))   # one_at_a_time: see there
        out.append(jnp.pad(inv, ((0, B - (c - a)), (0, B - (c - a)))))
    return jnp.stack(out)


def triangular_pair(blocks, Dinv, b):
    """x = L^-T L^-1 b (K^-1 b for K = L L^T) for b (n, k), L given as ``factor_blocks``
    (U_i, the row blocks of L^T), by block substitution in which every operation is a
    product with a block U_i or a diagonal block's inverse (``blocked_inverses``; U's lower
    triangle is zero). Why: XLA's CPU triangular solve (with L an argument, as in a solver
    state) is several times slower than a product with the same matrix: at n = 2,400, one
    right-hand side, same run (load average 6), cho_solve 89 ms, this 12 ms; cutting the
    blocks and inverting the diagonal ones, once per factorisation, 21 ms (the Cholesky
    factorisation ~1.5 s there).

    A single block (n <= TRIANGULAR_BLOCK) is solved by LAPACK's triangular solves with L
    itself, and has no inverse (``blocked_inverses``): inverting it cost 2.7x its Cholesky
    factorisation (n = 192, the needle phantom: 0.65 against 0.24 ms), and a solve with two
    right-hand sides took 0.08 ms against 0.11 ms by the inverse."""
    B = TRIANGULAR_BLOCK
    n = b.shape[0]
    blocks = [Ui.reshape(-1, n) for Ui in blocks]
    if len(blocks) == 1:
        return _upper_pair(blocks[0], b)
    contract_rows = (((0,), (0,)), ((), ()))
    r = b
    y = []
    for i, Ui in enumerate(blocks):             # L y = b by columns of L (U_i^T): once y_i is
        a, c = i * B, i * B + Ui.shape[0]       # known, it leaves the later right-hand sides
        yi = Dinv[i, :c - a, :c - a] @ r[a:c]
        r = r - jax.lax.dot_general(Ui, yi, contract_rows)   # (U_i is zero left of block i;
        y.append(yi)                                          # block i of r is not read again)
    x = jnp.zeros_like(b)
    for i in reversed(range(len(blocks))):      # U x = y by rows of U: x's later blocks are
        Ui = blocks[i]                          # known, its block i and earlier ones still zero
        a, c = i * B, i * B + Ui.shape[0]
        xi = jax.lax.dot_general(Dinv[i, :c - a, :c - a], y[i] - Ui @ x, contract_rows)
        x = x.at[a:c].set(xi)
    return x


def lowest_modes(K, k: int = 1):
    """The k lowest eigenpairs of a dense symmetric K_ff (n, n): (eigenvalues (k,) ascending,
    modes (n, k) orthonormal columns). Where the smallest eigenvalue is <= 0 the equilibrium is
    not stable and its column 0 is the critical (buckling) mode. A full ``eigh`` (O(n^3), a few
    Cholesky factorisations' worth): small dense systems, once per critical point."""
    n = K.shape[0]
    if not 1 <= k <= n:
        raise ValueError(f"k must lie in 1..{n} (the size of K), got {k}")
    lam, vecs = jnp.linalg.eigh(0.5 * (K + K.T))   # symmetrised: assembly round-off is not physics
    return lam[:k], vecs[:, :k]


def one_at_a_time(factorise):
    """``factorise`` (a LAPACK call on one matrix: a factorisation or a triangular solve)
    with a batching rule that runs the members of a vmapped batch one after another
    (``lax.map``), each an unbatched LAPACK call.

    Why: jaxlib 0.10's batched CPU LAPACK kernels split the batch over XLA's intra-op thread
    pool and block the calling pool thread until the pieces are done (``ParallelBatchMap``).
    XLA runs independent operations side by side on that pool, so two batched LAPACK calls
    at once (the Cholesky and the LU of a vmapped DenseSolver, or the triangular solves of
    its two branches: ``lapack_dtrsm_ffi``, seen in gdb in a hung vmapped needle sweep) can
    occupy every pool thread (two on a 2-core machine) with waiting, and nothing is left to
    run the pieces: a deadlock
    (tests/test_threads.py keeps the reduced pattern; experiments/vmap_deadlock.py measures
    it). Unbatched calls never wait on the pool.

    Only on CPU: elsewhere (GPU) the batch goes to the native batched factorisation in one
    call (``lax.platform_dependent``), where a member-by-member loop would serialise the
    batch (measured on an H100, 80 phantom configurations: the vmapped sweep's time grew
    linearly with the batch)."""
    batched = jax.custom_batching.custom_vmap(factorise)

    @batched.def_vmap
    def _rule(axis_size, in_batched, *args):
        args = tuple(a if b else jnp.broadcast_to(a, (axis_size,) + a.shape) for a, b in zip(args, in_batched))
        out = jax.lax.platform_dependent(*args, cpu=lambda *xs: jax.lax.map(lambda x: batched(*x), xs),
                                         default=jax.vmap(factorise))
        return out, jax.tree.map(lambda _: True, out)

    return batched


_cholesky = one_at_a_time(lambda K: jnp.linalg.cholesky(K))


def _usable(L):
    """Whether a Cholesky factor exists (LAPACK's failure leaves NaN or a non-positive pivot)."""
    return jnp.all(jnp.isfinite(L)) & jnp.all(jnp.diagonal(L) > 0)


def _single_else_double(K):
    L = jnp.linalg.cholesky(K.astype(jnp.float32))
    # single precision could not factorise it: let double decide (near a critical point)
    return jax.lax.cond(_usable(L), lambda: L, lambda: jnp.linalg.cholesky(K).astype(jnp.float32))


# per member under vmap on CPU, so the cond stays a branch there (a vmapped cond is a select:
# every member would pay for the double factorisation too)
_mixed_cholesky = one_at_a_time(_single_else_double)
_lu_solve = one_at_a_time(lambda K, b: jax.scipy.linalg.lu_solve(jax.scipy.linalg.lu_factor(K), b))
_lower_solve = one_at_a_time(lambda L, b: jax.lax.linalg.triangular_solve(L, b, left_side=True, lower=True))
# x = U^-1 U^-T b with U = L^T upper triangular (K = U^T U)
_upper_pair = one_at_a_time(lambda U, b: jax.lax.linalg.triangular_solve(
    U, jax.lax.linalg.triangular_solve(U, b, left_side=True, lower=False, transpose_a=True),
    left_side=True, lower=False))


@dataclass(frozen=True)
class DenseSolver:
    """Dense Cholesky of K_ff (LU where it is not positive definite): small systems. Both
    factorisations run one batch member at a time under vmap (``one_at_a_time``).

    A solve is block substitution with the inverses of L's diagonal blocks, kept with the
    factorisation (``triangular_pair``: matrix products only, ~7x faster than XLA's CPU
    triangular solves at n = 2,400). ``inverse=True`` keeps all of L^-1 instead, so that a
    solve is two matrix-vector products: for a factorisation reused over many solves (the
    chord corrections and Jacobians of a control loop). Measured at n = 2,400 (one thread):
    the two products 3.5 ms; forming L^-1 costs ~3 Cholesky factorisations (0.56 s against
    0.2 s).

    ``mixed=True`` factorises in single precision and refines every solve in double
    (``REFINEMENTS`` steps x <- x + M^-1 (b - K x) with the double K_ff; LAPACK's dsposv
    idea): a single-precision Cholesky takes half the time (n = 2,400, one thread: 75 ms
    against 168 ms) and its triangular solves move half the bytes, while the refined solve
    keeps double accuracy wherever cond(K_ff) eps_single << 1 (the 10^3 cube: cond 373, each
    step cuts the residual ~1e-6: two give 1e-12). Where the single-precision factorisation
    fails, K_ff is factorised in double (near a critical point, where eps_single no longer
    resolves the smallest eigenvalue); its inertia is then the double one. An eigenvalue of
    K_ff within ~n eps_single |K_ff| of zero on the positive side of a single-precision
    factorisation is not resolved: stability studies near critical points keep the default
    ``mixed=False`` (``Model(precision="double")``)."""

    name: str = "dense"
    inverse: bool = False
    mixed: bool = False
    tight_rtol = None     # solves are exact: no iteration to stop early (see SparseSolver)

    def matrix(self, ops, blocks):
        return dense_tangent(ops, blocks)

    def factor(self, K):
        """Cholesky factor of K_ff in the factorisation's precision, and whether it exists."""
        L = _mixed_cholesky(K) if self.mixed else _cholesky(K)
        return L, _usable(L)

    def init(self, ops, blocks) -> DenseState:
        return self.factorise(dense_tangent(ops, blocks))

    def factorise(self, K) -> DenseState:
        """The state of a dense K_ff (n, n) given as a matrix."""
        L, spd = self.factor(K)
        if not self.inverse:
            rows = factor_blocks(L)
            return DenseState(K.ravel(), spd, jnp.zeros((0,), L.dtype), rows, blocked_inverses(rows))
        eye = jnp.eye(K.shape[0], dtype=L.dtype)
        # not positive definite (past a critical point): K^-1 itself, by LU, in its place
        Linv = jax.lax.cond(spd, lambda: _lower_solve(L, eye),
                            lambda: _lu_solve(K, eye.astype(K.dtype)).astype(L.dtype))
        return DenseState(K.ravel(), spd, Linv.ravel(), (), jnp.zeros((0, 0, 0), L.dtype))

    def empty(self, ops, dtype) -> DenseState:
        n = ops.free.shape[0] * ops.f_ext.shape[1]
        z = jnp.zeros(n * n, dtype)
        fdtype = jnp.float32 if self.mixed else dtype
        if self.inverse:
            return DenseState(z, jnp.array(False), jnp.zeros(n * n, fdtype), (), jnp.zeros((0, 0, 0), fdtype))
        edges = _block_edges(n)
        rows = tuple(jnp.zeros(((c - a) * n,), fdtype) for a, c in zip(edges[:-1], edges[1:]))
        inverses = len(rows) if len(rows) > 1 else 0   # as ``blocked_inverses`` makes them
        return DenseState(z, jnp.array(False), jnp.zeros((0,), fdtype), rows,
                          jnp.zeros((inverses, TRIANGULAR_BLOCK, TRIANGULAR_BLOCK), fdtype))

    def solve(self, state: DenseState, rhs):
        n = state.K.shape[0]
        b = rhs.reshape(n, -1)
        if self.inverse:
            def apply(r):
                # L^-T y as a contraction over L^-1's rows: ``Linv.T @ y`` copied the
                # transpose first (32 ms against 3 ms for one right-hand side, n = 2,400).
                # No LU branch: it made XLA copy K into LAPACK's layout at every call
                y = state.Linv @ r
                x = jax.lax.dot_general(state.Linv, y, (((0,), (0,)), ((), ())))
                return jnp.where(state.spd, x, y)
            return self._refined(lambda r: by_columns(apply, r), state.K, b).reshape(rhs.shape)
        chol = lambda: self._refined(lambda r: triangular_pair(state.rows, state.Dinv, r), state.K, b)
        lu = lambda: _lu_solve(state.K, b)
        x = jax.lax.cond(state.spd, chol, lu)   # under vmap: both, then a select
        return x.reshape(rhs.shape)

    def _refined(self, apply, K, b):
        """``apply`` (an approximate K^-1 in the factorisation's precision) to b; with
        ``mixed``, then refined in b's precision against K (``REFINEMENTS`` steps)."""
        if not self.mixed:
            return apply(b)
        return refine(lambda r: apply(r.astype(jnp.float32)).astype(b.dtype), lambda x: K @ x, b, REFINEMENTS)

    def stability(self, state: DenseState):
        return jnp.where(state.spd, Stability.STABLE, Stability.UNSTABLE)

    def negative_eigenvalues(self, state: DenseState):
        """Number of negative eigenvalues of K_ff: 0 where the Cholesky factorisation
        succeeded, else counted from its eigenvalues (only past a critical point)."""
        count = lambda: jnp.sum(jnp.linalg.eigvalsh(state.K) < 0).astype(jnp.int64)
        return jax.lax.cond(state.spd, lambda: jnp.zeros((), jnp.int64), count)

    def newton_solve(self, state, ops, blocks, rhs, rtol=None):
        """Exact: the current tangent is factorised (``state`` and ``rtol`` are not needed)."""
        new = self.init(ops, blocks)
        return self.solve(new, rhs), new, self.stability(new)


# ------------------------------------------------------------------------------ sparse
class SparseState(NamedTuple):
    handle: jax.Array   # () int64 key of the host factorisation (0: none)
    inertia: jax.Array  # () int64 negative eigenvalues of K_ff; sparse.UNKNOWN/FAILED/NONE
    blocks: jax.Array   # (P, d, d) the tangent it factorises (to make it again if evicted)


def _sparse_stability(inertia):
    return jnp.where(inertia == 0, Stability.STABLE,
                     jnp.where(inertia > 0, Stability.UNSTABLE, Stability.UNKNOWN))


@dataclass(frozen=True, eq=False)
class SparseSolver:
    """Sparse path for large systems: the saddle-point form of the same transformation,

        [K  C^T] [dd]   [r]
        [C   0 ] [l ] = [0],   C dd = 0  <=>  dd = T du_f,

    whose free part solves T^T K T du_f = r exactly, on the host (jax.pure_callback, so it
    runs inside jit and while-loops): symmetric indefinite factorisations (PARDISO or
    SuperLU), reused as conjugate-gradient preconditioners while they work (see
    jaxrkpm.sparse). ``system`` is immutable; the factorisations are addressed by the
    handles in the state."""

    system: Any           # jaxrkpm.sparse.SaddlePointSystem
    name: str = "sparse"

    @property
    def tight_rtol(self) -> float:
        """CG's relative residual where ``newton_solve`` is given no other (None for the
        direct solvers, whose solves are exact)."""
        return self.system.cg_rtol

    def matrix(self, ops, blocks):
        return blocks  # the factorisation happens on the host

    @property
    def _pool(self):
        return sparse.pool(self.system)

    def init(self, ops, blocks) -> SparseState:
        i64 = jax.ShapeDtypeStruct((), jnp.int64)
        h, neg = host_callback(self._pool.init, (i64, i64), blocks)
        return SparseState(h, neg, blocks)

    def empty(self, ops, dtype) -> SparseState:
        P, d = ops.pair_i.shape[0], ops.f_ext.shape[1]
        return SparseState(jnp.zeros((), jnp.int64), jnp.asarray(sparse.NONE, jnp.int64),
                           jnp.zeros((P, d, d), dtype))

    def solve(self, state: SparseState, rhs):
        return host_callback(self._pool.solve, jax.ShapeDtypeStruct(rhs.shape, rhs.dtype),
                                 state.handle, state.blocks, rhs)

    def stability(self, state: SparseState):
        return _sparse_stability(state.inertia)

    def negative_eigenvalues(self, state: SparseState):
        """Number of negative eigenvalues of K_ff: the factorisation's inertia (-1: unknown)."""
        return jnp.maximum(state.inertia, -1).astype(jnp.int64)

    def newton_solve(self, state: SparseState, ops, blocks, rhs, rtol=None):
        """CG with the current tangent preconditioned by the held factorisation while it is
        positive definite and CG converges (to ``rtol``, default the system's tight cg_rtol;
        no negative curvature met counts as stable), else a new factorisation."""
        rtol = jnp.asarray(self.system.cg_rtol if rtol is None else rtol, rhs.dtype)
        i64 = jax.ShapeDtypeStruct((), jnp.int64)
        out = (jax.ShapeDtypeStruct(rhs.shape, rhs.dtype), i64, i64, jax.ShapeDtypeStruct((), jnp.bool_))
        x, h, neg, reused = host_callback(self._pool.newton_solve, out, state.handle, state.inertia,
                                              state.blocks, blocks, rhs, rtol)
        new = SparseState(h, neg, jnp.where(reused, state.blocks, blocks))
        return x, new, self.stability(new)


# ------------------------------------------------------------------------------ krylov
class KrylovState(NamedTuple):
    handle: jax.Array      # () int64 key of the host multigrid hierarchy (0: none)
    pre_blocks: jax.Array  # (P, d, d) the tangent the hierarchy was built from (to build it again)
    blocks: jax.Array      # (P, d, d) the tangent K_ff is made of (the matrix solved)
    outcome: jax.Array     # () int64 krylov.KrylovStatus of the last CG solve


@dataclass(frozen=True, eq=False)
class KrylovSolver:
    """Newton-Krylov for large systems: CG on K_ff = T^T K T with the assembled tangent,
    preconditioned by an algebraic multigrid hierarchy built rarely (``jaxrkpm.krylov``), on
    the host through jax.pure_callback (CPU). No factorisation: stability is inferred from CG
    (converged without negative curvature: STABLE; negative curvature met: UNSTABLE; not
    converged: FAILED, which ends the Newton attempt with Status.LINEAR_SOLVE)."""

    system: Any           # jaxrkpm.krylov.KrylovSystem
    name: str = "krylov"

    @property
    def tight_rtol(self) -> float:
        """CG's relative residual where ``newton_solve`` is given no other."""
        return self.system.rtol

    def matrix(self, ops, blocks):
        return blocks

    @property
    def _pool(self):
        return krylov.pool(self.system)

    def init(self, ops, blocks) -> KrylovState:
        i64 = jax.ShapeDtypeStruct((), jnp.int64)
        h, st = host_callback(self._pool.init, (i64, i64), blocks)
        return KrylovState(h, blocks, blocks, st)

    def empty(self, ops, dtype) -> KrylovState:
        P, d = ops.pair_i.shape[0], ops.f_ext.shape[1]
        z = jnp.zeros((P, d, d), dtype)
        return KrylovState(jnp.zeros((), jnp.int64), z, z, jnp.asarray(krylov.KrylovStatus.NONE, jnp.int64))

    def solve(self, state: KrylovState, rhs):
        """K_ff x = rhs to the system's rtol (NaN where CG does not converge)."""
        return host_callback(self._pool.solve, jax.ShapeDtypeStruct(rhs.shape, rhs.dtype),
                                 state.handle, state.pre_blocks, state.blocks, rhs)

    def stability(self, state: KrylovState):
        o = state.outcome
        return jnp.where(o == krylov.KrylovStatus.CONVERGED, Stability.STABLE,
                         jnp.where(o == krylov.KrylovStatus.NEGATIVE_CURVATURE, Stability.UNSTABLE,
                                   jnp.where(o == krylov.KrylovStatus.MAX_ITERATIONS, Stability.FAILED,
                                             Stability.UNKNOWN)))

    def negative_eigenvalues(self, state: KrylovState):
        """0 where CG inferred K_ff positive definite, else -1 (CG does not count them)."""
        return jnp.where(state.outcome == krylov.KrylovStatus.CONVERGED, 0, -1).astype(jnp.int64)

    def newton_solve(self, state: KrylovState, ops, blocks, rhs, rtol=None):
        """CG with the current tangent to ``rtol`` (the inexact-Newton forcing term; default
        the system's rtol), preconditioned by the kept hierarchy (rebuilt when CG slows)."""
        rtol = jnp.asarray(self.system.rtol if rtol is None else rtol, rhs.dtype)
        i64 = jax.ShapeDtypeStruct((), jnp.int64)
        out = (jax.ShapeDtypeStruct(rhs.shape, rhs.dtype), i64, i64, jax.ShapeDtypeStruct((), jnp.bool_))
        x, h, st, rebuilt = host_callback(self._pool.newton_solve, out, state.handle, state.pre_blocks,
                                              blocks, rhs, rtol)
        new = KrylovState(h, jnp.where(rebuilt, blocks, state.pre_blocks), blocks, st)
        return x, new, self.stability(new)


# ------------------------------------------------------------------------ quasi-Newton
class QuasiNewtonState(NamedTuple):
    base: Any         # the wrapped solver's factorisation (of K_ff at some earlier state)
    S: jax.Array      # (m, n) steps s_k of the secant pairs (newest last)
    Y: jax.Array      # (m, n) residual changes y_k = r(u + s_k) - r(u) at one load
    count: jax.Array  # () pairs held (<= m)


@dataclass(frozen=True)
class QuasiNewton:
    """A kept factorisation of K_ff made better by secant pairs: L-BFGS (Nocedal & Wright,
    Algorithm 7.4, the two-loop recursion) with the factorisation's inverse as the initial
    inverse Hessian H_0. So chord corrections with a factorisation of an earlier state
    converge superlinearly, and the factorisation serves many more control steps before it
    must be made again; the approximation H stays symmetric (and positive definite where
    the base is and every pair has s.y > 0), so it also serves the implicit Jacobian's
    transposable solve.

    ``update(state, s, y)`` adds the pair (s, y) (the oldest one drops out once ``memory``
    are held; pairs with too little curvature s.y are skipped); ``init`` factorises anew
    and forgets the pairs. Stability and inertia are the base factorisation's."""

    base: Any = DenseSolver(inverse=True)
    memory: int = 8
    tight_rtol = None     # its solves are direct (the base's and the two-loop recursion)

    @property
    def name(self) -> str:
        return "quasi-newton"

    def matrix(self, ops, blocks):
        return self.base.matrix(ops, blocks)

    def _fresh(self, base_state, ops, dtype) -> QuasiNewtonState:
        n = ops.free.shape[0] * ops.f_ext.shape[1]
        z = jnp.zeros((self.memory, n), dtype)
        return QuasiNewtonState(base_state, z, z, jnp.zeros((), jnp.int32))

    def init(self, ops, blocks) -> QuasiNewtonState:
        return self._fresh(self.base.init(ops, blocks), ops, blocks.dtype)

    def empty(self, ops, dtype) -> QuasiNewtonState:
        return self._fresh(self.base.empty(ops, dtype), ops, dtype)

    def solve(self, state: QuasiNewtonState, rhs):
        n = state.S.shape[1]
        q = rhs.reshape(n, -1)
        sy = jnp.sum(state.S * state.Y, axis=1)
        held = jnp.arange(self.memory) >= self.memory - state.count    # newest pairs at the end
        rho = jnp.where(held, 1.0 / jnp.where(held, sy, 1.0), 0.0)

        def backward(q, k):          # newest to oldest
            a = rho[k] * (state.S[k] @ q)
            return q - state.Y[k][:, None] * a[None], a

        q, alpha = jax.lax.scan(backward, q, jnp.arange(self.memory)[::-1])
        x = self.base.solve(state.base, q.reshape(rhs.shape)).reshape(n, -1)

        def forward(x, ka):          # oldest to newest
            k, a = ka
            b = rho[k] * (state.Y[k] @ x)
            return x + state.S[k][:, None] * (a - b)[None], None

        x, _ = jax.lax.scan(forward, x, (jnp.arange(self.memory), alpha[::-1]))
        return x.reshape(rhs.shape)

    def update(self, state: QuasiNewtonState, s, y, accept=True) -> QuasiNewtonState:
        """With the secant pair (s, y) added (y = r(u + s) - r(u) at one load) where
        ``accept``, unless its curvature s.y is not clearly positive (then H would lose
        positive definiteness). A select, not a lax.cond: a cond over the whole state made
        XLA copy the factorisation (3 n^2 doubles) at every correction."""
        s, y = s.reshape(-1), y.reshape(-1)
        good = accept & (jnp.sum(s * y) > 1e-12 * jnp.linalg.norm(s) * jnp.linalg.norm(y))
        S = jnp.where(good, jnp.roll(state.S, -1, axis=0).at[-1].set(s), state.S)
        Y = jnp.where(good, jnp.roll(state.Y, -1, axis=0).at[-1].set(y), state.Y)
        return QuasiNewtonState(state.base, S, Y, jnp.minimum(state.count + good, self.memory))

    def stability(self, state: QuasiNewtonState):
        return self.base.stability(state.base)

    def negative_eigenvalues(self, state: QuasiNewtonState):
        return self.base.negative_eigenvalues(state.base)

    def newton_solve(self, state, ops, blocks, rhs, rtol=None):
        """A Newton step with the current tangent: a new factorisation, no pairs."""
        x, base, stab = self.base.newton_solve(state.base, ops, blocks, rhs, rtol)
        return x, self._fresh(base, ops, blocks.dtype), stab
