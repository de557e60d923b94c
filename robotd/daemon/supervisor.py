"""The daemon's main thread while it runs: sd_notify (READY=1 once camera and vehicle deliver,
WATCHDOG=1 only on real SLAM progress, STATUS=), the once-a-second health line, the health
document for the outputs, and the stop conditions (the duration, the source's end, a failed
recording, the stop flag that the signal handlers set).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import Any

from robotd.config import Config
from robotd.daemon.health import HealthMonitor
from robotd.daemon.sdnotify import Notifier
from robotd.outputs import OutputRunner
from robotd.outputs.base import shortest_period
from robotd.outputs.recorder import RecorderOutput

logger = logging.getLogger("robotd.daemon")


class Supervisor:
    """:meth:`run` until the daemon is to stop. ``health_doc``: the daemon's health document;
    ``slam_alive``: the SLAM thread still runs (it ends when the source does); ``fail``: stop the
    daemon with a non-zero status (thread, why); ``needs_vehicle``: a vehicle link is configured."""

    def __init__(
        self,
        cfg: Config,
        duration_s: float,
        stop_event: threading.Event,
        notifier: Notifier,
        health: HealthMonitor,
        runner: OutputRunner,
        recorder: RecorderOutput | None,
        health_doc: Callable[[], dict[str, Any]],
        slam_alive: Callable[[], bool],
        fail: Callable[[str, str], None],
        needs_vehicle: bool,
    ) -> None:
        self.cfg = cfg
        self.duration_s = duration_s
        self.stop_event = stop_event
        self.notifier = notifier
        self.health = health
        self.runner = runner
        self.recorder = recorder
        self.health_doc = health_doc
        self.slam_alive = slam_alive
        self.fail = fail
        self.needs_vehicle = needs_vehicle  # readiness waits for the vehicle's odometry too
        self.ready = False  # camera and vehicle deliver: READY=1 was sent

    def run(self) -> str:
        """Returns why it stopped when the daemon is to stop for a reason of its own ("duration
        reached", "source ended"); "" when the stop flag was set (a signal, or ``fail``)."""
        cfg, stats = self.cfg, self.health.stats
        t_start = time.monotonic()
        next_status = t_start + cfg.log.status_period_s
        health_period = shortest_period(self.runner.outputs, "health_period_s")
        next_health = t_start + health_period
        wd = self.notifier.watchdog_interval_s
        next_wd = t_start
        last_steps = 0
        last_rate_t, last_rate_steps = t_start, 0
        while not self.stop_event.wait(0.05):
            now = time.monotonic()
            if self.duration_s and now - t_start >= self.duration_s:
                return "duration reached"
            if not self.slam_alive():
                # the thread may have ended by failing (``fail`` set the flag after the wait above
                # timed out): the flag's reason stands, the source did not end
                return "" if self.stop_event.is_set() else "source ended"
            if self.recorder is not None and self.recorder.error is not None:
                self.fail("recorder", f"recording failed: {self.recorder.error}")
                break
            if not self.ready and stats.steps > 0 and (stats.odometry_in > 0 or not self.needs_vehicle):
                self.ready = True
                self.notifier.ready("tracking")
                logger.info("ready: camera and vehicle link deliver (first step after %.2f s)", now - t_start)
            if wd is not None and now >= next_wd:
                # ping only on real progress: SLAM completed a step since the last ping
                if stats.steps > last_steps:
                    self.notifier.watchdog()
                    last_steps = stats.steps
                next_wd = now + wd / 2
            if now >= next_health:
                next_health = now + health_period
                self.runner.publish_health(self.health_doc())
            if now >= next_status:
                next_status = now + cfg.log.status_period_s
                fps = (stats.steps - last_rate_steps) / max(now - last_rate_t, 1e-6)
                last_rate_t, last_rate_steps = now, stats.steps
                line = self.health.status_line(self.health_doc(), fps)
                logger.info(line)
                self.notifier.status(line[:200])
        return ""
