"""Threading of the BLAS/LAPACK libraries under JAX: single-threaded by default.

Why. jaxlib's CPU LAPACK kernels (Cholesky, LU, ...) call SciPy's OpenBLAS, and XLA runs
independent operations of one program on its own thread pool at the same time. With
OpenBLAS's default threads, several XLA threads call the threaded OpenBLAS at once: its
worker threads spin-wait for each other, so a vmapped batch of Newton solves livelocks
(tests/base/test_threads.py keeps the reduced pattern; ``experiments/vmap_deadlock.py`` runs
it with threaded and single-threaded BLAS) and a dense Cholesky beside another CPU-bound
process slows down (``experiments/bench_contention.py --workloads cholesky``, with
``JAXRKPM_BLAS_THREADS=keep`` for the libraries' own threads). The small and medium dense
systems of this library do not gain from BLAS threads anyway; parallelism comes from XLA's
own pool and from batching configurations (vmap).

What. ``configure()`` (run by ``import jaxrkpm``, before JAX is loaded) sets
OPENBLAS_NUM_THREADS, MKL_NUM_THREADS and OMP_NUM_THREADS to ``JAXRKPM_BLAS_THREADS``
(default 1) unless they are already set, and limits BLAS libraries that are already loaded
(numpy/scipy imported first) through threadpoolctl. Override: ``JAXRKPM_BLAS_THREADS=4``
(four threads), ``JAXRKPM_BLAS_THREADS=keep`` (leave every library as it is; the
OPENBLAS_/MKL_/OMP_NUM_THREADS variables then decide).

The host-side sparse linear algebra of large (3D) models is the exception: PARDISO's
factorisations and triangular solves, and the conjugate-gradient products with the sparse
tangent, run on ``JAXRKPM_SPARSE_THREADS`` threads (default: every core this process may
use). They are large, run one at a time (never from several XLA threads at once) and gain
from every core (``experiments/bench_cube3d_large.py``, against
``JAXRKPM_SPARSE_THREADS=1``). Threads collapse where they spin-wait for a core that another
process holds. PARDISO's threads are OpenMP's (Intel's runtime, libiomp5), so ``configure``
sets KMP_BLOCKTIME=0 where unset: a thread that waits sleeps at once instead of spinning for
the runtime's default block time (``experiments/bench_contention.py --workloads cube20``
compares, beside a busy process). The products run on a Python thread pool (SciPy's sparse
kernels release the GIL), whose waits are blocking. ``JAXRKPM_SPARSE_THREADS=1`` keeps all
of it on one thread.
"""
from __future__ import annotations

import os
import sys

ENV = "JAXRKPM_BLAS_THREADS"
DEFAULT = 1
LIBRARY_VARIABLES = ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OMP_NUM_THREADS")
SPARSE_ENV = "JAXRKPM_SPARSE_THREADS"
# Intel OpenMP (PARDISO's threads): how long a waiting thread spins before it sleeps (ms)
SPIN_VARIABLE = ("KMP_BLOCKTIME", "0")


def usable_cores() -> int:
    """The cores this process may run on (its CPU affinity where the OS reports it)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:      # not Linux
        return os.cpu_count() or 1


def sparse_threads() -> int:
    """Threads of the host-side sparse linear algebra (PARDISO, the sparse products):
    ``JAXRKPM_SPARSE_THREADS``, default every usable core. Not a positive integer: an error."""
    raw = os.environ.get(SPARSE_ENV, "").strip()
    if not raw:
        return usable_cores()
    if not raw.isdigit() or int(raw) < 1:
        raise ValueError(f"{SPARSE_ENV}={raw!r}: give a positive number of threads for the "
                         "sparse factorisations and products (unset: every usable core)")
    return int(raw)


def blas_threads() -> int | None:
    """The BLAS thread count asked for by ``JAXRKPM_BLAS_THREADS`` (default 1); None for
    ``keep``. A value that is neither a positive integer nor ``keep`` is an error."""
    raw = os.environ.get(ENV, str(DEFAULT)).strip().lower()
    if raw == "keep":
        return None
    if not raw.isdigit() or int(raw) < 1:
        raise ValueError(f"{ENV}={raw!r}: give a positive number of BLAS threads, or 'keep' to "
                         "leave the BLAS libraries' own threading alone")
    return int(raw)


def configure() -> int | None:
    """Apply ``blas_threads()``: the library variables (where unset) for libraries not yet
    loaded, threadpoolctl for those already loaded; and KMP_BLOCKTIME=0 where unset (OpenMP
    threads that wait sleep, see above). Returns the BLAS thread count (None: keep)."""
    n = blas_threads()
    if n is None:
        return None
    for name in LIBRARY_VARIABLES:
        os.environ.setdefault(name, str(n))
    os.environ.setdefault(*SPIN_VARIABLE)
    limit_loaded(n)
    return n


def limit_loaded(n: int) -> None:
    """Limit the BLAS libraries already loaded in this process to ``n`` threads (a no-op
    when threadpoolctl is missing or nothing is loaded yet: the variables then apply)."""
    if not any(m in sys.modules for m in ("numpy", "scipy", "jax")):
        return    # nothing loaded BLAS yet (keeps ``jaxrkpm --help`` fast)
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        return
    threadpool_limits(n, user_api="blas")
