"""Stereo marker tracking (thesis section 4.2.1): detection, Algorithm 2 matching,
triangulation (eqs 4.1-4.3) for an ideal parallel rig and a calibrated rig with lens
distortion, on synthetic images. Accuracy target: the thesis' 0.5 mm camera accuracy."""

import cv2
import numpy as np
import pytest

from jaxrkpm.rig.stereo import AmbiguousMatchError, CalibratedStereo, MarkerCountError, ParallelStereo, StereoFrame, StereoTracker, auto_threshold, detect_blobs, draw_blobs, match_by_row, render_markers

ACCURACY_M = 0.5e-3          # thesis: camera accuracy 0.5 mm
ROW_TOL_PX = 2.0


def parallel_rig():
    return ParallelStereo(focal_px=900.0, baseline_m=0.12, cx=511.5, cy=383.5,
                          image_size=(1024, 768))


def bumblebee_rig():
    return ParallelStereo.bumblebee_like(image_size=(640, 480))


def calibrated_rig():
    K1 = np.array([[910.0, 0, 515.2], [0, 912.0, 380.7], [0, 0, 1]])
    K2 = np.array([[905.0, 0, 508.9], [0, 906.5, 388.1], [0, 0, 1]])
    D1 = np.array([-0.25, 0.08, 0.001, -0.0005, 0.0])    # strong barrel distortion
    D2 = np.array([-0.22, 0.06, -0.0008, 0.0006, 0.0])
    R, _ = cv2.Rodrigues(np.array([0.004, -0.012, 0.003]))   # ~0.7 deg misalignment
    T = np.array([-0.12, 0.0008, -0.0005])                   # right camera ~0.12 m right
    return CalibratedStereo(K1, D1, K2, D2, R, T, image_size=(1024, 768))


def random_markers(rng, camera, n, min_row_gap_px=4 * ROW_TOL_PX, margin_px=20):
    """n marker positions at 0.4-0.5 m, visible in both images with rectified rows at
    least min_row_gap_px apart (so the row matching is unambiguous)."""
    w, h = camera.image_size
    for _ in range(2000):  # rejection sampling, bounded
        Z = rng.uniform(0.40, 0.50, n)
        f = camera.focal_px if isinstance(camera, ParallelStereo) else camera.K1[0, 0]
        # centred between the cameras, spread over ~60% of the image width/height
        X = camera.baseline_m / 2 + rng.uniform(-0.3, 0.3, n) * w * Z / f
        Y = rng.uniform(-0.3, 0.3, n) * h * Z / f
        P = np.c_[X, Y, Z]
        l, r = camera.project(P)
        inside = all(np.all((uv > margin_px) & (uv < np.array([w, h]) - margin_px))
                     for uv in (l, r))
        rows = np.sort(camera.rectify(l, "left")[:, 1])
        if inside and np.all(np.diff(rows) > min_row_gap_px):
            return P
    raise AssertionError("could not sample a marker set")


def by_left_row(P, camera):
    """Ground truth in the tracker's output order (left-image row)."""
    l, _ = camera.project(P)
    return P[np.argsort(camera.rectify(l, "left")[:, 1])]


def tracking_errors(camera, n_sets, n_markers, seed, noise_std=2.0):
    rng = np.random.default_rng(seed)
    tracker = StereoTracker(camera, n_markers, row_tol_px=ROW_TOL_PX)
    errs = []
    for _ in range(n_sets):
        P = random_markers(rng, camera, n_markers)
        left, right = render_markers(P, camera, radius_px=3.0, noise_std=noise_std, rng=rng)
        frame = tracker.track(left, right)
        assert frame.ok, frame.message
        errs.append(np.linalg.norm(frame.points_m - by_left_row(P, camera), axis=1))
    return np.concatenate(errs)


# ----------------------------------------------------------------------------- detection


@pytest.mark.parametrize("threshold", [None, 60.0])
def test_detect_blobs_subpixel_centroids(threshold):
    rng = np.random.default_rng(0)
    uv = np.array([[100.3, 50.7], [400.81, 300.25], [600.5, 120.0], [33.05, 450.9]])
    img = draw_blobs((640, 480), uv, radius_px=3.0, noise_std=2.0, rng=rng)
    assert img.shape == (480, 640) and img.dtype == np.uint8
    found = detect_blobs(img, threshold=threshold)
    assert found.shape == (4, 2)
    truth = uv[np.lexsort((uv[:, 0], uv[:, 1]))]   # detect_blobs sorts by row
    assert np.abs(found - truth).max() < 0.03      # pixels


@pytest.mark.parametrize("noise_std", [4.0, 8.0, 16.0])
def test_auto_threshold_survives_noise_where_plain_otsu_fails(noise_std):
    rng = np.random.default_rng(1)
    uv = np.array([[100.3, 50.7], [400.8, 300.2], [600.5, 120.0]])
    img = draw_blobs((640, 480), uv, radius_px=3.0, noise_std=noise_std, rng=rng)
    otsu, _ = cv2.threshold(img, 0, 255, cv2.THRESH_BINARY | cv2.THRESH_OTSU)
    n_otsu = cv2.connectedComponentsWithStats((img > otsu).astype(np.uint8))[0] - 1
    assert n_otsu > 100                     # Otsu alone splits the background noise
    assert auto_threshold(img) > otsu
    found = detect_blobs(img)
    assert found.shape == (3, 2)
    assert np.abs(found - uv[np.lexsort((uv[:, 0], uv[:, 1]))]).max() < 0.02 * noise_std


def test_parallel_rig_below_half_mm_at_high_pixel_noise():
    errs = tracking_errors(parallel_rig(), n_sets=6, n_markers=5, seed=13, noise_std=8.0)
    assert errs.max() < ACCURACY_M


def test_detect_blobs_rejects_specks_and_accepts_colour_and_float():
    img = draw_blobs((320, 240), [[100.0, 100.0]], radius_px=3.0)
    img[20, 30] = 255                               # hot pixel: area 1 < min_area
    assert detect_blobs(img).shape == (1, 2)
    assert detect_blobs(img, min_area=1).shape == (2, 2)
    bgr = np.repeat(img[:, :, None], 3, axis=2)
    assert np.allclose(detect_blobs(bgr), detect_blobs(img))
    assert np.allclose(detect_blobs(img.astype(np.float32) / 255.0), detect_blobs(img), atol=1e-6)
    assert detect_blobs(np.zeros((50, 60), np.uint8)).shape == (0, 2)


# ----------------------------------------------------------------------------- geometry


def test_parallel_projection_triangulation_roundtrip_exact():
    cam = parallel_rig()
    P = np.array([[0.01, -0.02, 0.45], [-0.05, 0.03, 0.41], [0.08, 0.0, 0.5]])
    l, r = cam.project(P)
    assert np.allclose(l[:, 1], r[:, 1])                  # same row: rectified
    assert np.all(l[:, 0] - r[:, 0] > 0)                  # positive disparity
    # eq 4.1: Z = f b / d
    assert np.allclose(cam.focal_px * cam.baseline_m / (l[:, 0] - r[:, 0]), P[:, 2], rtol=1e-14)
    assert np.abs(cam.triangulate(l, r) - P).max() < 1e-14
    with pytest.raises(ValueError, match="disparity"):
        cam.triangulate(r, l)


def test_bumblebee_like_focal():
    cam = bumblebee_rig()
    assert cam.focal_px == pytest.approx(3.8e-3 / 4.65e-6)   # ~817 px
    assert cam.baseline_m == 0.12 and cam.image_size == (640, 480)


def test_calibrated_rectification_aligns_rows_and_triangulates_exactly():
    cam = calibrated_rig()
    rng = np.random.default_rng(3)
    P = np.c_[rng.uniform(-0.1, 0.1, 20), rng.uniform(-0.08, 0.08, 20), rng.uniform(0.4, 0.5, 20)]
    l, r = cam.project(P)
    rl, rr = cam.rectify(l, "left"), cam.rectify(r, "right")
    assert np.abs(rl[:, 1] - rr[:, 1]).max() < 1e-8      # rows agree after rectification
    assert np.abs(cam.triangulate(l, r) - P).max() < 1e-10


@pytest.mark.parametrize("rig", [parallel_rig, bumblebee_rig], ids=["f900_1024x768", "bumblebee_640x480"])
def test_parallel_rig_recovers_markers_below_half_mm(rig):
    errs = tracking_errors(rig(), n_sets=6, n_markers=5, seed=11)
    assert errs.size == 30
    assert errs.max() < ACCURACY_M
    assert np.median(errs) < 0.1e-3


def test_calibrated_rig_recovers_markers_below_half_mm_and_undoes_distortion():
    cam = calibrated_rig()
    errs = tracking_errors(cam, n_sets=6, n_markers=5, seed=12)
    assert errs.max() < ACCURACY_M
    assert np.median(errs) < 0.1e-3

    # the same images read with a model that ignores distortion are far off: the
    # test above passes because the distortion is undone, not because it is negligible
    naive = CalibratedStereo(cam.K1, np.zeros(5), cam.K2, np.zeros(5), cam.R, cam.T,
                             cam.image_size)
    rng = np.random.default_rng(12)
    P = random_markers(rng, cam, 5)
    left, right = render_markers(P, cam, radius_px=3.0, noise_std=2.0, rng=rng)
    frame = StereoTracker(cam, 5).track(left, right)
    l, r = frame.left_uv, frame.right_uv
    assert np.linalg.norm(naive.triangulate(l, r) - frame.points_m, axis=1).max() > 5 * ACCURACY_M


# ----------------------------------------------------------------------------- failures


def _images_with(cam, P, drop_left=(), drop_right=(), extra_left=(), extra_right=(), seed=0):
    rng = np.random.default_rng(seed)
    l, r = cam.project(P)
    l = np.delete(l, list(drop_left), axis=0)
    r = np.delete(r, list(drop_right), axis=0)
    l = np.vstack([l, np.reshape(extra_left, (-1, 2))])
    r = np.vstack([r, np.reshape(extra_right, (-1, 2))])
    kw = dict(radius_px=3.0, noise_std=2.0, rng=rng)
    return draw_blobs(cam.image_size, l, **kw), draw_blobs(cam.image_size, r, **kw)


def test_occluded_marker_is_reported():
    cam = parallel_rig()
    P = random_markers(np.random.default_rng(5), cam, 4)
    left, right = _images_with(cam, P, drop_right=[2])
    tracker = StereoTracker(cam, 4)
    with pytest.raises(MarkerCountError, match=r"right image: found 3 blobs, expected 4") as ei:
        tracker.track(left, right, strict=True)
    assert (ei.value.image, ei.value.n_left, ei.value.n_right, ei.value.n_expected) == ("right", 4, 3, 4)
    frame = tracker.track(left, right)            # default: flagged frame, not an exception
    assert isinstance(frame, StereoFrame) and not frame.ok
    assert "right image" in frame.message and frame.points_m.shape == (4, 3)
    assert np.all(np.isnan(frame.points_m))
    with pytest.raises(MarkerCountError):
        frame.raise_if_bad()


def test_glare_blob_is_reported():
    cam = parallel_rig()
    P = random_markers(np.random.default_rng(6), cam, 4)
    left, right = _images_with(cam, P, extra_left=[[50.0, 60.0]])
    frame = StereoTracker(cam, 4).track(left, right)
    assert not frame.ok and frame.error.image == "left"
    assert (frame.n_left, frame.n_right) == (5, 4)
    assert "left image: found 5 blobs, expected 4" in frame.message

    left, right = _images_with(cam, P, drop_left=[0], extra_right=[[50.0, 60.0]])
    with pytest.raises(MarkerCountError) as ei:
        StereoTracker(cam, 4).track(left, right, strict=True)
    assert ei.value.image == "both" and (ei.value.n_left, ei.value.n_right) == (3, 5)


def test_glare_that_keeps_the_count_but_breaks_the_rows_is_reported():
    # one marker hidden in the right image and a glare spot elsewhere: counts match,
    # but the glare has no row partner -> an error, not a wrong 3D point
    cam = parallel_rig()
    P = random_markers(np.random.default_rng(7), cam, 4)
    l, _ = cam.project(P)
    glare = [[300.0, np.max(l[:, 1]) + 40.0]]
    left, right = _images_with(cam, P, drop_right=[1], extra_right=glare)
    frame = StereoTracker(cam, 4).track(left, right)
    assert not frame.ok and isinstance(frame.error, AmbiguousMatchError)
    assert np.all(np.isnan(frame.points_m))


def test_same_row_markers_are_ambiguous_unless_ordering_is_allowed():
    cam = parallel_rig()
    P = np.array([[-0.05, 0.02, 0.45], [0.04, 0.02, 0.45], [0.0, -0.05, 0.42]])
    left, right = render_markers(P, cam, radius_px=3.0, noise_std=2.0,
                                 rng=np.random.default_rng(1))
    with pytest.raises(AmbiguousMatchError, match="ambiguous"):
        StereoTracker(cam, 3).track(left, right, strict=True)
    frame = StereoTracker(cam, 3, same_row="order").track(left, right, strict=True)
    truth = P[[2, 0, 1]]     # left order: row, then column
    assert np.linalg.norm(frame.points_m - truth, axis=1).max() < ACCURACY_M


def test_match_by_row_unit():
    left = np.array([[300.0, 100.0], [200.0, 200.0], [400.0, 300.0]])
    right = np.array([[350.0, 300.5], [150.0, 199.2], [260.0, 100.4]])   # shuffled
    m = match_by_row(left, right, 3)
    assert m.ok and m.points_m is None
    assert np.array_equal(m.right_uv, right[[2, 1, 0]])
    with pytest.raises(MarkerCountError, match="left image: found 3 blobs, expected 4"):
        match_by_row(left, right, 4)
    bad = right.copy()
    bad[0, 1] = 310.0                      # outside row_tol
    with pytest.raises(AmbiguousMatchError, match="no right-image blob"):
        match_by_row(left, bad, 3)
    flagged = match_by_row(left, bad, 3, strict=False)
    assert not flagged.ok and np.all(np.isnan(flagged.left_uv))
    neg = right.copy()
    neg[:, 0] += 200.0                     # negative disparity: behind the cameras
    with pytest.raises(AmbiguousMatchError):
        match_by_row(left, neg, 3)


def test_tracker_keeps_marker_identity_when_rows_swap():
    cam = parallel_rig()
    P0 = np.array([[-0.06, 0.010, 0.45], [0.05, 0.014, 0.45], [0.0, -0.06, 0.43]])
    P1 = P0.copy()
    P1[0, 1] = 0.020                        # marker 0 moves below marker 1 in the image
    rng = np.random.default_rng(2)
    tracker = StereoTracker(cam, 3, reference_points_m=P0)
    for P in (P0, P1):
        frame = tracker.track(*render_markers(P, cam, noise_std=2.0, rng=rng))
        assert frame.ok
        assert np.linalg.norm(frame.points_m - P, axis=1).max() < ACCURACY_M
