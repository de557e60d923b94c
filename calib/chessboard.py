"""Chessboard stereo calibration: find boards in image pairs, calibrate, drop bad views, recalibrate.

Thesis §3.1.2 and §3.2.1 calibrate each camera from a chessboard and get the relative pose from the
same board views; here OpenCV does the optimisation: ``calibrateCamera`` per camera for a start,
then ``stereoCalibrateExtended`` refines both cameras and the extrinsics jointly and reports the
reprojection RMS of every view. Views whose RMS is an outlier (above both ``outlier_min_px`` and
``outlier_factor`` × the median view RMS) are dropped with the numbers and the rig is recalibrated.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from robotd.core.errors import CalibrationError
from robotd.core.stereo import StereoCalibration

logger = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")

#: distortion option -> (model name, OpenCV flags)
DISTORTION_OPTIONS: dict[str, tuple[str, int]] = {
    "radtan": ("radtan", cv2.CALIB_FIX_K3),  # 4 coefficients, exactly Kalibr's radtan
    "radtan-k3": ("radtan", 0),  # 5 coefficients (k1, k2, p1, p2, k3)
    "rational": ("rational", cv2.CALIB_RATIONAL_MODEL),  # 8 coefficients
}


def parse_board(text: str) -> tuple[int, int]:
    """'9x6' -> (9, 6) inner corners (columns, rows)."""
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not m or int(m.group(1)) < 2 or int(m.group(2)) < 2:
        raise CalibrationError(f"--board: expected inner corners as COLSxROWS such as 9x6, got {text!r}")
    return int(m.group(1)), int(m.group(2))


def board_points(board: tuple[int, int], square_m: float) -> np.ndarray:
    """Board corner coordinates (cols·rows, 3) float32 [m] in the board plane z = 0, row-major."""
    cols, rows = board
    grid = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2)
    pts = np.zeros((cols * rows, 3), np.float32)
    pts[:, :2] = grid * square_m
    return pts


def find_pairs(directory: str | Path) -> tuple[list[tuple[str, Path, Path]], list[tuple[str, str]]]:
    """Pair DIR/left<ID>.<ext> with DIR/right<ID>.<ext>, sorted by ID.

    Returns (pairs as (id, left, right), unpaired as (file name, reason)).
    """
    d = Path(directory)
    if not d.is_dir():
        raise CalibrationError(f"{d}: not a directory of left*/right* image pairs")
    sides: dict[str, dict[str, Path]] = {"left": {}, "right": {}}
    for p in sorted(d.iterdir()):
        if p.suffix.lower() not in IMAGE_SUFFIXES:
            continue
        for side in sides:
            if p.name.lower().startswith(side):
                sides[side][p.stem[len(side) :]] = p
    pairs = [(k, sides["left"][k], sides["right"][k]) for k in sorted(sides["left"]) if k in sides["right"]]
    unpaired = [
        (p.name, "no right image with the same id") for k, p in sides["left"].items() if k not in sides["right"]
    ]
    unpaired += [
        (p.name, "no left image with the same id") for k, p in sides["right"].items() if k not in sides["left"]
    ]
    return pairs, unpaired


def detect_corners(gray: np.ndarray, board: tuple[int, int]) -> np.ndarray | None:
    """Sub-pixel chessboard corners (cols·rows, 2) float32 [px], or None if the board is not found."""
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCorners(gray, board, flags=flags)
    if not found:
        return None
    # (11, 11) half-window as OpenCV's stereo_calib sample: the squares here are ≳ 25 px wide
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.01)
    corners = cv2.cornerSubPix(gray, corners, (11, 11), (-1, -1), crit)
    return corners.reshape(-1, 2).astype(np.float32)


@dataclass
class ViewError:
    """Reprojection RMS of one view [px]; ``rms_px`` combines both images."""

    name: str
    rms_left_px: float
    rms_right_px: float

    @property
    def rms_px(self) -> float:
        return float(np.sqrt(0.5 * (self.rms_left_px**2 + self.rms_right_px**2)))


@dataclass
class StereoCalibrationReport:
    """What a chessboard calibration produced, and which views it used or dropped and why."""

    calibration: StereoCalibration
    stereo_rms_px: float
    mono_rms_left_px: float
    mono_rms_right_px: float
    views: list[ViewError]  # views used in the final calibration
    dropped: list[tuple[str, str]] = field(default_factory=list)  # (view, reason)
    rounds: int = 1

    def as_dict(self) -> dict[str, object]:
        c = self.calibration
        return {
            "stereo_rms_px": self.stereo_rms_px,
            "mono_rms_left_px": self.mono_rms_left_px,
            "mono_rms_right_px": self.mono_rms_right_px,
            "fx_left": float(c.K_left[0, 0]),
            "fy_left": float(c.K_left[1, 1]),
            "cx_left": float(c.K_left[0, 2]),
            "cy_left": float(c.K_left[1, 2]),
            "fx_right": float(c.K_right[0, 0]),
            "fy_right": float(c.K_right[1, 1]),
            "baseline": c.baseline_m,
            "T": c.T.tolist(),
            "distortion_model": c.distortion_model,
            "views_used": len(self.views),
            "per_view_rms_px": {v.name: {"left": v.rms_left_px, "right": v.rms_right_px} for v in self.views},
            "dropped": [{"view": n, "reason": r} for n, r in self.dropped],
            "rounds": self.rounds,
        }


def _calibrate_once(
    obj: list[np.ndarray],
    left: list[np.ndarray],
    right: list[np.ndarray],
    size: tuple[int, int],
    flags: int,
) -> tuple[float, float, float, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    rms_l, K1, D1, _, _ = cv2.calibrateCamera(obj, left, size, None, None, flags=flags)
    rms_r, K2, D2, _, _ = cv2.calibrateCamera(obj, right, size, None, None, flags=flags)
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-6)
    out = cv2.stereoCalibrateExtended(
        obj,
        left,
        right,
        K1,
        D1,
        K2,
        D2,
        size,
        np.eye(3),
        np.zeros((3, 1)),
        flags=flags | cv2.CALIB_USE_INTRINSIC_GUESS,
        criteria=crit,
    )
    rms, K1, D1, K2, D2, R, T = out[:7]
    per_view = np.asarray(out[-1], dtype=float).reshape(-1, 2)
    return float(rms), float(rms_l), float(rms_r), K1, D1, K2, D2, R, T, per_view


def calibrate_views(
    names: list[str],
    left: list[np.ndarray],
    right: list[np.ndarray],
    image_size: tuple[int, int],
    board: tuple[int, int],
    square_m: float = 1.0,
    distortion: str = "radtan",
    outlier_factor: float = 3.0,
    outlier_min_px: float = 0.5,
    min_views: int = 5,
    max_rounds: int = 3,
    dropped: list[tuple[str, str]] | None = None,
    source: str = "",
) -> StereoCalibrationReport:
    """Calibrate a stereo rig from detected corners, dropping per-view RMS outliers.

    ``left``/``right``: per view (cols·rows, 2) corners [px]; ``square_m``: square side [m]
    (the extrinsic translation comes out in these units). A view is an outlier when its combined
    RMS exceeds max(``outlier_min_px``, ``outlier_factor`` × median view RMS); at most
    ``max_rounds`` rounds, never below ``min_views`` views.
    """
    if distortion not in DISTORTION_OPTIONS:
        raise CalibrationError(f"distortion: expected one of {sorted(DISTORTION_OPTIONS)}, got {distortion!r}")
    if not square_m > 0:
        raise CalibrationError(f"--square: expected a positive square size in metres, got {square_m}")
    model, flags = DISTORTION_OPTIONS[distortion]
    dropped = list(dropped or [])
    names, left, right = list(names), list(left), list(right)
    if len(names) < min_views:
        raise CalibrationError(
            f"only {len(names)} usable board views (need >= {min_views}); dropped: "
            + ("; ".join(f"{n}: {r}" for n, r in dropped) or "none")
        )
    pts = board_points(board, square_m)
    rounds = 0
    while True:
        rounds += 1
        obj = [pts] * len(names)
        rms, rms_l, rms_r, K1, D1, K2, D2, R, T, per_view = _calibrate_once(obj, left, right, image_size, flags)
        views = [ViewError(n, float(a), float(b)) for n, (a, b) in zip(names, per_view)]
        combined = np.array([v.rms_px for v in views])
        med = float(np.median(combined))
        limit = max(outlier_min_px, outlier_factor * med)
        logger.info("round %d: %d views, stereo RMS %.3f px, outlier limit %.3f px", rounds, len(views), rms, limit)
        order = np.argsort(-combined)
        bad = [int(i) for i in order if combined[i] > limit][: max(0, len(names) - min_views)]
        if not bad or rounds >= max_rounds:
            break
        for i in bad:
            reason = (
                f"per-view RMS {combined[i]:.3f} px > limit {limit:.3f} px "
                f"(= max({outlier_min_px}, {outlier_factor} x median {med:.3f}))"
            )
            dropped.append((names[i], reason))
            logger.info("dropping view %s: %s", names[i], reason)
        keep = [i for i in range(len(names)) if i not in bad]
        names = [names[i] for i in keep]
        left = [left[i] for i in keep]
        right = [right[i] for i in keep]
    D1 = np.asarray(D1, float).ravel()
    D2 = np.asarray(D2, float).ravel()
    if distortion == "radtan":
        D1, D2 = D1[:4], D2[:4]  # k3 is fixed at 0: drop it to stay Kalibr's 4-coefficient radtan
    calib = StereoCalibration(
        K_left=np.asarray(K1, float),
        D_left=D1,
        K_right=np.asarray(K2, float),
        D_right=D2,
        R=np.asarray(R, float),
        T=np.asarray(T, float).ravel(),
        image_size=image_size,
        distortion_model=model,
        source=source,
        extra={"stereo_rms_px": rms, "views_used": len(names), "square_m": square_m, "board": list(board)},
    )
    return StereoCalibrationReport(calib, rms, rms_l, rms_r, views, dropped, rounds)


def calibrate_directory(
    directory: str | Path,
    board: tuple[int, int] = (9, 6),
    square_m: float = 1.0,
    distortion: str = "radtan",
    outlier_factor: float = 3.0,
    outlier_min_px: float = 0.5,
    min_views: int = 5,
) -> StereoCalibrationReport:
    """Find boards in DIR/left*/right* pairs and calibrate (see :func:`calibrate_views`)."""
    pairs, dropped = find_pairs(directory)
    if not pairs:
        raise CalibrationError(f"{directory}: no left*/right* image pairs ({', '.join(IMAGE_SUFFIXES)}) found")
    names: list[str] = []
    left: list[np.ndarray] = []
    right: list[np.ndarray] = []
    size: tuple[int, int] | None = None
    for key, lp, rp in pairs:
        name = key or lp.stem
        read = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in (lp, rp)]
        if read[0] is None or read[1] is None:
            dropped.append((name, f"cannot read {lp.name if read[0] is None else rp.name} as an image"))
            continue
        imgs: list[np.ndarray] = [np.asarray(im) for im in read]
        shapes = {im.shape[::-1] for im in imgs}
        if len(shapes) != 1:
            dropped.append((name, f"left and right sizes differ: {sorted(shapes)}"))
            continue
        this_size = (int(imgs[0].shape[1]), int(imgs[0].shape[0]))
        if size is None:
            size = this_size
        elif this_size != size:
            dropped.append((name, f"image size {this_size} differs from the first pair's {size}"))
            continue
        cl = detect_corners(imgs[0], board)
        cr = detect_corners(imgs[1], board)
        if cl is None or cr is None:
            which = "both sides" if cl is None and cr is None else ("left" if cl is None else "right")
            dropped.append((name, f"board {board[0]}x{board[1]} not found in {which}"))
            continue
        names.append(name)
        left.append(cl)
        right.append(cr)
    logger.info("%s: board found in %d of %d pairs", directory, len(names), len(pairs))
    assert size is not None or not names
    return calibrate_views(
        names,
        left,
        right,
        size or (0, 0),
        board,
        square_m=square_m,
        distortion=distortion,
        outlier_factor=outlier_factor,
        outlier_min_px=outlier_min_px,
        min_views=min_views,
        dropped=dropped,
        source=f"chessboard {board[0]}x{board[1]}, square {square_m} m, {Path(directory).resolve()}",
    )
