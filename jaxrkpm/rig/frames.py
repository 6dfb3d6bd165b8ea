"""Coordinate frames and calibration (thesis sections 4.2.2-4.2.3).

* camera -> object frame from three L-shaped markers (eqs 4.4-4.9);
* tool-tip (pivot) calibration (eqs 4.10-4.21, solved as one least-squares system);
* robot <-> object registration by Arun, Huang & Blostein (1987), reflection-safe;
* unit helpers: the thesis mixes inches (object, plate, tool) and metres.

Transforms follow ``p_dst = R @ p_src + t`` and act on (n, 3) arrays of row vectors.
All lengths are metres unless a name says otherwise (``*_mm``, ``*_in``).
Nothing here imports the jaxrkpm solver core.
"""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = [
    "Units",
    "RigidTransform",
    "object_frame_from_l_markers",
    "label_l_markers",
    "PivotResult",
    "pivot_calibration",
    "Registration",
    "arun_registration",
    "register_from_three_touches",
]


# ----------------------------------------------------------------------------- units


class Units:
    """Length conversions. The thesis gives the object, plate and tool in inches and the
    camera accuracy in millimetres; everything in this package is metres."""

    M_PER_INCH = 0.0254   # exact, by definition
    M_PER_MM = 1e-3

    # thesis section 4.2.4-4.2.5 hardware, converted once here
    OBJECT_SIZE_M = (6 * 0.0254, 6 * 0.0254, 0.5 * 0.0254)   # 0.1524 x 0.1524 x 0.0127
    TOOL_LENGTH_M = 8 * 0.0254                               # aluminium rod, ~8 in
    TOOL_DIAMETER_M = 0.25 * 0.0254
    PLATE_HOLE_PITCH_M = 1 * 0.0254                          # 11 x 11 threaded holes

    @staticmethod
    def inch_to_m(x_in):
        return np.asarray(x_in, dtype=np.float64) * Units.M_PER_INCH

    @staticmethod
    def m_to_inch(x_m):
        return np.asarray(x_m, dtype=np.float64) / Units.M_PER_INCH

    @staticmethod
    def mm_to_m(x_mm):
        return np.asarray(x_mm, dtype=np.float64) * Units.M_PER_MM

    @staticmethod
    def m_to_mm(x_m):
        return np.asarray(x_m, dtype=np.float64) / Units.M_PER_MM


# ----------------------------------------------------------------------------- transforms


def _as_points(p, name: str) -> np.ndarray:
    a = np.asarray(p, dtype=np.float64)
    if a.ndim == 1 and a.shape[0] == 3:
        return a[None, :]
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must be (n, 3) or (3,); got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} contains non-finite values")
    return a


def _check_rotation(R: np.ndarray, name: str = "R", atol: float = 1e-6) -> np.ndarray:
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3):
        raise ValueError(f"{name} must be (3, 3); got {R.shape}")
    if not np.allclose(R @ R.T, np.eye(3), atol=atol):
        raise ValueError(f"{name} is not orthonormal (|R R^T - I| = "
                         f"{np.abs(R @ R.T - np.eye(3)).max():.2e})")
    if np.linalg.det(R) <= 0:
        raise ValueError(f"{name} is a reflection (det = {np.linalg.det(R):.3f}), not a rotation")
    return R


@dataclasses.dataclass(frozen=True)
class RigidTransform:
    """Rigid transform ``p_dst = R p_src + t``.

    Attributes: R (3, 3) proper rotation; t (3,) translation in metres.
    """

    R: np.ndarray
    t: np.ndarray

    def __post_init__(self):
        object.__setattr__(self, "R", _check_rotation(self.R))
        t = np.asarray(self.t, dtype=np.float64).reshape(-1)
        if t.shape != (3,):
            raise ValueError(f"t must have 3 entries; got {t.shape}")
        object.__setattr__(self, "t", t)

    @classmethod
    def identity(cls) -> "RigidTransform":
        return cls(np.eye(3), np.zeros(3))

    @classmethod
    def from_matrix(cls, M: np.ndarray) -> "RigidTransform":
        """From a (4, 4) homogeneous matrix."""
        M = np.asarray(M, dtype=np.float64)
        return cls(M[:3, :3], M[:3, 3])

    def as_matrix(self) -> np.ndarray:
        """(4, 4) homogeneous matrix."""
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = self.R, self.t
        return M

    def apply(self, points_m) -> np.ndarray:
        """Source-frame points (n, 3) or (3,) -> destination frame, same shape."""
        p = np.asarray(points_m, dtype=np.float64)
        out = _as_points(p, "points_m") @ self.R.T + self.t
        return out.reshape(p.shape)

    def apply_inverse(self, points_m) -> np.ndarray:
        """Destination-frame points (n, 3) or (3,) -> source frame: R^T (p - t)."""
        p = np.asarray(points_m, dtype=np.float64)
        out = (_as_points(p, "points_m") - self.t) @ self.R
        return out.reshape(p.shape)

    def inverse(self) -> "RigidTransform":
        return RigidTransform(self.R.T, -self.R.T @ self.t)

    def compose(self, other: "RigidTransform") -> "RigidTransform":
        """``self ∘ other``: apply ``other`` first, then ``self``."""
        return RigidTransform(self.R @ other.R, self.R @ other.t + self.t)


# ----------------------------------------------------------------------------- L markers


def object_frame_from_l_markers(markers_m, *, leg_ratio: float | None = None,
                                ratio_rtol: float = 0.1) -> RigidTransform:
    """Camera -> object transform from the three L-shaped markers (eqs 4.4-4.9).

    Args:
      markers_m: (3, 3) camera-frame positions (metres), rows V0 (corner), V1 (end of the
        x leg), V2 (end of the y leg). The thesis' L has |V2 - V0| = 2 |V1 - V0|; use
        :func:`label_l_markers` to order unlabelled detections.
      leg_ratio: if given, require |V2 - V0| / |V1 - V0| within ``ratio_rtol`` of it (a
        cheap check that the markers are labelled right).

    Returns:
      :class:`RigidTransform` T with ``T.apply(p_camera) = p_object`` (eq 4.9); rows of
      ``T.R`` are the object axes in camera coordinates (eq 4.7), ``T.t = -R V0`` (eq 4.8).
      ``T.apply_inverse`` maps object -> camera.

    The measured legs are never exactly perpendicular (marker placement, noise), so the
    y axis is Gram-Schmidt-orthogonalised against x, and z = x × y: R is orthonormal to
    rounding error whatever the noise.
    """
    V = np.asarray(markers_m, dtype=np.float64)
    if V.shape != (3, 3) or not np.all(np.isfinite(V)):
        raise ValueError(f"markers_m must be a finite (3, 3) array (rows V0, V1, V2); got {V.shape}")
    a, b = V[1] - V[0], V[2] - V[0]
    la, lb = np.linalg.norm(a), np.linalg.norm(b)
    if la < 1e-12 or lb < 1e-12:
        raise ValueError("coincident L markers: a leg has zero length")
    if leg_ratio is not None and abs(lb / la - leg_ratio) > ratio_rtol * leg_ratio:
        raise ValueError(f"L legs |V2-V0|/|V1-V0| = {lb / la:.3f}, expected {leg_ratio} "
                         f"(markers mislabelled or misdetected?)")
    x = a / la
    y = b - (b @ x) * x
    ly = np.linalg.norm(y)
    if ly < 1e-6 * lb:
        raise ValueError("collinear L markers: the legs do not span a plane")
    y /= ly
    z = np.cross(x, y)
    # one more Gram-Schmidt pass on x, y: makes R R^T = I hold to ~1e-16, not ~1e-13
    y = np.cross(z, x)
    R = np.vstack([x, y, z])
    return RigidTransform(R, -R @ V[0])


def label_l_markers(points_m, *, max_cos: float = 0.25, min_leg_ratio: float = 1.2) -> np.ndarray:
    """Order three unlabelled L markers as (V0, V1, V2).

    V0 is the corner (the vertex opposite the longest side, the hypotenuse), V1 the end
    of the shorter leg, V2 the end of the longer one -- so the labelling follows from the
    geometry and not from image order.

    Args:
      points_m: (3, 3) positions in any frame.
      max_cos: reject if |cos| of the corner angle exceeds this (not an L).
      min_leg_ratio: reject if long/short leg < this (legs too similar to tell apart).
    Returns:
      (3, 3) rows V0, V1, V2. Raises ValueError if the points are not an L.
    """
    P = np.asarray(points_m, dtype=np.float64)
    if P.shape != (3, 3):
        raise ValueError(f"need exactly 3 markers (3, 3); got {P.shape}")
    side = [np.linalg.norm(P[(i + 1) % 3] - P[(i + 2) % 3]) for i in range(3)]  # opposite i
    i0 = int(np.argmax(side))
    j, k = (i0 + 1) % 3, (i0 + 2) % 3
    dj, dk = np.linalg.norm(P[j] - P[i0]), np.linalg.norm(P[k] - P[i0])
    if min(dj, dk) < 1e-12:
        raise ValueError("coincident markers")
    i1, i2 = (j, k) if dj < dk else (k, j)
    cos = (P[i1] - P[i0]) @ (P[i2] - P[i0]) / (dj * dk)
    if abs(cos) > max_cos:
        raise ValueError(f"not an L: corner angle {np.degrees(np.arccos(np.clip(cos, -1, 1))):.1f} deg")
    ratio = max(dj, dk) / min(dj, dk)
    if ratio < min_leg_ratio:
        raise ValueError(f"L legs too similar to label (ratio {ratio:.2f} < {min_leg_ratio})")
    return P[[i0, i1, i2]].copy()


# ----------------------------------------------------------------------------- pivot


@dataclasses.dataclass(frozen=True)
class PivotResult:
    """Pivot calibration result.

    tip_m: (3,) tool tip in the flange/tool frame; pivot_m: (3,) the fixed pivot point in
    the robot base frame; rms_m: RMS over poses of |R_i tip + t_i - pivot|;
    residuals_m: (n, 3) per-pose residual vectors; condition: 2-norm condition number of
    the stacked system (large -> poses barely rotate, tip poorly determined).
    """

    tip_m: np.ndarray
    pivot_m: np.ndarray
    rms_m: float
    residuals_m: np.ndarray
    condition: float


def pivot_calibration(rotations, translations_m, *, rank_rtol: float = 1e-8) -> PivotResult:
    """Tool-tip (pivot) calibration: every pose puts the tip on one fixed point.

    For pose i (flange rotation R_i, translation t_i from the robot's sensors),
    R_i p_tip + t_i = p_pivot, stacked over all poses as the linear least-squares system

        [R_i | -I] [p_tip; p_pivot] = -t_i,   i = 1..n   (3n x 6)

    and solved with ``np.linalg.lstsq``. The thesis (eqs 4.14-4.21) differences each pose
    against an "average" pose instead; the stacked form solves for the tip and the pivot
    jointly, uses every pose symmetrically and yields a residual to judge the fit by.

    Args:
      rotations: (n, 3, 3) proper rotations. translations_m: (n, 3) metres. n >= 3.
      rank_rtol: singular values below ``rank_rtol * s_max`` count as zero.

    Raises:
      ValueError: fewer than 3 poses, bad shapes/non-rotations, or a degenerate pose set
        (rank < 6: e.g. all rotations about one axis leave the tip's component along that
        axis undetermined).
    """
    Rs = np.asarray(rotations, dtype=np.float64)
    ts = np.asarray(translations_m, dtype=np.float64)
    if Rs.ndim != 3 or Rs.shape[1:] != (3, 3):
        raise ValueError(f"rotations must be (n, 3, 3); got {Rs.shape}")
    n = Rs.shape[0]
    if ts.shape != (n, 3):
        raise ValueError(f"translations_m must be ({n}, 3) to match rotations; got {ts.shape}")
    if n < 3:
        raise ValueError(f"pivot calibration needs at least 3 poses; got {n}")
    if not (np.all(np.isfinite(Rs)) and np.all(np.isfinite(ts))):
        raise ValueError("non-finite pose data")
    for i, R in enumerate(Rs):
        _check_rotation(R, f"rotations[{i}]")
    A = np.concatenate([Rs, np.broadcast_to(-np.eye(3), (n, 3, 3))], axis=2).reshape(3 * n, 6)
    b = -ts.reshape(3 * n)
    x, _, rank, s = np.linalg.lstsq(A, b, rcond=rank_rtol)
    if rank < 6:
        raise ValueError(f"degenerate pivot poses: system rank {rank} < 6 (singular values "
                         f"{np.array2string(s, precision=2)}); rotate about at least two "
                         f"different axes")
    tip, pivot = x[:3], x[3:]
    res = (A @ x - b).reshape(n, 3)
    return PivotResult(tip_m=tip, pivot_m=pivot,
                       rms_m=float(np.sqrt(np.mean(np.sum(res ** 2, axis=1)))),
                       residuals_m=res, condition=float(s[0] / s[-1]))


# ----------------------------------------------------------------------------- Arun


@dataclasses.dataclass(frozen=True)
class Registration:
    """Least-squares rigid fit ``target ≈ R source + T``.

    R: (3, 3) proper rotation (det = +1); T: (3,) metres; rms_m: RMS point residual;
    residuals_m: (n, 3).
    """

    R: np.ndarray
    T: np.ndarray
    rms_m: float
    residuals_m: np.ndarray

    @property
    def transform(self) -> RigidTransform:
        return RigidTransform(self.R, self.T)


def arun_registration(source_m, target_m) -> Registration:
    """Rigid registration by SVD (Arun, Huang & Blostein 1987), never a reflection.

    Finds R, T minimising sum |target_i - (R source_i + T)|^2. With H = sum over centred
    points of s_i t_i^T = U S V^T, Arun's R = V U^T can be a reflection (det = -1) when
    the points are (nearly) coplanar -- the thesis' three touch points are exactly
    coplanar -- since the sign of the last singular vector is then decided by noise.
    We use the Umeyama form R = V diag(1, 1, det(V U^T)) U^T: the best proper rotation.

    Args:
      source_m, target_m: (n, 3) corresponding points, n >= 3, not collinear.
    Raises:
      ValueError: shape mismatch, fewer than 3 points, or a rank < 2 configuration
      (collinear or coincident points leave a rotation about their line free).
    """
    X = _as_points(source_m, "source_m")
    Y = _as_points(target_m, "target_m")
    if X.shape != Y.shape:
        raise ValueError(f"source_m {X.shape} and target_m {Y.shape} differ in shape")
    if len(X) < 3:
        raise ValueError(f"registration needs at least 3 point pairs; got {len(X)}")
    xc, yc = X.mean(0), Y.mean(0)
    H = (X - xc).T @ (Y - yc)
    U, s, Vt = np.linalg.svd(H)
    scale = max(np.linalg.norm(X - xc), np.linalg.norm(Y - yc)) ** 2
    if s[1] <= 1e-10 * max(scale, 1e-300):
        raise ValueError("degenerate registration: points are collinear or coincident "
                         f"(singular values of H: {np.array2string(s, precision=2)})")
    V = Vt.T
    d = np.sign(np.linalg.det(V @ U.T))
    d = 1.0 if d == 0 else d
    R = V @ np.diag([1.0, 1.0, d]) @ U.T
    T = yc - R @ xc
    res = Y - (X @ R.T + T)
    return Registration(R=R, T=T, rms_m=float(np.sqrt(np.mean(np.sum(res ** 2, axis=1)))),
                        residuals_m=res)


def register_from_three_touches(origin_m, x_point_m, y_point_m) -> Registration:
    """Object -> robot registration from three tool-tip touches (eqs 4.22-4.25).

    The tip touches, in robot coordinates, the object's origin, a point on its x axis and
    a point on its y axis (planar object, z = 0). Their object coordinates are taken as
    (0,0,0), (|x - o|,0,0), (0,|y - o|,0) (eq 4.25: measured distances, so no ruler is
    needed) and Arun's method gives ``robot = R object + T``.

    Args: three (3,) robot-frame positions in metres.
    Returns: :class:`Registration` (R, T: object -> robot).
    """
    Y = _as_points(np.vstack([origin_m, x_point_m, y_point_m]), "touch points")
    X = np.array([[0.0, 0.0, 0.0],
                  [np.linalg.norm(Y[1] - Y[0]), 0.0, 0.0],
                  [0.0, np.linalg.norm(Y[2] - Y[0]), 0.0]])
    return arun_registration(X, Y)
