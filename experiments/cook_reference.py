"""Converged mixed-FEM reference values, computed with FElupe (an independent FEM code), for
two nearly-incompressible benchmarks with exactly jaxrkpm's ``NeoHookean(lam, mu)`` energy

    W = mu/2 (tr C - 3) - mu ln J + lam/2 (ln J)^2     (2D: plane strain, C33 = 1),
    mu = 80.194,  lam = 2 mu nu / (1 - 2 nu).

Why: jaxrkpm's own locking checks need reference displacements that no RKPM choice
(integration, stabilisation) influenced.

Formulation: FElupe's three-field Hu-Washizu ``NearlyIncompressible`` (u, p, Jbar),

    Pi_int = int psi_hat(F) + U(Jbar) + p (J - Jbar) dV,
    psi_hat = mu/2 tr C - mu ln J        (FElupe's NeoHookeCompressible(mu), lmbda=None)
    U       = lam/2 (ln Jbar)^2          (passed as dU/dJ, d2U/dJ2),

so psi_hat(F) + U(J) = W(F) + const exactly; at the solution of the p and Jbar equations
(Jbar = J, p = U'(J)) its displacement stress equals dW/dF, checked below (to round-off) by a
complex-step derivative of W itself at random F (3D and plane strain).

Problem "cook" (2D plane strain): Cook's membrane, vertices (0,0), (48,44), (48,60), (0,44);
x = 0 clamped; dead vertical traction 5/16 per unit length on x = 48 (total shear 5).
Output: u_y at (48, 60). Two element families on structured N x N meshes of the mapped
quadrilateral, N = 8, 16, 32, 64:
  * tri6-TH : quadratic triangles, continuous linear p and Jbar (Taylor-Hood),
  * quad8-P0: serendipity quadrilaterals, element-constant p and Jbar.
Problem "block" (3D): cantilever [0,4]x[0,1]x[0,1], x = 0 clamped, dead traction (0,0,0.5)
per unit area on x = 4. Output: u_z at (4,0.5,1), (4,0.5,0.5), (4,1,1). Family hex20-P0
(serendipity hexahedra, element-constant p and Jbar) on 4n x n x n meshes, n = 2, 4, 8
(n = 8: 34k unknowns, minutes per solve on a shared 2-core machine; n = 16 is out of reach).

Extrapolation (2D): both families see the same corner singularity (at (0,44)), so their errors
share the leading order p; on the three finest meshes the six values fit exactly
V + C_f h^p + D_f h^2 (f = tri6-TH, quad8-P0: six unknowns V, p, C_f, D_f). The families
bracket the limit (triangles from below, quadrilaterals from above), p comes out ~1.03. The
error estimate is the largest difference to the same fit with h^(p+1) or h^3 as the second
term and to the one-term common-order extrapolation V + C_f h^p of the finest pair; the JSON
also keeps each family's own Richardson value and the change of the fit from the coarser
triple (8-16-32), a pessimistic bound (the coarsest mesh is not yet asymptotic: p 1.2 there).
Validation: the two values known from finer meshes (COOK_KNOWN) lie within the estimates.

Extrapolation (3D): the cross-check family tet10-TH (quadratic tetrahedra, six per hexahedron,
continuous linear p and Jbar: ``--block-family tet10-TH``) on the same meshes brackets the
limit from below (hex20-P0 from above). With only n = 2, 4, 8 (and p ~ 2, where a second
h^2 term is degenerate) the value is the one-term common-order extrapolation of the finest
pair (n = 4-8); the error estimate is the largest of its change from the pair 2-4 and its
distances to the two families' own Richardson values (the observed order still drifts,
2.1 -> 1.9 at nu = 0.3, 1.9 -> 1.55 at nu = 0.499: the clamped edges are singular too). Without the cross-check: the
hex20-P0 Richardson value, error the size of its correction.

Newton (FElupe's newtonraphson, relative residual 1e-8, i.e. the update is converged to
round-off) with load steps; a failed step sequence is retried with twice the steps.

Run:  python experiments/cook_reference.py            (all; writes experiments/cook_reference.json)
      python experiments/cook_reference.py --quick    (coarse smoke run; prints, writes --out if given)
      python experiments/cook_reference.py --problem cook|block   (one problem; merges into the JSON)
      python experiments/cook_reference.py --problem block --block-family tet10-TH --nus 0.3   (cross-check only)
      python experiments/cook_reference.py --resummarise     (extrapolations from the stored values)
Needs the optional extra ``reference`` (felupe). The run times are taken on a shared machine:
they say what a solve costs, roughly, not a benchmark.
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import sys
import time

import numpy as np

try:
    import felupe as fem
except ImportError as e:  # pragma: no cover
    raise SystemExit("experiments/cook_reference.py needs FElupe: pip install 'jaxrkpm[reference]' "
                     "(or pip install felupe)") from e

MU = 80.194
NUS = (0.3, 0.45, 0.49, 0.499)
HERE = os.path.dirname(os.path.abspath(__file__))
DEFAULT_OUT = os.path.join(HERE, "cook_reference.json")

# values computed the same way elsewhere (quadratic triangles to 256 a side, serendipity
# quads to 128, Richardson, agreeing to 8e-5): the validation targets of this script
COOK_KNOWN = {0.3: 0.54654, 0.499: 0.40155}


def lam_of(nu: float) -> float:
    return 2.0 * MU * nu / (1.0 - 2.0 * nu)


# ----------------------------------------------------------------------------- material

def W_numpy(F, lam, mu=MU):
    """jaxrkpm's NeoHookean energy of a 3x3 F (complex-safe, for complex-step derivatives)."""
    C = F.T @ F
    lnJ = np.log(np.linalg.det(F))
    return 0.5 * mu * (np.trace(C) - 3.0) - mu * lnJ + 0.5 * lam * lnJ**2


def dW_complex_step(F, lam, h=1e-30):
    P = np.zeros((3, 3))
    for i in range(3):
        for j in range(3):
            Fc = F.astype(complex)
            Fc[i, j] += 1j * h
            P[i, j] = W_numpy(Fc, lam).imag / h
    return P


def umat_of(nu: float):
    """The three-field material: psi_hat(F) + U(Jbar) + p (J - Jbar) with psi_hat + U = W."""
    lam = lam_of(nu)
    return fem.NearlyIncompressible(
        fem.NeoHookeCompressible(mu=MU),  # mu/2 tr C - mu ln J  (no lmbda: no volumetric term)
        bulk=lam,
        dUdJ=lambda J, K: K * np.log(J) / J,  # U = K/2 (ln J)^2
        d2UdJdJ=lambda J, K: K * (1.0 - np.log(J)) / J**2,
    )


def energy_check(nsamples: int = 5, seed: int = 0) -> dict:
    """At random F (3D and plane strain F33 = 1): the split energy equals W, and the
    three-field displacement stress at Jbar = J, p = U'(J) equals dW/dF (complex step)."""
    rng = np.random.default_rng(seed)
    worst_stress, worst_energy, worst_jax = 0.0, 0.0, None
    for nu in NUS:
        lam = lam_of(nu)
        umat = umat_of(nu)
        for k in range(nsamples):
            F = np.eye(3) + 0.3 * rng.standard_normal((3, 3))
            if k % 2:  # plane strain
                F[2, :2] = F[:2, 2] = 0.0
                F[2, 2] = 1.0
            if np.linalg.det(F) <= 0.2:
                F = np.eye(3) + 0.1 * rng.standard_normal((3, 3))
            J = np.linalg.det(F)
            P_ref = dW_complex_step(F, lam)
            Fq = F.reshape(3, 3, 1, 1)
            Jq = np.full((1, 1), J)
            pq = lam * np.log(Jq) / Jq  # p = U'(J)
            g = umat.gradient([Fq, pq, Jq, np.zeros((0, 1, 1))])
            P = g[0][..., 0, 0]
            scale = max(1.0, np.abs(P_ref).max())
            worst_stress = max(worst_stress, np.abs(P - P_ref).max() / scale,
                               abs(float(g[1][..., 0, 0])), abs(float(g[2][..., 0, 0])) / scale)
            psi_hat = fem.NeoHookeCompressible(mu=MU).function([Fq, None])[0][0, 0]
            W_split = psi_hat - 1.5 * MU + 0.5 * lam * np.log(J) ** 2
            worst_energy = max(worst_energy, abs(W_split - W_numpy(F, lam)) / max(1.0, abs(W_numpy(F, lam))))
    out = {"max_rel_stress_difference": worst_stress, "max_rel_energy_difference": worst_energy,
           "samples": nsamples * len(NUS)}
    try:  # the same energy as jaxrkpm's public NeoHookean (optional: only where jaxrkpm imports)
        import jax
        jax.config.update("jax_enable_x64", True)
        import jaxrkpm
        worst_jax = 0.0
        for nu in NUS:
            lam = lam_of(nu)
            mat = jaxrkpm.NeoHookean(lam, MU)
            for k in range(nsamples):
                F = np.eye(3) + 0.2 * rng.standard_normal((3, 3))
                if np.linalg.det(F) <= 0.2:
                    continue
                E = 0.5 * (F.T @ F - np.eye(3))
                worst_jax = max(worst_jax, abs(float(mat.W(E, mat.params)) - W_numpy(F, lam)))
                F2 = F.copy()
                F2[2, :2] = F2[:2, 2] = 0.0
                F2[2, 2] = 1.0
                if np.linalg.det(F2) > 0.2:
                    E2 = 0.5 * (F2[:2, :2].T @ F2[:2, :2] - np.eye(2))
                    worst_jax = max(worst_jax, abs(float(mat.W(E2, mat.params)) - W_numpy(F2, lam)))
        out["max_abs_difference_to_jaxrkpm_NeoHookean_W"] = worst_jax
    except Exception as e:  # noqa: BLE001 - jaxrkpm is optional here
        out["jaxrkpm_check"] = f"skipped ({type(e).__name__}: {e})"
    return out


# ----------------------------------------------------------------------------- solves

def _linear_solver():
    """PARDISO (pypardiso) where installed, for the 3D solves; else SciPy's SuperLU (the same
    numbers to round-off, only slower)."""
    try:
        import pypardiso
        return pypardiso.spsolve, "pypardiso " + getattr(pypardiso, "__version__", "")
    except ImportError:
        from scipy.sparse.linalg import spsolve
        return spsolve, "scipy.sparse.linalg.spsolve (SuperLU)"


SOLVER, SOLVER_NAME = _linear_solver()


def _solve(field, solid, load, vals, bounds, nsteps, maxsteps=16):
    """Newton with ``nsteps`` equal load steps; on failure restart with twice the steps."""
    from felupe.tools._newton import NewtonConvergenceError
    x0 = [f.values.copy() for f in field.fields]
    while True:
        try:
            ramp = {load: [s * vals for s in np.linspace(0.0, 1.0, nsteps + 1)[1:]]}
            step = fem.Step(items=[solid, load], ramp=ramp, boundaries=bounds)
            iters = [res.iterations for res in step.generate(x0=field, tol=1e-8, maxiter=30, verbose=0,
                                                         solver=SOLVER)]
            return nsteps, int(sum(iters))
        except (NewtonConvergenceError, FloatingPointError, np.linalg.LinAlgError, ValueError):
            if 2 * nsteps > maxsteps:
                raise
            for f, v in zip(field.fields, x0):
                f.values[:] = v
            nsteps *= 2


def cook_mesh(N: int, family: str):
    m = fem.Rectangle(a=(0.0, 0.0), b=(1.0, 1.0), n=(N + 1, N + 1))
    xi, eta = m.points[:, 0].copy(), m.points[:, 1].copy()
    # bilinear map of the unit square: grid lines stay straight, so the quadratic nodes
    # added afterwards are the geometric mid-points of straight edges
    m.points[:, 0] = 48.0 * xi
    m.points[:, 1] = 44.0 * xi * (1.0 - eta) + (44.0 + 16.0 * xi) * eta
    if family == "tri6-TH":
        m = m.triangulate().convert(order=2)
        return m, fem.RegionQuadraticTriangle(m)
    if family == "quad8-P0":
        m = m.convert(order=2)
        return m, fem.RegionQuadraticQuad(m)
    raise ValueError(family)


def solve_cook(N: int, nu: float, family: str, nsteps: int = 1) -> dict:
    m, region = cook_mesh(N, family)
    field = fem.FieldsMixed(region, n=3, planestrain=True)
    solid = fem.SolidBody(umat_of(nu), field)
    x = m.points
    bounds = {"clamped": fem.Boundary(field[0], mask=np.isclose(x[:, 0], 0.0))}
    # consistent nodal loads of a constant traction on the straight quadratic edges of x = 48
    right = np.where(np.isclose(x[:, 0], 48.0))[0]
    right = right[np.argsort(x[right, 1])]
    f = np.zeros(len(right))
    t = 5.0 / 16.0
    for k in range(0, len(right) - 1, 2):
        L = x[right[k + 2], 1] - x[right[k], 1]
        f[k:k + 3] += t * L * np.array([1.0 / 6.0, 2.0 / 3.0, 1.0 / 6.0])
    assert abs(f.sum() - 5.0) < 1e-12
    vals = np.zeros((len(right), 2))
    vals[:, 1] = f
    load = fem.PointLoad(field, right, vals)
    t0 = time.perf_counter()
    nsteps, iters = _solve(field, solid, load, vals, bounds, nsteps)
    dt = time.perf_counter() - t0
    c = np.where(np.isclose(x[:, 0], 48.0) & np.isclose(x[:, 1], 60.0))[0][0]
    return {"uy": float(field[0].values[c, 1]), "seconds": round(dt, 2), "load_steps": nsteps,
            "newton_iterations": iters,
            "dofs": int(sum(fi.values.size for fi in field.fields))}


BLOCK_FAMILIES = {
    "hex20-P0": "4n x n x n serendipity 20-node hexahedra, element-constant p and Jbar",
    "tet10-TH": "the same 4n x n x n grid, each hexahedron cut into 6 quadratic 10-node tetrahedra, "
                "continuous linear p and Jbar (Taylor-Hood); results under cross_check",
}
BLOCK_POINTS = {"(4,0.5,1)": (4.0, 0.5, 1.0), "(4,0.5,0.5)": (4.0, 0.5, 0.5), "(4,1,1)": (4.0, 1.0, 1.0)}


def solve_block(n: int, nu: float, family: str = "hex20-P0", nsteps: int = 1) -> dict:
    m = fem.Cube(a=(0.0, 0.0, 0.0), b=(4.0, 1.0, 1.0), n=(4 * n + 1, n + 1, n + 1))
    if family == "hex20-P0":
        m = m.convert(order=2)
        region = fem.RegionQuadraticHexahedron(m)
    elif family == "tet10-TH":  # cross-check: quadratic tetrahedra, continuous linear p and Jbar
        m = m.triangulate().convert(order=2)
        region = fem.RegionQuadraticTetra(m)
    else:
        raise ValueError(family)
    field = fem.FieldsMixed(region, n=3)
    solid = fem.SolidBody(umat_of(nu), field)
    x = m.points
    bounds = {"clamped": fem.Boundary(field[0], mask=np.isclose(x[:, 0], 0.0))}
    fz = np.zeros(len(x))
    if family == "hex20-P0":
        # consistent nodal loads f_a = int_{x=4} N_a t dA by FElupe's boundary region
        bnd = fem.RegionQuadraticHexahedronBoundary(m, mask=np.isclose(x[:, 0], 4.0))
        w = np.einsum("aqc,qc->ca", bnd.h, bnd.dV)
        np.add.at(fz, bnd.mesh.cells, 0.5 * w)
    else:
        # 6-node triangle faces on x = 4: a constant traction loads the corners with 0 and
        # the mid-edge nodes with A/3 each
        on = np.isclose(x[:, 0], 4.0)
        for cell in m.cells:
            if on[cell].sum() < 6:
                continue
            for face in ((0, 1, 2, 4, 5, 6), (0, 1, 3, 4, 8, 7), (1, 2, 3, 5, 9, 8), (2, 0, 3, 6, 7, 9)):
                nodes = cell[list(face)]
                if on[nodes].all():
                    a, b, c = x[nodes[:3]]
                    A = 0.5 * np.linalg.norm(np.cross(b - a, c - a))
                    fz[nodes[3:]] += 0.5 * A / 3.0
    assert abs(fz.sum() - 0.5) < 1e-12
    pts = np.where(fz != 0.0)[0]
    vals = np.zeros((len(pts), 3))
    vals[:, 2] = fz[pts]
    load = fem.PointLoad(field, pts, vals)
    t0 = time.perf_counter()
    nsteps, iters = _solve(field, solid, load, vals, bounds, nsteps)
    dt = time.perf_counter() - t0
    uz = {}
    for name, p in BLOCK_POINTS.items():
        c = np.where(np.all(np.isclose(x, p), axis=1))[0][0]
        uz[name] = float(field[0].values[c, 2])
    return {"uz": uz, "seconds": round(dt, 2), "load_steps": nsteps, "newton_iterations": iters,
            "dofs": int(sum(fi.values.size for fi in field.fields))}


# ----------------------------------------------------------------------------- Richardson

def richardson(v, ratio=2.0) -> dict:
    """Extrapolate the last three values of a sequence refined by ``ratio`` each time."""
    v = [float(a) for a in v]
    if len(v) < 3:
        return {"value": v[-1], "order": None, "error_estimate": abs(v[-1] - v[-2]) if len(v) > 1 else None}

    def ext3(a, b, c):
        d1, d2 = b - a, c - b
        if d1 == 0 or d2 == 0 or d2 / d1 <= 0 or abs(d2 / d1) >= 1:
            return c, None  # not in the asymptotic range: no extrapolation
        p = math.log(d1 / d2) / math.log(ratio)
        return c + d2 / (ratio**p - 1.0), p

    value, p = ext3(*v[-3:])
    if len(v) >= 4:
        prev, _ = ext3(*v[-4:-1])
        err = max(abs(value - prev), 0.0)
    else:
        err = abs(value - v[-1])
    if p is None:
        err = max(err, abs(v[-1] - v[-2]))
    return {"value": value, "order": p, "error_estimate": err}


def common_order(a2h, ah, b2h, bh) -> tuple[float, float] | None:
    """Two families (a, b) on meshes h and 2h, with errors C_a h^p and C_b h^p of one order p
    (the same corner singularity sets it for both): 4 equations for V, p, C_a, C_b. None
    where the families do not bracket V (same sign of error) or p is not positive."""
    den = a2h + bh - b2h - ah
    if den == 0:
        return None
    V = (a2h * bh - b2h * ah) / den
    ra, rb = (a2h - V) / (ah - V), (b2h - V) / (bh - V)
    if not (ra > 1 and rb > 1) or (ah - V) * (bh - V) >= 0:
        return None
    return V, math.log(ra) / math.log(2.0)


def two_term_fit(levels, a, b, q="2"):
    """Two families on the three finest meshes, each value = V + C_f h^p + D_f h^q with one
    leading order p for both (the corner singularity sets it) and a second term of order
    q (2, p+1 or 3): six equations, six unknowns. Returns (V, p) or None."""
    from scipy.optimize import least_squares
    h = 1.0 / np.asarray(levels[-3:], float)
    h = h / h[-1]
    ya, yb = np.asarray(a[-3:], float), np.asarray(b[-3:], float)
    scale = max(abs(ya[-1]), 1e-30)

    def res(x):
        V, p, ca, cb, da, db = x
        qq = {"2": 2.0, "3": 3.0, "p+1": p + 1.0}[q]
        return np.r_[V + ca * h**p + da * h**qq - ya, V + cb * h**p + db * h**qq - yb] / scale

    best = None
    for p0 in (0.8, 1.2, 1.6, 2.2):
        x0 = [0.5 * (ya[-1] + yb[-1]), p0, ya[-1] - yb[-1], yb[-1] - ya[-1], 0.0, 0.0]
        sol = least_squares(res, x0, xtol=1e-15, ftol=1e-15, gtol=1e-15)
        if sol.x[1] > 0 and np.abs(sol.fun).max() < 1e-10 and (best is None or abs(sol.x[1] - 1.2) < abs(best[1] - 1.2)):
            best = (float(sol.x[0]), float(sol.x[1]))
    return best


def summarise_two(levels, a, b) -> dict:
    """The value and its error estimate from two families' sequences ``a`` and ``b`` on the
    meshes ``levels`` (each twice as fine as the one before; see the module docstring): the
    common-order two-family extrapolation of the finest pair where the families bracket the
    limit on the two finest pairs; else the mean of the per-family Richardson values."""
    rich = [richardson(a), richardson(b)]
    pairs = [common_order(a[k], a[k + 1], b[k], b[k + 1]) for k in range(len(a) - 1)]
    out = {"common_order_extrapolation": [None if q is None else {"meshes": f"{levels[k]}-{levels[k + 1]}",
                                                                   "value": q[0], "order": q[1]}
                                          for k, q in enumerate(pairs)],
           "bracket": [min(a[-1], b[-1]), max(a[-1], b[-1])]}
    fits = {q: two_term_fit(levels, a, b, q) for q in ("2", "p+1", "3")} if len(a) >= 3 else {}
    out["two_term_fits_finest_three"] = {q: None if f is None else {"value": f[0], "order": f[1]}
                                         for q, f in fits.items()}
    out["richardson_per_family"] = rich
    if len(a) >= 4:
        coarser = two_term_fit(levels[:-1], a[:-1], b[:-1], "2")
        if coarser is not None and fits.get("2") is not None:
            out["two_term_fit_coarser_three"] = {"value": coarser[0], "order": coarser[1],
                                                 "change": fits["2"][0] - coarser[0]}
    if fits.get("2") is not None and pairs[-1] is not None:
        V = fits["2"][0]
        alts = [f[0] for f in fits.values() if f is not None] + [pairs[-1][0]]
        err = max(abs(v - V) for v in alts)
        out.update(method="two-term common-order fit V + C_f h^p + D_f h^2 of both families on the three "
                          "finest meshes; error: the largest difference to the same fit with h^(p+1) or "
                          "h^3 as the second term and to the one-term common-order extrapolation of the "
                          "finest pair", value=V, error_estimate=err)
    elif len(pairs) >= 2 and pairs[-1] is not None and pairs[-2] is not None:
        V = pairs[-1][0]
        err = max(abs(V - pairs[-2][0]), abs(V - rich[0]["value"]), abs(V - rich[1]["value"]))
        out.update(method="common-order extrapolation of the two finest meshes of both families; error: "
                          "max(its change from the next coarser pair, its distance to either family's own "
                          "Richardson value)", value=V, error_estimate=err)
    else:
        errs = [rich[0]["error_estimate"] or 0.0, rich[1]["error_estimate"] or 0.0]
        vals = [rich[0]["value"], rich[1]["value"]]
        out.update(method="mean of the families' Richardson values; error: max(their error estimates, "
                          "their difference)", value=float(np.mean(vals)),
                   error_estimate=float(max(errs + [abs(vals[0] - vals[1])])))
    return out


def summarise_cook(fams: dict) -> dict:
    (_, fa), (_, fb) = fams.items()
    assert [r["N"] for r in fa["levels"]] == [r["N"] for r in fb["levels"]]
    return summarise_two([r["N"] for r in fa["levels"]], [r["uy"] for r in fa["levels"]],
                         [r["uy"] for r in fb["levels"]])


# ----------------------------------------------------------------------------- drivers

def run_cook(levels, nus, families=("tri6-TH", "quad8-P0"), log=print) -> dict:
    out = {}
    for nu in nus:
        fams = {}
        for fam in families:
            rows = []
            for N in levels:
                r = solve_cook(N, nu, fam)
                log(f"cook nu={nu} {fam} N={N}: u_y={r['uy']:.7f} dofs={r['dofs']} "
                    f"steps={r['load_steps']} newton={r['newton_iterations']} {r['seconds']} s")
                rows.append({"N": N, **r})
            fams[fam] = {"meshes": [f"{r['N']}x{r['N']} " + fam for r in rows], "levels": rows,
                         "richardson": richardson([r["uy"] for r in rows])}
        out[str(nu)] = finish_cook(nu, fams, log)
    return out


def finish_cook(nu: float, fams: dict, log=print) -> dict:
    summ = summarise_cook(fams)
    value, err = summ["value"], summ["error_estimate"]
    res = {"uy_48_60": value, "error_estimate": err, "summary": summ, "families": fams}
    if nu in COOK_KNOWN:
        res["validation"] = {"known": COOK_KNOWN[nu], "difference": value - COOK_KNOWN[nu],
                             "relative_difference": (value - COOK_KNOWN[nu]) / COOK_KNOWN[nu]}
    log(f"cook nu={nu}: u_y(48,60) = {value:.6f} +- {err:.1e}"
        + (f"  (known {COOK_KNOWN[nu]}, rel. diff {(value - COOK_KNOWN[nu]) / COOK_KNOWN[nu]:+.1e})"
           if nu in COOK_KNOWN else "")
        + "  [per family Richardson: " + ", ".join(f"{k} {f['richardson']['value']:.6f} (p={f['richardson']['order'] or float('nan'):.2f})" for k, f in fams.items())
        + "; common order: " + ", ".join("-" if q is None else f"{q['meshes']}: {q['value']:.6f} (p={q['order']:.2f})"
                                         for q in summ["common_order_extrapolation"])
        + "; two-term fits: " + ", ".join(f"h^{q}: " + ("-" if f is None else f"{f['value']:.6f} (p={f['order']:.2f})")
                                          for q, f in summ.get("two_term_fits_finest_three", {}).items()) + "]")
    return res


def run_block(levels, nus, family="hex20-P0", log=print) -> dict:
    out = {}
    for nu in nus:
        rows = []
        for n in levels:
            r = solve_block(n, nu, family)
            log(f"block nu={nu} {family} n={n}: " + " ".join(f"{k}={v:.7f}" for k, v in r["uz"].items())
                + f" dofs={r['dofs']} steps={r['load_steps']} newton={r['newton_iterations']} {r['seconds']} s")
            rows.append({"n": n, **r})
        res = {}
        for name in BLOCK_POINTS:
            rich = richardson([r["uz"][name] for r in rows])
            res[name] = {"uz": rich["value"], "error_estimate": rich["error_estimate"], "order": rich["order"]}
            log(f"block nu={nu}: u_z{name} = {rich['value']:.6f} +- {rich['error_estimate'] or float('nan'):.1e} "
                f"(observed order {rich['order']})")
        out[str(nu)] = {"points": res, "family": family,
                        "meshes": [f"{4 * r['n']}x{r['n']}x{r['n']} " + family for r in rows],
                        "levels": rows}
    return out


def _table(record: dict) -> dict:
    """The values at a glance: [value, error estimate] per problem, nu (and point)."""
    out = {}
    if "cook" in record:
        out["cook u_y(48,60)"] = {nu: [r["uy_48_60"], r["error_estimate"]]
                                  for nu, r in record["cook"]["results"].items()}
    if "block" in record:
        out["block u_z"] = {nu: {k: [p["uz"], p["error_estimate"]] for k, p in r["points"].items()}
                            for nu, r in record["block"].get("results", {}).items()}
    return out


def resummarise(record: dict) -> None:
    """Recompute every extrapolation and error estimate from the stored mesh values."""
    for nu, res in record.get("cook", {}).get("results", {}).items():
        fams = res["families"]
        for f in fams.values():
            f["richardson"] = richardson([r["uy"] for r in f["levels"]])
        record["cook"]["results"][nu] = finish_cook(float(nu), fams)
    for nu, res in record.get("block", {}).get("results", {}).items():
        cc = record["block"].get("cross_check", {}).get("tet10-TH", {}).get(nu)
        for name, pt in res["points"].items():
            pt.clear()
            a = [r["uz"][name] for r in res["levels"]]
            rich = richardson(a)
            pt.update(uz=rich["value"], error_estimate=rich["error_estimate"], order=rich["order"],
                      method="hex20-P0 Richardson")
            if cc is not None and [r["n"] for r in cc["levels"]] == [r["n"] for r in res["levels"]]:
                b = [r["uz"][name] for r in cc["levels"]]
                summ = summarise_two([r["n"] for r in res["levels"]], a, b)
                last = summ["common_order_extrapolation"][-1]
                pt.update(uz=summ["value"], error_estimate=summ["error_estimate"], method=summ["method"],
                          order=None if last is None else last["order"],
                          hex20_P0_richardson=rich, tet10_TH_richardson=richardson(b), summary=summ)
            print(f"block nu={nu}: u_z{name} = {pt['uz']:.6f} +- {pt['error_estimate'] or float('nan'):.1e} "
                  f"({pt['method']})")
    record["values"] = _table(record)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="coarse smoke run (seconds); writes only with --out")
    ap.add_argument("--problem", choices=["cook", "block", "all"], default="all")
    ap.add_argument("--out", default=None, help=f"JSON to write/merge into (default {DEFAULT_OUT})")
    ap.add_argument("--block-family", choices=["hex20-P0", "tet10-TH"], default="hex20-P0",
                    help="tet10-TH: only the cross-check family (the full run does both)")
    ap.add_argument("--nus", type=float, nargs="*", default=None, help="(cross-check) Poisson's ratios")
    ap.add_argument("--levels", type=int, nargs="*", default=None, help="(cross-check) mesh levels n")
    ap.add_argument("--resummarise", action="store_true",
                    help="recompute the extrapolations and error estimates of the JSON from its stored "
                         "mesh values (no solves)")
    args = ap.parse_args(argv)
    out_path = args.out if (args.out or args.quick) else DEFAULT_OUT
    if args.resummarise:
        with open(out_path) as fh:
            record = json.load(fh)
        resummarise(record)
        with open(out_path, "w") as fh:
            json.dump(record, fh, indent=1)
        print("wrote", out_path)
        return

    if args.quick:
        cook_levels, cook_nus, block_levels, block_nus = (2, 4, 8), (0.3, 0.499), (2,), (0.499,)
    else:
        cook_levels, cook_nus = (8, 16, 32, 64), NUS
        block_levels, block_nus = (2, 4, 8), (0.3, 0.499, 0.45, 0.49)  # the two asked for first

    record = {}
    if out_path and os.path.exists(out_path):
        with open(out_path) as fh:
            record = json.load(fh)
    record.update({
        "what": "mixed-FEM (FElupe three-field u-p-Jbar) reference values for jaxrkpm's NeoHookean",
        "script": "experiments/cook_reference.py" + (" --quick" if args.quick else ""),
        "felupe_version": fem.__version__,
        "numpy_version": np.__version__,
        "python": sys.version.split()[0],
        "date": datetime.date.today().isoformat(),
        "material": {"energy": "W = mu/2 (tr C - 3) - mu ln J + lam/2 (ln J)^2 (2D: plane strain, C33 = 1)",
                     "mu": MU, "lam": "2 mu nu / (1 - 2 nu)",
                     "formulation": "felupe.NearlyIncompressible(NeoHookeCompressible(mu), bulk=lam, "
                                    "U = lam/2 (ln Jbar)^2): Pi = int psi_hat(F) + U(Jbar) + p (J - Jbar)"},
        "timing_note": "seconds measured on a shared 2-core machine beside other jobs: cost indications only",
    })
    t0 = time.perf_counter()
    record["energy_check"] = energy_check()
    print("energy check:", record["energy_check"], flush=True)
    log = lambda s: print(s, flush=True)
    if args.problem in ("cook", "all"):
        record["cook"] = {
            "problem": "Cook's membrane, plane strain: vertices (0,0),(48,44),(48,60),(0,44); x=0 clamped; "
                       "dead traction (0, 5/16) on x=48 (total 5); output u_y at (48,60)",
            "error_estimate_rule": "max(change of each family's Richardson value from meshes 8-16-32 to 16-32-64, "
                                   "difference between the two families' Richardson values); value = their mean",
            "results": run_cook(cook_levels, cook_nus, log=log)}
    record["linear_solver"] = SOLVER_NAME

    def write():
        if out_path:
            with open(out_path, "w") as fh:
                json.dump(record, fh, indent=1)
            print("wrote", out_path, flush=True)

    if args.problem in ("cook", "all"):
        write()
    if args.problem in ("block", "all") and args.block_family == "hex20-P0":
        record["block"] = {
            "problem": "cantilever block [0,4]x[0,1]x[0,1]; x=0 clamped; dead traction (0,0,0.5) on x=4 "
                       "(total 0.5); output u_z at (4,0.5,1), (4,0.5,0.5), (4,1,1)",
            "error_estimate_rule": "per point: points[...].method (module docstring of the script)",
            "families": BLOCK_FAMILIES,
            "results": {}, **{k: v for k, v in record.get("block", {}).items() if k == "cross_check"}}
        for nu in block_nus:  # written after each nu: a long run keeps what it finished
            record["block"]["results"].update(run_block(block_levels, (nu,), log=log))
            write()
    if args.problem in ("block", "all") and (args.block_family == "tet10-TH" or not args.quick):
        # the second family: a cross-check of the hex20-P0 values (the full run does both)
        cc = record.setdefault("block", {}).setdefault("cross_check", {}).setdefault("tet10-TH", {})
        for nu in args.nus or block_nus:
            cc.update(run_block(args.levels or block_levels, (nu,), family="tet10-TH", log=log))
            write()
    resummarise(record)
    print(f"total {time.perf_counter() - t0:.0f} s", flush=True)
    write()


if __name__ == "__main__":
    main()
