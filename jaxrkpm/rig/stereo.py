"""Stereo vision for marker tracking (thesis section 4.2.1, Algorithm 2, eqs 4.1-4.3).

Pipeline: binarise + segment each image into blobs (IR LED markers), match left/right
blobs by image row (Algorithm 2, valid for a rectified / parallel rig), triangulate.

Conventions used throughout this module:

* pixel coordinates ``(u, v)``: ``u`` = column, ``v`` = row, integer values at pixel
  *centres* (the OpenCV convention, so ``cv2.projectPoints`` and our centroids agree);
* image sizes are ``(width_px, height_px)`` as in OpenCV; image arrays are ``(H, W)``;
* the camera frame is the LEFT camera's: origin at its optical centre, X right, Y down
  (along image rows), Z forward along the optical axis; all 3D coordinates in metres.

Nothing here imports the jaxrkpm solver core.
"""

from __future__ import annotations

import dataclasses
from typing import Protocol

import cv2
import numpy as np

__all__ = [
    "MarkerCountError",
    "AmbiguousMatchError",
    "StereoFrame",
    "auto_threshold",
    "detect_blobs",
    "match_by_row",
    "ParallelStereo",
    "CalibratedStereo",
    "draw_blobs",
    "render_markers",
    "StereoTracker",
]

# cv2.undistortPoints iterates a fixed-point scheme; its default (a handful of iterations)
# leaves ~1e-3 px of error under strong radial distortion. Converge it fully: it is cheap
# for a few markers and removes one error source from the accuracy budget.
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-14)


def _undistort(uv, K, D, R, P):
    # OpenCV 4.x takes the criteria only in undistortPointsIter; 5.x folded it into
    # undistortPoints (and dropped undistortPointsIter). pyproject allows both.
    if hasattr(cv2, "undistortPointsIter"):
        return cv2.undistortPointsIter(uv, K, D, R, P, _UNDISTORT_CRITERIA)
    return cv2.undistortPoints(uv, K, D, R=R, P=P, criteria=_UNDISTORT_CRITERIA)


# ----------------------------------------------------------------------------- errors


class MarkerCountError(ValueError):
    """The images do not show exactly the expected markers, or they cannot be paired.

    Attributes: ``image`` ('left', 'right', 'both' or 'match'), ``n_left``, ``n_right``,
    ``n_expected`` (blob counts; ``None`` where not known).
    """

    def __init__(self, message: str, *, image: str, n_left: int | None,
                 n_right: int | None, n_expected: int | None):
        super().__init__(message)
        self.image = image
        self.n_left = n_left
        self.n_right = n_right
        self.n_expected = n_expected


class AmbiguousMatchError(MarkerCountError):
    """Blob counts are right but the row matching is not unique (or a blob has no partner)."""


# ----------------------------------------------------------------------------- frame


@dataclasses.dataclass(frozen=True)
class StereoFrame:
    """Result of matching (and, from :class:`StereoTracker`, triangulating) one image pair.

    ``left_uv``/``right_uv``: (n_expected, 2) matched pixel coordinates, row i of each is
    the same marker (from :func:`match_by_row`: the coordinates it was given; from
    :class:`StereoTracker`: the raw detected centroids, before rectification). ``points_m``: (n_expected, 3) metres in the left-camera frame, or
    ``None`` when only matching was done. When ``ok`` is False every array is NaN-filled
    (shapes stay fixed so downstream code cannot silently use a wrong match) and
    ``message`` / ``error`` say what went wrong.
    """

    ok: bool
    message: str
    left_uv: np.ndarray
    right_uv: np.ndarray
    points_m: np.ndarray | None
    n_left: int
    n_right: int
    n_expected: int
    error: MarkerCountError | None = None

    def raise_if_bad(self) -> "StereoFrame":
        """Raise the stored error if the frame is flagged, else return self."""
        if not self.ok:
            assert self.error is not None
            raise self.error
        return self

    @classmethod
    def flagged(cls, err: MarkerCountError, n_expected: int, with_points: bool) -> "StereoFrame":
        nan2 = np.full((n_expected, 2), np.nan)
        return cls(ok=False, message=str(err), left_uv=nan2, right_uv=nan2.copy(),
                   points_m=np.full((n_expected, 3), np.nan) if with_points else None,
                   n_left=-1 if err.n_left is None else err.n_left,
                   n_right=-1 if err.n_right is None else err.n_right,
                   n_expected=n_expected, error=err)


# ----------------------------------------------------------------------------- detection


_BGR_WEIGHTS = np.array([0.114, 0.587, 0.299])   # cv2.COLOR_BGR2GRAY's


def _to_gray(image: np.ndarray) -> np.ndarray:
    """(H, W) grey image of any real dtype; a clear error for an empty image, a non-numeric
    one or non-finite pixels (a NaN would silently remove every blob)."""
    img = np.asarray(image)
    if img.dtype == bool or not (np.issubdtype(img.dtype, np.integer) or np.issubdtype(img.dtype, np.floating)):
        raise TypeError(f"image must hold real pixel values (uint8, uint16, float ...), got dtype {img.dtype}")
    if img.ndim == 3:
        if img.shape[2] == 1:
            img = img[:, :, 0]
        elif img.shape[2] in (3, 4) and img.dtype in (np.uint8, np.uint16, np.float32):
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY if img.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
        elif img.shape[2] in (3, 4):   # dtypes cv2.cvtColor refuses (float64, int32 ...)
            img = img[:, :, :3].astype(np.float64) @ _BGR_WEIGHTS
    if img.ndim != 2:
        raise ValueError(f"image must be (H, W) or (H, W, C) with C in 1, 3, 4; got shape {np.shape(image)}")
    if img.size == 0:
        raise ValueError(f"image is empty (shape {np.shape(image)})")
    if np.issubdtype(img.dtype, np.floating):
        bad = ~np.isfinite(img)
        if bad.any():
            r, c = (int(x[0]) for x in np.nonzero(bad))
            raise ValueError(f"image has {int(bad.sum())} NaN/inf pixels (first at row {r}, column {c}): "
                             "replace them (e.g. np.nan_to_num) before blob detection")
    return img


def auto_threshold(image: np.ndarray, noise_k: float = 6.0) -> float:
    """Binarisation level for bright markers on a dark, noisy background (image units).

    Otsu's method, floored at ``median + noise_k * sigma`` (sigma = 1.4826 * MAD, a robust
    estimate of the background noise). Why the floor: Otsu assumes two classes of
    comparable size; a few small LEDs are ~0.01% of the pixels, so once the noise exceeds a
    couple of grey levels Otsu splits the background itself (thousands of noise "blobs").
    At 6 sigma a Gaussian background gives ~1e-9 false pixels per pixel.
    """
    f = _to_gray(image).astype(np.float64)
    lo, hi = float(f.min()), float(f.max())
    if hi <= lo:
        return hi  # flat image: nothing is above it
    g8 = np.clip(np.rint((f - lo) * (255.0 / (hi - lo))), 0, 255).astype(np.uint8)
    t8, _ = cv2.threshold(g8, 0, 255, cv2.THRESH_BINARY | cv2.THRESH_OTSU)
    otsu = lo + float(t8) * (hi - lo) / 255.0
    med = float(np.median(f))
    sigma = 1.4826 * float(np.median(np.abs(f - med)))
    return max(otsu, med + noise_k * sigma)


def detect_blobs(image: np.ndarray, threshold: float | None = None, min_area: int = 4,
                 max_area: int | None = None, grow_px: int = 2) -> np.ndarray:
    """Bright blobs in a dark image -> sub-pixel centroids.

    Args:
      image: (H, W) grey image (uint8, or any real dtype; (H, W, 3) BGR is converted).
      threshold: fixed binarisation level in image units (pixels > threshold are blob);
        ``None`` = :func:`auto_threshold` (Otsu, floored by a robust noise estimate).
      min_area: components smaller than this many pixels are rejected as noise specks.
      max_area: components larger than this are rejected (large glare patches); None = no cap.
      grow_px: the centroid is taken over each component dilated by this many pixels, so
        the dim tails of the spot (lost by the threshold) count too: a mask edge that
        flickers with noise at a high threshold would otherwise jitter the centroid.

    Returns:
      (n, 2) float64 array of (u, v) pixel centroids, intensity-weighted (weight = pixel
      value above the image median, the background level), sorted by row v then column u.
    """
    gray = _to_gray(image)
    f = gray.astype(np.float64)
    level = auto_threshold(gray) if threshold is None else float(threshold)
    binary = (f > level).astype(np.uint8)
    n_lab, labels, stats, _ = cv2.connectedComponentsWithStats(binary, connectivity=8,
                                                               ltype=cv2.CV_32S)
    background = float(np.median(f))
    weight_img = np.clip(f - background, 0.0, None)
    H, W = f.shape
    out = []
    kernel = np.ones((2 * grow_px + 1, 2 * grow_px + 1), np.uint8) if grow_px > 0 else None
    for k in range(1, n_lab):  # label 0 is the background
        x, y, w, h, area = (int(s) for s in stats[k])
        if area < min_area or (max_area is not None and area > max_area):
            continue
        x0, y0 = max(x - grow_px, 0), max(y - grow_px, 0)
        x1, y1 = min(x + w + grow_px, W), min(y + h + grow_px, H)
        lab = labels[y0:y1, x0:x1]
        mask = (lab == k).astype(np.uint8)
        if kernel is not None:
            # grow into background pixels only, never into a neighbouring blob
            mask = cv2.dilate(mask, kernel) & ((lab == k) | (lab == 0)).astype(np.uint8)
        wts = weight_img[y0:y1, x0:x1] * mask
        s = wts.sum()
        if s <= 0.0:
            continue
        vv, uu = np.mgrid[y0:y1, x0:x1]
        out.append(((wts * uu).sum() / s, (wts * vv).sum() / s))
    if not out:
        return np.zeros((0, 2))
    uv = np.asarray(out, dtype=np.float64)
    return uv[np.lexsort((uv[:, 0], uv[:, 1]))]


# ----------------------------------------------------------------------------- matching


def match_by_row(left: np.ndarray, right: np.ndarray, n_expected: int, row_tol: float = 2.0,
                 *, strict: bool = True, min_disparity_px: float = 0.0,
                 same_row: str = "raise") -> StereoFrame:
    """Pair left/right blobs by image row (thesis Algorithm 2) for a rectified rig.

    In a rectified (parallel) rig a marker appears on the same row in both images and
    further left in the right image (disparity ``u_left - u_right > 0``). Algorithm 2 pairs
    each left blob with the right blob of nearest row; we add the checks that make a wrong
    pairing impossible to miss: exact blob counts, a partner within ``row_tol`` pixels with
    disparity > ``min_disparity_px``, and uniqueness.

    Args:
      left, right: (n_l, 2) and (n_r, 2) rectified pixel coordinates (u, v).
      n_expected: the number of markers that must be visible in both images.
      row_tol: max |v_left - v_right| in pixels for a pair (centroid noise + rectification
        error).
      strict: True -> raise :class:`MarkerCountError` on failure; False -> return a
        flagged :class:`StereoFrame` (``ok=False``, NaN arrays).
      min_disparity_px: pairs with smaller disparity are not candidates (point behind the
        cameras or at infinity).
      same_row: what to do when several markers share a row band: ``"raise"`` (the
        thesis' rule has no answer: :class:`AmbiguousMatchError`), or ``"order"``: pair
        them left-to-right (the ordering constraint; true for markers on one surface
        with no large depth jumps between them).

    Returns:
      :class:`StereoFrame` with ``points_m=None``; row i of ``left_uv`` and ``right_uv``
      is one marker, in the order of the left blobs (by row, then column).
    """
    if same_row not in ("raise", "order"):
        raise ValueError(f"same_row must be 'raise' or 'order', got {same_row!r}")
    left = np.asarray(left, dtype=np.float64).reshape(-1, 2)
    right = np.asarray(right, dtype=np.float64).reshape(-1, 2)
    nl, nr = len(left), len(right)
    try:
        pairs = _match_pairs(left, right, n_expected, row_tol, min_disparity_px, same_row)
    except MarkerCountError as err:
        if strict:
            raise
        return StereoFrame.flagged(err, n_expected, with_points=False)
    li, ri = pairs[:, 0], pairs[:, 1]
    return StereoFrame(ok=True, message="ok", left_uv=left[li], right_uv=right[ri],
                       points_m=None, n_left=nl, n_right=nr, n_expected=n_expected)


def _count_hint(n: int, n_expected: int) -> str:
    if n < n_expected:
        return "missing blob: occluded or out-of-view marker?"
    return "extra blob: glare or reflection?"


def _match_pairs(left, right, n_expected, row_tol, min_disp, same_row) -> np.ndarray:
    nl, nr = len(left), len(right)
    bad = [(side, n) for side, n in (("left", nl), ("right", nr)) if n != n_expected]
    if bad:
        side = bad[0][0] if len(bad) == 1 else "both"
        parts = "; ".join(f"{s} image: found {n} blobs, expected {n_expected} "
                          f"({_count_hint(n, n_expected)})" for s, n in bad)
        raise MarkerCountError(parts, image=side, n_left=nl, n_right=nr, n_expected=n_expected)
    kw = dict(image="match", n_left=nl, n_right=nr, n_expected=n_expected)
    drow = np.abs(left[:, None, 1] - right[None, :, 1])          # (nl, nr)
    disp = left[:, None, 0] - right[None, :, 0]
    cand = (drow <= row_tol) & (disp > min_disp)
    pairs = []
    if same_row == "raise":
        for i in range(nl):
            js = np.flatnonzero(cand[i])
            if len(js) != 1:
                raise AmbiguousMatchError(_describe(i, left, js, right, row_tol), **kw)
            pairs.append((i, int(js[0])))
    else:
        # connected groups of the bipartite candidate graph, paired left-to-right in u
        seen_l = np.zeros(nl, bool)
        for i0 in range(nl):
            if seen_l[i0]:
                continue
            gl, gr = {i0}, set()
            frontier_l = [i0]
            for _ in range(nl + nr):  # bounded BFS over the candidate graph
                if not frontier_l:
                    break
                new_r = set(np.flatnonzero(cand[frontier_l].any(0)).tolist()) - gr
                gr |= new_r
                new_l = set(np.flatnonzero(cand[:, sorted(new_r)].any(1)).tolist()) - gl \
                    if new_r else set()
                gl |= new_l
                frontier_l = sorted(new_l)
            seen_l[list(gl)] = True
            gl_s = sorted(gl, key=lambda a: left[a, 0])
            gr_s = sorted(gr, key=lambda b: right[b, 0])
            if len(gl_s) != len(gr_s):
                raise AmbiguousMatchError(
                    f"row band near v={left[i0, 1]:.1f}px holds {len(gl_s)} left and "
                    f"{len(gr_s)} right blobs within row_tol={row_tol}px", **kw)
            for a, b in zip(gl_s, gr_s):
                if not cand[a, b]:
                    raise AmbiguousMatchError(
                        f"ordering constraint fails in row band near v={left[a, 1]:.1f}px "
                        f"(left blob {a} vs right blob {b})", **kw)
                pairs.append((a, b))
        pairs.sort()
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    if len(np.unique(pairs[:, 1])) != len(pairs):
        raise AmbiguousMatchError("two left blobs paired with the same right blob", **kw)
    return pairs


def _describe(i, left, js, right, row_tol) -> str:
    u, v = left[i]
    if len(js) == 0:
        return (f"left blob {i} at (u={u:.1f}, v={v:.1f})px has no right-image blob within "
                f"row_tol={row_tol}px with positive disparity")
    rows = ", ".join(f"{right[j, 1]:.1f}" for j in js)
    return (f"left blob {i} at (u={u:.1f}, v={v:.1f})px has {len(js)} right-image "
            f"candidates on rows [{rows}] within row_tol={row_tol}px (ambiguous; "
            f"same_row='order' pairs them left-to-right)")


# ----------------------------------------------------------------------------- cameras


class StereoCamera(Protocol):
    """What :func:`render_markers` and :class:`StereoTracker` need from a rig model."""

    image_size: tuple[int, int]

    def project(self, points_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...

    def rectify(self, uv: np.ndarray, side: str) -> np.ndarray: ...

    def triangulate_rectified(self, left_rect: np.ndarray,
                              right_rect: np.ndarray) -> np.ndarray: ...


@dataclasses.dataclass(frozen=True)
class ParallelStereo:
    """Ideal parallel-axis stereo rig (thesis Figure 4.7, eqs 4.1-4.3).

    Both cameras share focal length and principal point; the right camera sits at
    X = +baseline_m in the left camera frame, with parallel optical axes, so the images
    are already rectified.

    Attributes:
      focal_px: focal length in pixels (thesis' f / W_p: focal length over pixel pitch).
      baseline_m: distance between the optical centres, metres.
      cx, cy: principal point, pixels.
      image_size: (width_px, height_px).
    """

    focal_px: float
    baseline_m: float
    cx: float
    cy: float
    image_size: tuple[int, int] = (1024, 768)

    def __post_init__(self):
        if not (self.focal_px > 0 and self.baseline_m > 0):
            raise ValueError(f"focal_px and baseline_m must be > 0; got {self.focal_px}, "
                             f"{self.baseline_m}")

    @classmethod
    def from_physical(cls, focal_length_mm: float, pixel_pitch_um: float, baseline_m: float,
                      image_size: tuple[int, int] = (1024, 768)) -> "ParallelStereo":
        """Rig from lens focal length (mm) and pixel pitch (micrometres); centred principal point."""
        f_px = focal_length_mm * 1e-3 / (pixel_pitch_um * 1e-6)
        w, h = image_size
        return cls(f_px, baseline_m, (w - 1) / 2.0, (h - 1) / 2.0, tuple(image_size))

    @classmethod
    def bumblebee_like(cls, image_size: tuple[int, int] = (1024, 768)) -> "ParallelStereo":
        """A Bumblebee2-like rig: 3.8 mm lens, 4.65 um pixels (f ~ 817 px), 0.12 m baseline."""
        return cls.from_physical(3.8, 4.65, 0.12, image_size)

    def project(self, points_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(n, 3) metres in the left-camera frame -> ((n, 2) left, (n, 2) right) pixels."""
        P = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
        if np.any(P[:, 2] <= 0):
            raise ValueError("points must be in front of the cameras (Z > 0)")
        f = self.focal_px
        v = f * P[:, 1] / P[:, 2] + self.cy
        ul = f * P[:, 0] / P[:, 2] + self.cx
        ur = f * (P[:, 0] - self.baseline_m) / P[:, 2] + self.cx
        return np.c_[ul, v], np.c_[ur, v]

    def rectify(self, uv: np.ndarray, side: str) -> np.ndarray:
        """Identity: a parallel rig's images are rectified already. (n, 2) -> (n, 2)."""
        return np.asarray(uv, dtype=np.float64).reshape(-1, 2).copy()

    def triangulate_rectified(self, left_rect, right_rect) -> np.ndarray:
        return self.triangulate(left_rect, right_rect)

    def triangulate(self, left_uv: np.ndarray, right_uv: np.ndarray) -> np.ndarray:
        """Matched pixel pairs -> (n, 3) points in metres, left-camera frame (eqs 4.1-4.3).

        Z = f B / d with disparity d = u_left - u_right (px); X = (u_left - cx) Z / f;
        Y = (v - cy) Z / f, with v the mean of both rows (both are equally noisy
        measurements of the same row, so averaging halves the variance of Y).
        Raises ValueError for a non-positive disparity.
        """
        L = np.asarray(left_uv, dtype=np.float64).reshape(-1, 2)
        R = np.asarray(right_uv, dtype=np.float64).reshape(-1, 2)
        if L.shape != R.shape:
            raise ValueError(f"left/right shapes differ: {L.shape} vs {R.shape}")
        d = L[:, 0] - R[:, 0]
        if np.any(d <= 0):
            raise ValueError(f"non-positive disparity for markers {np.flatnonzero(d <= 0)}")
        f = self.focal_px
        Z = f * self.baseline_m / d
        X = (L[:, 0] - self.cx) * Z / f
        Y = (0.5 * (L[:, 1] + R[:, 1]) - self.cy) * Z / f
        return np.c_[X, Y, Z]


class CalibratedStereo:
    """Real (calibrated) stereo rig: OpenCV model with lens distortion.

    Args:
      K1, K2: (3, 3) intrinsic matrices of the left / right camera (pixels).
      D1, D2: distortion coefficients (k1, k2, p1, p2[, k3 ...]) in OpenCV order.
      R: (3, 3) rotation and T: (3,) translation in METRES taking left-camera coordinates
        to right-camera coordinates, X_right = R X_left + T (cv2.stereoCalibrate's R, T;
        a right camera 0.12 m to the right has T ~ (-0.12, 0, 0)).
      image_size: (width_px, height_px).

    Rectification (cv2.stereoRectify, zero-disparity flag so both rectified principal
    points coincide) is computed once; detected centroids are undistorted and rectified
    with cv2.undistortPoints, matched by rectified row, and triangulated with
    cv2.triangulatePoints; results are rotated back to the (unrectified) left camera frame.
    """

    def __init__(self, K1, D1, K2, D2, R, T, image_size: tuple[int, int]):
        self.K1 = np.asarray(K1, np.float64).reshape(3, 3)
        self.K2 = np.asarray(K2, np.float64).reshape(3, 3)
        self.D1 = np.asarray(D1, np.float64).ravel()
        self.D2 = np.asarray(D2, np.float64).ravel()
        self.R = np.asarray(R, np.float64).reshape(3, 3)
        self.T = np.asarray(T, np.float64).ravel()
        if self.T.shape != (3,):
            raise ValueError(f"T must have 3 entries (metres); got {self.T.shape}")
        if not np.allclose(self.R @ self.R.T, np.eye(3), atol=1e-9) or np.linalg.det(self.R) < 0:
            raise ValueError("R must be a proper rotation matrix")
        self.image_size = (int(image_size[0]), int(image_size[1]))
        R1, R2, P1, P2, Q, _, _ = cv2.stereoRectify(
            self.K1, self.D1, self.K2, self.D2, self.image_size, self.R, self.T.reshape(3, 1),
            flags=cv2.CALIB_ZERO_DISPARITY, alpha=-1)
        self.R1, self.R2, self.P1, self.P2, self.Q = R1, R2, P1, P2, Q
        if abs(P2[1, 3]) > abs(P2[0, 3]):
            raise ValueError("vertical stereo rig: row matching needs a horizontal baseline")
        self._rvec_r, _ = cv2.Rodrigues(self.R)

    @property
    def baseline_m(self) -> float:
        return float(np.linalg.norm(self.T))

    def project(self, points_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(n, 3) metres, left-camera frame -> distorted raw pixels ((n, 2) left, (n, 2) right)."""
        P = np.asarray(points_m, dtype=np.float64).reshape(-1, 3)
        zero = np.zeros(3)
        l, _ = cv2.projectPoints(P, zero, zero, self.K1, self.D1)
        r, _ = cv2.projectPoints(P, self._rvec_r, self.T, self.K2, self.D2)
        return l.reshape(-1, 2), r.reshape(-1, 2)

    def rectify(self, uv: np.ndarray, side: str) -> np.ndarray:
        """Raw (distorted) pixels (n, 2) -> rectified pixels (n, 2) of camera ``side``."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 1, 2)
        if uv.shape[0] == 0:
            return np.zeros((0, 2))
        if side == "left":
            K, D, Rr, P = self.K1, self.D1, self.R1, self.P1
        elif side == "right":
            K, D, Rr, P = self.K2, self.D2, self.R2, self.P2
        else:
            raise ValueError(f"side must be 'left' or 'right', got {side!r}")
        return _undistort(uv, K, D, Rr, P).reshape(-1, 2)

    def triangulate_rectified(self, left_rect: np.ndarray, right_rect: np.ndarray) -> np.ndarray:
        """Rectified pixel pairs (n, 2), (n, 2) -> (n, 3) metres in the LEFT camera frame."""
        L = np.asarray(left_rect, np.float64).reshape(-1, 2)
        Rr = np.asarray(right_rect, np.float64).reshape(-1, 2)
        if L.shape != Rr.shape:
            raise ValueError(f"left/right shapes differ: {L.shape} vs {Rr.shape}")
        if len(L) == 0:
            return np.zeros((0, 3))
        Xh = cv2.triangulatePoints(self.P1, self.P2, L.T.copy(), Rr.T.copy())  # (4, n)
        if np.any(np.abs(Xh[3]) < 1e-300):
            raise ValueError("point at infinity (zero disparity)")
        X_rect = (Xh[:3] / Xh[3]).T
        # rectified-left frame -> original left frame: X_rect = R1 X_left
        return X_rect @ self.R1

    def triangulate(self, left_uv: np.ndarray, right_uv: np.ndarray) -> np.ndarray:
        """Matched RAW pixel pairs -> (n, 3) metres in the left camera frame."""
        return self.triangulate_rectified(self.rectify(left_uv, "left"),
                                          self.rectify(right_uv, "right"))


# ----------------------------------------------------------------------------- rendering


def draw_blobs(image_size: tuple[int, int], uv: np.ndarray, radius_px: float = 3.0, *,
               peak: float = 220.0, background: float = 12.0, noise_std: float = 0.0,
               rng: np.random.Generator | None = None, edge_px: float = 0.6) -> np.ndarray:
    """Synthetic IR image: anti-aliased bright discs at ``uv`` on a dark background.

    Each disc has intensity ``peak * 0.5 * erfc((r - radius_px) / (sqrt(2) edge_px))``:
    a disc blurred by a Gaussian of std ``edge_px`` (a defocused LED), evaluated at pixel
    centres; overlapping discs add. Gaussian pixel noise of std ``noise_std`` (grey levels)
    is added, then values are clipped and rounded to uint8 like a real 8-bit sensor.

    Args:
      image_size: (width_px, height_px). uv: (n, 2) disc centres in pixels.
    Returns:
      (height_px, width_px) uint8 image.
    """
    from scipy.special import erfc

    w, h = int(image_size[0]), int(image_size[1])
    img = np.full((h, w), float(background))
    half = int(np.ceil(radius_px + 5 * edge_px)) + 1
    for u, v in np.asarray(uv, np.float64).reshape(-1, 2):
        if not (np.isfinite(u) and np.isfinite(v)):
            continue
        x0, x1 = max(int(np.floor(u)) - half, 0), min(int(np.ceil(u)) + half + 1, w)
        y0, y1 = max(int(np.floor(v)) - half, 0), min(int(np.ceil(v)) + half + 1, h)
        if x0 >= x1 or y0 >= y1:
            continue  # off-image marker: simply not seen
        yy, xx = np.mgrid[y0:y1, x0:x1]
        r = np.hypot(xx - u, yy - v)
        img[y0:y1, x0:x1] += peak * 0.5 * erfc((r - radius_px) / (np.sqrt(2.0) * edge_px))
    if noise_std > 0:
        rng = np.random.default_rng() if rng is None else rng
        img += rng.normal(0.0, noise_std, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def render_markers(points_m: np.ndarray, camera: StereoCamera,
                   image_size: tuple[int, int] | None = None, radius_px: float = 3.0,
                   noise_std: float = 2.0, rng: np.random.Generator | None = None,
                   **draw_kw) -> tuple[np.ndarray, np.ndarray]:
    """Synthetic left/right images of markers at ``points_m``.

    Args:
      points_m: (n, 3) marker centres in metres, left-camera frame.
      camera: :class:`ParallelStereo` or :class:`CalibratedStereo` (its ``project`` includes
        lens distortion for the calibrated rig, via cv2.projectPoints).
      image_size: (width_px, height_px); default the camera's.
      radius_px: disc radius in pixels; noise_std: pixel noise std in grey levels.
      rng: numpy Generator for the noise. Extra keywords go to :func:`draw_blobs`.

    Returns:
      (left, right): two (H, W) uint8 images.
    """
    size = tuple(camera.image_size) if image_size is None else tuple(image_size)
    rng = np.random.default_rng() if rng is None else rng
    uv_l, uv_r = camera.project(points_m)
    left = draw_blobs(size, uv_l, radius_px, noise_std=noise_std, rng=rng, **draw_kw)
    right = draw_blobs(size, uv_r, radius_px, noise_std=noise_std, rng=rng, **draw_kw)
    return left, right


# ----------------------------------------------------------------------------- tracker


class StereoTracker:
    """Image pair -> (n_markers, 3) marker positions (metres, left-camera frame).

    detect (:func:`detect_blobs`) -> rectify (camera) -> match by row
    (:func:`match_by_row`) -> triangulate (camera). A frame with missing/extra blobs or an
    ambiguous match is returned flagged (``ok=False``, NaN points) -- or raised with
    ``strict=True`` -- never silently mismatched.

    Marker order: by left-image row (then column) -- unless ``reference_points_m`` (n, 3)
    is given, in which case each good frame is reordered to best match the previous good
    frame (minimum total distance, Hungarian assignment), so marker i keeps its identity
    while the object moves by less than about half the marker spacing per frame.
    """

    def __init__(self, camera: StereoCamera, n_markers: int, *, threshold: float | None = None,
                 min_area: int = 4, max_area: int | None = None, row_tol_px: float = 2.0,
                 same_row: str = "raise", reference_points_m: np.ndarray | None = None):
        if n_markers < 1:
            raise ValueError(f"n_markers must be >= 1, got {n_markers}")
        self.camera = camera
        self.n_markers = int(n_markers)
        self.threshold = threshold
        self.min_area = min_area
        self.max_area = max_area
        self.row_tol_px = row_tol_px
        self.same_row = same_row
        self._reference = None
        if reference_points_m is not None:
            ref = np.asarray(reference_points_m, np.float64)
            if ref.shape != (self.n_markers, 3):
                raise ValueError(f"reference_points_m must be ({n_markers}, 3); got {ref.shape}")
            self._reference = ref.copy()

    def __call__(self, left_image, right_image, strict: bool = False) -> StereoFrame:
        return self.track(left_image, right_image, strict=strict)

    def track(self, left_image: np.ndarray, right_image: np.ndarray,
              strict: bool = False) -> StereoFrame:
        """Process one image pair; returns a :class:`StereoFrame` with ``points_m`` (n, 3)."""
        det = dict(threshold=self.threshold, min_area=self.min_area, max_area=self.max_area)
        uv_l = detect_blobs(left_image, **det)
        uv_r = detect_blobs(right_image, **det)
        rect_l = self.camera.rectify(uv_l, "left")
        rect_r = self.camera.rectify(uv_r, "right")
        n = self.n_markers
        try:
            pairs = _match_pairs(rect_l, rect_r, n, self.row_tol_px, 0.0, self.same_row)
        except MarkerCountError as err:
            if strict:
                raise
            return StereoFrame.flagged(err, n, with_points=True)
        li, ri = pairs[:, 0], pairs[:, 1]
        pts = self.camera.triangulate_rectified(rect_l[li], rect_r[ri])
        L, R = uv_l[li], uv_r[ri]
        if self._reference is not None:
            from scipy.optimize import linear_sum_assignment

            cost = np.linalg.norm(self._reference[:, None, :] - pts[None, :, :], axis=-1)
            _, order = linear_sum_assignment(cost)
            pts, L, R = pts[order], L[order], R[order]
            self._reference = pts.copy()
        return StereoFrame(ok=True, message="ok", left_uv=L, right_uv=R, points_m=pts,
                           n_left=len(uv_l), n_right=len(uv_r), n_expected=n)
