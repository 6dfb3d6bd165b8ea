"""Snap-through of a clamped shallow arch, followed through its limit point by arc-length
continuation (jaxrkpm.continuation), against displacement control of the crown.

The arch: a sinusoidal strip (span 1, thickness 0.05, rise 0.1 = 2 thicknesses), both end
sections clamped, Saint Venant-Kirchhoff in plane stress (E = 1, nu = 0.3), a structured
triangle mesh (mirror-symmetric about mid-span) as the body, Gauss integration on it. The load
is a concentrated downward force at the crown's mid-surface point, ``point_load``: the load
work-conjugate to the crown displacement u(X_c). The reference is the same discretisation with
the crown point prescribed instead (it is then one of the essential particles): under
displacement control the path passes the load maximum without arc length, the crown force is
the reaction (``Model.reaction``), and by symmetry (u_x(X_c) = 0, no horizontal reaction) both
problems have the same equilibria, so the largest reaction is the limit load of the load-driven
arch.

``python experiments/snap_through.py --out results/snap_through`` prints a JSON summary and
writes snap_through.png (load against crown deflection; shapes along the path) and
summary.json to --out.
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass
from pathlib import Path

import jax
import meshio
import numpy as np

import jaxrkpm as jr
from jaxrkpm import plot
from jaxrkpm.continuation import arc_length, point_load

MATERIAL = jr.SaintVenantKirchhoff.plane_stress(1.0, 0.3)
SUPPORT = 2.5          # kernel support in spacings: three particles through the thickness
LIFT = 4e-3            # upward body force (per unit area) of the load model: a load without a limit point


@dataclass(frozen=True)
class Arch:
    body: jr.Body
    ends: dict          # "left", "right": the particles of the clamped end sections
    crown: int          # index of the crown's mid-surface particle (the loaded point)

    @property
    def crown_point(self) -> np.ndarray:
        return self.body.X[self.crown]


def shallow_arch(n_along: int = 41, n_thick: int = 3, span: float = 1.0, thickness: float = 0.05,
                 rise: float = 0.1) -> Arch:
    """A sinusoidal arch y = rise sin(pi x / span), ``thickness`` measured normal to its
    centre line, as a structured triangle mesh body: n_along x n_thick particles (both odd,
    so that the crown is a particle), each quad split by the diagonal mirrored at mid-span
    (the discretisation is symmetric, so a symmetric load gives a symmetric path)."""
    if n_along % 2 == 0 or n_thick % 2 == 0 or n_along < 5 or n_thick < 3:
        raise ValueError(f"n_along >= 5 and n_thick >= 3 must be odd (a crown particle), got {n_along}, {n_thick}")
    s = np.linspace(0.0, span, n_along)
    slope = rise * np.pi / span * np.cos(np.pi * s / span)
    normal = np.stack([-slope, np.ones_like(s)], 1) / np.sqrt(1 + slope**2)[:, None]
    centre = np.stack([s, rise * np.sin(np.pi * s / span)], 1)
    t = np.linspace(-thickness / 2, thickness / 2, n_thick)
    X = (centre[:, None, :] + t[None, :, None] * normal[:, None, :]).reshape(-1, 2)
    idx = np.arange(n_along * n_thick).reshape(n_along, n_thick)
    a, b = idx[:-1, :-1], idx[1:, :-1]        # (n_along - 1, n_thick - 1) quad corners
    c, d = idx[1:, 1:], idx[:-1, 1:]
    left = (np.arange(n_along - 1) < (n_along - 1) // 2)[:, None]
    tri1 = np.where(left[..., None], np.stack([a, b, c], -1), np.stack([a, b, d], -1))
    tri2 = np.where(left[..., None], np.stack([a, c, d], -1), np.stack([b, c, d], -1))
    cells = np.concatenate([tri1.reshape(-1, 3), tri2.reshape(-1, 3)])
    body = jr.Body.from_mesh(meshio.Mesh(X, [("triangle", cells)]), dim=2)
    return Arch(body, {"left": idx[0], "right": idx[-1]}, int(idx[n_along // 2, n_thick // 2]))


def load_model(arch: Arch) -> jr.Model:
    """Ends clamped, the crown free; its own dead load is an upward body force ``LIFT`` (the
    snap-through is driven by ``point_load`` at the crown instead)."""
    return jr.Model(arch.body, MATERIAL, essential=arch.ends, support=SUPPORT, body_force=[0.0, LIFT])


def crown_model(arch: Arch) -> jr.Model:
    """The same discretisation with the crown point prescribed (displacement control)."""
    return jr.Model(arch.body, MATERIAL, essential={**arch.ends, "crown": [arch.crown]}, support=SUPPORT)


def crown_load(model: jr.Model, arch: Arch) -> np.ndarray:
    """A unit downward force at the crown point as nodal loads."""
    return point_load(model, [arch.crown_point], [0.0, -1.0])


def displacement_control(model: jr.Model, depth: float, n: int):
    """The crown pushed down to ``depth`` in n equal steps (each solve warm-started from the
    last): crown deflections (n+1,) and the downward crown force (n+1,) = -reaction_y."""
    v = np.linspace(0.0, depth, n + 1)
    reaction = jax.jit(lambda s: model.reaction(s, "crown"))   # compiled once, not traced per call
    sol, force = model.initial(), [0.0]
    for vk in v[1:]:
        sol = model.solve({"crown": [0.0, -vk]}, initial=sol)
        force.append(-float(reaction(sol)[1]))
    return v, np.asarray(force)


def first_maximum(x, y) -> float:
    """The first local maximum of y(x) (the limit point; past the snap the force rises
    again), between samples: the vertex of the parabola through the sample and its two
    neighbours."""
    peaks = np.flatnonzero((y[1:-1] > y[:-2]) & (y[1:-1] >= y[2:])) + 1
    if not len(peaks):
        raise ValueError("no local maximum inside the samples: sample further")
    k = int(peaks[0])
    c2, c1, c0 = np.polyfit(x[k - 1:k + 2] - x[k], y[k - 1:k + 2], 2)
    return float(c0 - c1 * c1 / (4 * c2))


def snap(arch: Arch, model: jr.Model, ds: float = 0.03, steps: int = 40):
    """The load-driven arch followed by arc length (cylindrical constraint, ds fixed)."""
    return arc_length(model, ds, steps=steps, ds_max=ds, load_pattern=crown_load(model, arch),
                      points=[arch.crown_point])


def figure(path: Path, arch: Arch, model: jr.Model, eq, v_ref, f_ref):
    fig, (ax, ax2) = plot.plt.subplots(1, 2, figsize=(11, 4.2))
    defl = -eq.displacement[:, 0, 1]
    ax.plot(v_ref, f_ref, "k-", lw=1, label="displacement control of the crown (reference)")
    stable = eq.negative == 0
    ax.plot(defl[stable], eq.load[stable], "o", ms=5, color="tab:blue", label="arc length: K_ff positive definite")
    ax.plot(defl[~stable], eq.load[~stable], "o", ms=5, color="tab:red", label="arc length: one negative eigenvalue")
    for F in eq.limit_loads():
        ax.axhline(F, color="0.6", ls="--", lw=0.8)
    ax.set_xlabel(f"crown deflection ({plot.UNITS})")
    ax.set_ylabel(f"crown force ({plot.UNITS}, per unit thickness)")
    ax.set_title("clamped shallow arch: snap-through")
    ax.legend(fontsize=8)
    picks = [0, *eq.limit_points.tolist(), len(eq) - 1]
    for k in picks:
        x = arch.body.X + np.asarray(model.particle_displacements(eq.solution(k)))
        ax2.plot(x[:, 0], x[:, 1], ".", ms=3, label=f"point {k}: force {eq.load[k]:.3g}")
    ax2.set_aspect("equal")
    ax2.set_xlabel(f"x ({plot.UNITS})")
    ax2.set_ylabel(f"y ({plot.UNITS})")
    ax2.set_title("shapes along the path (start, limit points, end)")
    ax2.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.45), ncol=2)
    plot.save(fig, path)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("results/snap_through"))
    ap.add_argument("--along", type=int, default=41, help="particles along the arch (odd)")
    ap.add_argument("--ds", type=float, default=0.03, help="arc length per step")
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--depth", type=float, default=0.16, help="crown deflection of the reference sweep")
    ap.add_argument("--ref-steps", type=int, default=40, help="steps of the reference sweep")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    arch = shallow_arch(args.along)
    model = load_model(arch)
    t = time.perf_counter()
    eq = snap(arch, model, args.ds, args.steps)
    t_arc = time.perf_counter() - t
    t = time.perf_counter()
    v_ref, f_ref = displacement_control(crown_model(arch), args.depth, args.ref_steps)
    t_ref = time.perf_counter() - t
    reference = first_maximum(v_ref, f_ref)
    limits = eq.limit_loads()
    summary = {
        "particles": arch.body.n, "status": str(eq.outcome), "message": eq.message,
        "points": len(eq), "limit_points": eq.limit_points.tolist(),
        "limit_loads": limits.tolist(), "largest_sampled_load": float(eq.load.max()),
        "reference_limit_load": reference,
        "relative_error": float(limits[0] / reference - 1) if len(limits) else None,
        "critical_points": eq.critical_points.tolist(), "negative_eigenvalues": eq.negative.tolist(),
        "arc_length_s": round(t_arc, 2), "reference_s": round(t_ref, 2),
    }
    figure(args.out / "snap_through.png", arch, model, eq, v_ref, f_ref)
    (args.out / "summary.json").write_text(json.dumps(summary, indent=2))
    print(json.dumps(summary))
    return summary


if __name__ == "__main__":
    main()
