"""The live view: the Foxglove SDK's WebSocket server, on loopback, advertising the recording's
channels; a plain WebSocket client (``websockets``, offering Foxglove's ``foxglove.sdk.v1`` or the
older ``foxglove.websocket.v1`` subprotocol) subscribes and decodes what arrives with the schemas
the server advertised."""

from __future__ import annotations

import base64
import json
import socket
import struct
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

pytest.importorskip("foxglove", reason="the live view needs foxglove-sdk (robotd[live])")
from websockets.sync.client import ClientConnection, connect

from robotd.config import Config, LiveViewConfig
from robotd.core.errors import DriverError
from robotd.core.msgs import LandmarkMap, Observations, Odometry, PoseEstimate, StepResult, StereoFrame, UpdateReport
from robotd.core.stereo import RectifiedStereo
from robotd.formats.record import CHANNELS
from robotd.outputs import OutputContext, build_outputs
from robotd.outputs.base import StepReport
from robotd.outputs.liveview import LiveViewOutput
from tests.support.net import free_port
from tests.support.paths import REPO

RIG = RectifiedStereo(60.0, 32.0, 20.0, 0.075, 64, 40)
SUBPROTOCOL = "foxglove.sdk.v1"
# what older Foxglove Studio, Lichtblick (before it added the new name) and ws-protocol clients offer
LEGACY_SUBPROTOCOL = "foxglove.websocket.v1"


@pytest.fixture
def live() -> Iterator[LiveViewOutput]:
    out = LiveViewOutput(LiveViewConfig(enabled=True, port=free_port()), RIG, "r1")
    try:
        yield out
    finally:
        out.close()


def _advertised(ws: ClientConnection) -> dict[str, dict[str, Any]]:
    """serverInfo, then the advertised channels by topic."""
    info = json.loads(ws.recv(timeout=5))
    assert info["op"] == "serverInfo" and info["name"] == "robotd r1"
    adv = json.loads(ws.recv(timeout=5))
    assert adv["op"] == "advertise"
    return {c["topic"]: c for c in adv["channels"]}


def _message_class(channel: dict[str, Any]) -> Any:
    """The protobuf class of an advertised channel, from the schema the server sent (base64
    FileDescriptorSet), not from robotd's code."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    assert channel["encoding"] == "protobuf" and channel["schemaEncoding"] == "protobuf"
    pool = descriptor_pool.DescriptorPool()
    for fd in descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"])).file:
        pool.Add(fd)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(channel["schemaName"]))


def _step(t_ns: int) -> tuple[StereoFrame, Odometry, StepReport]:
    rng = np.random.default_rng(1)
    left = rng.integers(0, 256, (40, 64), dtype=np.uint8)
    frame = StereoFrame(t_ns, 7, left, np.roll(left, -2, axis=1), True, np.eye(4))
    odo = Odometry(t_ns - 1000, np.array([1.0, 0.0, 0.0]), np.zeros(3), "sim")
    pose = PoseEstimate(t_ns, np.array([1.0, 2.0, 0.5]), np.array([0.0, 0.0, 0.3]), np.eye(6) * 1e-3)
    obs = Observations(t_ns, np.ones((2, 3)), np.stack([np.eye(3)] * 2), np.array([4, 5]), np.array([False, True]),
                       np.array([[30.0, 25.0, 10.0], [40.0, 31.0, 20.0]]))  # fmt: skip
    lm = LandmarkMap(np.array([4, 5], np.int64), np.array([[3.0, 0.0, 0.0], [4.0, 1.0, 0.0]]),
                     np.stack([np.eye(3) * 0.01] * 2))  # fmt: skip
    res = StepResult(t_ns, pose, UpdateReport(), {}, {}, True, False, observations=obs)
    return frame, odo, StepReport(res, 1, 7, 50, 0, 10.0, "tracking", landmarks=lm)


@pytest.mark.parametrize("offered", [SUBPROTOCOL, LEGACY_SUBPROTOCOL])
def test_a_client_sees_the_recordings_channels_and_decodes_what_it_subscribed_to(
    live: LiveViewOutput, offered: str
) -> None:
    """With either subprotocol name (issue 27, item 5: the old one was refused with HTTP 400)."""
    with connect(f"ws://127.0.0.1:{live.port}", subprotocols=[offered], open_timeout=5) as ws:
        assert ws.subprotocol == offered
        channels = _advertised(ws)
        assert set(channels) == {topic for topic, _ in CHANNELS.values()}  # exactly a recording's channels
        assert channels["/camera/left/image"]["schemaName"] == "foxglove.CompressedImage"
        assert channels["/robotd/map"]["schemaName"] == "foxglove.PointCloud"
        assert channels["/tf"]["schemaName"] == "foxglove.FrameTransforms"
        wanted = ["/robotd/pose", "/camera/left/image", "/robotd/map", "/robotd/odometry"]
        subs = {i: channels[topic] for i, topic in enumerate(wanted, start=1)}
        ws.send(json.dumps({"op": "subscribe",
                            "subscriptions": [{"id": i, "channelId": c["id"]} for i, c in subs.items()]}))  # fmt: skip
        time.sleep(0.3)  # the server registers the subscriptions
        t = time.monotonic_ns()
        frame, odo, report = _step(t)
        live.record_inputs(frame, [odo])
        live.publish(report)
        got: dict[str, Any] = {}
        deadline = time.monotonic() + 5.0
        while len(got) < len(wanted) and time.monotonic() < deadline:
            data = ws.recv(timeout=5)
            if isinstance(data, str):
                continue
            op, sub, log_time = struct.unpack_from("<BIQ", data)
            assert op == 1  # message data
            ch = subs[sub]
            got[ch["topic"]] = (log_time, _message_class(ch).FromString(data[13:]))
    assert set(got) == set(wanted)
    pose_t, pose = got["/robotd/pose"]
    assert abs(pose_t / 1e9 - time.time()) < 60  # wall clock
    assert (pose.pose.position.x, pose.pose.position.y) == (1.0, 2.0) and pose.frame_id == "world"
    img = got["/camera/left/image"][1]
    assert np.array_equal(cv2.imdecode(np.frombuffer(img.data, np.uint8), cv2.IMREAD_UNCHANGED), frame.left)
    assert len(got["/robotd/map"][1].data) == 2 * 16
    assert got["/robotd/odometry"][1].linear_velocity.x == 1.0
    # nothing is sent on the channels nobody subscribed to
    assert live.stats()["sent"] == len(wanted)


def test_the_front_passes_what_the_sdk_answers_to_other_offers(live: LiveViewOutput) -> None:
    """Both names at once: the SDK's choice, untouched; neither, or no subprotocol: the SDK's 400."""
    from websockets.exceptions import InvalidStatus

    with connect(f"ws://127.0.0.1:{live.port}", subprotocols=[LEGACY_SUBPROTOCOL, SUBPROTOCOL]) as ws:
        assert ws.subprotocol == SUBPROTOCOL and _advertised(ws)
    for offer in (["foxglove.websocket.v2"], None):
        with pytest.raises(InvalidStatus) as e:
            connect(f"ws://127.0.0.1:{live.port}", subprotocols=offer, open_timeout=5)
        assert e.value.response.status_code == 400
    assert live.stats()["clients"] == {"connections": 3, "renamed": 0, "refused": 2}


def test_rewriting_touches_only_the_subprotocol_header() -> None:
    from robotd.outputs.liveview_front import rewrite_request, rewrite_response

    req = (b"GET / HTTP/1.1\r\nHost: h\r\nsec-websocket-protocol: foxglove.websocket.v1\r\n"
           b"Sec-WebSocket-Key: k==\r\n\r\n")  # fmt: skip
    out, renamed = rewrite_request(req)
    assert renamed and out == req.replace(b"sec-websocket-protocol: foxglove.websocket.v1",
                                          b"Sec-WebSocket-Protocol: foxglove.sdk.v1")  # fmt: skip
    both = req.replace(b"foxglove.websocket.v1", b"foxglove.websocket.v1, foxglove.sdk.v1")
    assert rewrite_request(both) == (both, False)
    resp = b"HTTP/1.1 101 Switching Protocols\r\nSec-WebSocket-Protocol: foxglove.sdk.v1\r\nX: y\r\n\r\n"
    assert rewrite_response(resp) == resp.replace(b"foxglove.sdk.v1", b"foxglove.websocket.v1")


def test_off_by_default_on_loopback_when_on_and_a_taken_port_is_one_line() -> None:
    assert Config().liveview.enabled is False and Config().liveview.host == "127.0.0.1"
    from contextlib import ExitStack

    with ExitStack() as stack:
        outs = build_outputs(OutputContext(Config(), RIG), stack)
        assert not any(o.name == "liveview" for o in outs)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        with pytest.raises(DriverError) as e:
            LiveViewOutput(LiveViewConfig(enabled=True, port=port), RIG, "r1")
    msg = str(e.value)
    assert msg.startswith(f"liveview.port: cannot listen on 127.0.0.1:{port}") and "\n" not in msg


@pytest.mark.slow
def test_robotd_run_serves_the_live_view(tmp_path: Path) -> None:
    port = free_port()
    cfg = tmp_path / "c.toml"
    cfg.write_text(
        '[camera]\nurl = "sim://?fps=10&width=320&height=200"\n[vehicle]\nurl = "sim://?fps=10&width=320&height=200"\n'
        f"[zenoh]\nenabled = false\n[liveview]\nenabled = true\nport = {port}\n"
        f'[persistence]\nstate_dir = "{tmp_path / "state"}"\n'
    )
    proc = subprocess.Popen([sys.executable, "-m", "robotd", "run", "--config", str(cfg), "--duration", "60"],
                            cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)  # fmt: skip
    try:
        deadline = time.monotonic() + 60.0
        ws = None
        while ws is None and time.monotonic() < deadline:
            assert proc.poll() is None, proc.communicate()[1][-2000:]
            try:
                ws = connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL], open_timeout=2)
            except OSError:
                time.sleep(0.5)
        assert ws is not None, "the live view never listened"
        with ws:
            channels = _advertised(ws)
            pose = channels["/robotd/pose"]
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 1, "channelId": pose["id"]}]}))
            n = 0
            while n < 3:
                data = ws.recv(timeout=30)
                if isinstance(data, bytes):
                    n += 1
            msg = _message_class(pose).FromString(data[13:])
            assert msg.frame_id == "world"
    finally:
        proc.terminate()
        proc.wait(timeout=30)


def test_the_shipped_foxglove_layout_names_only_channels_robotd_sends() -> None:
    import re

    layout = json.loads((REPO / "docs" / "foxglove-layout.json").read_text())
    text = json.dumps(layout["configById"])
    named = set(re.findall(r'"(/[a-z_]+/[a-z_]+(?:/[a-z_]+)?)', text))
    topics = {topic for topic, _ in CHANNELS.values()}
    assert named and named <= topics, named - topics
    panels = set(layout["configById"])

    def leaves(node: Any) -> set[str]:
        return {node} if isinstance(node, str) else leaves(node["first"]) | leaves(node["second"])

    assert leaves(layout["layout"]) == panels
