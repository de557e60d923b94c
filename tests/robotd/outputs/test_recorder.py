"""The recording output: under a crash, a ``robotd record`` killed with SIGKILL (no handler, no
close, no summary) leaves ``OUT.mcap.tmp`` that replays up to its last whole chunk, and the next
``robotd record`` to the same path keeps it instead of overwriting it. A writer that falls behind
loses samples, counted per stream, and never blocks the threads that hand them over; one that
fails stops the recording with its reason. A ``robotd record`` leaves every state directory as it
found it (issue 27, items 1 and 2)."""

from __future__ import annotations

import errno
import io
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from robotd.core.msgs import Odometry, PoseEstimate, StepResult, StereoFrame, UpdateReport
from robotd.core.stereo import RectifiedStereo
from robotd.daemon.health import HealthMonitor
from robotd.formats.record import SessionReader, SessionWriter
from robotd.outputs.base import StepReport
from robotd.outputs.recorder import RecorderOutput, SampleQueue, summary_line
from robotd.tools.cli import main
from tests.support.mcap_decode import decode_all
from tests.support.paths import REPO

FLUSHES_BEFORE_KILL = 3  # seconds of recording (one chunk a second) before the kill


def _config(tmp: Path) -> Path:
    cfg = tmp / "c.toml"
    cfg.write_text(
        '[camera]\nurl = "sim://?fps=10&seed=3"\n[vehicle]\nurl = "sim://?fps=10&seed=3"\n'
        f'[zenoh]\nenabled = false\n[persistence]\nstate_dir = "{tmp / "state"}"\nsave_period_s = 0.0\n'
    )
    return cfg


@pytest.mark.slow
def test_a_sigkilled_record_leaves_a_replayable_recording(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg, out = _config(tmp_path), tmp_path / "s.mcap"
    tmp = out.with_name("s.mcap.tmp")
    proc = subprocess.Popen(
        [sys.executable, "-m", "robotd", "record", str(out), "--config", str(cfg), "--duration", "120"],
        cwd=REPO,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        # wait for the recording to start (the kernels load first), then for a few chunks
        deadline = time.monotonic() + 90.0
        while not (tmp.exists() and tmp.stat().st_size > 100_000) and time.monotonic() < deadline:
            assert proc.poll() is None, proc.communicate()[1]
            time.sleep(0.2)
        assert tmp.exists(), "the recording never started"
        time.sleep(FLUSHES_BEFORE_KILL)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == -signal.SIGKILL
    assert not out.exists() and tmp.stat().st_size > 0
    size = tmp.stat().st_size

    # the reader gets every frame of the whole chunks and says the file was not closed
    r = SessionReader(tmp)
    frames = list(r.frames())
    assert len(frames) >= 2 * FLUSHES_BEFORE_KILL, len(frames)  # 10 fps: ≥ 2 s of frames survive
    assert not r.finished and r.stopped is not None and f"of {size}" in r.stopped

    # robotd replay takes the .tmp as it is, and says where it stopped
    traj = tmp_path / "t.txt"
    assert main(["replay", str(tmp), "--out", str(traj), "--json", "--quiet", "--log-level", "WARNING"]) == 0
    cap = capsys.readouterr()
    s = json.loads(cap.out.strip().splitlines()[-1])
    assert s["frames"] == len(frames) and s["recording"]["finished"] is False
    assert "recording not closed cleanly (interrupted), read up to the damage: stopped at byte" in cap.err
    # asking for the file that was never finished names the .tmp
    assert main(["replay", str(out), "--quiet"]) == 2
    assert f"robotd replay {tmp}" in capsys.readouterr().err

    # the next recording to the same path keeps the interrupted one
    assert main(["record", str(out), "--config", str(cfg), "--duration", "1", "--log-level", "WARNING"]) == 0
    kept = list(tmp_path.glob("s.interrupted-*.mcap"))
    assert len(kept) == 1 and kept[0].stat().st_size == size
    assert len(list(SessionReader(kept[0]).frames())) == len(frames)
    assert out.exists() and SessionReader(out).format_version == 2

    # what the daemon's recording holds besides the inputs: the SLAM, in Foxglove's schemas
    msgs = decode_all(out)
    assert len(msgs["/robotd/map"]) >= 1 and len(msgs["/robotd/map"][0][1].data) > 0
    assert msgs["/robotd/map_covariance"][0][1].entities[0].spheres
    feats = msgs["/camera/left/features"]
    assert len(feats) >= 2 and any(len(a.points) > 10 for _, m in feats for a in m.points)
    assert any(a.type == 4 and a.points for _, m in feats[1:] for a in m.points), "no track drawn"
    assert len(msgs["/robotd/trajectory"][-1][1].poses) >= 2 and msgs["/truth/pose"]
    frames = {(t.parent_frame_id, t.child_frame_id) for _, m in msgs["/tf"] for t in m.transforms}
    assert {("world", "robot"), ("robot", "camera_left"), ("robot", "camera_right")} <= frames
    # wall-clock log times: the recording is dated today, not 1970
    assert abs(msgs["/camera/left/image"][0][0] / 1e9 - time.time()) < 3600


# --------------------------------------------------------------------------------------------
# a writer that falls behind, or fails

RIG = RectifiedStereo(100.0, 31.5, 19.5, 0.1, 64, 40)


def _frames(n: int) -> list[StereoFrame]:
    rng = np.random.default_rng(5)
    img = lambda: rng.integers(0, 256, (40, 64), dtype=np.uint8)  # noqa: E731
    return [StereoFrame(10**9 + k * 50_000_000, k, img(), img(), True) for k in range(n)]


def _odometry(n: int) -> list[Odometry]:
    return [Odometry(10**9 + k * 20_000_000, np.array([1.0, 0, 0]), np.zeros(3), "wheels") for k in range(n)]


def test_the_queue_refuses_what_does_not_fit_and_counts_it_per_stream() -> None:
    q = SampleQueue(max_bytes=100, max_items=5)
    assert q.put("frames", "a", 60) and not q.put("frames", "b", 60)  # 120 bytes > 100
    assert q.put("odometry", 1) and q.put("odometry", 2) and q.put("poses", "p", 40)
    assert q.put("odometry", 3) and not q.put("odometry", 4)  # 5 items
    assert q.lost == {"frames": 1, "odometry": 1, "poses": 0} and q.last_loss_ns > 0
    assert q.get() == ("frames", "a") and q.bytes == 40
    q.close()
    assert not q.put("odometry", 5) and q.lost["odometry"] == 2  # refused after close, counted
    assert [q.get() for _ in range(5)] == [("odometry", 1), ("odometry", 2), ("poses", "p"), ("odometry", 3), None]
    big = SampleQueue(max_bytes=10)
    assert big.put("frames", "x", 1000)  # an empty queue takes any one sample


def test_a_writer_that_falls_behind_loses_samples_counted_and_never_blocks_the_producers(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    release = threading.Event()
    write_frame = SessionWriter.write_frame

    def stuck(self: SessionWriter, frame: StereoFrame) -> None:
        release.wait(60.0)  # the disk hangs until the producers are done
        write_frame(self, frame)

    monkeypatch.setattr(SessionWriter, "write_frame", stuck)
    frames, odometry = _frames(20), _odometry(30)
    per_frame = frames[0].left.nbytes * 2
    rec = RecorderOutput(str(tmp_path / "s.mcap"), RIG, {}, buffer_mb=3.5 * per_frame / 1e6)
    for k, f in enumerate(frames):  # the camera thread: every call returns while the writer hangs
        rec.tee_frame(f)
        rec.tee_odometry(odometry[k])
    pose = PoseEstimate(frames[0].t_ns, np.zeros(3), np.zeros(3), np.eye(6) * 0.01)
    result = StepResult(pose.t_ns, pose, UpdateReport())
    rec.publish(StepReport(result=result, seq=1, frame_seq=0, quality=50, reset_counter=0, latency_ms=1.0,
                           health="tracking"))  # fmt: skip
    st = rec.stats()
    assert 16 <= st["frames_lost"] <= 17 and st["odometry_lost"] == 0 and st["poses_lost"] == 0
    # the health document says so, and the summary line
    h = {"recording": st, "budget": {"level": 0}, "tracking": True, "pose_sigma_m": None}
    problems = HealthMonitor().assess(h, needs_vehicle=False)["problems"]
    assert f"recording lost {st['frames_lost']} frames, 0 odometry" in problems
    release.set()
    rec.close()  # what was queued is written
    st = rec.stats()
    assert st["frames"] + st["frames_lost"] == 20 and st["odometry"] == 20 and st["poses"] == 1
    summary = {**st, "frames_delivered": 20, "odometry_delivered": 20, "slam_steps": 1}
    assert f"LOST {st['frames_lost']} frames, 0 odometry samples, 0 poses: the writer fell behind" in summary_line(
        summary
    )
    # the file holds the frames that were written, and says what it lost
    r = SessionReader(tmp_path / "s.mcap")
    assert [f.seq for f in r.frames()] == [f.seq for f in frames[: st["frames"]]]
    with open(tmp_path / "s.mcap", "rb") as fh:
        recs = {m.name: m.metadata for m in make_reader(fh, validate_crcs=True).iter_metadata()}
    assert "robotd.session" in recs and recs["robotd.recording"]["frames_lost"] == str(st["frames_lost"])


class _FullDisk(io.FileIO):
    def __init__(self, path: Path, limit: int) -> None:
        super().__init__(path, "wb")
        self.limit = limit

    def write(self, b: bytes) -> int:  # type: ignore[override]
        if self.tell() + len(b) > self.limit:
            raise OSError(errno.ENOSPC, "No space left on device")
        return super().write(b)


def test_a_write_error_stops_the_recording_with_its_reason(tmp_path: Path) -> None:
    path = tmp_path / "s.mcap"
    writer = SessionWriter(path, RIG, {}, chunk_size=4096, opener=lambda p: _FullDisk(p, 20_000))
    rec = RecorderOutput(str(path), RIG, {}, writer=writer)
    for f in _frames(20):
        rec.tee_frame(f)
    rec.close()
    assert rec.error is not None and "No space left on device" in rec.error
    assert not path.exists() and not path.with_name("s.mcap.tmp").exists()
    st = rec.stats()
    assert st["frames"] + st["frames_lost"] == 20 and st["frames_lost"] > 0
    assert summary_line(st).startswith("recording failed: ")


def test_a_write_error_stops_robotd_record_with_exit_status_1(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from robotd.config import load_config
    from robotd.core.errors import PersistenceError
    from robotd.daemon import Daemon

    def full(self: SessionWriter, frame: StereoFrame) -> None:
        raise PersistenceError(f"{self.path}: No space left on device (simulated)")

    monkeypatch.setattr(SessionWriter, "write_frame", full)
    cam = "sim://?fps=10&realtime=0&width=160&height=100"
    cfg = load_config(None, {"camera": {"url": cam}, "vehicle": {"url": cam}, "zenoh": {"enabled": False}})
    d = Daemon(cfg, duration_s=0.0, environ={}, record_path=str(tmp_path / "s.mcap"))
    assert d.run() == 1
    assert d.stop_reason.startswith("recording failed: ") and "No space left on device" in d.stop_reason
    assert d.failed == ["recorder"] and not (tmp_path / "s.mcap").exists()


# --------------------------------------------------------------------------------------------
# a recording beside a running daemon leaves the daemon's state alone


def _snapshot(d: Path) -> dict[str, tuple[bytes, int]]:
    return {p.name: (p.read_bytes(), p.stat().st_mtime_ns) for p in sorted(d.iterdir())}


def test_a_record_run_leaves_the_state_directory_byte_identical(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """The daemon's state directory, named both ways a ``robotd record`` beside it would find it:
    $STATE_DIRECTORY (systemd) and the shared config's ``persistence.state_dir``."""
    state = tmp_path / "daemon-state"
    state.mkdir()
    (state / "map.robotd").write_bytes(b"RBTDMAP\x01 the running daemon's map")
    (state / "map.20250101-000000.robotd").write_bytes(b"an earlier map")
    (state / "reset_counter").write_text("41\n")
    before = _snapshot(state)
    monkeypatch.setenv("STATE_DIRECTORY", str(state))
    cam = '[camera]\nurl = "sim://?fps=10&width=160&height=100"\n[vehicle]\nurl = "sim://?fps=10"\n'
    shared = tmp_path / "shared.toml"  # the daemon's own config, with its state_dir
    shared.write_text(cam + f'[zenoh]\nenabled = false\n[persistence]\nstate_dir = "{state}"\nresume = true\n')
    env_only = tmp_path / "env.toml"  # the state directory from the environment
    env_only.write_text(cam + "[zenoh]\nenabled = false\n")
    for cfg in (shared, env_only):
        out = tmp_path / f"{cfg.stem}.mcap"
        assert main(["record", str(out), "--config", str(cfg), "--duration", "1.5", "--log-level", "WARNING"]) == 0
        assert out.exists()
        assert _snapshot(state) == before, f"record --config {cfg.name} changed the state directory"
    assert "recorded " in capsys.readouterr().err
    # a state directory of its own, when asked for: the map and the counter go there
    own = tmp_path / "record-state"
    args = ["record", str(tmp_path / "own.mcap"), "--config", str(shared), "--duration", "1.5", "--state-dir", str(own)]
    assert main([*args, "--log-level", "WARNING"]) == 0
    assert {p.name for p in own.iterdir()} >= {"map.robotd", "reset_counter"}
    assert _snapshot(state) == before
