"""The device URLs of a configuration, and their check before anything slow starts.

Which driver URL each config key opens and with which options (the MAVLink link takes some from
``[mavlink]``, the camera its calibration from ``camera.calibration``), and
:func:`check_device_urls`: each URL's scheme and parameters checked by its own driver
(``drivers.check_camera_url`` / ``check_vehicle_url``) without opening a device or reading a file
but the calibration file. ``robotd print-config``, ``run`` and ``record`` call it with the rest of
the config, and the daemon again at the start of its start-up, before the 10–40 s kernel load: a
typo in ``camera.url`` is one error line at once, not a log line after the load (issue 27, item 6).

The calibration path (docs/architecture.md "Calibration"): :func:`camera_options` reads the
camchain file ``camera.calibration`` names (``calib.camchain``, the one reader of the format) into
a :class:`robotd.core.stereo.StereoCalibration` and hands it to the camera's driver as the keyword
``calibration``; the driver rectifies with it or refuses it (its declared ``own_rig``, a size or mode
it cannot use: drivers.cameras). Either way a calibration that cannot be used is a ConfigError naming the key, at
start-up, never a file silently ignored.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Mapping
from typing import Any

import drivers
from robotd.config import Config
from robotd.core.errors import CalibrationError, ConfigError, DriverError
from robotd.core.stereo import StereoCalibration


def link_options(cfg: Config, url: str) -> dict[str, Any]:
    """Driver keywords from the config for a MAVLink link (other links take theirs from the URL)."""
    if not url.startswith("mavlink"):
        return {}
    m = cfg.mavlink
    opts: dict[str, Any] = {"sysid": m.system_id, "message": m.message}
    if m.signing_key_file:
        opts["signing_key"] = m.signing_key_file
    if m.set_origin:
        opts["origin"] = (m.origin_lat_deg, m.origin_lon_deg, m.origin_alt_m)
    return opts


def load_camera_calibration(cfg: Config) -> StereoCalibration | None:
    """The calibration file ``camera.calibration`` names, read and checked; None when it is unset.
    ConfigError naming the key when it cannot be read (missing, malformed, not a rig)."""
    path = cfg.camera.calibration
    if not path:
        return None
    from calib.camchain import load_calibration  # the calibration file format has one reader

    try:
        return load_calibration(path)
    except CalibrationError as exc:
        raise ConfigError(f"camera.calibration: {exc}") from None


@contextlib.contextmanager
def calibration_refusals(cfg: Config) -> Iterator[None]:
    """A CalibrationError raised inside (a camera driver that cannot use ``camera.calibration``:
    its rig is its own, another image size or rectification mode) as the ConfigError naming the
    key and the file. Only while a calibration is set: else the error is the camera's own."""
    try:
        yield
    except CalibrationError as exc:
        if not cfg.camera.calibration:
            raise
        raise ConfigError(f"camera.calibration: {cfg.camera.calibration}: {exc}; unset camera.calibration") from None


def camera_options(cfg: Config, url: str | None = None) -> dict[str, Any]:
    """Driver keywords from the config for the camera at ``url`` (default ``camera.url``):
    ``calibration``, the StereoCalibration of ``camera.calibration``, when that is set. ConfigError
    naming the key when the file cannot be read or that camera's driver cannot use it (checked by
    the driver, without opening the camera); an error in ``url`` itself is left to its own check."""
    calibration = load_camera_calibration(cfg)
    if calibration is None:
        return {}
    url = cfg.camera.url if url is None else url
    with calibration_refusals(cfg):
        try:
            drivers.check_camera_url(url, calibration=calibration)
        except DriverError:
            pass  # the URL's own error: check_device_urls names camera.url, and opening it says it again
    return {"calibration": calibration}


def device_urls(cfg: Config) -> list[tuple[str, str, str, dict[str, Any]]]:
    """(config key, "camera" or "vehicle", URL, driver options) of every device the daemon opens:
    the camera, the vehicle link and, when ``mavlink.enabled`` and the vehicle link is not MAVLink,
    the autopilot link (robotd.daemon.devices.open_devices)."""
    out = [
        ("camera.url", "camera", cfg.camera.url, {}),
        ("vehicle.url", "vehicle", cfg.vehicle.url, link_options(cfg, cfg.vehicle.url)),
    ]
    if cfg.mavlink.enabled and not cfg.vehicle.url.startswith("mavlink"):
        out.append(("mavlink.url", "vehicle", cfg.mavlink.url, link_options(cfg, cfg.mavlink.url)))
    return out


def check_device_urls(cfg: Config, where: str | None = None, given: Mapping[str, str] | None = None) -> None:
    """Raise ConfigError naming the key when a device URL's scheme or parameters are wrong.

    ``where``: the config file the values came from (appended as "(in FILE)", as config errors
    are); ``given``: keys set elsewhere, e.g. ``{"camera.url": "--camera"}``, named instead."""
    given = given or {}
    for key, kind, url, options in device_urls(cfg):
        check = drivers.check_camera_url if kind == "camera" else drivers.check_vehicle_url
        try:
            check(url, **options)
        except DriverError as exc:
            msg = str(exc) if repr(url) in str(exc) else f"{url!r}: {exc}"
            origin = f" (from {given[key]})" if key in given else (f" (in {where})" if where else "")
            raise ConfigError(f"{key}: {msg}{origin}") from None
    # the calibration file after the URL it is for: read, and judged by that camera's driver
    try:
        camera_options(cfg)
    except ConfigError as exc:
        raise ConfigError(f"{exc}{f' (in {where})' if where else ''}") from None
