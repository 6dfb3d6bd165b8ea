"""Hertz line contact: a rigid cylinder (a disc, plane strain) pressed into an elastic block,
against Hertz's half-width a = sqrt(4 P R / (pi E*)) and peak pressure p_max = 2 P / (pi a)
(E* = E / (1 - nu^2), P the force per unit thickness), at the measured force P.

The half-model: the block's right half, its symmetry plane held by a frictionless rigid wall
(a ``HalfSpace`` contact: rollers, as the library has no per-component essential sets), its
bottom clamped; the disc's centre on the symmetry plane. The measured half-width comes from
the pressure's second moment (for Hertz's p = p_max sqrt(1 - x^2 / a^2),
int p x^2 / int p = a^2 / 4); Hertz's ellipse fitted to the nodal pressures is recorded too,
but the node on the axis (the half-model's corner, held by both tools) carries a low pressure
that spoils the fit. The peak pressure is the largest nodal pressure.

    python experiments/hertz_contact.py [--spacing 0.02] [--depths 0.004 0.008] [--quick]
"""
from __future__ import annotations

import argparse
import json
import time

import jax.numpy as jnp
import numpy as np

import jaxrkpm as jr


def run(spacing=0.02, width=1.0, depth=1.0, radius=1.0, young=1.0, nu=0.3, depths=(0.004, 0.008), gap=None,
        steps=4):
    gap = 0.02 * spacing if gap is None else gap
    nx, ny = int(round(width / spacing)) + 1, int(round(depth / spacing)) + 1
    body = jr.Body.grid((nx, ny), spacing, origin=(0.0, -depth))
    mu = young / (2 * (1 + nu))
    lam = young * nu / ((1 + nu) * (1 - 2 * nu))
    p0 = young   # the barrier stiffer than the pressures met: its compliance about 1% of the block's
    tol = 1e-9 * spacing
    disc = jr.Contact(jr.Sphere(radius), position=(0.0, radius + 2 * gap), gap=gap, pressure=p0, name="disc",
                      where=lambda X: (X[:, 1] > -tol) & (X[:, 0] < 0.5 * width))
    wall = jr.Contact(jr.HalfSpace((1.0, 0.0)), position=(-gap, 0.0), gap=gap, pressure=p0, name="wall",
                      where=lambda X: X[:, 0] < tol)
    t0 = time.perf_counter()
    model = jr.Model(body, jr.SaintVenantKirchhoff(lam, mu),
                     essential={"bottom": body.select(lambda X: X[:, 1] < -depth + tol)}, terms=[disc, wall])
    build = time.perf_counter() - t0
    estar = young / (1 - nu ** 2)
    out = []
    for dd in depths:
        params = {"disc": {"position": jnp.array([0.0, radius + 2 * gap - dd])},
                  "wall": {"position": jnp.array([-gap, 0.0])}}
        t0 = time.perf_counter()
        sol = model.solve(params=params, steps=steps)   # each load from load 0
        t = time.perf_counter() - t0
        r = jr.contact_forces(model, sol, "disc", params)
        x = np.asarray(r.points)[:, 0]
        p = np.asarray(r.pressure)
        w = np.asarray(model.problem(params).term("disc").w)
        # the half-model's force and moments, mirrored: P = 2 int_0 p dx (per unit thickness)
        P = -2 * float(r.force[1])
        a_moment = 2 * np.sqrt(np.sum(w * p * x ** 2) / np.sum(w * p))
        # Hertz's ellipse p^2 = p_max^2 (1 - x^2 / a^2) fitted to the points that carry load
        on = p > 0.05 * p.max()
        slope, icpt = np.polyfit(x[on] ** 2, p[on] ** 2, 1)
        a_fit, p_fit = np.sqrt(-icpt / slope), np.sqrt(icpt)
        a_fem = a_moment
        a_h = np.sqrt(4 * P * radius / (np.pi * estar))
        pmax_h = 2 * P / (np.pi * a_h)
        out.append({"depth": dd, "force": P, "half_width": a_fem, "hertz_half_width": a_h,
                    "half_width_ratio": a_fem / a_h, "fitted_half_width_ratio": a_fit / a_h,
                    "fitted_peak_ratio": p_fit / (2 * P / (np.pi * a_h)), "peak_pressure": float(p.max()),
                    "hertz_peak_pressure": pmax_h, "peak_ratio": float(p.max()) / pmax_h,
                    "active": int(np.sum(np.asarray(r.active))), "min_gap": float(r.min_gap),
                    "block_over_half_width": min(2 * width, depth) / a_h, "solve_s": t,
                    "status": str(sol.message), "x": x[np.argsort(x)][:12].tolist(),
                    "pressure": p[np.argsort(x)][:12].tolist()})
        print(json.dumps(out[-1]))
    return {"spacing": spacing, "width": width, "depth": depth, "radius": radius, "young": young, "nu": nu,
            "gap": gap, "particles": body.n, "build_s": build, "loads": out}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spacing", type=float, default=0.02)
    ap.add_argument("--depths", type=float, nargs="+", default=[0.004, 0.008])
    ap.add_argument("--quick", action="store_true", help="a tiny coarse run (checks that it runs)")
    ap.add_argument("--out", default=None, help="write the JSON record here")
    a = ap.parse_args()
    rec = run(spacing=0.1, width=0.5, depth=0.5, depths=(0.01,)) if a.quick else run(a.spacing, depths=a.depths)
    rec["note"] = "timings beside other processes are not figures: retake on a quiet machine"
    if a.out:
        with open(a.out, "w") as f:
            json.dump(rec, f, indent=1)
    print(json.dumps(rec, indent=1))


if __name__ == "__main__":
    main()
