"""Needle studies with contact (push-only) paddles beside the glued paddles of chapter 6
(issue 36 item 4): the 2D phantom, inclusions none and right, friction mu 0.3 and 0.8.

For each case: the static sweep (every paddle position's contact paddle pressed one particle
spacing in, then the needle inserted) with the glued sweep and the no-paddle run; the
dynamic contact paddle (its pose moved during insertion); the optimised pose (Adam on
indentation and shift). Every contact force is checked compressive and within the friction
cone at every increment (``contact_ok``). Writes needle_contact.json (the closing note's
table) beside this script, or --out.

    python experiments/needle_contact.py [--increments 5] [--paddle 3] [--quick] [--out FILE]
"""
from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

from jaxrkpm.thesis import contact_paddle as cp
from jaxrkpm.thesis import needle as nd


# the optimised pose's start: indentation in particle spacings (no shift)
OPTIMUM_START = 1.5


def dynamic_row(r):
    return {"paddle": r.paddle, "status": r.status.name, "message": r.message, "final": r.final,
            "deviation": r.deviation.tolist(), "uncorrected": r.uncorrected.tolist(),
            "control": r.control.tolist(), "corrections": r.iterations.tolist(), "contact_ok": r.contact_ok,
            "max_cone_ratio": max([c.cone for c in r.checks] or [0.0]),
            "min_point_normal_force": min([c.min_normal for c in r.checks] or [0.0]),
            "active_points": [c.active for c in r.checks]}


def optimum_row(o):
    return {"paddle": o.paddle, "status": o.status.name, "message": o.message, "control": np.asarray(o.control).tolist(),
            "final": o.deviation, "start": o.history[0].tolist() if len(o.history) else None,
            "history": o.history.tolist(), "contact_ok": o.run.contact_ok,
            "in_contact_at_end": o.run.in_contact}


def dump(out, path):
    with open(path, "w") as f:
        json.dump(out, f, indent=1)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--increments", type=int, default=15)
    ap.add_argument("--paddle", type=int, default=3, help="paddle position of the dynamic and optimised runs")
    ap.add_argument("--iterations", type=int, default=6, help="Adam iterations of the optimised pose")
    ap.add_argument("--optimum-only", type=float, default=None, metavar="INDENTATION",
                    help="only the optimised pose, from this indentation (no shift; the full run starts it "
                         f"{OPTIMUM_START} spacings in)")
    ap.add_argument("--quick", action="store_true", help="one case, paddles 3 and 5, two increments")
    ap.add_argument("--inclusion", choices=("none", "right"), default=None, help="one inclusion (default both)")
    ap.add_argument("--mu", type=float, default=None, help="one friction coefficient (default 0.3 and 0.8)")
    ap.add_argument("--out", default=None, help="default: needle_contact[_INCLUSION][_MU].json beside this script")
    a = ap.parse_args(argv)
    ph = nd.Phantom()
    cases = [("none", 0.3)] if a.quick else [(inc, mu) for inc in ([a.inclusion] if a.inclusion else ("none", "right"))
                                             for mu in ([a.mu] if a.mu is not None else (0.3, 0.8))]
    if a.out is None:
        tag = "".join(f"_{v}" for v in (a.inclusion, a.mu) if v is not None)
        tag += "_optimum" if a.optimum_only is not None else ""
        a.out = os.path.join(os.path.dirname(os.path.abspath(__file__)), f"needle_contact{tag}.json")
    inc_n = 2 if a.quick else a.increments
    out = {"phantom": "2D Figure 6.1 phantom (needle.Phantom defaults)", "increments": inc_n,
           "static_control": [ph.spacing, 0.0], "cases": []}
    for inclusion, mu in cases:
        spec = cp.ContactPaddle(mu=mu)
        t0 = time.perf_counter()
        if a.optimum_only is not None:
            opt = cp.optimize_contact_paddle(ph, a.paddle, inclusion, inc_n, spec, iterations=a.iterations,
                                             start=[a.optimum_only, 0.0])
            out["cases"].append({"inclusion": inclusion, "mu": mu, "optimum": optimum_row(opt)})
            print(inclusion, mu, "optimum", opt.control, opt.deviation, opt.status.name, flush=True)
            dump(out, a.out)
            continue
        sw = cp.contact_sweep(ph, inclusion, inc_n, spec=spec, paddles=[3, 5] if a.quick else None)
        case = {"inclusion": inclusion, "mu": mu, "static": sw.rows(), "glued_only": sw.glued_only(),
                "static_contact_ok": sw.contact_ok}
        print(inclusion, mu, "static", [(r["paddle"], r["glued"], r["contact"]) for r in case["static"]], flush=True)
        out["cases"].append(case)
        dump(out, a.out)
        dyn = cp.dynamic_contact_paddle(ph, a.paddle, inclusion, inc_n, spec, start=[0.5 * ph.spacing, 0.0],
                                        max_corrections=2 if a.quick else 4)
        case["dynamic"] = dynamic_row(dyn)
        dump(out, a.out)
        print(inclusion, mu, "dynamic", dyn.status.name, dyn.deviation, flush=True)
        if not a.quick:
            # from 1.5 spacings in, not from the pose the closed loop ended at: pressed in to follow
            # the tissue to full insertion, that pose fails at the start of a static insertion
            opt = cp.optimize_contact_paddle(ph, a.paddle, inclusion, inc_n, spec, iterations=a.iterations,
                                             start=[OPTIMUM_START * ph.spacing, 0.0])
            case["optimum"] = optimum_row(opt)
            print(inclusion, mu, "optimum", opt.control, opt.deviation, flush=True)
        case["seconds"] = time.perf_counter() - t0
        dump(out, a.out)
    print("wrote", a.out)
    return out


if __name__ == "__main__":
    main()
