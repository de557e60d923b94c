"""ROS 2 messages, CDR-encoded, on Zenoh keys that zenoh-bridge-ros2dds maps to ROS 2 topics.

With ``[zenoh] ros2 = true`` the Zenoh output also publishes (docs/topics.md, "ROS 2"):

============================== ================================== ==================================
key (= ROS 2 topic without /)  type                               when
============================== ================================== ==================================
``robotd/<id>/odom``           ``nav_msgs/msg/Odometry``          with every pose
``robotd/<id>/landmarks``      ``sensor_msgs/msg/PointCloud2``    with every map update
``robotd/<id>/diagnostics``    ``diagnostic_msgs/msg/DiagnosticArray`` with every health message
============================== ================================== ==================================

zenoh-bridge-ros2dds routes the ROS topic ``/a/b`` to the Zenoh key ``a/b`` (its ``namespace``
option, when set, prefixes the key) and passes the payload through as the CDR bytes of the DDS
sample, encapsulation header included. The bytes come from ``rosbags``' serializer
(``Typestore.serialize_cdr``, little-endian), never from hand-written CDR.

Frames. robotd's world frame is the robot's start pose forward-right-down (MAVLink LOCAL_FRD) and
its body frame is FRD; ROS (REP-103) wants forward-left-up bodies and (REP-105) a world frame with
z up. The two differ by a half turn about x, ``F = diag(1, -1, -1)`` (its own inverse):

- position ``p_ROS = F p``; landmark positions likewise;
- rotation ``R_ROS = F R F``, i.e. for ZYX Euler angles ``(roll, pitch, yaw) -> (roll, -pitch, -yaw)``
  (a right turn, positive yaw in FRD, is a negative yaw in ROS);
- the 6×6 pose covariance over (x, y, z, roll, pitch, yaw): ``C_ROS = J C J`` with
  ``J = diag(1, -1, -1, 1, -1, -1)``: the signs of the y/z/pitch/yaw cross terms with x/roll flip.

The angular block stays over (roll, pitch, yaw) as robotd estimates them; ROS documents the block
as rotations about the fixed X, Y, Z axes, which robot_localization reads as roll, pitch, yaw. The
twist is not estimated: zero, with ``twist.covariance[0] = -1`` (sensor_msgs' "not provided").

Stamps: ``header.stamp`` is the capture time on the wall clock by default (ROS tools compare stamps
with ``now()``): robotd's monotonic ``t_ns`` plus the wall-minus-monotonic offset read when the
message is built; ``ros2_stamp = "monotonic"`` keeps ``t_ns`` as it is.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from robotd.core.geometry import R_to_quat, euler_to_R
from robotd.core.msgs import LandmarkMap, PoseEstimate

ODOMETRY = "nav_msgs/msg/Odometry"
POINT_CLOUD2 = "sensor_msgs/msg/PointCloud2"
DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"
# (Zenoh key suffix under robotd/<id>/, ROS 2 type)
TOPICS = {"odom": ODOMETRY, "landmarks": POINT_CLOUD2, "diagnostics": DIAGNOSTIC_ARRAY}

F_FRD_FLU = np.diag([1.0, -1.0, -1.0])  # FRD <-> FLU (a half turn about x; its own inverse)
J_POSE6 = np.diag([1.0, -1.0, -1.0, 1.0, -1.0, -1.0])  # (x, y, z, roll, pitch, yaw) FRD <-> FLU

# diagnostic_msgs/DiagnosticStatus levels
OK, WARN, ERROR = 0, 1, 2


def pose_to_ros(pose: PoseEstimate) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """robotd's FRD pose -> (position (3,) [m], quaternion (x, y, z, w), covariance (6, 6)) in ROS's FLU."""
    R = F_FRD_FLU @ euler_to_R(np.asarray(pose.rpy_rad, float)) @ F_FRD_FLU
    w, x, y, z = R_to_quat(R)
    cov = J_POSE6 @ np.asarray(pose.cov, float) @ J_POSE6
    return F_FRD_FLU @ np.asarray(pose.xyz_W_m, float), np.array([x, y, z, w]), cov


def wall_offset_ns() -> int:
    """Wall clock minus monotonic clock, now [ns]."""
    return time.time_ns() - time.monotonic_ns()


def _flatten(doc: Mapping[str, Any], prefix: str = "") -> list[tuple[str, str]]:
    """Nested health document -> (dotted key, value text); strings as they are, the rest as JSON."""
    out: list[tuple[str, str]] = []
    for k, v in doc.items():
        key = f"{prefix}{k}"
        if isinstance(v, Mapping):
            out += _flatten(v, key + ".")
        else:
            out.append((key, v if isinstance(v, str) else json.dumps(v)))
    return out


def health_level(health: Mapping[str, Any]) -> tuple[int, str]:
    """The DiagnosticStatus level and message of a health document (docs/topics.md)."""
    budget = health.get("budget")
    level = budget.get("level", 0) if isinstance(budget, Mapping) else 0
    if not health.get("ready", False):
        return WARN, "starting: camera or vehicle link not delivering yet"
    if not health.get("tracking", False):
        return ERROR, "tracking lost"
    if isinstance(level, int) and level > 0:
        return WARN, f"degraded: latency budget level {level}"
    return OK, "tracking"


class Ros2Encoder:
    """Builds the CDR payloads. ``offset_ns`` gives the stamp offset added to monotonic ``t_ns``
    (:func:`wall_offset_ns` for wall-clock stamps, ``lambda: 0`` to keep the monotonic clock)."""

    def __init__(
        self, robot_id: str, world_frame: str, body_frame: str, offset_ns: Callable[[], int] = wall_offset_ns
    ) -> None:
        from rosbags.typesys import Stores, get_typestore

        # the three types are the same in every ROS 2 release rosbags knows; Humble is the oldest LTS
        self.store = get_typestore(Stores.ROS2_HUMBLE)
        self.robot_id = robot_id
        self.world_frame = world_frame
        self.body_frame = body_frame
        self.offset_ns = offset_ns
        t = self.store.types
        self._Header, self._Time = t["std_msgs/msg/Header"], t["builtin_interfaces/msg/Time"]
        self._pf: Any = t["sensor_msgs/msg/PointField"]

    def _header(self, t_ns: int, frame: str) -> Any:
        stamp = int(t_ns) + int(self.offset_ns())
        return self._Header(stamp=self._Time(sec=stamp // 1_000_000_000, nanosec=stamp % 1_000_000_000), frame_id=frame)

    def odometry(self, pose: PoseEstimate) -> bytes:
        t = self.store.types
        p, q, cov = pose_to_ros(pose)
        twist_cov = np.zeros(36)
        twist_cov[0] = -1.0
        msg = t[ODOMETRY](
            header=self._header(pose.t_ns, self.world_frame),
            child_frame_id=self.body_frame,
            pose=t["geometry_msgs/msg/PoseWithCovariance"](
                pose=t["geometry_msgs/msg/Pose"](
                    position=t["geometry_msgs/msg/Point"](x=float(p[0]), y=float(p[1]), z=float(p[2])),
                    orientation=t["geometry_msgs/msg/Quaternion"](
                        x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3])
                    ),
                ),
                covariance=np.ascontiguousarray(cov, dtype=np.float64).ravel(),
            ),
            twist=t["geometry_msgs/msg/TwistWithCovariance"](
                twist=t["geometry_msgs/msg/Twist"](
                    linear=t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                    angular=t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                ),
                covariance=twist_cov,
            ),
        )
        return bytes(self.store.serialize_cdr(msg, ODOMETRY))

    def point_cloud(self, t_ns: int, lm: LandmarkMap) -> bytes:
        """x, y, z (float32, world frame in FLU) and id (uint32, the landmark id's low 32 bits)."""
        pts = np.zeros(lm.n, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("id", "<u4")])
        xyz = np.asarray(lm.xyz_W_m, float) @ F_FRD_FLU
        pts["x"], pts["y"], pts["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
        pts["id"] = (np.asarray(lm.ids, np.int64) & 0xFFFFFFFF).astype(np.uint32)
        fields = [
            self._pf(name="x", offset=0, datatype=self._pf.FLOAT32, count=1),
            self._pf(name="y", offset=4, datatype=self._pf.FLOAT32, count=1),
            self._pf(name="z", offset=8, datatype=self._pf.FLOAT32, count=1),
            self._pf(name="id", offset=12, datatype=self._pf.UINT32, count=1),
        ]
        msg = self.store.types[POINT_CLOUD2](
            header=self._header(t_ns, self.world_frame),
            height=1,
            width=lm.n,
            fields=fields,
            is_bigendian=False,
            point_step=pts.itemsize,
            row_step=pts.itemsize * lm.n,
            data=np.frombuffer(pts.tobytes(), dtype=np.uint8),
            is_dense=True,
        )
        return bytes(self.store.serialize_cdr(msg, POINT_CLOUD2))

    def diagnostics(self, health: Mapping[str, Any]) -> bytes:
        """One DiagnosticStatus named ``robotd/<id>``: the level from the health state, every field
        of the health document as a key/value (nested keys dotted)."""
        t = self.store.types
        level, message = health_level(health)
        KeyValue = t["diagnostic_msgs/msg/KeyValue"]
        status = t["diagnostic_msgs/msg/DiagnosticStatus"](
            level=level,
            name=f"robotd/{self.robot_id}",
            message=message,
            hardware_id=self.robot_id,
            values=[KeyValue(key=k, value=v) for k, v in _flatten(health)],
        )
        t_ns = health.get("t_ns")
        stamp_src = int(t_ns) if isinstance(t_ns, int) else time.monotonic_ns()
        msg = t[DIAGNOSTIC_ARRAY](header=self._header(stamp_src, ""), status=[status])
        return bytes(self.store.serialize_cdr(msg, DIAGNOSTIC_ARRAY))
