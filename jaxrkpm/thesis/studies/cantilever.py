"""Timoshenko cantilever (Timoshenko & Goodier; plane stress, small load, SVK) under
refinement: displacement error against the analytic solution and its convergence rate.
Writes summary.json and convergence.png (error against spacing, with an h^2 guide)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

import jaxrkpm as jr
from jaxrkpm.thesis.studies import interface
from jaxrkpm.thesis.studies.command import Command, lazy
from jaxrkpm.thesis.studies.experiments import AGREES, DIFFERS, Entry

plot = lazy("jaxrkpm.io.plot")

LEVELS_MAX = 6                  # refinements: h = 1/4 .. 1/128 (257 x 129 particles)


def exact(X, L, D, P, E, nu):
    """Analytic displacement (u_x, u_y) of the cantilever fixed at x=0, end load P at x=L."""
    x, y = X[:, 0], X[:, 1] - D / 2
    I = D**3 / 12
    ux = -P * y / (6 * E * I) * ((6 * L - 3 * x) * x + (2 + nu) * (y**2 - D**2 / 4))
    uy = P / (6 * E * I) * (3 * nu * y**2 * (L - x) + (4 + 5 * nu) * D**2 * x / 4 + (3 * L - x) * x**2)
    return np.stack([ux, uy], 1)


def solve(h, L=2.0, D=1.0, P=1e-3, E=1e3, nu=0.3, order=2):
    """Relative L2 displacement error at the particles for spacing h."""
    nx, ny = int(round(L / h)) + 1, int(round(D / h)) + 1
    body = jr.Body.grid((nx, ny), spacing=h)
    left = body.select(lambda X: X[:, 0] < 1e-9)
    I = D**3 / 12

    def shear(X):  # parabolic end shear, per unit reference length
        y = X[:, 1] - D / 2
        return np.stack([np.zeros(len(X)), P / (2 * I) * (D**2 / 4 - y**2)], 1)

    model = jr.Model(body, jr.SaintVenantKirchhoff.plane_stress(E, nu), essential={"left": left},
                     tractions=[(lambda X: X[:, 0] > L - 1e-9, shear)], order=order)
    sol = model.solve({"left": exact(body.X[left], L, D, P, E, nu)})
    u = np.asarray(model.particle_displacements(sol))
    ue = exact(body.X, L, D, P, E, nu)
    return float(np.linalg.norm(u - ue) / np.linalg.norm(ue)), model, sol


def convergence(hs=(1 / 4, 1 / 8, 1 / 16)):
    errs = [solve(h)[0] for h in interface.progress(hs, desc="cantilever", unit="level")]
    rates = [float(np.log(errs[i] / errs[i + 1]) / np.log(hs[i] / hs[i + 1])) for i in range(len(hs) - 1)]
    return {"h": list(hs), "relative_l2_error": errs, "rates": rates}


def figure(out: Path, s: dict):
    """convergence.png: the error against the spacing on log axes, with an h^2 guide."""
    import matplotlib.ticker
    fig, ax = plot.plt.subplots(figsize=(5, 4))
    ax.loglog(s["h"], s["relative_l2_error"], "o-", label="RKPM (Gauss, SVK)")
    h0, e0 = s["h"][0], s["relative_l2_error"][0]
    ax.loglog(s["h"], [e0 * (h / h0) ** 2 for h in s["h"]], "k--", lw=0.8, label=r"$\propto h^2$")
    ax.set_xticks(s["h"], [f"1/{round(1 / h)}" for h in s["h"]])   # readable ticks on the log axis
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.set_xlabel("particle spacing h (beam depth = 1)")
    ax.set_ylabel("relative L2 displacement error")
    ax.set_title("Timoshenko cantilever")
    ax.legend()
    plot.save(fig, out / "convergence.png")


def result(s: dict) -> tuple[bool, str]:
    """(second-order convergence, the result in words)."""
    words = ("Timoshenko cantilever: relative L2 errors " + ", ".join(f"{e:.2e}" for e in s["relative_l2_error"])
             + "; rates " + ", ".join(f"{r:.2f}" for r in s["rates"]) + " (expected >= 2, linear basis)")
    return min(s["rates"]) > 1.8, words


def parser() -> interface.Parser:
    p = interface.parser("cantilever", __doc__, "results/cantilever")
    p.add_argument("--levels", type=interface.number(int, 2, LEVELS_MAX), default=3,
                   help=f"refinement levels, h = 1/4, 1/8, ...; 2..{LEVELS_MAX} (1/128: 257 x 129 particles)")
    return p


def main(argv=None):
    a = parser().parse_args(argv)
    results = interface.results("cantilever", a)
    with results as out:
        s = convergence(tuple(0.25 / 2**k for k in range(a.levels)))
        (out / "summary.json").write_text(json.dumps(s, indent=2))
        figure(out, s)
        results.finish(s, *result(s), a.json)
    return s


# ------------------------------------------------------------------ the experiment of reproduce
def _run(out: Path, quick: bool) -> tuple[str, list]:
    return "cantilever", ["--levels", "2" if quick else "3", "--out", str(out)]


def _ours(s):
    return ("relative L2 errors " + ", ".join(f"{e:.2e}" for e in s["relative_l2_error"])
            + "; rates " + ", ".join(f"{r:.2f}" for r in s["rates"]))


def _judge(s):
    """Not in the thesis: checked against the analytic solution's second-order rate."""
    return (AGREES, "analytic") if min(s["rates"]) > 1.8 else (DIFFERS, "rate")


def entries() -> list:
    return [Entry("cantilever", "- (verification, not in the thesis)", "-", _run, _ours, quick=True, judge=_judge,
                  note="Timoshenko beam, plane stress SVK, small load: the error must fall at least as h^2 "
                       "(linear RK basis)")]


COMMAND = Command("cantilever", "Timoshenko cantilever: error and convergence rate (verification)",
                  parser, main, result, order=60, reproduce=entries)
