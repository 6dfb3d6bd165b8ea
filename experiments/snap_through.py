"""Snap-through of a clamped shallow arch, followed through its limit point by arc-length
continuation (jaxrkpm.arc_length), against displacement control of the crown.

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

``python -m experiments.snap_through --out results/snap_through`` prints a JSON summary and
writes snap_through.png (load against crown deflection; shapes along the path) and
summary.json to --out.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

import jaxrkpm as jr
from jaxrkpm.io import plot
from tests.problems import Arch, crown_model, displacement_control, first_maximum, load_model, shallow_arch, snap



















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
