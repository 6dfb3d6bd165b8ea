"""Tracking with a contact tool (``jr.track(model, path, "ball", ...)``, issue 36): the tool's
position is the manipulation point; each reached state is the equilibrium solved directly at
that pose, the loop's Jacobian is the implicit derivative in the tool's position, and a
waypoint that needs the tool to pull is not reached (a push-only tool)."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxrkpm as jr
from jaxrkpm.control.tracking import ControlledModel, TrackStatus, track

GAP = 4e-3
MAT = jr.NeoHookean(lam=1.0, mu=1.0)
CP = np.array([[0.5, 1.0]])             # the top centre of the block
PRESS = 0.03                           # the ball's indentation at the start
# one compiled loop for every run of this module (the Tracker's settings are static); one
# factorisation per iteration (reuse=0), the loop that compiles fastest
SETTINGS = dict(gain=0.5, clamp=1e-3, tol=1e-5, max_iter=200, max_steps=400, window=20, reuse=0)
SOLVE = dict(steps=2, rtol=1e-12)       # every direct solve of the module: one compiled solve


@pytest.fixture(scope="module")
def pushed():
    """A 1 x 1 block (SCNI, 7 x 7 particles), its bottom held, pressed at the top centre by a
    rigid frictionless disc moved in by ``PRESS`` (the start of the runs)."""
    body = jr.Body.grid((7, 7), 1.0 / 6)
    ball = jr.Contact(jr.Sphere(0.5), position=(0.5, 1.5 + 2 * GAP), gap=GAP, pressure=0.1, name="ball",
                      where=lambda X: X[:, 1] > 1 - 1e-9)
    model = jr.Model(body, MAT, integration="scni", essential={"bottom": body.select(lambda X: X[:, 1] < 1e-9)},
                     terms=[ball])
    params = {"ball": {"position": jnp.array([0.5, 1.5 + 2 * GAP - PRESS])}}
    start = model.solve(params=params, **SOLVE)
    return model, params, start


def at(pos):
    return {"ball": {"position": jnp.asarray(pos)}}


def test_push_tracking_reaches_equilibria(pushed):
    model, params, start = pushed
    cp0 = np.asarray(model.displacement(start, CP)).ravel()
    path = [cp0 + [0.0, -0.01], cp0 + [0.0, -0.02]]
    res = track(model, path, "ball", CP, params=params, initial=start, **SETTINGS)
    print(res.message)
    assert res.status == TrackStatus.DONE and np.all(res.reached > 0)
    assert np.all(res.solve_status == 0) and res.max_waypoint_error < SETTINGS["tol"]
    pos = res.tool_position
    assert pos.shape == (len(res.mp), 2) and np.allclose(pos[0], params["ball"]["position"])
    # each reached state is the equilibrium solved directly (from the unloaded block) at the
    # tool's position there
    errs = []
    for i, k in enumerate(res.reached):
        direct = model.solve(params=at(pos[k]), **SOLVE)
        errs.append(np.abs(np.asarray(model.displacement(direct, CP)).ravel() - res.achieved[i]).max())
    final = model.solve(params=at(pos[-1]), **SOLVE)
    u_err = np.abs(np.asarray(res.controller_solution.u - final.u)).max()
    print(f"tool moved {pos[-1] - pos[0]}, control point error to the direct solves {max(errs):.2e}, "
          f"final state {u_err:.2e}; iterations per waypoint {np.diff([0, *res.reached]).tolist()}")
    assert max(errs) < 1e-8 and u_err < 1e-8
    # the ball pushed down: it moved down, and only down (a symmetric push)
    assert pos[-1, 1] < pos[0, 1] - 0.015 and abs(pos[-1, 0] - pos[0, 0]) < 1e-8


def test_loop_jacobian_against_differences(pushed):
    model, params, start = pushed
    side = ControlledModel.of(model, "ball", CP, params)
    # the loop's Jacobian: the tool's response from the factorisation at the state
    J = np.asarray(jax.jit(lambda sd, s: sd.jacobian(s, sd.factorise(s)))(side, start))
    pos = np.asarray(params["ball"]["position"])
    eps = 1e-5
    fd = np.stack([(np.asarray(model.displacement(model.solve(params=at(pos + e), initial=start, rtol=1e-12), CP))
                    - np.asarray(model.displacement(model.solve(params=at(pos - e), initial=start, rtol=1e-12),
                                                    CP))).ravel() / (2 * eps) for e in eps * np.eye(2)], 1)
    err = np.abs(J - fd).max() / np.abs(J).max()
    print(f"J = dCP/d(ball position) {J.tolist()}, relative difference to central FD {err:.2e}")
    assert J[1, 1] > 0.3 and err < 1e-6


def test_a_push_only_tool_cannot_pull(pushed):
    model, params, start = pushed
    cp0 = np.asarray(model.displacement(start, CP)).ravel()
    # the first waypoint is a push; the second lifts the top above its unloaded height: the
    # block would have to follow the tool away
    res = track(model, [cp0 + [0.0, -0.01], [0.0, 0.02]], "ball", CP, params=params, initial=start, **SETTINGS)
    print(res.message, f"highest control point {res.cp[:, 1].max():.2e}")
    assert res.status in (TrackStatus.NO_PROGRESS, TrackStatus.ITERATION_CAP)
    assert res.reached[0] > 0 and res.reached[1] == -1 and np.all(res.solve_status == 0)
    # the tool went up and left the block (its lowest point above the undeformed top), which
    # came back to rest: the top never higher than unloaded, and the tool stopped there
    pos = res.tool_position
    assert pos[-1, 1] - 0.5 > 1.0 and res.cp[:, 1].max() < 1e-9
    assert np.abs(pos[-SETTINGS["window"]:] - pos[-1]).max() == 0
    # jitted: its eager evaluation compiles op by op, slower than the whole
    contact = jax.jit(lambda sol, p: jr.contact_forces(model, sol, "ball", at(p)))(res.controller_solution, pos[-1])
    assert not np.any(np.asarray(contact.active)) and float(contact.min_gap) > GAP


def test_bad_driven_names_both_kinds(pushed):
    model, params, start = pushed
    with pytest.raises(ValueError, match=r"essential set.*\['bottom'\].*Contact.*\['ball'\]"):
        track(model, [[0.0, 0.0]], "paddle", CP, params=params)
    with pytest.raises(ValueError, match="frictionless"):
        track(model, [[0.0, 0.0]], "ball", CP, params={"ball": {**params["ball"], "mu": 0.3}})
    with pytest.raises(ValueError, match="loads=1"):
        track(model, [[0.0, 0.0]], "ball", CP, params=params, initial=model.initial())
    with pytest.raises(ValueError, match="both"):
        track(model, [[0.0, 0.0]], "ball", CP, params=params, initial=start, plant=model, plant_driven="bottom")
