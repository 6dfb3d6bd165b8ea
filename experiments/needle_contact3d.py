"""The 3D phantom's static sweep with a contact (push-only) paddle beside the glued patches
(issue 36 item 4, 3D part): the glued sweep over every patch (batched), then the contact
paddle (a flat rounded box tangent to the skin at the patch centre, pressed in along the
normal) at the glued sweep's best patches, friction mu 0.3 and 0.8. Writes
needle_contact3d.json beside this script, or --out (the runs of record:
needle_contact3d_indent0.15.json, needle_contact3d_indent0.02.json).

    python experiments/needle_contact3d.py [--spacing 0.3] [--increments 4] [--patches 3]
"""
from __future__ import annotations

import argparse
import json
import os

import numpy as np

from jaxrkpm.thesis import contact_paddle as cp
from jaxrkpm.thesis import needle as nd
from jaxrkpm.thesis.phantom3d import Phantom3D


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spacing", type=float, default=0.3)
    ap.add_argument("--increments", type=int, default=4)
    ap.add_argument("--patches", type=int, default=3, help="the contact paddle at this many best glued patches")
    ap.add_argument("--indentation", type=float, default=None, help="default: half a spacing")
    ap.add_argument("--out", default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "needle_contact3d.json"))
    a = ap.parse_args(argv)
    ph = Phantom3D(spacing=a.spacing, material_law="neohookean")
    sw = nd.static_sweep(ph, "none", a.increments)
    glued = np.where(sw.converged_paddles, np.abs(sw.final), np.inf)
    best = [int(i) + 1 for i in np.argsort(glued)[:a.patches]]
    delta = 0.5 * a.spacing if a.indentation is None else a.indentation
    out = {"phantom": f"Phantom3D(spacing={a.spacing}, material_law='neohookean')", "increments": a.increments,
           "no_paddle": float(sw.no_paddle[-1]), "glued": {p: float(sw.final[p - 1]) for p in best},
           "indentation": delta, "contact": []}
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
            with open(a.out, "w") as f:
                json.dump(out, f, indent=1)
    print("wrote", a.out)


if __name__ == "__main__":
    main()
