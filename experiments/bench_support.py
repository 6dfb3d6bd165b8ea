"""Benchmark: which kernel support and integration reach a given error with the least work in
3D (issue 48, build 3: "measure, do not assume").

The problem is ``bench_peer``'s clamped cube (compressible neo-Hookean, nu = 0.3, right face
pushed 20% in 5 load steps); its errors are taken against the converged hex27 reference that
``bench_peer`` keeps in ``experiments/bench_peer_reference.json`` (the reaction on the pushed
face and the displacement at the top edge's midpoint). Per n^3 cube, every variant (a kernel
support in spacings x an integration x a linear solver) is built and solved once, then timed in
``--repeats`` interleaved rounds (one warm solve each). Each row counts the work that sets the
cost: neighbours per integration point K, points Q, particle pairs (the tangent's (d, d) blocks),
free DOFs and Newton iterations. Ratios give each variant's warm time and errors over the
default's (support 2.01, Gauss, ``solver="auto"``) at the same n, and its time to the default's
reaction error (log-log interpolation over n). Run from the repository root:
``python -m experiments.bench_support [--n 6 8 10] [--support 1.51 2.01]``; writes a record
(experiments/records.py). Figures only from a quiet machine."""
from __future__ import annotations

import argparse
import json
import math
import time

from experiments import records

DEFAULT = (2.01, "gauss", "auto")
REFERENCE_KEY = ('{"case": "cube", "family": "hex27", "levels": [2, 4, 8, 16], "mu": 1.0, "nu": 0.3, '
                 '"probe": [0.5, 1.0, 1.0], "push": 0.2}')
PUSH, STEPS, NU, MU = 0.2, 5, 0.3, 1.0
PROBE = (0.5, 1.0, 1.0)


def reference() -> tuple[float, float]:
    """(reaction, probe u_y) of the cube from bench_peer's converged hex27 sequence."""
    from experiments.bench_peer import REFERENCE_FILE
    ref = json.loads(REFERENCE_FILE.read_text())[REFERENCE_KEY]
    return ref["reaction"]["value"], ref["probe"]["1"]["value"]


class Variant:
    """One cube model, built and solved once (compiled)."""

    def __init__(self, n: int, support: float, integration: str, solver: str):
        import jax
        import jax.numpy as jnp
        import numpy as np

        import jaxrkpm as jr
        self.key = (support, integration, solver)
        lam = 2.0 * MU * NU / (1.0 - 2.0 * NU)
        body = jr.Body.grid((n, n, n), 1.0 / (n - 1))
        sets = {"left": body.select(lambda Y: Y[:, 0] < 1e-9), "right": body.select(lambda Y: Y[:, 0] > 1 - 1e-9)}
        self.model = jr.Model(body, jr.NeoHookean(lam=lam, mu=MU), integration=integration, essential=sets,
                              support=support, solver=solver)
        push = jnp.array([-PUSH, 0.0, 0.0])
        self.solve = lambda: jax.block_until_ready(self.model.solve({"right": push}, steps=STEPS))   # noqa: E731
        t0 = time.perf_counter()
        self.sol = self.solve()
        self.first_s = time.perf_counter() - t0
        self.reaction = float(self.model.reaction(self.sol, "right")[0])
        self.probe = float(np.asarray(self.model.displacement(self.sol, np.array([PROBE])))[0, 1])
        prob = self.model.problem()
        self.work = {"K": int(self.model.volume.idx.shape[1]), "Q": int(self.model.volume.idx.shape[0]),
                     "pairs": int(prob.n_pairs), "free_dof": int(prob.n_free * 3),
                     "linear_solver": getattr(self.model.linear, "name", type(self.model.linear).__name__)}
        self.times = []

    def time_once(self):
        t0 = time.perf_counter()
        self.solve()
        self.times.append(time.perf_counter() - t0)

    def row(self, n: int, ref) -> dict:
        support, integration, solver = self.key
        return {"n": n, "support": support, "integration": integration, "solver": solver, **self.work,
                "newton_iterations": int(self.sol.iterations), "status": self.sol.outcome.name,
                "first_solve_s": self.first_s, "warm_s": records.stats(self.times),
                "reaction": self.reaction, "reaction_error": abs(self.reaction - ref[0]) / abs(ref[0]),
                "probe_error": abs(self.probe - ref[1]) / abs(ref[1])}


def time_at(points, error):
    """Warm time at ``error``, interpolated log-log between the two rows (error, time) that
    bracket it (None outside the rows' range)."""
    pts = sorted(points)
    for (e0, t0), (e1, t1) in zip(pts, pts[1:]):
        if e0 <= error <= e1 and e0 > 0 and e1 > e0:
            s = (math.log(error) - math.log(e0)) / (math.log(e1) - math.log(e0))
            return math.exp(math.log(t0) + s * (math.log(t1) - math.log(t0)))
    return None


def ratios_of(rows) -> dict:
    """Per variant and n: warm time and errors over the default's; and the time to the
    default's reaction error over the default's time."""
    name = lambda r: f"support {r['support']:g} {r['integration']} {r['solver']}"   # noqa: E731
    default = {r["n"]: r for r in rows if (r["support"], r["integration"], r["solver"]) == DEFAULT}
    curves = {}
    for r in rows:
        curves.setdefault(name(r), []).append((r["reaction_error"], r["warm_s"]["median"]))
    out = {}
    for r in rows:
        d = default.get(r["n"])
        if d is None or d is r:
            continue
        key = f"{name(r)} n={r['n']}"
        out[f"{key}: warm time / default's"] = r["warm_s"]["median"] / d["warm_s"]["median"]
        out[f"{key}: reaction error / default's"] = r["reaction_error"] / d["reaction_error"]
        out[f"{key}: probe error / default's"] = r["probe_error"] / d["probe_error"]
        t = time_at(curves[name(r)], d["reaction_error"])
        if t is not None:
            out[f"{key}: time to the default's reaction error / default's time"] = t / d["warm_s"]["median"]
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--n", type=int, nargs="*", default=[6, 8, 10], help="particles per edge")
    p.add_argument("--support", type=float, nargs="*", default=[1.51, 2.01], help="kernel supports (x spacing)")
    p.add_argument("--integration", nargs="*", default=["gauss", "scni", "mscni"], choices=["gauss", "scni", "mscni"])
    p.add_argument("--solver", nargs="*", default=["auto"], choices=["auto", "dense", "sparse"])
    p.add_argument("--repeats", type=int, default=3)
    records.add_arguments(p)
    a = p.parse_args(argv)
    if a.smoke:
        a.n, a.repeats, a.integration = [4], 1, ["gauss"]
    run = records.start("bench_support", a)
    ref = reference()
    rows = []
    for n in a.n:
        variants = [Variant(n, s, i, v) for s in a.support for i in a.integration for v in a.solver]
        for _ in range(a.repeats):
            for v in variants:
                v.time_once()
        for v in variants:
            rows.append(v.row(n, ref))
            print(json.dumps({k: rows[-1][k] for k in ("n", "support", "integration", "solver", "K", "pairs",
                                                       "newton_iterations", "reaction_error", "probe_error")}
                             | {"warm_s": rows[-1]["warm_s"]["median"]}), flush=True)
    records.finish(run, {"reference": {"reaction": ref[0], "probe_uy": ref[1]}, "rows": rows}, ratios_of(rows))


if __name__ == "__main__":
    main()
