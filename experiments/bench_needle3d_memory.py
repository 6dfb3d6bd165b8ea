"""Where the 3D phantom's memory goes at large resolutions: build the model, optionally run
one insertion increment (--solve), and report per stage (body, model, solve) the resident
peak, the Python stack (jaxrkpm frames) where that peak was reached, the sizes the tangent
assembly and the sparse solver work on, and PARDISO's own memory report. A watchdog stops
the run at --limit-gb.

    python -m experiments.bench_needle3d_memory 0.055 [--solve] [--limit-gb 13]

Writes a record (experiments/records.py).
"""
import os
import resource
import sys
import threading
import time

for _v in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "OMP_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

from experiments import records  # noqa: E402


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


def pardiso_report(model) -> dict:
    """PARDISO's memory report of each held factorisation (iparm 15-18, 1-based)."""
    from jaxrkpm.solvers.linalg import factorisations as sparse
    pool = sparse.pool(model.linear.system)
    facs = [f for f, _ in pool.slots.values()] + ([pool.spare] if pool.spare is not None else [])
    held = []
    for f in facs:
        ip = getattr(f, "iparm", None)
        if ip is not None:
            held.append({"analysis_peak_gb": ip[14] / 1e6, "permanent_gb": ip[15] / 1e6,
                         "factorisation_gb": ip[16] / 1e6, "factor_nonzeros": int(ip[17])})
            print(f"  PARDISO: analysis peak {ip[14] / 1e6:.2f} GB, permanent {ip[15] / 1e6:.2f} GB, "
                  f"factorisation {ip[16] / 1e6:.2f} GB, factor nonzeros {int(ip[17]):,}", flush=True)
    print(f"  factorisations held {len(facs)} (pool size {pool.size}, spare {pool.spare is not None})", flush=True)
    return {"held": held, "pool_size": pool.size, "spare": pool.spare is not None}


def main(argv=None):
    import argparse

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("spacing", type=float, help="mesh size of the phantom (0.055: about 6,000 particles)")
    p.add_argument("--solve", action="store_true", help="also run one insertion increment")
    p.add_argument("--limit-gb", type=float, default=8.0, help="stop the run above this resident memory")
    records.add_arguments(p)
    a = p.parse_args(argv)
    run = records.start("bench_needle3d_memory", a)
    s = Sampler(a.limit_gb)
    from jaxrkpm.thesis.phantom3d import Phantom3D
    s.enter("body")
    t0 = time.time()
    ph = Phantom3D(spacing=a.spacing)
    body = ph.body
    fig = {"spacing": a.spacing, "particles": int(body.n), "tetrahedra": int(len(body.cells)),
           "body_s": time.time() - t0, "rss_after_body_gb": rss_gb()}
    print(f"particles {body.n}, tetrahedra {len(body.cells)}, body {fig['body_s']:.0f} s, rss {rss_gb():.2f} GB", flush=True)
    s.enter("model")
    t0 = time.time()
    model = ph.model("none", None)
    problem = model.problem()
    ops = problem.term("strain")
    Q, K = ops.idx.shape
    pairs = int(problem.n_pairs)
    free = int(len(model.sets.free) * 3)
    chunk = max(1, ops.block_budget // (K * K * 9))
    fig.update(model_s=time.time() - t0, rss_after_model_gb=rss_gb(), solver=model.linear.name, free_dof=free,
               integration_points=int(Q), neighbours=int(K), groups=list(ops.groups.shape),
               pair_id_table_gb=ops.pair_id.size * 4 / 1e9, particle_pairs=pairs,
               pair_blocks_gb=pairs * 9 * 8 / 1e9, assembly_chunk_groups=int(chunk),
               assembly_intermediate_gb=chunk * K * K * 9 * 8 / 1e9, kff_nonzeros=pairs * 9)
    print(f"model {fig['model_s']:.0f} s, rss {rss_gb():.2f} GB; solver {model.linear.name}, free DOF {free}, "
          f"integration points {Q}, neighbours per point K {K}, groups {ops.groups.shape}, "
          f"pair id table {ops.pair_id.size * 4 / 1e9:.2f} GB (int32), "
          f"particle pairs {pairs} ({pairs / body.n:.0f} per particle), pair blocks {pairs * 9 * 8 / 1e9:.2f} GB "
          f"per copy, assembly chunk {chunk} groups = (chunk, K, K, 3, 3) {chunk * K * K * 9 * 8 / 1e9:.2f} GB "
          f"per intermediate; nonzeros of K_ff ~ {pairs * 9:,} ({pairs * 9 * 12 / 1e9:.2f} GB as CSR)", flush=True)
    if a.solve:
        s.enter("solve")
        t0 = time.time()
        sol = model.solve({"needle": ph.needle_at(ph.insertion / 4)}, throw=False)
        fig.update(increment_s=time.time() - t0, increment_status=sol.outcome.name, rss_after_solve_gb=rss_gb())
        print(f"one increment {fig['increment_s']:.0f} s, status {int(sol.status)}, rss {rss_gb():.2f} GB", flush=True)
        if model.linear.name == "sparse":
            fig["pardiso"] = pardiso_report(model)
    s.enter("end")
    fig["peak_by_stage"] = {stage: {"peak_gb": r, "where": at} for stage, (r, at) in s.peaks.items()}
    fig["peak_rss_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
    print(f"peak rss {fig['peak_rss_gb']:.2f} GB", flush=True)
    records.finish(run, fig)


if __name__ == "__main__":
    main()
