"""ROS 2 payloads on Zenoh: a real loopback session receives them, rosbags decodes them, and they
say what the JSON pose published at the same step says, in ROS's frames."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest
import zenoh
from rosbags.typesys import Stores, get_typestore

from robotd.config import ZenohConfig
from robotd.core.msgs import LandmarkMap, PoseEstimate, StepResult, UpdateReport
from robotd.outputs.base import StepReport
from robotd.outputs.ros2 import pose_to_ros
from robotd.outputs.zenoh import ZenohOutput
from tests.support.net import free_port, zenoh_client
from tests.support.tolerances import ROUNDOFF_ATOL

STORE = get_typestore(Stores.ROS2_JAZZY)  # decode with another release's definitions than robotd encodes with
RECEIVE_TIMEOUT_S = 10.0
# the wall-minus-monotonic offset is read when the message is built, between the test's two reads;
# an NTP slew moves it by microseconds at most over that interval
OFFSET_SLACK_NS = 5_000_000
FLIP = np.diag([1.0, -1.0, -1.0])


class Inbox:
    """Every sample under robotd/r1/**, by the key's last chunk; copied out of the Zenoh thread."""

    def __init__(self) -> None:
        self.samples: dict[str, list[tuple[bytes, str]]] = {}
        self.cond = threading.Condition()

    def __call__(self, sample: zenoh.Sample) -> None:
        with self.cond:
            name = str(sample.key_expr).rsplit("/", 1)[-1]
            self.samples.setdefault(name, []).append((sample.payload.to_bytes(), str(sample.encoding)))
            self.cond.notify_all()

    def wait(self, names: set[str]) -> None:
        with self.cond:
            ok = self.cond.wait_for(lambda: names <= set(self.samples), timeout=RECEIVE_TIMEOUT_S)
        assert ok, f"received {sorted(self.samples)}, waiting for {sorted(names)}"


@pytest.fixture
def link(request: pytest.FixtureRequest) -> Iterator[tuple[ZenohOutput, Inbox]]:
    port = free_port()
    cfg = ZenohConfig(listen=[f"tcp/127.0.0.1:{port}"], **getattr(request, "param", {"ros2": True}))
    out = ZenohOutput(cfg, "r1")
    inbox = Inbox()
    with zenoh.open(zenoh_client(port)) as s:
        sub = s.declare_subscriber("robotd/r1/**", inbox)
        # a put before the subscription reached the publishing session would be lost
        t_end = time.monotonic() + RECEIVE_TIMEOUT_S
        while not out._pose.matching_status.matching and time.monotonic() < t_end:
            time.sleep(0.02)
        assert out._pose.matching_status.matching, "the subscription never reached robotd's session"
        try:
            yield out, inbox
        finally:
            sub.undeclare()
            out.close()


def _pose(rng: np.random.Generator) -> PoseEstimate:
    A = rng.normal(size=(6, 6))
    return PoseEstimate(
        t_ns=123_456_789_012,
        xyz_W_m=np.array([1.5, -0.7, -0.2]),
        rpy_rad=np.array([0.05, -0.1, 0.8]),
        cov=A @ A.T * 1e-3,  # full, with every cross term
        neff=42.0,
        n_particles=100,
    )


def _report(pose: PoseEstimate, landmarks: LandmarkMap | None) -> StepReport:
    return StepReport(
        result=StepResult(t_ns=pose.t_ns, pose=pose, report=UpdateReport()),
        seq=7,
        frame_seq=7,
        quality=80,
        reset_counter=0,
        latency_ms=12.5,
        health="tracking",
        landmarks=landmarks,
    )


def _R_from_wxyz(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def test_odometry_matches_the_json_pose_of_the_same_step(link, rng: np.random.Generator) -> None:
    out, inbox = link
    pose = _pose(rng)
    before = time.time_ns() - time.monotonic_ns()
    out.publish(_report(pose, None))
    after = time.time_ns() - time.monotonic_ns()
    inbox.wait({"pose", "odom"})
    doc = json.loads(inbox.samples["pose"][0][0])
    payload, encoding = inbox.samples["odom"][0]
    assert encoding == "application/cdr;nav_msgs/msg/Odometry"
    assert payload[:4] == b"\x00\x01\x00\x00"  # CDR little-endian encapsulation, as DDS sends it
    odom = STORE.deserialize_cdr(payload, "nav_msgs/msg/Odometry")
    assert (odom.header.frame_id, odom.child_frame_id) == ("map", "base_link")
    stamp = odom.header.stamp.sec * 1_000_000_000 + odom.header.stamp.nanosec
    assert before - OFFSET_SLACK_NS <= stamp - doc["t_ns"] <= after + OFFSET_SLACK_NS
    # position: FRD -> FLU flips y and z
    p = odom.pose.pose.position
    assert [p.x, p.y, p.z] == [doc["xyz_m"][0], -doc["xyz_m"][1], -doc["xyz_m"][2]]
    # orientation: R_ROS = F R F, F = diag(1, -1, -1)
    o = odom.pose.pose.orientation
    R_ros = _R_from_wxyz(np.array([o.w, o.x, o.y, o.z]))
    assert np.allclose(R_ros, FLIP @ _R_from_wxyz(np.array(doc["quat_wxyz"])) @ FLIP, atol=ROUNDOFF_ATOL)
    # covariance: the JSON's cov6 with the y, z, pitch, yaw signs flipped, row-major
    J = np.diag([1.0, -1.0, -1.0, 1.0, -1.0, -1.0])
    cov = np.asarray(odom.pose.covariance).reshape(6, 6)
    assert np.array_equal(cov, J @ np.array(doc["cov6"]) @ J)
    assert cov[0, 1] == -doc["cov6"][0][1] and cov[0, 3] == doc["cov6"][0][3] and cov[1, 2] == doc["cov6"][1][2]
    assert odom.twist.covariance[0] == -1.0  # no twist estimate


@pytest.mark.parametrize("link", [{"ros2": True, "ros2_stamp": "monotonic", "ros2_world_frame": "odom",
                                   "ros2_body_frame": "rig"}], indirect=True)  # fmt: skip
def test_landmarks_and_diagnostics(link, rng: np.random.Generator) -> None:
    out, inbox = link
    lm = LandmarkMap(
        ids=np.array([3, 17, 2**33 + 5], np.int64),
        xyz_W_m=np.array([[4.0, 1.0, -2.0], [6.5, -2.25, 0.5], [10.0, 0.0, 0.0]]),
        cov_W=np.tile(np.eye(3) * 0.01, (3, 1, 1)),
    )
    pose = _pose(rng)
    out.publish(_report(pose, lm))
    health = {"t_ns": 5_000_000_123, "ready": True, "tracking": True, "quality": 80, "budget": {"level": 2},
              "latency_ms": {"p50": 13.0, "p99": None}, "camera": {"frames": 10}}  # fmt: skip
    out.publish_health(health)
    inbox.wait({"odom", "landmarks", "diagnostics", "map"})
    odom = STORE.deserialize_cdr(inbox.samples["odom"][0][0], "nav_msgs/msg/Odometry")
    assert (odom.header.frame_id, odom.child_frame_id) == ("odom", "rig")
    assert (odom.header.stamp.sec, odom.header.stamp.nanosec) == (123, 456_789_012)  # monotonic kept

    cloud = STORE.deserialize_cdr(inbox.samples["landmarks"][0][0], "sensor_msgs/msg/PointCloud2")
    assert cloud.header.frame_id == "odom" and (cloud.height, cloud.width) == (1, 3)
    FLOAT32, UINT32 = 7, 6  # sensor_msgs/PointField
    layout = [(f.name, f.offset, f.datatype, f.count) for f in cloud.fields]
    assert layout == [("x", 0, FLOAT32, 1), ("y", 4, FLOAT32, 1), ("z", 8, FLOAT32, 1), ("id", 12, UINT32, 1)]
    pts = np.frombuffer(bytes(cloud.data), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("id", "<u4")])
    assert cloud.point_step == 16 and cloud.row_step == 48 and not cloud.is_bigendian
    xyz = np.column_stack([pts["x"], pts["y"], pts["z"]])
    assert np.array_equal(xyz, (lm.xyz_W_m @ FLIP).astype(np.float32))
    assert pts["id"].tolist() == [3, 17, 5]  # low 32 bits

    diag = STORE.deserialize_cdr(inbox.samples["diagnostics"][0][0], "diagnostic_msgs/msg/DiagnosticArray")
    (status,) = diag.status
    assert (diag.header.stamp.sec, diag.header.stamp.nanosec) == (5, 123)
    assert status.name == "robotd/r1" and status.hardware_id == "r1"
    assert status.level == 1 and "budget level 2" in status.message  # WARN while degraded
    values = {kv.key: kv.value for kv in status.values}
    assert values["budget.level"] == "2" and values["latency_ms.p99"] == "null" and values["camera.frames"] == "10"
    assert values["tracking"] == "true"


@pytest.mark.parametrize("link", [{"ros2": False}], indirect=True)
def test_off_by_default_nothing_but_json(link, rng: np.random.Generator) -> None:
    assert ZenohConfig().ros2 is False
    out, inbox = link
    out.publish(_report(_pose(rng), None))
    inbox.wait({"pose"})
    time.sleep(0.3)
    assert set(inbox.samples) == {"pose"}


def test_frame_conversion_by_hand() -> None:
    """Facing right (yaw +90° in FRD) one metre to the right and 2 m below the start is, in ROS's
    FLU world, yaw -90°, y = -1 and z = -2; the x-y covariance term changes sign, x-x does not."""
    cov = np.eye(6)
    cov[0, 1] = cov[1, 0] = 0.3
    pose = PoseEstimate(1, np.array([0.0, 1.0, 2.0]), np.array([0.0, 0.0, np.pi / 2]), cov)
    p, (x, y, z, w), c = pose_to_ros(pose)
    assert np.allclose(p, [0.0, -1.0, -2.0])
    q = np.array([x, y, z, w]) * np.sign(w)  # q and -q are the same rotation
    assert np.allclose(q, [0.0, 0.0, -np.sin(np.pi / 4), np.cos(np.pi / 4)], atol=ROUNDOFF_ATOL)
    assert c[0, 1] == -0.3 and c[0, 0] == 1.0
