"""Host-side sparse linear algebra of the Newton solver (large systems).

The constrained tangent system is the saddle-point form of the thesis transformation,

    [K  C^T] [dd]   [r]
    [C   0 ] [l ] = [0],      C dd = 0  <=>  dd = T du_f,

whose free part solves K_ff du_f = T^T K T du_f = r exactly. C = [D^nb D^b] (x) I is sparse
while T (through (D^b)^-1) is dense per essential set, so the saddle-point matrix is
factorised instead of K_ff. Its pattern, and the position of every tangent block entry in
it, are built once: each Newton iteration only writes the data array.

Two factorisations of the symmetric indefinite saddle-point matrix:

* ``pardiso`` (default where Intel MKL is installed: x86-64): PARDISO's supernodal LDL^T
  with Bunch-Kaufman pivoting, weighted matching and scaling (the zero multiplier block needs
  2x2 pivots), METIS ordering, on ``jaxrkpm.base.threads.sparse_threads()`` threads
  (``experiments/bench_cube3d_large.py``).
* ``superlu``: SciPy's SuperLU with static pivoting on a geometric nested-dissection order
  in which each essential particle's multipliers follow its own coefficients (every
  multiplier pivot is preceded by the coefficient pivot it constrains). Portable, but it
  fills several times more in 3D.

JAX-native alternatives were measured on a 14^3 cube's tangent (issue 20): ``sparsax``
(SuiteSparse through XLA FFI, no Python callback) cannot factorise the indefinite
saddle-point matrix with CHOLMOD (SPD only), and its KLU LU of it did not finish; CHOLMOD of
the SPD free-free block K_nn was slower than PARDISO on the same matrix, and K_nn alone is not
K_ff (it would need CG for the transformation, as ``jaxrkpm.solvers.linalg.multigrid`` does).
``klujax`` is the same KLU. So PARDISO stays, through the callback.

Factorisations are reused: the last positive definite one preconditions a conjugate-gradient
solve of K_ff x = r (matrix-vector products with the current K and T); only when CG stalls or
meets negative curvature is the current matrix factorised again. The factorisation's inertia
gives stability: its negative eigenvalues minus the number of constraints is the number of
negative eigenvalues of K_ff (Haynsworth); where pivots were perturbed or permuted the
inertia is reported unknown, never as positive definite.

Which factorisation a Newton step uses is explicit solver state (``jaxrkpm.solvers.linalg``): a
handle into a ``FactorPool`` together with the tangent it factorises. The system itself is
immutable, so it can sit in the static configuration of jitted functions.
"""
from __future__ import annotations

import ctypes
import glob
import os
import sys
import threading
import time
import weakref
from contextlib import contextmanager

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ...base.threads import sparse_threads
from ...discretise.constraints import HostElimination
from .base import LinearStats
from .refinement import preconditioned_cg, refine


class HostWork:
    """The host-side work of one call into a pool (a factorisation, a Newton step's solve),
    counted as it happens and handed back to the solver state as ``LinearStats``: the
    statistics of a solve are those its own calls returned, never a module-wide tally."""

    def __init__(self):
        self.counts = dict.fromkeys(LinearStats._fields, 0)

    def add(self, **counts):
        for k, v in counts.items():
            self.counts[k] += v

    @contextmanager
    def timed(self, field: str):
        """Adds the seconds the block takes to ``field``."""
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.counts[field] += time.perf_counter() - t0

    @staticmethod
    def of(work: "HostWork | None") -> "HostWork":
        """``work``, or a new ledger where a caller keeps none (a call outside a pool)."""
        return HostWork() if work is None else work

    def stats(self) -> LinearStats:
        """As host scalars (int64 counts, float64 seconds), for a callback's result."""
        return LinearStats(*(np.float64(v) if k.endswith("_s") else np.int64(v) for k, v in self.counts.items()))


def nested_dissection(X: np.ndarray, indptr: np.ndarray, indices: np.ndarray, leaf: int = 64) -> np.ndarray:
    """Fill-reducing order of n nodes with coordinates X (n, dim) and the symmetric
    adjacency (indptr, indices) (CSR): recursive median bisection along the longest extent;
    the nodes of the upper half adjacent to the lower half form the separator, numbered last."""
    n = X.shape[0]
    mark = np.zeros(n, bool)
    parts = []

    def rec(nodes):
        if len(nodes) <= leaf:
            parts.append(nodes)
            return
        x = X[nodes]
        ax = int(np.argmax(x.max(0) - x.min(0)))
        lower = x[:, ax] < np.median(x[:, ax])
        if lower.all() or not lower.any():
            parts.append(nodes)
            return
        lo, hi = nodes[lower], nodes[~lower]
        mark[lo] = True
        starts, stops = indptr[hi], indptr[hi + 1]
        lens = stops - starts
        flat = np.repeat(starts - np.cumsum(np.r_[0, lens[:-1]]), lens) + np.arange(lens.sum())
        owner = np.repeat(np.arange(len(hi)), lens)
        touch = np.zeros(len(hi), bool)
        touch[owner[mark[indices[flat]]]] = True
        mark[lo] = False
        rec(lo)
        rec(hi[~touch])
        parts.append(hi[touch])

    rec(np.arange(n))
    return np.concatenate(parts)


MKL_DOMAIN_PARDISO = 4     # mkl_domain_set_num_threads' domain of PARDISO (mkl_service.h)


def _mkl_runtime():
    """Intel MKL's single dynamic library (the ``mkl`` wheel puts it under sys.prefix/lib),
    or None."""
    names = sorted(glob.glob(os.path.join(sys.prefix, "lib", "libmkl_rt.so*")), key=len)
    for path in names + ["libmkl_rt.so.2", "libmkl_rt.so"]:
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        lib.MKL_Set_Interface_Layer(0)  # LP64: 32-bit integers, whatever MKL_INTERFACE_LAYER says
        # PARDISO's own threads, whatever MKL_NUM_THREADS (jaxrkpm.base.threads) says for BLAS
        lib.MKL_Domain_Set_Num_Threads(ctypes.c_int(sparse_threads()), ctypes.c_int(MKL_DOMAIN_PARDISO))
        return lib
    return None


_MKL = _mkl_runtime()
PARDISO_ERRORS = {-1: "input inconsistent", -2: "not enough memory", -3: "reordering problem",
                  -4: "zero pivot, numerical factorization or iterative refinement problem",
                  -5: "unclassified (internal) error", -6: "reordering failed",
                  -7: "diagonal matrix is singular", -8: "32-bit integer overflow problem",
                  -9: "not enough memory for OOC", -10: "error opening OOC files",
                  -11: "read/write error with OOC files"}


class FactorisationError(RuntimeError):
    pass


class PardisoLDL:
    """MKL PARDISO, real symmetric indefinite (mtype -2), on the lower triangle in CSC (= the
    upper triangle in CSR, as PARDISO wants it), zero-based. The ordering and symbolic
    analysis are done on the first factorisation and reused (the pattern never changes).
    ``single``: factorise and solve in single precision (iparm(28) = 1): the caller refines
    (``SaddlePointSystem.exact``) or uses it as a preconditioner."""

    name = "pardiso"
    lower = True        # stores the lower triangle only
    reorders = True     # needs no ordering of ours
    has_single = True   # can factorise in single precision

    def __init__(self, n, indptr, indices, single=False):
        self.n = n
        self.dtype = np.float32 if single else np.float64
        self.indptr = np.ascontiguousarray(indptr, np.int32)
        self.indices = np.ascontiguousarray(indices, np.int32)
        self.pt = np.zeros(64, np.int64)            # PARDISO's opaque handle
        self.iparm = np.zeros(64, np.int32)
        for i, v in {1: 1, 2: 2, 10: 8, 11: 1, 13: 1, 18: -1, 21: 1, 35: 1}.items():
            self.iparm[i - 1] = v   # (1-based as in the manual) non-default; METIS; pivot
            # perturbation 1e-8; scaling and weighted matching; report fill; Bunch-Kaufman;
            # zero-based indices
        self.iparm[27] = int(single)
        self.analysed = False
        self._data = None
        # free PARDISO's memory with this object (phase -1)
        weakref.finalize(self, PardisoLDL._release, self.pt, self.iparm, n)

    @staticmethod
    def _call(pt, iparm, n, phase, data, indptr, indices, b, x):
        err = ctypes.c_int32(0)
        i32 = ctypes.POINTER(ctypes.c_int32)
        nrhs = 1 if b is None else b.shape[1]
        ptr = lambda a: None if a is None else a.ctypes.data_as(ctypes.c_void_p)
        _MKL.pardiso(pt.ctypes.data_as(ctypes.c_void_p), ctypes.byref(ctypes.c_int32(1)),
                     ctypes.byref(ctypes.c_int32(1)), ctypes.byref(ctypes.c_int32(-2)),
                     ctypes.byref(ctypes.c_int32(phase)), ctypes.byref(ctypes.c_int32(n)),
                     ptr(data), ptr(indptr), ptr(indices), None, ctypes.byref(ctypes.c_int32(nrhs)),
                     iparm.ctypes.data_as(i32), ctypes.byref(ctypes.c_int32(0)), ptr(b), ptr(x),
                     ctypes.byref(err))
        return err.value

    @staticmethod
    def _release(pt, iparm, n):
        if pt.any():
            PardisoLDL._call(pt, iparm, n, -1, None, None, None, None, None)
            pt[:] = 0

    def _run(self, phase, b=None, x=None):
        err = self._call(self.pt, self.iparm, self.n, phase, self._data, self.indptr, self.indices, b, x)
        if err:
            raise FactorisationError(f"PARDISO phase {phase}: error {err} "
                                     f"({PARDISO_ERRORS.get(err, 'unknown')})")

    def factor(self, data):
        """Factorise; returns the number of negative eigenvalues of the saddle-point matrix
        (None: unknown, when pivots had to be perturbed)."""
        self._data = np.ascontiguousarray(data, self.dtype)
        if not self.analysed:
            self._run(11)
            self.analysed = True
        self._run(22)
        return None if self.iparm[13] > 0 else int(self.iparm[22])

    def solve(self, B):
        B = np.asfortranarray(B, self.dtype)
        X = np.zeros_like(B)
        self._run(33, B, X)
        return X.astype(np.float64, copy=False)

    def release(self):
        self._release(self.pt, self.iparm, self.n)
        self.analysed = False


class SuperLU:
    """SciPy's SuperLU with static (diagonal) pivoting on our nested-dissection order (full
    matrix in CSC; SymmetricMode)."""

    name = "superlu"
    lower = False
    reorders = False
    has_single = False

    def __init__(self, n, indptr, indices, single=False):
        if single:
            raise ValueError("SuperLU factorises in double precision only")
        self.n, self.indptr, self.indices = n, indptr, indices
        self.lu = None

    def factor(self, data):
        A = sp.csc_matrix((data, self.indices, self.indptr), shape=(self.n, self.n))
        try:
            self.lu = spla.splu(A, permc_spec="NATURAL", diag_pivot_thresh=0.0,
                                options=dict(SymmetricMode=True))
        except RuntimeError as e:
            raise FactorisationError(f"SuperLU: {e}") from None
        if not np.array_equal(self.lu.perm_r, self.lu.perm_c):
            return None                                 # pivoting happened: inertia unknown
        return int(np.count_nonzero(self.lu.U.diagonal() < 0))

    def solve(self, B):
        return self.lu.solve(np.asarray(B, np.float64))

    def release(self):
        self.lu = None


FACTORISATIONS = {"pardiso": PardisoLDL, "superlu": SuperLU}


def factoriser(name: str):
    """The factorisation class for ``name`` ("auto": PARDISO where Intel MKL loads, else
    SuperLU); a ValueError naming an unknown or unavailable one."""
    if name == "auto":
        name = "pardiso" if _MKL is not None else "superlu"
    if name not in FACTORISATIONS:
        raise ValueError(f"unknown factorisation {name!r}: choose 'auto', "
                         + ", ".join(repr(k) for k in FACTORISATIONS))
    if name == "pardiso" and _MKL is None:
        raise ValueError("factorisation='pardiso' needs Intel MKL (pip install mkl; x86-64 "
                         "only): use 'superlu'")
    return FACTORISATIONS[name]


def block_pattern(pair_i: np.ndarray, pair_j: np.ndarray, N: int):
    """(indptr, indices) of the block-sparse (BSR) matrix whose blocks are the particle pairs
    (pair_i, pair_j), which must be sorted by (i, j) and unique (as the model builds them):
    then the (P, d, d) pair blocks are its data as they are."""
    pair_i, pair_j = np.asarray(pair_i, np.int64), np.asarray(pair_j, np.int64)
    if np.any(np.diff(pair_i * N + pair_j) <= 0):
        raise ValueError("the particle pairs must be sorted by (i, j) and unique")
    return np.searchsorted(pair_i, np.arange(N + 1)).astype(np.int32), pair_j.astype(np.int32)


def lower_pattern(pair_i: np.ndarray, pair_j: np.ndarray, d: int, C):
    """The lower triangle, in CSC and the natural order, of the saddle-point matrix
    [K C^T; C 0] whose K has the (sorted, symmetric) particle-pair pattern (pair_i, pair_j)
    with (d, d) blocks: (indices, indptr, pos_K, take_K, template) as
    ``SaddlePointSystem._pattern`` gives them (take_K indexes the (P, d, d) blocks raveled).

    Built by arithmetic on the pairs, without sorting the entries: column c = j d + b holds,
    for each pair (j, i) with i >= j (in order of i), the rows i d + a (a >= b where i = j),
    then the rows of C's column c; each multiplier column holds its zero diagonal. Its
    entries are K[i d + a, j d + b], taken from the block of the pair (i, j). The general
    builder sorts int64 keys of every entry (about 10 arrays of P d^2 entries; GBs for a
    3D body); this one holds about 4 arrays of half that."""
    N = int(max(pair_i.max(), pair_j.max())) + 1 if len(pair_i) else 0
    pair_i, pair_j = np.asarray(pair_i, np.int64), np.asarray(pair_j, np.int64)
    key = pair_i * N + pair_j
    up = np.flatnonzero(pair_j >= pair_i)                      # pairs (j, i) with i >= j
    tp = np.searchsorted(key, pair_j[up] * N + pair_i[up])      # their transposes (i, j)
    j, i = pair_i[up], pair_j[up]
    first = np.searchsorted(j, np.arange(N))                   # each row's first upper pair
    if not np.array_equal(i[first], np.arange(N)):
        raise ValueError("every particle must pair with itself (the diagonal blocks)")
    rank = np.arange(len(up)) - first[j]                        # 0: the diagonal block
    u = np.bincount(j, minlength=N)
    n_dof = N * d
    Cc = sp.csc_matrix(C)
    nc = Cc.shape[0]
    b = np.arange(d)
    length = (u[:, None] * d - b[None]).ravel()                 # K entries of column j d + b
    count = np.concatenate([length + np.diff(Cc.indptr), np.ones(nc, np.int64)])
    indptr = np.concatenate([[0], np.cumsum(count)])
    nnz = int(indptr[-1])
    indices = np.empty(nnz, np.int32)
    template = np.zeros(nnz)
    take = np.full(nnz, -1, np.int64)      # K entry -> its index in the raveled blocks
    # K entries, one (b, a) plane at a time (arrays of the upper pairs' length only)
    for bb in range(d):
        start = indptr[j * d + bb]
        for a in range(d):
            sel = (rank > 0) | (a >= bb)
            pos = (start + np.where(rank == 0, a - bb, (d - bb) + (rank - 1) * d + a))[sel]
            indices[pos] = (i[sel] * d + a).astype(np.int32)
            take[pos] = tp[sel] * d * d + a * d + bb
    # C's entries after the K rows of each of its columns
    cpos = indptr[:-1][:n_dof] + length
    ccol = np.repeat(np.arange(n_dof), np.diff(Cc.indptr))
    crank = np.arange(Cc.nnz) - Cc.indptr[ccol]
    indices[cpos[ccol] + crank] = (Cc.indices + n_dof).astype(np.int32)
    template[cpos[ccol] + crank] = Cc.data
    # the multipliers' zero diagonal
    indices[indptr[n_dof:-1]] = np.arange(n_dof, n_dof + nc, dtype=np.int32)
    pos_K = np.flatnonzero(take >= 0)
    return indices, indptr.astype(np.int32), pos_K, take[pos_K], template


def block_matrix(blocks, indptr, indices) -> sp.bsr_matrix:
    """The tangent K (N d, N d) with the (P, d, d) pair ``blocks`` as its data (no copy)."""
    d = blocks.shape[-1]
    n = (len(indptr) - 1) * d
    return sp.bsr_matrix((np.asarray(blocks, np.float64), indices, indptr), shape=(n, n))


_executors: dict = {}           # worker count -> the thread pool of the product parts
_executors_lock = threading.Lock()


def _threads_pool(n: int):
    from concurrent.futures import ThreadPoolExecutor
    with _executors_lock:
        if n not in _executors:
            _executors[n] = ThreadPoolExecutor(n, thread_name_prefix="jaxrkpm-sparse")
        return _executors[n]


def row_parts_product(K: sp.bsr_matrix, threads: int | None = None, min_blocks: int = 1 << 16):
    """x -> K @ x with K's block rows cut into ``threads`` parts of about equal nonzeros,
    multiplied side by side (SciPy's sparse kernels release the GIL; the product is memory-
    bound, and two cores move about twice the bytes: ``experiments/bench_cube3d_large.py``).
    The parts are views of K's arrays (no copy). One part, the product as it is, where
    ``threads`` (default ``jaxrkpm.base.threads.sparse_threads()``) is 1 or K has fewer than
    ``min_blocks`` blocks (a product too short to share out among threads)."""
    threads = sparse_threads() if threads is None else threads
    nb = K.indptr.shape[0] - 1
    if threads <= 1 or K.indices.shape[0] < min_blocks:
        return lambda x: K @ x
    R = K.blocksize[0]
    cuts = np.unique(np.searchsorted(K.indptr, np.linspace(0, K.indptr[-1], threads + 1)).clip(0, nb))
    cuts[0], cuts[-1] = 0, nb
    parts = [sp.bsr_matrix((K.data[K.indptr[a]:K.indptr[b]], K.indices[K.indptr[a]:K.indptr[b]],
                            K.indptr[a:b + 1] - K.indptr[a]), shape=((b - a) * R, K.shape[1]))
             for a, b in zip(cuts[:-1], cuts[1:]) if b > a]
    if len(parts) == 1:
        return lambda x: K @ x
    pool = _threads_pool(len(parts) - 1)

    def product(x):
        rest = [pool.submit(part.__matmul__, x) for part in parts[1:]]
        return np.concatenate([parts[0] @ x] + [f.result() for f in rest])

    return product


def kff(elimination, K):
    """v -> K_ff v = T^T K T v for the full tangent K (BSR, ``block_matrix``; its products in
    row parts on the sparse threads, ``row_parts_product``)."""
    product = row_parts_product(K)
    return lambda v: elimination.reduce(product(elimination.expand(v)))


class SaddlePointSystem:
    """The saddle-point pattern and its data map: immutable once built (it is part of the
    static solver configuration of jitted functions). Factorisations are not kept here but
    in a ``FactorPool`` (see ``pool``), addressed by the handles in the solver state."""

    cg_rtol = 1e-11     # relative residual of the preconditioned CG solves
    cg_maxiter = 40     # beyond this the current matrix is factorised instead
    # a kept factorisation is replaced (the current tangent factorised after the solve) once
    # CG needs more than ``growth`` x the iterations per decade of its first solve with it
    growth = 2.0
    refinements = 2   # of a direct solve with a single-precision factorisation (each cuts the
    #                   residual by about cond(K_ff) eps_single)

    def __init__(self, X: np.ndarray, rows: np.ndarray, cols: np.ndarray, C, free_dofs: np.ndarray,
                 bnd: np.ndarray, dim: int, factorisation: str = "auto", precision: str = "auto"):
        self.Backend = factoriser(factorisation)
        # single precision where the backend has it, unless "double" is asked for: the
        # factorisation is a CG preconditioner and direct solves are refined in double
        # (``exact``), so the factorisation and its triangular solves cost less at the same CG
        # iterations (``experiments/bench_cube3d_large.py``)
        self.single = precision != "double" and self.Backend.has_single
        N = X.shape[0]
        d = dim
        n_dof = N * d
        C = sp.csr_matrix(C)
        nc = C.shape[0]
        self.n_dof, self.nc, self.n = n_dof, nc, n_dof + nc
        self.free_dofs = np.asarray(free_dofs, np.int64)
        self.bnd_dofs = (np.asarray(bnd, np.int64)[:, None] * d + np.arange(d)).ravel()

        self._X, self._d, self._bnd = X, d, np.asarray(bnd, np.int64)
        self.inv = np.arange(self.n) if self.Backend.reorders else self._ordering(rows, cols)
        Ccoo = C.tocoo()
        self._c_entries = (np.concatenate([Ccoo.row + n_dof, Ccoo.col]),
                           np.concatenate([Ccoo.col, Ccoo.row + n_dof]),
                           np.concatenate([Ccoo.data, Ccoo.data]))
        self.lower = self.Backend.lower
        if self.Backend.reorders and self.lower:
            # PARDISO orders itself: the lower triangle in the natural order, from the pairs
            (self.indices, self.indptr, self.pos_K, self.take_K,
             self.template) = lower_pattern(rows[::d * d] // d, cols[::d * d] // d, d, C)
        else:
            (self.indices, self.indptr, self.pos_K, self.take_K,
             self.template) = self._pattern(rows, cols, self.inv, self.lower)
        self.elimination = HostElimination(C, self.free_dofs, self.bnd_dofs)
        # the block pattern of K (rows, cols come pair-major, d*d entries a pair): CG's products
        # with the current tangent use its blocks as they are (no saddle-point matrix made)
        self.block_indptr, self.block_indices = block_pattern(rows[::d * d] // d, cols[::d * d] // d, N)
        for a in (self.free_dofs, self.bnd_dofs, self.inv, self.indices, self.indptr, self.pos_K,
                  self.take_K, self.template, self.block_indptr, self.block_indices):
            a.setflags(write=False)

    @property
    def factorisation(self) -> str:
        return self.Backend.name

    # ----------------------------------------------------------------------- pieces
    def _ordering(self, rows, cols):
        """old -> new dof positions: nested dissection of the particle graph of the K
        entries (rows, cols) (block order: d*d entries a pair), each particle's dofs followed
        (essential particles) by its multipliers."""
        X, d, bnd = self._X, self._d, self._bnd
        N, n_dof = X.shape[0], self.n_dof
        pi, pj = rows[::d * d] // d, cols[::d * d] // d
        G = sp.csr_matrix((np.ones(len(pi), np.int8), (pi, pj)), shape=(N, N))
        order = nested_dissection(X, G.indptr, G.indices)
        is_b = np.zeros(N, bool)
        is_b[bnd] = True
        bpos = -np.ones(N, np.int64)
        bpos[bnd] = np.arange(len(bnd))
        per = d + d * is_b[order]
        node = np.repeat(order, per)
        k = np.arange(per.sum()) - np.repeat(np.cumsum(per) - per, per)
        perm = np.where(k < d, node * d + k, n_dof + bpos[node] * d + (k - d))   # new -> old
        inv = np.empty_like(perm)
        inv[perm] = np.arange(len(perm))
        return inv

    def _pattern(self, rows, cols, inv, lower):
        """CSC pattern (permuted by inv; its lower triangle only if ``lower``, with the zero
        diagonal of the multiplier block stored) of the saddle-point matrix with K entries
        (rows, cols): indices, indptr, the data positions pos_K of the K entries take_K, and
        the data with C filled in."""
        cr, cc, cv = self._c_entries
        mult = np.arange(self.n_dof, self.n) if lower else np.arange(0)
        rn = inv[np.concatenate([rows, cr, mult])]
        cn = inv[np.concatenate([cols, cc, mult])]
        val = np.concatenate([np.zeros(len(rows)), cv, np.zeros(len(mult))])
        src = np.concatenate([np.arange(len(rows)), np.full(len(cr) + len(mult), -1)])
        if lower:
            keep = rn >= cn
            rn, cn, val, src = rn[keep], cn[keep], val[keep], src[keep]
        key = cn.astype(np.int64) * self.n + rn
        srt = np.argsort(key, kind="stable")
        if np.any(np.diff(key[srt]) == 0):
            raise ValueError("duplicate entries in the tangent pattern")
        indices = rn[srt].astype(np.int32)
        indptr = np.searchsorted(cn[srt], np.arange(self.n + 1)).astype(np.int32)
        template = val[srt]
        pos_K = np.flatnonzero(src[srt] >= 0)
        return indices, indptr, pos_K, src[srt][pos_K], template

    def matrix(self, blocks, work: HostWork | None = None) -> sp.csc_matrix:
        """The stored saddle-point matrix (the lower triangle for PARDISO); ``work`` (of this
        method and the others) the call's ledger, where one counts."""
        with HostWork.of(work).timed("matrix_s"):
            data = self.template.copy()
            data[self.pos_K] = np.asarray(blocks, np.float64).ravel()[self.take_K]
            return sp.csc_matrix((data, self.indices, self.indptr), shape=(self.n, self.n))

    def factorise(self, A, fac=None, work: HostWork | None = None):
        """A new factorisation of the stored matrix A: (factor, number of negative eigenvalues
        of K_ff: -1 unknown (perturbed or pivoted), -2 failed: a singular matrix). ``fac``:
        a released factor object of this system to reuse (PARDISO keeps its analysis)."""
        fac = self.Backend(self.n, self.indptr, self.indices, self.single) if fac is None else fac
        work = HostWork.of(work)
        try:
            with work.timed("factorise_s"):
                neg = fac.factor(A.data)
        except FactorisationError:
            return None, FAILED
        work.add(factorisations=1)
        return fac, (UNKNOWN if neg is None else neg - self.nc)

    def direct(self, fac, b, work: HostWork | None = None):
        """K_ff x = b (n_free, m) with a factorisation of the saddle-point matrix."""
        with HostWork.of(work).timed("triangular_s"):
            B = np.zeros((self.n, b.shape[1]))
            B[self.inv[self.free_dofs]] = b
            return fac.solve(B)[self.inv[self.free_dofs]]

    def kff(self, blocks):
        """x -> K_ff x for the tangent ``blocks`` (host arrays; no saddle-point matrix made)."""
        return kff(self.elimination, block_matrix(blocks, self.block_indptr, self.block_indices))

    def exact(self, fac, blocks, b, work: HostWork | None = None):
        """K_ff x = b (n_free, m) by the factorisation ``fac`` of ``blocks``, to double
        accuracy: a single-precision factorisation's solve is refined (``refinements`` steps
        x <- x + direct(b - K_ff x), as the dense path's mixed precision)."""
        work = HostWork.of(work)
        if not self.single:
            return self.direct(fac, b, work)
        kff = self.kff(blocks)
        return refine(lambda r: self.direct(fac, r, work), lambda x: np.stack([kff(c) for c in x.T], 1), b,
                      self.refinements)

    def _pcg(self, fac, kff, b, rtol, work: HostWork):
        """CG on K_ff x = b preconditioned by the factorisation ``fac`` of another matrix,
        to the relative residual rtol; (x, iterations), or None when it stalls or meets
        negative curvature."""
        x, its, ok = preconditioned_cg(kff, lambda r: self.direct(fac, r[:, None], work)[:, 0], b, rtol,
                                       self.cg_maxiter)
        if not ok:
            return None
        work.add(cg_iterations=its)
        return x, its

    def preconditioned(self, fac, blocks, b, rtol, work: HostWork | None = None):
        """K_ff x = b for the tangent ``blocks`` by CG preconditioned with ``fac`` (every
        column): (x, the most CG iterations per decade of residual reduction of a column), or
        None when any column fails."""
        work = HostWork.of(work)
        t0, tri0 = time.perf_counter(), work.counts["triangular_s"]
        kff = self.kff(blocks)
        cols, rate = [], 0.0
        try:
            for j in range(b.shape[1]):
                done = self._pcg(fac, kff, b[:, j], rtol, work)
                if done is None:
                    return None
                cols.append(done[0])
                rate = max(rate, done[1] / max(-np.log10(rtol), 1.0))
        finally:   # cg_s: CG's own work (products, updates); its triangular solves are apart
            work.add(cg_s=time.perf_counter() - t0 - (work.counts["triangular_s"] - tri0))
        work.add(cg_solves=1)
        return np.stack(cols, 1), rate


# the inertia codes of a factorisation: >= 0 the number of negative eigenvalues of K_ff
UNKNOWN = -1    # pivots were perturbed (PARDISO) or permuted (SuperLU): the count is unknown
FAILED = -2     # the factorisation failed (a singular matrix)
NONE = -3       # no factorisation held yet


class FactorPool:
    """The host-side factorisations of one SaddlePointSystem, addressed by handle.

    A memo, not state: a handle always comes with the tangent blocks it was made from (the
    solver state carries both), so a factorisation that was evicted to bound memory is made
    again from those blocks and every result is the same whatever the call history.
    ``size`` factorisations are kept (a kept preconditioner and a fresh one)."""

    def __init__(self, system: SaddlePointSystem, size: int = 2):
        self.system, self.size = system, size
        self.slots: dict[int, tuple] = {}        # handle -> (factor, inertia), oldest first
        self.rates: dict[int, float] = {}        # handle -> CG iterations a decade, first solve
        self.spare = None                        # an evicted factor object, reused next
        self.next = 1
        self.lock = threading.Lock()

    def _store(self, handle: int, fac, neg):
        while len(self.slots) >= self.size:
            self._drop(next(iter(self.slots)))
        self.slots[handle] = (fac, neg)

    def _factorise(self, blocks, work: HostWork):
        fac, self.spare = self.spare, None
        return self.system.factorise(self.system.matrix(blocks, work), fac, work)

    def _keep(self, fac, neg) -> int:
        """A new handle for a new factorisation (kept unless it failed)."""
        h = self.next
        self.next += 1
        if fac is not None:
            self._store(h, fac, neg)
        return h

    def factor(self, handle: int, blocks, work: HostWork):
        """The factorisation of ``handle`` (made again from ``blocks`` if evicted), or None."""
        if handle in self.slots:
            self.slots[handle] = self.slots.pop(handle)     # most recently used last
            return self.slots[handle][0]
        work.add(refactorisations=1)
        fac, neg = self._factorise(blocks, work)
        if fac is not None:
            self._store(handle, fac, neg)
        return fac

    def init(self, blocks):
        """Factorise the tangent ``blocks``: (handle, inertia code, LinearStats of the call)."""
        work = HostWork()
        with self.lock:
            fac, neg = self._factorise(blocks, work)
            return np.int64(self._keep(fac, neg)), np.int64(neg), work.stats()

    def solve(self, handle, blocks, rhs):
        """x (rhs.shape) with K_ff x = rhs by the factorisation ``handle`` of ``blocks``
        (NaN where that factorisation failed)."""
        rhs = np.asarray(rhs, np.float64)
        work = HostWork()   # a solve returns no state to carry it: its work stays uncounted
        with self.lock:
            fac = self.factor(int(handle), blocks, work) if int(handle) > 0 else None
            if fac is None:
                return np.full(rhs.shape, np.nan)
            b = rhs.reshape(len(self.system.free_dofs), -1)
            return self.system.exact(fac, blocks, b, work).reshape(rhs.shape)

    def _drop(self, handle: int):
        """Forget ``handle``'s factorisation; its object (memory, PARDISO's analysis) serves
        the next one made."""
        if handle in self.slots:
            self.spare = self.slots.pop(handle)[0]
            self.rates.pop(handle, None)

    def newton_solve(self, handle, neg, kept_blocks, blocks, rhs, rtol):
        """A Newton step's solve with the current tangent ``blocks``: CG preconditioned by the
        held factorisation while it is positive definite and CG converges, else a new
        factorisation. Returns (x, handle, inertia, reused) of the factorisation held after
        the step and the call's LinearStats: a CG solve that needed more than ``system.growth`` x the iterations per
        decade of the held factorisation's first one (the tangent has moved away from it)
        factorises ``blocks`` after it, for the steps to come (kept where its inertia is
        known): one factorisation for a whole path let CG's iterations grow several-fold
        along it (``experiments/bench_cube3d_large.py``). A replaced factorisation is dropped
        first, so one is held at a time (a large 3D factorisation takes gigabytes)."""
        rhs = np.asarray(rhs, np.float64)
        b = rhs.reshape(len(self.system.free_dofs), -1)
        h, work = int(handle), HostWork()
        with self.lock:
            done = self._reusing(h, int(neg), kept_blocks, blocks, b, float(rtol), work) \
                if int(neg) == 0 and h > 0 else None
            x, h, neg, reused = self._refactorised(h, blocks, b, work) if done is None else done
        return x.reshape(rhs.shape), np.int64(h), np.int64(neg), np.bool_(reused), work.stats()

    def _reusing(self, h, neg, kept_blocks, blocks, b, rtol, work):
        """``newton_solve`` by CG preconditioned with the held factorisation ``h``: (x, handle,
        inertia, reused), or None where CG failed."""
        fac = self.factor(h, kept_blocks, work)
        done = None if fac is None else self.system.preconditioned(fac, blocks, b, rtol, work)
        if done is None:
            return None
        x, rate = done
        if rate <= self.system.growth * self.rates.setdefault(h, rate):
            return x, h, neg, True
        self._drop(h)
        new, new_neg = self._factorise(blocks, work)
        if new is not None and new_neg >= 0:
            return x, self._keep(new, new_neg), new_neg, False
        # inertia unknown: the held one stays (made again from its blocks when used)
        if new is not None:
            self.spare = new
        return x, h, neg, True

    def _refactorised(self, h, blocks, b, work):
        """``newton_solve`` by a new factorisation of ``blocks`` (``h`` dropped): (x, handle,
        inertia, reused=False); x NaN where the factorisation failed."""
        self._drop(h)
        fac, neg = self._factorise(blocks, work)
        h = self._keep(fac, neg)
        if fac is None:
            return np.full(b.shape, np.nan), h, neg, False
        return self.system.exact(fac, blocks, b, work), h, neg, False

    def clear(self):
        with self.lock:
            for fac, _ in self.slots.values():
                fac.release()
            self.slots.clear()
            self.rates.clear()
            self.spare = None


def pooled(make):
    """``system -> make(system)``, made on first use and freed with the system: the host-side
    pool of a linear solver (factorisations, multigrid hierarchies) kept per system."""
    pools = weakref.WeakKeyDictionary()
    lock = threading.Lock()

    def pool(system):
        with lock:
            if system not in pools:
                pools[system] = make(system)
            return pools[system]

    return pool


pool = pooled(FactorPool)   # the factorisation pool of a SaddlePointSystem
