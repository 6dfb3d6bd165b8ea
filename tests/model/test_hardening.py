"""Hostile input to the library API (issue 18): every case fails well, with a named error
(type and a word of the message), a status that tells the truth, or a result that is right.

One small block model (5x5, Fung) is shared by the module; most cases raise at construction
and compile nothing."""
import inspect
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrkpm as jr
from jaxrkpm.thesis import needle as nd
from jaxrkpm.control.tracking import track
from jaxrkpm.solvers.results import Limits, Status
from jaxrkpm.solvers.implicit import solve_path_jit
from jaxrkpm.thesis.scenarios import planar_square
from tests.problems import FUNG, block, unit_grid

POINT = [[0.5, 0.5]]


@pytest.fixture(scope="module")
def blk():
    """(body, sets, model) of the 5x5 block: left edge "wall" held, right edge "right" driven."""
    return block(5)


@pytest.fixture(scope="module")
def small():
    """A 3x3 block: a model of other shapes than ``blk``'s (built, never solved)."""
    return block(3)[2]


# ------------------------------------------------------------------------------ hangs
def test_needle_insert_has_no_deadlocking_chunk_parameter():
    """``chunk`` vmapped configurations and deadlocked XLA:CPU: the parameter is gone, and
    passing it fails at once instead of hanging."""
    assert "chunk" not in inspect.signature(nd.insert).parameters
    t0 = time.monotonic()
    with pytest.raises(TypeError, match="chunk"):
        nd.insert([], [0.1], (0.5, 0.4), chunk=5)
    assert time.monotonic() - t0 < 5.0


def test_tiny_load_step_converges_to_the_linear_response(blk):
    """No absolute floor in the convergence test made a 1e-9 increment (steps=10**6 of an
    ordinary move) end in MAX_ITERATIONS at 0%: it converges now, to the linearised answer."""
    _, _, model = blk
    amp = 1e-9
    sol = model.solve({"right": [amp, 0.0]})
    assert sol.outcome == Status.CONVERGED and float(sol.t) == 1.0
    u = np.asarray(model.displacement(sol, POINT)).ravel()
    J = np.asarray(model.jacobian(model.initial(), "right", POINT))      # d u(point) / d g_right
    np.testing.assert_allclose(u, amp * J[:, 0], rtol=1e-6, atol=1e-6 * amp)


def test_steps_are_bounded(blk):
    _, _, model = blk
    with pytest.raises(ValueError, match=f"steps must lie in 1..{Limits.most_steps}"):
        model.solve({"right": [0.05, 0.0]}, steps=10**6)
    with pytest.raises(TypeError, match="steps must be an int"):
        model.solve({"right": [0.05, 0.0]}, steps=2.5)


# ------------------------------------------------------------- silent wrong results
def test_nan_prescribed_value_is_named_and_never_kept(blk):
    _, _, model = blk
    g = model.prescribed({"right": [0.05, 0.0]}).at[0, 0].set(jnp.nan)
    with pytest.raises(ValueError, match="non-finite prescribed values"):
        model.solve_g(g, throw=False)
    # where no check can run (the solver core, as under jit/vmap) the failed solve keeps the
    # last converged state: g0 exactly, not g0 + 0 * NaN
    start = model.initial()
    sol = solve_path_jit(model.solver(), model.problem(), Limits.of(), start.u, start.g, g, start.load, start.load)
    assert Status.of(sol.status) == Status.NONFINITE and float(sol.t) == 0.0
    assert np.array_equal(np.asarray(sol.g), np.asarray(start.g))
    assert np.all(np.isfinite(np.asarray(model.displacement(sol, POINT))))


def test_derivative_through_a_failed_solve(blk):
    """jacfwd / grad through a failed solve: SolveError (not a tracer error); with
    throw=False the derivative is NaN, never the finite derivative of the kept state."""
    _, _, model = blk
    g = model.prescribed({"right": [0.05, 0.0]})
    failing = dict(max_iter=1, max_cuts=0)        # one Newton iteration cannot converge
    with pytest.raises(jr.SolveError, match="MAX_ITERATIONS") as err:
        jax.jacfwd(lambda g: model.displacement(model.solve_g(g, **failing), POINT))(g)
    assert isinstance(err.value.solution.u, np.ndarray)          # concrete, not a tracer
    with pytest.raises(jr.SolveError, match="MAX_ITERATIONS"):
        jax.grad(lambda g: jnp.sum(model.solve_g(g, **failing).u))(g)
    J = jax.jacfwd(lambda g: model.solve_g(g, throw=False, **failing).u)(g)
    assert np.all(np.isnan(np.asarray(J)))
    dg = jax.grad(lambda g: jnp.sum(model.solve_g(g, throw=False, **failing).u))(g)
    assert np.all(np.isnan(np.asarray(dg)))
    ok = jax.jacfwd(lambda g: model.solve_g(g).u)(g)              # converged: finite
    assert np.all(np.isfinite(np.asarray(ok))) and np.abs(np.asarray(ok)).max() > 0


def test_float_indices_and_grid_counts_are_not_truncated():
    body = unit_grid(5)
    with pytest.raises(TypeError, match="integer particle indices"):
        jr.Model(body, FUNG, essential={"w": np.array([0.0, 1.7, 2.2])})
    with pytest.raises(TypeError, match="whole particle counts"):
        jr.Body.grid((2.7, 3.9), 0.1)


# ------------------------------------------------------------ raw crashes -> named
def test_solution_or_g_of_another_model(blk, small):
    _, _, model = blk
    other = small.initial()
    with pytest.raises(ValueError, match="does not belong to this model"):
        model.displacement(other, POINT)
    with pytest.raises(ValueError, match="does not belong to this model"):
        model.jacobian(other, "right", POINT)
    with pytest.raises(ValueError, match="initial does not belong"):
        model.solve({"right": [0.01, 0.0]}, initial=other)
    with pytest.raises(ValueError, match=r"g has shape \(3, 2\)"):
        model.solve_g(jnp.zeros((3, 2)))


@pytest.mark.parametrize("call", ["displacement", "stress", "jacobian"])
def test_empty_point_arrays(blk, call):
    _, _, model = blk
    sol, none = model.initial(), np.zeros((0, 2))
    fn = {"displacement": lambda: model.displacement(sol, none), "stress": lambda: model.stress(sol, none),
          "jacobian": lambda: model.jacobian(sol, "right", none)}[call]
    with pytest.raises(ValueError, match="no points given"):
        fn()


@pytest.mark.parametrize("make, error, word", [
    (lambda: jr.Material(lambda E, p: E.ravel(), {}), ValueError, "must return a scalar"),
    (lambda: jr.Material(lambda E, p: p["mu"] * jnp.sum(E * E), {"alpha": 1.0}), ValueError, "'mu'"),
    (lambda: jr.Material(None, {}), TypeError, "W must be a strain energy"),
    (lambda: jr.Material(lambda E, p: float(E[0, 0]) ** 2, {}), ValueError, "Concretization"),
    (lambda: jr.Fung(A=np.eye(2)), ValueError, r"shape \(2, 2, 2, 2\)"),
    (lambda: jr.Material(lambda E, p: jnp.sum(E * E), [1.0]), TypeError, "params must be a dict"),
])
def test_bad_materials_fail_at_construction(make, error, word):
    with pytest.raises(error, match=word):
        make()


def test_material_checked_for_the_model_dimension():
    """A 3D Fung tensor is a valid material, but not for a 2D body: named at Model()."""
    mat = jr.Fung(A=jr.fung_tensor(3, 1020.0, 254.0, 383.0))
    with pytest.raises(ValueError, match=r"A must be .* shape \(2, 2, 2, 2\) for a 2D body"):
        block(3, material=mat)


def test_body_builder_arguments():
    with pytest.raises(TypeError, match="spacing must be a positive number"):
        jr.Body.grid((3, 3), "0.1")
    with pytest.raises(ValueError, match="origin must be finite"):
        jr.Body.grid((3, 3), 0.1, origin=[np.nan, 0.0])


def test_model_arguments():
    body = unit_grid(5)
    with pytest.raises(TypeError, match="essential must be a dict"):
        jr.Model(body, FUNG, essential=[0, 1, 2])


def test_malformed_prescribed_values(blk):
    _, _, model = blk
    with pytest.raises(ValueError, match="prescribed value for 'right' must be numbers"):
        model.prescribed({"right": [[0.1, 0.0], [0.2]]})
    with pytest.raises(ValueError, match="prescribed value for 'right' must be numbers"):
        model.prescribed({"right": ["a", "b"]})


def test_static_sweep_paddle_indices():
    phantom = nd.Phantom()
    with pytest.raises(ValueError, match="paddles is empty"):
        nd.static_sweep(phantom, paddles=[])
    with pytest.raises(TypeError, match="1-based int index"):
        nd.static_sweep(phantom, paddles=[1.5])


# -------------------------------------------------------------- misleading statuses
def test_unconstrained_solve_and_oversized_support_named():
    """No essential set and no springs: the model builds (its tangent's rigid-body modes are
    worth studying) but a solve is refused by name, not NONFINITE / UNSTABLE_TANGENT."""
    free = jr.Model(unit_grid(5), FUNG, body_force=[0.0, -0.1])
    with pytest.raises(ValueError, match="unconstrained: rigid-body modes"):
        free.solve()
    with pytest.raises(ValueError, match="support 100 .* diameter"):
        block(5, support=100)


def test_nan_solver_setting_named(blk):
    _, _, model = blk
    with pytest.raises(ValueError, match="rtol must be a positive number"):
        model.solve({"right": [0.01, 0.0]}, rtol=float("nan"))


@pytest.mark.parametrize("kw, word", [
    (dict(path=[[np.nan, 0.0]]), "non-finite waypoints"),
    (dict(damping=np.nan), "damping must be a finite"),
    (dict(max_steps=0), "max_steps must be an int >= 1"),
    (dict(window=0), "window must be an int >= 1"),
])
def test_track_arguments(kw, word):
    kw = {"path": [[0.01, 0.0]], **kw}
    with pytest.raises(ValueError, match=word):
        track(planar_square(5), kw.pop("path"), "paddle", POINT, **kw)


def test_track_history_keeps_only_converged_states():
    """A paddle move that cannot be solved ends the run with SOLVE_FAILED; the history's
    last row holds the last converged state (with the failed solve's status), not the
    attempted, unbalanced paddle position."""
    model = planar_square(5)
    res = track(model, [[-0.45, 0.0]], "paddle", POINT, gain=1.0, clamp=0.4, max_steps=10)
    assert res.status.name == "SOLVE_FAILED"
    assert res.solve_status[-1] != Status.CONVERGED
    paddle_g = np.asarray(res.controller_solution.g)[model.sets.slices["paddle"]][0]
    np.testing.assert_array_equal(res.mp[-1], paddle_g)          # the kept (converged) paddle
    np.testing.assert_array_equal(res.cp[-1], res.cp[-2])
    assert res.error[-1] == pytest.approx(np.linalg.norm(res.desired[0] - res.cp[-1]))


@pytest.mark.parametrize("vertices, word", [
    ([[0, 0], [1, 1], [1, 0], [0, 1]], "self-intersecting"),
    ([[0, 0], [1, 0], [1, 0], [1, 1], [0, 1]], "repeats vertex"),
    ([[0, 0], [2, 0], [2, 2], [1, 0], [0, 2]], "self-intersecting"),   # touches an edge
])
def test_non_simple_polygon_named(vertices, word):
    with pytest.raises(ValueError, match=word):
        jr.Body.polygon(vertices, 0.1)
