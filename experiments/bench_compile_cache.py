"""The persistent compilation cache (jaxrkpm/base/cache.py), measured: ``jaxrkpm demo`` run
twice, each in a fresh process, with a fresh cache folder; each run's own line (its tracking
loop's compile time) and the whole command's wall time. ``--min-compile-s`` overrides the
smallest compile time a program must take to be kept (``use_compilation_cache(min_compile_s=...)``).

    python -m experiments.bench_compile_cache [--min-compile-s 0.1]

Only comparable on a quiet machine (``uptime``).
"""
import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from experiments import records

ROOT = Path(__file__).resolve().parents[1]

ap = argparse.ArgumentParser()
ap.add_argument("--min-compile-s", type=float, default=None)
records.add_arguments(ap)
a = ap.parse_args()
rec = records.start("bench_compile_cache", a)
figures = {}
code = "import sys\nfrom jaxrkpm.base import cache\n"
if a.min_compile_s is not None:   # set first: the command line keeps a cache JAX already has
    code += f"cache.use_compilation_cache(min_compile_s={a.min_compile_s})\n"
code += "from jaxrkpm.thesis import cli\nsys.exit(cli.main(sys.argv[1:]))"
with tempfile.TemporaryDirectory() as tmp:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("JAX_COMPILATION", "JAX_PERSISTENT", "JAXRKPM_"))}
    env.update(XDG_CACHE_HOME=tmp, PYTHONPATH=str(ROOT))
    for run in (1, 2):
        t0 = time.perf_counter()
        p = subprocess.run([sys.executable, "-c", code, "demo", "--overwrite", "--out", f"{tmp}/demo"],
                           capture_output=True, text=True, env=env, cwd=ROOT)
        wall = time.perf_counter() - t0
        line = p.stdout.strip().splitlines()[-1] if p.stdout.strip() else p.stderr[-500:]
        files = list((Path(tmp) / "jaxrkpm").glob("*-cache"))
        print(f"run {run}: wall {wall:.1f} s, {len(files)} programs cached; {line.split('iterations, ')[-1]}")
        assert p.returncode == 0, p.stderr[-2000:]
        # the demo's line: "..., <warm> s warm + <compile> s compile (thesis: ...)"
        tail = line.split("iterations, ")[-1]
        warm_s, compile_s = (float(part.split(" s ")[0]) for part in tail.split(" + ")[:2])
        figures[f"run{run}"] = {"wall_s": wall, "programs_cached": len(files), "warm_s": warm_s,
                                "compile_s": compile_s}
records.finish(rec, figures, {"second_over_first": {
    k: figures["run2"][k] / figures["run1"][k] for k in ("wall_s", "compile_s")}})
