"""Which candidate-patch grid of the 3D phantom gives what reduction of the final lateral
deviation (best patch vs no paddle): one static sweep per setting, the reduction map and the
target's two lateral displacement components per patch (x 1e4).

    PYTHONPATH=. python experiments/phantom3d_patch_grid.py SPACING INCREMENTS \
        "[theta_lo,theta_hi,n]" "[phi_lo/pi,phi_hi/pi,n]" PATCH_RADIUS

Measured (neo-Hookean, no inclusion, needle and target as thesis.PHANTOM_3D; 2 increments at
spacing 0.25 = the tests' 162-particle phantom, 4 at 0.2 = the CLI default, 258 particles):

  grid (theta; phi/pi; radius)          spacing 0.25   spacing 0.2   median (0.25)
  0.15..0.9 x4; -0.7..0.7 x6; 0.5  (today)   3.40x         4.3x (brief)   1.09x
  0.5..1.35 x4; -0.8..0.8 x8; 0.5 (flanks)   2.97x         2.87x          0.98x
  0.1..0.9 x6; -0.8..0.8 x10; 0.5            4.76x           -            1.11x
  0.1..0.9 x6; -0.8..0.8 x10; 0.7            9.99x           -            1.21x
  0.1..0.9 x6; -0.8..0.8 x10; 0.9            9.23x           -            1.46x
  0.1..0.7 x7;  0.0..0.8 x9;  0.7           18.3x          6.51x          2.22x (1.70x at 0.2)

Findings: a held skin patch restrains the target little by itself (median ~1-2x at every
setting); the large reductions are cancellations, where both lateral components change sign
across the dome; flank patches at the target's height (theta ~1.2) and the -y half make the
deviation larger. The best patch is an isolated grid point (its neighbours 3-8x), and the sign
map changes between spacing 0.25 and 0.2 (uz under a top patch is +1e-4..+9e-4 at 0.25,
-1.2e-3..-1.9e-3 at 0.2), so a >= 10x best discrete patch at one resolution is a fluke of
that mesh, not a property of the set-up.
"""
import json
import sys
import time

import numpy as np

from jaxrkpm import needle as nd
from jaxrkpm.phantom3d import Phantom3D


def main(argv):
    spacing, increments = float(argv[0]), int(argv[1])
    theta = tuple(json.loads(argv[2]))
    phi_lo, phi_hi, n_phi = json.loads(argv[3])
    phi = (phi_lo * np.pi, phi_hi * np.pi, n_phi)
    t0 = time.time()
    ph = Phantom3D(spacing=spacing, theta=theta, phi=phi, patch_radius=float(argv[4]))
    print("particles", ph.body.n, "patch_size", ph.patch_size, "target", np.round(ph.target, 3))
    s = nd.static_sweep(ph, "none", increments)
    red = abs(s.no_paddle[-1]) / np.abs(s.final)
    q = ph.patch_coordinates
    print(f"no paddle {s.no_paddle[-1]:.3e} converged {s.converged} best {s.best} at {q[s.best - 1]}: "
          f"reduction {red[s.best - 1]:.2f}x, median {np.median(red):.2f}x ({time.time() - t0:.0f} s)")
    shape = (int(theta[2]), int(n_phi))
    print("reduction per patch (rows theta, columns phi):\n", np.round(red.reshape(shape), 2))
    lat = s.target_u[:, -1] @ ph.lateral.T
    for k in range(lat.shape[1]):
        print(f"lateral component {k} x 1e4:\n", np.round(1e4 * lat[:, k].reshape(shape), 1))


if __name__ == "__main__":
    main(sys.argv[1:])
