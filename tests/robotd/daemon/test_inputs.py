"""The input threads hand every sample to the recorder before SLAM's queue can drop it (issue 27,
item 1): a recording is the sensor log, whatever SLAM keeps up with.

No wall clock is asserted: SLAM is made slow by a step that waits until the camera has delivered
its last frame (sim:// not in real time, a fixed number of frames), so SLAM's queue must drop
nearly all of them, and the recording must still hold every one.
"""

from __future__ import annotations

import itertools
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from robotd.config import load_config
from robotd.core.msgs import StereoFrame
from robotd.daemon import Daemon
from robotd.daemon.health import DaemonStats
from robotd.daemon.inputs import pump_frames, pump_odometry
from robotd.formats.queues import DropOldestQueue
from robotd.formats.record import SessionReader
from robotd.pipeline.step import Pipeline
from robotd.tools.replay import replay
from tests.support.mcap_decode import decode_all

FPS, SECONDS = 20, 3
N_FRAMES = FPS * SECONDS


def _config(tmp_path: Path) -> Any:
    return load_config(
        None,
        {
            "camera": {"url": f"sim://?fps={FPS}&realtime=0&duration={SECONDS}&width=160&height=100"},
            "vehicle": {"url": f"sim://?fps={FPS}&realtime=0&duration={SECONDS}"},
            "zenoh": {"enabled": False},
            "persistence": {"state_dir": str(tmp_path / "state"), "save_period_s": 0.0},
        },
    )


def test_a_recording_holds_every_frame_the_camera_delivered_while_slam_falls_behind(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "s.mcap"
    d = Daemon(_config(tmp_path), duration_s=0.0, environ={}, record_path=str(out))
    step = Pipeline.step
    first = threading.Event()

    def slow_step(self: Pipeline, frame: StereoFrame, inc: Any) -> Any:
        if not first.is_set():
            first.set()
            # SLAM is busy until the camera has delivered everything: its queue keeps the newest 2
            give_up = time.monotonic() + 120.0  # a safety net only, never reached
            while not d.frame_q.closed and time.monotonic() < give_up:
                time.sleep(0.01)
        return step(self, frame, inc)

    monkeypatch.setattr(Pipeline, "step", slow_step)
    assert d.run() == 0 and d.stop_reason == "source ended"

    assert d.stats.frames_in == N_FRAMES  # the camera delivered every frame of its 3 s
    assert d.stats.steps <= 4 and d.frame_q.dropped >= N_FRAMES - 4  # SLAM saw almost none of them
    # every frame, in the order and with the stamps the camera gave them
    frames = list(SessionReader(out).frames())
    assert [f.seq for f in frames] == list(range(N_FRAMES))
    s = d.record_summary()
    assert s["frames"] == s["frames_delivered"] == N_FRAMES and s["frames_lost"] == 0
    assert s["odometry"] == s["odometry_delivered"] == d.stats.odometry_in > 0 and s["odometry_lost"] == 0
    assert s["poses"] == d.stats.published  # SLAM's outputs beside the sensor log
    assert all(b.t_ns - a.t_ns == 1_000_000_000 // FPS for a, b in itertools.pairwise(frames))
    assert len(list(SessionReader(out).odometry())) == d.stats.odometry_in
    # another tool reads it whole, CRCs checked
    msgs = decode_all(out)
    assert len(msgs["/camera/left/image"]) == len(msgs["/camera/right/image"]) == N_FRAMES
    assert len(msgs["/robotd/pose"]) == d.stats.published
    # and a replay runs SLAM on every recorded frame
    summary = replay(_config(tmp_path), str(out), progress=False)
    assert summary["frames"] == N_FRAMES


class _Camera:
    """A camera that delivers ``n`` frames as fast as they are pulled."""

    url = "test://"

    def __init__(self, n: int) -> None:
        self.n = n

    def frames(self, timeout_s: float = 1.0) -> Any:
        import numpy as np

        img = np.zeros((4, 6), np.uint8)
        for k in range(self.n):
            yield StereoFrame(1_000 + k, k, img, img, True)


class _Vehicle:
    url = "test://"

    def odometry(self, timeout_s: float = 1.0) -> Any:
        import numpy as np

        from robotd.core.msgs import Odometry

        for k in range(50):
            yield Odometry(k, np.zeros(3), np.zeros(3))


def test_the_tees_get_every_sample_in_order_before_the_queue_drops_any() -> None:
    q: DropOldestQueue[StereoFrame] = DropOldestQueue(2)
    teed: list[int] = []
    stats = DaemonStats()
    pump_frames(_Camera(30), q, threading.Event(), stats, lambda *a: None, False, tees=[lambda f: teed.append(f.seq)])  # type: ignore[arg-type]
    assert teed == list(range(30)) and stats.frames_in == 30
    assert q.dropped == 28  # nobody read the queue: SLAM would have seen 2
    odo_q: DropOldestQueue[Any] = DropOldestQueue(4)
    got: list[int] = []
    pump_odometry(_Vehicle(), odo_q, threading.Event(), stats, [lambda o: got.append(o.t_ns)])  # type: ignore[arg-type]
    assert got == list(range(50)) and stats.odometry_in == 50 and odo_q.dropped == 46
