"""The vmapped-solve deadlock of XLA:CPU (jax 0.10), reduced: each arm runs a vmapped
while_loop with a Cholesky and an LU factorisation of a batch of 5 200x200 matrices and the
triangular solves of both (as DenseSolver.solve's two branches under vmap) per iteration in a subprocess limited to 2 CPUs (so XLA's intra-op pool has 2 threads), with a
timeout. Prints JSON: per arm, finished runs and their times.

Arms:
- ``threaded-blas``: OpenBLAS with its default threads, jax's batched factorisations;
- ``single-blas``: OPENBLAS_NUM_THREADS=1, jax's batched factorisations;
- ``fixed``: single-threaded BLAS (``import jaxrkpm``) and factorisations and triangular
  solves that run one batch member at a time (``jaxrkpm.solvers.linalg.dense.one_at_a_time``): what
  DenseSolver does.

Measured (loaded 2-core machine, 30 s timeout): threaded-blas and single-blas 0 of 3 finished,
fixed 3 of 3 in 6-8 s. A hung run's native stacks (gdb: ``thread apply all bt``) show both
XLA pool threads in ``jax::ParallelBatchMap`` (BlockingCounter::Wait) of lapack_dpotrf_ffi
and lapack_dgetrf_ffi (single-blas), or threads spinning in OpenBLAS's dpotrf_L_parallel
(threaded-blas). With the factorisations fixed, a vmapped needle sweep (5 configurations x 15
increments) still hung, in ParallelBatchMap of lapack_dtrsm_ffi (the triangular solves of
cho_solve and lu_solve): hence the solves in the pattern; the arms' figures above were
measured before they were added."""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

PATTERN = """
import os, sys
os.sched_setaffinity(0, set(sorted(os.sched_getaffinity(0))[:2]))
if sys.argv[1] == "fixed":
    import jaxrkpm
import jax, jax.numpy as jnp
jax.config.update("jax_enable_x64", True)
cholesky = lambda A: jnp.linalg.cholesky(A)
lu = lambda A: jax.scipy.linalg.lu_factor(A)[0]
cho_solve = lambda L, b: jax.scipy.linalg.cho_solve((L, True), b)
lu_solve = lambda A, b: jax.scipy.linalg.lu_solve(jax.scipy.linalg.lu_factor(A), b)
if sys.argv[1] == "fixed":
    from jaxrkpm.solvers.linalg.dense import one_at_a_time
    cholesky, lu, cho_solve, lu_solve = map(one_at_a_time, (cholesky, lu, cho_solve, lu_solve))

def member(A):
    def body(c):
        i, A = c
        L, b = cholesky(A), jnp.ones(A.shape[0])
        x = cho_solve(L, b) + lu_solve(A, b)
        return i + 1, A + 1e-6 * (jnp.sum(L) + jnp.sum(lu(A)) + jnp.sum(x))
    return jax.lax.while_loop(lambda c: c[0] < 100, body, (0, A))[1]

f = jax.jit(jax.vmap(member))
A = 3.0 * jnp.eye(200) + jnp.zeros((5, 200, 200))
for _ in range(10):
    jax.block_until_ready(f(A))
"""

ARMS = {"threaded-blas": {"OPENBLAS_NUM_THREADS": None}, "single-blas": {"OPENBLAS_NUM_THREADS": "1"},
        "fixed": {"OPENBLAS_NUM_THREADS": None}}


def run(arm, timeout):
    env = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "JAXRKPM_BLAS_THREADS")}
    env["PYTHONPATH"] = os.pathsep.join(sys.path)
    env.update({k: v for k, v in ARMS[arm].items() if v is not None})
    t0 = time.perf_counter()
    try:
        subprocess.run([sys.executable, "-c", PATTERN, arm], env=env, timeout=timeout, check=True,
                       capture_output=True)
        return time.perf_counter() - t0
    except subprocess.TimeoutExpired:
        return None


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--timeout", type=float, default=30.0)
    ap.add_argument("--arms", nargs="+", choices=list(ARMS), default=list(ARMS))
    args = ap.parse_args(argv)
    out = {"timeout_s": args.timeout, "load_average": os.getloadavg(), "arms": {}}
    for arm in args.arms:
        times = [run(arm, args.timeout) for _ in range(args.runs)]
        out["arms"][arm] = {"finished": sum(t is not None for t in times), "runs": args.runs,
                            "times_s": [None if t is None else round(t, 2) for t in times]}
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
