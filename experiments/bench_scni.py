"""Benchmark: time per Newton iteration, SCNI (and the sub-cell stabilised MSCNI) against
Gauss quadrature (2x2 points per background cell), on the thesis' Fung block (9x9 and 33x33;
left edge immobile, paddle of the right-edge particles with |y - 0.5| <= 0.125 pushed 5%).

Per scheme and size, in the same process: build, one solve to compile, then ``repeats`` warm
solves of the same problem; time per iteration = solve time / Newton iterations (median over
the repeats). The assembly alone (residual + tangent, jitted) is timed too, since at 33x33 the
dense LU of the tangent is shared by both schemes and dominates. Ratios are SCNI / Gauss.
Prints JSON."""
from __future__ import annotations

import argparse
import json
import statistics
import time

import jax
import jax.numpy as jnp

from experiments.compress import setup
from jaxrkpm import solve as jsolve

SCHEMES = ("gauss", "scni", "mscni")


def _median_time(fn, repeats):
    fn()  # warm
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts), ts


def bench(n: int, integration: str, repeats: int = 7, solver: str = "auto"):
    t0 = time.perf_counter()
    model = setup(n, integration)
    if solver != "auto":
        from experiments.compress import MATERIALS
        import jaxrkpm as jr
        model = jr.Model(model.body, MATERIALS["fung"](), integration=integration, solver=solver,
                         essential={k: model.set_indices(k) for k in model.set_names})
    build = time.perf_counter() - t0
    g = jnp.array([-0.05, 0.0])
    t0 = time.perf_counter()
    sol = model.solve({"paddle": g})
    sol.u.block_until_ready()
    first = time.perf_counter() - t0
    iters = int(sol.iterations)
    solve_med, solve_all = _median_time(lambda: model.solve({"paddle": g}).u, repeats)

    cfg = model._config()
    W = model.material.W
    assemble = jax.jit(lambda ops, params, u, g: (jsolve.residual(ops, params, W, u, g, 1.0),
                                                    jsolve.tangent(ops, params, cfg, u, g)))
    asm_med, _ = _median_time(lambda: assemble(model.ops, model.params, sol.u, sol.g), repeats)
    return {"n": n, "integration": integration, "solver": model.linear.name,
            "integration_points": int(model.ops.w.shape[0]), "neighbours_K": int(model.ops.idx.shape[1]),
            "free_dof": int(sol.u.size), "build_s": build, "first_solve_s_incl_compile": first,
            "newton_iterations": iters, "warm_solve_s_median": solve_med,
            "time_per_iteration_s": solve_med / iters, "assembly_s_median": asm_med,
            "warm_solve_s_all": solve_all}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--sizes", type=int, nargs="*", default=[9, 33])
    p.add_argument("--repeats", type=int, default=7)
    p.add_argument("--schemes", nargs="*", default=list(SCHEMES))
    p.add_argument("--sparse", action="store_true", help="also time the sparse linear path")
    a = p.parse_args(argv)
    out = {"results": [], "ratios_vs_gauss": {}}
    solvers = ["auto"] + (["sparse"] if a.sparse else [])
    for n in a.sizes:
        for solver in solvers:
            res = {s: bench(n, s, a.repeats, solver) for s in a.schemes}
            out["results"].extend(res.values())
            if "gauss" in res:
                for s in a.schemes:
                    if s == "gauss":
                        continue
                    key = f"{s}/gauss {n}x{n} {res[s]['solver']}"
                    out["ratios_vs_gauss"][key] = {
                        "time_per_iteration": res[s]["time_per_iteration_s"] / res["gauss"]["time_per_iteration_s"],
                        "assembly": res[s]["assembly_s_median"] / res["gauss"]["assembly_s_median"],
                        "integration_points": res[s]["integration_points"] / res["gauss"]["integration_points"]}
    print(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    main()
