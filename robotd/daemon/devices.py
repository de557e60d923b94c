"""Opening the daemon's devices: the camera, the vehicle link and, when it is elsewhere, the
autopilot link; a missing hardware device is a degraded state with retries, not an exit."""

from __future__ import annotations

import contextlib
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

import drivers
from robotd.config import Config
from robotd.core.errors import DriverError
from robotd.daemon.device_urls import calibration_refusals, camera_options, link_options
from robotd.daemon.sdnotify import Notifier

logger = logging.getLogger(__name__)

D = TypeVar("D")


@dataclass(frozen=True, slots=True)
class Devices:
    camera: drivers.StereoCamera
    vehicle: drivers.VehicleLink
    autopilot: drivers.AutopilotLink | None  # where the pose goes, if anywhere
    autopilot_link: drivers.VehicleLink | None  # a MAVLink link opened only for the pose


def open_devices(
    cfg: Config,
    stack: contextlib.ExitStack,
    stop: threading.Event,
    notifier: Notifier,
    give_up_at: float = math.inf,
) -> Devices:
    """Open the camera and the vehicle link (and a separate autopilot link when ``mavlink.enabled``
    and the vehicle link is not MAVLink: robotd.daemon.device_urls.device_urls); each is closed when
    ``stack`` unwinds. Hardware that is missing is retried until ``stop`` or the monotonic time
    ``give_up_at`` (``--duration``); the URLs were checked before (check_device_urls), so a
    DriverError here is the device's, not a typo's. The camera gets ``camera.calibration``
    (robotd.daemon.device_urls.camera_options); a camera that cannot use it is a ConfigError naming the
    key, never retried."""

    def open_(kind: str, opener: Callable[..., contextlib.AbstractContextManager[D]], url: str, **extra: Any) -> D:
        options = {**link_options(cfg, url), **extra}
        return open_with_retry(stack, kind, opener, url, stop, notifier, give_up_at, **options)

    with calibration_refusals(cfg):
        camera = open_("camera", drivers.open_camera, cfg.camera.url, **camera_options(cfg))
    vehicle = open_("vehicle", drivers.open_vehicle, cfg.vehicle.url)
    if cfg.mavlink.enabled and not cfg.vehicle.url.startswith("mavlink"):
        # odometry from one link (e.g. the MCU over serial), the pose to the autopilot on another
        link = open_("autopilot", drivers.open_vehicle, cfg.mavlink.url)
        return Devices(camera, vehicle, link.autopilot, link)
    return Devices(camera, vehicle, vehicle.autopilot, None)


def open_with_retry(
    stack: contextlib.ExitStack,
    kind: str,
    opener: Callable[..., contextlib.AbstractContextManager[D]],
    url: str,
    stop: threading.Event,
    notifier: Notifier,
    give_up_at: float = math.inf,
    **options: Any,
) -> D:
    """Open a driver; a missing hardware device (``drivers.is_hardware``: a camera whose driver
    declares it, a serial or MAVLink link) is retried (backing off to 10 s) until ``stop``, or until
    the monotonic time ``give_up_at``, when a DriverError says how long it waited."""
    delay = 0.5
    t0 = time.monotonic()
    while True:
        try:
            return stack.enter_context(opener(url, **options))
        except DriverError as exc:
            if stop.is_set():
                raise
            if not drivers.is_hardware(kind, url):
                raise  # a simulator or dataset that fails to open will not heal by waiting
            left = give_up_at - time.monotonic()
            if left <= 0:
                raise DriverError(f"{exc}; gave up after {time.monotonic() - t0:.1f} s (--duration)") from exc
            wait = min(delay, left)
            logger.error("%s %s unavailable: %s; retrying in %.1f s", kind, url, exc, wait)
            notifier.status(f"waiting for {kind}: {exc}")
            if stop.wait(wait):
                raise
            delay = min(delay * 2, 10.0)
