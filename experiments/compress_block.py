"""The plain square compressed between a fixed and a rigidly moved edge (issue 19): n x n
particles on the unit square, left edge x = 0 held, the whole right edge moved rigidly by
20% compression (Fung alpha = beta = 1) or 20% compression + 10% shear (Quadratic), for
Gauss, SCNI and MSCNI. Per case: the stable-branch solve's status, the load fraction reached,
whether the final state lies on a secondary branch, the critical points passed, the smallest
eigenvalue of K_ff at the end, the run time; then an independent check of whether stable
states exist past the point where the solve stopped: from the last stable
state, an exact trust-region minimisation of the energy (``jaxrkpm.solvers.minimise.stable_beyond``:
scipy's trust-exact, dense Hessian, det F <= 0 refused) at load fractions increasing by
``--dt``, until it fails to end on an equilibrium with K_ff positive definite. Writes every
row to a JSON file.

    python experiments/compress_block.py            # 33x33 (the issue's case), all six
    python experiments/compress_block.py --n 17 --case compression --integration gauss

Measured (33x33, 2-core machine shared with other jobs; results/compress_block_33.json):
every case stops short of the full load, and in every one the trust-region minimisation a
fraction of a percent further drives the smallest det F to ~1e-14 at a corner of the moved
edge while |r| stays O(1) and the energy keeps falling: past that point the discrete energy
has no minimum with det F > 0 (a corner folds flat: the energies of eqs 5.1-5.2 stay
bounded as det F -> 0), so no stable state of the full load exists on that path to reach.

With the volumetric barrier kappa/2 (ln J)^2 (issue 38; cases ``compression_barrier`` and
``compression_shear_barrier``, kappa = the material's small-strain shear modulus), Gauss,
33x33 (compress_block_33_barrier.json): both reach the full load in one stable-branch solve,
no critical point passed, K_ff positive definite at the end (smallest eigenvalue 2.6 and
2.4e-3), smallest det F 0.55 and 0.51. SCNI and MSCNI with the barrier are not run yet.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxrkpm as jr
from jaxrkpm.solvers.minimise import stable_beyond

CASES = {
    "compression": (lambda: jr.Fung(alpha=1.0, beta=1.0), (-0.2, 0.0)),
    "compression_shear": (lambda: jr.Quadratic(alpha=1.0), (-0.2, 0.1)),
    # the same with the volumetric barrier kappa/2 (ln J)^2 (issue 38), kappa = the material's
    # small-strain shear modulus (Fung: 2 (C_1212 + A_1212) = 509; Quadratic alpha = 1: 1/2)
    "compression_barrier": (lambda: jr.with_barrier(jr.Fung(alpha=1.0, beta=1.0), kappa=509.0), (-0.2, 0.0)),
    "compression_shear_barrier": (lambda: jr.with_barrier(jr.Quadratic(alpha=1.0), kappa=0.5), (-0.2, 0.1)),
}

_TANGENT = jax.jit(lambda prob, u, g: prob.tangent(u, g))


def block_model(n: int, integration: str, material) -> jr.Model:
    """The unit square, n x n particles: sets "wall" (x = 0) and "edge" (x = 1)."""
    body = jr.Body.grid((n, n), 1.0 / (n - 1))
    sets = {"wall": body.select(lambda X: X[:, 0] < 1e-9), "edge": body.select(lambda X: X[:, 0] > 1 - 1e-9)}
    return jr.Model(body, material, integration=integration, essential=sets)


def run_case(n: int, integration: str, case: str, steps: int = 10, warm: bool = False, check: bool = True,
             dt: float = 0.002, **options) -> dict:
    """One solve of a case: a dict of what it reached (see the module docstring)."""
    material, push = CASES[case]
    model = block_model(n, integration, material())
    t0 = time.perf_counter()
    sol = model.solve({"edge": jnp.asarray(push)}, steps=steps, throw=False, **options)
    sol.u.block_until_ready()
    cold = time.perf_counter() - t0
    row = {"n": n, "integration": integration, "case": case, "push": list(push), "options": options}
    if warm:
        t0 = time.perf_counter()
        again = model.solve({"edge": jnp.asarray(push)}, steps=steps, throw=False, **options)
        again.u.block_until_ready()
        row["time_warm_s"] = time.perf_counter() - t0
    prob = model.problem()
    K = np.asarray(_TANGENT(prob, sol.u, sol.g))
    crit = np.asarray(sol.critical.t_unstable)
    row.update({"status": sol.outcome.name, "t": float(sol.t), "compression": float(sol.t) * -push[0],
                "branch": int(sol.branch), "critical_t": crit[np.isfinite(crit)].tolist(),
                "min_eig": float(np.linalg.eigvalsh(K)[0]), "min_detF": float(prob.energy(sol.u, sol.g)[1]),
                "iterations": int(sol.iterations), "cuts": int(sol.cuts), "time_cold_s": cold})
    if check and float(sol.t) < 1.0:
        # minima every dt of the whole load, from the last stable state to the full load
        t0 = time.perf_counter()
        b = stable_beyond(model.problem(), sol, model.prescribed({"edge": jnp.asarray(push)}), min(1.0, dt / (1 - float(sol.t))))
        t = float(sol.t)
        b.update({"from_t": t, "last_stable_t": t + b["reached"] * (1 - t), "time_s": time.perf_counter() - t0})
        if "failed_at" in b:
            b["failed_t"] = t + b["failed_at"] * (1 - t)
        row["beyond"] = b
    return row


def describe(r: dict) -> str:
    line = (f"{r['n']}x{r['n']} {r['case']:18s} {r['integration']:6s} {r['status']:16s} t={r['t']:.4f} "
            f"branch={r['branch']} critical at t={[round(c, 4) for c in r['critical_t']]} "
            f"min eig K_ff={r['min_eig']:.2e} min det F={r['min_detF']:.3f} {r['iterations']} its "
            f"{r['cuts']} cuts {r['time_cold_s']:.1f} s")
    b = r.get("beyond")
    if b:
        line += (f"\n    trust-region minima: stable up to t={b['last_stable_t']:.4f}; at t={b.get('failed_t', 1):.4f} "
                 f"min det F={b.get('min_detF', float('nan')):.2e}, |r|={b.get('residual', float('nan')):.2e}, "
                 f"lowest eigenvalues {np.round(b.get('lowest_eigenvalues', []), 4).tolist()} "
                 f"({'collapse: det F -> 0' if b.get('collapse') else 'no stable minimum'}; {b['time_s']:.0f} s)")
    return line


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--n", type=int, default=33)
    p.add_argument("--steps", type=int, default=10)
    p.add_argument("--integration", nargs="+", default=["gauss", "scni", "mscni"])
    p.add_argument("--case", nargs="+", default=list(CASES))
    p.add_argument("--dt", type=float, default=0.002, help="load-fraction increment of the trust-region check")
    p.add_argument("--warm", action="store_true", help="time a second (warm) solve too")
    p.add_argument("--no-check", dest="check", action="store_false", help="skip the trust-region check")
    p.add_argument("--out", default=None, help="JSON file (default results/compress_block_<n>.json)")
    a = p.parse_args(argv)
    out = Path(a.out or f"results/compress_block_{a.n}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    rows = []
    for case in a.case:
        for integration in a.integration:
            r = run_case(a.n, integration, case, a.steps, a.warm, a.check, a.dt, stable_branch=True)
            rows.append(r)
            print(describe(r), flush=True)
            out.write_text(json.dumps(rows, indent=1))
    return rows


if __name__ == "__main__":
    main()
