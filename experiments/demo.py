"""Demo: a 9x9 Fung block (thesis Table 5.2 tensors) compressed 30% by its right edge,
left edge immobile. Writes summary.json and a figure of the deformed particles."""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import jax.numpy as jnp
import numpy as np

import jaxrkpm as jr
from jaxrkpm import plot


def run(out: Path, n: int = 9, compression: float = 0.3, steps: int = 10, alpha=1.0, beta=1.0):
    out.mkdir(parents=True, exist_ok=True)
    h = 1.0 / (n - 1)
    body = jr.Body.grid((n, n), spacing=h)
    wall = body.select(lambda X: X[:, 0] < 1e-9)
    right = body.select(lambda X: X[:, 0] > 1 - 1e-9)
    model = jr.Model(body, jr.Fung(alpha=alpha, beta=beta), essential={"wall": wall, "right": right})
    t0 = time.perf_counter()
    sol = model.solve({"right": jnp.array([-compression, 0.0])}, steps=steps)
    sol.u.block_until_ready()
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    sol = model.solve({"right": jnp.array([-compression, 0.0])}, steps=steps)
    sol.u.block_until_ready()
    warm = time.perf_counter() - t0
    u = np.asarray(model.particle_displacements(sol))
    force = np.asarray(model.reaction(sol, "right"))
    summary = {
        "particles": [n, n], "material": model.material.describe(), "integration": "gauss",
        "compression": compression, "status": jr.Status(int(sol.status)).name,
        "message": sol.message, "load_steps": int(sol.steps), "newton_iterations": int(sol.iterations),
        "max_displacement": float(np.linalg.norm(u, axis=1).max()),
        "reaction_right": force.tolist(),
        "centre_displacement": np.asarray(model.displacement(sol, [[0.5, 0.5]]))[0].tolist(),
        "first_solve_s": first, "warm_solve_s": warm,
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    fig, ax = plot.plt.subplots(figsize=(6, 5))
    sc = plot.deformed_particles(ax, body.X, u, title=f"Fung 9x9, {100 * compression:.0f}% compression "
                                 f"(alpha={alpha}, beta={beta})")
    fig.colorbar(sc, ax=ax, label="|u|")
    ax.legend(loc="upper right", fontsize=8)
    plot.save(fig, out / "deformed.png")
    return summary


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--out", default="results/demo")
    a = p.parse_args(argv)
    s = run(Path(a.out))
    print(json.dumps(s, indent=2))


if __name__ == "__main__":
    main()
