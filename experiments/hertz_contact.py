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

    python -m experiments.hertz_contact [--spacing 0.02] [--radius 4] [--depths 0.002 0.0038]
        [--gap G] [--integration gauss] [--quick] [--out F]
"""
from __future__ import annotations

import argparse
import json
import time

from tests.problems import hertz_line_contact


def run(*args, **kwargs) -> dict:
    """``tests.problems.hertz_line_contact`` with its wall time."""
    t0 = time.perf_counter()
    rec = hertz_line_contact(*args, **kwargs)
    rec["wall_s"] = time.perf_counter() - t0
    for load in rec["loads"]:
        print(json.dumps({k: v for k, v in load.items() if k not in ("x", "pressure")}))
    return rec


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
