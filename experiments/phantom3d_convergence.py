"""Mesh convergence of the 3D phantom's no-paddle state: the target displacement (axial, then the
lateral components) at full insertion for each spacing given on the command line, e.g.
``python experiments/phantom3d_convergence.py 0.25 0.2 0.15 0.12 0.1``.

Measured 2026-11-23 (quiet 2-core machine): not converged; the lateral y component changes sign
with the mesh. The needle particles are those within needle_radius x spacing of the track, so
the loaded region itself changes with the mesh (see the issue 17 note)."""
import jaxrkpm as jr
from jaxrkpm import needle as nd
from jaxrkpm.phantom3d import Phantom3D
for h in [float(x) for x in sys.argv[1:]]:
    t = time.time()
    ph = Phantom3D(spacing=h)
    model, sol = nd.static_state(ph, "none", None, 4)
    u = np.asarray(model.displacement(sol, np.atleast_2d(ph.target)))[0]
    print(f"spacing {h}: particles {ph.body.n}, status {sol.status}, load {float(sol.t) if hasattr(sol,'t') else ''}, "
          f"target u {np.round(u, 6).tolist()}, lateral {np.round(ph.lateral_components(u), 6).tolist()}, "
          f"{time.time() - t:.0f} s", flush=True)
