"""The calibration file: a camchain YAML that Kalibr's own reader loads, with robotd's keys inside.

Layout (docs/calibration.md has the full description)::

    cam0:                                          # left camera; Kalibr reads the keys down to cam_overlaps
      camera_model: pinhole
      intrinsics: [fu, fv, pu, pv]                 # px
      distortion_model: radtan                     # Kalibr's radtan: exactly [k1, k2, p1, p2]
      distortion_coeffs: [k1, k2, p1, p2]
      resolution: [width, height]
      rostopic: /cam0/image_raw                    # where Kalibr finds this camera's images in a bag
      cam_overlaps: [1]
      robotd:                                      # robotd's keys: Kalibr never looks inside
        calibration_version: 2
        source: chessboard calibration of 12 pairs in /data/calib
        info: {stereo_rms_px: 0.31, ...}           # optional, free-form metadata
        kalibr_fields: raw                         # raw | rectified-opencv | rectified-thesis
        raw: {...}                                 # only when the fields above are the rectified view
    cam1:                                          # right camera, same keys plus
      T_cn_cnm1: 4x4                               # x_cam1 = T x_cam0, translation in metres
      robotd: {raw: {..., T_cn_cnm1: 4x4}}         # only when the fields above are the rectified view

Kalibr counts every top-level key as a camera, so nothing but ``cam0`` and ``cam1`` is at the top.
Its fields say exactly robotd's model when that model is Kalibr's (pinhole, radtan with 4
coefficients, no skew): ``kalibr_fields: raw``. Otherwise (the OAK's 14-coefficient rational
model, radtan with k3, skew) Kalibr's fields describe the **rectified** pair robotd works on
(pinhole, zero radtan distortion, the rectified f, principal point and baseline) and robotd's exact
model is kept under ``camN.robotd.raw``; robotd reads that, so it loses nothing.

Files written by earlier robotd (``robotd_calibration_version: 1`` at the top level) are still
read, and so is a plain Kalibr camchain of two pinhole cameras with radtan or no distortion. Floats
are written with Python's shortest round-trip repr, so saving and loading gives back bit-identical
arrays.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from robotd.core.errors import CalibrationError
from robotd.core.stereo import (
    DISTORTION_LENGTHS,
    Rectification,
    StereoCalibration,
    camera_matrix,
    rectify_opencv,
    rectify_thesis,
)

CALIBRATION_VERSION = 2
LEGACY_VERSION = 1  # robotd_calibration_version: 1 at the top level (read, no longer written)
DEFAULT_ROSTOPICS = ("/cam0/image_raw", "/cam1/image_raw")
KALIBR_FIELDS = ("raw", "rectified-opencv", "rectified-thesis")

_HEADER = """\
# robotd stereo calibration: a Kalibr camchain (docs/calibration.md). cam0 = left, cam1 = right;
# cam1.T_cn_cnm1 maps cam0 points into cam1 [m]. robotd's own keys are under camN.robotd, which
# Kalibr ignores; kalibr_fields says whether Kalibr's fields are the raw cameras or the rectified pair.
"""


def _floats(a: np.ndarray) -> list[float]:
    return [float(v) for v in np.asarray(a, dtype=float).ravel()]


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


def _intrinsics(K: np.ndarray) -> list[float]:
    return [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])]


def _raw_block(K: np.ndarray, D: np.ndarray, model: str) -> dict[str, Any]:
    block: dict[str, Any] = {
        "camera_model": "pinhole",
        "intrinsics": _intrinsics(K),
        "distortion_model": model,
        "distortion_coeffs": _floats(D),
    }
    if K[0, 1] != 0.0:
        block["skew"] = float(K[0, 1])
    return block


def kalibr_is_exact(calib: StereoCalibration) -> bool:
    """True when robotd's model is one Kalibr has: pinhole, radtan with 4 coefficients, no skew."""
    return (
        calib.distortion_model == "radtan"
        and calib.D_left.size == 4
        and calib.D_right.size == 4
        and calib.K_left[0, 1] == 0.0
        and calib.K_right[0, 1] == 0.0
    )


def rectification_of(calib: StereoCalibration) -> Rectification:
    """The rectification robotd applies to this rig: OpenCV's with alpha 0 (what the OAK driver and
    the dataset drivers use), or the thesis construction when a camera has skew (OpenCV ignores it)."""
    if calib.K_left[0, 1] != 0.0 or calib.K_right[0, 1] != 0.0:
        return rectify_thesis(calib)
    return rectify_opencv(calib, alpha=0.0)


def _kalibr_cam(intr: list[float], model: str, coeffs: list[float], size: tuple[int, int], topic: str, other: int):
    return {
        "camera_model": "pinhole",
        "intrinsics": intr,
        "distortion_model": model,
        "distortion_coeffs": coeffs,
        "resolution": [int(size[0]), int(size[1])],
        "rostopic": topic,
        "cam_overlaps": [other],
    }


def calibration_to_dict(calib: StereoCalibration, rostopics: Sequence[str] = DEFAULT_ROSTOPICS) -> dict[str, Any]:
    """The YAML document as a plain dict (key order as written)."""
    if len(rostopics) != 2 or not all(isinstance(t, str) and t for t in rostopics):
        raise CalibrationError(f"rostopics: expected two topic names (left, right), got {list(rostopics)!r}")
    size = calib.image_size
    robotd0: dict[str, Any] = {"calibration_version": CALIBRATION_VERSION, "source": calib.source}
    if calib.extra:
        robotd0["info"] = _plain(calib.extra)
    if kalibr_is_exact(calib):
        robotd0["kalibr_fields"] = "raw"
        cam0 = _kalibr_cam(_intrinsics(calib.K_left), "radtan", _floats(calib.D_left), size, rostopics[0], 1)
        cam1 = _kalibr_cam(_intrinsics(calib.K_right), "radtan", _floats(calib.D_right), size, rostopics[1], 0)
        cam1["T_cn_cnm1"] = [_floats(row) for row in calib.T_right_left()]
        cam0["robotd"] = robotd0
        return {"cam0": cam0, "cam1": cam1}
    rect = rectification_of(calib)
    m = rect.model
    intr = [m.f_px, m.f_px, m.px, m.py]
    zero = [0.0, 0.0, 0.0, 0.0]
    T_rect = np.eye(4)
    T_rect[0, 3] = -m.baseline_m  # the rectified right camera sits b along the rectified x axis
    robotd0["kalibr_fields"] = f"rectified-{rect.method}"
    robotd0["raw"] = _raw_block(calib.K_left, calib.D_left, calib.distortion_model)
    raw1 = _raw_block(calib.K_right, calib.D_right, calib.distortion_model)
    raw1["T_cn_cnm1"] = [_floats(row) for row in calib.T_right_left()]
    cam0 = _kalibr_cam(intr, "radtan", zero, size, rostopics[0], 1)
    cam1 = _kalibr_cam(list(intr), "radtan", list(zero), size, rostopics[1], 0)
    cam1["T_cn_cnm1"] = [_floats(row) for row in T_rect]
    cam0["robotd"] = robotd0
    cam1["robotd"] = {"raw": raw1}
    return {"cam0": cam0, "cam1": cam1}


def save_calibration(calib: StereoCalibration, path: str | Path, rostopics: Sequence[str] = DEFAULT_ROSTOPICS) -> Path:
    """Write ``calib`` to ``path`` (parent directories must exist); returns the path."""
    path = Path(path)
    doc = calibration_to_dict(calib, rostopics)
    text = _HEADER + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=200)
    try:
        path.write_text(text)
    except OSError as exc:
        raise CalibrationError(f"{path}: cannot write the calibration file: {exc}") from exc
    return path


# --------------------------------------------------------------------------------------------
# reading


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


def _parse_model(cam: Any, name: str, src: str, allow_none: bool = False) -> tuple[np.ndarray, np.ndarray, str]:
    """K, D, distortion model of one camera mapping (``name`` prefixes the keys in errors)."""
    model = _get(cam, "camera_model", f"{name}.", src)
    if model != "pinhole":
        raise CalibrationError(f"{src}: {name}.camera_model {model!r} is not supported (expected 'pinhole')")
    fu, fv, pu, pv = _numbers(_get(cam, "intrinsics", f"{name}.", src), 4, f"{name}.intrinsics", src)
    dist = _get(cam, "distortion_model", f"{name}.", src)
    if allow_none and dist == "none":
        # Kalibr's undistorted pinhole: robotd's radtan with zero coefficients
        coeffs = cam.get("distortion_coeffs") or []
        if coeffs != []:
            raise CalibrationError(f"{src}: {name}.distortion_coeffs must be empty for 'none', got {coeffs!r}")
        dist, D = "radtan", np.zeros(4)
    elif dist not in DISTORTION_LENGTHS:
        raise CalibrationError(
            f"{src}: {name}.distortion_model {dist!r} is not supported (expected one of {sorted(DISTORTION_LENGTHS)})"
        )
    else:
        D = _numbers(
            _get(cam, "distortion_coeffs", f"{name}.", src), DISTORTION_LENGTHS[dist], f"{name}.distortion_coeffs", src
        )
    skew = cam.get("skew", 0.0)
    if isinstance(skew, bool) or not isinstance(skew, int | float) or not math.isfinite(skew):
        raise CalibrationError(f"{src}: {name}.skew must be a finite number, got {skew!r}")
    return camera_matrix(fu, fv, pu, pv, float(skew)), D, str(dist)


def _parse_resolution(cam: Any, name: str, src: str) -> tuple[int, int]:
    res = _numbers(_get(cam, "resolution", f"{name}.", src), 2, f"{name}.resolution", src)
    if any(r <= 0 or not float(r).is_integer() for r in res):
        raise CalibrationError(f"{src}: {name}.resolution must be two positive integers, got {res.tolist()}")
    return int(res[0]), int(res[1])


def _parse_T(cam: Any, name: str, src: str) -> np.ndarray:
    T = _numbers(_get(cam, "T_cn_cnm1", f"{name}.", src), 16, f"{name}.T_cn_cnm1", src).reshape(4, 4)
    if not np.array_equal(T[3], [0.0, 0.0, 0.0, 1.0]):
        raise CalibrationError(f"{src}: {name}.T_cn_cnm1 last row must be [0, 0, 0, 1], got {T[3].tolist()}")
    return T


def _build(
    cams: tuple[tuple[np.ndarray, np.ndarray, str], tuple[np.ndarray, np.ndarray, str]],
    T: np.ndarray,
    sizes: tuple[tuple[int, int], tuple[int, int]],
    source: str,
    info: Any,
    src: str,
) -> StereoCalibration:
    (K0, D0, m0), (K1, D1, m1) = cams
    if m0 != m1:
        raise CalibrationError(f"{src}: cam0 and cam1 distortion models differ ({m0!r} vs {m1!r})")
    if sizes[0] != sizes[1]:
        raise CalibrationError(f"{src}: cam0 and cam1 resolutions differ ({sizes[0]} vs {sizes[1]})")
    if not isinstance(info, dict):
        raise CalibrationError(f"{src}: the calibration's info must be a mapping, got {type(info).__name__}")
    try:
        return StereoCalibration(
            K_left=K0,
            D_left=D0,
            K_right=K1,
            D_right=D1,
            R=T[:3, :3],
            T=T[:3, 3],
            image_size=sizes[0],
            distortion_model=m0,
            source=source,
            extra=info,
        )
    except CalibrationError as exc:
        raise CalibrationError(f"{src}: {exc}") from exc


def _from_v1(doc: dict[str, Any], src: str) -> StereoCalibration:
    """robotd's first format: robotd_* keys at the top level beside cam0/cam1."""
    version = _get(doc, "robotd_calibration_version", "", src)
    if version != LEGACY_VERSION:
        raise CalibrationError(
            f"{src}: robotd_calibration_version {version!r} is not supported (this robotd reads "
            f"{LEGACY_VERSION} there, and {CALIBRATION_VERSION} as cam0.robotd.calibration_version)"
        )
    cam0, cam1 = _get(doc, "cam0", "", src), _get(doc, "cam1", "", src)
    return _build(
        (_parse_model(cam0, "cam0", src), _parse_model(cam1, "cam1", src)),
        _parse_T(cam1, "cam1", src),
        (_parse_resolution(cam0, "cam0", src), _parse_resolution(cam1, "cam1", src)),
        str(doc.get("robotd_source", "")),
        doc.get("robotd_info") or {},
        src,
    )


def _from_camchain(doc: dict[str, Any], src: str) -> StereoCalibration:
    """The current format (cam0.robotd present) or a plain Kalibr camchain of two cameras."""
    extra_keys = sorted(str(k) for k in doc if k not in ("cam0", "cam1"))
    if extra_keys:
        raise CalibrationError(
            f"{src}: robotd reads a stereo pair, cam0 and cam1 only at the top level; found {', '.join(extra_keys)}"
        )
    cam0, cam1 = _get(doc, "cam0", "", src), _get(doc, "cam1", "", src)
    sizes = (_parse_resolution(cam0, "cam0", src), _parse_resolution(cam1, "cam1", src))
    robotd = cam0.get("robotd")
    if robotd is None:  # a plain Kalibr camchain
        cams = (_parse_model(cam0, "cam0", src, True), _parse_model(cam1, "cam1", src, True))
        return _build(cams, _parse_T(cam1, "cam1", src), sizes, f"Kalibr camchain {src}", {}, src)
    if not isinstance(robotd, dict):
        raise CalibrationError(f"{src}: cam0.robotd must be a mapping, got {type(robotd).__name__}")
    version = _get(robotd, "calibration_version", "cam0.robotd.", src)
    if version != CALIBRATION_VERSION:
        raise CalibrationError(
            f"{src}: cam0.robotd.calibration_version {version!r} is not supported "
            f"(this robotd reads {CALIBRATION_VERSION})"
        )
    fields = _get(robotd, "kalibr_fields", "cam0.robotd.", src)
    if fields not in KALIBR_FIELDS:
        raise CalibrationError(f"{src}: cam0.robotd.kalibr_fields {fields!r} is not one of {list(KALIBR_FIELDS)}")
    source, info = str(robotd.get("source", "")), robotd.get("info") or {}
    if fields == "raw":
        cams = (_parse_model(cam0, "cam0", src), _parse_model(cam1, "cam1", src))
        return _build(cams, _parse_T(cam1, "cam1", src), sizes, source, info, src)
    raw0 = _get(robotd, "raw", "cam0.robotd.", src)
    raw1 = _get(_get(cam1, "robotd", "cam1.", src), "raw", "cam1.robotd.", src)
    cams = (_parse_model(raw0, "cam0.robotd.raw", src), _parse_model(raw1, "cam1.robotd.raw", src))
    return _build(cams, _parse_T(raw1, "cam1.robotd.raw", src), sizes, source, info, src)


def calibration_from_dict(doc: Any, src: str = "<dict>") -> StereoCalibration:
    """Parse and validate a loaded camchain document; ``src`` names the file in error messages."""
    if not isinstance(doc, dict):
        raise CalibrationError(f"{src}: expected a YAML mapping at the top level, got {type(doc).__name__}")
    if any(str(k).startswith("robotd_") for k in doc):
        return _from_v1(doc, src)
    return _from_camchain(doc, src)


def load_calibration(path: str | Path) -> StereoCalibration:
    """Read a calibration file robotd wrote (any version) or a two-camera Kalibr camchain."""
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
