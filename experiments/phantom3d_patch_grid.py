"""The 3D phantom's static patch sweep at several mesh spacings: the reduction of the final
lateral deviation (no paddle / patch) per candidate patch, the best and the median, and the
target's two lateral displacement components per patch (x 1e4), e.g.

    PYTHONPATH=. python experiments/phantom3d_patch_grid.py 0.25 0.2 0.15 [--increments 2]
        [--set key=value ...]   (Phantom3D fields as JSON, e.g. --set patch_radius=0.4)

Measured 2026-11-24 (default set-up, see phantom3d_convergence.py; grid theta 0.15..1.05 x 5,
phi -0.8 pi..0.8 pi x 5 = 25 patches, 2 increments; shared machine):
  spacing 0.3 (231 particles, 10 per patch): best = top patch, 3.60x; median 0.89x (416 s)
  spacing 0.2 (390 particles, 24 per patch): best = top patch, 17.5x; median 0.97x (906 s, 8 GB)
  the default 4 x 5 grid at 0.3 (12 per patch): best 6.2x (tests/test_needle3d.py)
Only patches on the top of the dome help (row theta = 0.15: 2-18x); flank patches give
0.65-1.05x (they make the deviation larger). The top patch turns the vertical motion from up
(no paddle) to about zero, its residual's sign changing with mesh and patch size
(phantom3d_convergence.py --paddle), so >= 10x at the best patch holds at some meshes and
patch sizes (18x, 33x, 16x) but not others (3.6x, 6.6x): not a mesh-robust result.
A needle at z = 0.4 (spacing 0.3, 24 patches): 28x at one grid point whose neighbours give
0.7x and 6.4x, a cancellation again.
"""
import sys
import time

import numpy as np

from jaxrkpm import needle as nd
from jaxrkpm.phantom3d import Phantom3D

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from phantom3d_convergence import options  # noqa: E402


def main(argv):
    fields, spacings, increments, _ = options(argv, default_increments=2)
    for h in spacings:
        t0 = time.time()
        ph = Phantom3D(spacing=h, **fields)
        print(f"spacing {h}: particles {ph.body.n}, needle {len(ph.needle)}, patch_size {ph.patch_size}, "
              f"target {np.round(ph.target, 3).tolist()}", flush=True)
        s = nd.static_sweep(ph, "none", increments)
        red = abs(s.no_paddle[-1]) / np.abs(s.final)
        q = ph.patch_coordinates
        print(f"  no paddle {s.no_paddle[-1]:.3e} (lateral {np.round(1e4 * ph.lateral_components(s.no_paddle_u[-1]), 2).tolist()} e-4) "
              f"converged {s.converged}; best {s.best} at {np.round(q[s.best - 1], 3).tolist()}: "
              f"{red[s.best - 1]:.2f}x, median {np.median(red):.2f}x ({time.time() - t0:.0f} s)", flush=True)
        shape = (int(ph.theta[2]), int(ph.phi[2]))
        print("  reduction per patch (rows theta, columns phi):\n", np.round(red.reshape(shape), 2))
        lat = s.target_u[:, -1] @ ph.lateral.T
        for k in range(lat.shape[1]):
            print(f"  lateral component {k} x 1e4:\n", np.round(1e4 * lat[:, k].reshape(shape), 2), flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
