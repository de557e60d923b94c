"""Calibration checks on real images: rectify a pair and measure how well matches share rows.

After a correct rectification, a true left/right correspondence lies on the same row
(docs/math.md §2.1: median |y_L - y_R| of good matches below ~0.3 px). The check matches
features between the rectified images **without** any row constraint (that is what is being
tested), with Lowe's ratio test and a mutual cross-check, then removes mismatches with RANSAC on
the fundamental matrix (thesis eq. 3.2.2: x_Rᵀ F x_L = 0 for some F; it assumes nothing about the
rectification, so a bad rectification still shows in Δy), and reports the statistics of
Δy = y_L - y_R. Repetitive texture (chessboards) breeds mismatches the ratio test lets through;
without the F check they dominate the median.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from robotd.core.errors import CalibrationError, InputError
from robotd.core.stereo import Rectifier, RectifyMethod, StereoCalibration

DETECTORS = ("sift", "orb")


def detect(gray: np.ndarray, detector: str = "sift", max_features: int = 4000) -> tuple[np.ndarray, np.ndarray]:
    """Keypoints (N, 2) float64 [px] and descriptors (N, D) of a grayscale image."""
    if detector == "sift":
        det: cv2.Feature2D = cv2.SIFT.create(nfeatures=max_features)
    elif detector == "orb":
        det = cv2.ORB.create(nfeatures=max_features)
    else:
        raise CalibrationError(f"detector: expected one of {DETECTORS}, got {detector!r}")
    kps, desc = det.detectAndCompute(gray, None)
    if desc is None or not kps:
        return np.zeros((0, 2)), np.zeros((0, 32 if detector == "orb" else 128), np.uint8)
    return np.array([k.pt for k in kps], dtype=float), desc


def match_features(
    xy_l: np.ndarray,
    desc_l: np.ndarray,
    xy_r: np.ndarray,
    desc_r: np.ndarray,
    ratio: float = 0.8,
    max_dy_px: float | None = None,
    disparity_px: tuple[float, float] | None = None,
    cross_check: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Indices (il, ir) of accepted left/right matches (docs/math.md §4.1–§4.2).

    Candidates may be restricted by the row constraint |y_L - y_R| <= ``max_dy_px`` and the
    disparity window d = x_L - x_R in ``disparity_px``; Lowe's ratio test is applied among the
    surviving candidates, then the mutual-nearest-neighbour cross-check.
    """
    n_l, n_r = len(xy_l), len(xy_r)
    if n_l == 0 or n_r < 2:
        return np.zeros(0, int), np.zeros(0, int)
    allowed = np.ones((n_l, n_r), bool)
    if max_dy_px is not None:
        allowed &= np.abs(xy_l[:, None, 1] - xy_r[None, :, 1]) <= max_dy_px
    if disparity_px is not None:
        d = xy_l[:, None, 0] - xy_r[None, :, 0]
        allowed &= (d >= disparity_px[0]) & (d <= disparity_px[1])
    # full distance matrix: a few thousand features make this cheap and keep the masks exact
    dist = descriptor_distances(desc_l, desc_r)
    dist[~allowed] = np.inf
    # the two nearest per row without a full sort (argsort of 4000x4000 costs seconds)
    order = np.argpartition(dist, 1, axis=1)[:, :2]
    rows = np.arange(n_l)
    swap = dist[rows, order[:, 1]] < dist[rows, order[:, 0]]
    order[swap] = order[swap][:, ::-1]
    d1 = dist[rows, order[:, 0]]
    d2 = dist[rows, order[:, 1]]
    ok = np.isfinite(d1) & (d1 < ratio * d2)  # d2 = inf (single candidate) passes: ratio undefined
    il = rows[ok]
    ir = order[ok, 0]
    if cross_check and len(il):
        best_l = np.argmin(dist[:, ir], axis=0)
        keep = best_l == il
        il, ir = il[keep], ir[keep]
    return il, ir


def descriptor_distances(desc_a: np.ndarray, desc_b: np.ndarray) -> np.ndarray:
    """(Na, Nb) distances: Hamming for uint8 (binary) descriptors, Euclidean for float ones."""
    if desc_a.dtype == np.uint8:
        a = np.ascontiguousarray(desc_a)
        b = np.ascontiguousarray(desc_b)
        out = np.empty((len(a), len(b)))
        for s in range(0, len(a), 256):  # chunks bound the (chunk, Nb, bytes) temporary
            out[s : s + 256] = np.bitwise_count(a[s : s + 256, None, :] ^ b[None, :, :]).sum(-1)
        return out
    # float32 is plenty for ranking SIFT distances and halves the time of the big product
    a = desc_a.astype(np.float32)
    b = desc_b.astype(np.float32)
    d2 = a @ b.T
    d2 *= -2.0
    d2 += (a * a).sum(1)[:, None]
    d2 += (b * b).sum(1)[None, :]
    np.maximum(d2, 0.0, out=d2)
    return np.sqrt(d2, out=d2)


def epipolar_inliers(xy_l: np.ndarray, xy_r: np.ndarray, threshold_px: float = 1.5) -> np.ndarray:
    """Boolean (N,) mask of matches consistent with a RANSAC fundamental matrix (eq. 3.2.2)."""
    if len(xy_l) < 8:
        return np.zeros(len(xy_l), bool)
    _F, mask = cv2.findFundamentalMat(xy_l, xy_r, cv2.FM_RANSAC, threshold_px, 0.999)
    if mask is None:
        return np.zeros(len(xy_l), bool)
    return np.asarray(mask).ravel().astype(bool)


def row_offsets(
    left_rect: np.ndarray, right_rect: np.ndarray, detector: str = "sift", ratio: float = 0.8, verify: bool = True
) -> tuple[np.ndarray, int]:
    """Δy = y_L - y_R (M,) of verified matches between two rectified grayscale images, and the
    number of ratio-test matches before the epipolar verification."""
    xl, dl = detect(left_rect, detector)
    xr, dr = detect(right_rect, detector)
    il, ir = match_features(xl, dl, xr, dr, ratio=ratio)
    n_candidates = len(il)
    if verify:
        keep = epipolar_inliers(xl[il], xr[ir])
        il, ir = il[keep], ir[keep]
    return xl[il, 1] - xr[ir, 1], n_candidates


@dataclass
class RowAlignment:
    """Statistics of Δy = y_L - y_R over the matches of a rectified pair [px]."""

    n_candidates: int  # ratio-test + cross-check matches before the epipolar check
    n_matches: int
    median_abs_dy_px: float
    share_within_1px: float
    mean_dy_px: float
    p90_abs_dy_px: float

    def as_dict(self) -> dict[str, float | int]:
        return {
            "n_candidates": self.n_candidates,
            "n_matches": self.n_matches,
            "median_abs_dy_px": self.median_abs_dy_px,
            "share_within_1px": self.share_within_1px,
            "mean_dy_px": self.mean_dy_px,
            "p90_abs_dy_px": self.p90_abs_dy_px,
        }


def summarize_offsets(dy: np.ndarray, n_candidates: int) -> RowAlignment:
    """Statistics of row offsets dy (M,) [px]."""
    if len(dy) == 0:
        raise CalibrationError(f"check: no verified matches between the rectified images ({n_candidates} before)")
    a = np.abs(dy)
    return RowAlignment(
        n_candidates=n_candidates,
        n_matches=len(dy),
        median_abs_dy_px=float(np.median(a)),
        share_within_1px=float(np.mean(a <= 1.0)),
        mean_dy_px=float(np.mean(dy)),
        p90_abs_dy_px=float(np.percentile(a, 90)),
    )


def check_pair(
    calib: StereoCalibration,
    left: np.ndarray,
    right: np.ndarray,
    method: RectifyMethod = "opencv",
    detector: str = "sift",
    ratio: float = 0.8,
    verify: bool = True,
) -> RowAlignment:
    """Rectify a raw pair with ``calib`` and measure row alignment of its matches."""
    if left.ndim == 3:
        left = cv2.cvtColor(left, cv2.COLOR_BGR2GRAY)
    if right.ndim == 3:
        right = cv2.cvtColor(right, cv2.COLOR_BGR2GRAY)
    w, h = calib.image_size
    for name, img in (("left", left), ("right", right)):
        if img.shape[:2] != (h, w):
            raise InputError(f"check: {name} image is {img.shape[1]}x{img.shape[0]}, the calibration is {w}x{h}")
    rl, rr = Rectifier(calib, method=method).rectify(left, right)
    dy, n = row_offsets(rl, rr, detector=detector, ratio=ratio, verify=verify)
    return summarize_offsets(dy, n)
