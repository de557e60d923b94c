"""The daemon's input threads: the camera's frames and the vehicle's odometry into their bounded
drop-oldest queues (counted), until the source ends, fails, or the daemon stops.

Every sample is first handed to the ``tees`` (the outputs that keep the sensor log, e.g. the
recorder), in the order the device delivered them, before SLAM's queue can drop it. A tee only
queues the sample for its own thread and returns: it never slows the input thread.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable, Sequence

import drivers
from robotd.core.errors import RobotdError
from robotd.core.msgs import Odometry, StereoFrame
from robotd.daemon.health import DaemonStats
from robotd.formats.queues import DropOldestQueue

logger = logging.getLogger("robotd.daemon")


def pump_frames(
    camera: drivers.StereoCamera,
    queue: DropOldestQueue[StereoFrame],
    stop: threading.Event,
    stats: DaemonStats,
    fail: Callable[[str, str], None],
    say_when_ended: bool,
    stall_s: float = math.inf,
    on_stall: Callable[[float], None] | None = None,
    tees: Sequence[Callable[[StereoFrame], None]] = (),
) -> None:
    """Frames into ``queue``; the queue is closed when the source ends (a replay's last frame) or
    fails, which ``fail`` hears about: without frames there is nothing left to run on. Frames the
    camera never delivered (sequence gaps) are counted in ``stats.frames_missed``, and a gap of
    more than ``stall_s`` between capture times goes to ``on_stall`` (the gap in seconds)."""
    last: StereoFrame | None = None
    try:
        for frame in camera.frames(timeout_s=0.5):
            stats.frames_in += 1
            for tee in tees:  # first: the sensor log keeps every frame delivered, even one in flight at the stop
                tee(frame)
            if stop.is_set():
                break
            if last is not None:
                if frame.seq > last.seq + 1:
                    stats.frames_missed += frame.seq - last.seq - 1
                gap_s = (frame.t_ns - last.t_ns) / 1e9
                if gap_s > stall_s and on_stall is not None:
                    on_stall(gap_s)
            last = frame
            queue.put(frame)
    except RobotdError as exc:
        fail("camera", f"camera stopped: {exc}")
    finally:
        if not stop.is_set() and say_when_ended:
            logger.info("camera source ended")
        queue.close()


def pump_odometry(
    vehicle: drivers.VehicleLink,
    queue: DropOldestQueue[Odometry],
    stop: threading.Event,
    stats: DaemonStats,
    tees: Sequence[Callable[[Odometry], None]] = (),
) -> None:
    """Odometry samples into ``queue`` (each to the ``tees`` first). A link that fails leaves SLAM
    running visual only; the health output shows the link's state."""
    try:
        for odo in vehicle.odometry(timeout_s=0.5):
            stats.odometry_in += 1
            for tee in tees:
                tee(odo)
            if stop.is_set():
                break
            queue.put(odo)
    except RobotdError as exc:
        logger.error("vehicle thread stopped: %s", exc)
