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
(they agree to round-off). Prints JSON."""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time

import jax
import numpy as np

from jaxrkpm import needle as nd
from jaxrkpm.model import Model
from jaxrkpm.solve import Status


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


def batched(models, depths, target, batching="map"):
    out = nd.insert(models, depths, target, batching=batching)
    jax.block_until_ready(out)
    return np.asarray(out.target_u[..., 0]), np.asarray(out.status)


def loop(models, depths, target):
    target = np.atleast_2d(target)
    dev = np.zeros((len(models), len(depths)))
    status = np.zeros((len(models), len(depths)), int)
    for i, model in enumerate(models):
        sol = model.initial()
        for k, depth in enumerate(depths):
            sol = model.solve({"needle": [0.0, float(depth)]}, initial=sol, throw=False)
            status[i, k] = int(sol.status)
            dev[i, k] = float(model.displacement(sol, target)[0, 0])
            if status[i, k] == Status.CONVERGED:
                np.asarray(model.jacobian(sol, "paddle", target))
    return dev, status


def timed(fn, *args):
    t0 = time.perf_counter()
    out = fn(*args)
    return time.perf_counter() - t0, out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--counts", type=int, nargs="+", default=[1, 5, 20, 80])
    ap.add_argument("--increments", type=int, default=15)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--batching", choices=nd.BATCHING, default="map",
                    help="needle.insert's batching: lax.map of configurations, or vmap (lock step)")
    ap.add_argument("--loop-max", type=int, default=80,
                    help="time the Python loop only up to this many configurations")
    args = ap.parse_args(argv)

    phantom = nd.Phantom()
    depths = phantom.depths(args.increments)
    rows = []
    for count in args.counts:
        models = configurations(phantom, count)
        cold_b, (dev_b, st_b) = timed(batched, models, depths, phantom.target, args.batching)
        row = {"configurations": count, "increments": args.increments,
               "solves": count * args.increments,
               "converged_fraction": float(np.mean(st_b == Status.CONVERGED)),
               "batched_cold_s": cold_b}
        do_loop = count <= args.loop_max
        if do_loop:
            cold_l, (dev_l, st_l) = timed(loop, models, depths, phantom.target)
            row["loop_cold_s"] = cold_l
            row["max_abs_difference"] = float(np.max(np.abs(dev_b - dev_l)))
            row["status_agree"] = bool(np.all(st_b == st_l))
        tb, tl = [], []
        for _ in range(args.repeats):
            tb.append(timed(batched, models, depths, phantom.target, args.batching)[0])
            if do_loop:
                tl.append(timed(loop, models, depths, phantom.target)[0])
        row["batched_warm_median_s"] = statistics.median(tb)
        row["batched_warm_per_configuration_s"] = statistics.median(tb) / count
        if do_loop:
            row["loop_warm_median_s"] = statistics.median(tl)
            row["speedup_warm"] = statistics.median(tl) / statistics.median(tb)
            row["speedup_cold"] = cold_l / cold_b
        rows.append(row)
        # progress on stderr: stdout holds only the final JSON (one document to parse)
        print(json.dumps(row), file=sys.stderr, flush=True)
    base = rows[0]["batched_warm_per_configuration_s"]
    result = {"benchmark": f"needle sweep: batched ({args.batching} of scan, one jitted call) vs Python "
                           "loop of model.solve + model.jacobian per increment",
              "batching": args.batching,
              "device": str(jax.devices()[0]), "repeats": args.repeats, "rows": rows,
              "per_configuration_vs_single": {r["configurations"]: r["batched_warm_per_configuration_s"] / base
                                              for r in rows}}
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
