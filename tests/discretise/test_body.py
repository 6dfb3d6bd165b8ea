import numpy as np
import pytest

import jaxrkpm as jr
from jaxrkpm.discretise import quadrature as integration
from jaxrkpm.discretise import polygons
from tests.problems import phantom_body, unit_grid



def test_grid_volumes_sum_to_measure():
    b2 = jr.Body.grid((9, 5), 0.125)
    assert b2.volumes.sum() == pytest.approx(1.0 * 0.5, rel=1e-14)
    b3 = jr.Body.grid((3, 3, 3), 0.5, origin=(-2.5, -0.5, 1.5))
    assert b3.volumes.sum() == pytest.approx(1.0, rel=1e-14)
    assert b3.X.min(0) == pytest.approx([-2.5, -0.5, 1.5])


def test_polygon_particles_and_volumes():
    body = phantom_body(0.1)
    assert body.volumes.sum() == pytest.approx(0.875, rel=1e-12)
    assert np.all(body.volumes > 0)
    assert body.contains(body.X).all()
    # particles on every edge, e.g. the cut x + y = 0.5 and the needle entry (0.5, 0)
    on_cut = np.abs(body.X.sum(1) - 0.5) < 1e-12
    assert on_cut.sum() >= 6
    assert np.min(np.linalg.norm(body.X - [0.5, 0.0], axis=1)) < 1e-12


def test_gauss_points_integrate_the_domain():
    for body in (phantom_body(0.1), jr.Body.grid((5, 4, 3), 0.25),
                 jr.Body.polygon([[0, 0], [1, 0], [1, 1], [0.5, 0.4], [0, 1]], 0.1)):
        p, w = integration.gauss_points(body, order=3)
        assert w.sum() == pytest.approx(body.measure, rel=1e-12)
        assert body.contains(p).all()
        # first moments too: the centroid
        if body.dim == 2 and not body.is_box:
            assert (w[:, None] * p).sum(0) / w.sum() == pytest.approx(polygons.centroid(body.vertices), abs=1e-12)
    bp, bw, bn = integration.boundary_points(phantom_body(0.1))
    perimeter = 0.5 + 1 + 1 + 0.5 + np.sqrt(0.5)
    assert bw.sum() == pytest.approx(perimeter, rel=1e-12)
    # the divergence theorem: closed boundary integral of n vanishes, of X (x) n is the area * I
    assert np.abs((bw[:, None] * bn).sum(0)).max() < 1e-12
    assert np.einsum("b,bi,bj->ij", bw, bp, bn) == pytest.approx(0.875 * np.eye(2), abs=1e-12)


def test_select_and_inside_checks():
    body = unit_grid(9)
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


def test_body_shape_functions_and_neighbours_wrap_rk():
    from scipy.spatial import cKDTree

    from jaxrkpm.discretise import rk
    body = phantom_body(0.1)
    tree = cKDTree(body.X)                      # the reference: rk on a tree built here
    P = np.array([[0.55, 0.43], [0.9, 0.1], [0.2, 0.8]])
    a = 2.01 * body.spacing
    ref = rk.shape_functions(body.X, body.volumes, tree, P, a, capacity=40)
    sf = body.shape_functions(P, a, capacity=40)
    assert np.array_equal(sf.idx, ref.idx) and np.array_equal(sf.psi, ref.psi)
    assert np.array_equal(sf.dpsi, ref.dpsi)
    vals = body.shape_functions(P, a, gradients=False)
    assert np.array_equal(vals.psi, rk.shape_functions(body.X, body.volumes, tree, P, a,
                                                      gradients=False).psi)
    nb, nb_ref = body.neighbours(P, a), rk.neighbours(tree, P, a)
    assert np.array_equal(nb.idx, nb_ref.idx) and np.array_equal(nb.mask, nb_ref.mask)


def test_distance_to_segment():
    a, b = np.array([0.0, 0.0]), np.array([2.0, 0.0])
    P = np.array([[1.0, 1.0], [-3.0, 4.0], [5.0, -4.0]])
    assert polygons.distance_to_segment(P, a, b) == pytest.approx([1.0, 5.0, 5.0])
    # a zero-length segment is its point; any dimension; broadcasting over segments
    assert polygons.distance_to_segment(np.array([3.0, 4.0, 12.0]), np.zeros(3), np.zeros(3)) == 13.0
    d = polygons.distance_to_segment(P[:, None], np.array([a, b])[None], np.array([b, b + 1])[None])
    assert d.shape == (3, 2) and d[0, 0] == pytest.approx(1.0)


def test_quadrature_rules():
    x, w = integration.gauss_1d(3)
    assert w.sum() == pytest.approx(1.0) and np.all((x > 0) & (x < 1))
    p, w = integration.tensor_rule(2, 3)
    assert p.shape == (8, 3) and w.sum() == pytest.approx(1.0)
    p, w = integration.segment_rule(np.array([0.0, 0.0, 1.0]), np.array([3.0, 4.0, 1.0]), 2)
    assert w.sum() == pytest.approx(5.0) and (w[:, None] * p).sum(0) / 5 == pytest.approx([1.5, 2, 1])
    tri2 = np.array([[0.0, 0.0], [2.0, 0.0], [0.0, 1.0]])
    tri3 = np.c_[tri2, [1.0, 1.0, 1.0]] @ np.linalg.qr(np.arange(9.0).reshape(3, 3) + np.eye(3))[0]
    for tri in (tri2, tri3):
        p, w = integration.triangle_rule(*tri, 2)
        assert w.sum() == pytest.approx(1.0) and (w[:, None] * p).sum(0) == pytest.approx(tri.mean(0))


def test_labelled_voronoi_cells_match_the_plain_ones():
    body = phantom_body(0.1)
    plain = polygons.voronoi_cells(body.X, body.vertices)
    labelled = polygons.voronoi_cells(body.X, body.vertices, labelled=True, tol=1e-11 * body.spacing)
    for i, (P, (Q, L)) in enumerate(zip(plain, labelled)):
        assert polygons.area(P) == pytest.approx(polygons.area(Q), rel=1e-12)
        assert len(L) == len(Q) and set(L.tolist()) - {-1} <= set(range(body.n)) - {i}
    # an edge label names the particle across it: the edge lies on their bisector
    P, L = labelled[40]
    for k in np.flatnonzero(L >= 0):
        m = 0.5 * (P[k] + P[(k + 1) % len(P)])
        j = L[k]
        assert np.linalg.norm(m - body.X[40]) == pytest.approx(np.linalg.norm(m - body.X[j]), abs=1e-12)
