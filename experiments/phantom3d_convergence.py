"""Mesh convergence of the 3D phantom's no-paddle state: the target displacement (axial, then the
lateral components) at full insertion for each spacing, e.g.
``python experiments/phantom3d_convergence.py 0.25 0.2 0.15 0.12`` (optionally
``--set key=value`` Phantom3D fields, e.g. ``--set needle_point=[0,0,0.2]``; ``--paddle N``: with
patch N held).

Measured 2026-11-24 (shared 2-core machine; 4 increments; the default set-up: needle of radius
0.1 in y = 0 at z = 0.3, the mesh conforming to its axis and four surface lines at track
spacing 0.1, mirror-symmetric). Target displacement at full insertion, no paddle:

  spacing  particles   u_x      u_z (the lateral deviation)   u_y
  0.3        231       0.0486   0.00645                        0 (symmetry, < 1e-15)
  0.25       304       0.0420   0.00812                        0
  0.2        390       0.0406   0.00737                        0
  0.15       598       0.0406   0.00747                        0
  0.12       906       0.0378   0.00769                        0
  0.1       1332       0.0369   0.00721                        0
  0.085     2089         -      0.00640  (bench_needle3d.py)   -

Within +-4% for spacing 0.2..0.1, where the needle's own lines (pitch track_spacing 0.1) are
no coarser than the mesh; at 0.085, finer than the needle's pitch, 13% lower: the needle's
discretisation must be refined with the mesh there (track_spacing <= spacing), not measured. Before (the same day): the needle as the particles
within 0.75 spacing of the track, an asymmetric mesh: u_y +0.0010/+0.0018/-0.0021/+0.0003/-0.0003
at spacing 0.25..0.1, u_z 0.0025..0.0047; the track embedded but the needle a line of particles
(radius below the mesh): u_z 0.0062, 0.0044, 0.0031, 0.0039 at 0.3..0.15 (a discrete line has
no capacity in 3D: its pull fades as the mesh refines around it), and on an asymmetric mesh
u_y = 15-25% of u_z from mesh asymmetry alone.

The top patch (theta 0.15, phi 0) held, 2 increments, u_z x 1e4 (reduction vs no paddle): its
particle count is the grid's smallest patch, so it depends on the grid:
  grid 5 x 5 (0.15..1.05; +-0.8 pi): 0.3 (10 particles) +17.9 (3.6x); 0.2 (24) -4.1 (18x);
                                     0.15 (37) -2.2 (33x); 0.12 (57) +4.7 (16x)
  grid 4 x 5 (the default)         : 0.3 (12) +19.0 (3.4x); 0.2 (27) -11.2 (6.6x);
                                     0.15 (42) -1.8, u_y 1.3 (33x); 0.12 (66) +6.8 (11x)
A near-cancellation whose residual changes sign with the mesh and the patch size.
"""
import json
import sys
import time

import numpy as np

from jaxrkpm.thesis import needle as nd
from jaxrkpm.thesis.phantom3d import Phantom3D


def options(argv, default_increments=4):
    """(Phantom3D fields, spacings, increments) from the command line."""
    fields, spacings, increments, paddle = {}, [], default_increments, None
    it = iter(argv)
    for a in it:
        if a == "--set":
            k, v = next(it).split("=", 1)
            v = json.loads(v)
            fields[k] = tuple(v) if isinstance(v, list) else v
        elif a == "--increments":
            increments = int(next(it))
        elif a == "--paddle":
            paddle = int(next(it))
        else:
            spacings.append(float(a))
    return fields, spacings, increments, paddle


def main(argv):
    fields, spacings, increments, paddle = options(argv)
    print(fields, "increments", increments, "paddle", paddle, flush=True)
    for h in spacings:
        t = time.time()
        ph = Phantom3D(spacing=h, **fields)
        model, sol = nd.static_state(ph, "none", paddle, increments)
        u = np.asarray(model.displacement(sol, np.atleast_2d(ph.target)))[0]
        where = "" if paddle is None else f"patch {paddle} at {ph.patch_coordinates[paddle - 1].round(3).tolist()} " \
            f"({ph.patch_size} particles), "
        print(f"spacing {h}: particles {ph.body.n}, needle {len(ph.needle)}, {where}status {int(sol.status)}, "
              f"target u {np.round(u, 6).tolist()}, lateral {np.round(ph.lateral_components(u), 6).tolist()}, "
              f"{time.time() - t:.0f} s", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
