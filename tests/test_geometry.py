import numpy as np
import pytest

import jaxrkpm as jr
from jaxrkpm import integration, polygons

PHANTOM = [[0.5, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0], [0.0, 0.5]]


def test_grid_volumes_sum_to_measure():
    b2 = jr.Body.grid((9, 5), 0.125)
    assert b2.volumes.sum() == pytest.approx(1.0 * 0.5, rel=1e-14)
    b3 = jr.Body.grid((3, 3, 3), 0.5, origin=(-2.5, -0.5, 1.5))
    assert b3.volumes.sum() == pytest.approx(1.0, rel=1e-14)
    assert b3.X.min(0) == pytest.approx([-2.5, -0.5, 1.5])


def test_polygon_particles_and_volumes():
    body = jr.Body.polygon(PHANTOM, 0.1)
    assert body.volumes.sum() == pytest.approx(0.875, rel=1e-12)
    assert np.all(body.volumes > 0)
    assert body.contains(body.X).all()
    # particles on every edge, e.g. the cut x + y = 0.5 and the needle entry (0.5, 0)
    on_cut = np.abs(body.X.sum(1) - 0.5) < 1e-12
    assert on_cut.sum() >= 6
    assert np.min(np.linalg.norm(body.X - [0.5, 0.0], axis=1)) < 1e-12


def test_gauss_points_integrate_the_domain():
    for body in (jr.Body.polygon(PHANTOM, 0.1), jr.Body.grid((5, 4, 3), 0.25),
                 jr.Body.polygon([[0, 0], [1, 0], [1, 1], [0.5, 0.4], [0, 1]], 0.1)):
        p, w = integration.gauss_points(body, order=3)
        assert w.sum() == pytest.approx(body.measure, rel=1e-12)
        assert body.contains(p).all()
        # first moments too: the centroid
        if body.dim == 2 and not body.is_box:
            assert (w[:, None] * p).sum(0) / w.sum() == pytest.approx(polygons.centroid(body.vertices), abs=1e-12)
    bp, bw, bn = integration.boundary_points(jr.Body.polygon(PHANTOM, 0.1))
    perimeter = 0.5 + 1 + 1 + 0.5 + np.sqrt(0.5)
    assert bw.sum() == pytest.approx(perimeter, rel=1e-12)
    # the divergence theorem: closed boundary integral of n vanishes, of X (x) n is the area * I
    assert np.abs((bw[:, None] * bn).sum(0)).max() < 1e-12
    assert np.einsum("b,bi,bj->ij", bw, bp, bn) == pytest.approx(0.875 * np.eye(2), abs=1e-12)


def test_select_and_inside_checks():
    body = jr.Body.grid((9, 9), 0.125)
    wall = body.select(lambda X: X[:, 0] < 1e-9)
    assert len(wall) == 9 and np.all(body.X[wall, 0] == 0)
    with pytest.raises(ValueError, match="predicate must return"):
        body.select(lambda X: X[:5, 0] > 0)
    with pytest.raises(ValueError, match=r"point 1 at \[1.5, 0.5\] is outside the body"):
        body.check_inside([[0.5, 0.5], [1.5, 0.5]])
    with pytest.raises(ValueError, match="grid shape"):
        jr.Body.grid((9,), 0.1)
    with pytest.raises(ValueError, match="spacing must be positive"):
        jr.Body.grid((3, 3), -1.0)
    with pytest.raises(ValueError, match="zero area"):
        jr.Body.polygon([[0, 0], [1, 0], [2, 0]], 0.1)
