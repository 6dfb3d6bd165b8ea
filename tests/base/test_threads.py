"""The vmapped-solve deadlock of XLA:CPU (jax 0.10), reduced, run in a subprocess that must
finish within a timeout.

The broken pattern (not run here: it hangs until killed), on a process limited to 2 CPUs so
that XLA's intra-op pool has 2 threads:

    def body(c):                       # inside a vmapped while_loop, n = 200, batch 5
        i, A = c
        return i + 1, A + 1e-6 * (jnp.sum(jnp.linalg.cholesky(A))
                                  + jnp.sum(jax.scipy.linalg.lu_factor(A)[0]))

Measured: with OPENBLAS_NUM_THREADS=1 it deadlocks every time (both pool threads wait in
jaxlib's ``ParallelBatchMap`` of the batched dpotrf and dgetrf kernels for pieces queued on
the same pool, gdb); with OpenBLAS's default threads it livelocks even with the Cholesky
alone (threads spinning in OpenBLAS's dpotrf_L_parallel, called from two XLA threads at
once). Each arm: 3 of 3 runs killed at 30 s; the fixed pattern below: 3 of 3 done in 6-8 s on
the loaded machine. The triangular solves of the same batch do the same (a vmapped needle
sweep hung with both pool threads in ParallelBatchMap of ``lapack_dtrsm_ffi``, gdb): the
pattern below has them too. The fix is two parts, both needed: single-threaded BLAS
(``jaxrkpm.base.threads``, applied by ``import jaxrkpm``) and factorisations that run one batch
member at a time under vmap (``jaxrkpm.solvers.linalg.dense.one_at_a_time``). DenseSolver has both.
"""
import subprocess
import sys
import textwrap

FIXED = textwrap.dedent("""
    import os
    os.sched_setaffinity(0, set(sorted(os.sched_getaffinity(0))[:2]))   # a 2-thread XLA pool
    import jaxrkpm                                   # single-threaded BLAS, before JAX loads
    import jax, jax.numpy as jnp
    from jaxrkpm.solvers.linalg.dense import one_at_a_time
    cholesky = one_at_a_time(lambda A: jnp.linalg.cholesky(A))
    lu = one_at_a_time(lambda A: jax.scipy.linalg.lu_factor(A)[0])
    cho_solve = one_at_a_time(lambda L, b: jax.scipy.linalg.cho_solve((L, True), b))
    lu_solve = one_at_a_time(lambda A, b: jax.scipy.linalg.lu_solve(jax.scipy.linalg.lu_factor(A), b))

    def member(A):
        def body(c):
            i, A = c
            L, b = cholesky(A), jnp.ones(A.shape[0])
            # two triangular-solve pairs side by side, as in DenseSolver.solve under vmap
            x = cho_solve(L, b) + lu_solve(A, b)
            return i + 1, A + 1e-6 * (jnp.sum(L) + jnp.sum(lu(A)) + jnp.sum(x))
        return jax.lax.while_loop(lambda c: c[0] < 30, body, (0, A))[1]

    A = 3.0 * jnp.eye(200) + jnp.zeros((5, 200, 200))
    f = jax.jit(jax.vmap(member))
    for _ in range(4):
        out = jax.block_until_ready(f(A))
    ref = jax.jit(member)(A[0])
    print("max difference to the unbatched member", float(jnp.max(jnp.abs(out[0] - ref))))
""")


def test_vmapped_factorisations_in_a_loop_finish():
    env = {"PATH": "/usr/bin:/bin", "HOME": "/tmp", "PYTHONPATH": ":".join(sys.path)}
    done = subprocess.run([sys.executable, "-c", FIXED], capture_output=True, text=True, timeout=120, env=env)
    assert done.returncode == 0, done.stderr[-2000:]
    diff = float(done.stdout.split()[-1])
    assert diff < 1e-12     # the batch rule changes the schedule, not the numbers


def test_blas_threads_default_and_override(monkeypatch):
    from jaxrkpm.base import threads
    monkeypatch.delenv(threads.ENV, raising=False)
    assert threads.blas_threads() == 1
    monkeypatch.setenv(threads.ENV, "3")
    assert threads.blas_threads() == 3
    monkeypatch.setenv(threads.ENV, "keep")
    assert threads.blas_threads() is None
    monkeypatch.setenv(threads.ENV, "many")
    try:
        threads.blas_threads()
    except ValueError as e:
        assert threads.ENV in str(e) and "keep" in str(e)
    else:
        raise AssertionError("a bad JAXRKPM_BLAS_THREADS must raise")


def test_sparse_threads_default_and_override(monkeypatch):
    from jaxrkpm.base import threads
    monkeypatch.delenv(threads.SPARSE_ENV, raising=False)
    assert threads.sparse_threads() == threads.usable_cores() >= 1
    monkeypatch.setenv(threads.SPARSE_ENV, "1")
    assert threads.sparse_threads() == 1
    for bad in ("0", "all", "-2"):
        monkeypatch.setenv(threads.SPARSE_ENV, bad)
        try:
            threads.sparse_threads()
        except ValueError as e:
            assert threads.SPARSE_ENV in str(e)
        else:
            raise AssertionError(f"{threads.SPARSE_ENV}={bad} must raise")


def test_row_parts_product_is_the_product():
    """The tangent's product in row parts on several threads equals SciPy's whole product,
    for any number of parts (more parts than block rows included) and several right-hand
    sides; small matrices are not cut."""
    import numpy as np
    import scipy.sparse as sp
    from jaxrkpm.solvers.linalg import factorisations as sparse
    rng = np.random.default_rng(0)
    K = sp.random(60, 60, density=0.2, random_state=1, format="csr")
    K = sp.bsr_matrix(K + K.T + sp.eye(60), blocksize=(3, 3))
    x, X = rng.standard_normal(60), rng.standard_normal((60, 4))
    for threads in (1, 2, 3, 25):
        product = sparse.row_parts_product(K, threads, min_blocks=1)
        assert np.allclose(product(x), K @ x, rtol=0, atol=1e-13)
        assert np.allclose(product(X), K @ X, rtol=0, atol=1e-13)
