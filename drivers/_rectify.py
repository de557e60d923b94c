"""Host-side rectification helpers for the replay and camera drivers.

The raw-rig model (:class:`robotd.core.stereo.StereoCalibration`) and the remap-table
:class:`robotd.core.stereo.Rectifier` live in ``robotd.core.stereo``; they are re-exported here so the
drivers have one import site. Conventions (docs/math.md §2.1): optical frames,
``x_right = R x_left + T`` with ``T`` in metres, ``b = -P2[0,3]/P2[0,0]``.
"""

from __future__ import annotations

import numpy as np

from robotd.core.errors import CalibrationError
from robotd.core.geometry import R_ROBOT_OPTICAL, se3
from robotd.core.stereo import RectifiedStereo, Rectifier, StereoCalibration

__all__ = [
    "RectifiedStereo",
    "Rectifier",
    "StereoCalibration",
    "T_robot_leftraw",
    "check_calibration_size",
    "user_rectifier",
]


def check_calibration_size(url: str, calib: StereoCalibration, size: tuple[int, int], remedy: str) -> None:
    """CalibrationError unless ``calib`` is for images of ``size`` (width, height) [px]: intrinsics
    are per resolution, so a calibration made at another size would rectify the images wrongly.
    ``remedy`` ends the message: what the user can do."""
    w, h = calib.image_size
    if (w, h) != tuple(size):
        raise CalibrationError(
            f"{url!r}: the calibration is for {w}x{h} images but the camera gives {size[0]}x{size[1]}; {remedy}"
        )


def user_rectifier(calib: StereoCalibration, alpha: float = 0.0) -> Rectifier:
    """The rectifier for a calibration file's rig (camera.calibration): OpenCV's rectification with
    free scaling ``alpha``, or the thesis construction when a camera has skew, which OpenCV ignores
    (docs/calibration.md §2)."""
    if calib.K_left[0, 1] != 0.0 or calib.K_right[0, 1] != 0.0:
        return Rectifier(calib, method="thesis")
    return Rectifier(calib, alpha=alpha)


def T_robot_leftraw(R1: np.ndarray, baseline_m: float) -> np.ndarray:
    """(4, 4) transform from the raw (unrectified) left optical frame into the robot frame.

    The rectified left camera frame is ``x_Cr = R1 x_C`` (``R1`` from stereoRectify); the robot
    frame sits at the baseline centre, i.e. at (b/2, 0, 0) in the rectified left frame, with FRD
    axes (docs/math.md §1.2): ``x_R = A (R1 x_C - (b/2, 0, 0))`` with A the optical->FRD axis map.
    """
    R = R_ROBOT_OPTICAL @ np.asarray(R1, dtype=float)
    t = -R_ROBOT_OPTICAL @ np.array([baseline_m / 2.0, 0.0, 0.0])
    return se3(R, t)
