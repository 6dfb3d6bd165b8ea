"""Arc-length continuation (jaxrkpm.arc_length): snap-through of a clamped shallow arch
through its limit point against displacement control of the crown (experiments/snap_through.py),
agreement with load control where there is no limit point, and named bad input."""

import jax.numpy as jnp
import numpy as np
import pytest
from scipy.interpolate import CubicSpline

import jaxrkpm as jr
from tests import problems as st
from jaxrkpm.solvers.continuation import PathStatus
from jaxrkpm.model.continuation import arc_length, point_load
from jaxrkpm.solvers.linalg.base import Stability
from tests.problems import unit_grid

SNAP_STEPS = 16      # ten steps to the limit point, six past it (ds = 0.03)
REF_DEPTH, REF_STEPS = 0.09, 18   # crown deflection of the reference sweep (the limit is at ~0.05)


@pytest.fixture(scope="module")
def arch():
    return st.shallow_arch()


@pytest.fixture(scope="module")
def model(arch):
    return st.load_model(arch)


@pytest.fixture(scope="module")
def snap(arch, model):
    return st.snap(arch, model, ds=0.03, steps=SNAP_STEPS)


@pytest.fixture(scope="module")
def reference(arch):
    """Crown deflection and force under displacement control, and its largest force."""
    v, f = st.displacement_control(st.crown_model(arch), REF_DEPTH, REF_STEPS)
    return v, f, st.first_maximum(v, f)


def test_snap_through_limit_load_matches_displacement_control(snap, reference):
    """The limit load of the load-driven arch equals the largest crown reaction of the same
    discretisation under displacement control (the same equilibria, see the example's
    docstring): within 2% as sampled by the path, within 0.2% located between the samples."""
    _, _, F_ref = reference
    assert snap.completed, snap.message
    assert len(snap.limit_points) == 1, snap.load
    assert abs(snap.load.max() / F_ref - 1) < 0.02
    assert abs(snap.limit_loads()[0] / F_ref - 1) < 2e-3


def test_snap_through_path_is_continuous_through_the_limit_point(snap, reference):
    v_ref, f_ref, F_ref = reference
    k = int(snap.limit_points[0])
    assert 3 <= k <= len(snap) - 4, "the limit point must be inside the path, with points on both sides"
    # the load factor rises to the limit point and falls after it
    dl = np.diff(snap.load)
    assert np.all(dl[:k] > 0) and np.all(dl[k:] < 0)
    # no jump: consecutive states are one arc length apart (the constraint), the crown keeps
    # going down, and every point lies on the displacement-controlled curve
    jumps = np.linalg.norm((snap.u[1:] - snap.u[:-1]).reshape(len(snap) - 1, -1), axis=1)
    np.testing.assert_allclose(jumps, snap.arc[1:], rtol=1e-6)
    deflection = -snap.displacement[:, 0, 1]
    assert np.all(np.diff(deflection) > 0)
    assert deflection[-1] < REF_DEPTH
    on_curve = CubicSpline(v_ref, f_ref)(deflection)
    assert np.max(np.abs(snap.load - on_curve)) < 2e-3 * F_ref
    # stable up to the limit point, exactly one negative eigenvalue after it: a limit point,
    # not a bifurcation
    assert snap.critical_points.tolist() in ([k], [k + 1])
    j = int(snap.critical_points[0])
    assert np.all(snap.negative[:j] == 0) and np.all(snap.negative[j:] == 1)
    assert np.all(snap.stability == np.where(snap.negative == 0, Stability.STABLE, Stability.UNSTABLE))
    assert np.all(snap.residual_norm[1:] < 1e-10)


def test_without_a_limit_point_the_path_is_the_load_controlled_solution(model):
    """The arch lifted by its body force while its right end is pulled out (both driven by the
    path parameter): no limit point, and each point is plain ``solve``'s equilibrium at the
    same load and prescribed displacement."""
    pull = np.array([0.002, 0.0])
    path = arc_length(model, 0.03, steps=30, load_max=1.0, prescribed={"right": pull})
    assert path.completed and path.load[-1] >= 1.0, path.message
    assert np.all(np.diff(path.load) > 0) and len(path.limit_points) == 0
    assert np.all(path.negative == 0)
    for k in (len(path) // 2, len(path) - 1):
        lam = float(path.load[k])
        sol = model.solve({"right": lam * pull}, loads=lam, steps=2)
        np.testing.assert_allclose(np.asarray(sol.g), path.g[k], atol=1e-15)
        scale = np.abs(path.u[k]).max()
        assert np.abs(np.asarray(sol.u) - path.u[k]).max() < 1e-8 * scale
        state = path.solution(k)
        assert jr.Status.of(state.status) == jr.Status.CONVERGED and float(state.load) == lam


def test_bad_input_is_named(model):
    small = unit_grid(3)
    held = jr.Model(small, st.MATERIAL, essential={"left": small.select(lambda X: X[:, 0] < 1e-9)})
    cases = [
        (dict(ds=0.0), ValueError, "ds must be a positive"),
        (dict(ds=float("nan")), ValueError, "ds must be a positive"),
        (dict(ds=0.1, ds_max=0.05), ValueError, r"ds_max \(0.05\) must be at least ds"),
        (dict(ds=0.1, steps=0), ValueError, "steps must lie in"),
        (dict(ds=0.1, steps=2.5), TypeError, "steps must be an int"),
        (dict(ds=0.1, max_cuts=-1), ValueError, "max_cuts must lie in"),
        (dict(ds=0.1, psi=-1.0), ValueError, "psi must be a non-negative"),
        (dict(ds=0.1, direction=0), ValueError, "direction must be"),
        (dict(ds=0.1, load_max=float("inf")), ValueError, "load_max must be a finite"),
        (dict(ds=0.1, load_pattern=np.ones((3, 2))), ValueError, "load_pattern must be finite nodal loads"),
        (dict(ds=0.1, prescribed={"crown": [0.0, 1.0]}), ValueError, "unknown essential set 'crown'"),
        (dict(ds=0.1, initial=model.initial()._replace(status=jnp.asarray(1))), ValueError,
         "initial must be an equilibrium, but its status is MAX_ITERATIONS"),
        (dict(ds=0.1, rtol=-1.0), ValueError, "rtol must be a positive"),
    ]
    for kw, err, match in cases:
        with pytest.raises(err, match=match):
            arc_length(model, **kw)
    with pytest.raises(ValueError, match="nothing drives the path"):
        arc_length(held, 0.1)
    with pytest.raises(ValueError, match="unconstrained"):
        arc_length(jr.Model(small, st.MATERIAL), 0.1)
    with pytest.raises(TypeError, match="model must be a jaxrkpm Model"):
        arc_length("arch", 0.1)
    with pytest.raises(ValueError, match="forces must be finite"):
        point_load(held, [[0.5, 0.5]], [1.0, float("nan")])
    with pytest.raises(ValueError, match="n_along >= 5 and n_thick >= 3 must be odd"):
        st.shallow_arch(40)


def test_a_failed_step_keeps_every_accepted_point(model):
    """A corrector allowed one iteration cannot converge: the path stops with its status
    after max_cuts halvings, the start kept."""
    path = arc_length(model, 0.03, steps=5, max_iter=1, max_cuts=2)
    assert path.outcome == PathStatus.MAX_ITERATIONS and len(path) == 1 and path.cuts == 2
    assert "MAX_ITERATIONS" in path.message and "every accepted point is kept" in path.message


def test_an_interrupted_path_keeps_its_points(model, monkeypatch):
    from jaxrkpm.model import continuation   # the driver as arc_length calls it
    calls = []

    def interrupted_on_the_third_step(*args):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return step(*args)

    step = continuation.arc_step
    monkeypatch.setattr(continuation, "arc_step", interrupted_on_the_third_step)
    path = arc_length(model, 0.03, steps=5)
    assert path.outcome == PathStatus.INTERRUPTED and len(path) == 3 and np.all(np.diff(path.load) > 0)


def test_spherical_constraint_finds_the_same_limit_load(arch, model, snap):
    """psi > 0 (Riks' sphere in (u, psi lambda |q|)): each step satisfies
    |du|^2 + psi^2 dlambda^2 |q|^2 = ds^2 (q: the crown load, all on free particles) with a
    real share of the load term, and the limit load is the same."""
    psi, load = 2000.0, st.crown_load(model, arch)
    path = arc_length(model, 0.03, steps=14, psi=psi, ds_max=0.03, load_pattern=load)
    assert path.completed and len(path.limit_points) == 1
    du2 = np.sum((path.u[1:] - path.u[:-1]).reshape(len(path) - 1, -1) ** 2, axis=1)
    sphere = du2 + (psi * np.diff(path.load)) ** 2 * np.sum(load**2)
    np.testing.assert_allclose(sphere, path.arc[1:] ** 2, rtol=1e-8)
    assert np.min(du2 / path.arc[1:] ** 2) < 0.8
    assert abs(path.limit_loads()[0] / snap.limit_loads()[0] - 1) < 1e-3


def test_sparse_solver_follows_the_same_path_with_its_inertia(arch, snap):
    """The sparse path (SuperLU through host callbacks): the same points, and the number of
    negative eigenvalues from its factorisation's inertia."""
    sparse = jr.Model(arch.body, st.MATERIAL, essential=arch.ends, support=st.SUPPORT,
                      solver="sparse", factorisation="superlu")
    path = st.snap(arch, sparse, ds=0.03, steps=12)
    assert path.completed, path.message
    np.testing.assert_allclose(path.load, snap.load[:13], rtol=1e-7, atol=1e-12)
    assert path.negative.tolist() == snap.negative[:13].tolist()


def test_probe_points_outside_the_body_fail_before_the_path(model, monkeypatch):
    """A probe point outside the body is refused before any step is computed (it used to fail
    after the whole path, losing it)."""
    from jaxrkpm.model import continuation

    def no_step(*args):
        raise AssertionError("a path step was computed")
    monkeypatch.setattr(continuation, "arc_step", no_step)
    monkeypatch.setattr(continuation, "start_point", no_step)
    outside = model.body.upper + 1.0
    with pytest.raises(ValueError, match=r"probe point 1 at .* is outside the body"):
        arc_length(model, 0.03, steps=5, points=[model.body.X[0], outside])
    with pytest.raises(ValueError, match="probe points contain non-finite coordinates"):
        arc_length(model, 0.03, steps=5, points=[[np.nan, 0.0]])


def test_a_path_point_is_a_whole_index(model):
    path = arc_length(model, 0.03, steps=1)
    assert len(path) == 2 and path.solution(-1).load == path.load[-1]
    with pytest.raises(TypeError, match=r"a path point is a whole index, got 1.5 \(float\); the path has points 0..1"):
        path.solution(1.5)
    with pytest.raises(IndexError, match="point 2 of a path of 2 points"):
        path.solution(2)
