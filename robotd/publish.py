"""Zenoh key space, encodings, the map queryable and the liveliness token (docs/topics.md).

Keys under ``robotd/<robot_id>/``:

- ``pose``    JSON, every processed frame (PoseEstimate + quality, reset_counter, latency)
- ``map``     CBOR (robotd.codec, schema robotd.map/1), published periodically; also a queryable
              that answers with the full current map
- ``health``  JSON at 1 Hz: stage latencies p50/p99, drops, deadline misses, N_eff, counts, budget
- ``alive``   liveliness token (PUT while the daemon runs, DELETE when it stops or dies)

The session is loopback-only by default (listen on 127.0.0.1, multicast scouting off); a JSON5
file (config/zenoh.json5) can switch to router/client mode, other endpoints or TLS. Puts never
block the SLAM loop (congestion control DROP); the queryable replies from an immutable snapshot.
"""

from __future__ import annotations

import json
import logging
import sys
import threading
import time
from typing import Any

import numpy as np
import zenoh

from robotd.codec import decode_map, encode_map
from robotd.config import ZenohConfig
from robotd.errors import DriverError
from robotd.geometry import euler_to_quat
from robotd.msgs import LandmarkMap, PoseEstimate

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


def pose_to_json(
    pose: PoseEstimate, robot_id: str, seq: int, quality: int, reset_counter: int, latency_ms: float
) -> dict[str, Any]:
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


class Publisher:
    """Owns the Zenoh session and every declared entity; closes them all on ``close()``."""

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
            raise DriverError(f"zenoh: cannot open session ({exc})") from exc
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
        self._queryable = s.declare_queryable(f"{self.prefix}/map", self._on_map_query, complete=True)
        self._token = s.liveliness().declare_token(f"{self.prefix}/alive")
        self._closed = False
        logger.info("zenoh session %s publishing under %s/ (mode %s)", s.info.zid(), self.prefix, cfg.mode)

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

    def publish_health(self, doc: dict[str, Any]) -> None:
        self._put(self._health, json.dumps({"schema": HEALTH_SCHEMA, "robot": self.robot_id, **doc}), "health")

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
        for ent in (self._token, self._queryable, self._pose, self._map, self._health):
            try:
                ent.undeclare()
            except Exception as exc:
                logger.debug("undeclare: %s", exc)
        self.session.close()

    def __enter__(self) -> Publisher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# --------------------------------------------------------------------------------------------
# robotd echo


def _client_config(connect: list[str]) -> zenoh.Config:
    conf = zenoh.Config()
    if connect:
        conf.insert_json5("mode", '"client"' if len(connect) == 1 else '"peer"')
        conf.insert_json5("connect/endpoints", json.dumps(connect))
        conf.insert_json5("listen/endpoints", "[]")
    else:
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("listen/endpoints", json.dumps(["tcp/127.0.0.1:0"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return conf


def format_sample(key: str, payload: bytes) -> str:
    """A printable line for a published sample (CBOR maps summarised, JSON as is)."""
    if key.endswith("/map"):
        try:
            meta, lm = decode_map(payload)
            return json.dumps({"key": key, **{k: v for k, v in meta.items()}, "first_ids": lm.ids[:5].tolist()})
        except Exception as exc:
            return json.dumps({"key": key, "error": str(exc), "bytes": len(payload)})
    try:
        return json.dumps({"key": key, "value": json.loads(payload)})
    except ValueError:
        return json.dumps({"key": key, "bytes": len(payload)})


def echo(key: str, connect: list[str], count: int = 0, timeout_s: float = 0.0) -> int:
    """Print samples on ``key`` (one JSON line each). ``robotd/*/map`` queries the map once."""
    done = threading.Event()
    n = 0
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        nonlocal n
        with lock:
            if done.is_set():
                return
            print(format_sample(str(sample.key_expr), sample.payload.to_bytes()), flush=True)
            n += 1
            if count and n >= count:
                done.set()

    with zenoh.open(_client_config(connect or ["tcp/127.0.0.1:7447"])) as session:
        if key.endswith("/map") and "*" not in key:
            for reply in session.get(key, timeout=timeout_s or 5.0):
                if reply.ok is not None:
                    print(format_sample(str(reply.ok.key_expr), reply.ok.payload.to_bytes()), flush=True)
                    n += 1
            return 0 if n else 1
        sub = session.declare_subscriber(key, on_sample)
        t_end = time.monotonic() + timeout_s if timeout_s else float("inf")
        try:
            while not done.is_set() and time.monotonic() < t_end:
                done.wait(0.1)
        except KeyboardInterrupt:
            pass
        finally:
            done.set()
            sub.undeclare()
    sys.stdout.flush()
    return 0 if n or not count else 1
