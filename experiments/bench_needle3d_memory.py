"""Why the 3D phantom's ~8,000-particle bench point does not fit in ~8 GB: build the model
(no solve unless --solve) and report the sizes the tangent assembly and the sparse solver
work on, with the process's peak memory; a watchdog stops the run at --limit-gb.

    PYTHONPATH=. python experiments/bench_needle3d_memory.py 0.055 [--solve] [--limit-gb 8]
"""
import os
import resource
import sys
import threading
import time

for _v in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OMP_NUM_THREADS"):
    os.environ.setdefault(_v, "1")


def rss_gb():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e9


def watchdog(limit):
    while True:
        if rss_gb() > limit:
            print(f"STOPPED: resident memory {rss_gb():.1f} GB > {limit} GB", flush=True)
            os._exit(3)
        time.sleep(0.2)


def main(argv):
    spacing = float(argv[0])
    limit = float(argv[argv.index("--limit-gb") + 1]) if "--limit-gb" in argv else 8.0
    threading.Thread(target=watchdog, args=(limit,), daemon=True).start()
    import numpy as np
    from jaxrkpm.phantom3d import Phantom3D
    from jaxrkpm.solve import _BLOCK_BUDGET
    t0 = time.time()
    ph = Phantom3D(spacing=spacing)
    body = ph.body
    print(f"particles {body.n}, tetrahedra {len(body.cells)}, body {time.time() - t0:.0f} s, rss {rss_gb():.2f} GB", flush=True)
    t0 = time.time()
    model = ph.model("none", None)
    ops = model.ops
    Q, K = ops.idx.shape
    pairs = int(ops.pair_i.shape[0])
    free = int(len(model.sets.free) * 3)
    chunk = max(1, _BLOCK_BUDGET // (K * K * 9))
    print(f"model {time.time() - t0:.0f} s, rss {rss_gb():.2f} GB; solver {model.linear.name}, free DOF {free}, "
          f"integration points {Q}, neighbours per point K {K}, groups {ops.groups.shape}, "
          f"particle pairs {pairs} ({pairs / body.n:.0f} per particle), pair blocks {pairs * 9 * 8 / 1e9:.2f} GB "
          f"per copy, assembly chunk {chunk} groups = (chunk, s*3, K*9) {chunk * ops.groups.shape[1] * 3 * K * 9 * 8 / 1e9:.2f} GB "
          f"per intermediate; nonzeros of K_ff ~ {pairs * 9:,} ({pairs * 9 * 12 / 1e9:.2f} GB as CSR)", flush=True)
    if "--solve" in argv:
        t0 = time.time()
        sol = model.solve({"needle": ph.needle_at(ph.insertion / 4)}, throw=False)
        print(f"one increment {time.time() - t0:.0f} s, status {int(sol.status)}, rss {rss_gb():.2f} GB", flush=True)
    print(f"peak rss {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6:.2f} GB", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
