"""Needle studies with a contact (push-only) paddle (issue 36 item 4): the static sweep, the
dynamic paddle and the optimised pose on the 2D phantom, at two increments (the studies'
shape, not their converged figures: experiments/needle_contact.py has those)."""
import numpy as np
import pytest

from jaxrkpm.thesis import contact_paddle as cp
from jaxrkpm.thesis import needle as nd

# each contact insertion is tens of solves that run longer than they take to compile
pytestmark = pytest.mark.xla_optimised

INCREMENTS = 2


@pytest.fixture(scope="module")
def phantom():
    return nd.Phantom()


@pytest.fixture(scope="module")
def runs(phantom):
    """Paddle 3 pressed 1.5 spacings in (mu 0.8), the glued paddle 3 and no paddle."""
    target = np.atleast_2d(phantom.target)
    glued = {}
    for p in (None, 3):
        m, s = nd.static_state(phantom, "none", p, INCREMENTS)
        glued[p] = float(phantom.deviation_of(np.asarray(m.displacement(s, target)[0])))
    run = cp.contact_insertion(phantom, 3, [1.5 * phantom.spacing, 0.0], "none", INCREMENTS, cp.ContactPaddle(mu=0.8))
    return run, glued


def test_contact_face(phantom):
    """The contact paddle's face lies on the glued paddle's boundary piece, its normal outward."""
    c, n, t, half = phantom.contact_face(3)
    np.testing.assert_allclose(c, [0.15, 0.35])
    np.testing.assert_allclose(n, -np.ones(2) / np.sqrt(2))
    assert abs(t[0] @ n) < 1e-12 and np.isclose(half[0], 0.5 * np.sqrt(2) * 0.1)
    np.testing.assert_allclose(phantom.contact_face(5)[1], [-1.0, 0.0])
    with pytest.raises(ValueError, match="out of range"):
        phantom.contact_face(6)


def test_static_contact_paddle_pushes_only(runs):
    """Pressed in, the contact paddle pushes at every increment (every point force
    compressive and in the friction cone) and cannot hold the target as the glued paddle
    does, which pulls: at this placement the push-only paddle is no better than none, and the
    sweep names the placement one that only a glued paddle achieves."""
    run, glued = runs
    assert run.converged and len(run.deviation) == INCREMENTS and run.contact_ok
    assert all(c.active > 0 and c.min_normal > 0 and c.cone <= 1.01 and c.behind == 0 for c in run.checks)
    assert run.checks[0].push > 0
    assert abs(glued[3]) < abs(glued[None]) < abs(run.final)
    sw = cp.ContactSweep("none", 0.8, run.control, [run], np.array([glued[3]]), glued[None])
    assert sw.glued_only() == [1] and sw.contact_ok      # (1-based among the paddles swept)
    row = sw.rows()[0]
    assert row["contact_ok"] and row["in_contact_at_end"] and row["max_cone_ratio"] <= 1.01


def test_a_buried_paddle_is_refused(phantom):
    """Pressed deeper than its own thickness the tool would be buried (the tissue closing over
    its back lets it pull): refused before any solve."""
    with pytest.raises(ValueError, match="buries the paddle"):
        cp.contact_insertion(phantom, 3, [0.1, 0.0], "none", 1, cp.ContactPaddle(half_thickness=0.03))


def test_frictionless_has_no_tangential_force(phantom):
    """mu = 0: pressed in, the paddle's force on every point is along the tool's normal and
    pushes the body in."""
    spec = cp.ContactPaddle(mu=0.0)
    st = cp.Stepper(phantom, cp.contact_model(phantom, "none", 3, spec), 3, spec)
    sol, lag, res = st.step({"needle": np.zeros(2)}, [phantom.spacing, 0.0], None, None, steps=spec.press_steps)
    chk = cp.check_contact(res, -phantom.contact_face(3)[1], 0.0)
    assert chk.active > 0 and chk.cone < 1e-9 and chk.push > 0 and chk.ok()


def test_contact_face_3d():
    """The 3D contact paddle's face: on the skin at the patch centre, its normal outward."""
    from jaxrkpm.thesis.phantom3d import Phantom3D
    ph = Phantom3D(spacing=0.3, material_law="neohookean")
    c, n, t, half = ph.contact_face(8)
    semi = np.asarray(ph.semi_axes)
    assert np.isclose(np.sum((c / semi) ** 2), 1.0) and n @ (c / semi ** 2) > 0
    np.testing.assert_allclose(t @ t.T, np.eye(2), atol=1e-12)
    np.testing.assert_allclose(t @ n, 0.0, atol=1e-12)
    assert half.shape == (2,)


def test_dynamic_contact_paddle(phantom):
    """The closed loop keeps a pose correction only where it brings the target nearer the
    line than the pose held, stays within its bounds and never pulls."""
    r = cp.dynamic_contact_paddle(phantom, 3, "none", INCREMENTS, cp.ContactPaddle(mu=0.8),
                                  start=[0.5 * phantom.spacing, 0.0], max_corrections=2)
    assert len(r.deviation) == INCREMENTS and r.contact_ok
    # a correction is kept only where it brings the target nearer the line
    assert np.all(np.abs(r.deviation) <= np.abs(r.uncorrected) + 1e-12)
    lo, hi = cp.control_bounds(phantom, 3)
    assert np.all(r.control >= lo - 1e-12) and np.all(r.control <= hi + 1e-12)


def test_optimised_pose(phantom):
    """Adam on (indentation, shift): its best iterate is no worse than its start, the
    insertion there converged with every contact force in the cone."""
    o = cp.optimize_contact_paddle(phantom, 3, "none", INCREMENTS, cp.ContactPaddle(mu=0.8), iterations=2)
    assert o.status != nd.OptimizeStatus.START_FAILED
    assert abs(o.deviation) <= abs(o.history[0, 2]) + 1e-12
    assert o.run.converged and o.run.contact_ok


def test_bad_input(phantom):
    with pytest.raises(ValueError, match="friction coefficient"):
        cp.ContactPaddle(mu=-0.1)
    with pytest.raises(ValueError, match="control must be 2"):
        cp.contact_insertion(phantom, 3, [0.1], "none", 1)


def test_cli_options():
    from jaxrkpm.thesis.studies import interface
    a = interface.parse("needle", ["--paddle-model", "contact", "--friction", "0.8"])
    assert a.paddle_model == "contact" and a.friction == 0.8
    assert interface.parse("needle", []).paddle_model == "glued"
    with pytest.raises(SystemExit):
        interface.parse("needle", ["--friction", "-1"])


def test_contact_figure(phantom, runs, tmp_path):
    """The CLI's figure of a contact run: the final state with the paddle and its contact
    pressures, beside the deviation curves (the glued and no-paddle ones faked here)."""
    from jaxrkpm.thesis.studies import needle as study
    run, glued = runs
    state = study.contact_state(3, run.control, run.solution, run.lag, run.depths, run.deviation, "contact paddle 3")
    curves = {"depths": run.depths, "no_paddle": np.full(INCREMENTS, glued[None]),
              "glued": np.full(INCREMENTS, glued[3]), "glued_ok": True}
    name = study.contact_figure(tmp_path / "contact.png", phantom, "none", cp.ContactPaddle(mu=0.8), state, curves)
    assert name == "contact.png" and (tmp_path / name).stat().st_size > 10_000


@pytest.mark.slow(reason="3D contact solves with the implicit Jacobian of each correction: minutes on a CPU")
def test_dynamic_contact_paddle_3d():
    """The closed loop on the 3D phantom: the pose is (indentation, two shifts), the
    corrections bring the target nearer the line than the pose held, and never pull."""
    from jaxrkpm.thesis.phantom3d import Phantom3D
    ph = Phantom3D(spacing=0.3, material_law="neohookean")
    r = cp.dynamic_contact_paddle(ph, 5, "none", 1, cp.ContactPaddle(mu=0.3), start=[0.02, 0.0, 0.0],
                                  max_corrections=2)
    assert r.control.shape == (1, 3) and len(r.deviation) == 1 and r.solution is not None
    assert abs(r.deviation[0]) < abs(r.uncorrected[0])
    assert all(c.min_normal >= 0 for c in r.checks)


@pytest.mark.slow(reason="a 3D contact insertion through the CLI, compile included: minutes on a CPU")
def test_needle3d_contact_cli(tmp_path):
    """jaxrkpm needle3d --paddle-model contact: the summary beside the glued patch and no
    paddle, the contact checked at each increment, the figure and the .vtu written."""
    import json

    from jaxrkpm.thesis import cli
    out = tmp_path / "contact"
    code = cli.main(["needle3d", "--paddle-model", "contact", "--spacing", "0.3", "--increments", "1",
                     "--paddle", "5", "--material", "neohookean", "--indentation", "0.02", "--out", str(out)])
    s = json.loads((out / "summary.json").read_text())
    assert code in (0, 1) and s["paddle_model"] == "contact" and s["paddle"] == 5 and s["status"] == "converged"
    assert len(s["contact_ok_per_increment"]) == 1 and s["active_points"][0] > 0
    assert abs(s["final"]) < abs(s["no_paddle_deviation"])
    assert {"contact_static_none.png", "contact_static_none.vtu"} <= {p.name for p in out.iterdir()}
