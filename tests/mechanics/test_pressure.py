"""The follower pressure (jaxrkpm.Pressure): its residual is the pressure on the deformed
boundary and its tangent the residual's Jacobian; a pressurised thick-walled ring matches
Lamé's solution, inflates more than under the same dead load (the load follows the growing
wall) and is differentiable in the pressure, which the load scale scales."""
from dataclasses import replace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrkpm as jr
from tests.problems import annulus, unit_grid

A, B = 1.0, 2.0                                   # inner and outer radius of the ring
LAM, MU = 1.0, 1.0
RING = jr.NeoHookean(lam=LAM, mu=MU)


def inner(X):
    return np.linalg.norm(X, axis=1) < 0.5 * (A + B)


def holder():
    """Weak springs at four outer points: they take the ring's rigid-body modes and nothing else
    (k is 1e-4 of the ring's stiffness)."""
    return jr.Springs(0.999 * B * np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]]), 1e-4)


def ring_model(rings=4, sectors=32, **kw):
    return jr.Model(annulus(A, B, rings, sectors), RING, springs=holder(), terms=[jr.Pressure(inner, p=1.0)], **kw)


# the problem's methods compiled once per problem structure (eager, each would dispatch its
# many small operations one by one)
residual = jax.jit(lambda prob, u, g, load: prob.residual(u, g, load))
energy = jax.jit(lambda prob, u, g, load: prob.energy(u, g, load)[0])
tangent = jax.jit(lambda prob, u, g, load: prob.tangent(u, g, load))
coefficients = jax.jit(lambda prob, u, g: prob.coefficients(u, g))
reactions = jax.jit(lambda prob, u, g, load: prob.reactions(u, g, load))
transpose = jax.jit(lambda prob, u, g, f: jax.vjp(lambda v: prob.coefficients(v, g), u)[1](f)[0])


@pytest.fixture(scope="module")
def ring():
    return ring_model()


def radial(model, sol, radius):
    """The mean radial displacement of the particles at ``radius``."""
    X = model.body.X
    r = np.linalg.norm(X, axis=1)
    at = np.abs(r - radius) < 1e-9
    u = np.asarray(model.displacement(sol, X[at]))
    return float(np.mean(np.sum(u * X[at], 1) / r[at]))


# ------------------------------------------------------------------ the term itself
def cube_model(where, essential=None, n=3):
    body = unit_grid(n, dim=3)
    return jr.Model(body, jr.NeoHookean(lam=1.0, mu=1.0), essential=essential,
                    terms=[jr.Pressure(where, p=0.7)])


def top(X):
    return X[:, 2] > 1 - 1e-9


def rim_of_top(body):
    return {"rim": body.select(lambda X: (X[:, 2] > 1 - 1e-9) & np.any((X[:, :2] < 1e-9) | (X[:, :2] > 1 - 1e-9), 1))}


CASES = {
    "cavity (2D ring)": lambda: ring_model(rings=2, sectors=12),
    "closed surface (3D cube)": lambda: cube_model(lambda X: np.ones(len(X), bool)),
    "membrane (3D, rim held)": lambda: cube_model(top, rim_of_top(unit_grid(4, dim=3)), n=4),
}


@pytest.fixture(scope="module", params=list(CASES))
def case(request):
    """(name, model, pressure-only problem, a deformed state u, g, load)."""
    model = CASES[request.param]()
    prob = model.problem()
    rng = np.random.default_rng(7)
    u = jnp.asarray(0.05 * rng.standard_normal((prob.n_free, prob.dim)))
    g = jnp.asarray(0.03 * rng.standard_normal((len(model.sets.bnd), prob.dim)))
    return request.param, model, prob.replace(terms=(prob.term("pressure"),)), u, g, 0.8


def central_differences(f, prob, u, g, load, v, eps=1e-6):
    return (np.asarray(f(prob, u + eps * v, g, load)) - np.asarray(f(prob, u - eps * v, g, load))) / (2 * eps)


def test_pressure_residual_is_the_pressure_on_the_deformed_boundary(case):
    """r = T^T f with f the follower load on the particles: each deformed simplex (segment,
    triangle) of the loaded boundary carries -p n a, shared equally by its corners and carried
    to the particles by the shape functions there. Computed here from the deformed corners
    directly (no volume, no autodiff); for the held membrane the rim corners do not move, so
    their share drops out of r. The reference simplices tile the loaded boundary: their area
    and the volume they enclose are the cavity's, the cube's or the face's."""
    name, _, prob, u, g, load = case
    t = prob.term("pressure")
    dim = prob.dim
    Y, idx, psi, S = (np.asarray(x) for x in (t.Y, t.idx, t.psi, t.simplices))
    d = np.asarray(coefficients(prob, u, g))
    corners = (Y + np.einsum("sk,ski->si", psi, d[idx]))[S]               # (T, dim, dim)
    ref = Y[S]
    if dim == 2:
        def area_normal(c):
            e = c[:, 1] - c[:, 0]
            return np.stack([e[:, 1], -e[:, 0]], 1)
    else:
        def area_normal(c):
            return 0.5 * np.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0])
    f = np.zeros_like(d)
    for a in range(dim):
        share = -load * float(t.p) * area_normal(corners) / dim           # on each corner
        np.add.at(f, idx[S[:, a]], psi[S[:, a]][..., None] * share[:, None, :])
    expected = -np.asarray(transpose(prob, u, g, jnp.asarray(f)))          # r = dPi/du = -T^T f
    r = np.asarray(residual(prob, u, g, load))
    print(name, "|r|", np.linalg.norm(r), "error", np.abs(r - expected).max())
    assert np.abs(r - expected).max() < 1e-12 * np.abs(expected).max()
    # the reference simplices: outward normals, the loaded area and the enclosed volume
    na = area_normal(ref)
    signed_volume = np.sum(np.einsum("ti,ti->t", ref[:, 0], na)) / dim     # int X . N dA / d
    area, volume = {"cavity (2D ring)": (2 * 12 * np.sin(np.pi / 12), -12 * np.sin(np.pi / 6) / 2),
                    "closed surface (3D cube)": (6.0, 1.0), "membrane (3D, rim held)": (1.0, None)}[name]
    assert np.sum(np.linalg.norm(na, axis=1)) == pytest.approx(area, rel=1e-12)
    if volume is not None:
        assert signed_volume == pytest.approx(volume, rel=1e-12)


def test_pressure_tangent_is_the_jacobian_of_its_residual(case):
    """The pressure's tangent (its blocks reduced through T) is symmetric and equals central
    differences of its residual, and the residual central differences of its energy, at a
    deformed state and load scale 0.8 (the tangent scales with the load). Then, for the ring,
    the whole problem (strain energy, springs and pressure): the terms' blocks summed at that
    load scale are the Jacobian of its residual too (in 3D the strain energy's tangent would
    cost a long compile and is tested elsewhere). For the cube, the blocks summed in windows
    (``block_budget``) are the blocks summed at once."""
    name, model, prob, u, g, load = case
    K = np.asarray(tangent(prob, u, g, load))
    assert np.abs(K - K.T).max() < 1e-12 * np.abs(K).max()
    r = np.asarray(residual(prob, u, g, load))
    for v in np.random.default_rng(3).standard_normal((2,) + u.shape):
        v = jnp.asarray(v)
        dr = central_differences(residual, prob, u, g, load, v)
        Kv = K @ np.asarray(v).ravel()
        print(name, "|Kv - dr| / |Kv|", np.abs(Kv - dr.ravel()).max() / np.abs(Kv).max())
        assert np.abs(Kv).max() > 0.01 * np.abs(r).max()                   # not a trivial zero
        assert np.abs(Kv - dr.ravel()).max() < 1e-7 * np.abs(Kv).max()
        dE = float(central_differences(energy, prob, u, g, load, v))
        rv = float(np.sum(r * np.asarray(v)))
        print(name, "dE/dv vs r . v, relative", dE / rv - 1)
        assert dE == pytest.approx(rv, rel=1e-7)
    if name == "closed surface (3D cube)":
        # swept in windows of 7 simplices (the last one shifted back over simplices already
        # summed): the same tangent
        t = prob.term("pressure")
        T, _, Kt = t.spsi.shape
        windowed = prob.replace(terms=(replace(t, block_budget=7 * Kt * Kt * 9),))
        assert T % 7
        assert np.abs(np.asarray(tangent(windowed, u, g, load)) - K).max() < 1e-13 * np.abs(K).max()
    if prob.dim == 3:
        return
    whole = model.problem({"pressure": 0.3})
    K = np.asarray(tangent(whole, u, g, load))
    v = jnp.asarray(np.random.default_rng(11).standard_normal(u.shape))
    dr = central_differences(residual, whole, u, g, load, v)
    print(name, "whole problem: |Kv - dr| / |dr|", np.abs(K @ np.asarray(v).ravel() - dr.ravel()).max() / np.abs(dr).max())
    assert np.abs(K @ np.asarray(v).ravel() - dr.ravel()).max() < 1e-7 * np.abs(dr).max()


def test_an_open_loaded_part_needs_its_rim_held():
    """A follower pressure on an open surface with a free rim has no potential: refused, with
    the way out named. With the rim held (a pressed membrane: the top edge of a block between
    two held corners), accepted, and the supports carry the whole load: at any state, the
    reactions plus the residual (the out-of-balance force on the free particles, zero at
    equilibrium) sum to the pressure's resultant, and with the corners in place that is p x
    (the chord, of length 1) upwards whatever shape the pressed edge takes. Without the rim's
    reaction correction (the energy's gradient at the held corners, which depends on where
    the volume is measured from) the sum is off. Bad specifications are named too."""
    with pytest.raises(ValueError, match="rim are not held"):
        cube_model(top)
    body = unit_grid(5)
    held = {"bottom": body.select(lambda X: X[:, 1] < 1e-9)}
    with pytest.raises(ValueError, match="rim are not held"):
        jr.Model(body, RING, essential=held, terms=[jr.Pressure(lambda X: X[:, 1] > 1 - 1e-9)])
    corners = {**held, "corners": body.select(lambda X: (X[:, 1] > 1 - 1e-9)
                                                & ((X[:, 0] < 1e-9) | (X[:, 0] > 1 - 1e-9)))}
    m = jr.Model(body, RING, essential=corners, terms=[jr.Pressure(lambda X: X[:, 1] > 1 - 1e-9, p=1.0)])
    P, load = 0.4, 0.7
    prob = m.problem({"pressure": P})
    u = jnp.asarray(0.05 * np.random.default_rng(2).standard_normal((prob.n_free, 2)))
    u = u.at[:, 1].add(-0.1)                                    # the edge pressed in
    g = jnp.zeros((len(m.sets.bnd), 2))
    r = np.asarray(residual(prob, u, g, load)).sum(0)
    total = np.asarray(reactions(prob, u, g, load)).sum(0) + r
    bare = prob.replace(terms=tuple(replace(t, rim=0 * t.rim) if t.name == "pressure" else t for t in prob.terms))
    uncorrected = np.asarray(reactions(bare, u, g, load)).sum(0) + r
    print("reactions + residual", total, "without the rim correction", uncorrected, "expected", [0.0, load * P])
    assert np.abs(total - [0.0, load * P]).max() < 1e-12 * P
    assert np.abs(uncorrected - [0.0, load * P]).max() > 1e-3 * P
    with pytest.raises(ValueError, match="selects no boundary facet"):
        jr.Model(body, RING, essential=held, terms=[jr.Pressure(lambda X: X[:, 1] > 2)])
    with pytest.raises(ValueError, match="name 'mu' is taken"):
        jr.Model(body, RING, essential=held, terms=[jr.Pressure(lambda X: np.ones(len(X), bool), name="mu")])
    with pytest.raises(TypeError, match="list of term specifications"):
        jr.Model(body, RING, essential=held, terms=jr.Pressure(lambda X: np.ones(len(X), bool)))
    with pytest.raises(ValueError, match="finite number"):
        jr.Pressure(lambda X: np.ones(len(X), bool), p=np.nan)


# ------------------------------------------------------------------ the pressurised ring
def test_ring_under_internal_pressure_matches_lame(ring):
    """A small internal pressure p: the radial displacement of the inner and outer wall is
    Lamé's plane-strain u_r = C r + D / r, C = p a^2 / (2 (lam + mu) (b^2 - a^2)),
    D = p a^2 b^2 / (2 mu (b^2 - a^2)), within 2% at 4 x 32 cells."""
    p = 1e-3
    sol = ring.solve(params={"pressure": p})
    C = p * A**2 / (2 * (LAM + MU) * (B**2 - A**2))
    D = p * A**2 * B**2 / (2 * MU * (B**2 - A**2))
    for R in (A, B):
        got, want = radial(ring, sol, R), C * R + D / R
        print(f"u_r({R}) = {got:.6e}, Lame {want:.6e}, error {got / want - 1:+.2%}")
        assert got == pytest.approx(want, rel=0.02)


def test_follower_pressure_inflates_more_than_the_same_dead_load(ring):
    """At a large pressure (inner wall strain ~30%) the follower load acts on the stretched
    wall: the ring inflates more than under the same pressure as a dead load on the reference
    wall. The deformation being axisymmetric, the follower pressure p is the dead load of
    nominal pressure p (a + u_a) / a (the wall's length ratio); that dead load reproduces the
    follower's inflation to a few percent of the difference."""
    P = 0.3
    follower = radial(ring, ring.solve(params={"pressure": P}, steps=4), A)
    dead = jr.Model(ring.body, RING, springs=holder(),        # pressure 1 on the reference wall
                    tractions=[(inner, lambda X: X / np.linalg.norm(X, axis=1, keepdims=True))])
    same = radial(dead, dead.solve(loads=P, steps=4), A)
    nominal = radial(dead, dead.solve(loads=P * (1 + follower / A), steps=4), A)
    print(f"u_a: follower {follower:.5f}, dead {same:.5f}, dead at the stretched wall's pressure {nominal:.5f}")
    assert follower > 1.2 * same
    assert abs(nominal - follower) < 0.05 * (follower - same)


def test_load_scale_scales_the_pressure(ring):
    """loads = 1/2 at pressure 2p is the equilibrium at p, loads = 1 (the same load steps, so
    the same iterates up to the convergence test, whose force scale is p's)."""
    a = ring.solve(params={"pressure": 0.2}, steps=2)
    b = ring.solve(params={"pressure": 0.4}, loads=0.5, steps=2)
    print("|u(p, 1) - u(2p, 1/2)| / |u|", np.abs(np.asarray(a.u - b.u)).max() / np.abs(np.asarray(a.u)).max())
    assert np.abs(np.asarray(a.u - b.u)).max() < 1e-9 * np.abs(np.asarray(a.u)).max()
    # the load scale drives the pressure: arc-length continuation takes it for a load
    assert ring.problem().loaded() and not ring.problem({"pressure": 0.0}).loaded()
    assert radial(ring, a, A) > 0.1


def test_solution_is_differentiable_in_the_pressure(ring):
    """d u_r(a) / dp by the implicit derivative of the solve, against central differences of
    the solve, in the nonlinear range."""
    at = ring.body.X[np.abs(np.linalg.norm(ring.body.X, axis=1) - A) < 1e-9][:1]

    def inner_wall(p):
        return ring.displacement(ring.solve(params={"pressure": p}, steps=3), at)[0, 0]

    P, e = 0.25, 1e-5
    grad = float(jax.grad(inner_wall)(P))
    fd = (float(inner_wall(P + e)) - float(inner_wall(P - e))) / (2 * e)
    print("du/dp implicit", grad, "central differences", fd)
    assert grad > 0 and grad == pytest.approx(fd, rel=1e-6)
