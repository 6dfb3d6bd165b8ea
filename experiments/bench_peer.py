"""Benchmark against the peer (issue 48): jaxrkpm and FElupe solve the same 3D problems, and
each code's time is compared with the other's at the same error.

Problems (the same energy, loads, boundary conditions and load steps in both codes; jaxrkpm's
``NeoHookean(lam, mu)``, W = mu/2 (tr C - 3) - mu ln J + lam/2 (ln J)^2, which is FElupe's
``NeoHookeCompressible(mu, lmbda=lam)``; ``experiments/cook_reference.py`` checks the identity):

* ``cube``: the unit cube, the face x = 0 clamped, the face x = 1 moved by (-push, 0, 0) (every
  component of both faces prescribed), mu = 1 and Poisson's ratio --nu. jaxrkpm: n^3 particles
  (``Body.grid``), the model's defaults (Gauss integration; --integration adds SCNI). FElupe:
  m^3 tri-quadratic hexahedra (hex27, ``RegionTriQuadraticHexahedron``, 27 Gauss points).
* ``incompressible``: the same cube at Poisson's ratio --nu-incompressible. jaxrkpm: the same
  model with ``anti_locking=True``. FElupe: the three-field u-p-Jbar formulation
  (``NearlyIncompressible(NeoHookeCompressible(mu), bulk=lam, U = lam/2 (ln Jbar)^2)``, exactly
  W at p = U'(J), Jbar = J) on serendipity hexahedra with element-constant p and Jbar (hex20-P0,
  ``FieldsMixed`` on ``RegionQuadraticHexahedron``, cook_reference.py's family); --mixed
  hex27-P0: tri-quadratic hexahedra with element-constant p and Jbar; hex27-dQ1: FElupe's own
  dual fields of hex27 (discontinuous trilinear p and Jbar), which on this cube converge from
  above and slowly, where the P0 families converge from below.
* ``plate``: the unit cube, the face z = 0 clamped, pressed by --compression by a rigid
  frictionless plate over its top face. jaxrkpm: ``Contact(HalfSpace(normal=(0, 0, -1)))``
  on the top face's boundary points, its pose moved from 2 gaps above the top to z = 1 -
  compression (barrier range --gap, pressure parameter the nominal pressure E x compression).
  FElupe: hex27 with ``ContactRigidPlane`` on the top face's nodes (its centre point moved from
  z = 1 to the same final plane z = 1 - compression; penalty ``multiplier`` --penalty times
  FElupe's mean-stiffness base). Each code's regularisation error (barrier stand-off, penalty
  penetration) is part of its error.

Errors. Reaction: the x (cube) or z (plate) component of the resultant force that the moved
face or the plate exerts on the body (jaxrkpm: ``Model.reaction`` of the moved set,
``contact_forces(...).force``; FElupe: the sum of the internal nodal forces over those nodes),
error |R - R_ref| / |R_ref|. Probe: the displacement at a point (cube: the top edge's midpoint
(0.5, 1, 1), whose x component is -push/2 by symmetry, so only its bulge, y and z, counts;
plate: the side face's centre (0.5, 1, 0.5), y and z), error |u - u_ref| / |u_ref| over those
components. The references are FElupe solutions on finer meshes of the same element family
(--ref-m, each twice the one before; --ref-steps load steps: an equilibrium does not depend
on them), extrapolated by Richardson from the three finest with their observed order; the
error estimate is the extrapolation's correction |V - finest|, or with four levels or more
the change of V from the next coarser triple (where the three finest are not monotone and
contracting: V = the finest value, the estimate its last change). The plate's reference is
the limit of frictionless contact over the whole top face: u_z = -compression prescribed on
the top face, u_x and u_y free (exact contact, no penalty or barrier); the record checks that
every top node then pushes against the plate (no node would lift off). References are cached
in ``experiments/bench_peer_reference.json`` under their problem, family and levels
(--recompute-reference makes them anew; --smoke keeps its coarse ones out of the file).

Timing. Every (code, size) runs in a fresh subprocess, jaxrkpm and FElupe interleaved (the
jaxrkpm sizes and the FElupe sizes alternate within a case; --rounds repeats the whole
sequence). In each process: ``import`` (jax and jaxrkpm, or felupe and pypardiso), ``build``
(jaxrkpm: ``Body.grid`` and ``Model``; FElupe: mesh, region, fields, material, boundaries), the
first solve (the cold solve; jaxrkpm's compile inside it is the union of JAX's trace, lowering
and backend-compile spans, reported apart, with an empty compilation cache:
JAXRKPM_COMPILATION_CACHE=off and JAX_COMPILATION_CACHE_DIR a fresh empty folder), the first
post-processing (reaction and probe), then --repeats warm solves (median, min, max). A solve is
the whole load path from the undeformed state (FElupe: the fields reset, its items made anew,
one ``Step`` of --steps equal increments; jaxrkpm: ``Model.solve(..., steps=--steps)``, which may
cut and then regrow its steps; the load steps each took are recorded). "cold" = import + build +
first solve (the time from a fresh process to the solved state); "cold_to_answer" adds the first
post-processing (jaxrkpm compiles its reaction and displacement evaluations there).

Convergence criteria (the same tolerance, --tol, default jaxrkpm's ``Tolerance().rtol``):
jaxrkpm stops when |r_free| <= rtol max(|r_ref|, force scale) (``jaxrkpm.solvers.newton``);
FElupe when |f_free| / (1e-3 + |f_prescribed|) < tol (``felupe.tools.newtonraphson``, full
Newton, no line search, at most 30 iterations a step). After each code's first solve the
record keeps the same measure for both, |r_free| / |r_prescribed| (the reactions of the
essential DOFs), so that the two stops can be compared.

Equal error. For each jaxrkpm size, FElupe's time to reach jaxrkpm's error is read off
FElupe's (error, time) points: those that no cheaper size beats in error, joined log-log
("interpolated"). An error above the cheapest point's takes that point's time (FElupe reaches
a smaller error in it: "coarsest", the ratio a lower bound); one below the smallest error
FElupe reached takes the finest point's time (FElupe would need more: "finest", the ratio an
upper bound; add finer --m), never an extrapolation. The ratio is jaxrkpm's time over
FElupe's (above 1: FElupe reaches that error sooner), for the warm and the cold time, by the
reaction error and by the probe error; the ratio's key says where it is a bound. Errors
within twice the reference's own relative error estimate are marked unresolved
(``reaction_error_resolved``).

Threads: both codes run with the environment the bench was started in (recorded); KMP_BLOCKTIME
is set to 0 where unset, for both (jaxrkpm's import does so for its own PARDISO; FElupe's
pypardiso uses the same Intel OpenMP runtime). --single-thread runs both on one thread (BLAS,
MKL, OpenMP, XLA): for a shared machine, where threads that wait for a busy core distort both.

Run from the repository root on a quiet machine (FElupe from the ``reference`` extra)::

    python -m experiments.bench_peer                       # all cases, default sizes
    python -m experiments.bench_peer --quick               # fewer sizes and repeats
    python -m experiments.bench_peer --smoke --no-record   # tiny sizes: a check of the pipeline

writes a record (experiments/records.py) and prints the summary table.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from experiments import records

HERE = Path(__file__).resolve().parent
REFERENCE_FILE = HERE / "bench_peer_reference.json"
CASES = ("cube", "incompressible", "plate")
# default sizes: jaxrkpm particles a side (n) and FElupe elements a side (m) per case
SIZES = {"cube": {"n": [6, 8, 10, 12], "m": [1, 2, 3, 4, 6, 8]},
         "incompressible": {"n": [6, 8, 10, 12], "m": [1, 2, 3, 4, 6, 8]},
         "plate": {"n": [6, 10], "m": [1, 2, 3, 4, 6, 8]}}
QUICK = {"cube": {"n": [6, 8], "m": [1, 2, 3, 4]},
         "incompressible": {"n": [6, 8], "m": [1, 2, 3, 4]},
         "plate": {"n": [6], "m": [1, 2, 3, 4]}}
SMOKE = {"n": [4], "m": [1, 2]}
REF_M = [2, 4, 8, 16]
SMOKE_REF_M = [1, 2, 4]
PROBES = {"cube": ((0.5, 1.0, 1.0), (1, 2)), "incompressible": ((0.5, 1.0, 1.0), (1, 2)),
          "plate": ((0.5, 1.0, 0.5), (1, 2))}
TOL = 1e-9          # coordinates: which nodes or particles lie on a face
THREAD_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "JAXRKPM_BLAS_THREADS",
               "JAXRKPM_SPARSE_THREADS")
COMPILE_EVENTS = ("/jax/core/compile/jaxpr_trace_duration", "/jax/core/compile/jaxpr_to_mlir_module_duration",
                  "/jax/core/compile/backend_compile_duration")


# ----------------------------------------------------------------------------- the problems
def problem(case: str, a) -> dict:
    """The parameters of a case (both codes read them, and the reference cache keys on them)."""
    nu = a.nu_incompressible if case == "incompressible" else a.nu
    mu = a.mu
    lam = 2.0 * mu * nu / (1.0 - 2.0 * nu)
    p = {"case": case, "mu": mu, "nu": nu, "lam": lam, "steps": a.steps}
    if case == "plate":
        E = mu * (3 * lam + 2 * mu) / (lam + mu)
        p.update(compression=a.compression, gap=a.gap, contact_pressure=E * a.compression, penalty=a.penalty)
    else:
        p.update(push=a.push)
    if case == "incompressible":
        p["mixed"] = a.mixed
    p["probe"], p["probe_components"] = PROBES[case]
    return p


def family(p: dict) -> str:
    """FElupe's element family of a case."""
    return p.get("mixed", "hex27") if p["case"] == "incompressible" else "hex27"


# ----------------------------------------------------------------------------- jaxrkpm
class CompileClock:
    """The time JAX spends tracing, lowering and compiling (the union of its spans, so nested
    traces count once), within given windows of wall time (time.time())."""

    def __init__(self):
        import jax
        self.spans, self.hits = [], 0
        jax.monitoring.register_event_time_span_listener(self._span)
        jax.monitoring.register_event_listener(self._event)

    def _span(self, event, start, end, **_):
        if event in COMPILE_EVENTS:
            self.spans.append((start, end))

    def _event(self, event, **_):
        if event == "/jax/compilation_cache/cache_hits":
            self.hits += 1

    def within(self, t0: float, t1: float) -> float:
        spans = sorted((max(s, t0), min(e, t1)) for s, e in self.spans if e > t0 and s < t1)
        total, end = 0.0, -math.inf
        for s, e in spans:
            if e > end:
                total += e - max(s, end)
                end = e
        return total


def jaxrkpm_worker(p: dict, n: int, repeats: int, integration: str, solver: str) -> dict:
    t0 = time.perf_counter()
    import jax
    import jax.numpy as jnp
    import numpy as np

    import jaxrkpm as jr
    from jaxrkpm.solvers.newton import Tolerance
    jr.Model, jr.Body, jr.NeoHookean, jr.Contact, jr.HalfSpace, jr.contact_forces   # noqa: B018 - lazy imports load now
    out = {"import_s": time.perf_counter() - t0, "n": n, "particles": n ** 3, "integration": integration,
           "rtol": Tolerance().rtol, "jaxrkpm_path": str(Path(jr.__file__).parent)}
    clock = CompileClock()
    case = p["case"]

    w0, t0 = time.time(), time.perf_counter()
    body = jr.Body.grid((n, n, n), 1.0 / (n - 1))
    material = jr.NeoHookean(lam=p["lam"], mu=p["mu"])
    if case == "plate":
        gap, c = p["gap"], p["compression"]
        top = lambda Y: np.asarray(Y)[:, 2] > 1 - TOL   # noqa: E731
        plate = jr.Contact(jr.HalfSpace(normal=(0.0, 0.0, -1.0)), position=(0.5, 0.5, 1.0 + 2 * gap), gap=gap,
                           pressure=p["contact_pressure"], name="plate", where=top)
        bottom = body.select(lambda Y: Y[:, 2] < TOL)
        model = jr.Model(body, material, integration=integration, essential={"bottom": bottom}, terms=[plate],
                         solver=solver)
        params = {"plate": {"position": jnp.array([0.5, 0.5, 1.0 - c])}}
        solve = lambda: model.solve(params=params, steps=p["steps"])   # noqa: E731
    else:
        sets = {"left": body.select(lambda Y: Y[:, 0] < TOL), "right": body.select(lambda Y: Y[:, 0] > 1 - TOL)}
        model = jr.Model(body, material, integration=integration, essential=sets, solver=solver,
                         anti_locking=True if case == "incompressible" else None)
        params = None
        push = jnp.array([-p["push"], 0.0, 0.0])
        solve = lambda: model.solve({"right": push}, steps=p["steps"])   # noqa: E731
    out["build_s"] = time.perf_counter() - t0
    out["build_compile_s"] = clock.within(w0, time.time())
    out["dof"] = int(len(model.sets.free) * 3)
    out["linear_solver"] = getattr(model.linear, "name", type(model.linear).__name__)

    def timed_solve():
        w0, t0 = time.time(), time.perf_counter()
        sol = solve()
        jax.block_until_ready(sol.u)
        return sol, time.perf_counter() - t0, clock.within(w0, time.time())

    sol, out["first_solve_s"], out["first_solve_compile_s"] = timed_solve()
    out["cold_s"] = out["import_s"] + out["build_s"] + out["first_solve_s"]
    out["compile_cache_hits"] = clock.hits

    def post(sol):
        if case == "plate":
            force = float(jr.contact_forces(model, sol, "plate", params).force[2])
        else:
            force = float(model.reaction(sol, "right")[0])
        probe = np.asarray(model.displacement(sol, np.array([p["probe"]])))[0]
        return force, probe

    t0 = time.perf_counter()
    out["reaction"], probe = post(sol)
    out["first_post_s"] = time.perf_counter() - t0
    out["probe_u"] = probe.tolist()
    out.update(newton_iterations=int(sol.iterations), load_steps=int(sol.steps), cuts=int(sol.cuts),
               status=sol.outcome.name, message=str(sol.message))
    # the same convergence measure as FElupe's run: |r_free| / |r_prescribed|
    prob = model.problem(params)
    r = np.asarray(prob.residual(sol.u, sol.g, sol.load))
    R = np.asarray(model.reactions(sol, params))
    out["relative_residual"] = float(np.linalg.norm(r) / max(np.linalg.norm(R), 1e-300))
    if case == "plate":
        out["bottom_reaction"] = float(model.reaction(sol, "bottom", params)[2])
        out["min_gap"] = float(jr.contact_forces(model, sol, "plate", params).min_gap)
    times, its, compiles = [], [], []
    for _ in range(repeats):
        s, t, c = timed_solve()
        times.append(t)
        its.append(int(s.iterations))
        compiles.append(c)
    out["warm_s"] = records.stats(times)
    out["warm_newton_iterations"] = its
    out["warm_compile_s"] = max(compiles) if compiles else None
    return out


# ----------------------------------------------------------------------------- FElupe
def _linear_solver():
    try:
        import pypardiso
        return pypardiso.spsolve, "pypardiso"
    except ImportError:
        from scipy.sparse.linalg import spsolve
        return spsolve, "scipy.sparse.linalg.spsolve (SuperLU)"


def felupe_model(p: dict, m: int, variant: str):
    """(field, items-maker, boundaries, ramp-maker, readers) of a case on m^3 elements;
    ``variant`` "timed" (the plate: ContactRigidPlane) or "reference" (the plate: the exact
    frictionless-contact limit, u_z prescribed on the top face)."""
    import felupe as fem
    import numpy as np

    case = p["case"]
    fam = family(p)
    mesh = fem.Cube(n=m + 1)
    if fam == "hex20-P0":
        mesh = mesh.convert(order=2)
    else:
        mesh = mesh.add_midpoints_edges().add_midpoints_faces().add_midpoints_volumes()
    contact = case == "plate" and variant == "timed"
    if contact:
        mesh.update(points=np.vstack([mesh.points, [[0.5, 0.5, 1.0]]]))   # the plate's centre point
    x = mesh.points
    region = fem.RegionQuadraticHexahedron(mesh) if fam == "hex20-P0" else fem.RegionTriQuadraticHexahedron(mesh)
    if case == "incompressible" and fam == "hex27-P0":   # element-constant p and Jbar on hex27
        dual = fem.RegionConstantHexahedron(mesh.dual(points_per_cell=1), quadrature=region.quadrature, grad=False)
        field = fem.FieldContainer([fem.Field(region, dim=3), fem.Field(dual, values=0.0), fem.Field(dual, values=1.0)])
    elif case == "incompressible":
        field = fem.FieldsMixed(region, n=3)
    if case == "incompressible":
        lam = p["lam"]
        umat = fem.NearlyIncompressible(fem.NeoHookeCompressible(mu=p["mu"]), bulk=lam,
                                        dUdJ=lambda J, K: K * np.log(J) / J,
                                        d2UdJdJ=lambda J, K: K * (1.0 - np.log(J)) / J ** 2)
    else:
        field = fem.FieldContainer([fem.Field(region, dim=3)])
        umat = fem.NeoHookeCompressible(mu=p["mu"], lmbda=p["lam"])
    u = field[0]
    on = lambda axis, v: np.isclose(x[:, axis], v)   # noqa: E731
    if case == "plate":
        bottom, top = on(2, 0.0), on(2, 1.0)
        if contact:
            top[-1] = False
            centre = np.zeros(len(x), bool)
            centre[-1] = True
            bounds = {"bottom": fem.Boundary(u, mask=bottom),
                      "centre_xy": fem.Boundary(u, mask=centre, skip=(0, 0, 1)),
                      "move": fem.Boundary(u, mask=centre, skip=(1, 1, 0))}
        else:
            bounds = {"bottom": fem.Boundary(u, mask=bottom), "move": fem.Boundary(u, mask=top, skip=(1, 1, 0))}
        loaded, axis, total = top, 2, -p["compression"]
    else:
        left, right = on(0, 0.0), on(0, 1.0)
        bounds = {"left": fem.Boundary(u, mask=left), "right_yz": fem.Boundary(u, mask=right, skip=(1, 0, 0)),
                  "move": fem.Boundary(u, mask=right, skip=(0, 1, 1))}
        loaded, axis, total = right, 0, -p["push"]
    ramp = total * np.linspace(0.0, 1.0, p["steps"] + 1)[1:]

    def items():
        solid = fem.SolidBody(umat, field)
        if not contact:
            return solid, [solid]
        plane = fem.ContactRigidPlane(field, points=np.flatnonzero(top), centerpoint=len(x) - 1,
                                      normal=[0.0, 0.0, -1.0], multiplier=p["penalty"], items=[solid])
        return solid, [solid, plane]

    probe = np.flatnonzero(np.all(np.isclose(x, p["probe"]), axis=1))
    if len(probe) != 1:
        raise ValueError(f"no node at the probe {p['probe']} on {m}^3 {fam}")
    dofs = int(sum(f.values.size for f in field.fields))
    return field, items, bounds, ramp, (loaded, axis, probe[0]), dofs


def felupe_solve(field, items, bounds, ramp, tol, solver, initial):
    """One load path from the undeformed state: (solid, Newton iterations, load steps, the
    relative residual |f_free| / |f_prescribed| where the last step stopped)."""
    import felupe as fem
    import numpy as np
    for f, v in zip(field.fields, initial):
        f.values[:] = v
    solid, its = items()
    step = fem.Step(items=its, ramp={bounds["move"]: ramp}, boundaries=bounds)
    results = list(step.generate(x0=field, tol=tol, maxiter=30, verbose=0, solver=solver))
    if len(results) != len(ramp):
        raise RuntimeError(f"FElupe stopped after {len(results)} of {len(ramp)} load steps")
    dof0, dof1 = fem.dof.partition(field, bounds)
    f = np.asarray(results[-1].fun.toarray() if hasattr(results[-1].fun, "toarray") else results[-1].fun).ravel()
    residual = float(np.linalg.norm(f[dof1]) / max(np.linalg.norm(f[dof0]), 1e-300))
    return solid, sum(int(r.iterations) for r in results), len(results), residual


def felupe_results(p, field, solid, readers) -> dict:
    import numpy as np
    loaded, axis, probe = readers
    f = np.asarray(solid.assemble.vector(field).toarray()).ravel()
    nu = field[0].values.size
    forces = f[:nu].reshape(-1, 3)
    out = {"reaction": float(forces[loaded, axis].sum()), "probe_u": field[0].values[probe].tolist()}
    if p["case"] == "plate":
        out["bottom_reaction"] = float(forces[np.isclose(field.region.mesh.points[:, 2], 0.0), 2].sum())
        out["min_top_nodal_force"] = float(-forces[loaded, 2].max())   # > 0: every top node pushes on the plate
    return out


def felupe_worker(p: dict, m: int, repeats: int, tol: float, variant: str = "timed") -> dict:
    t0 = time.perf_counter()
    import felupe as fem
    import numpy as np
    solver, solver_name = _linear_solver()
    out = {"import_s": time.perf_counter() - t0, "m": m, "family": family(p), "linear_solver": solver_name,
           "felupe": fem.__version__, "tol": tol}
    t0 = time.perf_counter()
    field, items, bounds, ramp, readers, out["dof"] = felupe_model(p, m, variant)
    initial = [np.copy(f.values) for f in field.fields]
    out["build_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    solid, out["newton_iterations"], out["load_steps"], out["relative_residual"] = felupe_solve(
        field, items, bounds, ramp, tol, solver, initial)
    out["first_solve_s"] = time.perf_counter() - t0
    out["cold_s"] = out["import_s"] + out["build_s"] + out["first_solve_s"]
    t0 = time.perf_counter()
    out.update(felupe_results(p, field, solid, readers))
    out["first_post_s"] = time.perf_counter() - t0
    times, iters = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        _, k, _, _ = felupe_solve(field, items, bounds, ramp, tol, solver, initial)
        times.append(time.perf_counter() - t0)
        iters.append(k)
    out["warm_s"] = records.stats(times)
    out["warm_newton_iterations"] = iters
    return out


# ----------------------------------------------------------------------------- subprocesses
def worker_env(fresh_cache: Path | None) -> dict:
    """The environment of a worker: the bench's own, KMP_BLOCKTIME=0 where unset, and for a
    jaxrkpm worker an empty compilation cache."""
    env = dict(os.environ)
    env.setdefault("KMP_BLOCKTIME", "0")
    env.setdefault("PYTHONPATH", str(records.ROOT))
    if fresh_cache is not None:
        env["JAXRKPM_COMPILATION_CACHE"] = "off"
        env["JAX_COMPILATION_CACHE_DIR"] = str(fresh_cache)
    return env


def run_worker(code: str, p: dict, size: int, a, *, repeats: int, variant: str = "timed",
               integration: str = "gauss") -> dict:
    """One (code, size) in a fresh subprocess; its result, or {"error": ...}."""
    cache = Path(tempfile.mkdtemp(prefix="bench_peer_jax_")) if code == "jaxrkpm" else None
    cmd = [sys.executable, "-m", "experiments.bench_peer", "--worker", code, "--problem", json.dumps(p),
           "--size", str(size), "--repeats", str(repeats), "--tol", repr(a.tol), "--variant", variant,
           "--integration", integration, "--solver", a.solver]
    try:
        r = subprocess.run(cmd, cwd=records.ROOT, env=worker_env(cache), capture_output=True, text=True,
                           timeout=a.timeout)
    except subprocess.TimeoutExpired:
        return {"error": f"timed out after {a.timeout} s"}
    finally:
        if cache is not None:
            shutil.rmtree(cache, ignore_errors=True)
    lines = r.stdout.strip().splitlines()
    if r.returncode != 0 or not lines:
        tail = r.stderr.strip().splitlines()
        return {"error": tail[-1] if tail else f"exit {r.returncode}"}
    return json.loads(lines[-1])


def default_tol() -> float:
    """jaxrkpm's default residual tolerance (asked of a subprocess: the bench itself imports
    neither code, so that each worker starts with the bench's environment)."""
    r = subprocess.run([sys.executable, "-c", "from jaxrkpm.solvers.newton import Tolerance; print(Tolerance().rtol)"],
                       cwd=records.ROOT, env=worker_env(None), capture_output=True, text=True, timeout=300)
    if r.returncode != 0:
        raise SystemExit(f"cannot read jaxrkpm's tolerance: {r.stderr.strip()[-500:]}")
    return float(r.stdout.strip().splitlines()[-1])


# ----------------------------------------------------------------------------- references
def richardson(values, levels) -> dict:
    """The limit of a sequence on meshes each twice as fine as the one before: Richardson from
    the three finest with their observed order; error estimate: the correction |V - finest|,
    or with four levels or more the change of V from the next coarser triple (where the
    sequence is not monotone and contracting: V = the finest value, error its last change)."""
    if len(values) < 3 or any(b != 2 * c for b, c in zip(levels[1:], levels[:-1])):
        raise ValueError(f"reference levels must be at least three, each twice the one before: {levels}")

    def ext(v1, v2, v3):
        d1, d2 = v2 - v1, v3 - v2
        if d1 == 0 or d2 == 0 or not 0 < d2 / d1 < 1:
            return v3, None
        order = math.log(d1 / d2) / math.log(2.0)
        return v3 + d2 / (2.0 ** order - 1.0), order

    value, order = ext(*values[-3:])
    if order is None:
        error = abs(values[-1] - values[-2])
    elif len(values) >= 4:
        error = abs(value - ext(*values[-4:-1])[0])
    else:
        error = abs(value - values[-1])
    return {"value": value, "order": order, "error_estimate": error, "finest": values[-1]}


def reference_key(p: dict, levels) -> str:
    keep = ("case", "mu", "nu", "push", "compression", "probe")
    return json.dumps({**{k: p[k] for k in keep if k in p}, "family": family(p), "levels": list(levels)},
                      sort_keys=True)


def reference(p: dict, a, levels, log) -> dict:
    """The case's reference (cached in REFERENCE_FILE unless --smoke)."""
    key = reference_key(p, levels)
    cache = json.loads(REFERENCE_FILE.read_text()) if REFERENCE_FILE.exists() else {}
    if key in cache and not a.recompute_reference:
        return {**cache[key], "cached": True}
    rows = []
    p = {**p, "steps": a.ref_steps or p["steps"]}   # an equilibrium: the same whatever the path's steps
    for m in levels:
        t0 = time.perf_counter()
        r = run_worker("felupe", p, m, a, repeats=0, variant="reference")
        if "error" in r:
            raise SystemExit(f"reference {p['case']} m={m}: {r['error']}")
        log(f"reference {p['case']} {family(p)} m={m}: reaction {r['reaction']:.9g} probe {r['probe_u']} "
            f"({time.perf_counter() - t0:.0f} s)")
        rows.append({k: r.get(k) for k in ("m", "dof", "reaction", "probe_u", "newton_iterations", "load_steps",
                                           "relative_residual", "min_top_nodal_force", "first_solve_s")})
    comps = p["probe_components"]
    ref = {"case": p["case"], "family": family(p), "levels": list(levels), "meshes": rows,
           "reaction": richardson([r["reaction"] for r in rows], levels),
           "probe": {str(c): richardson([r["probe_u"][c] for r in rows], levels) for c in comps},
           "tol": a.tol, "felupe": run_version(),
           "date": records._now(), "what": ("exact frictionless contact over the top face: u_z prescribed on it, "
                                             "u_x, u_y free" if p["case"] == "plate" else "the same problem"),
           "method": richardson.__doc__.split("\n\n")[0].replace("\n", " ")}
    if p["case"] == "plate":
        ref["all_top_nodes_in_contact"] = all((r["min_top_nodal_force"] or 0) > 0 for r in rows)
    if not a.smoke:
        cache = json.loads(REFERENCE_FILE.read_text()) if REFERENCE_FILE.exists() else {}
        cache[key] = ref
        REFERENCE_FILE.write_text(json.dumps(cache, indent=1, sort_keys=True) + "\n")
    return {**ref, "cached": False}


def run_version() -> str | None:
    return records._version("felupe")


# ----------------------------------------------------------------------------- equal error
def errors_of(r: dict, p: dict, ref: dict) -> tuple[float | None, float | None]:
    """(reaction error, probe error) of a result against the reference (relative)."""
    if "reaction" not in r:
        return None, None
    R = ref["reaction"]["value"]
    e_r = abs(r["reaction"] - R) / abs(R)
    comps = p["probe_components"]
    diff = math.sqrt(sum((r["probe_u"][c] - ref["probe"][str(c)]["value"]) ** 2 for c in comps))
    size = math.sqrt(sum(ref["probe"][str(c)]["value"] ** 2 for c in comps))
    return e_r, diff / size


def time_at_error(points, e):
    """FElupe's time to reach error ``e`` from its (error, time) points: the points that no
    cheaper one beats in error, joined log-log ("interpolated"). Past the cheapest point's
    error: that point's time ("coarsest": FElupe reaches a smaller error in it, so its time at
    ``e`` is at most this); below the smallest error reached: the finest point's time
    ("finest": FElupe needs more than this; no extrapolation). (time, how) or (None, None)."""
    pts = sorted((t, err) for err, t in points if err is not None and t is not None and err > 0 and t > 0)
    front = []
    for t, err in pts:
        if not front or err < front[-1][1]:
            front.append((t, err))
    if not front or e is None or e <= 0:
        return None, None
    if e >= front[0][1]:
        return front[0][0], "coarsest"
    if e < front[-1][1]:
        return front[-1][0], "finest"
    lx = [math.log(err) for _, err in front]
    ly = [math.log(t) for t, _ in front]
    x = math.log(e)
    i = next(k for k in range(len(front) - 1) if lx[k] >= x >= lx[k + 1])
    s = (ly[i + 1] - ly[i]) / (lx[i + 1] - lx[i])
    return math.exp(ly[i] + s * (x - lx[i])), "interpolated"


def median_of(stats_list):
    vals = [s["median"] for s in stats_list if s and s.get("median") is not None]
    return statistics.median(vals) if vals else None


# ----------------------------------------------------------------------------- the bench
def series_name(code: str, p: dict, integration: str = "gauss") -> str:
    return f"jaxrkpm-{integration}" if code == "jaxrkpm" else f"felupe-{family(p)}"


def run_case(case: str, a, log) -> tuple[dict, dict, list]:
    p = problem(case, a)
    levels = SMOKE_REF_M if a.smoke else a.ref_m
    ref = reference(p, a, levels, log)
    ns = a.n or (SMOKE["n"] if a.smoke else (QUICK if a.quick else SIZES)[case]["n"])
    ms = a.m or (SMOKE["m"] if a.smoke else (QUICK if a.quick else SIZES)[case]["m"])
    jobs_j = [("jaxrkpm", integ, n) for integ in a.integration for n in ns]
    jobs_f = [("felupe", None, m) for m in ms]
    order = [job for pair in zip(jobs_j + [None] * len(jobs_f), jobs_f + [None] * len(jobs_j)) for job in pair if job]
    runs = {}
    for rnd in range(a.rounds):
        for code, integ, size in order:
            t0 = time.perf_counter()
            r = run_worker(code, p, size, a, repeats=a.repeats, integration=integ or "gauss")
            r["load_average"] = os.getloadavg()
            r["round"] = rnd
            key = (series_name(code, p, integ or "gauss"), size)
            runs.setdefault(key, []).append(r)
            log(f"{case} {key[0]} {'n' if code == 'jaxrkpm' else 'm'}={size} round {rnd}: "
                + (r["error"] if "error" in r else
                   f"warm {r['warm_s']['median']} s, cold {r['cold_s']:.3g} s, reaction {r['reaction']:.7g}, "
                   f"Newton {r['newton_iterations']} in {r['load_steps']} steps")
                + f" ({time.perf_counter() - t0:.0f} s)")
    rows = {}
    for (series, size), rs in runs.items():
        ok = [r for r in rs if "error" not in r]
        first = ok[0] if ok else rs[0]
        row = {"case": case, "series": series, "size": size, "particles_or_elements": size ** 3,
               "dof": first.get("dof"), "load_steps": first.get("load_steps"),
               "newton_iterations": first.get("newton_iterations"),
               "warm_s": median_of([r.get("warm_s") for r in ok]),
               "cold_s": statistics.median([r["cold_s"] for r in ok]) if ok else None,
               "import_s": statistics.median([r["import_s"] for r in ok]) if ok else None,
               "build_s": statistics.median([r["build_s"] for r in ok]) if ok else None,
               "first_solve_s": statistics.median([r["first_solve_s"] for r in ok]) if ok else None,
               "compile_s": (statistics.median([r["first_solve_compile_s"] + r["build_compile_s"] for r in ok])
                             if ok and "first_solve_compile_s" in first else None),
               "first_post_s": statistics.median([r["first_post_s"] for r in ok]) if ok else None,
               "cold_to_answer_s": statistics.median([r["cold_s"] + r["first_post_s"] for r in ok]) if ok else None,
               "reaction": first.get("reaction"), "relative_residual": first.get("relative_residual"),
               "error": None if ok else first.get("error")}
        row["reaction_error"], row["probe_error"] = errors_of(first, p, ref) if ok else (None, None)
        # an error within the reference's own uncertainty is not resolved by this reference
        row["reaction_error_resolved"] = (None if row["reaction_error"] is None else
                                          row["reaction_error"] > 2 * ref["reaction"]["error_estimate"]
                                          / abs(ref["reaction"]["value"]))
        rows[f"{case} {series} {'n' if series.startswith('jaxrkpm') else 'm'}={size}"] = row
    fel = [r for r in rows.values() if r["series"].startswith("felupe")]
    fel_newton = [r["newton_iterations"] for r in fel if r["newton_iterations"] is not None]
    ratios = {}
    for name, row in rows.items():
        if not row["series"].startswith("jaxrkpm"):
            continue
        for metric in ("reaction", "probe"):
            for kind in ("warm", "cold"):
                t, how = time_at_error([(r[f"{metric}_error"], r[f"{kind}_s"]) for r in fel], row[f"{metric}_error"])
                ratio = row[f"{kind}_s"] / t if t and row[f"{kind}_s"] else None
                row[f"felupe_{kind}_s_at_{metric}_error"] = t
                row[f"{kind}_ratio_at_{metric}_error"] = ratio
                row[f"felupe_{kind}_at_{metric}_error_from"] = how   # interpolated, coarsest or finest
                bound = {"coarsest": " (FElupe's coarsest is more accurate: a lower bound)",
                         "finest": " (below FElupe's finest error: an upper bound)"}.get(how, "")
                ratios[f"{name}: {kind} time / FElupe's at equal {metric} error{bound}"] = ratio
        if fel_newton and row["newton_iterations"] is not None:
            row["newton_over_felupe_median"] = row["newton_iterations"] / statistics.median(fel_newton)
            ratios[f"{name}: Newton iterations / FElupe's median"] = row["newton_over_felupe_median"]
    ref_summary = {"family": ref["family"], "levels": " ".join(map(str, ref["levels"])),
                   "reaction": ref["reaction"]["value"], "reaction_error_estimate": ref["reaction"]["error_estimate"],
                   "reaction_relative_error_estimate":
                       ref["reaction"]["error_estimate"] / abs(ref["reaction"]["value"]),
                   "reaction_order": ref["reaction"]["order"],
                   **{f"probe_u{'xyz'[int(c)]}": v["value"] for c, v in ref["probe"].items()},
                   **{f"probe_u{'xyz'[int(c)]}_error_estimate": v["error_estimate"] for c, v in ref["probe"].items()}}
    if "all_top_nodes_in_contact" in ref:
        ref_summary["all_top_nodes_in_contact"] = ref["all_top_nodes_in_contact"]
    detail = {"case": case, "problem": p, "reference": ref,
              "runs": [{"series": s, "size": size, **r} for (s, size), rs in runs.items() for r in rs]}
    return {"rows": rows, "reference": ref_summary}, ratios, [detail]


def print_table(rows: dict) -> None:
    cols = ("dof", "load_steps", "newton_iterations", "warm_s", "cold_s", "compile_s", "reaction_error",
            "probe_error", "warm_ratio_at_reaction_error", "cold_ratio_at_reaction_error")
    print("case/series/size".ljust(40) + "".join(c[:14].rjust(15) for c in cols))
    for name, r in rows.items():
        cells = []
        for c in cols:
            v = r.get(c)
            cells.append(("-" if v is None else f"{v:.4g}" if isinstance(v, float) else str(v)).rjust(15))
        print(name.ljust(40) + "".join(cells) + (f"  {r['error']}" if r.get("error") else ""))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", nargs="*", default=list(CASES), choices=CASES)
    ap.add_argument("--n", type=int, nargs="*", help="jaxrkpm particles a side (default: per case)")
    ap.add_argument("--m", type=int, nargs="*", help="FElupe elements a side (default: per case)")
    ap.add_argument("--repeats", type=int, default=3, help="warm solves per process (after the first)")
    ap.add_argument("--rounds", type=int, default=1, help="times the whole interleaved sequence runs")
    ap.add_argument("--steps", type=int, default=5, help="load steps (both codes)")
    ap.add_argument("--integration", nargs="*", default=["gauss"], choices=["gauss", "scni", "mscni"],
                    help="jaxrkpm's integration (each a series of its own)")
    ap.add_argument("--solver", default="auto", help="jaxrkpm's Model(solver=...)")
    ap.add_argument("--mu", type=float, default=1.0)
    ap.add_argument("--nu", type=float, default=0.3, help="Poisson's ratio of the cube and the plate")
    ap.add_argument("--nu-incompressible", type=float, default=0.499)
    ap.add_argument("--push", type=float, default=0.2, help="the cube's push (fraction of its edge)")
    ap.add_argument("--compression", type=float, default=0.1, help="the plate's indentation")
    ap.add_argument("--gap", type=float, default=1e-3, help="jaxrkpm's contact barrier range")
    ap.add_argument("--penalty", type=float, default=1000.0,
                    help="FElupe ContactRigidPlane's multiplier (times its mean-stiffness base)")
    ap.add_argument("--mixed", default="hex20-P0", choices=["hex20-P0", "hex27-P0", "hex27-dQ1"],
                    help="FElupe's u-p-Jbar family of the incompressible case")
    ap.add_argument("--tol", type=float, default=None, help="FElupe's Newton tolerance (default: jaxrkpm's rtol)")
    ap.add_argument("--ref-m", type=int, nargs="*", default=REF_M, help="the references' meshes (each twice the last)")
    ap.add_argument("--ref-steps", type=int, default=None, help="the references' load steps (default --steps)")
    ap.add_argument("--recompute-reference", action="store_true")
    ap.add_argument("--reference-only", action="store_true", help="compute (or read) the references and stop")
    ap.add_argument("--quick", action="store_true", help="fewer sizes, 2 repeats")
    ap.add_argument("--single-thread", action="store_true", help="both codes on one thread (a shared machine)")
    ap.add_argument("--timeout", type=float, default=3600.0, help="seconds per subprocess")
    ap.add_argument("--worker", choices=["jaxrkpm", "felupe"], help=argparse.SUPPRESS)
    ap.add_argument("--problem", help=argparse.SUPPRESS)
    ap.add_argument("--size", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--variant", default="timed", help=argparse.SUPPRESS)
    records.add_arguments(ap)
    a = ap.parse_args(argv)
    if a.worker:
        p = json.loads(a.problem)
        if a.worker == "jaxrkpm":
            out = jaxrkpm_worker(p, a.size, a.repeats, a.integration[0], a.solver)
        else:
            out = felupe_worker(p, a.size, a.repeats, a.tol, a.variant)
        print(json.dumps(out, default=records._plain))
        return
    if a.smoke:
        a.repeats = min(a.repeats, 1)
    elif a.quick:
        a.repeats = min(a.repeats, 2)
    if a.single_thread:
        for k in THREAD_VARS:
            os.environ[k] = "1"
        flags = os.environ.get("XLA_FLAGS", "")
        os.environ["XLA_FLAGS"] = f"{flags} --xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1".strip()
    if a.tol is None:
        a.tol = default_tol()
    log = lambda s: print(s, file=sys.stderr, flush=True)   # noqa: E731
    if a.reference_only:
        for case in a.cases:
            ref = reference(problem(case, a), a, SMOKE_REF_M if a.smoke else a.ref_m, log)
            print(json.dumps({case: {k: ref[k] for k in ("reaction", "probe", "cached")}}, default=records._plain))
        return
    run = records.start("bench_peer", a, variant="quick" if a.quick else "")
    figures = {"settings": {"steps": a.steps, "tol": a.tol, "repeats": a.repeats, "rounds": a.rounds,
                            "mu": a.mu, "nu": a.nu, "nu_incompressible": a.nu_incompressible, "push": a.push,
                            "compression": a.compression, "gap": a.gap, "penalty": a.penalty, "mixed": a.mixed,
                            "single_thread": a.single_thread, "KMP_BLOCKTIME": os.environ.get("KMP_BLOCKTIME", "0")},
               "summary": {}, "references": {}, "details": []}
    ratios = {}
    for case in a.cases:
        f, r, detail = run_case(case, a, log)
        figures["summary"].update(f["rows"])
        figures["references"][case] = f["reference"]
        figures["details"] += detail
        ratios.update(r)
        records.finish(run, figures, ratios, partial=True)
    records.finish(run, figures, ratios)
    print_table(figures["summary"])
    # the last line: the figures and ratios as one JSON object (for scripts and the test)
    print(json.dumps({"figures": {k: v for k, v in figures.items() if k != "details"}, "ratios": ratios},
                     default=records._plain))


if __name__ == "__main__":
    main(sys.argv[1:])
