"""Hertz line contact: a rigid cylinder (a disc, plane strain) pressed into an elastic block,
against Hertz's half-width a = sqrt(4 P R / (pi E*)) and peak pressure p_max = 2 P / (pi a)
(E* = E / (1 - nu^2), P the force per unit thickness), at the measured force P.

The half-model: the block's right half, its symmetry plane held by a frictionless rigid wall
(a ``HalfSpace`` contact: rollers, as the library has no per-component essential sets), its
bottom clamped; the disc's centre on the symmetry plane. The contact points are the model's
boundary Gauss points (``jaxrkpm.mechanics.contact``). The measured half-width a and peak
pressure p_max are those of Hertz's profile p(x) = p_max sqrt(1 - x^2 / a^2) (0 beyond a)
fitted by least squares to the contact points' pressures (weighted by their boundary
weights; p_max by linear least squares for each a, a by a bounded scalar search): a fit
uses every point, where the last point in contact or the first out of it alone would give a
only to within a point spacing. Recorded too: the largest point pressure and the half-width
from the pressure's second moment (for Hertz's profile int p x^2 / int p = a^2 / 4).

Why a cylinder four times the block's depth: Hertz's solution is of small strains (of the order
of a / R) on a half-space, so the radius is large against the half-width, which stays several
spacings wide and a tenth of the block; and the barrier's range is kept small against the
cylinder's rise a^2 / 2R over the contact, as the barrier's standoff varies by a fraction of
its range with the pressure.

    python experiments/hertz_contact.py [--spacing 0.02] [--radius 4] [--depths 0.002 0.0038]
        [--gap G] [--integration gauss] [--quick] [--out F]
"""
from __future__ import annotations

import argparse
import json
import time

import jax.numpy as jnp
import numpy as np
from scipy.optimize import minimize_scalar

import jaxrkpm as jr


def fit_hertz(x, p, w, guess):
    """(a, p_max) of Hertz's profile p_max sqrt(1 - x^2 / a^2) fitted to pressures p at
    points x with weights w (least squares; p_max linear for each a)."""
    def best(a):
        s = np.sqrt(np.clip(1 - (x / a) ** 2, 0.0, None))
        p0 = np.sum(w * p * s) / max(np.sum(w * s * s), 1e-300)
        return p0, np.sum(w * (p - p0 * s) ** 2)

    a = minimize_scalar(lambda a: best(a)[1], bounds=(0.3 * guess, 3.0 * guess), method="bounded",
                        options={"xatol": 1e-10 * guess}).x
    return float(a), float(best(a)[0])


def run(spacing=0.02, width=1.0, depth=1.0, radius=4.0, young=1.0, nu=0.3, depths=(0.002, 0.0038), gap=None,
        steps=4, integration="gauss"):
    gap = 0.005 * spacing if gap is None else gap
    nx, ny = round(width / spacing) + 1, round(depth / spacing) + 1
    if max(abs((nx - 1) * spacing - width), abs((ny - 1) * spacing - depth)) > 1e-9 * spacing:
        raise ValueError(f"spacing {spacing} must divide the width {width} and the depth {depth}")
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
    model = jr.Model(body, jr.SaintVenantKirchhoff(lam, mu), integration=integration,
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
        a_fit, p_fit = fit_hertz(x, p, w, a_moment)
        a_h = np.sqrt(4 * P * radius / (np.pi * estar))
        pmax_h = 2 * P / (np.pi * a_h)
        out.append({"depth": dd, "force": P, "half_width": a_fit, "hertz_half_width": a_h,
                    "half_width_ratio": a_fit / a_h, "peak_pressure": p_fit, "hertz_peak_pressure": pmax_h,
                    "peak_ratio": p_fit / pmax_h, "moment_half_width_ratio": a_moment / a_h,
                    "largest_point_pressure_ratio": float(p.max()) / pmax_h,
                    "active": int(np.sum(np.asarray(r.active))), "min_gap": float(r.min_gap),
                    "block_over_half_width": min(2 * width, depth) / a_h, "solve_s": t,
                    "status": str(sol.message), "x": x[np.argsort(x)][:24].tolist(),
                    "pressure": p[np.argsort(x)][:24].tolist()})
        print(json.dumps(out[-1]))
    return {"spacing": spacing, "integration": integration, "width": width, "depth": depth, "radius": radius, "young": young, "nu": nu,
            "gap": gap, "particles": body.n, "build_s": build, "loads": out}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spacing", type=float, default=0.02)
    ap.add_argument("--depths", type=float, nargs="+", default=[0.002, 0.0038])
    ap.add_argument("--radius", type=float, default=4.0, help="the cylinder's radius")
    ap.add_argument("--gap", type=float, default=None, help="the barrier's range (default: 0.005 x spacing)")
    ap.add_argument("--integration", default="gauss", help="gauss | scni | mscni")
    ap.add_argument("--quick", action="store_true", help="a tiny coarse run (checks that it runs)")
    ap.add_argument("--out", default=None, help="write the JSON record here")
    a = ap.parse_args()
    if a.quick:
        rec = run(spacing=0.1, width=0.5, depth=0.5, radius=1.0, depths=(0.01,), gap=2e-3)
    else:
        rec = run(a.spacing, radius=a.radius, depths=a.depths, gap=a.gap, integration=a.integration)
    rec["note"] = "timings beside other processes are not figures: retake on a quiet machine"
    if a.out:
        with open(a.out, "w") as f:
            json.dump(rec, f, indent=1)
    print(json.dumps(rec, indent=1))


if __name__ == "__main__":
    main()
