"""Benchmark: the batched needle-insertion sweep (issue 5) against a Python loop of the same
solves, and against the number of configurations.

A configuration is one static paddle position of Table 6.2 on the Figure 6.1 phantom with
the inclusion right of the target at one stiffness ratio; the ratios are spread
logarithmically over 1..100 so that 1, 5, 20, 80 configurations are 1, 5, 5x4, 5x16 distinct
problems (the thesis sweeps 5 positions; more positions along the same boundary would need
a finer lattice, which changes the problem). Every configuration inserts the needle to 15%
in ``increments`` warm-started increments and takes the paddle Jacobian at each one.

- batched: ``needle.insert`` -- all configurations x all increments in one jitted call
  (``lax.map`` or, with ``--batching vmap``, ``vmap`` over configurations of a ``scan`` over
  increments), one compile per batch size.
- loop: the same work the way a user without the batched path writes it -- per configuration
  and increment, ``model.solve`` warm-started from the last increment, then
  ``model.jacobian`` -- a host round trip and a dispatch per call.

Both are timed warm (after one untimed call that compiles) ``repeats`` times, interleaved,
and the first (cold) call is reported separately. The two paths' deviations are compared
(they agree to round-off). Prints JSON, with the load average before and after (quote the
ratios of one run; the machine may be shared) and writes a record (experiments/records.py).

Both solve alike: with "map" batching (CPU) modified Newton, as an eager ``model.solve``
does by default (``Model.newton_reuse``); with "vmap" full Newton (the loop is given reuse=0).

``floor`` (for the largest count the loop ran): what the same solves cost in arithmetic
alone. One more, untimed batched call counts every operation the solves execute
(``count_operations``: assembly + Cholesky, triangular solves, energy + residual passes, the
convergence test's force scales, the predictors), and each operation is costed by its kernel
timed per member inside one jitted ``lax.map`` over that many states (no dispatch, no
Python); the Jacobians add their right-hand sides. ``floor_s`` is that sum;
``floor_iterations_s`` the earlier records' estimate from the iteration count alone (one
factorisation per solve: modified Newton makes more, so it undercounts). ``ceiling_speedup`` =
loop / floor_s is the most any batching of these solves could gain over the loop on this
machine, if it made every overhead vanish and cost no more per member than the unbatched
kernels.

``--gpu``: the GPU scaling table in one short run: 20, 80, 320, 1,280, 4,100 configurations
in lock step (vmap), timed warm up to 320 (``--warm-max``; above it the cold call, compile
included, is the figure: ``batched_cold_per_configuration_s``), the loop at 20 only, one
warm repeat, the phantom's integration table built once for all models (``--cache-tables``:
``Model`` rebuilds it per model, host time outside the timed calls that took minutes at
4,100 models), and at every count the profile of a lock-step iteration (``--profile``,
``lock_step_profile``: assembly, factorisation, triangular solves, a line-search trial, the
convergence test, each a jitted vmap over the batch, beside their arithmetic). The presets
set defaults: options given on the command line win (``--gpu --counts 4100``: the largest
count as a call of its own). The record is written after every count (``"partial": true``
until the run ends), so a run stopped by a time limit keeps the counts it finished.
``--gpu --quick``: the same path at toy sizes on this machine (a smoke record), to check the
bench before device time is spent on it.

``--devices N`` splits the configurations over N XLA host devices (one per core; shard_map,
``needle.insert(n_devices=N)``), the loop stays on one: say so when quoting it."""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import statistics
import sys
import time
from functools import partial
from unittest import mock


def _host_devices(argv) -> None:
    """XLA reads its flags once, when JAX starts: --devices must reach it before the import."""
    args = list(sys.argv[1:] if argv is None else argv)
    if "--devices" in args:
        n = int(args[args.index("--devices") + 1])
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "")
                                   + f" --xla_force_host_platform_device_count={n}").strip()


if __name__ == "__main__":
    _host_devices(None)

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from experiments import records  # noqa: E402
from jaxrkpm.control import batching  # noqa: E402
from jaxrkpm.thesis import needle as nd  # noqa: E402
from jaxrkpm.model.model import Model  # noqa: E402
from jaxrkpm.solvers.implicit import response  # noqa: E402
from jaxrkpm.solvers.linalg.dense import DenseSolver  # noqa: E402
from jaxrkpm.solvers.results import Status  # noqa: E402


def cache_integration_tables() -> None:
    """Build each body's Gauss table once for all the bench's models (``Model`` builds it per
    model; the models here share body, support and order, so the tables are equal)."""
    from jaxrkpm.discretise import quadrature
    original, cache = quadrature.gauss_table, {}

    def cached(body, *args, **kwargs):
        key = (id(body), args, tuple(sorted(kwargs.items())))
        if key not in cache:
            cache[key] = (body, original(body, *args, **kwargs))     # the body kept: its id stays its own
        return cache[key][1]
    quadrature.gauss_table = cached


# the largest count: the first multiple of the 5 paddle positions at or above 4,096
GPU_PRESET = {"counts": [20, 80, 320, 1280, 4100], "batching": "vmap", "loop_max": 20, "repeats": 1,
              "warm_max": 320, "cache_tables": True, "profile": True}
# --quick: the same path at toy sizes, a check on a CPU that the bench runs before device time
# is spent on it (figures meaningless: a smoke record)
QUICK = {"counts": [5], "increments": 3, "loop_max": 0, "repeats": 1, "warm_max": 5, "smoke": True}


def configurations(phantom: nd.Phantom, count: int) -> list[Model]:
    """``count`` models: the 5 paddle positions x ``count // 5`` inclusion stiffness ratios
    (a single model for count = 1). All share the phantom's body and integration table."""
    paddles = range(1, len(phantom.paddles) + 1)
    if count == 1:
        pairs = [(4, 100.0)]
    else:
        if count % len(paddles):
            raise ValueError(f"count must be 1 or a multiple of {len(paddles)}, got {count}")
        ratios = np.geomspace(1.0, 100.0, count // len(paddles)) if count > len(paddles) else [100.0]
        pairs = [(p, float(r)) for r in ratios for p in paddles]
    models = []
    for p, r in pairs:
        material = nd.Phantom(stiffness_ratio=r).material("right")
        models.append(Model(phantom.body, material, phantom.integration,
                            essential=phantom.sets(p), support=phantom.support))
    return models


def batched(models, depths, target, batching="map", n_devices=1):
    out = nd.insert(models, depths, target, batching=batching, n_devices=n_devices)
    jax.block_until_ready(out)
    return np.asarray(out.target_u[..., 0]), np.asarray(out.status), np.asarray(out.iterations)


def loop(models, depths, target, reuse):
    """The same solves one call at a time; ``reuse``: the batched path's Newton reuse (map:
    modified Newton, as an eager solve's default; vmap: full Newton)."""
    target = np.atleast_2d(target)
    dev = np.zeros((len(models), len(depths)))
    status = np.zeros((len(models), len(depths)), int)
    for i, model in enumerate(models):
        sol = model.initial()
        for k, depth in enumerate(depths):
            sol = model.solve({"needle": [0.0, float(depth)]}, initial=sol, throw=False, reuse=reuse)
            status[i, k] = int(sol.status)
            dev[i, k] = float(model.displacement(sol, target)[0, 0])
            if status[i, k] == Status.CONVERGED:
                np.asarray(model.jacobian(sol, "paddle", target))
    return dev, status


def timed(fn, *args):
    t0 = time.perf_counter()
    out = fn(*args)
    return time.perf_counter() - t0, out


def per_member(fn, states, repeats=3):
    """Seconds per state of ``fn`` over the states (leading axis) in one jitted lax.map:
    the unbatched kernel's own cost, without dispatch (median of ``repeats``)."""
    f = jax.jit(lambda xs: jax.lax.map(fn, xs))
    jax.block_until_ready(f(states))
    times = [timed(lambda: jax.block_until_ready(f(states)))[0] for _ in range(repeats)]
    return statistics.median(times) / jax.tree.leaves(states)[0].shape[0]


@contextlib.contextmanager
def counted_operations():
    """Count, per execution, the operations a Newton solve is made of (a host callback in each,
    no effect on the results): the tangent's assembly + factorisation (``DenseSolver.factorise``:
    every one follows an assembly), the triangular solves, the energy + residual evaluations (the
    line-search trials and each solve's start), the force scale of the convergence test, the
    round-off floor's pass, and the predictor's linearisation (``Newton.increment``). The compiled
    programs are dropped on entry and exit, so that only the calls inside are instrumented."""
    from jaxrkpm.mechanics.problem import Problem
    from jaxrkpm.solvers.newton import Newton
    counts = dict.fromkeys(OPERATIONS, 0)

    def bump(name):
        counts[name] += 1

    def counting(cls, method, name):
        original = getattr(cls, method)

        def wrapped(*args, **kwargs):
            jax.debug.callback(partial(bump, name))
            return original(*args, **kwargs)
        return mock.patch.object(cls, method, wrapped)

    jax.clear_caches()
    with contextlib.ExitStack() as stack:
        for name, (cls, method) in {"factorise": (DenseSolver, "factorise"), "solve": (DenseSolver, "solve"),
                                    "energy_residual": (Problem, "energy_residual"),
                                    "force_scale": (Problem, "force_scale"),
                                    "force_scales": (Problem, "force_scales"),
                                    "predictor": (Newton, "increment")}.items():
            stack.enter_context(counting(cls, method, name))
        try:
            yield counts
        finally:
            jax.effects_barrier()
            jax.clear_caches()


# the operations ``counted_operations`` counts, each costed by ``floor``'s kernel of that name
OPERATIONS = ("factorise", "solve", "energy_residual", "force_scale", "force_scales", "predictor")


def count_operations(models, depths, target, batching) -> dict:
    """How many of each of ``OPERATIONS`` the batched sweep executes (one untimed, instrumented
    call, compile included)."""
    with counted_operations() as counts:
        batched(models, depths, target, batching)
    return dict(counts)


def floor(model, phantom, depths, operations: dict, jacobians: int, iterations: int, solves: int,
          samples: int = 40) -> dict:
    """The arithmetic of the sweep: each operation it executed (``operations``, counted by
    ``count_operations``) at the cost of its kernel alone, timed per member inside one jitted
    lax.map over ``samples`` states near the model's equilibrium at the last of ``depths``
    (perturbed), plus ``jacobians`` Jacobian right-hand sides (their factorisations and solves
    are among the counted operations). ``floor_iterations_s``: the estimate of earlier records,
    from the Newton ``iterations`` (one solve, trial and force scale each) and one factorisation
    per solve and per Jacobian (a lower bound for modified Newton, which refactorises where a
    kept factorisation stops contracting)."""
    prob = model.problem()
    sol = model.initial()
    for depth in depths:
        sol = model.solve({"needle": phantom.needle_at(depth)}, initial=sol)
    noise = 1e-6 * np.random.default_rng(0).standard_normal((samples,) + sol.u.shape)
    us = jnp.asarray(np.asarray(sol.u) + noise)
    g = sol.g
    dG = model.directions("paddle")
    linear = model.linear
    newton = model.solver(reuse=model.newton_reuse).newton
    state = linear.state_at(prob, sol.u, g)
    rhs = prob.residual(sol.u, g)
    no_rhs = jnp.zeros((0,) + dG.shape[1:], dG.dtype)   # the response's right-hand sides alone
    piece = {
        "factorise_s": per_member(lambda u: linear.state_at(prob, u, g), us),
        "solve_s": per_member(lambda r: linear.solve(state, r), us * 0 + rhs),
        "energy_residual_s": per_member(lambda u: prob.energy_residual(u, g), us),
        "force_scale_s": per_member(prob.force_scale, jax.lax.map(lambda u: prob.energy_residual(u, g)[3], us)),
        "force_scales_s": per_member(lambda u: prob.force_scales(u, g), us),
        "predictor_s": per_member(lambda u: newton.increment(prob, u, g, g + 1e-3, 1.0, 1.0, 25).rhs0, us),
        "jacobian_rhs_s": per_member(lambda u: response(prob, linear, u, g, sol.load, dG, state), us),
    }
    # a Jacobian's own work beyond its factorisation: the right-hand sides (its solve is counted)
    piece["jacobian_rhs_s"] = max(piece["jacobian_rhs_s"] - piece["solve_s"], 0.0)
    terms = {op: operations[op] * piece[f"{op}_s"] for op in OPERATIONS}
    terms["jacobian_rhs"] = jacobians * piece["jacobian_rhs_s"]
    iteration = piece["solve_s"] + piece["energy_residual_s"] + piece["force_scale_s"]
    estimate = (iterations * iteration + (solves + jacobians) * piece["factorise_s"]
                + jacobians * piece["jacobian_rhs_s"])
    return {"per_member": piece, "operations": dict(operations), "jacobians": int(jacobians),
            "newton_iterations": int(iterations), "solves": int(solves), "terms_s": terms,
            "floor_s": sum(terms.values()),
            "floor_iterations_s": estimate}


def straggler_iterations(its, stay, width: int) -> int:
    """The Newton iterations of ``needle._lock_step``'s straggler phase, given each member's
    iterations (B, n) (those of its unbatched solve, which the lock step reproduces) and where
    it stayed in the lock step (B, n): the members that left, in index order, solved in groups
    of ``width``, one group after another; a group runs from where each of its members left,
    and each of its increments lasts as long as its slowest member's."""
    done = np.sum(stay, axis=1)
    n = its.shape[1]
    pending = np.flatnonzero(done < n)
    total = 0
    for g in range(0, len(pending), width):
        group = pending[g:g + width]
        for i in range(n):
            active = group[done[group] + i < n]
            if active.size:
                total += int(np.max(its[active, done[active] + i]))
    return total


def lock_step_profile(models, its, st, repeats: int = 3) -> dict:
    """Where a lock-step ("vmap") iteration of ``models`` spends its time: each piece of a
    Newton iteration timed as its own jitted vmap over all the members (one batched kernel
    each, as inside the lock step): assembly of K_ff (``tangent_blocks`` + ``dense_tangent``),
    its Cholesky factorisation (with the blocks the solves use), the triangular solves, one
    energy + residual + det F evaluation (a line-search trial), the force scale (the
    convergence test), and the factorisation and solves of ``DenseSolver(inverse=True)`` (L^-1
    kept: solves are matrix products, which a device may run faster than triangular solves);
    beside them the arithmetic of the dense pieces (n = free unknowns:
    Cholesky n^3 / 3 flops, LU 2 n^3 / 3, a pair of triangular solves 2 n^2, per member).

    ``its``, ``st`` (the insertion's iterations and statuses, (B, n)) give the lock-step iterations: per increment, the
    largest count among the members in lock step (capped by ``needle.LOCK_ITERATIONS``; a
    member that left counts 1), plus the stragglers' (``straggler_iterations``: their groups one
    after another, each costed as its fraction of a full-width iteration; the earlier records'
    ``straggler_iterations_estimate`` counted them as one group). Both count Newton iterations
    as one line-search trial each: the trials a failing iteration adds are in ``other_s``, the
    warm time the pieces do not account for (with dispatch, loop control, selects, the
    Jacobians' extra solves)."""
    prob, batched = batching.stack_models(models)
    axes = batching.batch_axes(prob, batched)
    linear = models[0].solver(reuse=0.0).linear
    B, nf, d = len(models), prob.n_free, prob.dim
    g = jnp.stack([m.prescribed({"needle": np.zeros(d)}) for m in models])
    u = jnp.zeros((B, nf, d))

    def vm(f):
        return jax.jit(jax.vmap(f, in_axes=(axes, 0, 0)))

    def clock(f, *xs):
        jax.block_until_ready(f(*xs))
        return statistics.median(timed(lambda: jax.block_until_ready(f(*xs)))[0] for _ in range(repeats))

    assemble, factorise = vm(lambda p, u, g: p.dense_tangent(p.tangent_blocks(u, g))), jax.jit(jax.vmap(linear.factorise))
    K = assemble(prob, u, g)
    state = factorise(K)
    rhs = vm(lambda p, u, g: p.residual(u, g))(prob, u, g) + 1.0
    piece = {
        "assembly_s": clock(assemble, prob, u, g),
        "factorisation_s": clock(factorise, K),
        "triangular_solves_s": clock(jax.jit(jax.vmap(linear.solve)), state, rhs),
        "energy_residual_s": clock(vm(lambda p, u, g: p.energy_residual(u, g)), prob, u, g),
        "force_scale_s": clock(vm(lambda p, u, g: p.force_scale(p.energy_residual(u, g)[3])), prob, u, g),
        "lu_s": clock(jax.jit(jax.vmap(lambda K: jax.scipy.linalg.lu_factor(K))), K),
    }
    # the alternative a device may prefer: L^-1 kept, every solve two matrix products
    if isinstance(linear, DenseSolver) and not linear.inverse:
        inverse = dataclasses.replace(linear, inverse=True)
        piece["factorisation_inverse_s"] = clock(jax.jit(jax.vmap(inverse.factorise)), K)
        piece["triangular_solves_inverse_s"] = clock(jax.jit(jax.vmap(inverse.solve)),
                                                     jax.jit(jax.vmap(inverse.factorise))(K), rhs)
    n = nf * d
    stay = np.cumprod((st == Status.CONVERGED) & (its <= nd.LOCK_ITERATIONS), axis=1).astype(bool)
    locked = int(np.sum(np.max(np.where(stay, its, np.minimum(its, nd.LOCK_ITERATIONS)), axis=0)))
    left = ~stay
    width = nd.straggler_width(B)     # the stragglers' group: its pieces scaled by its width
    stragglers = straggler_iterations(its, stay, width)
    iteration = piece["assembly_s"] + piece["factorisation_s"] + piece["triangular_solves_s"] + \
        piece["energy_residual_s"] + piece["force_scale_s"]
    jacobian = piece["assembly_s"] + piece["factorisation_s"] + piece["triangular_solves_s"]
    increments = its.shape[1]
    return {"members": B, "unknowns": n, "pieces_s": piece,
            "flops_per_member": {"cholesky": n ** 3 / 3, "lu": 2 * n ** 3 / 3, "triangular_pair": 2 * n ** 2},
            "cholesky_gflops": B * n ** 3 / 3 / piece["factorisation_s"] / 1e9,
            "lock_step_iterations": locked, "straggler_iterations": stragglers,
            "members_that_left": int(np.sum(left.any(axis=1))),
            "straggler_width": width / B, "iteration_s": iteration,
            "modelled_s": (locked + stragglers * width / B) * iteration + increments * jacobian}


def progress(run, args, rows, row) -> None:
    """A finished count: on stderr (stdout holds only the final JSON, one document to parse)
    and into the record so far (a run stopped by a time limit keeps its finished counts)."""
    print(json.dumps(row), file=sys.stderr, flush=True)
    records.finish(run, {"batching": args.batching, "device": str(jax.devices()[0]), "rows": rows}, partial=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--counts", type=int, nargs="+", default=[1, 5, 20, 80])
    ap.add_argument("--increments", type=int, default=15)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--batching", choices=batching.BATCHING, default=None,
                    help="needle.insert's batching: lax.map of configurations, or vmap (lock step); "
                         "default: needle.default_batching() (map on CPU, vmap on GPU)")
    ap.add_argument("--loop-max", type=int, default=80,
                    help="time the Python loop only up to this many configurations")
    ap.add_argument("--devices", type=int, default=1,
                    help="XLA host devices (cores) the batched call splits the configurations over")
    ap.add_argument("--warm-max", type=int, default=None,
                    help="time warm repeats only up to this many configurations (above: the cold call only)")
    ap.add_argument("--cache-tables", action="store_true",
                    help="build the phantom's integration table once for all models (host time, not timed)")
    ap.add_argument("--gpu", action="store_true",
                    help="the GPU scaling table: " + ", ".join(f"--{k.replace('_', '-')} {v}" for k, v in GPU_PRESET.items()))
    ap.add_argument("--quick", action="store_true",
                    help="toy sizes (with --gpu: its path on this machine): " + ", ".join(
                        f"--{k.replace('_', '-')} {v}" for k, v in QUICK.items()))
    ap.add_argument("--profile", action="store_true",
                    help="time the pieces of a lock-step iteration at every count (lock_step_profile)")
    records.add_arguments(ap)
    given = sys.argv[1:] if argv is None else list(argv)
    # the presets set defaults: an option given on the command line (--counts 4100) wins
    if "--gpu" in given:
        ap.set_defaults(**GPU_PRESET)
    if "--quick" in given:
        ap.set_defaults(**QUICK)
    args = ap.parse_args(argv)
    if args.cache_tables:
        cache_integration_tables()
    args.batching = args.batching or batching.default_batching()
    if len(jax.devices()) < args.devices:
        raise SystemExit(f"--devices {args.devices}: JAX sees {len(jax.devices())} device(s); set "
                         "XLA_FLAGS=--xla_force_host_platform_device_count before JAX starts "
                         "(run this script directly)")
    load_before = os.getloadavg()
    run = records.start("bench_sweep", args)

    phantom = nd.Phantom()
    depths = phantom.depths(args.increments)
    rows, last_loop = [], None
    for count in args.counts:
        models_s, models = timed(configurations, phantom, count)     # host time, not in the figures
        sweep = (models, depths, phantom.target, args.batching, args.devices)
        reuse = models[0].newton_reuse if args.batching == "map" else 0.0   # what insert solves with
        cold_b, (dev_b, st_b, its_b) = timed(batched, *sweep)
        row = {"configurations": count, "increments": args.increments,
               "solves": count * args.increments,
               "converged_fraction": float(np.mean(st_b == Status.CONVERGED)),
               "newton_iterations": int(its_b.sum()), "batched_cold_s": cold_b, "models_build_s": models_s}
        do_loop = count <= args.loop_max
        if do_loop:
            cold_l, (dev_l, st_l) = timed(loop, models, depths, phantom.target, reuse)
            solved = (its_b.sum(), int(np.sum(st_l == Status.CONVERGED)), st_l.size)
            row["loop_cold_s"] = cold_l
            row["max_abs_difference"] = float(np.max(np.abs(dev_b - dev_l)))
            row["status_agree"] = bool(np.all(st_b == st_l))
        row["batched_cold_per_configuration_s"] = cold_b / count
        if args.profile and args.batching == "vmap":
            row["lock_step_profile"] = lock_step_profile(models, its_b, st_b, repeats=max(args.repeats, 1))
        if args.warm_max is not None and count > args.warm_max:
            rows.append(row)
            progress(run, args, rows, row)
            continue
        tb, tl = [], []
        for _ in range(args.repeats):
            tb.append(timed(batched, *sweep)[0])
            if do_loop:
                tl.append(timed(loop, models, depths, phantom.target, reuse)[0])
        row["batched_warm_s"] = records.stats(tb)
        row["batched_warm_median_s"] = statistics.median(tb)
        row["batched_warm_per_configuration_s"] = statistics.median(tb) / count
        if do_loop:
            row["loop_warm_s"] = records.stats(tl)
            row["loop_warm_median_s"] = statistics.median(tl)
            row["speedup_warm"] = statistics.median(tl) / statistics.median(tb)
            row["speedup_cold"] = cold_l / cold_b
            # the floor's states: a configuration whose every increment converged
            last_loop = (row, models[int(np.argmax(np.all(st_l == Status.CONVERGED, axis=1)))], solved, sweep)
        if "lock_step_profile" in row:
            prof = row["lock_step_profile"]
            prof["other_s"] = row["batched_warm_median_s"] - prof["modelled_s"]
        rows.append(row)
        progress(run, args, rows, row)
    warm = [r for r in rows if "batched_warm_per_configuration_s" in r]
    base = warm[0]["batched_warm_per_configuration_s"] if warm else None
    result = {"benchmark": f"needle sweep: batched ({args.batching} of scan, one jitted call) vs Python "
                           "loop of model.solve + model.jacobian per increment",
              "batching": args.batching, "devices": args.devices,
              "device": str(jax.devices()[0]), "repeats": args.repeats, "rows": rows,
              "per_configuration_vs_single": {r["configurations"]: r["batched_warm_per_configuration_s"] / base
                                              for r in rows if "batched_warm_per_configuration_s" in r}}
    if last_loop is not None:
        row, model, (iterations, jacobians, solves), sweep = last_loop
        operations = count_operations(*sweep[:4])
        fl = floor(model, phantom, depths, operations, jacobians, iterations, solves)
        fl["configurations"] = row["configurations"]
        fl["loop_warm_s"] = row["loop_warm_median_s"]
        fl["batched_warm_s"] = row["batched_warm_median_s"]
        fl["ceiling_speedup"] = row["loop_warm_median_s"] / fl["floor_s"]
        fl["batched_over_floor"] = row["batched_warm_median_s"] / fl["floor_s"]
        fl["batched_over_floor_iterations"] = row["batched_warm_median_s"] / fl["floor_iterations_s"]
        result["floor"] = fl
    result["load_average_before"] = load_before
    result["load_average_after"] = os.getloadavg()
    print(json.dumps(result, indent=1))
    ratios = {f"loop_over_batched_warm {r['configurations']}": r["speedup_warm"] for r in rows if "speedup_warm" in r}
    if "floor" in result:
        ratios["loop_over_floor"] = result["floor"]["ceiling_speedup"]
        ratios["batched_over_floor"] = result["floor"]["batched_over_floor"]
    records.finish(run, result, ratios)


if __name__ == "__main__":
    main()
