"""Benchmark: the 3D needle phantom (jaxrkpm.thesis.phantom3d.Phantom3D) at three resolutions, and its
batched patch sweep against a Python loop.

Per resolution (mesh size -> ~500, ~2,000, ~8,000 particles), in a fresh subprocess (its own
compile caches and peak memory):
- build: mesh (gmsh) -> Body.from_mesh -> Model (integration table, essential sets, tangent
  pattern), each timed;
- solve: the needle inserted in ``increments`` warm-started solves (no paddle); the first run
  compiles, then the median of ``repeats`` warm runs.
Sweep (the coarsest resolution by default): ``--patches`` patches x ``increments`` in one
batched call (``needle.insert``: lax.map over patches of a scan over increments) against the
loop a user writes without it (per patch and increment ``model.solve`` warm-started, then
``model.jacobian``), both warm (after an untimed compiling call), medians of ``repeats``,
interleaved; the two agree to round-off (reported).

BLAS is single-threaded (OPENBLAS/MKL/OMP_NUM_THREADS=1, set before numpy loads) so the
timings compare like with like on a shared machine; ratios are taken within one run.
Prints JSON.

What limits the largest resolutions (``bench_needle3d_memory.py`` reports the peak per stage,
the arrays held there and PARDISO's own memory report):
- the (G, K, K) int32 pair-id table of the tangent assembly, the floor of every stage (it
  grows as N K^2);
- the build's sparse pattern (int64 row, column, source and value arrays of every tangent
  entry, sorted and filtered to the lower triangle), the build's peak;
- PARDISO's fill, and the factorisation kept across solves.
``lax.map`` runs the sweep's patches one after another, so batching saves dispatch and compile
only: the per-solve work (assembly, factorisation) is the same as the loop's.

Run from the repository root: ``python -m experiments.bench_needle3d``; writes a record
(experiments/records.py).
"""
from __future__ import annotations

import os

for _v in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OMP_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import resource  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

from experiments import records  # noqa: E402

# mesh size -> target particle count (the mesher decides the exact count)
RESOLUTIONS = {"230": 0.3, "500": 0.15, "2000": 0.085, "6000": 0.055, "8000": 0.05}


def timed(fn, *args, **kw):
    t0 = time.perf_counter()
    out = fn(*args, **kw)
    return time.perf_counter() - t0, out


def insertion(model, phantom, depths):
    import numpy as np
    sol = model.initial()
    for d in depths:
        sol = model.solve({"needle": phantom.needle_at(d)}, initial=sol, throw=False)
    sol.u.block_until_ready()
    return sol, float(phantom.deviation_of(np.asarray(model.displacement(sol, np.atleast_2d(phantom.target))[0])))


def run_resolution(spacing, increments, repeats):
    import jaxrkpm as jr
    from jaxrkpm.thesis.phantom3d import Phantom3D
    ph = Phantom3D(spacing=spacing)
    t_mesh, m = timed(ph.mesh)                                      # the mesher alone
    t_body, _ = timed(jr.Body.from_mesh, m)                          # the mesh -> particles alone
    t_phantom, body = timed(lambda: ph.body)        # the phantom's own build: the same two calls
    t_model, model = timed(ph.model, "none", None)
    depths = ph.depths(increments)
    first, (sol, dev) = timed(insertion, model, ph, depths)
    warm = [timed(insertion, model, ph, depths)[0] for _ in range(repeats)]
    return {"spacing": spacing, "particles": body.n, "tetrahedra": int(len(body.cells)),
            "free_dof": int(len(model.sets.free) * 3), "integration_points": int(model.problem().term("strain").w.shape[0]),
            "neighbours": int(model.problem().term("strain").idx.shape[1]), "solver": model.linear.name,
            "mesh_s": t_mesh, "body_s": t_body, "model_s": t_model, "build_s": t_phantom + t_model,
            "first_insertion_s": first, "warm_insertion_s_median": statistics.median(warm),
            "warm_solve_s_median": statistics.median(warm) / increments, "increments": increments,
            "warm_insertion_s": records.stats(warm),
            "final_deviation": dev, "status": sol.outcome.name,
            "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6}


def loop(models, ph, depths):
    import numpy as np
    target = np.atleast_2d(ph.target)
    dev = np.zeros((len(models), len(depths)))
    for i, model in enumerate(models):
        sol = model.initial()
        for k, d in enumerate(depths):
            sol = model.solve({"needle": ph.needle_at(d)}, initial=sol, throw=False)
            dev[i, k] = float(ph.deviation_of(np.asarray(model.displacement(sol, target)[0])))
            np.asarray(model.jacobian(sol, "paddle", target))
    return dev


def batched(models, ph, depths):
    import jax
    import numpy as np
    from jaxrkpm.thesis import needle as nd
    out = nd.insert(models, depths, ph.target, direction=ph.needle_direction)
    jax.block_until_ready(out)
    return ph.deviation_of(np.asarray(out.target_u))


def run_sweep(spacing, patches, increments, repeats):
    import numpy as np
    from jaxrkpm.thesis.phantom3d import Phantom3D
    ph = Phantom3D(spacing=spacing)
    t_models, models = timed(lambda: [ph.model("none", p) for p in range(1, patches + 1)])
    depths = ph.depths(increments)
    cold_b, dev_b = timed(batched, models, ph, depths)
    cold_l, dev_l = timed(loop, models, ph, depths)
    tb, tl = [], []
    for _ in range(repeats):
        tb.append(timed(batched, models, ph, depths)[0])
        tl.append(timed(loop, models, ph, depths)[0])
    return {"spacing": spacing, "particles": ph.body.n, "patches": patches, "increments": increments,
            "models_build_s": t_models, "batched_cold_s": cold_b, "loop_cold_s": cold_l,
            "batched_warm_median_s": statistics.median(tb), "loop_warm_median_s": statistics.median(tl),
            "batched_warm_s": records.stats(tb), "loop_warm_s": records.stats(tl),
            "speedup_warm": statistics.median(tl) / statistics.median(tb),
            "max_abs_difference": float(np.max(np.abs(dev_b - dev_l))),
            "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--resolutions", nargs="*", default=["500", "2000", "8000"], choices=list(RESOLUTIONS))
    p.add_argument("--increments", type=int, default=4)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--patches", type=int, default=20)
    p.add_argument("--sweep-resolution", default="230", choices=list(RESOLUTIONS),
                   help="the sweep's resolution (230: the tests' phantom; a 20-patch loop at 500 takes long)")
    p.add_argument("--no-sweep", action="store_true")
    p.add_argument("--timeout", type=float, default=3600, help="per subprocess, seconds")
    p.add_argument("--case", help=argparse.SUPPRESS)
    records.add_arguments(p)
    a = p.parse_args(argv)
    if a.case:
        kind, res = a.case.split(":")
        if kind == "resolution":
            print(json.dumps(run_resolution(RESOLUTIONS[res], a.increments, a.repeats)))
        else:
            print(json.dumps(run_sweep(RESOLUTIONS[res], a.patches, a.increments, a.repeats)))
        return
    run = records.start("bench_needle3d", a)
    cases = [f"resolution:{r}" for r in a.resolutions] + ([] if a.no_sweep else [f"sweep:{a.sweep_resolution}"])
    out = {"device": None, "increments": a.increments, "repeats": a.repeats}
    for case in cases:
        cmd = [sys.executable, "-m", "experiments.bench_needle3d", "--case", case, "--increments", str(a.increments),
               "--repeats", str(a.repeats), "--patches", str(a.patches)]
        try:
            r = subprocess.run(cmd, capture_output=True, text=True, timeout=a.timeout)
            out[case] = json.loads(r.stdout.strip().splitlines()[-1]) if r.returncode == 0 else \
                {"error": r.stderr.strip().splitlines()[-1] if r.stderr.strip() else f"exit {r.returncode}"}
        except subprocess.TimeoutExpired:
            out[case] = {"error": f"did not finish in {a.timeout:.0f} s"}
        print(case, json.dumps(out[case]), file=sys.stderr, flush=True)
    import jax
    out["device"] = str(jax.devices()[0])
    print(json.dumps(out, indent=2))
    records.finish(run, out, {f"loop_over_batched_warm {k}": v["speedup_warm"]
                              for k, v in out.items() if isinstance(v, dict) and "speedup_warm" in v})


if __name__ == "__main__":
    main()
