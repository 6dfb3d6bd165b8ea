"""Benchmark of the chapter-5 Jacobian tracking. Prints JSON.

1. Warm wall time (median of --repeats runs, after a compile probe) of the box (Table 5.3)
   and figure-8 (Table 5.4) runs on the 9x9 Fung square with the thesis' gain 0.05 and
   increment clamp 0.01, Gauss integration (and SCNI where the Model accepts it), beside the
   thesis' times: 625 / 412 min (Gauss) and 38 / 25 min (collocated), as speed-up ratios.
2. Per-call cost (median) of the control-point Jacobian at a deformed state, implicit
   (model.jacobian(method="implicit")) vs central finite differences (Algorithm 4, eps=1e-5),
   on the same planar setup at 9x9, 17x17 and 33x33 particles; ratio FD / implicit.

   Also the Jacobian as the tracking loop takes it (jaxrkpm.control.tracking: one tangent assembly
   and a Cholesky factorisation that the predictor of the next solve reuses) and its
   marginal cost there given that factorisation (m residual JVPs, m back-substitutions).

Targets: box with Gauss < 2 s warm; implicit >= 3x cheaper than central FD at 9x9, the gap
growing with the model size.

Threads: unless already set, OPENBLAS_NUM_THREADS=1 and XLA's CPU runtime single-threaded
(``--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1``): the systems are
small (138 to 2106 free DOFs) and the machine is shared; the settings used are in the JSON."""
from __future__ import annotations

import os

_THREAD_ENV = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
               "XLA_FLAGS": "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"}
for _k, _v in _THREAD_ENV.items():   # before jax / numpy load their runtimes
    os.environ.setdefault(_k, _v)

import argparse
import json
import platform
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from experiments import records
from jaxrkpm.thesis.studies import track as T
from jaxrkpm.control import tracking as C
from jaxrkpm.thesis.data import TRACKING_MINUTES

# XLA compilations during a run (JAX's own compile events): a warm tracking run compiles nothing
COMPILES = []
jax.monitoring.register_event_duration_secs_listener(
    lambda event, duration, **kw: COMPILES.append(duration)
    if event == "/jax/core/compile/backend_compile_duration" else None)

THESIS_MIN = {p: {k: TRACKING_MINUTES[k][p] for k in TRACKING_MINUTES} for p in ("box", "figure8")}


def _median_time(f, repeats):
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(f())
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts)), ts


def bench_tracking(paths, integrations, repeats):
    out = {}
    for integ in integrations:
        for path in paths:
            key = f"{path}_{integ}"
            try:
                exp = T.build(path, 2, integ)
            except ValueError as e:   # e.g. an integration this Model does not accept
                out[key] = {"error": f"ValueError: {e}"}
                print(key, out[key], file=sys.stderr)
                continue
            compiles0 = len(COMPILES)
            res, timing = T.execute(exp, repeats=repeats)
            w = timing["wall_s"]
            r = {"wall_s_median": w, "wall_s": records.stats(timing["warm_runs_s"]), "compile_s": timing["compile_s"],
                 "status": res.status.name, "max_waypoint_error": res.max_waypoint_error,
                 "iterations": int(len(res.error) - 1), "newton_iterations": int(np.sum(res.newton)),
                 "ms_per_iteration": 1e3 * w / max(len(res.error) - 1, 1),
                 "integration": exp.model.integration, "particles": [9, 9],
                 # the compile probe and the warm runs share one compiled loop (no retrace)
                 "xla_compilations": len(COMPILES) - compiles0}
            ref = THESIS_MIN.get(path)
            if ref:
                r["thesis_min_gauss"] = ref["gauss"]
                r["thesis_min_collocated"] = ref["collocated"]
                r["speedup_vs_thesis_gauss"] = ref["gauss"] * 60 / w
                r["speedup_vs_thesis_collocated"] = ref["collocated"] * 60 / w
            if path == "box" and integ == "gauss":
                r["target_warm_s"] = 2.0
                r["meets_target"] = bool(w < 2.0)
            out[key] = r
            print(key, json.dumps(r), file=sys.stderr)
    return out


def bench_jacobian(sizes, repeats, mp=(0.05, 0.05), eps=1e-5):
    out = {}
    for n in sizes:
        model = T.planar_model(n)
        try:
            sol = model.solve({"paddle": jnp.asarray(mp)}, steps=4)
        except Exception as e:  # report, do not hide, a failed reference solve
            out[f"{n}x{n}"] = {"error": f"{type(e).__name__}: {e}"}
            continue
        cp = T.CP_2D
        t0 = time.perf_counter()
        Ji = np.asarray(model.jacobian(sol, "paddle", cp))
        first_imp = time.perf_counter() - t0
        t0 = time.perf_counter()
        Jf = np.asarray(model.jacobian(sol, "paddle", cp, method="fd", eps=eps, scheme="central"))
        first_fd = time.perf_counter() - t0
        reps = repeats if n <= 17 else max(3, min(repeats, 3))
        t_imp, all_imp = _median_time(lambda: model.jacobian(sol, "paddle", cp), max(reps, 10 if n == 9 else reps))
        t_fd, all_fd = _median_time(lambda: model.jacobian(sol, "paddle", cp, method="fd", eps=eps), reps)
        # the same implicit Jacobian as the tracking loop calls it (arrays prepared once)
        side = C.ControlledModel.of(model, "paddle", cp)
        kernel = jax.jit(lambda sd, s: sd.jacobian(s, sd.factorise(s)))
        t_kernel, _ = _median_time(lambda: kernel(side, sol), max(reps, 10 if n == 9 else reps))
        # the Jacobian as the tracking loop takes it: tangent + factorisation (reused by the predictor)
        loop_jac = jax.jit(lambda sd, s: sd.jacobian(s, sd.factorise(s)))
        Jl = np.asarray(loop_jac(side, sol))
        t_loop, _ = _median_time(lambda: loop_jac(side, sol), max(reps, 10 if n == 9 else reps))
        fac = jax.jit(lambda sd, s: sd.factorise(s))(side, sol)
        # what the Jacobian adds to a step that factorises K_ff anyway
        marginal = jax.jit(lambda sd, st, s: sd.jacobian(s, st))
        Jm = np.asarray(marginal(side, fac, sol))
        t_marg, _ = _median_time(lambda: marginal(side, fac, sol), max(reps, 10 if n == 9 else reps))
        g = model.prescribed({"paddle": jnp.asarray(mp) + eps}, base=sol.g)
        resolve_its = int(model.solve_g(g, initial=sol, loads=sol.load).iterations)
        out[f"{n}x{n}"] = {
            "particles": int(model.body.n), "free_dof": int(sol.u.size), "linear_solver": model.linear.name,
            "implicit_ms_median": 1e3 * t_imp, "implicit_kernel_ms": 1e3 * t_kernel, "central_fd_ms_median": 1e3 * t_fd,
            "ratio_fd_over_implicit": t_fd / t_imp, "ratio_fd_over_implicit_kernel": t_fd / t_kernel,
            "implicit_first_call_s": first_imp, "fd_first_call_s": first_fd,
            "implicit_ms": records.stats([1e3 * t for t in all_imp]),
            "central_fd_ms": records.stats([1e3 * t for t in all_fd]),
            "tracking_loop_jacobian_ms": 1e3 * t_loop, "ratio_fd_over_tracking_loop_jacobian": t_fd / t_loop,
            "in_loop_marginal_ms": 1e3 * t_marg, "ratio_fd_over_in_loop_marginal": t_fd / t_marg,
            "fd_solves_per_jacobian": 2 * 2, "newton_iterations_per_resolve": resolve_its,
            "factorisations": {"implicit": 1, "central_fd": 2 * 2 * resolve_its},
            "relative_difference": float(np.abs(Ji - Jf).max() / np.abs(Ji).max()),
            "relative_difference_tracking_loop": float(np.abs(Ji - Jl).max() / np.abs(Ji).max()),
            "relative_difference_marginal": float(np.abs(Ji - Jm).max() / np.abs(Ji).max()),
            "state": {"paddle_displacement": list(mp), "eps": eps}}
        print(f"{n}x{n}", json.dumps(out[f"{n}x{n}"]), file=sys.stderr)
    r9 = out.get("9x9", {}).get("ratio_fd_over_implicit")
    summary = {"target_ratio_9x9": 3.0, "meets_ratio_target_9x9": bool(r9 is not None and r9 >= 3.0)}
    ratios = [out[k]["ratio_fd_over_implicit"] for k in out if "ratio_fd_over_implicit" in out[k]]
    summary["ratio_grows_with_size"] = bool(len(ratios) > 1 and all(b > a for a, b in zip(ratios, ratios[1:])))
    for key in ("ratio_fd_over_tracking_loop_jacobian", "ratio_fd_over_in_loop_marginal"):
        rs = [out[k][key] for k in out if key in out[k]]
        summary[key.replace("ratio_", "") + "_grows_with_size"] = bool(
            len(rs) > 1 and all(b > a for a, b in zip(rs, rs[1:])))
    summary["note"] = (
        "Both Jacobians are dominated by dense factorisations of K_ff once the model is past 9x9: "
        "the implicit one factorises once, central FD re-solves 2*m times with about two Newton "
        "iterations (one factorisation each), so the standalone ratio tends to ~2*m*newton "
        "(see 'factorisations'), not growing; at 9x9 it is larger because per-call host overhead "
        "(dispatch, shape functions, eager post-processing) weighs on FD's four solves. Inside "
        "the tracking loop the factorisation is shared with the predictor of the next solve, "
        "so the Jacobian's marginal cost is m JVPs and back-substitutions (O(n^2)) against "
        "FD's O(n^3) re-solves.")
    return out, summary


def main(argv=None):
    p = argparse.ArgumentParser(prog="bench_tracking", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--paths", nargs="*", default=["box", "figure8"])
    p.add_argument("--integrations", nargs="*", default=["gauss", "scni"])
    p.add_argument("--sizes", nargs="*", type=int, default=[9, 17, 33])
    p.add_argument("--skip-tracking", action="store_true")
    p.add_argument("--skip-jacobian", action="store_true")
    records.add_arguments(p)
    a = p.parse_args(argv)
    if a.repeats < 3 and not a.smoke:
        p.error("--repeats must be >= 3 (a median of at least three warm runs; --smoke allows fewer)")
    run = records.start("bench_tracking", a)
    res = {"machine": {"platform": platform.platform(), "processor": platform.processor(),
                       "jax": jax.__version__, "devices": [str(d) for d in jax.devices()]},
           "settings": {"gain": 0.05, "clamp": 0.01, "tol": 1e-4, "repeats": a.repeats},
           "threads": {k: os.environ.get(k) for k in _THREAD_ENV}, "cpu_count": os.cpu_count()}
    if not a.skip_tracking:
        res["tracking"] = bench_tracking(a.paths, a.integrations, a.repeats)
    if not a.skip_jacobian:
        res["jacobian"], res["jacobian_summary"] = bench_jacobian(a.sizes, a.repeats)
    print(json.dumps(res, indent=2))
    ratios = {f"thesis_gauss_over_ours {k}": v["speedup_vs_thesis_gauss"]
              for k, v in res.get("tracking", {}).items() if "speedup_vs_thesis_gauss" in v}
    for k, v in res.get("jacobian", {}).items():
        for key in ("ratio_fd_over_implicit", "ratio_fd_over_tracking_loop_jacobian", "ratio_fd_over_in_loop_marginal"):
            if key in v:
                ratios[f"{key.removeprefix('ratio_')} {k}"] = v[key]
    records.finish(run, res, ratios)
    return res


if __name__ == "__main__":
    main()
