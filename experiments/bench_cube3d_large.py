"""Benchmark of issue 20's large 3D cases: the neo-Hookean n^3 cube of ``bench_cube3d`` (left
face immobile, right face pushed 30% in 10 load steps) at n >= 14, solved with each large-
system linear solver ("sparse": PARDISO factorisations reused as CG preconditioners;
"krylov": CG preconditioned by an algebraic multigrid hierarchy, ``Model(solver="krylov")``).

Per case (a fresh subprocess each, so peak memory is its own): the model build, a cold solve
(compile included) and a warm one, Newton iterations, the peak resident memory after the
build and after the solves, and the profile of the warm solve: assembly (the tangent's pair
blocks, timed alone and multiplied by the assemblies made), host-side work of the linear
solver (the solve's returned ``LinearStats``: sparse matrix from blocks, factorisations or
multigrid set-ups, triangular solves, CG) and the rest (residuals, line searches, callback transfers). The
solutions of the solvers at one size are compared (max |u_a - u_b| / max |u|).

A watchdog in this (parent) process kills a case whose resident memory passes --max-rss-gb
(the machine is shared); such a case reports "killed". One command gives every figure:

    python -m experiments.bench_cube3d_large --n 14 20 --solver sparse krylov

Prints JSON and writes a record (experiments/records.py); quote ratios within one run (the load average is printed)."""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import threading
import time

from experiments import records


def rss_gb(pid: int) -> float:
    """Resident memory of process ``pid`` (GB; 0 when it is gone)."""
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) * 1024 / 1e9
    except OSError:
        pass
    return 0.0


def peak_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e9


def run_case(n, solver, repeats, out_npz, check_stability=True):
    import jax
    import numpy as np

    import jaxrkpm as jr
    body = jr.Body.grid((n, n, n), 1.0 / (n - 1))
    sets = {"wall": body.select(lambda X: X[:, 0] < 1e-9), "right": body.select(lambda X: X[:, 0] > 1 - 1e-9)}
    t0 = time.perf_counter()
    model = jr.Model(body, jr.NeoHookean(lam=1.0, mu=1.0), integration="gauss", essential=sets, solver=solver)
    build_s = time.perf_counter() - t0
    build_peak = peak_gb()
    g = np.array([-0.3, 0.0, 0.0])
    # check_stability=False: the user says the path is stable, so an iterative linear solve
    # far from equilibrium may stop early (inexact Newton's forcing term, jaxrkpm.solvers.newton.newton)
    opts = {} if check_stability else {"check_stability": False}
    t0 = time.perf_counter()
    sol = jax.block_until_ready(model.solve({"right": g}, steps=10, **opts))
    cold_s = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        sol = jax.block_until_ready(model.solve({"right": g}, steps=10, **opts))
        times.append(time.perf_counter() - t0)
    # --repeats 0 (the largest sizes): the cold solve alone, and its profile (compile in "other")
    solve_s = sorted(times)[len(times) // 2] if times else cold_s
    # the last solve's linear work, returned with it (its host seconds are disjoint parts)
    host = {k: v for k, v in sol.stats.as_dict().items() if v}
    # assembly: the pair blocks at the converged state, alone, times the assemblies made
    # (one per Newton iteration: the sparse and Krylov paths assemble at every iteration)
    prob = model.problem()
    blocks = jax.jit(lambda u, gg: prob.tangent_blocks(u, gg))
    jax.block_until_ready(blocks(sol.u, sol.g))
    t0 = time.perf_counter()
    for _ in range(3):
        jax.block_until_ready(blocks(sol.u, sol.g))
    assembly_one = (time.perf_counter() - t0) / 3
    its = int(sol.iterations)
    linear_s = sum(v for k, v in host.items() if k.endswith("_s"))   # disjoint host parts
    profile = {"assembly_s": assembly_one * its, "assembly_one_s": assembly_one, **host}
    profile["other_s"] = solve_s - profile["assembly_s"] - linear_s
    np.savez(out_npz, u=np.asarray(sol.u))
    return {"n": n, "solver": solver, "path": model.linear.name, "dof": int(len(model.sets.free) * 3),
            "check_stability": check_stability,
            "build_s": build_s, "cold_solve_s": cold_s, "warm_solve_s": solve_s, "warm_solves": records.stats(times),
            "status": sol.outcome.name, "newton_iterations": its, "residual": float(sol.residual_norm),
            "profile": profile, "peak_rss_after_build_gb": build_peak, "peak_rss_gb": peak_gb()}


def watch(proc, limit_gb, seen):
    """Kill ``proc`` once its resident memory passes ``limit_gb``; record its largest."""
    while proc.poll() is None:
        r = rss_gb(proc.pid)
        seen["max_rss_gb"] = max(seen.get("max_rss_gb", 0.0), r)
        if r > limit_gb:
            seen["killed"] = f"resident memory {r:.1f} GB passed --max-rss-gb {limit_gb}"
            proc.kill()
            return
        time.sleep(0.2)


def compare(results):
    """max |u_a - u_b| / max |u_b| between the solvers at each size."""
    import numpy as np
    out = {}
    for n in {r["n"] for r in results.values() if "npz" in r}:
        done = [(k, r) for k, r in results.items() if r.get("n") == n and "npz" in r]
        for (ka, a), (kb, b) in zip(done, done[1:]):
            ua, ub = np.load(a["npz"])["u"], np.load(b["npz"])["u"]
            out[f"{ka}_vs_{kb}"] = float(abs(ua - ub).max() / abs(ub).max())
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--n", type=int, nargs="*", default=[14, 20], help="particles per edge")
    p.add_argument("--solver", nargs="*", default=["sparse", "krylov"], choices=["sparse", "krylov", "dense"])
    p.add_argument("--repeats", type=int, default=1,
                   help="warm solves (median); 0: the cold solve alone (its figures stand for the warm ones)")
    p.add_argument("--max-rss-gb", type=float, default=9.0, help="kill a case above this resident memory")
    p.add_argument("--no-stability-check", action="store_true",
                   help="solve with check_stability=False (inexact Newton: early CG stops far from equilibrium)")
    p.add_argument("--case", nargs=3, help=argparse.SUPPRESS)
    records.add_arguments(p)
    a = p.parse_args(argv)
    if a.case:
        n, solver, npz = a.case
        print(json.dumps(run_case(int(n), solver, a.repeats, npz, not a.no_stability_check)))
        return
    run = records.start("bench_cube3d_large", a)
    out = {"load_average_before": os.getloadavg()}
    tmp = tempfile.mkdtemp(prefix="bench_cube3d_large_")
    for n in a.n:
        for solver in a.solver:
            key = f"cube_{n}_{solver}" + ("_no_stability_check" if a.no_stability_check else "")
            npz = os.path.join(tmp, key + ".npz")
            t0 = time.perf_counter()
            proc = subprocess.Popen([sys.executable, "-m", "experiments.bench_cube3d_large", "--case", str(n),
                                     solver, npz, "--repeats", str(a.repeats)]
                                    + (["--no-stability-check"] if a.no_stability_check else []),
                                    stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            seen = {}
            watcher = threading.Thread(target=watch, args=(proc, a.max_rss_gb, seen), daemon=True)
            watcher.start()
            stdout, stderr = proc.communicate()
            watcher.join()
            if proc.returncode == 0:
                res = json.loads(stdout.strip().splitlines()[-1])
                res["npz"] = npz
            else:
                res = {"n": n, "error": seen.get("killed") or (stderr.strip().splitlines() or [f"exit {proc.returncode}"])[-1]}
            res.update(seen, wall_s=time.perf_counter() - t0, load_average=os.getloadavg())
            out[key] = res
            print(key, json.dumps(res), file=sys.stderr, flush=True)
    out["solution_difference"] = compare({k: v for k, v in out.items() if k.startswith("cube_")})
    for k, v in out.items():
        if k.startswith("cube_"):
            v.pop("npz", None)
    pairs = [(n, out.get(f"cube_{n}_sparse", {}), out.get(f"cube_{n}_krylov", {})) for n in a.n]
    out["krylov_over_sparse_warm"] = {n: k["warm_solve_s"] / s["warm_solve_s"] for n, s, k in pairs
                                      if "warm_solve_s" in s and "warm_solve_s" in k}
    out["load_average_after"] = os.getloadavg()
    print(json.dumps(out, indent=2))
    records.finish(run, out, {f"krylov_over_sparse_warm n={n}": r for n, r in out["krylov_over_sparse_warm"].items()})


if __name__ == "__main__":
    main(sys.argv[1:])
