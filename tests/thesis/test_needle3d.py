"""The 3D needle-insertion phantom (chapter 6 lifted to a half-ellipsoid mesh body) through the
generic needle functions (shape servoing on its mesh loaded from a file:
tests/thesis/test_needle3d_servoing.py).

One coarse phantom (~230 particles) and one set of compiled models for the module; few
increments (the 3D compiles dominate)."""
import numpy as np
import pytest
from scipy.spatial import cKDTree

import jaxrkpm as jr
from jaxrkpm.thesis import needle as nd
from jaxrkpm.thesis.phantom3d import Phantom3D
from jaxrkpm.solvers.results import Status

pytestmark = pytest.mark.xla_optimised   # 3D sweeps: their run time, not their compile, dominates

SPACING = 0.3
INCREMENTS = 2


# the module's measured expectations (README: 7.37e-3 converged) are those of the compressible
# neo-Hookean law (nu = 0.4) that was the phantom's default before the nearly incompressible
# tissue law (nu = 0.45); test_default_is_tissue solves the default
LAW = "neohookean"

# the 3D study itself (a sweep of the phantom's paddles, then the controls built on it) runs in the
# slow set: the needle functions it calls are tested on the 2D phantom in the default run
# (tests/thesis/test_needle.py), and the 3D phantom's construction and inputs here
STUDY = pytest.mark.slow(reason="the 3D needle study: 3D sweeps and the controls on them")


@pytest.fixture(scope="module")
def phantom():
    return Phantom3D(spacing=SPACING, material_law=LAW)


@pytest.fixture(scope="module")
def sweep(phantom):
    return nd.static_sweep(phantom, "none", INCREMENTS)


def test_phantom_layout(phantom):
    body = phantom.body
    a, b, c = phantom.semi_axes
    assert abs(body.volumes.sum() - 2 / 3 * np.pi * a * b * c) < 0.05 * 2 / 3 * np.pi * a * b * c
    X = body.X
    assert np.all(np.abs(X[phantom.base, 2]) < 1e-12) and len(phantom.base) > 10
    # the mesh conforms to the track: the needle is its particles on the first needle_length
    # (within the physical needle_radius), a particle sits on the target, none on the base
    d = phantom.needle_direction
    rel = X[phantom.needle] - phantom.entry
    along = rel @ d
    r = phantom.needle_radius
    assert len(phantom.needle) >= 10 and np.all((along > -r) & (along <= phantom.needle_length + r))
    assert np.all(np.linalg.norm(rel - along[:, None] * d, axis=1) <= r * (1 + 1e-9))
    on_axis = np.linalg.norm(rel - along[:, None] * d, axis=1) < 1e-12
    assert np.sum(on_axis & (along > 0) & (along <= phantom.needle_length)) >= 3
    assert np.linalg.norm(X - np.asarray(phantom.target), axis=1).min() < 1e-12
    # the needle lies in the symmetry plane y = 0 and the mesh is its exact mirror image
    assert phantom.mirror_symmetric
    assert cKDTree(X).query(X * [1, -1, 1])[0].max() < 1e-12
    # >= 20 candidate patches of equal size on the skin, distinct, away from the needle entry
    patches = [tuple(phantom.patch(p)) for p in range(1, len(phantom.paddles) + 1)]
    assert len(set(patches)) >= 20 and {len(p) for p in patches} == {phantom.patch_size}
    skin = np.concatenate(patches)
    assert np.allclose(phantom.level(X[skin]), 1.0, atol=1e-6) and np.all(X[skin, 2] > 0)
    assert np.linalg.norm(X[skin] - phantom.entry, axis=1).min() > phantom.needle_radius   # clear of the needle
    # the target on the needle line, at 40% of the chord
    assert np.allclose(phantom.target, phantom.entry + 0.4 * phantom.chord * np.array([1.0, 0, 0]))


@STUDY
def test_static_sweep_reduces_deviation(sweep):
    """No paddle: the target leaves the needle line only vertically (the needle lies in the
    plane of the mirror-symmetric mesh, so the sideways part is zero to round-off; the fixed
    base pushes the target up, as the immobile edge does in 2D). The best of the 20 patches
    over the target cuts the final lateral deviation >= 5x at this coarse test mesh (5.75x:
    17 particles per patch); issue 17's >= 10x holds at spacing 0.2 and 0.15 (20.8x, 116x: README,
    experiments/phantom3d_patch_grid.py). Placement matters: the median patch is far worse."""
    assert np.all(sweep.no_paddle_status == Status.CONVERGED) and np.all(sweep.converged_paddles)
    u = sweep.no_paddle_u[-1]
    assert abs(u[1]) < 1e-12 and u[2] > 1e-3, u
    assert np.all(np.diff(np.abs(sweep.no_paddle)) > 0)
    reduction = abs(sweep.no_paddle[-1]) / abs(sweep.final[sweep.best - 1])
    assert reduction >= 5.0, reduction
    assert np.median(np.abs(sweep.final)) > 3 * abs(sweep.final[sweep.best - 1])   # placement matters


FINE_SPACING = 0.2   # the mesh-converged phantom (no-paddle deviation within 4% of 0.15, 0.12, 0.1)
COARSE_TIE = 1.5     # coarse-mesh deviations within this factor of the best are not told apart


@STUDY
def test_best_patch_reduces_10x_on_the_converged_mesh(phantom, sweep):
    """Issue 17's >= 10x, on the mesh where the no-paddle deviation has converged (spacing
    0.2; the coarse test mesh gives 5.75x). Coarse search, fine check: the coarse mesh cannot
    rank patches whose deviations lie within COARSE_TIE of its best (the five around the pole
    lie within 1.1x there, and their fine-mesh order differs), so all of them are solved on
    the fine mesh, in one batched call, the needle inserted in one increment (hyperelastic:
    the same equilibrium as in several). The best of them cuts the deviation >= 10x (20.8x
    measured); the fine sweep's best patch does at least as well, so its reduction is >= that."""
    fine = Phantom3D(spacing=FINE_SPACING, material_law=LAW)
    best = abs(sweep.final[sweep.best - 1])
    candidates = [p + 1 for p in np.flatnonzero(np.abs(sweep.final) <= COARSE_TIE * best)]
    depths = fine.depths(1)

    def final_deviations(paddles):
        out = nd.insert([fine.model("none", p) for p in paddles], depths, fine.target, jacobian_set=None,
                        direction=fine.needle_direction)
        assert np.all(np.asarray(out.status) == Status.CONVERGED)
        return fine.deviation_of(np.asarray(out.target_u)[:, -1])

    none = float(final_deviations([None])[0])
    devs = final_deviations(candidates)
    assert abs(none - 7.37e-3) < 0.05 * 7.37e-3, none        # the converged value (README)
    assert none / devs.min() >= 10.0, dict(zip(candidates, devs))


@STUDY
def test_batched_equals_unbatched(phantom, sweep):
    """The batched sweep equals warm-started model.solve per increment, Jacobians included."""
    p = sweep.best
    model = phantom.model("none", p)
    target = np.atleast_2d(phantom.target)
    sol = model.initial()
    for k, depth in enumerate(sweep.depths):
        sol = model.solve({"needle": phantom.needle_at(depth)}, initial=sol)
        u = np.asarray(model.displacement(sol, target))[0]
        np.testing.assert_allclose(u, sweep.target_u[p - 1, k], rtol=0, atol=1e-10)
    J = np.asarray(model.jacobian(sol, "paddle", target))
    np.testing.assert_allclose(sweep.jacobian[p - 1, -1], J, rtol=1e-8, atol=1e-10)


@STUDY
def test_controllability(sweep):
    """delta x_min = largest ||J^-1 e|| over unit lateral e; in 2D it is the thesis'
    ||J^-1 [1 0]^T||."""
    ctrl = sweep.controllability
    assert ctrl.shape == sweep.deviation.shape and np.all(np.isfinite(ctrl)) and np.all(ctrl > 0)
    assert ctrl[:, 0].max() > 2 * ctrl[:, 0].min()          # patches differ
    J = sweep.jacobian[0, 0]
    M = np.linalg.inv(J)[:, 1:]
    worst = max(np.linalg.norm(M @ [np.cos(t), np.sin(t)]) for t in np.linspace(0, np.pi, 721))
    assert abs(ctrl[0, 0] - worst) < 1e-5 * worst
    J2 = np.array([[0.3, -0.1], [0.05, 0.4]])
    assert abs(nd.controllability(J2) - np.linalg.norm(np.linalg.solve(J2, [1.0, 0.0]))) < 1e-14


@STUDY
def test_dynamic_paddle_holds_target(phantom, sweep):
    """The closed loop keeps |lateral deviation| < 1e-4 of the object size at every increment."""
    best = int(np.argmin(sweep.controllability[:, 0])) + 1
    run = nd.dynamic_paddle(phantom, best, "none", INCREMENTS, tol=1e-5)
    assert run.status == nd.HoldStatus.CONVERGED, run.message
    size = 2 * max(phantom.semi_axes)
    assert len(run.deviation) == INCREMENTS and np.abs(run.deviation).max() < 1e-4 * size
    assert np.abs(run.uncorrected).max() > np.abs(run.deviation).max()
    assert run.paddle_u.shape == (INCREMENTS, 3) and run.travel > 1e-4


@STUDY
def test_optimised_patch_through_the_solve(phantom, sweep):
    """Adam on the two surface coordinates, through the solve, from the best discrete patch,
    the continuous paddle being that patch's own contact points as stiff springs slid over
    the skin (``with_footprint``): its first iterate is the held patch again (to the penalty
    error), and the best iterate, returned, lies well below it (2.8x in 4 iterations here:
    the paddle slides over the pole, beyond the grid's first ring)."""
    best = sweep.best
    start = phantom.patch_coordinates[best - 1]
    sliding = phantom.with_footprint(best)
    assert np.abs(np.asarray(sliding.paddle_points(start)) - phantom.body.X[phantom.patch(best)]).max() < 1e-12
    opt = nd.optimize_paddle(sliding, "none", start=start, increments=INCREMENTS, iterations=4,
                             learning_rate=0.05)
    lo, hi = phantom.paddle_bounds
    assert opt.q.shape == (2,) and np.all(opt.q >= lo) and np.all(opt.q <= hi)
    assert opt.history.shape[1] == 5 and np.all(np.isfinite(opt.history))
    assert abs(opt.deviation) == np.min(np.abs(opt.history[:, 2]))
    discrete = sweep.final[best - 1]
    assert abs(opt.start_deviation - discrete) < 1e-3 * abs(discrete), (opt.start_deviation, discrete)
    assert abs(opt.deviation) < 0.75 * abs(discrete), (opt.deviation, discrete)


def test_bad_input():
    with pytest.raises(ValueError, match="material_law"):
        Phantom3D(material_law="rubber")
    with pytest.raises(ValueError, match="needle line"):
        Phantom3D(needle_point=(0.0, 0.1, -0.1))
    with pytest.raises(ValueError, match="target"):
        Phantom3D(insertion=0.6)
    with pytest.raises(ValueError, match="start"):
        nd.optimize_paddle(Phantom3D(), start=[0.5])
    with pytest.raises(ValueError, match="paddle_footprint"):
        Phantom3D(paddle_footprint=21)


def test_hostile_phantom_input_blames_the_right_parameter():
    """Issue 35: each is refused where it is given, naming it (before any mesh is made)."""
    with pytest.raises(TypeError, match=r"paddle must be a 1-based int index into the 20 patches, got 1.5"):
        Phantom3D().patch(1.5)
    with pytest.raises(ValueError, match=r"needle_radius 2 is too large for the phantom: the needle's surface"):
        Phantom3D(needle_radius=2.0)
    for length in (-0.1, 0.0, float("nan")):
        with pytest.raises(ValueError, match="needle_length must be a positive length"):
            Phantom3D(needle_length=length)
    for ratio in (0.0, -1.0, float("inf")):
        with pytest.raises(ValueError, match="stiffness_ratio must be a positive factor"):
            Phantom3D(stiffness_ratio=ratio)
    with pytest.raises(TypeError, match=r"increments must be a whole number of insertion increments, got 2.5"):
        Phantom3D().depths(2.5)
    assert Phantom3D().depths(3)[-1] == pytest.approx(Phantom3D().insertion)


def test_default_is_tissue():
    """The default phantom is nearly incompressible neo-Hookean tissue (mu = 1, nu = 0.45): its
    insertion converges, the target moves up the needle in the symmetry plane, nearly
    keeping its volume."""
    tissue = Phantom3D(spacing=SPACING)
    material = tissue.material()
    assert tissue.material_law == "neo-hookean" and material.name == "NearlyIncompressibleNeoHookean"
    assert material.params["mu"] == 1.0 and material.params["kappa"] == pytest.approx(jr.bulk_modulus(1.0, 0.45))
    assert Phantom3D(material_law="fung-barrier").material().name == "Fung+barrier"
    model, sol = nd.static_state(tissue, "none", None, INCREMENTS)
    assert float(sol.t) == 1.0 and int(sol.status) == Status.CONVERGED
    u = np.asarray(model.displacement(sol, [tissue.target]))[0]
    assert abs(u[1]) < 1e-12 and u[2] > 1e-3, u             # as the compressible phantom's target
    J = float(np.linalg.det(np.asarray(model.deformation_gradient(sol, [tissue.target]))[0]))
    assert abs(J - 1) < 0.05, J


@STUDY
def test_cli_static(tmp_path, phantom, sweep):
    """``jaxrkpm needle3d --mode static``: summary, figures and .vtu files (its report on
    the module's sweep, so no second sweep is compiled and run)."""
    import json
    from jaxrkpm.thesis.studies import needle3d as cli
    s = cli.static_report(phantom, sweep, tmp_path)
    (tmp_path / "summary.json").write_text(json.dumps(s))
    saved = json.loads((tmp_path / "summary.json").read_text())
    assert saved["patches"] == 20 and saved["converged"] and saved["best_reduction"] >= 5.0
    assert len(saved["controllability"]) == 20 and 1 <= saved["most_controllable"] <= 20
    for name in ("patches_none.png", "deviation_none.png", "phantom_static_none.png"):
        assert (tmp_path / name).stat().st_size > 10_000
    assert all((tmp_path / p).name.endswith(".vtu") and (tmp_path / p).exists() for p in saved["vtu"])
    with pytest.raises(SystemExit):
        cli.main(["--increments", "0", "--out", str(tmp_path)])
