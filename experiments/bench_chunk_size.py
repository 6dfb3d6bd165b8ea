"""Benchmark: the chunk size ``chunk_size="auto"`` measures and chooses for the 2D needle
sweep on this machine (``jaxrkpm.choose_chunk_size``), and the throughput of
the sizes it tried.

The table is the needle sweep of ``--configurations`` configurations (5 paddle positions x
stiffness ratios spread logarithmically over 1..100, the right inclusion), each inserted
through ``--increments`` with the paddle Jacobian at each, as ``jaxrkpm sweep`` runs it.
``choose_chunk_size`` evaluates its first 4, 8, 16, ... configurations, each size twice (the
first call compiles, the second is the figure), until the next size would save less of the
sweep's time than measuring it costs (the table's size sets that: a larger sweep measures
further) or the next chunk would take over a minute. Chosen: the smallest size within 5% of
the best throughput.

Each size is timed once (the second call), so quote the record's throughputs with its load
average. On a GPU the batch is the vmap lock step and the throughput grows to thousands of
configurations; ``--start`` skips the sizes that are surely too small there
(``--start 64 --configurations 100000``)."""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import jax
import numpy as np

from experiments import records
from jaxrkpm import choose_chunk_size
from jaxrkpm.thesis import NeedleSweep, paddle_configurations


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--configurations", type=int, default=2000,
                    help="the sweep's size (a multiple of the 5 paddle positions)")
    ap.add_argument("--increments", type=int, default=15)
    ap.add_argument("--start", type=int, default=4, help="the first chunk size measured")
    records.add_arguments(ap)
    args = ap.parse_args(argv)
    if args.configurations % 5 or args.configurations < 5:
        raise SystemExit(f"--configurations {args.configurations}: give a positive multiple of the 5 paddle positions")
    load_before = os.getloadavg()
    run = records.start("bench_chunk_size", args)
    table = paddle_configurations(ratios=list(np.geomspace(1.0, 100.0, args.configurations // 5)))
    t0 = time.perf_counter()
    choice = choose_chunk_size(table, NeedleSweep(args.increments), start=args.start, progress=True)
    wall = time.perf_counter() - t0
    rate = choice.throughput
    sizes = {str(s): {"seconds": t, "configurations_per_s": r, "per_configuration_s": t / s}
             for s, t, r in zip(choice.sizes, choice.seconds, rate)}
    chosen = choice.sizes.index(choice.chosen)
    result = {"benchmark": "choose_chunk_size on the 2D needle sweep (one warm call per size)",
              "device": str(jax.devices()[0]), "configurations": args.configurations,
              "increments": args.increments, "chosen": choice.chosen, "why_stopped": choice.why,
              "measuring_s": wall, "sizes": sizes,
              "load_average_before": load_before, "load_average_after": os.getloadavg()}
    print(json.dumps(result, indent=1))
    records.finish(run, result, {"throughput chosen / first size": rate[chosen] / rate[0],
                                 "throughput best / chosen": max(rate) / rate[chosen]})


if __name__ == "__main__":
    sys.exit(main())
