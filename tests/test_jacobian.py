"""Implicit differentiation of equilibrium: Jacobians, jacfwd/grad through solve, tracking."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrkpm as jr
from jaxrkpm.control import PATHS, TrackStatus, control_increment, track
from jaxrkpm.linear import Stability
from jaxrkpm.solve import Status

CP = np.array([[0.5, 0.5]])


@pytest.fixture(scope="module")
def planar():
    """The chapter-5 object: 9x9 Fung square, left edge immobile, paddle = the three right-edge
    particles nearest (1, 0.5). (Not the three particles nearest (1, 0.5): (0.875, 0.5),
    (1, 0.375) and (1, 0.625) tie at 0.125 and a sort by distance picked the interior one.)"""
    body = jr.Body.grid((9, 9), 0.125)
    wall = body.select(lambda X: X[:, 0] < 1e-9)
    paddle = body.select(lambda X: (X[:, 0] > 1 - 1e-9) & (np.abs(X[:, 1] - 0.5) < 0.2))
    assert sorted(map(tuple, body.X[paddle])) == [(1.0, 0.375), (1.0, 0.5), (1.0, 0.625)]
    model = jr.Model(body, jr.Fung(alpha=1.0, beta=1.0), essential={"wall": wall, "paddle": paddle})
    sol = model.solve({"paddle": jnp.array([-0.08, 0.05])}, steps=2)
    return model, sol


def test_implicit_matches_central_fd_2d(planar):
    model, sol = planar
    Ji = np.asarray(model.jacobian(sol, "paddle", CP))
    Jf = np.asarray(model.jacobian(sol, "paddle", CP, method="fd", eps=1e-5))
    rel = np.abs(Ji - Jf).max() / np.abs(Ji).max()
    print("2D implicit vs central FD relative difference", rel)
    assert rel < 1e-6
    assert Ji.shape == (2, 2) and np.linalg.cond(Ji) < 10


def test_per_particle_driving(planar):
    model, sol = planar
    Jp = np.asarray(model.jacobian(sol, "paddle", CP, rigid=False))       # (2, 3*2)
    Jr = np.asarray(model.jacobian(sol, "paddle", CP))
    assert Jp.shape == (2, 6)
    # a rigid translation is the sum of the per-particle columns
    assert np.abs(Jp.reshape(2, 3, 2).sum(1) - Jr).max() < 1e-12


def test_implicit_matches_central_fd_3d():
    body = jr.Body.grid((3, 3, 3), 0.5, origin=(-2.5, -0.5, 1.5))
    model = jr.Model(body, jr.Quadratic(alpha=1.0), essential={
        "wall": body.select(lambda X: X[:, 0] > -1.5 - 1e-9),
        "paddle": body.select(lambda X: (X[:, 0] < -2.5 + 1e-9) & (X[:, 2] < 2.25))})
    sol = model.solve({"paddle": jnp.array([-0.1, 0.0, 0.1])})
    cp = [[-2.0, 0.0, 2.5]]
    Ji = np.asarray(model.jacobian(sol, "paddle", cp))
    Jf = np.asarray(model.jacobian(sol, "paddle", cp, method="fd", eps=1e-5))
    rel = np.abs(Ji - Jf).max() / np.abs(Ji).max()
    print("3D implicit vs central FD relative difference", rel)
    assert Ji.shape == (3, 3) and rel < 1e-6


def test_jacfwd_through_solve_equals_implicit_jacobian(planar):
    model, sol = planar
    g = jnp.array([-0.08, 0.05])
    Jd = jax.jacfwd(lambda v: model.displacement(model.solve({"paddle": v}, steps=2), CP).ravel())(g)
    assert np.abs(np.asarray(Jd) - np.asarray(model.jacobian(sol, "paddle", CP))).max() < 1e-10


def test_grad_wrt_prescribed_and_material_match_fd(planar):
    model, _ = planar
    g0 = jnp.array([-0.08, 0.05])

    def cp_y(g, alpha, beta):
        s = model.solve({"paddle": g}, steps=2, params={"alpha": alpha, "beta": beta})
        return model.displacement(s, CP)[0, 1]

    grads = jax.grad(cp_y, argnums=(0, 1, 2))(g0, 1.0, 1.0)
    eps = 1e-6
    fd_g = [(cp_y(g0.at[i].add(eps), 1.0, 1.0) - cp_y(g0.at[i].add(-eps), 1.0, 1.0)) / (2 * eps) for i in range(2)]
    fd_a = (cp_y(g0, 1.0 + eps, 1.0) - cp_y(g0, 1.0 - eps, 1.0)) / (2 * eps)
    fd_b = (cp_y(g0, 1.0, 1.0 + eps) - cp_y(g0, 1.0, 1.0 - eps)) / (2 * eps)
    print("grad g", grads[0], fd_g, "alpha", grads[1], fd_a, "beta", grads[2], fd_b)
    assert np.asarray(grads[0]) == pytest.approx(np.asarray(fd_g), rel=1e-6)
    # the material sensitivities are small but must not vanish (the Dirichlet reaction term)
    assert abs(float(grads[1])) > 1e-9 and abs(float(grads[2])) > 1e-9
    assert float(grads[1]) == pytest.approx(float(fd_a), rel=1e-4)
    assert float(grads[2]) == pytest.approx(float(fd_b), rel=1e-4)


def test_grad_of_reaction_wrt_load_path(planar):
    """Reverse mode through solve + reaction (a force objective), checked against FD."""
    model, _ = planar

    def fx(g):
        return model.reaction(model.solve({"paddle": g}, steps=2), "paddle")[0]

    g0 = jnp.array([-0.08, 0.05])
    gr = np.asarray(jax.grad(fx)(g0))
    eps = 1e-6
    fd = [(fx(g0.at[i].add(eps)) - fx(g0.at[i].add(-eps))) / (2 * eps) for i in range(2)]
    assert gr == pytest.approx(np.asarray(fd), rel=1e-6)


def test_control_increment_clamps_and_solves():
    J = jnp.array([[0.3, 0.01], [-0.02, 0.4]])
    e = jnp.array([1e-3, -2e-3])
    step = np.asarray(control_increment(J, e, 1.0, 0.01))
    assert np.asarray(J) @ step == pytest.approx(np.asarray(e), abs=1e-14)
    big = np.asarray(control_increment(J, 100 * e, 1.0, 0.01))
    assert np.abs(big).max() == pytest.approx(0.01)
    # more control coordinates than manipulation ones: least squares
    J3 = jnp.concatenate([J, jnp.array([[0.1, 0.1]])])
    s3 = np.asarray(control_increment(J3, jnp.asarray(np.asarray(J3) @ [0.001, 0.002]), 1.0, 0.01))
    assert s3 == pytest.approx([0.001, 0.002], abs=1e-12)


def test_setpoint_tracking_reaches_waypoint(planar):
    model, _ = planar
    res = track(model, PATHS["setpoint"], "paddle", CP)
    print(res.message, "max waypoint error", res.max_waypoint_error)
    assert res.status == TrackStatus.DONE
    assert res.max_waypoint_error < 1e-4
    assert np.abs(np.diff(res.mp, axis=0)).max() <= 0.01 + 1e-15     # the clamp holds
    # the plant's final state: the control point really is where the tracker says
    final = np.asarray(model.displacement(res.plant_solution, CP))[0]
    assert final == pytest.approx([0.05, 0.05], abs=1e-4)


def test_unreachable_waypoint_stops_with_status_and_history(planar):
    model, _ = planar
    res = track(model, [[0.0, 0.0], [0.02, 0.0], [0.9, 0.0]], "paddle", CP, gain=0.5, max_iter=15)
    assert res.status == TrackStatus.ITERATION_CAP
    assert res.reached[1] > 0 and res.reached[2] == -1
    assert len(res.error) == res.reached[1] + 16
    assert np.isnan(res.waypoint_errors[2])


def test_tracking_step_reuses_one_factorisation(planar):
    """The tracking loop's step: one factorisation at the converged state gives the implicit
    Jacobian and the predictor + chord corrections of the next solve, which lands on the same
    equilibrium as the full Newton solve; a step too big for it is refused."""
    from jaxrkpm.control import ControlledModel

    model, sol = planar
    side = ControlledModel.of(model, "paddle", CP)
    state = jax.jit(lambda p, s: p.factorise(s.u, s.g))(side.problem, sol)
    assert Stability.of(side.problem.stability(state)) == Stability.STABLE
    J = np.asarray(jax.jit(lambda sd, s, st: sd.jacobian(s, st))(side, sol, state))
    assert np.abs(J - np.asarray(model.jacobian(sol, "paddle", CP))).max() < 1e-12 * np.abs(J).max()

    @jax.jit
    def chord(prob, s, st, dmp):
        g1 = s.g + jnp.einsum("a,abi->bi", dmp, side.G)
        return prob.newton(s.u, s.g, g1, s.load, s.load, max_iter=7, state=st, chord=True), g1

    (u, status, its, rn, _), g1 = chord(side.problem, sol, state, jnp.array([0.004, -0.003]))
    ref = model.solve_g(g1, initial=sol, loads=sol.load)
    assert Status.of(status) == Status.CONVERGED and 2 <= int(its) <= 7
    assert np.abs(np.asarray(u - ref.u)).max() < 1e-10
    # half the object's size in one step: the chord iteration must give up (the loop then
    # runs the full Newton path)
    (_, status, *_), _ = chord(side.problem, sol, state, jnp.array([0.5, 0.0]))
    assert Status.of(status) != Status.CONVERGED


def test_tracking_fast_path_with_the_sparse_solver(planar):
    """The sparse solver takes the same fast path as the dense one (one factorisation per
    iteration, chord corrections with it) and tracks the same path."""
    from jaxrkpm import sparse as jsparse

    model, _ = planar
    sparse = jr.Model(model.body, model.material, essential={n: model.set_indices(n) for n in model.set_names},
                      solver="sparse")
    path = PATHS["setpoint"]
    dense_run = track(model, path, "paddle", CP)
    jsparse.reset_stats()
    sparse_run = track(sparse, path, "paddle", CP)
    stats = dict(jsparse.STATS)
    assert sparse_run.status == TrackStatus.DONE
    assert np.abs(sparse_run.cp - dense_run.cp).max() < 1e-8
    assert np.abs(sparse_run.mp - dense_run.mp).max() < 1e-8
    n = len(sparse_run.error) - 1
    # one factorisation per iteration (at the converged state; the loop also takes and
    # discards a step on each waypoint hit) and no full Newton solve: that would add CG
    # solves preconditioned by its first factorisation
    hits = int(np.sum(sparse_run.reached >= 0))
    assert stats["factorisations"] == n + hits and stats["cg_solves"] == 0, stats
    assert np.all(sparse_run.newton[1:] <= 7)
