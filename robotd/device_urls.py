"""The device URLs of a configuration, and their check before anything slow starts.

Which driver URL each config key opens and with which options (the MAVLink link takes some from
``[mavlink]``), and :func:`check_device_urls`: each URL's scheme and parameters checked by its own
driver (``drivers.check_camera_url`` / ``check_vehicle_url``) without opening a device or reading a
file. ``robotd print-config``, ``run`` and ``record`` call it with the rest of the config, and the
daemon again at the start of its start-up, before the 10–40 s kernel load: a typo in
``camera.url`` is one error line at once, not a log line after the load (issue 27, item 6).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import drivers
from robotd.config import Config
from robotd.errors import ConfigError, DriverError


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
