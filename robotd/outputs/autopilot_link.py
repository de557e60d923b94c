"""The autopilot output: every step's pose and health to the vehicle's autopilot link.

The link is a driver's pose-sink role (``drivers.AutopilotLink``): MAVLink ``ODOMETRY`` /
``VISION_POSITION_ESTIMATE`` to ArduPilot or PX4 (docs/mavlink.md), or the simulated rover's
autopilot. It is the vehicle link's own ``autopilot`` when it has one, or a separate MAVLink link
when ``mavlink.enabled`` and the odometry comes from elsewhere (robotd.daemon.devices).
"""

from __future__ import annotations

import logging
from typing import Any

from drivers import AutopilotLink
from robotd.core.errors import RobotdError
from robotd.outputs.base import Output, StepReport

logger = logging.getLogger(__name__)


class AutopilotOutput(Output):
    """Sends the health state, then the pose with its quality and reset counter, once per step."""

    name = "autopilot"

    def __init__(self, link: AutopilotLink) -> None:
        self.link = link
        self.errors = 0

    def publish(self, report: StepReport) -> None:
        try:
            self.link.set_health(report.health)
            self.link.send_pose(report.result.pose, report.quality, report.reset_counter, report.vel_R_mps)
        except RobotdError as exc:
            self.errors += 1
            logger.warning("autopilot pose not sent: %s", exc)

    def stats(self) -> dict[str, Any]:
        return {"errors": self.errors, **self.link.stats()}
