"""The 3D phantom with a contact (push-only) paddle beside the glued patches (issue 36 item 4,
3D part), friction mu 0.3 and 0.8.

Static (default): the glued sweep over every patch (batched), then the contact paddle (a flat
rounded box tangent to the skin at the patch centre, pressed in along the normal) at the
glued sweep's best patches. Writes needle_contact3d.json beside this script, or --out (the
runs of record: needle_contact3d_indent0.15.json, needle_contact3d_indent0.02.json).

--dynamic: the closed loop moving the contact paddle's pose (indentation, two shifts) during
the insertion at --patch, from --indentation; --optimum: Adam on that pose for the final
deviation, from --indentation (no shift). Each beside the glued patch and no paddle (the
same increments), every increment's contact checked compressive and within the friction cone.
Write needle_contact3d_dynamic.json / needle_contact3d_optimum.json beside this script.

    python experiments/needle_contact3d.py [--spacing 0.3] [--increments 4] [--patches 3]
    python experiments/needle_contact3d.py --dynamic [--patch 5] [--indentation 0.02] [--corrections 4]
    python experiments/needle_contact3d.py --optimum [--patch 5] [--indentation 0.02] [--iterations 6]
"""
from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

from jaxrkpm.thesis import contact_paddle as cp
from jaxrkpm.thesis import needle as nd
from jaxrkpm.thesis.phantom3d import Phantom3D

HERE = os.path.dirname(os.path.abspath(__file__))


def per_increment(checks) -> dict:
    """Each increment's contact check: ok (compressive, in the cone, no friction off contact),
    active points, the largest |f_t| / (mu f_n), the smallest point normal force."""
    return {"contact_ok_per_increment": [c.ok() for c in checks], "active_points": [c.active for c in checks],
            "cone_ratio": [c.cone for c in checks], "min_point_normal_force": [c.min_normal for c in checks],
            "contact_ok": all(c.ok() for c in checks)}


def dynamic_row(r) -> dict:
    return {"status": r.status.name, "message": r.message, "final": r.final,
            "depths": r.depths.tolist(), "deviation": r.deviation.tolist(), "uncorrected": r.uncorrected.tolist(),
            "control": r.control.tolist(), "corrections": r.iterations.tolist(), **per_increment(r.checks)}


def optimum_row(o) -> dict:
    return {"status": o.status.name, "message": o.message, "control": np.asarray(o.control).tolist(),
            "final": o.deviation, "history": o.history.tolist(), "insertion_status": o.run.status.name,
            "deviation": o.run.deviation.tolist(), "in_contact_at_end": o.run.in_contact,
            **per_increment(o.run.checks)}


def static(a, ph):
    sw = nd.static_sweep(ph, "none", a.increments)
    glued = np.where(sw.converged_paddles, np.abs(sw.final), np.inf)
    best = [int(i) + 1 for i in np.argsort(glued)[:a.patches]]
    delta = 0.5 * a.spacing if a.indentation is None else a.indentation
    out = {"phantom": f"Phantom3D(spacing={a.spacing}, material_law='neohookean')", "increments": a.increments,
           "no_paddle": float(sw.no_paddle[-1]), "glued": {p: float(sw.final[p - 1]) for p in best},
           "indentation": delta, "contact": []}
    path = a.out or os.path.join(HERE, "needle_contact3d.json")
    for mu in (0.3, 0.8):
        for p in best:
            r = cp.contact_insertion(ph, p, [delta, 0.0, 0.0], "none", a.increments, cp.ContactPaddle(mu=mu))
            out["contact"].append({"patch": p, "mu": mu, "status": r.status.name, "final": r.final,
                                   "deviation": r.deviation.tolist(), "contact_ok": r.contact_ok,
                                   "in_contact_at_end": r.in_contact,
                                   "active_points": [c.active for c in r.checks],
                                   "max_cone_ratio": max([c.cone for c in r.checks] or [0.0]),
                                   "min_point_normal_force": min([c.min_normal for c in r.checks] or [0.0])})
            print(mu, p, r.status.name, r.final, r.contact_ok, flush=True)
            dump(out, path)
    print("wrote", path)


def dump(out, path):
    with open(path, "w") as f:
        json.dump(out, f, indent=1)


def moving(a, ph):
    """The dynamic paddle or the optimised pose at one patch, mu 0.3 and 0.8."""
    kind = "dynamic" if a.dynamic else "optimum"
    path = a.out or os.path.join(HERE, f"needle_contact3d_{kind}.json")
    delta = 0.02 if a.indentation is None else a.indentation
    sw = nd.static_sweep(ph, "none", a.increments, paddles=[a.patch])
    out = {"phantom": f"Phantom3D(spacing={a.spacing}, material_law='neohookean')", "increments": a.increments,
           "patch": a.patch, "start_indentation": delta, "no_paddle": float(sw.no_paddle[-1]),
           "glued": float(sw.final[0]), "no_paddle_per_increment": sw.no_paddle.tolist(),
           "glued_per_increment": sw.deviation[0].tolist(), "cases": []}
    if a.dynamic:
        out.update(tol=a.tol, max_corrections=a.corrections)
    else:
        out.update(iterations=a.iterations, learning_rate=a.learning_rate, start=a.start or [delta, 0.0, 0.0])
    for mu in a.mu:
        spec = cp.ContactPaddle(mu=mu)
        t0 = time.perf_counter()
        if a.dynamic:
            r = cp.dynamic_contact_paddle(ph, a.patch, "none", a.increments, spec, tol=a.tol,
                                          max_corrections=a.corrections, start=[delta, 0.0, 0.0])
            row = dynamic_row(r)
        else:
            o = cp.optimize_contact_paddle(ph, a.patch, "none", a.increments, spec, start=a.start or [delta, 0.0, 0.0],
                                           iterations=a.iterations, learning_rate=a.learning_rate)
            row = optimum_row(o)
        row.update(mu=mu, seconds=time.perf_counter() - t0)
        out["cases"].append(row)
        print(kind, mu, row["status"], row["final"], row["contact_ok"], f"{row['seconds']:.0f} s", flush=True)
        dump(out, path)
    print("wrote", path)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spacing", type=float, default=0.3)
    ap.add_argument("--increments", type=int, default=4)
    ap.add_argument("--patches", type=int, default=3, help="static: the contact paddle at this many best glued patches")
    ap.add_argument("--indentation", type=float, default=None,
                    help="static: the press (default half a spacing); dynamic and optimum: the start (default 0.02)")
    which = ap.add_mutually_exclusive_group()
    which.add_argument("--dynamic", action="store_true", help="the closed loop on the pose at --patch")
    which.add_argument("--optimum", action="store_true", help="Adam on the pose at --patch")
    ap.add_argument("--patch", type=int, default=5, help="dynamic and optimum: the patch (the best glued one)")
    ap.add_argument("--mu", type=float, nargs="+", default=[0.3, 0.8])
    ap.add_argument("--tol", type=float, default=1e-4, help="dynamic: |lateral deviation| to hold")
    ap.add_argument("--corrections", type=int, default=4, help="dynamic: corrections per increment at most")
    ap.add_argument("--iterations", type=int, default=6, help="optimum: Adam iterations")
    ap.add_argument("--learning-rate", type=float, default=0.005, help="optimum: Adam's first step (a length)")
    ap.add_argument("--start", type=float, nargs=3, default=None, metavar=("INDENTATION", "SHIFT1", "SHIFT2"),
                    help="optimum: the start pose (default --indentation, no shift)")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    ph = Phantom3D(spacing=a.spacing, material_law="neohookean")
    if a.dynamic or a.optimum:
        moving(a, ph)
    else:
        static(a, ph)


if __name__ == "__main__":
    main()
