"""The daemon's input threads: the camera's frames and the vehicle's odometry into their bounded
drop-oldest queues (counted), until the source ends, fails, or the daemon stops."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

import drivers
from robotd.daemon.health import DaemonStats
from robotd.errors import RobotdError
from robotd.msgs import Odometry, StereoFrame
from robotd.queues import DropOldestQueue

logger = logging.getLogger("robotd.daemon")


def pump_frames(
    camera: drivers.StereoCamera,
    queue: DropOldestQueue[StereoFrame],
    stop: threading.Event,
    stats: DaemonStats,
    fail: Callable[[str, str], None],
    say_when_ended: bool,
) -> None:
    """Frames into ``queue``; the queue is closed when the source ends (a replay's last frame) or
    fails, which ``fail`` hears about: without frames there is nothing left to run on."""
    try:
        for frame in camera.frames(timeout_s=0.5):
            if stop.is_set():
                break
            stats.frames_in += 1
            queue.put(frame)
    except RobotdError as exc:
        fail("camera", f"camera stopped: {exc}")
    finally:
        if not stop.is_set() and say_when_ended:
            logger.info("camera source ended")
        queue.close()


def pump_odometry(
    vehicle: drivers.VehicleLink, queue: DropOldestQueue[Odometry], stop: threading.Event, stats: DaemonStats
) -> None:
    """Odometry samples into ``queue``. A link that fails leaves SLAM running visual only; the
    health output shows the link's state."""
    try:
        for odo in vehicle.odometry(timeout_s=0.5):
            if stop.is_set():
                break
            stats.odometry_in += 1
            queue.put(odo)
    except RobotdError as exc:
        logger.error("vehicle thread stopped: %s", exc)
