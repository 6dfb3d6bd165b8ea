"""Benchmark: this tree against a checkout of an earlier commit (``--base``, e.g. the
previous main), the same cases in one run, interleaved (base, this, base, this, ...), each run in
a fresh Python process with an empty compilation cache, so that both see the same machine.

Cases (``--cases``), each through the public API that both trees share:

* ``cook_block``: the cantilever block [0, 4] x [0, 1]^2 of ``tests/problems.py`` at spacing
  1/6 (1,225 particles), x = 0 clamped, dead traction (0, 0, 0.5) on x = 4, neo-Hookean at
  nu = 0.499 with anti-locking (the material's default), ``--integration`` (default MSCNI and
  Gauss), one solve;
* ``cube``: the n^3 cube (``--n``), x = 0 clamped, x = 1 pushed 20% in 5 load steps,
  compressible neo-Hookean (nu = 0.3), the default solver;
* ``plate``: the n^3 block, bottom clamped, pressed 10% by a rigid frictionless plate
  (``jaxrkpm.Contact`` with a ``HalfSpace``) in 5 load steps;
* ``phantom3d``: the 3D needle phantom at spacing 0.3 (``Phantom3D(spacing=0.3)``), its static
  paddle sweep with the side inclusion (``static_sweep``: every paddle x 15 increments batched,
  and the no-paddle run).

Per case and tree: the model's build, the first solve (compile included: the cold time), the
warm solve (median of ``--repeats``; not for ``phantom3d``, whose call is the figure), the
Newton iterations and a result (a displacement or force) to check that both trees solve the
same problem (``cube``, ``plate``: the first reaction's time, compile included, is
``first_reaction_s``). The ratio this / base of each figure is the same-run speed-up. Run from the
repository root: ``python -m experiments.bench_previous --base REV [--cases ...]``; writes a
record (experiments/records.py) after every case (``"partial": true`` until the run ends). Figures only from a quiet machine."""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from experiments import records

ROOT = Path(__file__).resolve().parents[1]


# ------------------------------------------------------------------ the cases (child process)
def _timed_solves(build, solve, repeats):
    import jax
    t0 = time.perf_counter()
    model = build()
    build_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    sol = jax.block_until_ready(solve(model))
    first_s = time.perf_counter() - t0
    warm = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        sol = jax.block_until_ready(solve(model))
        warm.append(time.perf_counter() - t0)
    return model, sol, {"build_s": build_s, "first_solve_s": first_s,
                        "warm_solve_s": statistics.median(warm) if warm else None,
                        "newton_iterations": int(sol.iterations), "message": str(sol.message)}


def case_cook_block(integration, repeats, **_):
    import jaxrkpm as jr
    spacing, mu, nu = 1.0 / 6.0, 80.194, 0.499
    lam = 2 * mu * nu / (1 - 2 * nu)

    def build():
        body = jr.Body.grid((round(4 / spacing) + 1, round(1 / spacing) + 1, round(1 / spacing) + 1), spacing)
        return jr.Model(body, jr.NeoHookean(lam, mu), integration=integration,
                        essential={"wall": body.select(lambda X: X[:, 0] < 1e-9)},
                        tractions=[(lambda X: X[:, 0] > 4.0 - 1e-9, [0.0, 0.0, 0.5])])

    model, sol, out = _timed_solves(build, lambda m: m.solve(), repeats)
    out["particles"] = int(model.body.n)
    out["u_z_at_4_0.5_1"] = float(model.displacement(sol, [[4.0, 0.5, 1.0]])[0, 2])
    return out


def case_cube(n, repeats, **_):
    import jax.numpy as jnp
    import jaxrkpm as jr

    def build():
        body = jr.Body.grid((n,) * 3, 1.0 / (n - 1))
        sets = {"wall": body.select(lambda X: X[:, 0] < 1e-9), "right": body.select(lambda X: X[:, 0] > 1 - 1e-9)}
        return jr.Model(body, jr.NeoHookean(lam=1.5, mu=1.0), essential=sets)

    model, sol, out = _timed_solves(build, lambda m: m.solve({"right": jnp.array([-0.2, 0.0, 0.0])}, steps=5),
                                    repeats)
    t0 = time.perf_counter()
    out["reaction_x"] = float(model.reaction(sol, "right")[0])
    out["first_reaction_s"] = time.perf_counter() - t0
    return out


def case_plate(n, repeats, **_):
    import jax.numpy as jnp
    import jaxrkpm as jr
    gap = 1e-3
    params = {"plate": {"position": jnp.array([0.5, 0.5, 0.9])}}

    def build():
        body = jr.Body.grid((n,) * 3, 1.0 / (n - 1))
        plate = jr.Contact(jr.HalfSpace((0.0, 0.0, -1.0)), position=(0.5, 0.5, 1 + 2 * gap), gap=gap, pressure=0.1,
                           name="plate", where=lambda X: X[:, 2] > 1 - 1e-9)
        return jr.Model(body, jr.NeoHookean(lam=1.5, mu=1.0), essential={"bottom": body.select(lambda X: X[:, 2] < 1e-9)},
                        terms=[plate])

    model, sol, out = _timed_solves(build, lambda m: m.solve(params=params, steps=5), repeats)
    out["load_steps"] = int(sol.steps)
    t0 = time.perf_counter()
    out["force_z"] = float(model.reaction(sol, "bottom", params=params)[2])
    out["first_reaction_s"] = time.perf_counter() - t0
    return out


def case_phantom3d(**_):
    import numpy as np
    from jaxrkpm.thesis.needle import static_sweep
    from jaxrkpm.thesis.phantom3d import Phantom3D
    t0 = time.perf_counter()
    phantom = Phantom3D(spacing=0.3)
    build_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    kw = {"progress": False} if "progress" in static_sweep.__code__.co_varnames else {}
    res = static_sweep(phantom, "side", **kw)
    return {"build_s": build_s, "first_solve_s": time.perf_counter() - t0, "warm_solve_s": None,
            "final_deviations": np.abs(np.asarray(res.deviation)[:, -1]).tolist(),
            "converged_fraction": float(np.mean(np.asarray(res.status) == 0))}


CASES = {"cook_block": case_cook_block, "cube": case_cube, "plate": case_plate, "phantom3d": case_phantom3d}


def child(argv):
    a = json.loads(argv)
    import jax
    jax.config.update("jax_enable_x64", True)
    out = CASES[a.pop("case")](**a)
    print("RESULT " + json.dumps(out))


# ------------------------------------------------------------------ the parent
def checkout(rev: str, where: Path) -> Path:
    """A detached worktree of ``rev`` under ``where`` (its package is imported by the base runs)."""
    path = where / "base"
    subprocess.run(["git", "worktree", "add", "--detach", "-f", str(path), rev], cwd=ROOT, check=True,
                   capture_output=True)
    return path


def run_child(tree: Path, spec: dict, timeout: float) -> dict:
    # the tree first (its package is the one imported), then whatever the caller's path held
    path = os.pathsep.join(p for p in (str(tree), os.environ.get("PYTHONPATH", "")) if p)
    env = {**os.environ, "PYTHONPATH": path, "JAXRKPM_COMPILATION_CACHE": "off"}
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    t0 = time.perf_counter()
    try:
        r = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--child", json.dumps(spec)],
                           cwd=tempfile.gettempdir(), env=env, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"error": f"timed out after {timeout:g} s"}
    lines = [line for line in r.stdout.splitlines() if line.startswith("RESULT ")]
    if r.returncode or not lines:
        return {"error": (r.stderr.strip().splitlines() or [f"exit {r.returncode}"])[-1]}
    out = json.loads(lines[-1][len("RESULT "):])
    out["process_s"] = time.perf_counter() - t0
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--base", help="the earlier commit to compare with (e.g. the previous main's sha): required")
    p.add_argument("--cases", nargs="*", default=["cube", "plate", "cook_block"], choices=sorted(CASES))
    p.add_argument("--n", type=int, nargs="*", default=[8], help="particles per edge of cube and plate")
    p.add_argument("--integration", nargs="*", default=["mscni", "gauss"], help="of cook_block")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--rounds", type=int, default=1, help="interleaved rounds of every case")
    p.add_argument("--timeout", type=float, default=1800.0, help="seconds one run may take")
    p.add_argument("--child", help=argparse.SUPPRESS)
    records.add_arguments(p)
    a = p.parse_args(argv)
    if a.child:
        return child(a.child)
    if not a.base:
        p.error("--base is required: the commit to compare with")
    base_sha = subprocess.run(["git", "rev-parse", a.base], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    if not base_sha:
        raise SystemExit(f"--base {a.base!r} is not a commit of this repository")
    specs = []
    for case in a.cases:
        if case == "cook_block":
            specs += [{"case": case, "integration": i, "repeats": a.repeats} for i in a.integration]
        elif case in ("cube", "plate"):
            specs += [{"case": case, "n": n, "repeats": a.repeats} for n in a.n]
        else:
            specs.append({"case": case})
    run = records.start("bench_previous", a)
    figures = {"base": base_sha, "cases": []}
    ratios = {}
    with tempfile.TemporaryDirectory() as tmp:
        base = checkout(base_sha, Path(tmp))
        try:
            for spec in specs:
                label = "_".join(str(v) for k, v in spec.items() if k != "repeats")
                rounds = {"base": [], "this": []}
                for _ in range(a.rounds):
                    for name, tree in (("base", base), ("this", ROOT)):
                        rounds[name].append(run_child(tree, spec, a.timeout))
                        print(label, name, json.dumps(rounds[name][-1]), file=sys.stderr)
                row = {"case": label, "spec": spec, **rounds}
                for key in ("first_solve_s", "warm_solve_s", "build_s", "first_reaction_s"):
                    vals = {k: [r[key] for r in v if r.get(key) is not None] for k, v in rounds.items()}
                    if vals["base"] and vals["this"]:
                        ratios[f"{label}: {key} this/base"] = statistics.median(vals["this"]) / statistics.median(vals["base"])
                figures["cases"].append(row)
                records.finish(run, figures, ratios, partial=True)   # a run cut short keeps its cases
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(base)], cwd=ROOT, capture_output=True)
    print(json.dumps(ratios, indent=1))
    records.finish(run, figures, ratios)


if __name__ == "__main__":
    main()
