"""oak:// driver package: the only code that imports depthai.

``calibration`` reads factory calibrations (EEPROM JSON or a device); ``camera`` (added
separately) is the stereo camera driver, loaded lazily by :func:`open_oak_camera`; ``host`` what
this machine needs for it (``robotd doctor``). :data:`OAK_CAMERA` is the camera's driver
(registered in drivers.cameras): depthai is imported only when a camera is checked or opened.
"""

from __future__ import annotations

import importlib
from typing import Any

from drivers.cameras import CameraBase, HostCheck
from drivers.oak.calibration import (
    available_devices,
    calibration_from_handler,
    import_oak_calibration,
    load_oak_eeprom_json,
    read_device_calibration,
    stereo_calibration_from_handler,
)
from robotd.core.errors import DriverError

__all__ = [
    "available_devices",
    "calibration_from_handler",
    "import_oak_calibration",
    "load_oak_eeprom_json",
    "open_oak_camera",
    "read_device_calibration",
    "stereo_calibration_from_handler",
]


def _camera_module(url: str) -> Any:
    """``drivers.oak.camera``, imported when first asked for; DriverError when this build lacks it."""
    try:
        return importlib.import_module("drivers.oak.camera")
    except ImportError as exc:
        if not isinstance(exc, ModuleNotFoundError) or exc.name != "drivers.oak.camera":
            raise DriverError(f"{url!r}: the oak:// camera driver could not be loaded: {exc}") from exc
        raise DriverError(
            f"{url!r}: the oak:// camera driver (drivers.oak.camera) is not available in this build"
        ) from exc


def open_oak_camera(url: str, **options: Any) -> Any:
    """Open oak://[device-id] through ``drivers.oak.camera`` (imported only when asked for)."""
    factory = getattr(_camera_module(url), "open_oak_camera", None)
    if factory is None:
        raise DriverError(f"{url!r}: drivers.oak.camera has no open_oak_camera(url, **options)")
    return factory(url, **options)


class OakCameraDriver(CameraBase):
    """``oak://`` (its kind is registered in drivers.cameras): the depthai modules imported when a
    camera is checked or opened; what this machine needs for it, checked by ``robotd doctor``."""

    def open(self, url: str, **options: Any) -> Any:
        return open_oak_camera(url, **options)

    def check_url(self, url: str, **options: Any) -> None:
        _camera_module(url).check_oak_url(url, **options)

    def host_checks(self) -> tuple[HostCheck, ...]:
        from drivers.oak.host import check_udev, check_usb

        return (HostCheck("oak-usb", check_usb), HostCheck("oak-udev", check_udev))


OAK_CAMERA = OakCameraDriver()
