"""Benchmark: a contact solve against the glued solve at the same size (issue 36). A neo-Hookean
block (2D square, or 3D cube), bottom clamped, pressed down by ``depth`` over the middle of its
top: once by a rigid frictionless box paddle with rounded edges (``jaxrkpm.Contact``, the tool
moved by its pose parameter), once by an essential set glued to the top particles under the
paddle (prescribed displacement). Per size: each model's build time, its first solve (compile
+ solve), then ``repeats`` warm solves of each taken in turn (contact, glued, contact, ...) so
that both medians see the same machine; the load steps and Newton iterations of each solve,
and the same-run ratio of the warm medians (contact / glued). The contact solve needs more
Newton iterations than the glued one (its active set settles during the load steps): the
record keeps the iteration counts so that the time ratio can be read as per-iteration cost
times iteration count. Run from the repository root:
``python -m experiments.bench_contact [--sizes 11 21] [--sizes3d 5 7] [--quick]``; writes a
record (experiments/records.py). Figures only from a quiet machine."""
from __future__ import annotations

import argparse
import json
import time

from experiments import records


# The paddle's rounded edges must span more than a particle spacing of the coarsest block: a
# convex tool adds a negative tangential stiffness (barrier slope times the sdf's curvature) at
# its edge, and with a sharper edge the 11-particle block's equilibrium is a saddle (the solve
# stops with UNSTABLE_TANGENT, as it should).
EDGE_RADIUS = 0.15


def models(n, dim, depth):
    """(contact model, its params, glued model, its prescribed values) for a block of n
    particles a side."""
    import jax.numpy as jnp
    import numpy as np

    import jaxrkpm as jr

    body = jr.Body.grid((n,) * dim, 1.0 / (n - 1))
    tol = 1e-9
    top, gap = dim - 1, 1e-3
    mid = lambda X: (X[:, top] > 1 - tol) & np.all(np.abs(X[:, :top] - 0.5) < 1 / 6 + tol, axis=1)
    bottom = body.select(lambda X: X[:, top] < tol)
    mat = jr.NeoHookean(lam=1.0, mu=1.0)
    half, radius = (1 / 6,) * top + (0.05,), EDGE_RADIUS
    c0 = (0.5,) * top + (1 + half[-1] + radius + 2 * gap,)
    paddle = jr.Contact(jr.Box(half, radius), position=c0, gap=gap, pressure=0.1, name="paddle",
                        where=lambda X: X[:, top] > 1 - tol)
    t0 = time.perf_counter()
    contact = jr.Model(body, mat, essential={"bottom": bottom}, terms=[paddle])
    build_c = time.perf_counter() - t0
    t0 = time.perf_counter()
    glued = jr.Model(body, mat, essential={"bottom": bottom, "paddle": body.select(mid)})
    build_g = time.perf_counter() - t0
    # pressed ``depth`` past first touch (2 gap), as far as the glued particles are moved
    params = {"paddle": {"position": jnp.asarray(c0) - (depth + 2 * gap) * jnp.eye(dim)[top]}}
    down = tuple(-depth * np.eye(dim)[top])
    return body, (contact, params, build_c), (glued, {"paddle": down}, build_g)


def case(n, dim, depth, repeats, steps):
    import jaxrkpm as jr

    body, (contact, params, build_c), (glued, values, build_g) = models(n, dim, depth)
    solves = {"contact": lambda: contact.solve(params=params, steps=steps),
              "glued": lambda: glued.solve(values, steps=steps)}
    out = {k: {"build_s": b} for k, b in (("contact", build_c), ("glued", build_g))}
    sols = {}
    for k, solve in solves.items():
        t0 = time.perf_counter()
        sols[k] = solve()
        out[k]["first_solve_s"] = time.perf_counter() - t0
    times = {k: [] for k in solves}
    for _ in range(repeats):                     # interleaved: both see the same machine
        for k, solve in solves.items():
            t0 = time.perf_counter()
            solve()
            times[k].append(time.perf_counter() - t0)
    for k, sol in sols.items():
        out[k].update(warm_solve_s=records.stats(times[k]), message=str(sol.message),
                      newton_iterations=int(sol.iterations), load_steps=int(sol.steps))
    out["contact"]["force"] = float(jr.contact_forces(contact, sols["contact"], "paddle", params).force[dim - 1])
    out["glued"]["force"] = float(glued.reaction(sols["glued"], "paddle")[dim - 1])
    out["particles"] = body.n
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="*", default=[11, 21], help="2D particles a side")
    ap.add_argument("--sizes3d", type=int, nargs="*", default=[5, 7], help="3D particles a side")
    ap.add_argument("--depth", type=float, default=0.05)
    ap.add_argument("--steps", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--quick", action="store_true", help="one tiny size per dimension, one repeat (implies --smoke)")
    records.add_arguments(ap)
    a = ap.parse_args()
    if a.quick:
        a.sizes, a.sizes3d, a.repeats, a.smoke = [5], [3], 1, True
    run = records.start("bench_contact", a)
    figures, ratios = {}, {}
    for dim, sizes in ((2, a.sizes), (3, a.sizes3d)):
        for n in sizes:
            r = case(n, dim, a.depth, a.repeats, a.steps)
            key = f"{dim}d_{n}"
            figures[key] = r
            c, g = r["contact"]["warm_solve_s"]["median"], r["glued"]["warm_solve_s"]["median"]
            ratios[f"{key}_warm_contact_over_glued"] = c / g if c and g else None
            ratios[f"{key}_newton_contact_over_glued"] = (r["contact"]["newton_iterations"]
                                                        / max(r["glued"]["newton_iterations"], 1))
            print(json.dumps({key: r}, indent=1))
    records.finish(run, figures, ratios)


if __name__ == "__main__":
    main()
