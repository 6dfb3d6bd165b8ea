"""Benchmark of issue 20's table: a neo-Hookean n^3 cube (left face immobile, right face
pushed 30% in 10 load steps), its warm full solve and model-based control steps.

"Control step" (one iteration of ``jaxrkpm.control.tracking.track_loop``): at the converged 30% state,
one factorisation of K_ff, the implicit Jacobian of the control point (the cube's centre) to
the paddle's 3 rigid translations from it, and a 1% paddle increment settled from the previous
state (Newton predictor + chord corrections with that factorisation; the adaptive path only if
they fail). "Jacobian": ``Model.jacobian`` as a user calls it (its own factorisation).
"Public control step": the same 1% move as a user writes it, ``model.solve(..., initial=last)``
then ``model.jacobian``, from the factorisations the Solutions keep (``Solution.linear``)
against the same calls with none kept. "Control loop": ``track_loop`` run for --loop-steps iterations towards a waypoint out of reach
(every iteration a clamped 1% move), per iteration, with a factorisation per iteration
(reuse 0) and with kept factorisations (``track(reuse=...)``: quasi-Newton chord corrections on
a factorisation of an earlier state, refactorised only where a correction cuts |r| by less than
--reuse; both to the solver's residual tolerance rtol = 1e-10 x the internal force scale); the
loop includes its one initial factorisation (``loop_*_s`` / iterations is the amortised cost).
The full solve is timed as ``model.solve`` gives it by default (eager, dense: modified Newton,
the Newton solver's ``reuse`` = ``Model.newton_reuse``, a kept factorisation while the residual contracts;
--reuse sets another) and with full Newton (reuse=0); both to the same tolerance. --integration runs each case
with Gauss and/or nodal (SCNI) integration and reports the displacement of a probe point (the
top edge's midpoint, which bulges), so that integrations and sizes can be compared against the
finest case run. "newton_iteration_parts_s" profiles one Newton iteration (pair blocks,
dense matrix, factorisation, solve, energy and residual, force scale). --crossover times one
Newton iteration's linear work dense against sparse (PARDISO where installed) at several
sizes, the measurement behind ``SolverChoice.dense_3d`` (``jaxrkpm.internal.SolverChoice``).
Medians of warm repeats; each size runs in a fresh subprocess (its peak RSS is its own).
Prints JSON and writes a record (experiments/records.py); quote ratios within one run (the machine may be shared: the load average is
printed)."""
from __future__ import annotations

import argparse
import itertools
import json
import os
import resource
import subprocess
import sys
import time

from experiments import records

SPREAD = {}   # label -> records.stats of the timings behind each median of a case


def timed(f, repeats, label=None):
    """Median wall time of ``f()`` over ``repeats`` warm calls (after one untimed call), and
    the last result; with ``label`` its spread goes to SPREAD (min, max, repeats)."""
    spread, out = records.warm(f, repeats)
    if label is not None:
        SPREAD[label] = spread
    return spread["median"], out


def newton_iteration_parts(prob, linear, sol, repeats):
    """The parts of one Newton iteration at ``sol``, each timed alone (medians): the tangent's
    pair blocks, the linear solver's matrix from them (dense: K_ff), the factorisation (blocks,
    matrix and Cholesky together), one solve with it, the energy with its gradient (a line
    search step or a chord correction) and the force scale of the convergence test."""
    import jax

    blocks = jax.jit(lambda p, s: p.tangent_blocks(s.u, s.g))
    matrix = jax.jit(lambda p, b: p.dense_tangent(b) if linear.modified_newton else b)
    factorise = jax.jit(lambda p, s: linear.state_at(p, s.u, s.g))
    solve = jax.jit(lambda st, r: linear.solve(st, r))
    energy = jax.jit(lambda p, s: jax.value_and_grad(lambda u: p.energy(u, s.g)[0])(s.u))
    scale = jax.jit(lambda p, s: p.force_scale(p.energy_residual(s.u, s.g)[3]))
    out = {}
    out["pair_blocks"], B = timed(lambda: blocks(prob, sol), repeats)
    out["matrix_from_blocks"], _ = timed(lambda: matrix(prob, B), repeats)
    out["factorise"], state = timed(lambda: factorise(prob, sol), repeats)
    out["solve"], _ = timed(lambda: solve(state, sol.u), repeats)
    out["energy_and_residual"], _ = timed(lambda: energy(prob, sol), repeats)
    out["force_scale"], _ = timed(lambda: scale(prob, sol), repeats)
    return out


def run_case(n, repeats, solver, reuse, integration="gauss", loop_steps=10, keep=0.5, precision="auto"):
    import jax
    import jax.numpy as jnp
    import numpy as np

    import jaxrkpm as jr
    from jaxrkpm.control.tracking import ControlledModel, track_loop
    from jaxrkpm.solvers.results import Limits

    body = jr.Body.grid((n, n, n), 1.0 / (n - 1))
    sets = {"wall": body.select(lambda X: X[:, 0] < 1e-9), "right": body.select(lambda X: X[:, 0] > 1 - 1e-9)}
    t0 = time.perf_counter()
    model = jr.Model(body, jr.NeoHookean(lam=1.0, mu=1.0), integration=integration, essential=sets, solver=solver,
                     precision=precision)
    build_s = time.perf_counter() - t0
    g = jnp.array([-0.3, 0.0, 0.0])
    solve_s, sol = timed(lambda: model.solve({"right": g}, steps=10, reuse=0), repeats, "full_newton_solve")   # full Newton
    # the default (modified Newton on the dense path: a kept factorisation while |r| contracts)
    reuse = model.newton_reuse if reuse is None else reuse
    reuse_s, re = timed(lambda: model.solve({"right": g}, steps=10, reuse=reuse), repeats, "default_solve")
    centre = np.array([[0.5, 0.5, 0.5]])
    jac_s, _ = timed(lambda: model.jacobian(sol._replace(linear=None), "right", centre), repeats, "jacobian")

    def public_step(start, keep):
        """A control step as a user writes it: solve a 1% paddle move from the last state,
        then the Jacobian there; ``keep``: from the factorisations the Solutions kept."""
        start = start if keep else start._replace(linear=None)
        new = model.solve({"right": g + jnp.array([-0.01, 0.0, 0.0])}, initial=start)
        return new, model.jacobian(new if keep else new._replace(linear=None), "right", centre)

    public_kept_s, (pub, _) = timed(lambda: public_step(re, True), repeats, "public_step_kept")
    public_fresh_s, _ = timed(lambda: public_step(re, False), repeats, "public_step_fresh")

    ctrl = ControlledModel.of(model, "right", centre)
    lim = Limits.of(steps=1)
    dg = jnp.einsum("a,abi->bi", jnp.array([-0.01, 0.0, 0.0]), ctrl.G)

    @jax.jit
    def factorise(c, s):
        return c.factorise(s)

    @jax.jit
    def jacobian_from(c, s, state):
        return c.jacobian(s, state)

    @jax.jit
    def settle(c, s, state):
        return c.settle(s, state, s.g + dg, lim, 6)[0]

    @jax.jit
    def control_step(c, s):
        state = c.factorise(s)
        return c.jacobian(s, state), c.settle(s, state, s.g + dg, lim, 6)[0]

    step_s, (J, moved) = timed(lambda: control_step(ctrl, sol), repeats, "control_step")
    fact_s, state = timed(lambda: factorise(ctrl, sol), repeats)
    jfrom_s, _ = timed(lambda: jacobian_from(ctrl, sol, state), repeats)
    settle_s, _ = timed(lambda: settle(ctrl, sol, state), repeats)
    parts = newton_iteration_parts(ctrl.problem, ctrl.linear, sol, repeats)
    loop = {}
    for kept in (0.0, keep):
        side = ControlledModel.of(model, "right", centre, reuse=kept)
        far = jnp.asarray(side.measure(sol)[None] + jnp.array([[0.05, 0.02, 0.0]]))   # out of reach

        def run_loop():
            return track_loop(side, side, True, lim, sol, sol, far, 0.5, 0.01, 1e-9, 0.0, 10**6,
                              loop_steps, 10**6)

        t, (k, _, hist, *_) = timed(run_loop, max(1, repeats - 1), f"loop_reuse_{kept}")
        loop[kept] = {"s_per_iteration": t / int(k), "iterations": int(k),
                      "newton_per_iteration": np.asarray(hist["newton"])[1:int(k) + 1].tolist(),
                      "error_after": float(np.asarray(hist["error"])[int(k)])}
    return {"n": n, "integration": integration, "build_s": build_s,
            # the centre moves by half the push whatever the discretisation (measured: -0.15
            # to 1e-15 at 6^3 with Gauss and SCNI); the bulge of the top edge's midpoint does not
            "probe_displacement_at_0.5_1_1": np.asarray(model.displacement(sol, np.array([[0.5, 1.0, 1.0]])))[0].tolist(),
            "loop_factorise_every_step": loop[0.0], "loop_kept_factorisation": loop[keep], "keep": keep,
            "loop_ratio_kept_over_every_step": loop[keep]["s_per_iteration"] / loop[0.0]["s_per_iteration"],
            "full_newton_over_default_solve": solve_s / reuse_s,
            "dof": int(len(model.sets.free) * 3), "path": model.linear.name,
            "mixed_precision": bool(getattr(model.linear, "mixed", False)),
            "status": sol.outcome.name, "newton_iterations": int(sol.iterations),
            "full_newton_warm_solve_s": solve_s, "default_reuse": reuse, "default_warm_solve_s": reuse_s,
            "default_status": re.outcome.name, "default_newton_iterations": int(re.iterations),
            "default_max_du_difference": float(abs(re.u - sol.u).max()), "jacobian_s": jac_s, "control_step_s": step_s,
            "public_step_kept_s": public_kept_s, "public_step_fresh_s": public_fresh_s,
            "public_step_fresh_over_kept": public_fresh_s / public_kept_s,
            "public_step_newton": int(pub.iterations),
            "control_step_parts_s": {"factorise": fact_s, "jacobian_from_state": jfrom_s, "settle": settle_s},
            "newton_iteration_parts_s": parts,
            "control_step_newton": int(moved.iterations), "control_step_status": int(moved.status),
            "control_step_residual": float(moved.residual_norm),
            "spread_s": dict(SPREAD),
            "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6}


def crossover_case(n, repeats, solver, dim=3, precision="auto"):
    """One Newton iteration's linear work (assemble the tangent, factorise it, solve once) on
    the n^3 cube (``dim`` 2: the n^2 square) with ``solver`` ("dense" or "sparse"), at the
    right face pushed in by 0.1 spacing, the other particles where they were (a deformed state whose
    tangent is positive definite; no solve first: a dense 14^3 solve alone takes minutes). The
    residual evaluations of an iteration are the same on both paths: left out."""
    import jax
    import jax.numpy as jnp

    import jaxrkpm as jr

    body = jr.Body.grid((n,) * dim, 1.0 / (n - 1))
    sets = {"wall": body.select(lambda X: X[:, 0] < 1e-9), "right": body.select(lambda X: X[:, 0] > 1 - 1e-9)}
    model = jr.Model(body, jr.NeoHookean(lam=1.0, mu=1.0), essential=sets, solver=solver, precision=precision)
    g = model.prescribed({"right": jnp.zeros(dim).at[0].set(-0.1 * body.spacing)})
    u = jnp.zeros((len(model.sets.free), dim))
    prob = model.problem()

    linear = model.linear

    @jax.jit
    def iteration(p, u, g):
        state = linear.state_at(p, u, g)
        return linear.solve(state, p.residual(u, g)), linear.stability(state)

    t, (x, stability) = timed(lambda: iteration(prob, u, g), repeats, "iteration")
    return {"n": n, "dim": dim, "solver": solver, "path": model.linear.name, "dof": int(len(model.sets.free) * dim),
            "mixed_precision": bool(getattr(model.linear, "mixed", False)),
            "iteration_s": t, "iteration_spread_s": SPREAD["iteration"],
            "finite": bool(jnp.all(jnp.isfinite(x))), "stability": int(stability),
            "peak_rss_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6}


def crossover(sizes, repeats, dim=3):
    """Dense (double and mixed precision) against sparse per Newton iteration at each size,
    interleaved (each case in a fresh subprocess); the crossover is the first size where
    sparse is faster than the dense path's precision="auto"."""
    from jaxrkpm.internal import SolverChoice
    mixed_min = SolverChoice().mixed_min

    rows = []
    for n in sizes:
        row = {"n": n, "dim": dim, "load_average": os.getloadavg()}
        for key, solver, precision in (("dense", "dense", "double"), ("dense_mixed", "dense", "mixed"),
                                       ("sparse", "sparse", "auto")):
            r = subprocess.run([sys.executable, "-m", "experiments.bench_cube3d", "--crossover-case", str(n),
                                "--repeats", str(repeats), "--solver", solver, "--dim", str(dim),
                                "--precision", precision], capture_output=True, text=True)
            row[key] = json.loads(r.stdout.strip().splitlines()[-1]) if r.returncode == 0 else \
                {"error": r.stderr.strip().splitlines()[-1] if r.stderr.strip() else f"exit {r.returncode}"}
        if all("iteration_s" in row[k] for k in ("dense", "dense_mixed", "sparse")):
            row["dof"] = row["dense"]["dof"]
            row["mixed_over_double"] = row["dense_mixed"]["iteration_s"] / row["dense"]["iteration_s"]
            auto = row["dense_mixed" if row["dof"] >= mixed_min else "dense"]["iteration_s"]
            row["dense_over_sparse"] = auto / row["sparse"]["iteration_s"]
        print(json.dumps(row), file=sys.stderr)
        rows.append(row)
    faster = [r["dof"] for r in rows if r.get("dense_over_sparse", 0) > 1]
    return {"sizes": rows, "first_dof_where_sparse_is_faster": min(faster) if faster else None}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--n", type=int, nargs="*", default=[6, 10], help="particles per edge")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--solver", default="auto", choices=["auto", "dense", "sparse"])
    p.add_argument("--reuse", type=float, default=None,
                   help="the Newton reuse of the default solve (default: the model's newton_reuse)")
    p.add_argument("--keep", type=float, default=0.5, help="track(reuse=...) of the kept-factorisation control loop")
    p.add_argument("--integration", nargs="*", default=["gauss"], choices=["gauss", "scni", "mscni"])
    p.add_argument("--loop-steps", type=int, default=10, help="control loop iterations timed")
    p.add_argument("--crossover", type=int, nargs="*", default=[6, 8, 10, 12, 14],
                   help="sizes of the dense/sparse crossover per Newton iteration (none: skip it)")
    p.add_argument("--only-crossover", action="store_true", help="the crossover alone")
    p.add_argument("--dim", type=int, default=3, choices=[2, 3], help="of --crossover: the n^3 cube or the n^2 square")
    p.add_argument("--precision", nargs="*", default=["auto"], choices=["auto", "double", "mixed"],
                   help="Model(precision=...) of the dense factorisation; several: each case with each")
    p.add_argument("--case", type=int, help=argparse.SUPPRESS)
    p.add_argument("--crossover-case", type=int, help=argparse.SUPPRESS)
    records.add_arguments(p)
    a = p.parse_args(argv)
    if a.crossover_case:
        print(json.dumps(crossover_case(a.crossover_case, a.repeats, a.solver, a.dim, a.precision[0])))
        return
    if a.only_crossover:
        run = records.start("bench_cube3d", a, variant="crossover")
        out = {"load_average_before": os.getloadavg(), "crossover": crossover(a.crossover, a.repeats, a.dim),
               "load_average_after": os.getloadavg()}
        print(json.dumps(out, indent=2))
        records.finish(run, out, ratios_of(out))
        return
    if a.case:
        print(json.dumps(run_case(a.case, a.repeats, a.solver, a.reuse, a.integration[0], a.loop_steps, a.keep,
                                  a.precision[0])))
        return
    run = records.start("bench_cube3d", a)
    out = {"load_average_before": os.getloadavg()}
    for n in a.n:
        for integration, precision in itertools.product(a.integration, a.precision):
            r = subprocess.run([sys.executable, "-m", "experiments.bench_cube3d", "--case", str(n),
                                "--repeats", str(a.repeats), "--solver", a.solver,
                                *(["--reuse", str(a.reuse)] if a.reuse is not None else []), "--integration", integration, "--loop-steps", str(a.loop_steps),
                                "--keep", str(a.keep), "--precision", precision],
                               capture_output=True, text=True)
            key = f"cube_{n}" + ("" if integration == "gauss" else f"_{integration}") + \
                ("" if precision == "auto" else f"_{precision}")
            out[key] = json.loads(r.stdout.strip().splitlines()[-1]) if r.returncode == 0 else \
                {"error": r.stderr.strip().splitlines()[-1] if r.stderr.strip() else f"exit {r.returncode}"}
            out[key]["load_average"] = os.getloadavg()
            print(key, json.dumps(out[key]), file=sys.stderr)
    if a.crossover:
        out["crossover"] = crossover(a.crossover, a.repeats, a.dim)
    out["load_average_after"] = os.getloadavg()
    print(json.dumps(out, indent=2))
    records.finish(run, out, ratios_of(out))


def ratios_of(out: dict) -> dict:
    """The same-run ratios of a bench_cube3d result: per case, kept over every-step control
    loop and full over modified Newton; per crossover size, dense (auto precision) over
    sparse and mixed over double."""
    ratios = {}
    for key, case in out.items():
        if key.startswith("cube_") and "loop_ratio_kept_over_every_step" in case:
            ratios[f"control_loop_kept_over_every_step {key}"] = case["loop_ratio_kept_over_every_step"]
            ratios[f"full_newton_over_default_solve {key}"] = case["full_newton_over_default_solve"]
            ratios[f"public_step_fresh_over_kept {key}"] = case["public_step_fresh_over_kept"]
    for row in out.get("crossover", {}).get("sizes", []):
        for name in ("dense_over_sparse", "mixed_over_double"):
            if name in row:
                ratios[f"{name} n={row['n']} dim={row['dim']}"] = row[name]
    return ratios


if __name__ == "__main__":
    main(sys.argv[1:])
