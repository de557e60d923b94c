"""Host-side rectification for the replay and camera drivers.

The raw-rig model (:class:`StereoCalibration`) and the remap-table :class:`Rectifier` belong to
``robotd.stereo``; this module re-exports them so the drivers have one import site. While that
half of ``robotd.stereo`` has not landed, a minimal OpenCV-only stand-in with the same names,
fields and behaviour (``cv2.stereoRectify`` with ``CALIB_ZERO_DISPARITY``, remap tables built
once) is used instead. Conventions (algorithms.md §2.1): optical frames, ``x_right = R x_left + T``
with ``T`` in metres, ``b = -P2[0,3]/P2[0,0]``.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from robotd.errors import CalibrationError, InputError
from robotd.stereo import RectifiedStereo

try:  # pragma: no cover - which branch runs depends on the state of robotd.stereo
    from robotd.stereo import Rectifier, StereoCalibration  # type: ignore[attr-defined]
except ImportError:  # pragma: no cover
    from dataclasses import dataclass, field

    @dataclass(frozen=True, slots=True, eq=False)
    class StereoCalibration:  # type: ignore[no-redef]
        """Stand-in for ``robotd.stereo.StereoCalibration`` (same fields, lengths in metres)."""

        K_left: np.ndarray  # (3, 3) [px]
        D_left: np.ndarray  # (n,) OpenCV order
        K_right: np.ndarray  # (3, 3) [px]
        D_right: np.ndarray  # (n,)
        R: np.ndarray  # (3, 3) left optical -> right optical
        T: np.ndarray  # (3,) [m] left -> right
        image_size: tuple[int, int]  # (width, height) [px]
        distortion_model: str = "radtan"
        source: str = ""
        extra: dict[str, object] = field(default_factory=dict)

        @property
        def baseline_m(self) -> float:
            return float(np.linalg.norm(self.T))

    @dataclass(frozen=True, slots=True, eq=False)
    class _Rectification:
        R1: np.ndarray
        R2: np.ndarray
        P1: np.ndarray
        P2: np.ndarray
        image_size: tuple[int, int]
        method: str

        @property
        def model(self) -> RectifiedStereo:
            return RectifiedStereo(
                f_px=float(self.P1[0, 0]),
                px=float(self.P1[0, 2]),
                py=float(self.P1[1, 2]),
                baseline_m=float(-self.P2[0, 3] / self.P2[0, 0]),
                width=int(self.image_size[0]),
                height=int(self.image_size[1]),
            )

    class Rectifier:  # type: ignore[no-redef]
        """Stand-in for ``robotd.stereo.Rectifier`` (OpenCV method only)."""

        def __init__(self, calib: Any, method: str = "opencv", alpha: float = 0.0, interpolation: int = 1) -> None:
            if method != "opencv":
                raise CalibrationError(f"rectification method {method!r} needs robotd.stereo; only 'opencv' here")
            T = np.asarray(calib.T, dtype=np.float64).reshape(3, 1)  # OpenCV 5 wants (3, 1)
            R1, R2, P1, P2, *_ = cv2.stereoRectify(
                calib.K_left,
                calib.D_left,
                calib.K_right,
                calib.D_right,
                calib.image_size,
                calib.R,
                T,
                flags=cv2.CALIB_ZERO_DISPARITY,
                alpha=float(alpha),
            )
            if not -P2[0, 3] / P2[0, 0] > 0:
                raise CalibrationError("rectification: baseline is not positive; is the right camera on the right?")
            self.calib = calib
            self.rectification = _Rectification(
                np.asarray(R1, float), np.asarray(R2, float), np.asarray(P1, float), np.asarray(P2, float),
                tuple(calib.image_size), "opencv",
            )  # fmt: skip
            self.interpolation = interpolation
            r = self.rectification
            self._maps = [
                cv2.initUndistortRectifyMap(calib.K_left, calib.D_left, r.R1, r.P1, calib.image_size, cv2.CV_16SC2),
                cv2.initUndistortRectifyMap(calib.K_right, calib.D_right, r.R2, r.P2, calib.image_size, cv2.CV_16SC2),
            ]

        @property
        def model(self) -> RectifiedStereo:
            return self.rectification.model

        def rectify(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            w, h = self.calib.image_size
            out = []
            for name, img, (m1, m2) in (("left", left, self._maps[0]), ("right", right, self._maps[1])):
                if img.shape[:2] != (h, w):
                    raise InputError(f"rectify: {name} image is {img.shape[1]}x{img.shape[0]}, calibration is {w}x{h}")
                out.append(cv2.remap(img, m1, m2, self.interpolation))
            return out[0], out[1]


__all__ = ["RectifiedStereo", "Rectifier", "StereoCalibration", "T_robot_leftraw"]


def T_robot_leftraw(R1: np.ndarray, baseline_m: float) -> np.ndarray:
    """(4, 4) transform from the raw (unrectified) left optical frame into the robot frame.

    The rectified left camera frame is ``x_Cr = R1 x_C`` (``R1`` from stereoRectify); the robot
    frame sits at the baseline centre, i.e. at (b/2, 0, 0) in the rectified left frame, with FRD
    axes (algorithms.md §1.2): ``x_R = A (R1 x_C - (b/2, 0, 0))`` with A the optical->FRD axis map.
    """
    from robotd.geometry import R_ROBOT_OPTICAL, se3

    R = R_ROBOT_OPTICAL @ np.asarray(R1, dtype=float)
    t = -R_ROBOT_OPTICAL @ np.array([baseline_m / 2.0, 0.0, 0.0])
    return se3(R, t)
