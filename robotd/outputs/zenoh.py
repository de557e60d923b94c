"""The Zenoh output: key space, encodings, the map queryable and the liveliness token (docs/topics.md).

Keys under ``robotd/<robot_id>/``:

- ``pose``    JSON, every processed frame (PoseEstimate + quality, reset_counter, latency)
- ``map``     CBOR (robotd.formats.codec, schema robotd.map/1), published periodically; also a queryable
              that answers with the full current map
- ``health``  JSON at 1 Hz: stage latencies p50/p99, drops, deadline misses, N_eff, counts, budget
- ``alive``   liveliness token (PUT while the daemon runs, DELETE when it stops or dies)

With ``ros2 = true`` also ``odom``, ``landmarks`` and ``diagnostics``: the pose, the map and the
health as ROS 2 messages in CDR, for zenoh-bridge-ros2dds (robotd.outputs.ros2).

The session is loopback-only by default (listen on 127.0.0.1, multicast scouting off); a JSON5
file (config/zenoh.json5) can switch to router/client mode, other endpoints or TLS. Puts never
block the SLAM loop (congestion control DROP); the queryable replies from an immutable snapshot.
"""

from __future__ import annotations

import json
import logging
import re
import threading
from collections.abc import Mapping
from typing import Any

import numpy as np
import zenoh

from robotd.config import ZenohConfig
from robotd.core.errors import DriverError
from robotd.core.geometry import euler_to_quat
from robotd.core.msgs import LandmarkMap, PoseEstimate
from robotd.formats.codec import encode_map
from robotd.outputs.base import Output, StepReport

logger = logging.getLogger(__name__)

POSE_SCHEMA = "robotd.pose/1"
HEALTH_SCHEMA = "robotd.health/1"


def make_zenoh_config(cfg: ZenohConfig) -> zenoh.Config:
    """The session config: from cfg.config_file when set, else loopback-only from the fields."""
    if cfg.config_file:
        try:
            return zenoh.Config.from_file(cfg.config_file)
        except Exception as exc:  # zenoh raises ZError with the parser's message
            raise DriverError(f"zenoh config {cfg.config_file}: {exc}") from exc
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(cfg.mode))
    if cfg.mode != "client":
        conf.insert_json5("listen/endpoints", json.dumps(cfg.listen))
    conf.insert_json5("connect/endpoints", json.dumps(cfg.connect))
    conf.insert_json5("scouting/multicast/enabled", "true" if cfg.multicast_scouting else "false")
    conf.insert_json5("scouting/gossip/enabled", "false" if not cfg.connect else "true")
    return conf


def session_error(cfg: ZenohConfig, exc: Exception) -> str:
    """One line for a session that would not open: which key to change, without zenoh's Rust
    source locations. The usual case is a second robotd on the host holding the listen port."""
    text = re.sub(r"\s+at /\S+\.rs:\d+\.?", "", str(exc)).strip().rstrip("]")
    busy = re.search(r"bound to (\S+?):? \[?.*Address already in use", text)
    if busy is not None:
        endpoint = busy.group(1)
        return (
            f"zenoh.listen: {endpoint} is already in use (another robotd on this host?); give this one "
            f'another port in its config, e.g. [zenoh] listen = ["tcp/127.0.0.1:7448"], or set '
            f"[zenoh] enabled = false"
        )
    where = f"zenoh.config_file {cfg.config_file}" if cfg.config_file else "zenoh.listen/zenoh.connect"
    return f"zenoh: cannot open the session ({where}): {text}"


def _zero() -> int:
    return 0


def pose_payload(
    pose: PoseEstimate, robot_id: str, seq: int, quality: int, reset_counter: int, latency_ms: float
) -> dict[str, Any]:
    """The ``robotd/<id>/pose`` message (schema robotd.pose/1, docs/topics.md)."""
    q = euler_to_quat(pose.rpy_rad)
    return {
        "schema": POSE_SCHEMA,
        "robot": robot_id,
        "seq": seq,
        "t_ns": int(pose.t_ns),
        "frame": "LOCAL_FRD",
        "child_frame": "BODY_FRD",
        "xyz_m": [float(v) for v in pose.xyz_W_m],
        "rpy_rad": [float(v) for v in pose.rpy_rad],
        "quat_wxyz": [float(v) for v in q],
        "cov6": [[float(v) for v in row] for row in pose.cov],
        "neff": None if not np.isfinite(pose.neff) else float(pose.neff),
        "n_particles": int(pose.n_particles),
        "quality": int(quality),
        "reset_counter": int(reset_counter),
        "latency_ms": float(latency_ms),
    }


class ZenohOutput(Output):
    """Owns the Zenoh session and every declared entity; closes them all on ``close()``."""

    name = "zenoh"

    def __init__(self, cfg: ZenohConfig, robot_id: str) -> None:
        self.cfg = cfg
        self.robot_id = robot_id
        self.prefix = f"robotd/{robot_id}"
        self._lock = threading.Lock()
        self._map_blob: bytes = encode_map(
            robot_id, 0, LandmarkMap(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3, 3)))
        )
        self._map_seq = 0
        self.counts = {"pose": 0, "map": 0, "health": 0, "map_queries": 0, "errors": 0}
        try:
            self.session = zenoh.open(make_zenoh_config(cfg))
        except Exception as exc:
            raise DriverError(session_error(cfg, exc)) from exc
        s = self.session
        self._pose = s.declare_publisher(
            f"{self.prefix}/pose",
            encoding=zenoh.Encoding.APPLICATION_JSON,
            congestion_control=zenoh.CongestionControl.DROP,
            priority=zenoh.Priority.DATA_HIGH,
            express=True,
        )
        self._map = s.declare_publisher(
            f"{self.prefix}/map",
            encoding=zenoh.Encoding.APPLICATION_CBOR,
            congestion_control=zenoh.CongestionControl.DROP,
        )
        self._health = s.declare_publisher(
            f"{self.prefix}/health",
            encoding=zenoh.Encoding.APPLICATION_JSON,
            congestion_control=zenoh.CongestionControl.DROP,
        )
        self._ros: Any = None
        self._ros_pubs: dict[str, Any] = {}
        if cfg.ros2:
            from robotd.outputs.ros2 import TOPICS, Ros2Encoder, wall_offset_ns

            offset = wall_offset_ns if cfg.ros2_stamp == "wall" else _zero
            self._ros = Ros2Encoder(robot_id, cfg.ros2_world_frame, cfg.ros2_body_frame, offset)
            for name, rostype in TOPICS.items():
                self._ros_pubs[name] = s.declare_publisher(
                    f"{self.prefix}/{name}",
                    encoding=zenoh.Encoding.APPLICATION_CDR.with_schema(rostype),
                    congestion_control=zenoh.CongestionControl.DROP,
                )
                self.counts[name] = 0
        self._queryable = s.declare_queryable(f"{self.prefix}/map", self._on_map_query, complete=True)
        self._token = s.liveliness().declare_token(f"{self.prefix}/alive")
        self._closed = False
        self.map_period_s = cfg.map_period_s
        self.health_period_s = cfg.health_period_s
        logger.info("zenoh session %s publishing under %s/ (mode %s)", s.info.zid(), self.prefix, cfg.mode)

    # ------------------------------------------------------------------ the Output hooks
    def publish(self, report: StepReport) -> None:
        """The pose on every step; the map when the report carries a snapshot."""
        res = report.result
        self.publish_pose(
            pose_payload(res.pose, self.robot_id, report.seq, report.quality, report.reset_counter, report.latency_ms)
        )
        if self._ros is not None:
            self._put(self._ros_pubs["odom"], self._ros.odometry(res.pose), "odom")
        if report.landmarks is not None:
            self.update_map(res.t_ns, report.landmarks)

    def stats(self) -> dict[str, Any]:
        return dict(self.counts)

    # runs on a Zenoh thread: reply from the immutable snapshot, never block
    def _on_map_query(self, query: zenoh.Query) -> None:
        with self._lock:
            blob = self._map_blob
        try:
            query.reply(f"{self.prefix}/map", blob, encoding=zenoh.Encoding.APPLICATION_CBOR)
            self.counts["map_queries"] += 1
        except Exception as exc:
            self.counts["errors"] += 1
            logger.warning("map query reply failed: %s", exc)

    def locators(self) -> list[str]:
        """Where this session listens (for `robotd echo --connect`)."""
        try:
            return [str(x) for x in self.session.info.locators()]  # type: ignore[attr-defined]
        except Exception:
            return []

    def publish_pose(self, doc: dict[str, Any]) -> None:
        self._put(self._pose, json.dumps(doc), "pose")

    def update_map(self, t_ns: int, lm: LandmarkMap, publish: bool = True) -> None:
        self._map_seq += 1
        blob = encode_map(self.robot_id, t_ns, lm, self._map_seq)
        with self._lock:
            self._map_blob = blob
        if publish:
            self._put(self._map, blob, "map")
            if self._ros is not None:
                self._put(self._ros_pubs["landmarks"], self._ros.point_cloud(t_ns, lm), "landmarks")

    def publish_health(self, doc: Mapping[str, Any]) -> None:
        self._put(self._health, json.dumps({"schema": HEALTH_SCHEMA, "robot": self.robot_id, **doc}), "health")
        if self._ros is not None:
            self._put(self._ros_pubs["diagnostics"], self._ros.diagnostics(doc), "diagnostics")

    def _put(self, pub: Any, payload: Any, name: str) -> None:
        try:
            pub.put(payload)
            self.counts[name] += 1
        except Exception as exc:
            self.counts["errors"] += 1
            logger.warning("zenoh put on %s/%s failed: %s", self.prefix, name, exc)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for ent in (self._token, self._queryable, self._pose, self._map, self._health, *self._ros_pubs.values()):
            try:
                ent.undeclare()
            except Exception as exc:
                logger.debug("undeclare: %s", exc)
        self.session.close()
