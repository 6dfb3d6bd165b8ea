"""Post-buckling of a clamped strip against the elastica (issue 19).

Strip 1 x 0.05, 81 x 5 particles, neo-Hookean lam = mu = 1 (plane-strain modulus E' = 8/3),
both ends clamped, the right end pushed along the axis with no imperfection; the stable-branch
solve passes the bifurcation and follows the buckled branch. Reference: the clamped
extensible elastica (four quarter waves; m = k^2 of the pinned elastica of length L / 2):
P / P_E = (2 K(m) / pi)^2, bending end shortening L (2 - 2 E(m) / K(m)), axial shortening
P L / (E' h); P_E = 4 pi^2 E' I / L^2 (effective length L / 2, I = h^3 / 12).

    python -m experiments.elastica [--out results/elastica]   # prints the table, writes elastica.png
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from tests.problems import E_PLANE, EULER, H, L, elastica_force, path, strip_model










def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="results/elastica")
    a = p.parse_args(argv)
    from jaxrkpm.io import plot
    model = strip_model()
    rows = path(model)
    print(f"Euler load P_E = {EULER:.5e} (axial strain {100 * EULER / (E_PLANE * H):.3f}%)")
    for c, sol in rows:
        P = -float(model.reaction(sol, "right")[0])
        ref = elastica_force(c) if c * L > EULER / (E_PLANE * H) else E_PLANE * H * c
        crit = np.asarray(sol.critical.t_unstable)
        print(f"shortening {100 * c:5.1f}%: P / P_E = {P / EULER:.4f}, reference {ref / EULER:.4f}, "
              f"critical points passed in this solve: {int(sol.branch)} {crit[np.isfinite(crit)]}")
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    fig, (a1, a2) = plot.plt.subplots(2, 1, figsize=(8, 6), layout="constrained")
    X = model.body.X
    for c, sol in rows:
        x = X + np.asarray(model.particle_displacements(sol))
        a1.plot(x[:, 0], x[:, 1], ".", ms=2, label=f"{100 * c:.1f}%")
    a1.set_aspect("equal")
    a1.legend(fontsize=7, ncol=6)
    a1.set_title("buckled strip (end shortening in % of L)")
    cs = np.linspace(EULER / (E_PLANE * H) * 1.001, 0.1, 40)
    a2.plot(100 * cs, [elastica_force(c) / EULER for c in cs], "-", label="elastica (extensible)")
    a2.plot([100 * c for c, _ in rows], [-float(model.reaction(s, "right")[0]) / EULER for _, s in rows], "o",
            label="RKPM, stable branch")
    a2.set_xlabel("end shortening (% of L)")
    a2.set_ylabel("P / P_E")
    a2.legend()
    fig.savefig(out / "elastica.png", dpi=110)
    print(f"wrote {out / 'elastica.png'}")
    return rows


if __name__ == "__main__":
    main()
