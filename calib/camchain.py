"""The calibration file: a Kalibr-style camchain YAML with a versioned robotd header.

Layout (docs/calibration.md has the full description)::

    robotd_calibration_version: 1
    robotd_source: chessboard calibration of 12 pairs in /data/calib
    robotd_info: {stereo_rms_px: 0.31, ...}       # optional, free-form metadata
    cam0:                                          # left camera
      camera_model: pinhole
      intrinsics: [fu, fv, pu, pv]                 # px
      distortion_model: radtan                     # radtan (4; 5 = +k3) | rational (8/12/14, OpenCV order)
      distortion_coeffs: [k1, k2, p1, p2]
      resolution: [width, height]
      skew: 0.0                                    # only written when non-zero (K[0, 1])
    cam1:                                          # right camera, same keys plus
      T_cn_cnm1: 4x4                               # x_cam1 = T x_cam0, translation in metres

``radtan`` with 4 coefficients is exactly Kalibr's model; the 5th coefficient (k3), the
``rational`` model and ``skew`` are robotd extensions. Floats are written with Python's shortest
round-trip repr, so saving and loading gives back bit-identical arrays.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from robotd.errors import CalibrationError
from robotd.stereo import DISTORTION_LENGTHS, StereoCalibration, camera_matrix

CALIBRATION_VERSION = 1

_HEADER = """\
# robotd stereo calibration: Kalibr camchain layout plus robotd keys (see docs/calibration.md).
# cam0 = left, cam1 = right; cam1.T_cn_cnm1 maps left-camera points into the right camera [m].
"""


def _floats(a: np.ndarray) -> list[float]:
    return [float(v) for v in np.asarray(a, dtype=float).ravel()]


def _cam_block(K: np.ndarray, D: np.ndarray, model: str, size: tuple[int, int]) -> dict[str, Any]:
    block: dict[str, Any] = {
        "camera_model": "pinhole",
        "intrinsics": [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])],
        "distortion_model": model,
        "distortion_coeffs": _floats(D),
        "resolution": [int(size[0]), int(size[1])],
    }
    if K[0, 1] != 0.0:
        block["skew"] = float(K[0, 1])
    return block


def _plain(obj: Any) -> Any:
    """numpy scalars/arrays in metadata -> plain Python for safe_dump."""
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _plain(obj.tolist())
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def calibration_to_dict(calib: StereoCalibration) -> dict[str, Any]:
    """The YAML document as a plain dict (key order as written)."""
    doc: dict[str, Any] = {"robotd_calibration_version": CALIBRATION_VERSION, "robotd_source": calib.source}
    if calib.extra:
        doc["robotd_info"] = _plain(calib.extra)
    doc["cam0"] = _cam_block(calib.K_left, calib.D_left, calib.distortion_model, calib.image_size)
    cam1 = _cam_block(calib.K_right, calib.D_right, calib.distortion_model, calib.image_size)
    cam1["T_cn_cnm1"] = [_floats(row) for row in calib.T_right_left()]
    doc["cam1"] = cam1
    return doc


def save_calibration(calib: StereoCalibration, path: str | Path) -> Path:
    """Write ``calib`` to ``path`` (parent directories must exist); returns the path."""
    path = Path(path)
    text = _HEADER + yaml.safe_dump(calibration_to_dict(calib), sort_keys=False, default_flow_style=None, width=200)
    try:
        path.write_text(text)
    except OSError as exc:
        raise CalibrationError(f"{path}: cannot write the calibration file: {exc}") from exc
    return path


def _get(d: Any, key: str, where: str, src: str) -> Any:
    if not isinstance(d, dict) or key not in d:
        raise CalibrationError(f"{src}: missing key {where}{key!r}")
    return d[key]


def _numbers(v: Any, n: int | tuple[int, ...], key: str, src: str) -> np.ndarray:
    sizes = (n,) if isinstance(n, int) else n
    try:
        a = np.asarray(v, dtype=float).ravel()
    except (TypeError, ValueError) as exc:
        raise CalibrationError(f"{src}: {key} must be a list of numbers, got {v!r}") from exc
    if a.size not in sizes or not np.all(np.isfinite(a)):
        raise CalibrationError(f"{src}: {key} must hold {' or '.join(map(str, sizes))} finite numbers, got {v!r}")
    return a


def _parse_cam(doc: dict[str, Any], name: str, src: str) -> tuple[np.ndarray, np.ndarray, str, tuple[int, int]]:
    cam = _get(doc, name, "", src)
    model = _get(cam, "camera_model", f"{name}.", src)
    if model != "pinhole":
        raise CalibrationError(f"{src}: {name}.camera_model {model!r} is not supported (expected 'pinhole')")
    fu, fv, pu, pv = _numbers(_get(cam, "intrinsics", f"{name}.", src), 4, f"{name}.intrinsics", src)
    dist = _get(cam, "distortion_model", f"{name}.", src)
    if dist not in DISTORTION_LENGTHS:
        raise CalibrationError(
            f"{src}: {name}.distortion_model {dist!r} is not supported (expected one of {sorted(DISTORTION_LENGTHS)})"
        )
    D = _numbers(
        _get(cam, "distortion_coeffs", f"{name}.", src), DISTORTION_LENGTHS[dist], f"{name}.distortion_coeffs", src
    )
    res = _numbers(_get(cam, "resolution", f"{name}.", src), 2, f"{name}.resolution", src)
    if any(r <= 0 or not float(r).is_integer() for r in res):
        raise CalibrationError(f"{src}: {name}.resolution must be two positive integers, got {res.tolist()}")
    skew = float(cam.get("skew", 0.0))
    if not math.isfinite(skew):
        raise CalibrationError(f"{src}: {name}.skew must be finite, got {skew}")
    return camera_matrix(fu, fv, pu, pv, skew), D, dist, (int(res[0]), int(res[1]))


def calibration_from_dict(doc: Any, src: str = "<dict>") -> StereoCalibration:
    """Parse and validate a loaded camchain document; ``src`` names the file in error messages."""
    if not isinstance(doc, dict):
        raise CalibrationError(f"{src}: expected a YAML mapping at the top level, got {type(doc).__name__}")
    version = _get(doc, "robotd_calibration_version", "", src)
    if version != CALIBRATION_VERSION:
        raise CalibrationError(
            f"{src}: robotd_calibration_version {version!r} is not supported (this robotd reads {CALIBRATION_VERSION})"
        )
    K0, D0, m0, size0 = _parse_cam(doc, "cam0", src)
    K1, D1, m1, size1 = _parse_cam(doc, "cam1", src)
    if m0 != m1:
        raise CalibrationError(f"{src}: cam0 and cam1 distortion models differ ({m0!r} vs {m1!r})")
    if size0 != size1:
        raise CalibrationError(f"{src}: cam0 and cam1 resolutions differ ({size0} vs {size1})")
    T = _numbers(_get(doc["cam1"], "T_cn_cnm1", "cam1.", src), 16, "cam1.T_cn_cnm1", src).reshape(4, 4)
    if not np.array_equal(T[3], [0.0, 0.0, 0.0, 1.0]):
        raise CalibrationError(f"{src}: cam1.T_cn_cnm1 last row must be [0, 0, 0, 1], got {T[3].tolist()}")
    info = doc.get("robotd_info") or {}
    if not isinstance(info, dict):
        raise CalibrationError(f"{src}: robotd_info must be a mapping, got {type(info).__name__}")
    try:
        return StereoCalibration(
            K_left=K0,
            D_left=D0,
            K_right=K1,
            D_right=D1,
            R=T[:3, :3],
            T=T[:3, 3],
            image_size=size0,
            distortion_model=m0,
            source=str(doc.get("robotd_source", "")),
            extra=info,
        )
    except CalibrationError as exc:
        raise CalibrationError(f"{src}: {exc}") from exc


def load_calibration(path: str | Path) -> StereoCalibration:
    """Read a camchain file written by :func:`save_calibration` (or a compatible hand-written one)."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise CalibrationError(f"{path}: cannot read the calibration file: {exc}") from exc
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise CalibrationError(f"{path}: not valid YAML: {exc}") from exc
    return calibration_from_dict(doc, str(path))
