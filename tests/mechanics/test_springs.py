"""Springs: zero-length springs holding material points (elastic supports, penalty paddles)."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrkpm as jr
from jaxrkpm.discretise.rk import psi_jax
from tests.problems import FUNG, unit_grid

N = 7


@pytest.fixture(scope="module")
def setup():
    body = unit_grid(N)
    X = body.X
    sets = {"wall": body.select(lambda X: X[:, 0] < 1e-9),
            "top": body.select(lambda X: (X[:, 1] > 1 - 1e-9) & (X[:, 0] > 1e-9))}
    pts = np.array([[1.0, 0.5], [0.75, 0.0]])
    model = jr.Model(body, FUNG, essential=sets, springs=jr.Springs(pts, 50.0, region=np.arange(body.n)))
    return body, X, sets, model


def test_psi_jax_matches_build_time_shape_functions(setup):
    body, X, _, model = setup
    P = np.random.default_rng(0).uniform(0, 1, (6, 2))
    sf = body.shape_functions(P, model.a)
    region = np.tile(np.arange(body.n), (len(P), 1))
    psi = np.asarray(psi_jax(X, body.volumes, region, jnp.asarray(P), model.a))
    dense = np.zeros_like(psi)
    np.add.at(dense, (np.arange(len(P))[:, None], sf.idx), sf.psi)   # padding: index 0, psi 0
    assert np.abs(psi - dense).max() < 1e-12
    assert np.abs(psi @ X - P).max() < 1e-12          # still reproduces linear fields


def test_tangent_with_springs_is_the_energy_hessian(setup):
    _, _, _, model = setup
    sol = model.solve({"top": [0.05, -0.1]})
    prob = model.problem()
    K = np.asarray(prob.tangent(sol.u, sol.g))
    grad = jax.grad(lambda u: prob.energy(u, sol.g)[0])
    for v in np.random.default_rng(1).normal(size=(3,) + sol.u.shape):   # Hessian-vector products
        Hv = np.asarray(jax.jvp(grad, (sol.u,), (jnp.asarray(v),))[1]).ravel()
        assert np.abs(K @ v.ravel() - Hv).max() < 1e-10 * np.abs(Hv).max()


def test_stiff_springs_converge_to_the_essential_set(setup):
    """Springs of stiffness k at particles hold them like an essential set, to O(1/k)."""
    body, X, sets, _ = setup
    held = body.select(lambda X: (X[:, 0] > 1 - 1e-9) & (abs(X[:, 1] - 0.5) < 0.2))
    ref = jr.Model(body, FUNG, essential={**sets, "held": held})
    u_ref = ref.displacement(ref.solve({"top": [0.05, -0.1]}), [[0.5, 0.5]])
    errors = []
    for k in (1e3, 1e5):
        m = jr.Model(body, FUNG, essential=sets, springs=jr.Springs(X[held], k))
        s = m.solve({"top": [0.05, -0.1]})
        errors.append(float(np.abs(m.displacement(s, [[0.5, 0.5]]) - u_ref).max()))
    print("spring vs essential:", errors)
    assert errors[1] < 1e-4 and errors[1] < errors[0] / 50


def test_solution_is_differentiable_in_the_spring_points(setup):
    """d u(probe) / d (spring point position), implicit, against central differences."""
    _, _, _, model = setup
    sf = model.shape_functions([[0.5, 0.5]], gradients=False)
    idx, psi = jnp.asarray(sf.idx), jnp.asarray(sf.psi)

    def probe(y):
        P = jnp.stack([jnp.array([1.0, y]), jnp.array([0.75, 0.0])])
        s = model.solve({"top": [0.05, -0.1]}, params={"springs": model.springs_at(P)})
        return model.constraint.point_values(idx, psi, s.u, s.g)[0, 0]

    g = float(jax.grad(probe)(0.5))
    e = 1e-5
    fd = (float(probe(0.5 + e)) - float(probe(0.5 - e))) / (2 * e)
    assert g != 0.0 and abs(g - fd) < 1e-6 * abs(fd)


def test_bad_springs(setup):
    body, X, sets, model = setup
    with pytest.raises(ValueError, match="stiffness"):
        jr.Model(body, FUNG, essential=sets, springs=jr.Springs(X[:2], -1.0))
    small = jr.Model(body, FUNG, essential=sets, springs=jr.Springs([[1.0, 0.5]], 10.0))
    with pytest.raises(ValueError, match="left its region"):
        small.springs_at([[0.0, 0.5]])
    with pytest.raises(ValueError, match="shape"):
        model.springs_at([[1.0, 0.5]])
    with pytest.raises(ValueError, match="springs_at"):
        model.solve({"top": [0.0, 0.0]}, params={"springs": {"k": 1.0}})
