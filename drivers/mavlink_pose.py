"""The pose-out role of a MAVLink link: the SLAM pose as ODOMETRY or VISION_POSITION_ESTIMATE.

:class:`MavlinkAutopilot` is what ``MavlinkVehicle.autopilot`` returns (drivers/mavlink_link.py).
It has no socket and no thread of its own: :meth:`MavlinkAutopilot.send_pose` parks the newest
pose and wakes the link's transmit thread, which calls :meth:`MavlinkAutopilot.send_pending` with
its connection after the heartbeat, the TIMESYNC request and the queued replies and setup
messages of that round. The heartbeat's ``system_status`` comes from
:meth:`MavlinkAutopilot.system_status`.

Data-driven: one message per ``send_pose``, a newer pose supersedes an unsent one, a pose not
newer than the last one sent is dropped (``time_usec`` must be strictly monotonic) and nothing is
ever re-sent. The counters (``odometry_sent``, ``vision_position_sent``, ``poses_superseded``,
``poses_stale``, ``poses_withheld``) live in the link's counter dict, so the link's ``stats()``
reports them.

No pymavlink here (drivers/mavlink_link.py is its only importer): the few MAV_STATE values are
written out below and tests check them against pymavlink.
"""

from __future__ import annotations

import math
import threading
from typing import Any, Protocol

import numpy as np

from drivers import HEALTH_STATES
from robotd.core.errors import DriverError
from robotd.core.msgs import PoseEstimate
from robotd.formats.autopilot import CovarianceFloors, odometry_fields, vision_position_fields

# MAV_STATE enum values (HEARTBEAT.system_status)
MAV_STATE_STANDBY = 3
MAV_STATE_ACTIVE = 4
MAV_STATE_CRITICAL = 5
MAV_STATE_FLIGHT_TERMINATION = 8

_SYSTEM_STATUS = {
    "starting": MAV_STATE_STANDBY,
    "tracking": MAV_STATE_ACTIVE,
    "degraded": MAV_STATE_CRITICAL,
    "failed": MAV_STATE_FLIGHT_TERMINATION,
}

STILL_SPEED_MPS = 0.05  # below this speed ...
STILL_TURN_RADPS = 0.02  # ... and this turn rate the vehicle stands still

# the keys of the link's counter dict this role counts in (and reports in stats())
POSE_COUNTERS = ("odometry_sent", "vision_position_sent", "poses_superseded", "poses_stale", "poses_withheld")


class PoseWire(Protocol):
    """The two senders of pymavlink's ``MAVLink`` object (``connection.mav``) used here."""

    def odometry_send(self, *args: object) -> object: ...
    def vision_position_estimate_send(self, *args: object) -> object: ...


class MavlinkAutopilot:
    """:class:`drivers.AutopilotLink` over a MAVLink link's connection and transmit thread.

    ``message`` is ``"odometry"`` or ``"vision_position_estimate"``; ``counters`` is the link's
    counter dict (must hold :data:`POSE_COUNTERS`); ``wake`` is the event the link's transmit
    thread waits on.
    """

    def __init__(
        self, url: str, message: str, floors: CovarianceFloors, counters: dict[str, int], wake: threading.Event
    ) -> None:
        self.url = url
        self.message = message
        self.floors = floors
        self._c = counters
        self._wake = wake
        self._lock = threading.Lock()  # guards the pending pose
        self._pending_pose: tuple[PoseEstimate, int, int, np.ndarray] | None = None
        self._last_pose_t_ns: int | None = None
        self._last_quality = 0
        self._health: str | None = None  # None: derive from quality
        self._last_yaw: tuple[int, float] | None = None  # (t_ns, yaw) of the last pose sent
        self._still_since_ns: int | None = None  # the vehicle has stood still since (pose time)

    # -- AutopilotLink (any thread) ------------------------------------------------------------
    def send_pose(
        self, pose: PoseEstimate, quality: int, reset_counter: int, vel_R_mps: np.ndarray | None = None
    ) -> None:
        """Queue the pose for the transmit thread; a newer pose replaces an unsent one.

        ``vel_R_mps`` (3,) is the body-frame velocity ODOMETRY carries (the daemon's
        :class:`robotd.formats.autopilot.ResetCounterPolicy` fits it); None or a non-finite value sends
        zero, since ArduPilot fuses the velocity without a NaN check."""
        v = np.zeros(3) if vel_R_mps is None else np.asarray(vel_R_mps, dtype=float).reshape(3)
        if not np.all(np.isfinite(v)):
            v = np.zeros(3)
        with self._lock:
            if self._pending_pose is not None:
                self._c["poses_superseded"] += 1
            self._pending_pose = (pose, int(quality), int(reset_counter), v)
        self._wake.set()

    def set_health(self, state: str | None) -> None:
        """ "tracking" -> MAV_STATE_ACTIVE, "degraded" -> CRITICAL, "failed" -> FLIGHT_TERMINATION,
        "starting" -> STANDBY; None derives it from the last quality (−1 -> CRITICAL)."""
        if state is not None and state not in HEALTH_STATES:
            raise DriverError(f"{self.url!r}: health {state!r}, expected one of {HEALTH_STATES}")
        self._health = state

    def health(self) -> str:
        """The health set last, else "starting" before the first pose sent, else from its quality."""
        if self._health is not None:
            return self._health
        if self._last_pose_t_ns is None:
            return "starting"
        return "tracking" if self._last_quality >= 0 else "degraded"

    def stats(self) -> dict[str, Any]:
        return {**{k: self._c[k] for k in POSE_COUNTERS}, "health": self.health()}

    def still_for_s(self) -> float:
        """How long [s] the vehicle has stood still, by the poses sent (0 when moving or unknown)."""
        since, last = self._still_since_ns, self._last_pose_t_ns
        return 0.0 if since is None or last is None else (last - since) * 1e-9

    def _note_motion(self, pose: PoseEstimate, vel: np.ndarray) -> None:
        yaw = float(pose.rpy_rad[2])
        turn = math.inf
        if self._last_yaw is not None and pose.t_ns > self._last_yaw[0]:
            dyaw = (yaw - self._last_yaw[1] + math.pi) % (2 * math.pi) - math.pi
            turn = abs(dyaw) / ((pose.t_ns - self._last_yaw[0]) * 1e-9)
        self._last_yaw = (pose.t_ns, yaw)
        still = math.hypot(*(float(v) for v in np.ravel(vel))) < STILL_SPEED_MPS and turn < STILL_TURN_RADPS
        if not still:
            self._still_since_ns = None
        elif self._still_since_ns is None:
            self._still_since_ns = pose.t_ns

    # -- the link's transmit thread --------------------------------------------------------------
    def system_status(self) -> int:
        """HEARTBEAT.system_status (MAV_STATE) for :meth:`health`."""
        return _SYSTEM_STATUS[self.health()]

    def send_pending(self, mav: PoseWire) -> None:
        """Send the parked pose, if any, on ``mav``; OSError/ValueError reach the caller."""
        with self._lock:
            pending, self._pending_pose = self._pending_pose, None
        if pending is not None:
            self._send_pose_now(mav, *pending)

    def _send_pose_now(
        self, mav: PoseWire, pose: PoseEstimate, quality: int, reset_counter: int, vel: np.ndarray
    ) -> None:
        if self._last_pose_t_ns is not None and pose.t_ns <= self._last_pose_t_ns:
            self._c["poses_stale"] += 1  # time_usec must be strictly monotonic; never re-send
            return
        self._note_motion(pose, vel)
        self._last_pose_t_ns = pose.t_ns
        self._last_quality = quality
        if self.message == "odometry":
            f = odometry_fields(pose, quality, reset_counter, vel_R_mps=vel, floors=self.floors)
            mav.odometry_send(*f.as_args())
            self._c["odometry_sent"] += 1
        else:
            if quality < 0:
                # VISION_POSITION_ESTIMATE has no quality field: a lost track stops the stream
                self._c["poses_withheld"] += 1
                return
            v = vision_position_fields(pose, reset_counter, self.floors)
            mav.vision_position_estimate_send(*v.as_args())
            self._c["vision_position_sent"] += 1
