"""Benchmark: does a workload's time survive one other CPU-bound process beside it?

Each workload runs warm in this process, ``repeats`` times quiet and ``repeats`` times while
a busy process (``python -c "while True: pass"``, started here and killed after each timed
call) occupies one core, interleaved (quiet, busy, quiet, ...), so both see the same
machine. Reported: medians and busy/quiet ratio (issue 20 asks <= 2.5), per workload, for the
BLAS threading that ``import jaxrkpm`` sets (``jaxrkpm.base.threads``; run with
``JAXRKPM_BLAS_THREADS=keep`` to measure the libraries' default threads instead).

Workloads:
- ``cholesky``: ``jnp.linalg.cholesky`` of a 1,152^2 SPD matrix (issue 20: with OpenBLAS's
  default threads, beside one busy process, many times its single-threaded time);
- ``cube6``: neo-Hookean 6^3 cube, 30% compression in 10 load steps (dense path);
- ``needle``: the 2D phantom's 5 paddle positions x 5 increments (``needle.insert``);
- ``box``: the 2D box path (Gauss, 9x9) of the tracking study;
- ``cube10`` / ``cube10_control``: the 10^3 cube's full solve and one control step;
- ``sweep20``: the needle sweep of experiments/bench_sweep.py, 20 configurations;
- ``cube20``: the 20^3 cube's full solve on the sparse path (PARDISO and the CG products on
  ``JAXRKPM_SPARSE_THREADS`` threads, every core by default; not in the default set: minutes
  a repeat pair).
Run from the repository root: ``python -m experiments.bench_contention``. Prints JSON (also
the load average before and after: other jobs on the machine skew both) and writes a record
(experiments/records.py)."""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

import numpy as np

import jaxrkpm  # noqa: F401  (BLAS threads before JAX loads)
from experiments import records
import jax
import jax.numpy as jnp


def cholesky_workload():
    n = 1152
    rng = np.random.default_rng(0)
    M = rng.standard_normal((n, n))
    A = jnp.asarray(M @ M.T + n * np.eye(n))
    f = jax.jit(jnp.linalg.cholesky)
    return lambda: jax.block_until_ready(f(A))


def cube6_workload():
    import jaxrkpm as jr
    body = jr.Body.grid((6, 6, 6), 1.0 / 5)
    sets = {"wall": body.select(lambda X: X[:, 0] < 1e-9), "right": body.select(lambda X: X[:, 0] > 1 - 1e-9)}
    model = jr.Model(body, jr.NeoHookean(lam=1.0, mu=1.0), essential=sets)
    move = {"right": np.array([-0.3, 0.0, 0.0])}
    return lambda: jax.block_until_ready(model.solve(move, steps=10).u)


def needle_workload():
    from jaxrkpm.thesis import needle as nd
    ph = nd.Phantom()
    models = [ph.model("none", p) for p in range(1, 6)]
    depths = ph.depths(5)
    return lambda: jax.block_until_ready(nd.insert(models, depths, ph.target, direction=ph.needle_direction))


def box_workload():
    """The 2D box path (Table 5.3: 9x9 Fung square, Gauss, gain 0.05, clamp 0.01)."""
    from jaxrkpm.thesis.studies import track as T
    exp = T.build("box", 2, "gauss")
    return lambda: T.execute(exp)


def cube10_models():
    import jaxrkpm as jr
    body = jr.Body.grid((10, 10, 10), 1.0 / 9)
    sets = {"wall": body.select(lambda X: X[:, 0] < 1e-9), "right": body.select(lambda X: X[:, 0] > 1 - 1e-9)}
    return jr.Model(body, jr.NeoHookean(lam=1.0, mu=1.0), essential=sets)


def cube10_workload():
    """The 10^3 cube's full solve: 30% compression in 10 load steps."""
    model = cube10_models()
    move = {"right": np.array([-0.3, 0.0, 0.0])}
    return lambda: jax.block_until_ready(model.solve(move, steps=10).u)


def cube10_control_workload():
    """One control step of the 10^3 cube at 30% (factorisation, Jacobian of the centre, a 1%
    paddle increment settled): what experiments/bench_cube3d.py times as ``control_step_s``."""
    from jaxrkpm.control.tracking import ControlledModel
    from jaxrkpm.solvers.results import Limits
    model = cube10_models()
    sol = model.solve({"right": np.array([-0.3, 0.0, 0.0])}, steps=10)
    ctrl = ControlledModel.of(model, "right", np.array([[0.5, 0.5, 0.5]]))
    lim = Limits.of(steps=1)
    dg = jnp.einsum("a,abi->bi", jnp.array([-0.01, 0.0, 0.0]), ctrl.G)

    @jax.jit
    def control_step(c, s):
        state = c.factorise(s)
        return c.jacobian(s, state), c.settle(s, state, s.g + dg, lim, 6)[0]

    return lambda: jax.block_until_ready(control_step(ctrl, sol))


def sweep_workload():
    """The needle sweep of experiments/bench_sweep.py at 20 configurations x 15 increments."""
    from experiments.bench_sweep import batched, configurations
    from jaxrkpm.thesis import needle as nd
    ph = nd.Phantom()
    models, depths = configurations(ph, 20), ph.depths(15)
    return lambda: batched(models, depths, ph.target)


def cube20_workload():
    import jaxrkpm as jr
    body = jr.Body.grid((20, 20, 20), 1.0 / 19)
    sets = {"wall": body.select(lambda X: X[:, 0] < 1e-9), "right": body.select(lambda X: X[:, 0] > 1 - 1e-9)}
    model = jr.Model(body, jr.NeoHookean(lam=1.0, mu=1.0), essential=sets, solver="sparse")
    move = {"right": np.array([-0.3, 0.0, 0.0])}
    return lambda: jax.block_until_ready(model.solve(move, steps=10).u)


WORKLOADS = {"cholesky": cholesky_workload, "cube6": cube6_workload, "needle": needle_workload,
             "box": box_workload, "cube10": cube10_workload, "cube10_control": cube10_control_workload,
             "sweep20": sweep_workload, "cube20": cube20_workload}
DEFAULT = [w for w in WORKLOADS if w != "cube20"]


def timed_call(fn, busy: bool) -> float:
    hog = subprocess.Popen([sys.executable, "-c", "while True: pass"]) if busy else None
    try:
        if hog is not None:
            time.sleep(0.2)          # let it start spinning
        t0 = time.perf_counter()
        fn()
        return time.perf_counter() - t0
    finally:
        if hog is not None:
            hog.kill()
            hog.wait()


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workloads", nargs="+", choices=list(WORKLOADS), default=DEFAULT)
    ap.add_argument("--repeats", type=int, default=5)
    records.add_arguments(ap)
    args = ap.parse_args(argv)
    run = records.start("bench_contention", args)
    result = {"blas_threads": os.environ.get(jaxrkpm.base.threads.ENV, str(jaxrkpm.base.threads.DEFAULT)),
              "sparse_threads": jaxrkpm.base.threads.sparse_threads(),
              "load_average_before": os.getloadavg(), "workloads": {}}
    for name in args.workloads:
        fn = WORKLOADS[name]()
        fn()                                          # compile
        quiet, busy = [], []
        for _ in range(args.repeats):
            quiet.append(timed_call(fn, False))
            busy.append(timed_call(fn, True))
        q, b = statistics.median(quiet), statistics.median(busy)
        result["workloads"][name] = {"quiet_median_s": q, "busy_median_s": b, "busy_over_quiet": b / q,
                                     "quiet_s": records.stats(quiet), "busy_s": records.stats(busy)}
        # progress on stderr: stdout holds only the final JSON (one document to parse)
        print(json.dumps({name: result["workloads"][name]}), file=sys.stderr, flush=True)
    result["load_average_after"] = os.getloadavg()
    print(json.dumps(result, indent=1))
    records.finish(run, result, {f"busy_over_quiet {k}": v["busy_over_quiet"] for k, v in result["workloads"].items()})


if __name__ == "__main__":
    main()
