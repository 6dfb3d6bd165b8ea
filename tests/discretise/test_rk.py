"""Reproducing conditions of the RK shape functions (eqs 3.16-3.21)."""
import numpy as np
import pytest

import jaxrkpm as jr
from jaxrkpm.discretise.rk import kernel, kernel_derivative
from tests.problems import phantom_body, unit_grid

BODIES = {
    "grid2d": lambda: unit_grid(9),
    "grid3d": lambda: jr.Body.grid((4, 5, 3), 0.25, origin=(-2.5, -0.5, 1.5)),
    "polygon": lambda: phantom_body(0.1),
    "nonconvex": lambda: jr.Body.polygon([[0, 0], [1, 0], [1, 1], [0.5, 0.4], [0, 1]], 0.1),
}


@pytest.mark.parametrize("name", BODIES)
def test_reproducing_conditions(name):
    body = BODIES[name]()
    rng = np.random.default_rng(1)
    P = body.lower + (body.upper - body.lower) * rng.random((400, body.dim))
    P = np.concatenate([P[body.contains(P)], body.X[:20]])
    sf = body.shape_functions(P, 2.01 * body.spacing)
    Xn = body.X[sf.idx]
    d = body.dim
    assert np.abs(sf.psi.sum(1) - 1).max() < 1e-12                                   # sum psi = 1
    assert np.abs(np.einsum("pk,pkd->pd", sf.psi, Xn) - P).max() < 1e-12              # sum psi X = X
    assert np.abs(sf.dpsi.sum(1)).max() < 1e-12                                       # sum grad psi = 0
    assert np.abs(np.einsum("pkj,pki->pij", sf.dpsi, Xn) - np.eye(d)).max() < 1e-12   # sum grad psi (x) X = I


def test_gradients_match_finite_differences():
    body = phantom_body(0.1)
    P = np.array([[0.55, 0.43], [0.9, 0.1]])
    a = 2.01 * body.spacing
    sf = body.shape_functions(P, a, capacity=40)
    eps = 1e-6
    for j in range(2):
        e = np.zeros(2)
        e[j] = eps
        fp = body.shape_functions(P + e, a, capacity=40)
        fm = body.shape_functions(P - e, a, capacity=40)
        assert np.array_equal(fp.idx, sf.idx)
        assert np.abs((fp.psi - fm.psi) / (2 * eps) - sf.dpsi[..., j]).max() < 1e-6


def test_kernel_is_eq_3_21():
    x = np.linspace(-1.2, 1.2, 241)
    assert kernel(np.array(0.0)) == pytest.approx(2 / 3)
    assert kernel(np.array(0.5)) == pytest.approx(1 / 6)
    assert np.all(kernel(np.array([1.0, 1.1, -1.05])) == 0)
    # C2 continuity at the break points and a derivative that matches differences
    h = 1e-6
    assert np.abs((kernel(x + h) - kernel(x - h)) / (2 * h) - kernel_derivative(x)).max() < 1e-6
    # eq 3.21 is the cubic B-spline B(2x), so its integral is 1/2 (the scale cancels in M^-1)
    xs = np.linspace(-1, 1, 200001)
    assert np.trapezoid(kernel(xs), xs) == pytest.approx(0.5, abs=1e-8)


def test_support_too_small_names_the_point():
    body = unit_grid(5)
    with pytest.raises(ValueError, match=r"moment matrix is singular at point .*larger support"):
        body.shape_functions(np.array([[0.1, 0.1]]), 0.6 * 0.25, support_factor=0.6)


def test_neighbour_capacity_overflow_is_reported():
    body = unit_grid(5)
    with pytest.raises(ValueError, match="capacity 3 overflows"):
        body.shape_functions(np.array([[0.5, 0.5]]), 0.5, capacity=3)
