"""ROS ``camera_info`` YAML files (the camera_calibration_parsers format) for the left and right cameras.

Each file describes one raw camera and the rectification robotd applies, as ROS's
``sensor_msgs/CameraInfo`` does (image_geometry, stereo_image_proc and camera_info_manager read
them)::

    image_width: 640
    image_height: 400
    camera_name: left
    camera_matrix: {rows: 3, cols: 3, data: [fx, 0, cx, 0, fy, cy, 0, 0, 1]}     # raw camera K
    distortion_model: plumb_bob                                                   # or rational_polynomial
    distortion_coefficients: {rows: 1, cols: 5, data: [k1, k2, t1, t2, k3]}
    rectification_matrix: {rows: 3, cols: 3, data: [...]}                         # R1 / R2
    projection_matrix: {rows: 3, cols: 4, data: [f, 0, px, Tx, 0, f, py, 0, 0, 0, 1, 0]}

``Tx = 0`` for the left camera and ``-f b`` for the right one (b the rectified baseline [m]), so
``stereo_image_proc`` and ``image_geometry.StereoCameraModel`` recover b. The rectification is
robotd's own (:func:`calib.camchain.rectification_of`), the one its images are rectified with.

Distortion: robotd's ``radtan`` (4 or 5 coefficients) is ROS's ``plumb_bob`` (k3 = 0 when there
are 4); ``rational`` is ``rational_polynomial`` with its first 8 coefficients. The OAK's 14
coefficients end in six zeros (thin prism and tilt), so nothing is lost there; when they are not
zero they are dropped, with a warning, because ROS's model has none.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from calib.camchain import rectification_of
from robotd.core.errors import CalibrationError
from robotd.core.stereo import StereoCalibration

logger = logging.getLogger(__name__)

SIDES = ("left", "right")


def _matrix(a: np.ndarray) -> dict[str, Any]:
    a = np.atleast_2d(np.asarray(a, dtype=float))
    return {"rows": int(a.shape[0]), "cols": int(a.shape[1]), "data": [float(v) for v in a.ravel()]}


def ros_distortion(model: str, D: np.ndarray, src: str = "") -> tuple[str, np.ndarray]:
    """robotd's distortion model and coefficients -> ROS's (``plumb_bob`` or ``rational_polynomial``)."""
    D = np.asarray(D, dtype=float).ravel()
    if model == "radtan":
        return "plumb_bob", np.concatenate([D, np.zeros(5 - D.size)]) if D.size < 5 else D[:5]
    if model == "rational":
        if D.size > 8 and np.any(D[8:] != 0.0):
            logger.warning(
                "%s: ROS's rational_polynomial has 8 coefficients; the thin-prism/tilt terms %s are dropped",
                src or "calibration",
                D[8:].tolist(),
            )
        return "rational_polynomial", D[:8]
    raise CalibrationError(f"{src}: distortion model {model!r} has no ROS equivalent")


def camera_info_docs(calib: StereoCalibration, names: tuple[str, str] = SIDES) -> tuple[dict[str, Any], ...]:
    """The two camera_info documents (left, right) as plain dicts in the order ROS writes them."""
    rect = rectification_of(calib)
    w, h = calib.image_size
    docs = []
    for name, K, D, R, P in (
        (names[0], calib.K_left, calib.D_left, rect.R1, rect.P1),
        (names[1], calib.K_right, calib.D_right, rect.R2, rect.P2),
    ):
        model, d = ros_distortion(calib.distortion_model, D, calib.source)
        docs.append(
            {
                "image_width": int(w),
                "image_height": int(h),
                "camera_name": name,
                "camera_matrix": _matrix(K),
                "distortion_model": model,
                "distortion_coefficients": _matrix(d),
                "rectification_matrix": _matrix(R),
                "projection_matrix": _matrix(P),
            }
        )
    return tuple(docs)


def camera_info_paths(camchain: str | Path, out_dir: str | Path | None = None) -> tuple[Path, Path]:
    """Where the YAMLs of ``camchain`` go: ``<stem>_left.yaml`` and ``<stem>_right.yaml`` beside it
    (or in ``out_dir``)."""
    camchain = Path(camchain)
    d = Path(out_dir) if out_dir is not None else camchain.parent
    return d / f"{camchain.stem}_left.yaml", d / f"{camchain.stem}_right.yaml"


def write_camera_info(calib: StereoCalibration, paths: tuple[Path, Path]) -> tuple[Path, Path]:
    """Write both YAMLs; a directory that does not exist or a write error is one CalibrationError."""
    for doc, path in zip(camera_info_docs(calib), paths, strict=True):
        try:
            path.write_text(yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=200))
        except OSError as exc:
            raise CalibrationError(f"{path}: cannot write the camera_info YAML: {exc}") from exc
    return paths
