"""Camera model, calibration container and rectification of robotd.core.stereo on synthetic rigs."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.ndimage import map_coordinates

from robotd.core.errors import CalibrationError, InputError
from robotd.core.geometry import numerical_jacobian
from robotd.core.stereo import (
    Rectifier,
    StereoCalibration,
    camera_matrix,
    covariance_from_points,
    distort_normalized,
    distort_points,
    normalized_to_pixels,
    pixels_to_normalized,
    project,
    project_points,
    rectify_maps_numpy,
    rectify_opencv,
    rectify_thesis,
    triangulate,
    triangulation_covariance,
    triangulation_jacobian,
    undistort_normalized,
    undistort_points,
)
from tests.support.tolerances import CONDITIONED_ATOL, CONDITIONED_RTOL, ULP_ATOL

# The project's OAK-D factory model (left camera, 640x400) plus made-up thin-prism and tilt terms, so
# every one of the 14 coefficients is exercised.
D_OAK = np.array([9.43198, 42.34534, 7.1167e-4, -8.0052e-5, 104.69678, 9.53309, 40.01633, 109.38067])
D14 = np.concatenate([D_OAK, [1e-3, -2e-3, 5e-4, 1e-3, 0.01, -0.02]])
D_RADTAN = np.array([-0.28, 0.083, 1.4e-3, -1.3e-4, 0.02])
K_OAK = camera_matrix(430.34, 430.21, 322.05, 199.18)

# undistort_normalized's Newton iteration stops at a residual of 1e-13 (normalised units) with a
# finite-difference Jacobian; strong distortion at the image corners leaves more (measured 1.3e-13)
NEWTON_ATOL = 1e-10
# the same in pixels (× f ≈ 500 px; measured 6.4e-11 px), and on the OAK's rational model, where
# OpenCV's fixed-point iterations are visibly off (measured 4.1e-11 px)
NEWTON_ATOL_PX = 1e-7
OAK_NEWTON_ATOL_PX = 1e-6
# K⁻¹ of a pixel: one affine map on O(1) normalised coordinates, a few ulps (measured 2.2e-16)
K_INVERSE_ATOL = 1e-13
# rectification of raw pixels (Newton undistortion, then a rotation): row offsets and triangulated
# points (measured 3.9e-11 px, 2.9e-11 m)
RECTIFIED_ATOL = 1e-6
# OpenCV's float32 (CV_32FC1) maps against ours: both float32 (equal on x86-64)
OPENCV_MAP_ATOL_PX = 2e-3
# central differences (h = 1e-6 px) of X = f b / d: relative to the entries, with an absolute floor
# for the round-off EPS·X/h ≈ 1e-9 m/px
TRIANGULATION_JAC_RTOL = 1e-6
TRIANGULATION_JAC_ATOL = 1e-9


def _grid(n: int = 400, half_w: float = 0.7, half_h: float = 0.45, seed: int = 1) -> np.ndarray:
    r = np.random.default_rng(seed)
    return r.uniform(-1, 1, (n, 2)) * [half_w, half_h]


@pytest.mark.parametrize("D", [D_RADTAN[:4], D_RADTAN, D_OAK, D14], ids=["radtan4", "radtan5", "rational8", "full14"])
def test_projection_matches_opencv(D: np.ndarray) -> None:
    xy = _grid()
    xyz = np.c_[xy, np.ones(len(xy))] * 2.5
    ours = project_points(xyz, K_OAK, D)
    ref, _ = cv2.projectPoints(xyz, np.zeros(3), np.zeros(3), K_OAK, D)
    assert np.abs(ours - ref.reshape(-1, 2)).max() < CONDITIONED_ATOL


@pytest.mark.parametrize("D", [D_RADTAN, D14], ids=["radtan5", "full14"])
def test_distort_undistort_round_trip(D: np.ndarray) -> None:
    xy = _grid(2000)
    back = undistort_normalized(distort_normalized(xy, D), D)
    assert not np.isnan(back).any()
    assert np.abs(back - xy).max() < NEWTON_ATOL
    # pixel level, including skew
    K = camera_matrix(500.0, 498.0, 320.0, 240.0, skew=1.5)
    uv = normalized_to_pixels(xy, K)
    assert np.abs(pixels_to_normalized(uv, K) - xy).max() < K_INVERSE_ATOL
    assert np.abs(undistort_points(distort_points(uv, K, D), K, D) - uv).max() < NEWTON_ATOL_PX


def test_undistort_beats_opencv_fixed_point_on_strong_distortion() -> None:
    """OpenCV's 5 fixed-point iterations leave visible error on the OAK's rational model; Newton does not."""
    xy = _grid(500, 0.75, 0.48)
    uv_d = project_points(np.c_[xy, np.ones(len(xy))], K_OAK, D_OAK)
    ours = undistort_points(uv_d, K_OAK, D_OAK)
    ideal = normalized_to_pixels(xy, K_OAK)
    err_ours = np.abs(ours - ideal).max()
    ref = cv2.undistortPoints(uv_d.reshape(-1, 1, 2), K_OAK, D_OAK, P=K_OAK).reshape(-1, 2)
    assert err_ours < OAK_NEWTON_ATOL_PX
    assert err_ours <= np.abs(ref - ideal).max()


def test_triangulate_project_round_trip(rng: np.random.Generator) -> None:
    f, px, py, b = 430.0, 320.0, 200.0, 0.075
    pts = np.c_[rng.uniform(0.5, 6, 200), rng.uniform(-2, 2, 200), rng.uniform(-1, 1, 200)]
    xl, xr, y = project(pts, f, px, py, b)
    # X = f b / d, d = x_L − x_R cancels ~300 px down to ~5 px: CONDITIONED_ATOL (1e-10 before; measured 5.1e-14)
    assert np.abs(triangulate(xl, xr, y, f, px, py, b) - pts).max() < CONDITIONED_ATOL


def test_triangulation_jacobian_and_covariance(rng: np.random.Generator) -> None:
    f, px, py, b = 430.0, 320.0, 200.0, 0.075
    pts = np.c_[rng.uniform(0.5, 6, 50), rng.uniform(-2, 2, 50), rng.uniform(-1, 1, 50)]
    xl, xr, y = project(pts, f, px, py, b)
    J = triangulation_jacobian(xl, xr, y, f, px, py, b)
    for i in range(0, 50, 7):
        Jn = numerical_jacobian(
            lambda u: triangulate(u[:1], u[1:2], u[2:], f, px, py, b)[0], np.array([xl[i], xr[i], y[i]])
        )
        assert np.allclose(J[i], Jn, rtol=TRIANGULATION_JAC_RTOL, atol=TRIANGULATION_JAC_ATOL)
    Q = triangulation_covariance(xl, xr, y, f, px, py, b)
    assert np.allclose(Q, covariance_from_points(pts, f, b), rtol=CONDITIONED_RTOL, atol=ULP_ATOL)
    assert np.all(np.linalg.eigvalsh(Q) > 0)


def _rig(skew: float = 0.0, D: np.ndarray = D_RADTAN) -> StereoCalibration:
    R, _ = cv2.Rodrigues(np.array([0.01, -0.02, 0.005]))
    return StereoCalibration(
        K_left=camera_matrix(520.0, 518.0, 322.0, 238.0, skew),
        D_left=D,
        K_right=camera_matrix(525.0, 524.0, 318.0, 243.0, skew),
        D_right=D * 0.9,
        R=R,
        T=np.array([-0.12, 0.004, 0.002]),
        image_size=(640, 480),
        distortion_model="radtan",
    )


@pytest.mark.parametrize("method", ["opencv", "thesis"])
def test_rectification_row_aligns_and_triangulates_truth(method: str, rng: np.random.Generator) -> None:
    """Noiseless points through the raw rig -> rectified pixels share rows and triangulate to the truth."""
    calib = _rig()
    rect = rectify_opencv(calib) if method == "opencv" else rectify_thesis(calib)
    m = rect.model
    assert m.baseline_m == pytest.approx(calib.baseline_m, rel=CONDITIONED_RTOL)
    xyz_L = np.c_[rng.uniform(-1.5, 1.5, 300), rng.uniform(-1, 1, 300), rng.uniform(2, 8, 300)]
    xyz_R = xyz_L @ calib.R.T + calib.T
    uv_l = project_points(xyz_L, calib.K_left, calib.D_left)
    uv_r = project_points(xyz_R, calib.K_right, calib.D_right)
    r = Rectifier(calib, method=method)  # type: ignore[arg-type]
    rl, rr = r.rectify_points(uv_l, "left"), r.rectify_points(uv_r, "right")
    assert np.abs(rl[:, 1] - rr[:, 1]).max() < RECTIFIED_ATOL
    pts = triangulate(rl[:, 0], rr[:, 0], 0.5 * (rl[:, 1] + rr[:, 1]), m.f_px, m.px, m.py, m.baseline_m)
    # robot frame (X fwd, Y right, Z down) at the baseline centre, in the rectified orientation
    xyz_rect = xyz_L @ rect.R1.T
    expected = np.c_[xyz_rect[:, 2], xyz_rect[:, 0] - m.baseline_m / 2, xyz_rect[:, 1]]
    assert np.abs(pts - expected).max() < RECTIFIED_ATOL


def test_thesis_rectification_structure() -> None:
    """Eqs. 3.2.5-3.2.9: new x axis along the baseline, common K = average, rotations orthonormal."""
    calib = _rig()
    rect = rectify_thesis(calib)
    base = calib.c_right_in_left / np.linalg.norm(calib.c_right_in_left)
    assert np.allclose(rect.R1[0], base)
    assert np.allclose(rect.R1 @ rect.R1.T, np.eye(3)) and np.allclose(rect.R2 @ rect.R2.T, np.eye(3))
    K_avg = 0.5 * (calib.K_left + calib.K_right)
    assert rect.P1[0, 0] == pytest.approx(0.5 * (K_avg[0, 0] + K_avg[1, 1]))
    assert np.allclose(rect.P1[:2, 2], K_avg[:2, 2])
    assert np.allclose(rect.P2[:, :3], rect.P1[:, :3])


def test_numpy_maps_match_opencv_and_skew_is_honoured() -> None:
    calib = _rig()
    rect = rectify_opencv(calib)
    mx, my = rectify_maps_numpy(calib.K_left, calib.D_left, rect.R1, rect.P1, calib.image_size)
    cx, cy = cv2.initUndistortRectifyMap(calib.K_left, calib.D_left, rect.R1, rect.P1, calib.image_size, cv2.CV_32FC1)
    assert np.abs(mx - cx).max() < OPENCV_MAP_ATOL_PX and np.abs(my - cy).max() < OPENCV_MAP_ATOL_PX
    skewed = _rig(skew=2.0)
    with pytest.raises(CalibrationError, match="skew"):
        rectify_opencv(skewed)
    # the numpy tables invert rectify_points for a skewed camera; ignoring skew would be ~1 px off
    rect_t = rectify_thesis(skewed)
    mx, my = rectify_maps_numpy(skewed.K_left, skewed.D_left, rect_t.R1, rect_t.P1, skewed.image_size)
    uv = np.c_[np.linspace(120, 520, 40), np.linspace(90, 390, 40)]
    rl = Rectifier(skewed, method="thesis").rectify_points(uv, "left")
    back = np.c_[map_coordinates(mx, [rl[:, 1], rl[:, 0]], order=1), map_coordinates(my, [rl[:, 1], rl[:, 0]], order=1)]
    assert np.abs(back - uv).max() < 0.02
    no_skew = camera_matrix(*skewed.K_left[[0, 1, 0, 1], [0, 1, 2, 2]])
    mx0, _ = rectify_maps_numpy(no_skew, skewed.D_left, rect_t.R1, rect_t.P1, skewed.image_size)
    assert np.abs(map_coordinates(mx0, [rl[:, 1], rl[:, 0]], order=1) - uv[:, 0]).max() > 0.5


def test_rectifier_image_shape_and_side_errors() -> None:
    r = Rectifier(_rig())
    img = np.zeros((480, 640), np.uint8)
    a, _ = r.rectify(img, img)
    assert a.shape == img.shape and a.dtype == img.dtype
    with pytest.raises(InputError, match="320x240"):
        r.rectify(np.zeros((240, 320), np.uint8), img)
    with pytest.raises(InputError, match="side"):
        r.rectify_points(np.zeros((1, 2)), "middle")  # type: ignore[arg-type]
    with pytest.raises(CalibrationError, match="method"):
        Rectifier(_rig(), method="bogus")  # type: ignore[arg-type]


def test_calibration_validation_messages() -> None:
    good = _rig()
    kw = dict(
        K_left=good.K_left,
        D_left=good.D_left,
        K_right=good.K_right,
        D_right=good.D_right,
        R=good.R,
        T=good.T,
        image_size=good.image_size,
    )
    with pytest.raises(CalibrationError, match="D_left.*radtan.*got 14"):
        StereoCalibration(**{**kw, "D_left": D14})  # type: ignore[arg-type]
    with pytest.raises(CalibrationError, match="R: not a rotation"):
        StereoCalibration(**{**kw, "R": good.R * 1.01})  # type: ignore[arg-type]
    with pytest.raises(CalibrationError, match="image_size"):
        StereoCalibration(**{**kw, "image_size": (0, 480)})  # type: ignore[arg-type]
    with pytest.raises(CalibrationError, match="distortion_model"):
        StereoCalibration(**kw, distortion_model="fisheye")  # type: ignore[arg-type]
    # a rig whose "right" camera is on the left cannot be described by RectifiedStereo
    swapped = StereoCalibration(**{**kw, "T": -good.T})  # type: ignore[arg-type]
    with pytest.raises(CalibrationError, match="baseline"):
        rectify_opencv(swapped)
