"""Benchmark: time per Newton iteration, SCNI (and the sub-cell stabilised MSCNI) against
Gauss quadrature (2x2 points per background cell), on the thesis' Fung block (9x9 and 33x33;
left edge immobile, paddle of the right-edge particles with |y - 0.5| <= 0.125 pushed 5%).

Per size, in the same process: build and compile every scheme, then ``repeats`` rounds that
time one warm solve of each scheme in turn (interleaved, so a drifting machine load hits all
schemes alike); time per iteration = solve time / Newton iterations (median over
the repeats). The assembly alone (residual + tangent, jitted) is timed too, since at 33x33 the
dense LU of the tangent is shared by both schemes and dominates. Ratios are SCNI / Gauss.
Prints JSON and writes a record (experiments/records.py)."""
from __future__ import annotations

import argparse
import json
import statistics
import time

import jax
import jax.numpy as jnp

from experiments import records
from jaxrkpm.thesis.studies.compress import setup

SCHEMES = ("gauss", "scni", "mscni")


class Case:
    """One model, compiled: ``solve()`` and ``assemble()`` time one warm call each."""

    def __init__(self, n, integration, solver="auto"):
        t0 = time.perf_counter()
        model = setup(n, integration)
        if solver != "auto":
            import jaxrkpm as jr
            from jaxrkpm.thesis.studies.compress import MATERIALS
            model = jr.Model(model.body, MATERIALS["fung"](), integration=integration, solver=solver,
                             essential={k: model.set_indices(k) for k in model.set_names})
        self.build_s = time.perf_counter() - t0
        self.model, self.n, self.integration = model, n, integration
        self.g = jnp.array([-0.05, 0.0])
        t0 = time.perf_counter()
        sol = model.solve({"paddle": self.g})
        sol.u.block_until_ready()
        self.first_s = time.perf_counter() - t0
        self.iters = int(sol.iterations)
        self._prob = model.problem()
        self._asm = jax.jit(lambda prob, u, g: (prob.residual(u, g), prob.tangent(u, g)))
        self.sol = sol
        jax.block_until_ready(self._asm(self._prob, sol.u, sol.g))
        self.t_solve, self.t_asm = [], []

    def time_once(self):
        t0 = time.perf_counter()
        s = self.model.solve({"paddle": self.g})
        s.u.block_until_ready()
        self.t_solve.append(time.perf_counter() - t0)
        assert int(s.iterations) == self.iters
        t0 = time.perf_counter()
        jax.block_until_ready(self._asm(self._prob, self.sol.u, self.sol.g))
        self.t_asm.append(time.perf_counter() - t0)

    def result(self):
        med = statistics.median(self.t_solve)
        m = self.model
        return {"n": self.n, "integration": self.integration, "solver": m.linear.name,
                "integration_points": int(m.problem().term("strain").w.shape[0]),
                "neighbours_K": int(m.problem().term("strain").idx.shape[1]),
                "tangent_pairs": int(m.problem().n_pairs), "free_dof": int(self.sol.u.size),
                "build_s": self.build_s, "first_solve_s_incl_compile": self.first_s,
                "newton_iterations": self.iters, "warm_solve_s_median": med,
                "time_per_iteration_s": med / self.iters,
                "time_per_iteration_s_min": min(self.t_solve) / self.iters,
                "assembly_s_median": statistics.median(self.t_asm),
                "warm_solve_s": records.stats(self.t_solve), "assembly_s": records.stats(self.t_asm)}


def bench(n, schemes, repeats, solver="auto"):
    """All schemes of one size, timed in interleaved rounds (fair under a drifting load)."""
    cases = {s: Case(n, s, solver) for s in schemes}
    for _ in range(repeats):
        for c in cases.values():
            c.time_once()
    return {s: c.result() for s, c in cases.items()}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--sizes", type=int, nargs="*", default=[9, 33])
    p.add_argument("--repeats", type=int, default=7)
    p.add_argument("--schemes", nargs="*", default=list(SCHEMES))
    p.add_argument("--sparse", action="store_true", help="also time the sparse linear path")
    records.add_arguments(p)
    a = p.parse_args(argv)
    run = records.start("bench_scni", a)
    out = {"results": [], "ratios_vs_gauss": {}}
    solvers = ["auto"] + (["sparse"] if a.sparse else [])
    for n in a.sizes:
        for solver in solvers:
            res = bench(n, a.schemes, a.repeats, solver)
            out["results"].extend(res.values())
            if "gauss" in res:
                for s in a.schemes:
                    if s == "gauss":
                        continue
                    key = f"{s}/gauss {n}x{n} {res[s]['solver']}"
                    out["ratios_vs_gauss"][key] = {
                        "time_per_iteration": res[s]["time_per_iteration_s"] / res["gauss"]["time_per_iteration_s"],
                        "time_per_iteration_min": (res[s]["time_per_iteration_s_min"]
                                                   / res["gauss"]["time_per_iteration_s_min"]),
                        "assembly": res[s]["assembly_s_median"] / res["gauss"]["assembly_s_median"],
                        "integration_points": res[s]["integration_points"] / res["gauss"]["integration_points"]}
    print(json.dumps(out, indent=2))
    records.finish(run, out, out["ratios_vs_gauss"])
    return out


if __name__ == "__main__":
    main()
