"""Several push-only tools on the 2D needle phantom (issue 50): the final lateral deviation of
the target with 1, 2 and 3 tools (``jaxrkpm.thesis.tools``), static, preloaded (depths
optimised), optimised (positions and depths) and closed loop, beside no tool and the best glued
paddle; inclusions none and right, friction mu 0.3 and 0.8.

Static: each tool at the target's height (nearest edge point), pressed half a spacing in.
Preload / optimise: ``optimize_placement`` (L-BFGS-B, converged by its projected gradient or
the relative change of the objective), compared with a grid of the same space. Closed loop:
``closed_loop`` (a QP per correction). Every contact force is checked compressive and inside
the cone at every increment (``contact_ok``). Writes needle_tools.json beside this script
(or --out), case by case.

    python experiments/needle_tools.py [--increments 5] [--tools 1 2 3] [--inclusion none]
        [--mu 0.3] [--modes static preload optimize dynamic] [--grid 4] [--grid-start] [--out FILE]
"""
from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

from jaxrkpm.thesis import contact_paddle as cp
from jaxrkpm.thesis import needle as nd
from jaxrkpm.thesis import tools as tl

MODES = ("static", "preload", "optimize", "dynamic")
BEST_GLUED = {"none": 4, "right": 2}    # the best glued paddle of the static sweep (Table 6.2 index)


def checks_row(checks):
    flat = [c for row in checks for c in row]
    return {"contact_ok": all(c.ok() for c in flat),
            "max_cone_ratio": max([c.cone for c in flat] or [0.0]),
            "min_point_normal_force": min([c.min_normal for c in flat if c.active] or [0.0]),
            "active_points_final": [c.active for c in checks[-1]] if checks else []}


def run_case(ph, inclusion, mu, ntools, modes, increments, grid, out, path, grid_start=False):
    spec = cp.ContactPaddle(mu=mu)
    tools = tl.default_tools(ntools)
    base = {"inclusion": inclusion, "mu": mu, "tools": ntools,
            "sites": [f"{t.site}:{t.shape}" for t in tools]}
    for mode in modes:
        t0 = time.perf_counter()
        row = dict(base, mode=mode)
        if mode == "static":
            c = tl.rest_control(ph, tools, spec, depth=0.5 * ph.spacing)
            run = tl.insertion(ph, tools, c, inclusion, increments, spec)
            row.update(control=c.tolist(), deviation=run.final, status=run.status.name,
                       deviation_per_increment=run.deviation.tolist(), force_final=run.force[-1].tolist()
                       if len(run.force) else None, **checks_row(run.checks))
        elif mode in ("preload", "optimize"):
            free = "depth" if mode == "preload" else "all"
            gx = None
            if grid_start:
                gx, gd, rows = tl.grid_search(ph, tools, inclusion, increments, spec, points=grid, free=free)
            opt = tl.optimize_placement(ph, tools, inclusion, increments, spec, free=free, start=gx)
            row["start"] = "the best grid point" if gx is not None else "default"
            row.update(control=opt.control.tolist(), deviation=opt.deviation, status=opt.status.name,
                       message=opt.message, iterations=opt.iterations, evaluations=opt.evaluations,
                       projected_gradient=opt.projected_gradient, objective=opt.value,
                       history=opt.history, force_final=opt.run.force[-1].tolist() if len(opt.run.force) else None,
                       **checks_row(opt.run.checks))
            if grid and (ntools == 1 or free == "depth"):
                if gx is None:
                    gx, gd, rows = tl.grid_search(ph, tools, inclusion, increments, spec, points=grid, free=free)
                row["grid"] = {"points_per_axis": grid, "best_control": None if gx is None else gx.tolist(),
                               "best_deviation": gd, "rows": [(x.tolist(), d) for x, d in rows]}
        else:
            loop = tl.closed_loop(ph, tools, inclusion, increments, spec)
            row.update(deviation=loop.final, status=loop.status.name, message=loop.message,
                       deviation_per_increment=loop.deviation.tolist(), uncorrected=loop.uncorrected.tolist(),
                       max_abs_deviation=float(np.max(np.abs(loop.deviation))) if len(loop.deviation) else None,
                       control=loop.control.tolist(), corrections=loop.corrections,
                       qp_status=[[q.name for q in qs] for qs in loop.qp_status], **checks_row(loop.checks))
        row["seconds"] = time.perf_counter() - t0
        out["rows"].append(row)
        print(inclusion, mu, ntools, mode, row.get("deviation"), row.get("status"), f"{row['seconds']:.0f}s",
              flush=True)
        with open(path, "w") as f:
            json.dump(out, f, indent=1)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--increments", type=int, default=5)
    ap.add_argument("--tools", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--inclusion", nargs="+", default=["none", "right"])
    ap.add_argument("--mu", type=float, nargs="+", default=[0.3, 0.8])
    ap.add_argument("--modes", nargs="+", default=list(MODES), choices=MODES)
    ap.add_argument("--grid", type=int, default=4, help="grid points per free control (one tool; preloads)")
    ap.add_argument("--grid-start", action="store_true", help="start the optimiser from the grid's best point")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    path = a.out or os.path.join(os.path.dirname(os.path.abspath(__file__)), "needle_tools.json")
    ph = nd.Phantom()
    out = {"phantom": "2D Figure 6.1 phantom (needle.Phantom defaults)", "increments": a.increments,
           "gradient": "final_gradient with lag_sweeps 0 (the settled friction pressures and normals held)",
           "reference": {}, "rows": []}
    for inclusion in a.inclusion:
        glued = cp.glued_finals(ph, inclusion, a.increments, [BEST_GLUED[inclusion]])
        out["reference"][inclusion] = {"no_tool": float(glued[1]), "glued_paddle": BEST_GLUED[inclusion],
                                       "glued": float(glued[0][0])}
        print(inclusion, "no tool", glued[1], "glued", glued[0][0], flush=True)
    for ntools in a.tools:
        for inclusion in a.inclusion:
            for mu in a.mu:
                run_case(ph, inclusion, mu, ntools, a.modes, a.increments, a.grid, out, path, a.grid_start)
    print("wrote", path)
    return out


if __name__ == "__main__":
    main()
