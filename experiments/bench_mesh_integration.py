"""The default integration of unstructured (mesh) bodies, measured: Gauss points on the
tetrahedra against SCNI (and its stabilised form) on the 225-vertex tetrahedral box of issue 35
(scikit-fem's MeshTet.init_tensor, 9 x 5 x 5 vertices, 768 tetrahedra, 2 x 1 x 1).

Schemes: "gauss" (the Model's default order 2, 8 points a tetrahedron), "gauss1" (order 1,
one point a tetrahedron), "scni", "mscni" (its sub-cell stabilised form). For each: the
integration points, the warm solve time (median of ``--repeats`` solves
after a first, compiling one), and two accuracies:

- the affine patch test: u = (F0 - I) X on the surface particles, no load; the largest error
  of u and F at the interior particles (a consistent scheme passes it to round-off);
- a manufactured large-deformation solution, u = A (sin(2x + z), cos(x + y), y sin z) with
  A = 0.05 and the body force -Div P(F(u)) (autodiff), u prescribed on the surface: the
  volume-weighted RMS error of the particle displacements against the exact field, and the
  same on the once-refined box (``refine=1``, 1,377 particles) for the trend.

    python experiments/bench_mesh_integration.py [--repeats 3]

Prints one table; timings are only comparable on a quiet machine (``uptime``).
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import jax
import numpy as np

import jaxrkpm as jr
from experiments import records
from tests.problems import MANUFACTURED_MATERIAL, manufactured_body_force, manufactured_u, skfem_box

jax.config.update("jax_enable_x64", True)

F0 = np.array([[1.1, 0.05, 0.02], [-0.04, 0.95, 0.03], [0.01, -0.02, 1.05]])
MAT = MANUFACTURED_MATERIAL
u_exact = manufactured_u


def model(body, scheme, body_force=None):
    """``scheme``: "gauss" (order 2: 8 points a tetrahedron), "gauss1" (order 1: one point),
    "scni", "mscni"."""
    surface = body.surface_particles()
    bf = None if body_force is None else manufactured_body_force
    integration, order = ("gauss", 1) if scheme == "gauss1" else (scheme, 2)
    return jr.Model(body, MAT, integration=integration, order=order, essential={"surface": surface},
                    body_force=bf)


def timed_solve(m, g, repeats):
    sol = m.solve(g)                         # compiles
    sol.u.block_until_ready()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        sol = m.solve(g)
        sol.u.block_until_ready()
        times.append(time.perf_counter() - t0)
    return sol, float(np.median(times))


def patch(body, integration, repeats):
    m = model(body, integration)
    surface = m.set_indices("surface")
    sol, wall = timed_solve(m, {"surface": body.X[surface] @ (F0 - np.eye(3)).T}, repeats)
    inner = np.setdiff1d(np.arange(body.n), surface)
    u = np.asarray(m.particle_displacements(sol))
    F = np.asarray(m.deformation_gradient(sol, body.X[inner]))
    return (np.abs(u[inner] - body.X[inner] @ (F0 - np.eye(3)).T).max(), np.abs(F - F0).max(),
            int(m.problem().term("strain").w.shape[0]), wall)


def manufactured(body, integration, repeats):
    m = model(body, integration, body_force=True)
    surface = m.set_indices("surface")
    sol, wall = timed_solve(m, {"surface": np.asarray(u_exact(body.X[surface]))}, repeats)
    ref = np.asarray(u_exact(body.X))
    e = np.asarray(m.particle_displacements(sol)) - ref
    w = body.volumes[:, None]
    return float(np.sqrt(np.sum(w * e ** 2) / np.sum(w * ref ** 2))), wall, str(sol.outcome)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--schemes", nargs="+", default=["gauss", "gauss1", "scni", "mscni"])
    records.add_arguments(ap)
    a = ap.parse_args()
    run = records.start("bench_mesh_integration", a)
    with tempfile.TemporaryDirectory() as tmp:
        path = skfem_box(Path(tmp) / "box.vtu")
        body = jr.Body.from_mesh(path)
        fine = jr.Body.from_mesh(path, refine=1)
    print(f"box: {body.n} particles, {len(body.cells)} tetrahedra; refined: {fine.n} particles")
    print(f"{'scheme':7s} {'points':>7s} {'patch |u err|':>14s} {'patch |F err|':>14s} {'patch solve s':>14s} "
          f"{'MS rel err':>11s} {'MS solve s':>11s} {'MS rel err (refined)':>21s} {'refined solve s':>16s}")
    rows = {}
    for scheme in a.schemes:
        eu, eF, points, t_patch = patch(body, scheme, a.repeats)
        err, t_ms, status = manufactured(body, scheme, a.repeats)
        err_f, t_f, status_f = manufactured(fine, scheme, 1)
        print(f"{scheme:7s} {points:7d} {eu:14.2e} {eF:14.2e} {t_patch:14.3f} {err:11.3e} {t_ms:11.3f} "
              f"{err_f:21.3e} {t_f:16.3f}  ({status}, {status_f})")
        rows[scheme] = {"integration_points": points, "patch_u_error": eu, "patch_F_error": eF,
                        "patch_solve_s": t_patch, "manufactured_rel_error": err, "manufactured_solve_s": t_ms,
                        "refined_rel_error": err_f, "refined_solve_s": t_f, "status": [status, status_f]}
        jr.release_if_crowded()
    ratios = {}
    if "gauss" in rows:
        for scheme, r in rows.items():
            if scheme != "gauss":
                ratios[f"{scheme}_over_gauss"] = {
                    "manufactured_solve_s": r["manufactured_solve_s"] / rows["gauss"]["manufactured_solve_s"],
                    "manufactured_rel_error": r["manufactured_rel_error"] / rows["gauss"]["manufactured_rel_error"],
                    "refined_rel_error": r["refined_rel_error"] / rows["gauss"]["refined_rel_error"]}
    records.finish(run, {"particles": body.n, "tetrahedra": len(body.cells), "refined_particles": fine.n,
                         "schemes": rows}, ratios)


if __name__ == "__main__":
    main()
