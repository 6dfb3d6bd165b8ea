"""Where the 3D phantom's memory goes at large resolutions: build the model, optionally run
one insertion increment (--solve), and report per stage (body, model, solve) the resident
peak, the Python stack (jaxrkpm frames) where that peak was reached, the sizes the tangent
assembly and the sparse solver work on, and PARDISO's own memory report. A watchdog stops
the run at --limit-gb.

    PYTHONPATH=. python experiments/bench_needle3d_memory.py 0.055 [--solve] [--limit-gb 13]
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


class Sampler:
    """Samples the resident size every 0.1 s; per stage, keeps the peak and the main thread's
    stack at that peak (the innermost few jaxrkpm / experiments frames)."""

    def __init__(self, limit):
        self.limit, self.stage, self.peaks = limit, "start", {}
        self.main = threading.main_thread().ident
        threading.Thread(target=self.run, daemon=True).start()

    def where(self):
        frame = sys._current_frames().get(self.main)
        out = []
        while frame is not None and len(out) < 4:
            name = frame.f_code.co_filename
            if "jaxrkpm" in name or "experiments" in name:
                out.append(f"{os.path.basename(name)}:{frame.f_lineno} {frame.f_code.co_name}")
            frame = frame.f_back
        return " < ".join(out)

    def held(self, floor=0.05e9):
        """Arrays of at least ``floor`` bytes held by the main thread's frames (their locals
        and their ``self``'s attributes), largest first: what the peak is made of."""
        frame, out, seen = sys._current_frames().get(self.main), [], set()
        while frame is not None:
            where = f"{os.path.basename(frame.f_code.co_filename)}:{frame.f_code.co_name}"
            items = list(frame.f_locals.items())
            me = frame.f_locals.get("self")
            items += [(f"self.{k}", v) for k, v in list(getattr(me, "__dict__", {}).items())]
            for name, v in items:
                nb = getattr(v, "nbytes", None)
                if isinstance(nb, int) and nb >= floor and id(v) not in seen:
                    seen.add(id(v))
                    out.append((nb, f"{where} {name} {type(v).__name__}{tuple(getattr(v, 'shape', ()))} "
                                    f"{getattr(v, 'dtype', '')}"))
            frame = frame.f_back
        return "; ".join(f"{desc} {nb / 1e9:.2f} GB" for nb, desc in sorted(out, reverse=True))

    def run(self):
        while True:
            r = rss_gb()
            if r > self.limit:
                print(f"STOPPED: resident memory {r:.1f} GB > {self.limit} GB in stage {self.stage} "
                      f"at {self.where()}", flush=True)
                os._exit(3)
            if r > self.peaks.get(self.stage, (0.0, ""))[0]:
                self.peaks[self.stage] = (r, self.where() + "\n    holding: " + self.held())
            time.sleep(0.1)

    def enter(self, stage):
        self.report()
        self.stage = stage

    def report(self):
        if self.stage in self.peaks:
            r, at = self.peaks[self.stage]
            print(f"  stage {self.stage}: peak {r:.2f} GB at {at}", flush=True)


def pardiso_report(model):
    """PARDISO's memory report of each held factorisation (iparm 15-18, 1-based)."""
    from jaxrkpm.solvers.linalg import factorisations as sparse
    pool = sparse.pool(model.linear.system)
    facs = [f for f, _ in pool.slots.values()] + ([pool.spare] if pool.spare is not None else [])
    for f in facs:
        ip = getattr(f, "iparm", None)
        if ip is not None:
            print(f"  PARDISO: analysis peak {ip[14] / 1e6:.2f} GB, permanent {ip[15] / 1e6:.2f} GB, "
                  f"factorisation {ip[16] / 1e6:.2f} GB, factor nonzeros {int(ip[17]):,}", flush=True)
    print(f"  factorisations held {len(facs)} (pool size {pool.size}, spare {pool.spare is not None})", flush=True)


def main(argv):
    spacing = float(argv[0])
    limit = float(argv[argv.index("--limit-gb") + 1]) if "--limit-gb" in argv else 8.0
    s = Sampler(limit)
    from jaxrkpm.thesis.phantom3d import Phantom3D
    from jaxrkpm.mechanics.assembly import BLOCK_BUDGET
    s.enter("body")
    t0 = time.time()
    ph = Phantom3D(spacing=spacing)
    body = ph.body
    print(f"particles {body.n}, tetrahedra {len(body.cells)}, body {time.time() - t0:.0f} s, rss {rss_gb():.2f} GB", flush=True)
    s.enter("model")
    t0 = time.time()
    model = ph.model("none", None)
    ops = model.ops
    Q, K = ops.idx.shape
    pairs = int(ops.pair_i.shape[0])
    free = int(len(model.sets.free) * 3)
    chunk = max(1, BLOCK_BUDGET // (K * K * 9))
    print(f"model {time.time() - t0:.0f} s, rss {rss_gb():.2f} GB; solver {model.linear.name}, free DOF {free}, "
          f"integration points {Q}, neighbours per point K {K}, groups {ops.groups.shape}, "
          f"pair id table {ops.pair_id.size * 4 / 1e9:.2f} GB (int32), "
          f"particle pairs {pairs} ({pairs / body.n:.0f} per particle), pair blocks {pairs * 9 * 8 / 1e9:.2f} GB "
          f"per copy, assembly chunk {chunk} groups = (chunk, K, K, 3, 3) {chunk * K * K * 9 * 8 / 1e9:.2f} GB "
          f"per intermediate; nonzeros of K_ff ~ {pairs * 9:,} ({pairs * 9 * 12 / 1e9:.2f} GB as CSR)", flush=True)
    if "--solve" in argv:
        s.enter("solve")
        t0 = time.time()
        sol = model.solve({"needle": ph.needle_at(ph.insertion / 4)}, throw=False)
        print(f"one increment {time.time() - t0:.0f} s, status {int(sol.status)}, rss {rss_gb():.2f} GB", flush=True)
        if model.linear.name == "sparse":
            pardiso_report(model)
    s.enter("end")
    print(f"peak rss {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6:.2f} GB", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
