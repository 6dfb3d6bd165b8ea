"""Several push-only tools on the 2D needle phantom (issue 50): the concave probe, the
frictional solve that settles every tool's lag, the path derivatives of the final deviation
against finite differences, the continuation term where a tool lets go, the closed loop's QP,
and every contact force compressive and in the cone (one increment: the studies' shape;
experiments/needle_tools.py has the measured table)."""
import numpy as np
import pytest

import jaxrkpm as jr
from jaxrkpm.control.friction import LagStatus, solve_frictional
from jaxrkpm.thesis import contact_paddle as cp
from jaxrkpm.thesis import needle as nd
from jaxrkpm.thesis import tools as tl

pytestmark = pytest.mark.xla_optimised

INCREMENTS = 1
ONE = (tl.Tool("right"),)


@pytest.fixture(scope="module")
def phantom():
    return nd.Phantom()


@pytest.fixture(scope="module")
def frictionless(phantom):
    """One paddle on the right edge at the target's height, 0.6 spacings in, frictionless."""
    spec = cp.ContactPaddle(mu=0.0)
    c = tl.rest_control(phantom, ONE, spec, depth=0.6 * phantom.spacing)
    return spec, c, tl.insertion(phantom, ONE, c, "none", INCREMENTS, spec)


def test_arc_is_a_concave_probe():
    """The cup's apex is on its surface's inner side at -thickness, its ends stand ``sag``
    below the apex, and a point under the middle of its mouth is outside it (concave)."""
    arc = jr.Arc(0.2, np.pi / 4, 0.02)
    assert np.isclose(float(arc.sdf(np.zeros((1, 2)))[0]), -0.02)
    end = np.array([[0.2 * np.sin(np.pi / 4), -arc.sag]])
    assert abs(float(arc.sdf(end)[0]) + 0.02) < 1e-12
    assert float(arc.sdf(np.array([[0.0, -0.5 * arc.sag]]))[0]) > 0
    with pytest.raises(ValueError, match="half_angle"):
        jr.Arc(0.2, 2.0, 0.01)
    jr.Contact(arc, position=(0.0, 2.0))      # a shape Contact accepts


def test_tools_validate_their_input(phantom):
    with pytest.raises(ValueError, match="unknown skin site"):
        tl.Tool("bottom")
    with pytest.raises(ValueError, match="tools must be one of"):
        tl.default_tools(4)
    with pytest.raises(ValueError, match="outside the bounds"):
        tl.insertion(phantom, ONE, [[0.4, 0.5]], "none", 1)
    lo, hi = tl.bounds(phantom, tl.default_tools(3))
    assert np.all(lo < hi) and np.all(hi[:, 1] <= tl.MAX_DEPTH * phantom.spacing)


def test_frictionless_gradient_matches_finite_differences(phantom, frictionless):
    """d(final deviation)/d(position, depth) by implicit differentiation against central
    differences of whole insertions (the contact set stays the same over the step)."""
    spec, c, run = frictionless
    assert run.converged and run.contact_ok and all(run.in_contact)
    lat, J, gaps, _ = tl.final_gradient(phantom, ONE, run, "none", spec)
    assert np.isclose(lat[0], run.final, rtol=0, atol=1e-12)
    eps = 1e-6
    for k, rtol in ((1, 1e-6), (0, 1e-5)):
        cp_, cm = c.copy().reshape(-1), c.copy().reshape(-1)
        cp_[k] += eps
        cm[k] -= eps
        fd = (tl.insertion(phantom, ONE, cp_.reshape(1, 2), "none", INCREMENTS, spec).final
              - tl.insertion(phantom, ONE, cm.reshape(1, 2), "none", INCREMENTS, spec).final) / (2 * eps)
        assert abs(fd - J[0, k]) <= rtol * abs(J[0, k]), (k, fd, J[0, k])
    # pressing the paddle in pushes the target back towards the needle line
    assert run.final > 0 and J[0, 1] < 0


@pytest.mark.slow(reason="five frictional insertions for the derivative with the lag replayed; the "
                         "frictionless one checks the same path derivative against differences in the "
                         "default run, and the suite keeps its time")
def test_frictional_gradient_matches_finite_differences(phantom):
    """With friction (mu 0.3), the path derivative with the lag's fixed point replayed (30
    sweeps per increment) against central differences of whole insertions."""
    spec = cp.ContactPaddle(mu=0.3)
    c = tl.rest_control(phantom, ONE, spec, depth=0.6 * phantom.spacing)
    run = tl.insertion(phantom, ONE, c, "none", INCREMENTS, spec)
    assert run.converged and all(s == LagStatus.SETTLED for s in run.lag_status)
    J = tl.final_gradient(phantom, ONE, run, "none", spec, lag_sweeps=30)[1]
    eps = 1e-6
    # along the edge, the rounded edge's seam and the lag's tolerance (1e-6) both show
    for k, rtol in ((1, 1e-6), (0, 1e-4)):
        a, b = c.copy().reshape(-1), c.copy().reshape(-1)
        a[k] += eps
        b[k] -= eps
        fd = (tl.insertion(phantom, ONE, a.reshape(1, 2), "none", INCREMENTS, spec).final
              - tl.insertion(phantom, ONE, b.reshape(1, 2), "none", INCREMENTS, spec).final) / (2 * eps)
        assert abs(fd - J[0, k]) <= rtol * abs(J[0, k]), (k, fd, J[0, k])


def test_continuation_presses_a_lost_tool_back(phantom):
    """A paddle on the left edge at depth 0 lets go as the needle pushes the tissue away: the
    deviation no longer depends on its pose, the continuation term's gradient does, and a
    step against it lowers the objective."""
    spec = cp.ContactPaddle(mu=0.0)
    tools = (tl.Tool("left"),)
    c = tl.rest_control(phantom, tools, spec, depth=0.0)
    v, g, run = tl.objective(phantom, tools, c, "none", INCREMENTS, spec, scale=0.07)
    lat, J, gaps, Jg = tl.final_gradient(phantom, tools, run, "none", spec)
    assert not any(run.in_contact) and np.all(np.abs(J) < 1e-12)
    assert g[0, 1] < 0                   # descent presses it in
    step = c - 0.2 * phantom.spacing * g / np.max(np.abs(g))
    assert tl.objective(phantom, tools, step, "none", INCREMENTS, spec, scale=0.07)[0] < v


def test_frictional_solve_equals_the_stepper(phantom):
    """solve_frictional on the contact paddle's model settles to the thesis Stepper's state."""
    spec = cp.ContactPaddle(mu=0.8, lag_tol=1e-8, lag_iterations=200)
    model = cp.contact_model(phantom, "none", 3, spec)
    st = cp.Stepper(phantom, model, 3, spec)
    control = [phantom.spacing, 0.0]
    sol, lag, _ = st.step({"needle": np.zeros(2)}, control, None, None, steps=spec.press_steps)
    fs = solve_frictional(model, {"needle": np.zeros(2)}, params=st.params(control, None), steps=spec.press_steps,
                          tol=1e-8, max_lag=200)
    assert fs.status == LagStatus.SETTLED and fs.iterations > 0
    np.testing.assert_allclose(np.asarray(fs.solution.u), np.asarray(sol.u), rtol=0, atol=1e-10)
    np.testing.assert_allclose(fs.lag[cp.NAME]["pressure"], lag["pressure"], rtol=1e-10, atol=1e-10)


def test_two_frictional_tools_push_only(phantom):
    """Two tools with friction: at every increment each settles its friction lag, and every
    contact force of each pushes and stays inside the cone."""
    spec = cp.ContactPaddle(mu=0.8)
    tools = tl.default_tools(2)
    c = tl.rest_control(phantom, tools, spec, depth=0.3 * phantom.spacing)
    run = tl.insertion(phantom, tools, c, "none", INCREMENTS, spec)
    assert run.converged and run.contact_ok and all(s == LagStatus.SETTLED for s in run.lag_status)
    assert run.force.shape == (INCREMENTS, 2, 2)
    for row in run.checks:
        for chk in row:
            assert chk.min_normal >= 0 and chk.cone <= 1.0 + 1e-6


def test_qp_statuses():
    """The correction QP: unconstrained it cancels the error within its move limit; a
    minimum force that no move reaches is INFEASIBLE."""
    e, Je = np.array([0.01]), np.array([[1.0, 0.5]])
    z = np.zeros(1)
    dx, st = tl.qp_move(e, Je, z, np.zeros((1, 2)), z, np.zeros((1, 2)), 0.3, np.zeros(2), -np.ones(2),
                        np.ones(2), 0.1, 1.0)
    assert st == tl.QPStatus.OPTIMAL and abs(e[0] + Je[0] @ dx) < 1e-6
    dx, st = tl.qp_move(e, Je, np.ones(1), np.zeros((1, 2)), z, np.zeros((1, 2)), 0.3, np.zeros(2), -np.ones(2),
                        np.ones(2), 0.1, 2.0)
    assert st == tl.QPStatus.INFEASIBLE and not np.any(dx)


def test_cli_tools_options():
    """--tools needs the contact model, --mode preload needs --tools; the summary's goal is
    missed where the tools do no better than no tool."""
    from jaxrkpm.thesis.studies import interface
    from jaxrkpm.thesis.studies import needle as study
    a = interface.parse("needle", ["--paddle-model", "contact", "--tools", "2", "--mode", "preload"])
    assert a.tools == 2 and study.tools_error(a) is None
    assert "contact" in study.tools_error(type(a)(**{**vars(a), "paddle_model": "glued"}))
    assert "--tools" in study.tools_error(type(a)(**{**vars(a), "tools": None}))
    for wrong in (["--tools", "1"], ["--paddle-model", "contact", "--mode", "preload"]):
        with pytest.raises(SystemExit):           # the parser runs the check
            interface.parse("needle", wrong)
    s = {"mode": "static", "inclusion": "none", "tools": 1, "friction": 0.3, "no_tool_deviation": 0.0688,
         "final": 0.0688, "status": "converged", "contact_ok": True}
    assert not study.result(s)[0]
    assert study.result({**s, "final": 0.001})[0]
