"""Shape servoing (Algorithm 3) on the 3D phantom's mesh loaded from a file.

Apart from tests/thesis/test_needle3d.py because its programs compile rather than run long: it
keeps the suite's lighter XLA optimisation (tests/conftest.py), which costs it less CPU than the
sweeps' module's full one."""
import numpy as np
import pytest

import jaxrkpm as jr
from jaxrkpm.thesis.phantom3d import Phantom3D

SPACING = 0.3    # tests/thesis/test_needle3d.py's coarse phantom


@pytest.mark.slow(reason="Algorithm 3 on a 3D mesh body loaded from a file: tracking is tested in the "
                         "default run (tests/model/test_jacobian.py, tests/thesis/test_track.py)")
def test_shape_servoing_on_loaded_mesh(tmp_path):
    """Algorithm 3 (``control.track``) on a body loaded from a mesh file: a skin patch driven,
    an interior control point following a short path, every waypoint reached."""
    from jaxrkpm.control.tracking import track
    phantom = Phantom3D(spacing=SPACING, material_law="neohookean")   # as test_needle3d.py's phantom
    path = tmp_path / "phantom.vtu"
    phantom.mesh().write(path)
    body = jr.Body.from_mesh(str(path))
    np.testing.assert_allclose(body.X, phantom.body.X, atol=1e-12)
    model = jr.Model(body, phantom.material(), essential={"base": phantom.base, "paddle": phantom.patch(1)},
                     support=phantom.support)
    cp = np.array([[0.3, 0.0, 0.25]])
    waypoints = np.array([[0.0, 0.0, 0.0], [0.004, 0.0, 0.002], [0.004, 0.003, 0.004]])
    res = track(model, waypoints, "paddle", cp, gain=0.5, clamp=0.01, tol=1e-4)
    assert res.status.name == "DONE", res.message
    assert np.all(res.reached >= 0) and res.max_waypoint_error < 1e-4
