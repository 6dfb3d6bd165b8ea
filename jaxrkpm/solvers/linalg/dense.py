"""The dense linear solver: Cholesky (LU past a critical point) of K_ff, in double or mixed
precision, with explicit state (in the manner of lineax).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp

from ..iterate import when
from .base import LinearSolver, Stability
from .refinement import refine


class DenseState(NamedTuple):
    """A dense factorisation of K_ff. Its matrices are held flat (row-major by construction):
    held as (n, n) arrays inside a Newton or control loop, XLA gave the loop's carry LAPACK's
    column-major layout and every solve then copied them to the row-major layout of its
    products (measured by ``experiments/bench_cube3d.py``'s kept control loop)."""
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


def by_columns(f, b, block: int):
    """f(b) for b (n, k) as k calls on single columns where n <= ``block`` (else f(b)).
    Why: XLA:CPU runs the products of a small matrix with a few columns slower than that
    many matrix-vector products, worst where the matrix is contracted over its rows (A^T b
    without a transposed copy); not for large matrices, which each column would stream from
    memory again (both measured by ``experiments/bench_tracking.py`` and the kept control
    loop of ``experiments/bench_cube3d.py``)."""
    if b.shape[0] > block or b.shape[1] == 1:
        return f(b)
    return jnp.concatenate([f(b[:, j:j + 1]) for j in range(b.shape[1])], axis=1)


def _block_edges(n, block: int):
    return list(range(0, n, block)) + [n]


def factor_blocks(L, block: int):
    """The Cholesky factor L (n, n) as the row blocks of U = L^T (``block`` rows each, every
    one its own array, held flat as ``DenseState`` holds its matrices): U_i = L[:, a:c]^T, a
    column panel of L.

    Why separate arrays: a product with a slice of L taken inside jit ran several times slower
    than the same product with the slice held as an array (XLA:CPU), so the blocks are cut
    once per factorisation instead of at every solve. Why column panels of L: LAPACK leaves L
    column-major, where a panel is contiguous and its transpose is row-major with no copy."""
    edges = _block_edges(L.shape[0], block)
    return jax.lax.optimization_barrier(tuple(L[:, a:c].T.ravel() for a, c in zip(edges[:-1], edges[1:])))


def blocked_inverses(blocks, block: int):
    """Inverses of the diagonal blocks of L given as ``factor_blocks``: (m, B, B) with
    B = ``block``, L_ii^-1; the last block's in the top left corner of its slot (zeros
    elsewhere). Formed once per factorisation (m small triangular solves, ~n B^2 flops)."""
    B = block
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
    state) is several times slower than a product with the same matrix
    (``experiments/bench_cube3d.py``).

    A single block is solved by LAPACK's triangular solves with L itself, and has no inverse
    (``blocked_inverses``): for a small factor, inverting it costs more than its Cholesky
    factorisation (the needle phantom of ``experiments/bench_sweep.py``)."""
    n = b.shape[0]
    blocks = [Ui.reshape(-1, n) for Ui in blocks]
    if len(blocks) == 1:
        return _upper_pair(blocks[0], b)
    B = blocks[0].shape[0]
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

    Why: jaxlib's batched CPU LAPACK kernels split the batch over XLA's intra-op thread pool
    and block the calling pool thread until the pieces are done, so two batched LAPACK calls
    at once can occupy every pool thread with waiting: a deadlock (reproduced by
    ``experiments/vmap_deadlock.py``; ``tests/base/test_threads.py`` keeps the pattern).
    Unbatched calls never wait on the pool.

    Only on CPU: elsewhere (GPU) the batch goes to the native batched factorisation in one
    call (``lax.platform_dependent``), where a member-by-member loop would serialise the
    batch (``experiments/bench_sweep.py`` on a GPU)."""
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
    return when(~_usable(L), lambda: jnp.linalg.cholesky(K).astype(jnp.float32), L)


# per member under vmap on CPU; elsewhere ``when`` runs the double factorisation only while
# some member needs it (a vmapped cond is a select: every member would pay for it)
_mixed_cholesky = one_at_a_time(_single_else_double)

_lu_solve = one_at_a_time(lambda K, b: jax.scipy.linalg.lu_solve(jax.scipy.linalg.lu_factor(K), b))

_lower_solve = one_at_a_time(lambda L, b: jax.lax.linalg.triangular_solve(L, b, left_side=True, lower=True))

# x = U^-1 U^-T b with U = L^T upper triangular (K = U^T U)
_upper_pair = one_at_a_time(lambda U, b: jax.lax.linalg.triangular_solve(
    U, jax.lax.linalg.triangular_solve(U, b, left_side=True, lower=False, transpose_a=True),
    left_side=True, lower=False))


@dataclass(frozen=True)
class DenseSolver(LinearSolver):
    """Dense Cholesky of K_ff (LU where it is not positive definite): small systems. Both
    factorisations run one batch member at a time under vmap (``one_at_a_time``).

    A solve is block substitution with the inverses of L's diagonal blocks (``block`` rows
    each), kept with the factorisation (``triangular_pair``: matrix products only).
    ``inverse=True`` keeps all of L^-1 instead, so that a solve is two matrix-vector
    products: for a factorisation reused over many solves (the chord corrections and
    Jacobians of a control loop), at the price of forming L^-1 once.

    ``mixed=True`` factorises in single precision and refines every solve in double
    (``refinements`` steps x <- x + M^-1 (b - K x) with the double K_ff; LAPACK's dsposv
    idea): a single-precision Cholesky takes about half the time and its solves move half the
    bytes (``experiments/bench_cube3d.py --precision``), while the refined solve keeps double
    accuracy wherever cond(K_ff) eps_single << 1 (each step cuts the residual by about
    cond(K_ff) eps_single: two give ~1e-12 on the 10^3 cube). Where the single-precision
    factorisation fails, K_ff is factorised in double (near a critical point, where
    eps_single no longer resolves the smallest eigenvalue); its inertia is then the double
    one. An eigenvalue of K_ff within ~n eps_single |K_ff| of zero on the positive side of a
    single-precision factorisation is not resolved: stability studies near critical points
    keep the default ``mixed=False`` (``Model(precision="double")``)."""

    name: str = "dense"
    inverse: bool = False
    mixed: bool = False
    block: int = 256          # rows of L per block of the blocked triangular solves
    refinements: int = 2      # refinement steps of a mixed-precision solve
    modified_newton = True    # a factorisation serves later Newton iterations as it is
    branch_switching = True   # exact inertia, and small enough for the dense eigenpairs

    def factor(self, K):
        """Cholesky factor of K_ff in the factorisation's precision, and whether it exists."""
        L = _mixed_cholesky(K) if self.mixed else _cholesky(K)
        return L, _usable(L)

    def init(self, problem, blocks) -> DenseState:
        return self.factorise(problem.dense_tangent(blocks))

    def factorise(self, K) -> DenseState:
        """The state of a dense K_ff (n, n) given as a matrix."""
        L, spd = self.factor(K)
        if not self.inverse:
            rows = factor_blocks(L, self.block)
            return DenseState(K.ravel(), spd, jnp.zeros((0,), L.dtype), rows, blocked_inverses(rows, self.block))
        eye = jnp.eye(K.shape[0], dtype=L.dtype)
        # not positive definite (past a critical point): K^-1 itself, by LU, in its place
        Linv = when(~spd, lambda: _lu_solve(K, eye.astype(K.dtype)).astype(L.dtype), _lower_solve(L, eye))
        return DenseState(K.ravel(), spd, Linv.ravel(), (), jnp.zeros((0, 0, 0), L.dtype))

    def empty(self, problem, dtype) -> DenseState:
        n = problem.n_free * problem.dim
        z = jnp.zeros(n * n, dtype)
        fdtype = jnp.float32 if self.mixed else dtype
        if self.inverse:
            return DenseState(z, jnp.array(False), jnp.zeros(n * n, fdtype), (), jnp.zeros((0, 0, 0), fdtype))
        edges = _block_edges(n, self.block)
        rows = tuple(jnp.zeros(((c - a) * n,), fdtype) for a, c in zip(edges[:-1], edges[1:]))
        inverses = len(rows) if len(rows) > 1 else 0   # as ``blocked_inverses`` makes them
        return DenseState(z, jnp.array(False), jnp.zeros((0,), fdtype), rows,
                          jnp.zeros((inverses, self.block, self.block), fdtype))

    def solve(self, state: DenseState, rhs):
        n = state.K.shape[0]
        b = rhs.reshape(n, -1)
        if self.inverse:
            def apply(r):
                # L^-T y as a contraction over L^-1's rows: ``Linv.T @ y`` copied the
                # transpose first. No LU branch: it made XLA copy K into LAPACK's layout at
                # every call
                y = state.Linv @ r
                x = jax.lax.dot_general(state.Linv, y, (((0,), (0,)), ((), ())))
                return jnp.where(state.spd, x, y)
            return self._refined(lambda r: by_columns(apply, r, self.block), state.K, b).reshape(rhs.shape)
        x = self._refined(lambda r: triangular_pair(state.rows, state.Dinv, r), state.K, b)
        # LU only where K_ff is not positive definite; ``when``, not a cond: under vmap a cond
        # factorised every member's K by LU at every solve (a select of both sides), the
        # dearest operation of a lock-step Newton iteration, where ``when`` runs it only while
        # some member needs it (a member past a critical point)
        x = when(~state.spd, lambda: _lu_solve(state.K, b), x)
        return x.reshape(rhs.shape)

    def _refined(self, apply, K, b):
        """``apply`` (an approximate K^-1 in the factorisation's precision) to b; with
        ``mixed``, then refined in b's precision against K (``refinements`` steps)."""
        if not self.mixed:
            return apply(b)
        return refine(lambda r: apply(r.astype(jnp.float32)).astype(b.dtype), lambda x: K @ x, b, self.refinements)

    def stability(self, state: DenseState):
        return jnp.where(state.spd, Stability.STABLE, Stability.UNSTABLE)

    def negative_eigenvalues(self, state: DenseState):
        """Number of negative eigenvalues of K_ff: 0 where the Cholesky factorisation
        succeeded, else counted from its eigenvalues (only past a critical point)."""
        count = lambda: jnp.sum(jnp.linalg.eigvalsh(state.K) < 0).astype(jnp.int64)
        return jax.lax.cond(state.spd, lambda: jnp.zeros((), jnp.int64), count)

    def newton_solve(self, state, problem, blocks, rhs, rtol=None):
        """Exact: the current tangent is factorised (``state`` and ``rtol`` are not needed)."""
        new = self.init(problem, blocks)
        return self.solve(new, rhs), new, self.stability(new)
