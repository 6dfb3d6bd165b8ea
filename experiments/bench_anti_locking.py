"""Benchmark: the cost of the anti-locking (F-bar) formulation against plain Gauss integration
at the same resolution (``Model(anti_locking=True / False)``).

Cases: Cook's membrane (plane strain, neo-Hookean at nu = 0.499, one load step; spacing 2: 412
particles) and the n^3 neo-Hookean cube of ``bench_cube3d`` (left face immobile, right face
pushed 30% in 10 load steps; lam = mu: the cost, not the locking, is measured there). Per case,
in one process: build and compile both variants, then ``repeats`` interleaved rounds that time
one warm solve and one jitted assembly (residual + tangent) of each. Ratios are anti-locking
over plain. Prints JSON and writes a record (experiments/records.py)."""
from __future__ import annotations

import argparse
import json
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxrkpm as jr
from experiments import records

COOK = np.array([[0.0, 0.0], [48.0, 44.0], [48.0, 60.0], [0.0, 44.0]])


def cook(spacing: float, anti_locking: bool):
    body = jr.Body.polygon(COOK, spacing)
    mu, nu = 80.194, 0.499
    model = jr.Model(body, jr.NeoHookean(2 * mu * nu / (1 - 2 * nu), mu), anti_locking=anti_locking,
                     essential={"left": body.select(lambda X: X[:, 0] < 1e-9)},
                     tractions=[(lambda X: X[:, 0] > 48 - 1e-9, [0.0, 5.0 / 16.0])])
    return model, lambda: model.solve()


def cube(n: int, anti_locking: bool):
    body = jr.Body.grid((n, n, n), 1.0 / (n - 1))
    sets = {"wall": body.select(lambda X: X[:, 0] < 1e-9), "right": body.select(lambda X: X[:, 0] > 1 - 1e-9)}
    model = jr.Model(body, jr.NeoHookean(lam=1.0, mu=1.0), essential=sets, anti_locking=anti_locking)
    g = jnp.array([-0.3, 0.0, 0.0])
    return model, lambda: model.solve({"right": g}, steps=10)


class Case:
    """One model, compiled: ``time_once`` times one warm solve and one assembly."""

    def __init__(self, make, arg, anti_locking):
        t0 = time.perf_counter()
        self.model, self.solve = make(arg, anti_locking)
        self.build_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        self.sol = self.solve()
        self.first_s = time.perf_counter() - t0
        self.iters = int(self.sol.iterations)
        self.prob = self.model.problem()
        self.asm = jax.jit(lambda prob, u, g: (prob.residual(u, g), prob.tangent(u, g)))
        jax.block_until_ready(self.asm(self.prob, self.sol.u, self.sol.g))
        self.t_solve, self.t_asm = [], []

    def time_once(self):
        t0 = time.perf_counter()
        s = self.solve()
        s.u.block_until_ready()
        self.t_solve.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        jax.block_until_ready(self.asm(self.prob, self.sol.u, self.sol.g))
        self.t_asm.append(time.perf_counter() - t0)

    def result(self):
        strain = self.prob.term("strain")
        return {"particles": int(self.model.body.n), "integration_points": int(strain.w.shape[0]),
                "neighbours_K": int(strain.idx.shape[1]), "groups": list(map(int, strain.groups.shape)),
                "build_s": self.build_s, "first_solve_s_incl_compile": self.first_s,
                "newton_iterations": self.iters, "warm_solve_s": records.stats(self.t_solve),
                "assembly_s": records.stats(self.t_asm)}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--cook-spacing", type=float, default=2.0)
    p.add_argument("--cube", type=int, default=10)
    p.add_argument("--repeats", type=int, default=5)
    records.add_arguments(p)
    a = p.parse_args(argv)
    run = records.start("bench_anti_locking", a)
    out, ratios = {}, {}
    for label, make, arg in (("cook_2d", cook, a.cook_spacing), (f"cube_{a.cube}", cube, a.cube)):
        cases = {on: Case(make, arg, on) for on in (False, True)}
        for _ in range(a.repeats):
            for c in cases.values():
                c.time_once()
        out[label] = {("anti_locking" if on else "plain"): c.result() for on, c in cases.items()}
        med = lambda on, k: statistics.median(getattr(cases[on], k))
        ratios[label] = {"warm_solve": med(True, "t_solve") / med(False, "t_solve"),
                         "assembly": med(True, "t_asm") / med(False, "t_asm"),
                         "per_newton_iteration": (med(True, "t_solve") / cases[True].iters)
                         / (med(False, "t_solve") / cases[False].iters)}
    out["ratios_anti_locking_over_plain"] = ratios
    print(json.dumps(out, indent=2))
    records.finish(run, out, ratios)
    return out


if __name__ == "__main__":
    main()
