"""Benchmark: compile time, warm solve time (median) and peak memory for neo-Hookean blocks
compressed 30% in 10 load steps (left face immobile, right face pushed). Run from the
repository root: ``python -m experiments.bench_solve``; writes a record (experiments/records.py).

Each case runs in a fresh subprocess so its peak RSS is its own. Every timed solve starts
from a cold factorisation cache (the sparse solver otherwise reuses the last factorisation as
a preconditioner across solves). Prints JSON."""
from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time

from experiments import records

CASES = {"2d_9": (9, 9), "2d_101": (101, 101), "3d_20": (20, 20, 20)}


def reset_factorisation(model):
    """Drop the host's factorisations: every timed solve starts cold (a solve's linear state
    starts empty anyway; this also frees the memory)."""
    from jaxrkpm.solvers.linalg import factorisations as sparse
    system = getattr(model.linear, "system", None)
    if system is not None:
        sparse.pool(system).clear()


COMPILE_EVENTS = ("/jax/core/compile/jaxpr_trace_duration",
                  "/jax/core/compile/jaxpr_to_mlir_module_duration",
                  "/jax/core/compile/backend_compile_duration")


def run_case(shape, repeats, factorisation="auto"):
    import jax
    import jax.numpy as jnp

    import jaxrkpm as jr
    # compile time as JAX reports it (tracing, lowering, XLA compile), not first - warm: that
    # difference drowns in the solve time's spread when a solve takes minutes
    compiling = []
    jax.monitoring.register_event_duration_secs_listener(
        lambda event, secs, **kw: compiling.append(secs) if event in COMPILE_EVENTS else None)
    t0 = time.perf_counter()
    body = jr.Body.grid(shape, 1.0 / (shape[0] - 1))
    sets = {"wall": body.select(lambda X: X[:, 0] < 1e-9), "right": body.select(lambda X: X[:, 0] > 1 - 1e-9)}
    model = jr.Model(body, jr.NeoHookean(lam=1.0, mu=1.0), essential=sets, factorisation=factorisation)
    build = time.perf_counter() - t0
    g = jnp.zeros(len(shape)).at[0].set(-0.3)
    compiling.clear()               # the model's build compiles a few helpers of its own
    t0 = time.perf_counter()
    sol = model.solve({"right": g}, steps=10)
    sol.u.block_until_ready()
    first = time.perf_counter() - t0
    compile_s = sum(compiling)
    times = []
    for _ in range(repeats):
        reset_factorisation(model)
        t0 = time.perf_counter()
        sol = model.solve({"right": g}, steps=10)
        sol.u.block_until_ready()
        times.append(time.perf_counter() - t0)
    warm = statistics.median(times)
    system = getattr(model.linear, "system", None)
    # the last warm solve's linear work, returned with it (host seconds on the sparse path only)
    iterations, linear = int(sol.iterations), sol.stats.as_dict()
    # inexact Newton (loose early linear solves) is on only without the stability check; one
    # solve, its own compile included (a different static configuration)
    reset_factorisation(model)
    t0 = time.perf_counter()
    loose = model.solve({"right": g}, steps=10, check_stability=False)
    loose.u.block_until_ready()
    loose_s = time.perf_counter() - t0
    return {"shape": list(shape), "dof": int(len(model.sets.free) * len(shape)),
            "solver": model.linear.name, "factorisation": getattr(system, "factorisation", None),
            "build_s": build, "compile_s": compile_s,
            "first_solve_s": first, "warm_solve_s_median": warm, "warm_solve_s": records.stats(times),
            "newton_iterations": iterations, "linear": linear,
            "no_stability_check_solve_s": loose_s, "no_stability_check_newton_iterations": int(loose.iterations),
            "no_stability_check_max_du_difference": float(abs(loose.u - sol.u).max()), "load_steps": int(sol.steps),
            "status": sol.outcome.name,
            "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--cases", nargs="*", default=list(CASES))
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--factorisation", default="auto", choices=["auto", "pardiso", "superlu"],
                   help="of the sparse path (the large cases)")
    p.add_argument("--case", help=argparse.SUPPRESS)
    records.add_arguments(p)
    a = p.parse_args(argv)
    if a.case:
        print(json.dumps(run_case(CASES[a.case], a.repeats, a.factorisation)))
        return
    run = records.start("bench_solve", a)
    out = {}
    for name in a.cases:
        reps = a.repeats if name == "2d_9" else max(1, min(a.repeats, 2))
        r = subprocess.run([sys.executable, "-m", "experiments.bench_solve", "--case", name,
                            "--repeats", str(reps), "--factorisation", a.factorisation],
                           capture_output=True, text=True)
        out[name] = json.loads(r.stdout.strip().splitlines()[-1]) if r.returncode == 0 else \
            {"error": r.stderr.strip().splitlines()[-1] if r.stderr.strip() else f"exit {r.returncode}"}
        print(name, json.dumps(out[name]), file=sys.stderr)
    print(json.dumps(out, indent=2))
    records.finish(run, out)


if __name__ == "__main__":
    main()
