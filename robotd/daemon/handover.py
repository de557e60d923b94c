"""Handover across a restart: robotd's pose carried over its own downtime by the autopilot's motion.

A robotd restarted while the rover drives (a watchdog, an update, a crash) resumes its saved map at
the pose it saved, which is where the rover was up to ~2 s earlier; at 1.5 m/s that is 3 m off, and
relocalising against the map cannot help while the rover is in ground the map does not hold
(docs/sitl.md). The autopilot did not stop: its EKF carried the vehicle through the gap on its IMU
(and wheels), and its motion over a few seconds is good to centimetres. So each map save records
the autopilot's pose at the saved pose's frame (``A_saved``, its local NED frame, with its boot
clock), and the first frame of the next run takes

    T_map_robot(now) = T_map_robot(saved) · A_saved⁻¹ · A_now

as the filter's pose, with a covariance that grows with the gap. Only the autopilot's motion
between the two is used, never its frame: the relation between the autopilot's frame and robotd's
map (a compass yaw trim, a vision yaw shift after a gap) does not matter. It assumes robotd's robot
frame and the autopilot's body frame are the same rigid body with the same origin (a lever arm
ℓ adds about ℓ·Δψ of error for a turn Δψ across the gap).

It is refused (the resume then relocalises against the map as before) when the autopilot's boot
clock went backwards or did not advance with the host's (it rebooted: its frame started again),
when the gap is longer than :data:`MAX_GAP_S` (dead reckoning without aiding for that long is no
longer centimetres), or when no autopilot pose is known within :data:`WAIT_S` of the first frame.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from drivers.mavlink_odometry import AutopilotPose
from robotd.core.errors import PersistenceError, RobotdError
from robotd.core.geometry import T_to_pose6, se3_inverse

if TYPE_CHECKING:
    from robotd.pipeline.step import Pipeline

logger = logging.getLogger("robotd.relocalise")

MAX_GAP_S = 10.0  # longer downtimes are dead reckoning the autopilot cannot vouch for
CLOCK_SLACK_S = 1.0  # the autopilot's boot clock and the host's may differ by this across the gap
# how long (frame time) the first frames wait for an autopilot pose before the map alone decides:
# ArduPilot's heartbeat comes at 1 Hz and the link takes nothing from it before, so the first
# LOCAL_POSITION_NED reached robotd 1.0 s after its first frame in SITL on a slow VM
WAIT_S = 3.0
# the prior's standard deviations: a base for the two poses' own errors, and a growth per second of
# gap for the autopilot's dead reckoning (SITL: 2 s gaps came out at centimetres; these are wider)
SIGMA_POS_M = 0.05
SIGMA_POS_MPS = 0.05
SIGMA_ANG_RAD = math.radians(1.0)
SIGMA_ANG_RADPS = math.radians(0.5)


@dataclass(frozen=True, slots=True)
class SavedHandover:
    """What a map save records of the autopilot: its pose ``T`` (4, 4, body FRD -> its local NED)
    at the saved pose's frame, its boot clock then, and the host's Unix time then."""

    T: np.ndarray
    boot_ms: int
    unix_s: float

    def to_doc(self) -> dict[str, Any]:
        return {"T": np.asarray(self.T, float).copy(), "boot_ms": int(self.boot_ms), "unix_s": float(self.unix_s)}

    @staticmethod
    def from_doc(doc: Any) -> SavedHandover:
        """From a map file's ``handover`` table; PersistenceError naming what is wrong."""
        if not isinstance(doc, Mapping):
            raise PersistenceError(f"handover: expected a table, got {type(doc).__name__}")
        try:
            T = np.asarray(doc["T"], dtype=float)
            boot_ms, unix_s = int(doc["boot_ms"]), float(doc["unix_s"])
        except (KeyError, TypeError, ValueError) as exc:
            raise PersistenceError(f"handover: {type(exc).__name__}: {exc}") from None
        if T.shape != (4, 4) or not np.all(np.isfinite(T)) or not math.isfinite(unix_s) or boot_ms < 0:
            raise PersistenceError(f"handover: pose of shape {T.shape} or clock values not finite")
        if not np.allclose(T[3], [0, 0, 0, 1]) or not np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-6):
            raise PersistenceError("handover: the autopilot's pose is not a rigid transform")
        return SavedHandover(T, boot_ms, unix_s)


def unix_of(t_ns: int) -> float:
    """The Unix time of host monotonic ``t_ns`` (a frame's capture time)."""
    return time.time() - (time.monotonic_ns() - int(t_ns)) * 1e-9


def record(pose_at: Callable[[int], AutopilotPose | None] | None, t_ns: int | None) -> dict[str, Any] | None:
    """The ``handover`` table a map save carries for the pose of the frame at ``t_ns``; None when
    there is no autopilot pose then (no MAVLink link, no LOCAL_POSITION_NED near that time)."""
    if pose_at is None or t_ns is None:
        return None
    ap = pose_at(int(t_ns))
    if ap is None:
        return None
    return SavedHandover(ap.T, ap.boot_ms, unix_of(t_ns)).to_doc()


def carried_pose(
    saved: SavedHandover, T_saved_robot: np.ndarray, now: AutopilotPose, unix_now: float
) -> tuple[np.ndarray, float] | str:
    """The robot's pose now (4, 4) in the saved map, and the gap [s]; or why the autopilot's
    motion cannot carry it (a reboot, a gap beyond MAX_GAP_S)."""
    gap_host = unix_now - saved.unix_s
    gap_ap = (now.boot_ms - saved.boot_ms) * 1e-3
    if gap_ap < 0:
        return f"the autopilot's clock went back {-gap_ap:.1f} s (it rebooted)"
    if abs(gap_ap - gap_host) > CLOCK_SLACK_S:
        return f"the autopilot's clock advanced {gap_ap:.1f} s over the host's {gap_host:.1f} s (it rebooted)"
    if gap_ap > MAX_GAP_S:
        return f"down {gap_ap:.1f} s (more than {MAX_GAP_S:g} s of the autopilot's dead reckoning)"
    D = se3_inverse(saved.T) @ now.T  # the vehicle's motion over the gap, in its body frame
    return np.asarray(T_saved_robot, float) @ D, gap_ap


def prior_cov(gap_s: float, dim: int) -> np.ndarray:
    """The carried pose's covariance for a gap of ``gap_s`` seconds, (3, 3) in 2D (x, y, yaw) or
    (6, 6) in 3D."""
    sp = SIGMA_POS_M + SIGMA_POS_MPS * max(gap_s, 0.0)
    sa = SIGMA_ANG_RAD + SIGMA_ANG_RADPS * max(gap_s, 0.0)
    return np.diag([sp**2, sp**2, sa**2]) if dim == 2 else np.diag([sp**2] * 3 + [sa**2] * 3)


def filter_pose(T: np.ndarray, dim: int) -> np.ndarray:
    """(x, y, yaw) in 2D, (x, y, z, roll, pitch, yaw) in 3D, of a (4, 4) pose."""
    x6 = T_to_pose6(T)
    return np.r_[x6[:2], x6[5]] if dim == 2 else x6


class Handover:
    """The SLAM thread's side: before each of the first frames after a resume, :meth:`on_frame`
    asks the autopilot for its pose at the frame's time and, once it has one, resets the filter's
    pose to the carried one (``reset(x, cov)``, robotd.pipeline.step.Pipeline.hand_over). Done
    after one try that decides, or WAIT_S after the first frame without an autopilot pose."""

    def __init__(
        self,
        saved: SavedHandover,
        T_saved_robot: np.ndarray,
        dim: int,
        pose_at: Callable[[int], AutopilotPose | None],
        reset: Callable[[np.ndarray, np.ndarray], None],
        map_found: Callable[[], bool] = lambda: False,
    ) -> None:
        self.saved = saved
        self.T_saved_robot = np.asarray(T_saved_robot, float)
        self.dim = dim
        self.pose_at = pose_at
        self.reset = reset
        self.map_found = map_found
        self.done = False
        self.first_t_ns: int | None = None
        self.outcome: str | None = None  # what happened, for the health document

    @property
    def pending(self) -> bool:
        return not self.done

    def on_frame(self, t_ns: int) -> bool:
        """True when this frame's pose was carried over (the filter reset)."""
        if self.done:
            return False
        if self.map_found():
            # the relocalising window found the pose in the map before the autopilot's was known:
            # a fix from the map's own landmarks beats any dead reckoning
            self.done = True
            self.outcome = "not needed: the map fixed the pose first"
            logger.info("handover: %s", self.outcome)
            return False
        if self.first_t_ns is None:
            self.first_t_ns = int(t_ns)
        now = self.pose_at(int(t_ns))
        if now is None:
            if (t_ns - self.first_t_ns) * 1e-9 >= WAIT_S:
                self.done = True
                self.outcome = f"no autopilot pose within {WAIT_S:g} s of the first frame"
                logger.warning("handover: %s; relocalising against the map alone", self.outcome)
            return False
        self.done = True
        carried = carried_pose(self.saved, self.T_saved_robot, now, unix_of(t_ns))
        if isinstance(carried, str):
            self.outcome = f"refused: {carried}"
            logger.warning("handover: the autopilot's motion not used: %s", carried)
            return False
        T, gap_s = carried
        moved = float(np.linalg.norm(T[:3, 3] - self.T_saved_robot[:3, 3]))
        try:
            self.reset(filter_pose(T, self.dim), prior_cov(gap_s, self.dim))
        except RobotdError as exc:
            self.outcome = f"refused: {exc}"
            logger.warning("handover: the autopilot's motion not used: %s", exc)
            return False
        self.outcome = f"carried {moved:.2f} m over a {gap_s:.1f} s gap"
        logger.info("handover: the pose carried by the autopilot's motion, %s", self.outcome)
        return True


def handover_from(
    doc: object, pipeline: Pipeline, pose_at: Callable[[int], AutopilotPose | None] | None
) -> Handover | None:
    """The handover for a pipeline that just resumed a map whose file held ``doc`` (its
    ``handover`` table, or None); None when the map has none, it is unreadable (logged), or no
    link carries the autopilot's pose in this run."""
    if doc is None:
        logger.info("handover: the saved map holds no autopilot pose; relocalising against the map")
        return None
    if pose_at is None:
        logger.info("handover: no link carries the autopilot's pose in this run; relocalising against the map")
        return None
    try:
        saved = SavedHandover.from_doc(doc)
    except PersistenceError as exc:
        logger.warning("handover ignored: %s", exc)
        return None
    est = pipeline.estimator
    counters = pipeline.counters
    return Handover(
        saved, est.estimate().T_world_robot, est.dim, pose_at, pipeline.hand_over, lambda: counters.relocalisations > 0
    )
