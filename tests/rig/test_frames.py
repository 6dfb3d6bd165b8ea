"""Frames and calibration (thesis sections 4.2.2-4.2.3): L-marker object frame
(eqs 4.4-4.9), pivot calibration (eqs 4.10-4.21), Arun registration, units."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jaxrkpm.rig.frames import RigidTransform, Units, arun_registration, label_l_markers, object_frame_from_l_markers, pivot_calibration, register_from_three_touches
from jaxrkpm.rig.stereo import ParallelStereo, StereoTracker, render_markers


def rot(seed, n=None):
    return Rotation.random(n, random_state=seed).as_matrix()


# ----------------------------------------------------------------------------- units


def test_units():
    assert Units.inch_to_m(6) == pytest.approx(0.1524, abs=1e-15)
    assert Units.OBJECT_SIZE_M == pytest.approx((0.1524, 0.1524, 0.0127), abs=1e-15)
    assert Units.m_to_inch(Units.inch_to_m(8.0)) == pytest.approx(8.0, abs=1e-14)
    assert Units.mm_to_m(0.5) == pytest.approx(5e-4, abs=1e-18)
    assert Units.m_to_mm(0.0254) == pytest.approx(25.4, abs=1e-12)
    assert np.allclose(Units.inch_to_m([1, 2]), [0.0254, 0.0508], atol=1e-16)


# ----------------------------------------------------------------------------- transforms


def test_rigid_transform_roundtrip():
    T = RigidTransform(rot(1), [0.1, -0.2, 0.45])
    P = np.random.default_rng(0).normal(size=(7, 3))
    assert np.abs(T.apply_inverse(T.apply(P)) - P).max() < 1e-14
    assert np.abs(T.inverse().apply(T.apply(P)) - P).max() < 1e-14
    assert T.apply(P[0]).shape == (3,)
    U = RigidTransform(rot(2), [0.0, 0.3, 0.0])
    assert np.abs(T.compose(U).apply(P) - T.apply(U.apply(P))).max() < 1e-14
    assert np.abs(RigidTransform.from_matrix(T.as_matrix()).apply(P) - T.apply(P)).max() < 1e-15
    with pytest.raises(ValueError, match="reflection"):
        RigidTransform(np.diag([1.0, 1.0, -1.0]), np.zeros(3))
    with pytest.raises(ValueError, match="orthonormal"):
        RigidTransform(2 * np.eye(3), np.zeros(3))


# ----------------------------------------------------------------------------- L markers


def l_markers_in_camera(R_co, t_co, leg_m=0.05):
    """Thesis L: V1 on the object x axis, V2 on the y axis, |V2 - V0| = 2 |V1 - V0|.
    R_co, t_co: object -> camera."""
    obj = np.array([[0.0, 0.0, 0.0], [leg_m, 0.0, 0.0], [0.0, 2 * leg_m, 0.0]])
    return obj @ R_co.T + t_co, obj


@pytest.mark.parametrize("seed", range(5))
def test_l_marker_frame_recovers_known_frame(seed):
    R_co = rot(seed)
    t_co = np.random.default_rng(seed).uniform([-0.1, -0.1, 0.4], [0.1, 0.1, 0.5])
    V, obj = l_markers_in_camera(R_co, t_co)
    T = object_frame_from_l_markers(V, leg_ratio=2.0)
    assert np.abs(T.R - R_co.T).max() < 1e-12           # eq 4.7: object axes as rows
    assert np.abs(T.t - (-R_co.T @ t_co)).max() < 1e-12  # eq 4.8
    assert np.abs(T.apply(V) - obj).max() < 1e-12       # eq 4.9
    P_obj = np.array([[0.07, 0.03, 0.0], [0.02, 0.11, 0.004]])
    assert np.abs(T.apply(T.apply_inverse(P_obj)) - P_obj).max() < 1e-15
    assert np.abs(T.R @ T.R.T - np.eye(3)).max() < 1e-12
    assert np.linalg.det(T.R) == pytest.approx(1.0, abs=1e-12)


def test_l_marker_frame_is_orthonormal_for_noisy_markers():
    rng = np.random.default_rng(4)
    for k in range(20):
        V, _ = l_markers_in_camera(rot(100 + k), [0.0, 0.0, 0.45])
        V = V + rng.normal(0.0, 1e-3, V.shape)            # 1 mm: legs far from perpendicular
        R = object_frame_from_l_markers(V).R
        assert np.abs(R @ R.T - np.eye(3)).max() < 1e-12
        assert abs(np.linalg.det(R) - 1.0) < 1e-12


def test_l_marker_frame_rejects_bad_input():
    with pytest.raises(ValueError, match="collinear"):
        object_frame_from_l_markers([[0, 0, 0.4], [0.05, 0, 0.4], [0.1, 0, 0.4]])
    with pytest.raises(ValueError, match="coincident"):
        object_frame_from_l_markers([[0, 0, 0.4], [0, 0, 0.4], [0, 0.1, 0.4]])
    V, _ = l_markers_in_camera(np.eye(3), [0, 0, 0.45])
    with pytest.raises(ValueError, match="mislabelled"):
        object_frame_from_l_markers(V[[0, 2, 1]], leg_ratio=2.0)


def test_label_l_markers():
    V, _ = l_markers_in_camera(rot(9), [0.01, 0.02, 0.45])
    for perm in ([0, 1, 2], [2, 0, 1], [1, 2, 0], [2, 1, 0]):
        assert np.array_equal(label_l_markers(V[perm]), V)
    with pytest.raises(ValueError, match="not an L"):
        label_l_markers([[0, 0, 0], [1, 0, 0], [0.5, 0.2, 0]])
    with pytest.raises(ValueError, match="too similar"):
        label_l_markers([[0, 0, 0], [1, 0, 0], [0, 1.05, 0]])


def find_l_triple(pts):
    """(L (3, 3) labelled V0, V1, V2; index of the other marker) among 4 markers."""
    hits = []
    for k in range(4):
        try:
            L = label_l_markers(np.delete(pts, k, axis=0))
            object_frame_from_l_markers(L, leg_ratio=2.0)
        except ValueError:
            continue
        hits.append((L, k))
    assert len(hits) == 1, f"{len(hits)} triples look like the L"
    return hits[0]


def test_l_frame_from_stereo_images_end_to_end():
    """Render the L markers and a control marker, track them, build the object frame and
    read the control point in object coordinates (the thesis' measurement chain)."""
    cam = ParallelStereo(900.0, 0.12, 511.5, 383.5, (1024, 768))
    R_co = Rotation.from_euler("xyz", [150.0, 10.0, 25.0], degrees=True).as_matrix()
    t_co = np.array([0.03, 0.0, 0.45])
    V, _ = l_markers_in_camera(R_co, t_co, leg_m=0.06)
    control_obj = np.array([0.08, 0.05, 0.0])
    P = np.vstack([V, control_obj @ R_co.T + t_co])
    rng = np.random.default_rng(0)
    errs = []
    for _ in range(5):
        frame = StereoTracker(cam, 4).track(*render_markers(P, cam, noise_std=2.0, rng=rng))
        assert frame.ok, frame.message
        pts = frame.points_m
        # which three of the four markers form the thesis' 2:1 L? exactly one triple must
        L, k = find_l_triple(pts)
        T = object_frame_from_l_markers(L, leg_ratio=2.0)
        errs.append(np.linalg.norm(T.apply(pts[k]) - control_obj))
    assert max(errs) < 0.5e-3


# ----------------------------------------------------------------------------- pivot


def pivot_poses(n, seed, tip_m=(0.012, -0.008, Units.TOOL_LENGTH_M),
                pivot_m=(0.40, 0.10, 0.05), max_tilt_deg=35.0):
    """Poses of a flange that keep tip_m (flange frame) on pivot_m (base frame)."""
    rng = np.random.default_rng(seed)
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.radians(rng.uniform(5.0, max_tilt_deg, n))
    R = Rotation.from_rotvec(axes * angles[:, None]).as_matrix()
    t = np.asarray(pivot_m) - R @ np.asarray(tip_m)
    return R, t, np.asarray(tip_m), np.asarray(pivot_m)


def test_pivot_calibration_exact():
    R, t, tip, pivot = pivot_poses(8, seed=0)           # thesis: eight orientations
    res = pivot_calibration(R, t)
    assert np.abs(res.tip_m - tip).max() < 1e-9
    assert np.abs(res.pivot_m - pivot).max() < 1e-9
    assert res.rms_m < 1e-12
    assert res.residuals_m.shape == (8, 3)


def test_pivot_calibration_with_noise_reaches_noise_level():
    sigma = 0.1e-3                                       # 0.1 mm on each translation
    R, t, tip, pivot = pivot_poses(40, seed=1)
    t = t + np.random.default_rng(2).normal(0.0, sigma, t.shape)
    res = pivot_calibration(R, t)
    # 120 equations, 6 unknowns: RMS residual ~ sigma sqrt(3 (n-2)/n)
    assert 0.7 * sigma * np.sqrt(3) < res.rms_m < 1.3 * sigma * np.sqrt(3)
    assert np.linalg.norm(res.tip_m - tip) < 3 * sigma
    assert np.linalg.norm(res.pivot_m - pivot) < 3 * sigma


def test_pivot_calibration_rejects_bad_pose_sets():
    R, t, _, _ = pivot_poses(8, seed=3)
    with pytest.raises(ValueError, match="at least 3 poses"):
        pivot_calibration(R[:2], t[:2])
    # all rotations about one axis: the tip's component along that axis is undetermined
    Rz = Rotation.from_euler("z", np.linspace(0, 90, 6)[:, None], degrees=True).as_matrix()
    tz = np.array([0.4, 0.1, 0.05]) - Rz @ np.array([0.01, 0.0, 0.2])
    with pytest.raises(ValueError, match="degenerate"):
        pivot_calibration(Rz, tz)
    with pytest.raises(ValueError, match="reflection|orthonormal"):
        pivot_calibration(np.concatenate([R[:3], -R[:1]]), t[:4])
    with pytest.raises(ValueError, match="translations_m"):
        pivot_calibration(R, t[:5])


# ----------------------------------------------------------------------------- Arun


def naive_arun(X, Y):
    """Arun's SVD without the reflection fix (what the test guards against)."""
    H = (X - X.mean(0)).T @ (Y - Y.mean(0))
    U, _, Vt = np.linalg.svd(H)
    return Vt.T @ U.T


@pytest.mark.parametrize("seed", range(8))
def test_arun_recovers_random_rigid_transforms(seed):
    rng = np.random.default_rng(seed)
    R, T = rot(seed), rng.uniform(-0.5, 0.5, 3)
    X = rng.uniform(-0.1, 0.1, (10, 3))
    reg = arun_registration(X, X @ R.T + T)
    assert np.abs(reg.R - R).max() < 1e-12
    assert np.abs(reg.T - T).max() < 1e-12
    assert reg.rms_m < 1e-13
    assert np.linalg.det(reg.R) == pytest.approx(1.0, abs=1e-12)


def test_arun_never_returns_a_reflection_for_noisy_coplanar_points():
    found = 0
    for seed in range(200):            # bounded search for cases where naive SVD reflects
        rng = np.random.default_rng(seed)
        R, T = rot(1000 + seed), rng.uniform(-0.5, 0.5, 3)
        X = np.c_[rng.uniform(-0.1, 0.1, (6, 2)), np.zeros(6)]     # coplanar object points
        Y = X @ R.T + T + rng.normal(0.0, 1e-4, (6, 3))
        reg = arun_registration(X, Y)
        assert np.linalg.det(reg.R) == pytest.approx(1.0, abs=1e-12)
        assert np.abs(reg.R @ reg.R.T - np.eye(3)).max() < 1e-12
        assert np.degrees(np.arccos(np.clip((np.trace(reg.R.T @ R) - 1) / 2, -1, 1))) < 1.0
        if np.linalg.det(naive_arun(X, Y)) < 0:
            found += 1
            # the plain SVD answer is a reflection: the fix matters in this case
            assert reg.rms_m < 3e-4
        if found >= 3:
            break
    assert found >= 3


def test_arun_noisy_rms_matches_noise():
    rng = np.random.default_rng(7)
    sigma = 0.2e-3
    R, T = rot(77), np.array([0.3, -0.1, 0.2])
    X = rng.uniform(-0.1, 0.1, (200, 3))
    reg = arun_registration(X, X @ R.T + T + rng.normal(0.0, sigma, X.shape))
    assert 0.8 * sigma * np.sqrt(3) < reg.rms_m < 1.2 * sigma * np.sqrt(3)
    assert np.abs(reg.R - R).max() < 1e-2 * sigma / 1e-4


def test_arun_three_touches_thesis_case():
    """Eqs 4.22-4.25: tip touches the object origin, an x-axis and a y-axis point."""
    R_or = rot(21)
    T_or = np.array([0.55, -0.12, 0.08])        # object -> robot
    obj = np.array([[0, 0, 0], [Units.inch_to_m(4), 0, 0], [0, Units.inch_to_m(3), 0]])
    touches = obj @ R_or.T + T_or
    reg = register_from_three_touches(*touches)
    assert np.abs(reg.R - R_or).max() < 1e-12 and np.abs(reg.T - T_or).max() < 1e-12
    assert np.abs(reg.transform.apply_inverse(touches) - obj).max() < 1e-12


def test_arun_rejects_degenerate_input():
    with pytest.raises(ValueError, match="at least 3"):
        arun_registration(np.zeros((2, 3)), np.zeros((2, 3)))
    line = np.c_[np.linspace(0, 1, 5), np.zeros(5), np.zeros(5)]
    with pytest.raises(ValueError, match="collinear"):
        arun_registration(line, line + 1.0)
    with pytest.raises(ValueError, match="differ in shape"):
        arun_registration(np.zeros((4, 3)), np.zeros((5, 3)))
