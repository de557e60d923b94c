"""A reader of ROS ``camera_info`` YAML files (the camera_calibration_parsers format), for the tests.

The format, as camera_calibration_parsers reads it (our own code, from those rules):
``image_width``/``image_height`` (integers), ``camera_name`` (optional, "unknown" without it),
``camera_matrix`` (rows 3, cols 3, data of 9), ``rectification_matrix`` (3×3),
``projection_matrix`` (3×4), ``distortion_model`` (optional; plumb_bob when absent) and
``distortion_coefficients`` (rows × cols numbers, any length). Matrices are row-major. The
distortion models of sensor_msgs are ``plumb_bob`` (5: k1 k2 t1 t2 k3), ``rational_polynomial``
(8: k1 k2 t1 t2 k3 k4 k5 k6) and ``equidistant`` (4).

camera_info_manager also checks the camera name: letters, digits and '_' only.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

DISTORTION_LENGTHS = {"plumb_bob": 5, "rational_polynomial": 8, "equidistant": 4}


class CameraInfoError(ValueError):
    pass


@dataclass(frozen=True)
class CameraInfo:
    width: int
    height: int
    camera_name: str
    distortion_model: str
    K: np.ndarray  # (3, 3)
    D: np.ndarray  # (n,)
    R: np.ndarray  # (3, 3)
    P: np.ndarray  # (3, 4)


def _matrix(doc: dict[str, Any], key: str, rows: int | None, cols: int | None) -> np.ndarray:
    node = doc.get(key)
    if not isinstance(node, dict) or not {"rows", "cols", "data"} <= set(node):
        raise CameraInfoError(f"{key}: expected a mapping with rows, cols, data")
    r, c, data = node["rows"], node["cols"], node["data"]
    shape_ok = (rows is None or r == rows) and (cols is None or c == cols)
    if not isinstance(r, int) or not isinstance(c, int) or not shape_ok:
        raise CameraInfoError(f"{key}: expected {rows}x{cols}, got {r}x{c}")
    if not isinstance(data, list) or len(data) != r * c or not all(isinstance(v, int | float) for v in data):
        raise CameraInfoError(f"{key}: expected {r * c} numbers, got {data!r}")
    return np.array(data, dtype=float).reshape(r, c)


def read_camera_info(path: str | Path) -> CameraInfo:
    doc = yaml.safe_load(Path(path).read_text())
    if not isinstance(doc, dict):
        raise CameraInfoError(f"{path}: not a mapping")
    w, h = doc.get("image_width"), doc.get("image_height")
    if not isinstance(w, int) or not isinstance(h, int) or w <= 0 or h <= 0:
        raise CameraInfoError(f"{path}: image_width/image_height must be positive integers, got {w!r}, {h!r}")
    name = doc.get("camera_name", "unknown")
    if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z0-9_]+", name):
        raise CameraInfoError(f"{path}: camera_name {name!r} is not a valid camera_info_manager name")
    model = doc.get("distortion_model", "plumb_bob")
    D = _matrix(doc, "distortion_coefficients", 1, None).ravel()
    if model not in DISTORTION_LENGTHS or D.size != DISTORTION_LENGTHS[model]:
        raise CameraInfoError(f"{path}: distortion model {model!r} with {D.size} coefficients")
    return CameraInfo(
        width=w,
        height=h,
        camera_name=name,
        distortion_model=model,
        K=_matrix(doc, "camera_matrix", 3, 3),
        D=D,
        R=_matrix(doc, "rectification_matrix", 3, 3),
        P=_matrix(doc, "projection_matrix", 3, 4),
    )
