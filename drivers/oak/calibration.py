"""OAK-D factory calibration -> :class:`robotd.core.stereo.StereoCalibration` (the only depthai import).

depthai reports lengths in **centimetres** and intrinsics for the sensor's full resolution unless
asked for an output size (docs/interfaces.md §2.3). This module is the border: it converts to metres
once and always requests intrinsics for the output size. CAM_B is the left mono camera, CAM_C the
right one; ``getCameraExtrinsics(CAM_B, CAM_C)`` is the 4×4 transform x_C = R x_B + t [cm], the
convention of :class:`StereoCalibration`. Distortion is OpenCV's 14-coefficient rational model.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from robotd.core.errors import CalibrationError, DriverError
from robotd.core.stereo import StereoCalibration

logger = logging.getLogger(__name__)

CM_PER_M = 100.0


@contextlib.contextmanager
def _native_stdout_to_stderr() -> Iterator[None]:
    """Send file descriptor 1 to stderr for the duration.

    depthai's native logger prints its import-time warnings ("USB protocol not available") to
    **stdout**, which would corrupt the one JSON object ``robotd-calib ... --json`` prints.
    """
    try:
        sys.stdout.flush()
        saved = os.dup(1)
    except (OSError, ValueError):  # no real fd 1 (embedded interpreters): nothing to protect
        yield
        return
    try:
        os.dup2(2, 1)
        yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)


def _dai() -> Any:
    if "depthai" in sys.modules:
        return sys.modules["depthai"]
    try:
        with _native_stdout_to_stderr():
            import depthai as dai
    except ImportError as exc:  # pragma: no cover - depthai is a declared dependency
        raise DriverError(f"depthai is not installed ({exc}); it is needed for OAK calibrations") from exc
    return dai


def calibration_from_handler(handler: Any, width: int, height: int, source: str = "") -> StereoCalibration:
    """Left (CAM_B) / right (CAM_C) calibration at the output size ``width`` x ``height`` [px]."""
    dai = _dai()
    if width <= 0 or height <= 0:
        raise CalibrationError(f"OAK calibration: output size must be positive, got {width}x{height}")
    left, right = dai.CameraBoardSocket.CAM_B, dai.CameraBoardSocket.CAM_C
    cams = handler.getEepromData().cameraData
    for name, sock in (("left CAM_B", left), ("right CAM_C", right)):
        if sock not in cams:
            raise CalibrationError(
                f"{source}: the calibration has no {name} camera (has {sorted(str(c) for c in cams)})"
            )
        model = handler.getDistortionModel(sock)
        if model != dai.CameraModel.Perspective:
            raise CalibrationError(f"{source}: {name} uses distortion model {model}; only Perspective is supported")
    try:
        K_l = np.array(handler.getCameraIntrinsics(left, width, height), dtype=float)
        K_r = np.array(handler.getCameraIntrinsics(right, width, height), dtype=float)
        D_l = np.array(handler.getDistortionCoefficients(left), dtype=float)
        D_r = np.array(handler.getDistortionCoefficients(right), dtype=float)
        T_rl = np.array(handler.getCameraExtrinsics(left, right), dtype=float)
    except RuntimeError as exc:
        raise CalibrationError(f"{source}: depthai could not read the stereo calibration: {exc}") from exc
    # depthai pads to 14 coefficients; anything shorter is padded here so the model stays "rational"
    D_l = np.pad(D_l, (0, max(0, 14 - D_l.size)))[:14]
    D_r = np.pad(D_r, (0, max(0, 14 - D_r.size)))[:14]
    R = T_rl[:3, :3]
    # the EEPROM stores float32: re-orthonormalise so the rotation passes StereoCalibration's check
    u, _s, vt = np.linalg.svd(R)
    R = u @ vt
    T_m = T_rl[:3, 3] / CM_PER_M  # centimetres -> metres, once, here
    eeprom = handler.getEepromData()
    info: dict[str, object] = {
        "board": str(eeprom.boardName),
        "product": str(eeprom.productName),
        "eeprom_version": int(eeprom.version),
        "baseline_spec_m": float(handler.getBaselineDistance(right, left, True)) / CM_PER_M,
    }
    return StereoCalibration(
        K_left=K_l,
        D_left=D_l,
        K_right=K_r,
        D_right=D_r,
        R=R,
        T=T_m,
        image_size=(int(width), int(height)),
        distortion_model="rational",
        source=source,
        extra=info,
    )


def load_oak_eeprom_json(path: str | Path, width: int = 640, height: int = 400) -> StereoCalibration:
    """Read a depthai EEPROM JSON dump (``eepromToJsonFile``) without a device."""
    path = Path(path)
    if not path.is_file():
        raise CalibrationError(f"{path}: OAK calibration JSON not found")
    dai = _dai()
    try:
        handler = dai.CalibrationHandler(str(path.resolve()))
    except RuntimeError as exc:
        raise CalibrationError(f"{path}: depthai cannot read it as an EEPROM calibration: {exc}") from exc
    if not handler.getEepromData().cameraData:
        raise CalibrationError(f"{path}: no camera calibration in this file (is it a depthai EEPROM JSON?)")
    return calibration_from_handler(handler, width, height, source=f"OAK EEPROM JSON {path.resolve()}")


def available_devices() -> list[str]:
    """Device ids of the OAKs attached now; returns within about a second (never blocks like Pipeline())."""
    dai = _dai()
    return [str(d.getDeviceId()) for d in dai.Device.getAllAvailableDevices()]


def read_device_calibration(device_id: str = "", width: int = 640, height: int = 400) -> StereoCalibration:
    """Open the OAK with ``device_id`` (or the first one for "") and read its factory calibration.

    Fails fast with :class:`DriverError` when no such device is attached: the device list is checked
    first, because ``dai.Pipeline()``/``dai.Device()`` without hardware block for ~11 s.
    """
    dai = _dai()
    t0 = time.monotonic()
    infos = list(dai.Device.getAllAvailableDevices())
    ids = [str(d.getDeviceId()) for d in infos]
    if not infos:
        raise DriverError(
            f"oak://{device_id}: no OAK device found (searched {time.monotonic() - t0:.1f} s); "
            "plug one in or pass an EEPROM JSON file instead"
        )
    match = [d for d in infos if not device_id or str(d.getDeviceId()) == device_id]
    if not match:
        raise DriverError(f"oak://{device_id}: no attached OAK has this id (found: {', '.join(ids)})")
    try:
        with dai.Device(match[0]) as device:
            handler = device.readCalibration()
    except RuntimeError as exc:
        raise DriverError(f"oak://{device_id}: could not open the device: {exc}") from exc
    return calibration_from_handler(handler, width, height, source=f"OAK device {match[0].getDeviceId()}")


def import_oak_calibration(source: str, width: int = 640, height: int = 400) -> StereoCalibration:
    """``source`` is an EEPROM JSON path (ends in .json or exists) or a device id ("" = first device)."""
    if source.lower().endswith(".json") or Path(source).is_file():
        return load_oak_eeprom_json(source, width, height)
    return read_device_calibration(source, width, height)


def stereo_calibration_from_handler(handler: Any, size: tuple[int, int]) -> StereoCalibration:
    """Adapter for ``drivers.oak.camera``: :func:`calibration_from_handler` with size = (width, height)."""
    return calibration_from_handler(handler, int(size[0]), int(size[1]), source="OAK device calibration")
