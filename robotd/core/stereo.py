"""Stereo camera model: distortion, calibration, rectification, triangulation and its covariance.

Two halves:

- The **rectified** rig (thesis §3.2.4, docs/math.md §2.2–§3.2): :class:`RectifiedStereo`,
  :func:`triangulate` (eq. 3.2.14), :func:`project`, and the first-order covariance. Points are
  returned in the robot frame (docs/math.md §1.2): origin at the baseline centre, X forward
  (depth), Y right along the baseline, Z down. All functions are vectorised over N points.
- The **raw** rig (thesis §3.1–§3.2.3, docs/math.md §2.1): a pinhole camera with skew (eq. 3.1.8)
  and OpenCV's distortion models (radial-tangential with 4/5 coefficients, the 8/12/14-coefficient
  rational model with thin-prism and tilt terms that the OAK-D factory calibration uses), the
  :class:`StereoCalibration` of two such cameras, and rectification either as the thesis derives
  it (eqs. 3.2.5–3.2.10) or with OpenCV's ``stereoRectify``. :class:`Rectifier` holds the remap
  tables and rectifies image pairs.

Camera frames are OpenCV's optical frames (x right, y down, z forward). The extrinsics follow the
OpenCV/Kalibr convention: a point in the left camera frame maps into the right one as
``x_right = R @ x_left + T`` (metres).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Literal

import cv2
import numpy as np
from scipy import special

from robotd.core.errors import CalibrationError, InputError

logger = logging.getLogger("robotd.stereo")  # its name before the layer packages: users filter by it


@dataclass(frozen=True, slots=True)
class RectifiedStereo:
    """A rectified rig is described by f, p_x, p_y, b and the image size (docs/math.md §2.1).

    This is what the front end needs; how it was obtained (calibration, OAK factory data,
    dataset files) is the business of the calibration code.
    """

    f_px: float
    px: float
    py: float
    baseline_m: float
    width: int
    height: int

    @property
    def fb(self) -> float:
        """f·b [px·m]: depth X = fb / d."""
        return self.f_px * self.baseline_m

    def disparity_bounds(self, depth_min_m: float = 0.3, d_min_px: float = 5.0) -> tuple[float, float]:
        """(d_min, d_max) from the configured near limit and disparity floor (docs/math.md §2.2)."""
        return d_min_px, self.fb / depth_min_m


def triangulate(xl: np.ndarray, xr: np.ndarray, y: np.ndarray, f: float, px: float, py: float, b: float) -> np.ndarray:
    """Rectified correspondences -> (N, 3) points in the robot frame (eq. 3.2.14).

    ``xl``, ``xr``: (N,) columns in the left/right rectified image; ``y``: (N,) common row
    (use the mean of both rows); ``f``, ``px``, ``py`` [px]; ``b`` baseline [m]. Disparity
    ``d = xl - xr`` must be positive (callers enforce the disparity bounds).
    """
    xl = np.asarray(xl, dtype=float)
    xr = np.asarray(xr, dtype=float)
    y = np.asarray(y, dtype=float)
    d = xl - xr
    X = f * b / d
    Y = (xl - px) * b / d - b / 2.0
    Z = (y - py) * b / d
    return np.stack([X, Y, Z], -1)


def triangulation_jacobian(
    xl: np.ndarray, xr: np.ndarray, y: np.ndarray, f: float, px: float, py: float, b: float
) -> np.ndarray:
    """∂(X, Y, Z)/∂(x_L, x_R, y), (N, 3, 3) (docs/math.md §3.1)."""
    xl = np.asarray(xl, dtype=float)
    xr = np.asarray(xr, dtype=float)
    y = np.asarray(y, dtype=float)
    d = xl - xr
    k = b / d**2
    z = np.zeros_like(d)
    J = np.stack(
        [
            np.stack([-f * np.ones_like(d), f * np.ones_like(d), z], -1),
            np.stack([px - xr, xl - px, z], -1),
            np.stack([py - y, y - py, d], -1),
        ],
        -2,
    )
    return J * k[:, None, None]


def triangulation_covariance(
    xl: np.ndarray,
    xr: np.ndarray,
    y: np.ndarray,
    f: float,
    px: float,
    py: float,
    b: float,
    sigma_x_px: float = 0.5,
    sigma_y_px: float = 0.5 / np.sqrt(2.0),
    inflation: float = 1.0,
) -> np.ndarray:
    """First-order covariance Q = J Σ_px J^T of each triangulated point, (N, 3, 3) [m²].

    Σ_px = diag(σx², σx², σy²) for (x_L, x_R, y) (docs/math.md §3.1); ``inflation`` multiplies Q
    (§3.3, default 1).
    """
    J = triangulation_jacobian(xl, xr, y, f, px, py, b)
    s = np.array([sigma_x_px**2, sigma_x_px**2, sigma_y_px**2])
    Q = np.einsum("nij,j,nkj->nik", J, s, J)
    return inflation * 0.5 * (Q + np.swapaxes(Q, -1, -2))


def streak_px(rate_radps: float, exposure_s: float, f_px: float) -> float:
    """The streak [px] a point draws across the image while the camera turns at ``rate_radps``
    during one exposure of ``exposure_s``: rate × exposure × f (the small-angle image motion of a
    rotation, which dominates a translation's at the rates that blur); 0 for no exposure, NaN
    or negative inputs."""
    b = float(rate_radps) * float(exposure_s) * float(f_px)
    return b if math.isfinite(b) and b > 0.0 else 0.0


def blur_covariance(xl: np.ndarray, xr: np.ndarray, y: np.ndarray, rig: RectifiedStereo, b_px: float) -> np.ndarray:
    """The covariance (N, 3, 3) [m²] a motion-blur streak of ``b_px`` adds to each triangulated
    point (docs/math.md §3.4).

    A blurred corner is found somewhere along its streak, uniformly: b²/12 of variance along it.
    Both cameras expose together, so the left and right images hold the same streak and the
    corner moves by the same amount in both: x_L and x_R fully correlated, the disparity (the
    depth) untouched. The streak's direction differs across the frame and between frames; taken
    as uniform, each image axis gets half: Σ_b = b²/24 [[1, 1, 0], [1, 1, 0], [0, 0, 1]] on
    (x_L, x_R, y), mapped by the triangulation's Jacobian."""
    n = np.shape(xl)[0]
    if not (b_px > 0.0 and math.isfinite(b_px)) or n == 0:
        return np.zeros((n, 3, 3))
    J = triangulation_jacobian(xl, xr, y, rig.f_px, rig.px, rig.py, rig.baseline_m)
    # Σ_b = b²/24 (u uᵀ + e₃ e₃ᵀ), u = (1, 1, 0): two outer products of J's columns
    u, v = J[:, :, 0] + J[:, :, 1], J[:, :, 2]
    return (b_px * b_px / 24.0) * (u[:, :, None] * u[:, None, :] + v[:, :, None] * v[:, None, :])


def covariance_from_points(
    xyz_R: np.ndarray, f: float, b: float, sigma_x_px: float = 0.5, sigma_y_px: float = 0.5 / np.sqrt(2.0)
) -> np.ndarray:
    """Closed form of the same covariance from the triangulated points (docs/math.md §3.2).

    Q = X²/(f²b²) (2σx² z zᵀ + diag(0, σx² b²/2, σy² b²)), (N, 3, 3). Used by simulators that
    produce points directly; agrees with :func:`triangulation_covariance`.
    """
    z = np.asarray(xyz_R, dtype=float)
    X = z[:, 0]
    k = (X**2 / (f * f * b * b))[:, None, None]
    Q = 2.0 * sigma_x_px**2 * np.einsum("ni,nj->nij", z, z)
    Q[:, 1, 1] += 0.5 * sigma_x_px**2 * b * b
    Q[:, 2, 2] += sigma_y_px**2 * b * b
    return k * Q


def project(xyz_R: np.ndarray, f: float, px: float, py: float, b: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inverse of :func:`triangulate`: robot-frame points (N, 3) -> (xl, xr, y) pixel coordinates."""
    z = np.asarray(xyz_R, dtype=float)
    X, Y, Z = z[:, 0], z[:, 1], z[:, 2]
    xl = px + f * (Y + b / 2.0) / X
    xr = px + f * (Y - b / 2.0) / X
    y = py + f * Z / X
    return xl, xr, y


# ---------------------------------------------------------------------------------------------
# Single camera: pinhole with skew (eq. 3.1.8) and OpenCV's distortion models
# ---------------------------------------------------------------------------------------------

DistortionModel = Literal["radtan", "rational"]

#: Accepted coefficient counts per model, in OpenCV order
#: (k1, k2, p1, p2[, k3[, k4, k5, k6[, s1, s2, s3, s4[, τx, τy]]]]).
DISTORTION_LENGTHS: dict[str, tuple[int, ...]] = {"radtan": (4, 5), "rational": (8, 12, 14)}


def camera_matrix(fx: float, fy: float, cx: float, cy: float, skew: float = 0.0) -> np.ndarray:
    """Calibration matrix K (3, 3) of eq. 3.1.8: [[αx, s, x0], [0, αy, y0], [0, 0, 1]] [px]."""
    return np.array([[fx, skew, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=float)


def _coeffs14(D: np.ndarray) -> np.ndarray:
    """Any accepted OpenCV coefficient vector, zero-padded to the 14 of the full rational model."""
    d = np.zeros(14)
    D = np.asarray(D, dtype=float).ravel()
    if D.size not in (0, 4, 5, 8, 12, 14):
        raise CalibrationError(f"distortion: expected 0, 4, 5, 8, 12 or 14 coefficients, got {D.size}")
    d[: D.size] = D
    return d


def _tilt_matrix(tau_x: float, tau_y: float) -> np.ndarray:
    """OpenCV's tilted-sensor homography (3, 3) for the τx, τy coefficients (Louhichi et al. 2007)."""
    cx, sx, cy, sy = np.cos(tau_x), np.sin(tau_x), np.cos(tau_y), np.sin(tau_y)
    rot_x = np.array([[1.0, 0.0, 0.0], [0.0, cx, sx], [0.0, -sx, cx]])
    rot_y = np.array([[cy, 0.0, -sy], [0.0, 1.0, 0.0], [sy, 0.0, cy]])
    rot_xy = rot_y @ rot_x
    proj_z = np.array([[rot_xy[2, 2], 0.0, -rot_xy[0, 2]], [0.0, rot_xy[2, 2], -rot_xy[1, 2]], [0.0, 0.0, 1.0]])
    return proj_z @ rot_xy


def _distort_no_tilt(xy: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Radial (rational), tangential and thin-prism terms; ``d`` has 14 entries."""
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = d[:12]
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    r4 = r2 * r2
    r6 = r4 * r2
    radial = (1.0 + k1 * r2 + k2 * r4 + k3 * r6) / (1.0 + k4 * r2 + k5 * r4 + k6 * r6)
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x) + s1 * r2 + s2 * r4
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y + s3 * r2 + s4 * r4
    return np.stack([xd, yd], -1)


def _apply_h(H: np.ndarray, xy: np.ndarray) -> np.ndarray:
    v = xy @ H[:, :2].T + H[:, 2]
    return v[:, :2] / v[:, 2:3]


def distort_normalized(xy: np.ndarray, D: np.ndarray) -> np.ndarray:
    """Ideal normalized image coordinates (N, 2) -> distorted normalized coordinates (N, 2).

    OpenCV's model (the one ``cv2.projectPoints`` applies): rational radial factor
    (1 + k1 r² + k2 r⁴ + k3 r⁶)/(1 + k4 r² + k5 r⁴ + k6 r⁶), tangential p1, p2, thin prism s1..s4,
    then the tilt homography of τx, τy. ``D`` may have 0, 4, 5, 8, 12 or 14 entries.
    """
    d = _coeffs14(D)
    out = _distort_no_tilt(np.asarray(xy, dtype=float).reshape(-1, 2), d)
    if d[12] != 0.0 or d[13] != 0.0:
        out = _apply_h(_tilt_matrix(d[12], d[13]), out)
    return out


def undistort_normalized(xy_d: np.ndarray, D: np.ndarray, max_iter: int = 30, tol: float = 1e-13) -> np.ndarray:
    """Inverse of :func:`distort_normalized`, (N, 2) -> (N, 2), solved per point by damped Newton.

    OpenCV's ``undistortPoints`` runs a fixed number of fixed-point iterations, which leaves
    errors of several pixels near the border under the OAK-D's strong rational model; Newton
    with a finite-difference 2×2 Jacobian converges to ~1e-13 in normalized units. Points that do
    not converge (outside the model's invertible region) come back as NaN.
    """
    d = _coeffs14(D)
    target = np.asarray(xy_d, dtype=float).reshape(-1, 2)
    if d[12] != 0.0 or d[13] != 0.0:
        target = _apply_h(np.linalg.inv(_tilt_matrix(d[12], d[13])), target)
    x = target.copy()
    h = 1e-7
    res = _distort_no_tilt(x, d) - target
    err = np.linalg.norm(res, axis=1)
    for _ in range(max_iter):
        active = err > tol
        if not active.any():
            break
        xa = x[active]
        ra = res[active]
        ex, ey = np.array([h, 0.0]), np.array([0.0, h])
        jx = (_distort_no_tilt(xa + ex, d) - _distort_no_tilt(xa - ex, d)) / (2 * h)
        jy = (_distort_no_tilt(xa + ey, d) - _distort_no_tilt(xa - ey, d)) / (2 * h)
        det = jx[:, 0] * jy[:, 1] - jy[:, 0] * jx[:, 1]
        det = np.where(np.abs(det) < 1e-12, 1e-12, det)
        # solve [jx jy] step = -res with the closed-form 2×2 inverse
        step = -np.stack([jy[:, 1] * ra[:, 0] - jy[:, 0] * ra[:, 1], -jx[:, 1] * ra[:, 0] + jx[:, 0] * ra[:, 1]], -1)
        step /= det[:, None]
        # damping: halve the step while the residual grows (keeps far-out points from diverging)
        ea = err[active]
        scale = np.ones(len(xa))
        for _ in range(8):
            trial = xa + step * scale[:, None]
            rt = _distort_no_tilt(trial, d) - target[active]
            et = np.linalg.norm(rt, axis=1)
            worse = ~(et <= ea)
            if not worse.any():
                break
            scale[worse] *= 0.5
        x[active] = trial
        res[active] = rt
        err[active] = et
    bad = ~(err <= max(tol, 1e-9))
    if bad.any():
        logger.debug("undistort_normalized: %d of %d points did not converge", int(bad.sum()), len(x))
        x[bad] = np.nan
    return x


def _check_K(K: np.ndarray, name: str = "K") -> np.ndarray:
    K = np.asarray(K, dtype=float)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise CalibrationError(f"{name}: expected a finite 3x3 camera matrix with fx, fy > 0, got {K.tolist()}")
    if K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1:
        raise CalibrationError(f"{name}: expected upper-triangular K with K[2,2] = 1, got {K.tolist()}")
    return K


def pixels_to_normalized(uv: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) -> normalized coordinates (N, 2) through K^-1 (skew included)."""
    uv = np.asarray(uv, dtype=float).reshape(-1, 2)
    fx, s, cx, fy, cy = K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2]
    y = (uv[:, 1] - cy) / fy
    x = (uv[:, 0] - cx - s * y) / fx
    return np.stack([x, y], -1)


def normalized_to_pixels(xy: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Normalized coordinates (N, 2) -> pixels (N, 2) through K (eq. 3.1.8, skew included)."""
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    u = K[0, 0] * xy[:, 0] + K[0, 1] * xy[:, 1] + K[0, 2]
    v = K[1, 1] * xy[:, 1] + K[1, 2]
    return np.stack([u, v], -1)


def project_points(xyz_C: np.ndarray, K: np.ndarray, D: np.ndarray | None = None) -> np.ndarray:
    """Camera-frame points (N, 3) [m] (optical frame, z forward) -> distorted pixels (N, 2)."""
    xyz = np.asarray(xyz_C, dtype=float).reshape(-1, 3)
    xy = xyz[:, :2] / xyz[:, 2:3]
    if D is not None:
        xy = distort_normalized(xy, D)
    return normalized_to_pixels(xy, K)


def distort_points(uv: np.ndarray, K: np.ndarray, D: np.ndarray) -> np.ndarray:
    """Ideal (undistorted) pixels (N, 2) -> the pixels the real lens images them at (N, 2), same K."""
    return normalized_to_pixels(distort_normalized(pixels_to_normalized(uv, K), D), K)


def undistort_points(
    uv_d: np.ndarray, K: np.ndarray, D: np.ndarray, R: np.ndarray | None = None, P: np.ndarray | None = None
) -> np.ndarray:
    """Distorted pixels (N, 2) -> ideal pixels (N, 2); NaN where the inversion does not converge.

    Like ``cv2.undistortPoints``: with ``R`` (3, 3, original camera -> rectified camera) and ``P``
    (3, 3 or 3, 4, the new camera matrix) the result is in the rectified image; by default the
    same K is kept.
    """
    xy = undistort_normalized(pixels_to_normalized(uv_d, K), D)
    if R is not None:
        ray = np.concatenate([xy, np.ones((len(xy), 1))], 1) @ np.asarray(R, dtype=float).T
        xy = ray[:, :2] / ray[:, 2:3]
    Kn = K if P is None else np.asarray(P, dtype=float)[:3, :3]
    return normalized_to_pixels(xy, Kn)


# ---------------------------------------------------------------------------------------------
# Stereo calibration
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True, eq=False)
class StereoCalibration:
    """Intrinsics of both cameras and the pose of the right camera w.r.t. the left.

    ``x_right = R @ x_left + T`` maps a point from the left optical frame into the right one
    (Kalibr's ``T_cn_cnm1`` for cam1, OpenCV's ``stereoCalibrate`` R, T). Lengths in metres.
    Both cameras use the same ``distortion_model`` (``"radtan"``: 4 or 5 coefficients;
    ``"rational"``: OpenCV's 8/12/14). Calibration is data: it lives in a camchain file
    (``calib.camchain``), not in the tuning config.
    """

    K_left: np.ndarray  # (3, 3) [px], skew allowed in K[0, 1]
    D_left: np.ndarray  # (n,) OpenCV order
    K_right: np.ndarray  # (3, 3) [px]
    D_right: np.ndarray  # (n,)
    R: np.ndarray  # (3, 3) rotation left optical -> right optical
    T: np.ndarray  # (3,) [m] translation left -> right (≈ (-b, 0, 0) for a horizontal rig)
    image_size: tuple[int, int]  # (width, height) [px]
    distortion_model: str = "radtan"
    source: str = ""
    extra: dict[str, object] = field(default_factory=dict)  # metadata (RMS, view counts), not geometry

    def __post_init__(self) -> None:
        if self.distortion_model not in DISTORTION_LENGTHS:
            raise CalibrationError(
                f"distortion_model: expected one of {sorted(DISTORTION_LENGTHS)}, got {self.distortion_model!r}"
            )
        allowed = DISTORTION_LENGTHS[self.distortion_model]
        for name in ("K_left", "K_right"):
            object.__setattr__(self, name, _check_K(getattr(self, name), name))
        for name in ("D_left", "D_right"):
            d = np.asarray(getattr(self, name), dtype=float).ravel().copy()
            if d.size not in allowed or not np.all(np.isfinite(d)):
                raise CalibrationError(
                    f"{name}: model {self.distortion_model!r} expects {allowed} finite coefficients, got {d.size}"
                )
            object.__setattr__(self, name, d)
        R = np.asarray(self.R, dtype=float)
        if R.shape != (3, 3) or not np.all(np.isfinite(R)):
            raise CalibrationError(f"R: expected a finite 3x3 rotation, got shape {R.shape}")
        ortho = float(np.abs(R @ R.T - np.eye(3)).max())
        if ortho > 1e-6 or np.linalg.det(R) < 0:
            raise CalibrationError(f"R: not a rotation (|R Rᵀ - I|max = {ortho:.2e}, det = {np.linalg.det(R):.6f})")
        object.__setattr__(self, "R", R.copy())
        T = np.asarray(self.T, dtype=float).ravel()
        if T.shape != (3,) or not np.all(np.isfinite(T)) or np.linalg.norm(T) == 0:
            raise CalibrationError(f"T: expected a finite non-zero 3-vector [m], got {T.tolist()}")
        object.__setattr__(self, "T", T.copy())
        w, h = (int(v) for v in self.image_size)
        if w <= 0 or h <= 0 or (w, h) != tuple(self.image_size):
            raise CalibrationError(f"image_size: expected positive integers (width, height), got {self.image_size}")
        object.__setattr__(self, "image_size", (w, h))

    @property
    def baseline_m(self) -> float:
        """Distance between the optical centres, |T| [m]."""
        return float(np.linalg.norm(self.T))

    @property
    def c_right_in_left(self) -> np.ndarray:
        """Right optical centre in the left camera frame, -Rᵀ T, (3,) [m]."""
        return -self.R.T @ self.T

    def T_right_left(self) -> np.ndarray:
        """4×4 homogeneous transform left optical -> right optical (Kalibr ``T_cn_cnm1``)."""
        M = np.eye(4)
        M[:3, :3] = self.R
        M[:3, 3] = self.T
        return M


# ---------------------------------------------------------------------------------------------
# Rectification
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True, eq=False)
class Rectification:
    """Rectifying rotations and new projection matrices, as ``cv2.stereoRectify`` returns them.

    ``R1``/``R2`` (3, 3) rotate the original left/right optical frame into the common rectified
    frame of each camera; ``P1``/``P2`` (3, 4) project rectified-frame points (left camera at the
    origin) into the rectified images: ``P2 = K [I | (-b, 0, 0)]`` up to the factor f.
    """

    R1: np.ndarray
    R2: np.ndarray
    P1: np.ndarray
    P2: np.ndarray
    image_size: tuple[int, int]
    method: str

    @property
    def model(self) -> RectifiedStereo:
        """f, p_x, p_y from P1 and b = -P2[0,3]/P2[0,0] (docs/math.md §2.1)."""
        return RectifiedStereo(
            f_px=float(self.P1[0, 0]),
            px=float(self.P1[0, 2]),
            py=float(self.P1[1, 2]),
            baseline_m=float(-self.P2[0, 3] / self.P2[0, 0]),
            width=int(self.image_size[0]),
            height=int(self.image_size[1]),
        )


def _check_horizontal(P1: np.ndarray, P2: np.ndarray, method: str) -> None:
    """RectifiedStereo describes a horizontal rig with the right camera on the right."""
    b = -P2[0, 3] / P2[0, 0]
    if not b > 0:
        raise CalibrationError(
            f"{method} rectification: baseline -P2[0,3]/P2[0,0] = {b:.6g} m is not positive; "
            "is the right camera really to the right (T_x < 0)? Swap the images."
        )
    if abs(P2[1, 3]) > 1e-6 * abs(P2[0, 3]):
        raise CalibrationError(f"{method} rectification: vertical rig (P2[1,3] = {P2[1, 3]:.6g}) is not supported")
    if abs(P1[0, 2] - P2[0, 2]) > 1e-9 or abs(P1[1, 2] - P2[1, 2]) > 1e-9:
        raise CalibrationError(
            f"{method} rectification: principal points differ (P1 {P1[:2, 2].tolist()}, P2 {P2[:2, 2].tolist()})"
        )


def rectify_thesis(calib: StereoCalibration, square_pixels: bool = True) -> Rectification:
    """Rectification as the thesis derives it (eqs. 3.2.5–3.2.10), a Fusiello-style construction.

    - K = ½(K_L + K_R) (3.2.5). With ``square_pixels`` (default) f = ½(α_x + α_y) on both axes
      and zero skew, because the rectified model (3.2.14) has a single f; otherwise K is used as
      averaged, which is row-aligned too but not what :class:`RectifiedStereo` describes.
    - The new rotation (3.2.6–3.2.9), written in optical axes: the new x axis (the thesis's Y_r)
      is the baseline direction r2 = (c_R - c_L)/|c_R - c_L|; the new y axis (Z_r, down) is
      r3 = k × r2 / |k × r2| with k the left camera's optical axis; the new optical axis (X_r)
      is r1 = r2 × r3. Here everything is expressed in the left camera frame (c_L = 0).
    - Each image is warped by x' = M M_i^{-1} x (3.2.10) with M = K R_new and M_i = K_i R_i; in
      OpenCV terms the rectifying rotations are R1 = R_new and R2 = R_new Rᵀ, and P_i = K[I | -R_new c_i].
    """
    KL, KR = calib.K_left, calib.K_right
    K = 0.5 * (KL + KR)
    if square_pixels:
        f = 0.5 * (K[0, 0] + K[1, 1])
        K = camera_matrix(f, f, K[0, 2], K[1, 2])
    r2 = calib.c_right_in_left
    b = float(np.linalg.norm(r2))
    r2 = r2 / b
    k = np.array([0.0, 0.0, 1.0])
    r3 = np.cross(k, r2)
    n3 = np.linalg.norm(r3)
    if n3 < 1e-6:
        raise CalibrationError("thesis rectification: the baseline is parallel to the optical axis")
    r3 /= n3
    r1 = np.cross(r2, r3)
    # rows: new optical-frame axes x (= r2), y (= r3), z (= r1) expressed in the left frame
    R_new = np.stack([r2, r3, r1])
    R1 = R_new
    R2 = R_new @ calib.R.T
    P1 = np.concatenate([K, np.zeros((3, 1))], 1)
    # right centre in the rectified frame is (b, 0, 0): P2 = K [I | -(b, 0, 0)]
    P2 = np.concatenate([K, (K @ np.array([-b, 0.0, 0.0]))[:, None]], 1)
    _check_horizontal(P1, P2, "thesis")
    return Rectification(R1, R2, P1, P2, calib.image_size, "thesis")


def rectify_opencv(calib: StereoCalibration, alpha: float = 0.0) -> Rectification:
    """Rectification with ``cv2.stereoRectify`` (CALIB_ZERO_DISPARITY, so both images share p_x).

    ``alpha`` is OpenCV's free scaling: 0 keeps only valid pixels (no black borders, which
    would otherwise breed false corners), 1 keeps every source pixel, -1 is OpenCV's default.
    OpenCV 5 wants the translation as a (3, 1) float64 array. Skew is not modelled by OpenCV;
    a calibration with skew is refused here (use :func:`rectify_thesis`).
    """
    for name, K in (("K_left", calib.K_left), ("K_right", calib.K_right)):
        if K[0, 1] != 0.0:
            raise CalibrationError(f"opencv rectification: {name} has skew {K[0, 1]:.6g}; use method='thesis'")
    R1, R2, P1, P2, _Q, _roi1, _roi2 = cv2.stereoRectify(
        calib.K_left,
        calib.D_left,
        calib.K_right,
        calib.D_right,
        calib.image_size,
        calib.R,
        calib.T.reshape(3, 1).astype(np.float64),
        flags=cv2.CALIB_ZERO_DISPARITY,
        alpha=float(alpha),
    )
    P1 = np.asarray(P1, dtype=float)
    P2 = np.asarray(P2, dtype=float)
    _check_horizontal(P1, P2, "opencv")
    return Rectification(np.asarray(R1, float), np.asarray(R2, float), P1, P2, calib.image_size, "opencv")


def rectify_maps_numpy(
    K: np.ndarray, D: np.ndarray, R: np.ndarray, P: np.ndarray, image_size: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """Remap tables (map_x, map_y), each (height, width) float32, computed with this module's model.

    Equivalent to ``cv2.initUndistortRectifyMap`` but honours skew in K (OpenCV ignores it): for
    each rectified pixel, back-project through P[:, :3]^-1, rotate by Rᵀ into the original
    camera, distort, and project with K.
    """
    w, h = image_size
    u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    uv1 = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], 1)
    rays = uv1 @ np.linalg.inv(np.asarray(P, dtype=float)[:3, :3]).T @ np.asarray(R, dtype=float)
    xy = rays[:, :2] / rays[:, 2:3]
    uv = normalized_to_pixels(distort_normalized(xy, D), K)
    return uv[:, 0].reshape(h, w).astype(np.float32), uv[:, 1].reshape(h, w).astype(np.float32)


RectifyMethod = Literal["opencv", "thesis"]


class Rectifier:
    """Rectifies stereo pairs with remap tables built once from a :class:`StereoCalibration`.

    ``method="opencv"`` uses ``cv2.stereoRectify`` (:func:`rectify_opencv`), ``"thesis"`` the
    construction of eqs. 3.2.5–3.2.10 (:func:`rectify_thesis`). Tables are fixed-point
    (CV_16SC2), the fastest form ``cv2.remap`` takes. :attr:`model` is the rectified rig for the
    front end.
    """

    def __init__(
        self,
        calib: StereoCalibration,
        method: RectifyMethod = "opencv",
        alpha: float = 0.0,
        interpolation: int = cv2.INTER_LINEAR,
    ) -> None:
        if method == "opencv":
            rect = rectify_opencv(calib, alpha=alpha)
        elif method == "thesis":
            rect = rectify_thesis(calib)
        else:
            raise CalibrationError(f"rectification method: expected 'opencv' or 'thesis', got {method!r}")
        self.calib = calib
        self.rectification = rect
        self.interpolation = interpolation
        self._maps = [
            self._build(K, D, R_i, P_i, calib.image_size)
            for K, D, R_i, P_i in (
                (calib.K_left, calib.D_left, rect.R1, rect.P1),
                (calib.K_right, calib.D_right, rect.R2, rect.P2),
            )
        ]
        logger.debug("rectifier (%s): %s", method, rect.model)

    @staticmethod
    def _build(
        K: np.ndarray, D: np.ndarray, R: np.ndarray, P: np.ndarray, size: tuple[int, int]
    ) -> tuple[np.ndarray, np.ndarray]:
        if K[0, 1] == 0.0:
            return cv2.initUndistortRectifyMap(K, D, R, P, size, cv2.CV_16SC2)  # type: ignore[return-value]
        mx, my = rectify_maps_numpy(K, D, R, P, size)
        return cv2.convertMaps(mx, my, cv2.CV_16SC2)  # type: ignore[return-value]

    @property
    def model(self) -> RectifiedStereo:
        return self.rectification.model

    def rectify(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Raw images (H, W[, C]) -> rectified images of the same size and dtype."""
        w, h = self.calib.image_size
        out = []
        for name, img, (m1, m2) in (("left", left, self._maps[0]), ("right", right, self._maps[1])):
            if img.shape[:2] != (h, w):
                raise InputError(f"rectify: {name} image is {img.shape[1]}x{img.shape[0]}, calibration is {w}x{h}")
            out.append(cv2.remap(img, m1, m2, self.interpolation))
        return out[0], out[1]

    def rectify_points(self, uv: np.ndarray, side: Literal["left", "right"]) -> np.ndarray:
        """Raw (distorted) pixels (N, 2) of one camera -> rectified pixels (N, 2)."""
        r = self.rectification
        if side == "left":
            return undistort_points(uv, self.calib.K_left, self.calib.D_left, r.R1, r.P1)
        if side == "right":
            return undistort_points(uv, self.calib.K_right, self.calib.D_right, r.R2, r.P2)
        raise InputError(f"rectify_points: side must be 'left' or 'right', got {side!r}")


def gate_selection_shift(disparity_px: np.ndarray, d_min_px: float, d_max_px: float, sigma_d_px: float) -> np.ndarray:
    """How much nearer (in disparity [px]) a point looks because a gate on its *measured* disparity kept it.

    A front end keeps a match only when its measured disparity lies in [d_min, d_max]. A point
    whose true disparity d is near d_min (the far limit) is therefore kept only on the frames its
    noise made it look nearer, and the first time a landmark coming into range is seen is such a
    frame: the kept measurements are biased by the mean of a normal truncated to the gate,
    E[d̂ | d_min ≤ d̂ ≤ d_max] − d = σ_d (φ(α) − φ(β)) / (Φ(β) − Φ(α)), α = (d_min − d)/σ_d,
    β = (d_max − d)/σ_d. This returns that shift evaluated at the measured disparity (the
    plug-in estimate: the true one is unknown), so ``d̂ − shift`` is the corrected disparity. It
    is about 0.8 σ_d at the far limit, 0.29 σ_d one σ_d inside it and nothing from a few σ_d on;
    the near limit gets the mirror correction. (N,) measured disparities -> (N,) shifts [px].
    """
    d = np.asarray(disparity_px, dtype=float)
    s = float(sigma_d_px)
    if s <= 0 or d.size == 0:
        return np.zeros_like(d)
    a = (float(d_min_px) - d) / s
    b = (float(d_max_px) - d) / s
    num = np.exp(-0.5 * a * a) - np.exp(-0.5 * b * b)
    den = np.sqrt(2.0 * np.pi) * np.maximum(special.ndtr(b) - special.ndtr(a), 1e-12)
    return s * num / den


def debias_points(xyz_R: np.ndarray, disparity_px: np.ndarray, sigma_x_px: float = 0.5) -> np.ndarray:
    """Second-order correction of the triangulation bias (Sibley et al. 2005; docs/math.md §3.3).

    With disparity noise of variance σ_d² = 2σx², E[fb/d̂] ≈ (fb/d)(1 + σ_d²/d²): points come out
    too far, and a stereo odometry built on them overestimates distance travelled by the same
    factor. Dividing out that factor to second order scales each point along its ray by
    (1 − σ_d²/d²). (N, 3) points, (N,) measured disparities -> (N, 3).
    """
    d = np.asarray(disparity_px, dtype=float)
    k = 1.0 - 2.0 * sigma_x_px**2 / d**2
    return np.asarray(xyz_R, dtype=float) * k[:, None]
