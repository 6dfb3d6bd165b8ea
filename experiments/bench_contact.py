"""Benchmark: a contact solve against the glued solve at the same size (issue 36). A neo-Hookean
block, bottom clamped, pressed down by ``depth`` over its middle third: once by a rigid
frictionless box paddle with rounded edges (``jaxrkpm.Contact``, the tool moved by its pose
parameter), once by an essential set glued to the same top particles (prescribed displacement).
Reports the first solve (compile + solve) and the warm solve's median time, load steps and
Newton iterations of each, and their ratios. Run from the repository root:
``python -m experiments.bench_contact [--sizes 11 21] [--quick]``; writes a record
(experiments/records.py). Figures only from a quiet machine."""
from __future__ import annotations

import argparse
import json
import time

from experiments import records


def case(n, depth, repeats, steps):
    import jax.numpy as jnp
    import numpy as np

    import jaxrkpm as jr

    body = jr.Body.grid((n, n), 1.0 / (n - 1))
    tol = 1e-9
    mid = lambda X: (X[:, 1] > 1 - tol) & (np.abs(X[:, 0] - 0.5) < 1 / 6 + tol)
    bottom = body.select(lambda X: X[:, 1] < tol)
    mat = jr.NeoHookean(lam=1.0, mu=1.0)
    gap = 1e-3
    out = {}

    def timed(solve):
        t0 = time.perf_counter()
        sol = solve()
        first = time.perf_counter() - t0
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            solve()
            times.append(time.perf_counter() - t0)
        return sol, first, times

    t0 = time.perf_counter()
    paddle = jr.Contact(jr.Box((1 / 6, 0.05), 0.05), position=(0.5, 1.1 + 2 * gap), gap=gap, pressure=0.1,
                        name="paddle", where=lambda X: X[:, 1] > 1 - tol)
    contact = jr.Model(body, mat, essential={"bottom": bottom}, terms=[paddle])
    build_c = time.perf_counter() - t0
    params = {"paddle": {"position": jnp.array([0.5, 1.1 + 2 * gap - depth])}}
    sol, first, times = timed(lambda: contact.solve(params=params, steps=steps))
    out["contact"] = {"build_s": build_c, "first_solve_s": first, "warm_solve_s": records.stats(times),
                      "message": str(sol.message), "force": float(jr.contact_forces(contact, sol, "paddle",
                                                                                     params).force[1])}
    t0 = time.perf_counter()
    glued = jr.Model(body, mat, essential={"bottom": bottom, "paddle": body.select(mid)})
    build_g = time.perf_counter() - t0
    sol, first, times = timed(lambda: glued.solve({"paddle": (0.0, -depth)}, steps=steps))
    out["glued"] = {"build_s": build_g, "first_solve_s": first, "warm_solve_s": records.stats(times),
                    "message": str(sol.message), "force": float(glued.reaction(sol, "paddle")[1])}
    out["particles"] = body.n
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[11, 21])
    ap.add_argument("--depth", type=float, default=0.05)
    ap.add_argument("--steps", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="one tiny size, one repeat (implies --smoke)")
    records.add_arguments(ap)
    a = ap.parse_args()
    if a.quick:
        a.sizes, a.repeats, a.smoke = [5], 1, True
    run = records.start("bench_contact", a)
    figures, ratios = {}, {}
    for n in a.sizes:
        r = case(n, a.depth, a.repeats, a.steps)
        figures[f"2d_{n}"] = r
        c, g = r["contact"]["warm_solve_s"]["median"], r["glued"]["warm_solve_s"]["median"]
        ratios[f"2d_{n}_warm_contact_over_glued"] = c / g if c and g else None
        print(json.dumps({f"2d_{n}": r}, indent=1))
    records.finish(run, figures, ratios)


if __name__ == "__main__":
    main()
