"""Implicit differentiation of equilibrium: Jacobians, jacfwd/grad through solve, tracking."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrkpm as jr
from jaxrkpm.control.tracking import TrackStatus, control_increment, track
from jaxrkpm.thesis.data import PATHS
from jaxrkpm.solvers.linalg.base import Stability
from jaxrkpm.solvers.results import Status

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


def test_solution_keeps_its_linear_state_where_eager(planar):
    """An eager solve keeps its last factorisation in the Solution; a traced one keeps none
    (it would be stacked or differentiated for nothing)."""
    model, sol = planar
    assert sol.linear is not None
    traced = jax.jit(lambda v: model.solve({"paddle": v}, steps=2))(jnp.array([-0.08, 0.05]))
    assert traced.linear is None
    assert np.abs(np.asarray(traced.u) - np.asarray(sol.u)).max() < 1e-12


def test_jacobian_and_next_solve_from_the_kept_state(planar):
    """The implicit Jacobian refined from the kept factorisation (an iterate next to the
    converged state) equals the one from a factorisation at it; a solve started from a
    Solution that kept its state lands on the same equilibrium as one started from a
    Solution that kept none."""
    model, sol = planar
    bare = sol._replace(linear=None)
    Jk = np.asarray(model.jacobian(sol, "paddle", CP))
    Jb = np.asarray(model.jacobian(bare, "paddle", CP))
    assert np.abs(Jk - Jb).max() < 1e-10 * np.abs(Jb).max()
    g = {"paddle": jnp.array([-0.06, 0.07])}
    nk, nb = model.solve(g, initial=sol), model.solve(g, initial=bare)
    assert nk.status == nb.status == Status.CONVERGED
    assert np.abs(np.asarray(nk.u) - np.asarray(nb.u)).max() < 1e-9


def test_sparse_jacobian_from_the_kept_state_factorises_nothing(planar):
    """With the sparse solver, the Jacobian at a Solution that kept its factorisation costs no
    factorisation (conjugate gradients preconditioned by it), one without costs one (counted
    by the handles the model's factorisation pool gives out: a Jacobian returns no stats)."""
    from jaxrkpm.solvers.linalg import factorisations as jsparse

    model, _ = planar
    sparse = jr.Model(model.body, model.material, essential={n: model.set_indices(n) for n in model.set_names},
                      solver="sparse")
    sol = sparse.solve({"paddle": jnp.array([-0.08, 0.05])}, steps=2)
    assert sol.linear is not None
    pool = jsparse.pool(sparse.linear.system)
    made = pool.next
    Jk = np.asarray(sparse.jacobian(sol, "paddle", CP))
    kept = pool.next - made
    Jb = np.asarray(sparse.jacobian(sol._replace(linear=None), "paddle", CP))
    fresh = pool.next - made - kept
    assert kept == 0 and fresh == 1, (kept, fresh)
    assert np.abs(Jk - Jb).max() < 1e-10 * np.abs(Jb).max()
    with pytest.raises(ValueError, match="rtol"):
        sparse.jacobian(sol, "paddle", CP, rtol=2.0)


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
    from jaxrkpm.control.tracking import ControlledModel

    model, sol = planar
    side = ControlledModel.of(model, "paddle", CP)
    state = jax.jit(lambda sd, s: sd.factorise(s))(side, sol)
    assert Stability.of(side.linear.stability(state)) == Stability.STABLE
    J = np.asarray(jax.jit(lambda sd, s, st: sd.jacobian(s, st))(side, sol, state))
    assert np.abs(J - np.asarray(model.jacobian(sol, "paddle", CP))).max() < 1e-12 * np.abs(J).max()

    @jax.jit
    def chord(prob, s, st, dmp):
        g1 = s.g + jnp.einsum("a,abi->bi", dmp, side.G)
        return side.chord.solve(prob, s.u, s.g, g1, s.load, s.load, st, max_iter=7), g1

    (u, status, its, rn, *_), g1 = chord(side.problem, sol, state, jnp.array([0.004, -0.003]))
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
    model, _ = planar
    sparse = jr.Model(model.body, model.material, essential={n: model.set_indices(n) for n in model.set_names},
                      solver="sparse")
    path = PATHS["setpoint"]
    dense_run = track(model, path, "paddle", CP, reuse=0)   # the dense default keeps factorisations
    sparse_run = track(sparse, path, "paddle", CP)
    stats = sparse_run.stats.as_dict()   # the run's own statistics, returned with it
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


# ------------------------------------------------ kept factorisations across control steps
def test_inverse_and_quasi_newton_solves(planar):
    """DenseSolver(inverse=True) solves K_ff x = b as Cholesky does; QuasiNewton without
    pairs is its base, and with pairs it is symmetric and meets the newest secant equation
    H y = s exactly (L-BFGS), so a pair taken from the true K makes it exact along y."""
    from jaxrkpm.solvers.linalg.dense import DenseSolver
    from jaxrkpm.solvers.linalg.quasi_newton import QuasiNewton

    model, sol = planar
    prob = model.problem()
    blocks = prob.tangent_blocks(sol.u, sol.g)
    K = np.asarray(prob.tangent(sol.u, sol.g))
    n = K.shape[0]
    rng = np.random.default_rng(0)
    b = jnp.asarray(rng.standard_normal((n, 3)))
    inv = DenseSolver(inverse=True)
    x = np.asarray(inv.solve(inv.init(prob, blocks), b))
    assert np.abs(x - np.linalg.solve(K, b)).max() < 1e-9 * np.abs(x).max()
    qn = QuasiNewton(inv, memory=3)
    st = qn.init(prob, blocks)
    assert np.abs(np.asarray(qn.solve(st, b)) - x).max() < 1e-12 * np.abs(x).max()
    A = K + np.diag(rng.uniform(0.1, 1.0, n)) * np.abs(np.diag(K)).max()   # another SPD "tangent"
    for _ in range(4):                       # one more than the memory: the oldest drops out
        s = rng.standard_normal(n)
        st = qn.update(st, jnp.asarray(s), jnp.asarray(A @ s))
    assert int(st.count) == 3
    H = np.asarray(qn.solve(st, jnp.eye(n)))
    assert np.abs(H - H.T).max() < 1e-9 * np.abs(H).max()
    assert np.abs(H @ (A @ s) - s).max() < 1e-9 * np.abs(s).max()
    # a pair without positive curvature is refused (H would lose positive definiteness)
    assert int(qn.update(st, jnp.asarray(s), jnp.asarray(-A @ s)).count) == 3 and \
        np.array_equal(np.asarray(qn.update(st, jnp.asarray(s), jnp.asarray(-A @ s)).S), np.asarray(st.S))


@pytest.mark.slow(reason="chord corrections over two large steps settling onto full Newton; kept "
                         "factorisations are tested in the default run by the tracking and Jacobian tests below")
def test_kept_factorisation_settles_to_full_newton(planar):
    """Control steps that keep the factorisation of an earlier state (quasi-Newton chord
    corrections, ControlledModel.of(reuse=...)) land on full Newton's equilibrium to the
    solver tolerance, without refactorising; the Jacobian from a kept factorisation of the
    same state equals the fresh one, and from one two steps old, refined, too."""
    from jaxrkpm.control.tracking import ControlledModel
    from jaxrkpm.solvers.results import Limits

    model, sol = planar
    side = ControlledModel.of(model, "paddle", CP, reuse=0.5)
    assert side.keeps and side.linear.name == "quasi-newton"
    lim = Limits.of(steps=1)
    state0 = jax.jit(lambda sd, s: sd.factorise(s))(side, sol)
    jac = jax.jit(lambda sd, s, st: sd.jacobian(s, st))
    J0 = np.asarray(jac(side, sol, state0))
    fresh = np.asarray(model.jacobian(sol, "paddle", CP))
    assert np.abs(J0 - fresh).max() < 1e-10 * np.abs(fresh).max()

    settle = jax.jit(lambda sd, s, st, g1: sd.settle(s, st, g1, lim, 6))
    s, state = sol, state0
    for dmp in ([0.01, -0.005], [0.01, 0.005]):
        g1 = s.g + jnp.einsum("a,abi->bi", jnp.array(dmp), side.G)
        s, state = settle(side, s, state, g1)
        assert Status.of(s.status) == Status.CONVERGED
    # no refactorisation: the base is still the factorisation at the start; pairs were learnt
    assert np.array_equal(np.asarray(state.base.Linv), np.asarray(state0.base.Linv)) and int(state.count) > 0
    ref = model.solve_g(s.g, initial=sol, loads=sol.load, reuse=0)   # full Newton, fresh tangents
    assert np.abs(np.asarray(s.u - ref.u)).max() < 1e-9 * np.abs(np.asarray(ref.u)).max()
    prob = model.problem()
    assert float(jnp.linalg.norm(prob.residual(s.u, s.g))) <= 1e-10 * float(prob.force_scale(prob.energy_residual(s.u, s.g)[3]))
    # from the factorisation two (large: 0.01 of a unit square) steps old, with the secant
    # pairs of the last step's corrections: refined with exact products to the Jacobian of
    # this state, to jacobian_rtol (unrefined it is 11% off here, measured)
    J = np.asarray(jac(side, s, state))
    Jref = np.asarray(model.jacobian(s, "paddle", CP))
    print("refined Jacobian, relative error", np.abs(J - Jref).max() / np.abs(Jref).max())
    assert np.abs(J - Jref).max() < 10 * side.jacobian_rtol * np.abs(Jref).max()
    unrefined = ControlledModel(side.problem, side.G, side.idx, side.psi, side.driver, side.chord, jacobian_rtol=0.0)
    stale = np.asarray(jax.jit(lambda sd, st: sd.jacobian(s, st))(unrefined, state))
    assert np.abs(stale - Jref).max() > 1e-3 * np.abs(Jref).max()     # refinement did the work
    # the response predicts a move to first order (Tracker.move passes it to settle): from it
    # the stale factorisation's chord needs fewer corrections than from its own predictor,
    # and lands on the same equilibrium
    dmp = jnp.array([0.002, 0.001])
    g1 = s.g + jnp.einsum("a,abi->bi", dmp, side.G)
    du = jax.jit(lambda sd, s, st: sd.response(s, st))(side, s, state)
    own, _ = settle(side, s, state, g1)
    predicted, _ = jax.jit(lambda sd, s, st, g1, du: sd.settle(s, st, g1, lim, 6, du))(
        side, s, state, g1, jnp.einsum("a,aij->ij", dmp, du))
    assert Status.of(predicted.status) == Status.CONVERGED == Status.of(own.status)
    print("chord iterations from the response / own predictor", int(predicted.iterations), int(own.iterations))
    assert int(predicted.iterations) < int(own.iterations)
    assert np.abs(np.asarray(predicted.u - own.u)).max() < 1e-9 * np.abs(np.asarray(own.u)).max()


def test_second_order_prediction_along_a_straight_move(planar):
    """response_trend and predicted_change: with the response at the state before the last
    move, a move along the same line changes the free coefficients as predicted to second
    order (the error falls as the move cubed; the first-order prediction's as its square), and
    the response as predicted to first order (the error falls as the move squared; taking the
    last response as it is: as the move). A move across the last one, or a last response that
    is not finite, gets no trend."""
    from jaxrkpm.control.tracking import ControlledModel, predicted_change, response_trend

    model, sol = planar
    side = ControlledModel.of(model, "paddle", CP)
    response = jax.jit(lambda sd, s: sd.response(s, sd.factorise(s)))
    errors = []
    for h in (0.01, 0.005):
        move = h * jnp.array([1.0, -0.5])
        at = lambda k: model.solve_g(sol.g + k * jnp.einsum("a,abi->bi", move, side.G), initial=sol,
                                     loads=sol.load)
        s1, s2 = at(1), at(2)
        du0, du1, du2 = response(side, sol), response(side, s1), response(side, s2)
        trend = response_trend(du1, move, du0, move)
        change = np.asarray(s2.u - s1.u)
        errors.append([np.abs(np.asarray(predicted_change(du1, move)) - change).max(),
                       np.abs(np.asarray(predicted_change(du1, move, trend)) - change).max(),
                       np.abs(np.asarray(du1 - du2)).max(), np.abs(np.asarray(du1 + trend - du2)).max()])
    a, b = np.array(errors)
    print("errors at moves 0.01 and 0.005 (change: first, second order; response: last, with trend):", a, b)
    order = np.log2(a / b)
    assert a[1] < 0.2 * a[0] and a[3] < 0.2 * a[2]
    assert 1.6 < order[0] < 2.4 and order[1] > 2.6      # the change: move^2, move^3
    assert 0.6 < order[2] < 1.4 and order[3] > 1.6      # the response: move, move^2
    zero = np.zeros_like(np.asarray(du1))
    across = jnp.array([0.005, 0.01])                    # orthogonal to the last move
    assert np.array_equal(np.asarray(response_trend(du1, across, du0, move)), zero)
    assert np.array_equal(np.asarray(response_trend(du1, move, du0 * jnp.nan, move)), zero)
    assert np.array_equal(np.asarray(response_trend(du1, move, du0, jnp.zeros(2))), zero)


def test_tracking_with_kept_factorisations_reaches_the_waypoints(planar):
    model, _ = planar
    kept = track(model, PATHS["setpoint"], "paddle", CP, reuse=0.5)
    assert kept.status == TrackStatus.DONE
    assert kept.max_waypoint_error < 1e-4
    # the dense path's default (reuse=None) keeps factorisations; factorising at every step
    # (reuse=0) reaches each waypoint at the same iteration, at the same place to the tolerances
    default, every = track(model, PATHS["setpoint"], "paddle", CP), \
        track(model, PATHS["setpoint"], "paddle", CP, reuse=0)
    assert np.array_equal(default.reached, kept.reached) and np.array_equal(every.reached, kept.reached)
    assert np.abs(np.asarray(every.achieved) - np.asarray(kept.achieved)).max() < 1e-8
    with pytest.raises(ValueError, match="reuse"):
        track(model, PATHS["setpoint"], "paddle", CP, reuse=1.5)


def vmapped_solves(solver, Ks, b, rtol):
    """``solver``'s factorisation and solve of each matrix of Ks with the right-hand sides
    b, per member under vmap, each equal to numpy's solve to ``rtol``: the solutions."""
    def solve(K, b):
        return solver.solve(solver.factorise(K), b)

    xs = np.asarray(jax.vmap(solve)(jnp.asarray(np.stack(Ks)), jnp.asarray(np.stack([b] * len(Ks)))))
    for k, M in enumerate(Ks):
        ref = np.linalg.solve(M, b)
        assert np.abs(xs[k] - ref).max() < rtol * np.abs(ref).max(), k
    return xs


@pytest.mark.parametrize("n", [5, 300])
def test_blocked_triangular_solves_equal_a_dense_solve(n):
    """DenseSolver's block substitution (``triangular_pair``: row blocks of L^T and inverted
    diagonal blocks, products only) solves K x = b as numpy does, for sizes below, at and past
    one block (a partial last block), several right-hand sides, and per member under vmap;
    where K is not positive definite the LU fallback still solves it."""
    from jaxrkpm.solvers.linalg import dense as linear

    rng = np.random.default_rng(n)
    A = rng.standard_normal((n, n))
    K = A @ A.T / n + np.eye(n)
    b = rng.standard_normal((n, 2))
    L = jnp.linalg.cholesky(jnp.asarray(K))
    rows = linear.factor_blocks(L, 128)
    assert len(rows) == -(-n // 128)
    x = np.asarray(linear.triangular_pair(rows, linear.blocked_inverses(rows, 128), jnp.asarray(b)))
    assert np.abs(x - np.linalg.solve(K, b)).max() < 1e-10 * np.abs(x).max()

    # through the solver's state, as Newton calls it; SPD and indefinite
    vmapped_solves(linear.DenseSolver(block=128), [K, K - 2 * np.eye(n) * np.linalg.eigvalsh(K)[0] - np.eye(n) * 0.5], b, 1e-9)


@pytest.mark.parametrize("n", [40, 300])
def test_kept_inverse_solves_several_columns_as_a_dense_solve(n):
    """DenseSolver(inverse=True) with three right-hand sides (column by column up to
    ``block`` rows, one product past it) solves K x = b as numpy does, past a
    critical point too (K^-1 by LU there), per member under vmap, and a column alone gives
    the same column."""
    from jaxrkpm.solvers.linalg import dense as linear

    rng = np.random.default_rng(n)
    A = rng.standard_normal((n, n))
    K = A @ A.T / n + np.eye(n)
    Kind = K - 2 * np.eye(n) * np.linalg.eigvalsh(K)[0] - np.eye(n) * 0.5
    b = rng.standard_normal((n, 3))
    dense = linear.DenseSolver(inverse=True)
    xs = vmapped_solves(dense, [K, Kind], b, 1e-9)
    one = np.asarray(dense.solve(dense.factorise(jnp.asarray(K)), jnp.asarray(b[:, 1:2])))
    assert np.abs(one - xs[0][:, 1:2]).max() < 1e-12 * np.abs(one).max()


@pytest.mark.parametrize("inverse", [False, True])
def test_mixed_precision_solves_to_double_accuracy(inverse):
    """DenseSolver(mixed=True): a single-precision factorisation whose solves are refined in
    double reaches double accuracy (unrefined it is ~1e-5 off at this conditioning), per member
    under vmap, with the LU fallback where K is indefinite; where single precision cannot
    factorise an SPD K (an eigenvalue below its resolution), double does, and the inertia is
    the double one."""
    from jaxrkpm.solvers.linalg import dense as linear

    n = 300
    rng = np.random.default_rng(7)
    Q = np.linalg.qr(rng.standard_normal((n, n)))[0]
    lam = np.geomspace(1e-3, 1.0, n)
    K = (Q * lam) @ Q.T                                            # cond 1e3, as a 3D tangent
    Kind = (Q * np.where(np.arange(n) < 3, -lam, lam)) @ Q.T       # three negative eigenvalues
    b = rng.standard_normal((n, 2))
    mixed = linear.DenseSolver(inverse=inverse, mixed=True, block=128)

    vmapped_solves(mixed, [K, Kind], b, 1e-11)
    state = mixed.factorise(jnp.asarray(K))
    assert (state.Linv if inverse else state.rows[0]).dtype == jnp.float32
    assert Stability.of(mixed.stability(state)) == Stability.STABLE
    assert Stability.of(mixed.stability(mixed.factorise(jnp.asarray(Kind)))) == Stability.UNSTABLE
    # refinement does the work: one single-precision solve alone is far from double accuracy
    once = linear.DenseSolver(inverse=inverse, mixed=True, block=128, refinements=0)
    x0 = np.asarray(once.solve(once.factorise(jnp.asarray(K)), jnp.asarray(b)))
    assert np.abs(x0 - np.linalg.solve(K, b)).max() > 1e-8 * np.abs(x0).max()

    # 1 - 1e-9 rounds to 1 in single precision: [[1, 1 - 1e-9], [1 - 1e-9, 1]] is singular
    # there and positive definite in double (eigenvalues 1e-9 and 2)
    S = np.eye(4)
    S[:2, :2] = [[1.0, 1 - 1e-9], [1 - 1e-9, 1.0]]
    L32 = np.asarray(jnp.linalg.cholesky(jnp.asarray(S, jnp.float32)))
    assert not (np.all(np.isfinite(L32)) and np.all(L32.diagonal() > 0))   # single: no factor
    L, spd = mixed.factor(jnp.asarray(S))
    assert bool(spd) and L.dtype == jnp.float32
