"""Kalibr's camchain reading rules, re-implemented for the tests (our own code, from the rules).

What Kalibr's ``kalibr_common.ConfigReader`` does with a camchain YAML, as facts:

- the document is loaded with ``yaml.safe_load``; the number of cameras is the number of
  **top-level keys** (every key, not only ``cam<N>``), and the tools loop ``for n in
  range(numCameras)`` over ``data["cam<n>"]``: any other top-level key makes a ``cam<N>`` go
  missing and the reader fails with ``Field 'cam<N>' missing``;
- per camera it reads ``rostopic`` (must be a str), ``camera_model`` with ``intrinsics``
  (pinhole: 4 = [fu, fv, pu, pv]; omni: 5 = [xi, fu, fv, pu, pv], xi >= 0; eucm: 6 =
  [alpha, beta, fu, fv, pu, pv]; ds: 6 = [xi, alpha, fu, fv, pu, pv], 0 <= alpha < 1), where the
  focal lengths and the principal point must be Python floats >= 0; ``distortion_model`` with
  ``distortion_coeffs`` (radtan 4, equidistant 4, fov 1, none 0: exactly that many);
  ``resolution`` (two ints);
- for cam<n>, n >= 1, ``T_cn_cnm1``: a 4x4 homogeneous transform (a rotation and a translation)
  from cam<n-1> into cam<n>;
- optional per camera, read only by the tools that need them: ``cam_overlaps`` (camera ids, each
  < numCameras), ``T_cam_imu`` (4x4), ``timeshift_cam_imu`` (float), ``line_delay``;
- any other key inside a camera mapping is never looked at.

:func:`read_camchain` raises :class:`KalibrError` with Kalibr's wording where Kalibr would fail.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

CAMERA_MODELS = {"pinhole": 4, "omni": 5, "eucm": 6, "ds": 6}
DISTORTION_MODELS = {"radtan": 4, "equidistant": 4, "fov": 1, "none": 0}
# the keys Kalibr's camchain reader ever reads inside a camera mapping
KALIBR_CAMERA_KEYS = frozenset(
    {
        "rostopic",
        "camera_model",
        "intrinsics",
        "distortion_model",
        "distortion_coeffs",
        "resolution",
        "T_cn_cnm1",
        "T_cam_imu",
        "timeshift_cam_imu",
        "cam_overlaps",
        "line_delay",
    }
)


class KalibrError(RuntimeError):
    pass


@dataclass(frozen=True)
class KalibrCamera:
    rostopic: str
    camera_model: str
    intrinsics: list[float]
    distortion_model: str
    distortion_coeffs: list[float]
    resolution: tuple[int, int]
    T_cn_cnm1: np.ndarray | None  # (4, 4), None for cam0


def _field(cam: dict[str, Any], key: str, src: str) -> Any:
    if key not in cam:
        raise KalibrError(f"[CameraChainParameters Reader]: Field '{key}' missing in file: {src}")
    return cam[key]


def _check_transform(T: Any, what: str, src: str) -> np.ndarray:
    try:
        M = np.array(T, dtype=float)
    except (TypeError, ValueError) as exc:
        raise KalibrError(f"invalid {what} in {src}") from exc
    if M.shape != (4, 4) or not np.all(np.isfinite(M)) or not np.allclose(M[3], [0, 0, 0, 1]):
        raise KalibrError(f"invalid {what} in {src}")
    R = M[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise KalibrError(f"invalid {what} in {src}: not a rotation")
    return M


def _camera(cam: Any, n: int, ncams: int, src: str) -> KalibrCamera:
    if not isinstance(cam, dict):
        raise KalibrError(f"cam{n} in {src} is not a mapping")
    topic = _field(cam, "rostopic", src)
    if not isinstance(topic, str):
        raise KalibrError("[CameraConfig Reader]: rostopic has to be a string")
    model = _field(cam, "camera_model", src)
    intr = _field(cam, "intrinsics", src)
    if model not in CAMERA_MODELS:
        raise KalibrError(f"[CameraConfig Reader]: Unknown camera model '{model}'")
    if not isinstance(intr, list) or len(intr) != CAMERA_MODELS[model]:
        raise KalibrError(f"[CameraConfig Reader]: invalid intrinsics for {model}")
    focal, pp = intr[-4:-2], intr[-2:]
    if model == "omni" and intr[0] < 0:
        raise KalibrError("[CameraConfig Reader]: invalid xi_omni")
    if model == "ds" and not 0 <= intr[1] < 1:
        raise KalibrError("[CameraConfig Reader]: invalid alpha_ds")
    if not all(isinstance(v, float) and v >= 0.0 for v in focal):
        raise KalibrError("[CameraConfig Reader]: invalid focalLength (2 floats)")
    if not all(isinstance(v, float) and v >= 0.0 for v in pp):
        raise KalibrError("[CameraConfig Reader]: invalid principalPoint")
    dist = _field(cam, "distortion_model", src)
    coeffs = _field(cam, "distortion_coeffs", src)
    if dist not in DISTORTION_MODELS:
        raise KalibrError(f"[CameraConfig Reader]: Unknown distortion model '{dist}'")
    if not isinstance(coeffs, list) or len(coeffs) != DISTORTION_MODELS[dist]:
        raise KalibrError(f"[CameraConfig Reader]: distortion model '{dist}' requires {DISTORTION_MODELS[dist]}")
    res = _field(cam, "resolution", src)
    if not isinstance(res, list) or len(res) != 2 or not all(isinstance(v, int) for v in res):
        raise KalibrError("[CameraConfig Reader]: invalid resolution")
    T = None
    if n >= 1:
        T = _check_transform(_field(cam, "T_cn_cnm1", src), f"camera baseline (cam{n} in {src})", src)
    for cid in cam.get("cam_overlaps", []):
        if not isinstance(cid, int) or cid >= ncams:
            raise KalibrError(f"out-of-range: camera id of {cid}")
    if "T_cam_imu" in cam:
        _check_transform(cam["T_cam_imu"], f"T_cam_imu (cam{n} in {src})", src)
    if "timeshift_cam_imu" in cam and not isinstance(cam["timeshift_cam_imu"], float):
        raise KalibrError(f"invalid timeshift cam-imu (cam{n} in {src})")
    return KalibrCamera(topic, model, list(intr), dist, list(coeffs), (res[0], res[1]), T)


def read_camchain(path: str | Path) -> list[KalibrCamera]:
    """Every camera of the chain, as Kalibr's tools would loop over them."""
    src = str(path)
    data = yaml.safe_load(Path(path).read_text())
    if not isinstance(data, dict):
        raise KalibrError(f"Could not read configuration from {src}")
    ncams = len(data)  # every top-level key counts as a camera
    cams = [_field(data, f"cam{n}", src) for n in range(ncams)]  # getCameraParameters(n) for each n
    return [_camera(cam, n, ncams, src) for n, cam in enumerate(cams)]
