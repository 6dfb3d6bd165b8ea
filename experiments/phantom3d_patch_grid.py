"""The 3D phantom's static patch sweep at several mesh spacings: the reduction of the final
lateral deviation (no paddle / patch) per candidate patch, the best and the median, and the
target's two lateral displacement components per patch (x 1e4), e.g.

    PYTHONPATH=. python experiments/phantom3d_patch_grid.py 0.25 0.2 0.15 [--increments 2]
        [--set key=value ...]   (Phantom3D fields as JSON, e.g. --set patch_radius=0.4)

Issue 17 (shared 2-core machine, 2 increments): best patch reduction (particles per patch);
the grid over the target's side of the dome top is the default (thesis.PHANTOM_3D):

  grid (theta lo..hi x count, phi lo..hi x count)    spacing 0.3     0.2          0.15
  0.15..0.9 x 4, -0.8pi..0.8pi x 5 (the old default)   6.2x (12)      7.2x (27)    33x (42, top)
  0.1..0.45 x 4,  0.5pi..1.5pi x 5                    13.3x (15)*    110x (32)        -
  0.1..0.45 x 4,  0.4pi..1.6pi x 5 (the default)       5.75x (17)    20.8x (30)   116x (47)
  (* only 18 distinct patches at 0.3: the centres at theta 0.1 crowd together)

Only patches on the dome's top help (the best always in the row theta = 0.1 of the target
grid; flank patches 0.8-2x). The held top turns the target's vertical motion from up (no
paddle) to about zero; its residual (+-1e-3 at spacing 0.3, +-3e-4 at 0.2, of 6.4e-3 and
7.4e-3 without a paddle) changes with the patch's particle count, so >= 10x holds at spacing
0.2 and 0.15 but not at 0.3 (17 particles per patch).

The continuous paddle (``optimize_paddle`` on ``Phantom3D.with_footprint(best)``, Adam, learning
rate 0.05, 2 increments) starts on the best patch's own particles, reproducing it to 1e-5
relative (penalty springs 1e6), and slides off it: spacing 0.3, default grid: 1.12e-3 ->
4.05e-4 in 4 iterations (2.8x below the best patch, over the pole at theta 0.011); spacing
0.2: 3.54e-4 -> 1.29e-4 in 4 (2.7x; 57x below no paddle); the grid 0.5pi..1.5pi at 0.3:
4.87e-4 -> 2.40e-4 (2.0x). Confined to the grid's own theta range (before the
bounds crossed the pole) it stopped at once on the bounds' corner (the best patch's centre).

Earlier (2026-11-24; the old grid, 25 patches 5 x 5): spacing 0.3 (10 per patch) 3.60x, 0.2
(24) 17.5x; the top patch at spacings 0.3/0.2/0.15/0.12: 3.4x/6.6x/33x/11x; a needle at
z = 0.4 (spacing 0.3, 24 patches): 28x at one grid point whose neighbours give 0.7x and 6.4x.
"""
import sys
import time

import numpy as np

from jaxrkpm.thesis import needle as nd
from jaxrkpm.thesis.phantom3d import Phantom3D

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
