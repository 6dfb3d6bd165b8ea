"""The plain square compressed between a fixed and a rigidly moved edge (issue 19): n x n
particles on the unit square, left edge x = 0 held, the whole right edge moved rigidly by
20% compression (Fung alpha = beta = 1) or 20% compression + 10% shear (Quadratic), for
Gauss, SCNI and MSCNI. Prints, per case, the status, the load fraction reached, whether the
final state lies on a secondary branch, the critical points passed, the smallest eigenvalue
of K_ff at the end, and the run time (compile included, then warm).

    python experiments/compress_block.py            # 33x33 (the issue's case)
    python experiments/compress_block.py --n 17 --steps 10
"""
from __future__ import annotations

import argparse
import time

import jax.numpy as jnp
import numpy as np

import jaxrkpm as jr

CASES = {
    "compression": (lambda: jr.Fung(alpha=1.0, beta=1.0), (-0.2, 0.0)),
    "compression_shear": (lambda: jr.Quadratic(alpha=1.0), (-0.2, 0.1)),
}


def block_model(n: int, integration: str, material) -> jr.Model:
    """The unit square, n x n particles: sets "wall" (x = 0) and "edge" (x = 1)."""
    body = jr.Body.grid((n, n), 1.0 / (n - 1))
    sets = {"wall": body.select(lambda X: X[:, 0] < 1e-9), "edge": body.select(lambda X: X[:, 0] > 1 - 1e-9)}
    return jr.Model(body, material, integration=integration, essential=sets)


def run_case(n: int, integration: str, case: str, steps: int = 10, **options) -> dict:
    """One solve of a case: a dict of what it reached (see the module docstring)."""
    material, push = CASES[case]
    model = block_model(n, integration, material())
    t0 = time.perf_counter()
    sol = model.solve({"edge": jnp.asarray(push)}, steps=steps, throw=False, **options)
    sol.u.block_until_ready()
    cold = time.perf_counter() - t0
    t0 = time.perf_counter()
    again = model.solve({"edge": jnp.asarray(push)}, steps=steps, throw=False, **options)
    again.u.block_until_ready()
    warm = time.perf_counter() - t0
    K = np.asarray(model.problem().tangent(sol.u, sol.g))
    crit = np.asarray(sol.critical.t_unstable)
    return {"n": n, "integration": integration, "case": case, "status": sol.outcome.name,
            "t": float(sol.t), "branch": int(sol.branch), "critical_t": crit[np.isfinite(crit)].tolist(),
            "min_eig": float(np.linalg.eigvalsh(K)[0]), "iterations": int(sol.iterations),
            "cuts": int(sol.cuts), "time_cold_s": cold, "time_warm_s": warm}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, default=33)
    p.add_argument("--steps", type=int, default=10)
    p.add_argument("--integration", nargs="+", default=["gauss", "scni", "mscni"])
    p.add_argument("--case", nargs="+", default=list(CASES))
    a = p.parse_args(argv)
    rows = []
    for case in a.case:
        for integration in a.integration:
            r = run_case(a.n, integration, case, a.steps, stable_branch=True)
            rows.append(r)
            print(f"{r['n']}x{r['n']} {case:18s} {integration:6s} {r['status']:16s} t={r['t']:.3f} "
                  f"branch={r['branch']} critical at t={[round(c, 4) for c in r['critical_t']]} "
                  f"min eig K_ff={r['min_eig']:.2e} {r['iterations']} its {r['cuts']} cuts "
                  f"{r['time_cold_s']:.1f} s cold, {r['time_warm_s']:.1f} s warm", flush=True)
    return rows


if __name__ == "__main__":
    main()
