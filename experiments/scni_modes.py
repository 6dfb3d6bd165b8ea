"""Eigen-analysis of the unconstrained tangent at rest (no essential sets) for Gauss, SCNI
and the sub-cell stabilised MSCNI: zero modes (only the rigid ones, 3 in 2D and 6 in 3D,
should appear) and low-energy modes, measured against an accurate reference stiffness
(Gauss, 4x4 points per cell) through the generalized problem K v = lam M v (consistent mass
M_IJ = int Psi_I Psi_J): for each mode v of a scheme, ratio = v.K_ref.v / v.K.v. Nodal
integration under-integrates oscillatory fields; a ratio >> 1 marks a spurious low-energy mode
(a ratio of infinity would be a spurious zero-energy mode). Prints JSON."""
from __future__ import annotations

import argparse
import json

import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg as sla

import jaxrkpm as jr
from jaxrkpm.discretise import quadrature as integ
from jaxrkpm.discretise import scni

BODIES = {
    "grid2d_9": lambda: jr.Body.grid((9, 9), 0.125),
    "polygon_0.1": lambda: jr.Body.polygon([[0.5, 0], [1, 0], [1, 1], [0, 1], [0, 0.5]], 0.1),
    "grid3d_5": lambda: jr.Body.grid((5, 5, 5), 0.25),
}


def stiffness(body, integration, support, order=2):
    model = jr.Model(body, jr.Fung(alpha=1.0, beta=1.0), integration=integration, essential={},
                     support=support, order=order)
    K = jax.jit(lambda prob, u, g: prob.tangent(u, g))(model.problem(), jnp.zeros((body.n, body.dim)),
                                                        jnp.zeros((0, body.dim)))
    return np.asarray(K)


def mass(body, a):
    pts, w = integ.gauss_points(body, 4)
    T = integ.table(body, pts, w, a)
    M = np.zeros((body.n, body.n))
    r = np.repeat(T.idx[:, :, None], T.idx.shape[1], 2)
    np.add.at(M, (r, np.swapaxes(r, 1, 2)), w[:, None, None] * T.psi[:, :, None] * T.psi[:, None, :])
    return np.kron(M, np.eye(body.dim))


def analyse(body, schemes, support):
    d = body.dim
    rigid = 3 if d == 2 else 6
    M = mass(body, support * body.spacing)
    Kref = stiffness(body, "gauss", support, order=4)
    lam_ref = sla.eigh(Kref, M, eigvals_only=True)
    out = {"reference_lowest_nonrigid": lam_ref[rigid:rigid + 5].tolist()}
    for s in schemes:
        K = stiffness(body, s, support)
        ev = np.linalg.eigvalsh(K)
        lam, V = sla.eigh(K, M)
        ratio = np.einsum("ij,ik,kj->j", V, Kref, V)[rigid:] / lam[rigid:]
        out[s] = {"zero_modes": int(np.sum(np.abs(ev) < 1e-10 * ev.max())),
                  "smallest_nonzero_eig_over_max": float(np.sort(np.abs(ev))[rigid] / ev.max()),
                  "lowest_nonrigid_generalized": lam[rigid:rigid + 5].tolist(),
                  "max_energy_ratio_ref_over_scheme": float(ratio.max()),
                  "modes_with_ratio_above_2": int(np.sum(ratio > 2)),
                  "modes_with_ratio_above_4": int(np.sum(ratio > 4)),
                  "non_rigid_modes": int(len(ratio))}
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--bodies", nargs="*", default=list(BODIES))
    p.add_argument("--supports", type=float, nargs="*", default=[1.5, 2.01])
    p.add_argument("--schemes", nargs="*", default=["gauss", "scni", "mscni"])
    p.add_argument("--betas", type=float, nargs="*", default=[],
                   help="extra sub-cell stabilisation parameters beta to analyse")
    a = p.parse_args(argv)
    schemes = list(a.schemes)
    for b in a.betas:
        scni.SCHEMES[f"mscni_beta{b:g}"] = (b, "nodal")
        schemes.append(f"mscni_beta{b:g}")
    out = {}
    for name in a.bodies:
        for sup in a.supports:
            out[f"{name} support {sup:g}"] = analyse(BODIES[name](), schemes, sup)
    print(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    main()
