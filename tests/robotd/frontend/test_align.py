"""Frame-to-frame patch alignment (robotd.frontend.align): it finds the sub-pixel shift the
detector's keypoints miss, its kernel computes what the numpy twin does, and it refuses bad input."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

import drivers
from robotd.core.errors import InputError
from robotd.frontend import _align_kernels
from robotd.frontend.align import ALIGN_HALF_PX, ALIGN_ITERATIONS, align_to_previous
from tests.support.reference_frontend import align_numpy


@pytest.fixture(scope="module")
def frames():
    with drivers.open_camera("sim://?realtime=0&fps=30&seed=3") as cam:
        it = cam.frames()
        out = [next(it) for _ in range(3)]
    return out[1].left, out[2].left


def _shifted(img: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """``img`` moved by (sx, sy) px exactly (a phase shift), out(x, y) = img(x − sx, y − sy)."""
    fy, fx = np.fft.fftfreq(img.shape[0])[:, None], np.fft.fftfreq(img.shape[1])[None, :]
    F = np.fft.fft2(img.astype(np.float64)) * np.exp(-2j * np.pi * (fx * sx + fy * sy))
    return np.clip(np.rint(np.real(np.fft.ifft2(F))), 0, 255).astype(np.uint8)


def _orb_matches(a: np.ndarray, b: np.ndarray, within_px: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    orb = cv2.ORB_create(1000)
    ka, da = orb.detectAndCompute(a, None)
    kb, db = orb.detectAndCompute(b, None)
    m = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(da, db)
    pa = np.array([ka[q.queryIdx].pt for q in m])
    pb = np.array([kb[q.trainIdx].pt for q in m])
    keep = np.linalg.norm(pb - pa, axis=1) < within_px  # true matches move by about the shift
    return pa[keep], pb[keep]


def _z(p: np.ndarray, disparity: float = 10.0) -> np.ndarray:
    return np.c_[p[:, 0], p[:, 0] - disparity, p[:, 1]]


def test_alignment_recovers_the_subpixel_shift_keypoints_stick_at(frames):
    img = frames[0]
    moved = _shifted(img, 0.3, 0.2)
    pa, pb = _orb_matches(img, moved)
    assert len(pa) > 200
    keypoint_shift = np.median(pb - pa, axis=0)
    assert abs(keypoint_shift[0] - 0.3) > 0.1  # the detector's corners stick to the pixel grid
    z, ok = align_to_previous(img, moved, _z(pa), _z(pb), 1.5)
    assert ok.mean() > 0.8
    shift = z[ok][:, [0, 2]] - pa[ok]
    np.testing.assert_allclose(np.median(shift, axis=0), [0.3, 0.2], atol=0.03)
    np.testing.assert_allclose(z[ok, 0] - z[ok, 1], 10.0)  # the disparity stays
    np.testing.assert_array_equal(z[~ok], _z(pb)[~ok])


def test_a_match_whose_depth_changes_keeps_its_keypoint(frames):
    img = frames[0]
    pa, pb = _orb_matches(img, _shifted(img, 0.3, 0.0))
    _, ok_same = align_to_previous(img, _shifted(img, 0.3, 0.0), _z(pa), _z(pb), 1.5)
    _, ok_nearer = align_to_previous(img, _shifted(img, 0.3, 0.0), _z(pa, 10.0), _z(pb, 11.0), 1.5)
    assert ok_same.any() and not ok_nearer.any()  # 10 % nearer: the patch's scale changed


def test_kernel_equals_numpy_twin(frames):
    a, b = frames[0], _shifted(frames[0], 0.4, -0.3)
    pa, pb = _orb_matches(a, b)
    pf, pg = _orb_matches(*frames, within_px=30.0)  # and a real frame-to-frame motion
    pa, pb = np.r_[pa[:80], pf[:80]], np.r_[pb[:80], pg[:80]]
    pa = np.r_[pa, [[2.0, 2.0], [a.shape[1] - 3.0, 50.0]]]  # at the border: refused by both
    pb = np.r_[pb, [[2.0, 2.0], [a.shape[1] - 3.0, 50.0]]]
    n = len(pa)
    dx, dy, ok = np.zeros(n), np.zeros(n), np.zeros(n, bool)
    _align_kernels.align_kernel(
        a, b, pa[:, 0], pa[:, 1], pb[:, 0], pb[:, 1], ALIGN_HALF_PX, ALIGN_ITERATIONS, 1.5, dx, dy, ok
    )
    rdx, rdy, rok = align_numpy(a, b, pa[:, 0], pa[:, 1], pb[:, 0], pb[:, 1], ALIGN_HALF_PX, ALIGN_ITERATIONS, 1.5)
    np.testing.assert_array_equal(ok, rok)
    assert ok.sum() > 50 and not ok[-2:].any()
    np.testing.assert_allclose(dx, rdx, atol=1e-9)
    np.testing.assert_allclose(dy, rdy, atol=1e-9)


def test_bad_input_is_refused_with_what_is_wrong():
    img = np.zeros((40, 60), np.uint8)
    z = np.array([[30.0, 20.0, 20.0]])
    with pytest.raises(InputError, match="one shape"):
        align_to_previous(img, img, z, np.zeros((2, 3)), 1.5)
    with pytest.raises(InputError, match="one size"):
        align_to_previous(img, img[:30], z, z, 1.5)
    with pytest.raises(InputError, match="max_px > 0"):
        align_to_previous(img, img, z, z, 0.0)
    zn = z.copy()
    zn[0, 0] = np.nan
    out, ok = align_to_previous(img, img, z, zn, 1.5)  # NaN pixels: left alone, never read
    assert not ok.any() and np.isnan(out[0, 0])
    out, ok = align_to_previous(img, img, np.zeros((0, 3)), np.zeros((0, 3)), 1.5)  # no matches: nothing to do
    assert out.shape == (0, 3) and ok.shape == (0,)
