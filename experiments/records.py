"""Benchmark records: every run of an ``experiments/bench_*.py`` writes one JSON record, and
the performance page (``docs/performance.md``, rendered by ``experiments/performance.py``) is
made from the latest record of each bench. A figure is only ever written by a bench run.

A bench adds two lines::

    run = records.start("bench_solve", args)     # after parsing its arguments
    ...
    records.finish(run, figures, ratios)         # what it prints, and its same-run ratios

A record holds the commit (and whether the tree had uncommitted changes), the date, the
machine (CPU model, cores, memory, GPU if any, the versions of Python, jax, jaxlib, NumPy,
SciPy and MKL, the thread settings), the load average before and after the run, the bench's
arguments, its figures (medians with min/max and the repeats, via :func:`stats`) and the
ratios it reports between figures of the same run.

Records go to ``experiments/records/<bench>/<date>-<commit>.json`` (committed: the page's
source). ``--smoke`` marks a run as a smoke run (tiny arguments, a check that the bench and
the pipeline work, figures meaningless) and writes it under ``experiments/records/smoke/``,
which git ignores; ``--no-record`` writes nothing. Run the benches from the repository root
as modules (``python -m experiments.bench_solve``) on a quiet machine: the load average is
recorded beside every figure, and a page table from a loaded machine says so.
"""
from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import time
from importlib import metadata
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RECORDS = Path(__file__).resolve().parent / "records"
SMOKE = RECORDS / "smoke"
SCHEMA = 1
THREAD_VARIABLES = ("JAXRKPM_BLAS_THREADS", "JAXRKPM_SPARSE_THREADS", "OPENBLAS_NUM_THREADS",
                    "MKL_NUM_THREADS", "OMP_NUM_THREADS", "KMP_BLOCKTIME", "XLA_FLAGS")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The record options every bench takes: ``--smoke`` and ``--no-record``."""
    group = parser.add_argument_group("record")
    group.add_argument("--smoke", action="store_true",
                       help="a smoke run (tiny arguments): its record goes to experiments/records/smoke/ "
                            "(ignored by git) and never onto the performance page")
    group.add_argument("--no-record", action="store_true", help="write no record")
    group.add_argument("--label", default="",
                       help="a name for this kind of run: the performance page shows the latest record of "
                            "each label of a bench (e.g. a second size range)")


def stats(times) -> dict:
    """Median, min, max and repeats of a list of timings (seconds)."""
    times = [float(t) for t in times]
    if not times:
        return {"median": None, "min": None, "max": None, "repeats": 0}
    return {"median": statistics.median(times), "min": min(times), "max": max(times), "repeats": len(times)}


def warm(f, repeats: int):
    """(``stats`` of ``repeats`` warm calls of ``f()``, its last result): one untimed call first
    (the compile), and every call waited for (JAX returns before it has computed)."""
    import jax
    out = jax.block_until_ready(f())
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(f())
        times.append(time.perf_counter() - t0)
    return stats(times), out


def _git(*args: str) -> str | None:
    try:
        out = subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() if out.returncode == 0 else None


def commit() -> dict:
    """The commit the bench ran at, and whether tracked files differed from it (the records
    folder itself aside: writing records does not make a tree dirty)."""
    status = _git("status", "--porcelain", "--untracked-files=no", "--", ".", ":(exclude)experiments/records")
    return {"sha": _git("rev-parse", "HEAD"), "dirty": bool(status) if status is not None else None,
            "branch": _git("rev-parse", "--abbrev-ref", "HEAD")}


def _version(name: str) -> str | None:
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return None


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _memory_gb() -> float | None:
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemTotal:"):
                    return int(line.split()[1]) * 1024 / 1e9
    except OSError:
        pass
    return None


def _gpus() -> list[str]:
    """GPUs the machine has: JAX's devices where JAX is loaded, else nvidia-smi's list."""
    jax = sys.modules.get("jax")
    if jax is not None:
        try:
            return [str(d) for d in jax.devices() if d.platform != "cpu"]
        except RuntimeError:
            return []
    if shutil.which("nvidia-smi"):
        out = subprocess.run(["nvidia-smi", "-L"], capture_output=True, text=True)
        return [line for line in out.stdout.splitlines() if line.strip()]
    return []


def machine() -> dict:
    """The machine a bench ran on (no JAX import: the versions come from the installed
    packages)."""
    try:
        usable = len(os.sched_getaffinity(0))
    except AttributeError:
        usable = os.cpu_count()
    return {"cpu": _cpu_model(), "cores": os.cpu_count(), "usable_cores": usable,
            "memory_gb": _memory_gb(), "gpus": _gpus(), "platform": platform.platform(),
            "python": platform.python_version(),
            "versions": {name: _version(name) for name in ("jax", "jaxlib", "numpy", "scipy", "mkl")},
            "threads": {k: os.environ.get(k) for k in THREAD_VARIABLES if os.environ.get(k) is not None}}


def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


class Run(dict):
    """A record being made (a dict: what :func:`finish` writes)."""


def start(bench: str, args: argparse.Namespace | None = None, variant: str = "") -> Run:
    """Begin the record of a run of ``bench``: the date, the commit, the load average now and
    the arguments (call it once the arguments are parsed, before any timing). ``variant``
    names a mode of the bench whose figures stand apart (``--label`` overrides it)."""
    arguments = {k: v for k, v in vars(args or argparse.Namespace()).items()}
    variant = arguments.pop("label", "") or variant
    run = Run(bench=bench, variant=variant, schema=SCHEMA, smoke=bool(arguments.pop("smoke", False)),
              date=_now(), commit=commit(), arguments=arguments, argv=sys.argv[1:],
              load_average={"before": list(os.getloadavg())})
    run["_record"] = not arguments.pop("no_record", False)
    run["_t0"] = time.perf_counter()
    return run


def finish(run: Run, figures: dict, ratios: dict | None = None, notes: str | None = None,
           partial: bool = False) -> Path | None:
    """Complete the record with the machine, the load average now, the figures and the
    same-run ratios, and write it; returns its path (None with ``--no-record``).
    ``partial``: write the figures so far (marked ``"partial": true``) and leave the run
    open, to the same path, so that a run stopped by a time limit keeps what it finished."""
    if partial:
        run = Run(run, load_average=dict(run["load_average"]), partial=True)
    run["load_average"]["after"] = list(os.getloadavg())
    run["wall_s"] = time.perf_counter() - run.pop("_t0")
    write = run.pop("_record")
    run["machine"] = machine()
    run["figures"] = figures
    run["ratios"] = _flat(ratios or {})
    if notes:
        run["notes"] = notes
    if not write:
        return None
    folder = (SMOKE if run["smoke"] else RECORDS) / run["bench"]
    folder.mkdir(parents=True, exist_ok=True)
    sha = (run["commit"]["sha"] or "nogit")[:8]
    path = folder / f"{run['date'].replace(':', '').replace('-', '')}-{sha}.json"
    path.write_text(json.dumps(run, indent=1, default=_plain) + "\n")
    if not partial:
        print(f"record: {path.relative_to(ROOT)}", file=sys.stderr)
    return path


def _flat(ratios: dict, prefix: str = "") -> dict:
    """Nested ratio dicts as one level: {"a": {"b": 2}} -> {"a: b": 2}."""
    out = {}
    for k, v in ratios.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}: "))
        else:
            out[f"{prefix}{k}"] = v
    return out


def _plain(x):
    """JSON for NumPy scalars and arrays, and anything else by its text."""
    if hasattr(x, "tolist"):
        return x.tolist()
    return str(x)


def latest(bench: str, smoke: bool = False, folder: Path = RECORDS) -> list[dict]:
    """The newest record of each variant of ``bench``, in the order of the variants' names
    (smoke runs count only with ``smoke``)."""
    paths = list((folder / bench).glob("*.json"))
    if smoke:
        paths += list((folder / "smoke" / bench).glob("*.json"))
    newest = {}
    for path in sorted(paths, key=lambda p: p.name):
        record = json.loads(path.read_text())
        newest[record.get("variant", "")] = record
    return [newest[k] for k in sorted(newest)]
