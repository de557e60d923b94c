"""oak:// driver package: the only code that imports depthai.

``calibration`` reads factory calibrations (EEPROM JSON or a device); ``camera`` (added
separately) is the stereo camera driver, loaded lazily by :func:`open_oak_camera`.
"""

from __future__ import annotations

import importlib
from typing import Any

from drivers.oak.calibration import (
    available_devices,
    calibration_from_handler,
    import_oak_calibration,
    load_oak_eeprom_json,
    read_device_calibration,
    stereo_calibration_from_handler,
)
from robotd.errors import DriverError

__all__ = [
    "available_devices",
    "calibration_from_handler",
    "import_oak_calibration",
    "load_oak_eeprom_json",
    "open_oak_camera",
    "read_device_calibration",
    "stereo_calibration_from_handler",
]


def open_oak_camera(url: str, **options: Any) -> Any:
    """Open oak://[device-id] through ``drivers.oak.camera`` (imported only when asked for)."""
    try:
        camera = importlib.import_module("drivers.oak.camera")
    except ModuleNotFoundError as exc:
        if exc.name != "drivers.oak.camera":
            raise DriverError(f"{url!r}: the oak:// camera driver could not be loaded: {exc}") from exc
        raise DriverError(
            f"{url!r}: the oak:// camera driver (drivers.oak.camera) is not available in this build"
        ) from exc
    factory = getattr(camera, "open_oak_camera", None)
    if factory is None:
        raise DriverError(f"{url!r}: drivers.oak.camera has no open_oak_camera(url, **options)")
    return factory(url, **options)
