"""The recording output under a crash: a ``robotd record`` killed with SIGKILL (no handler, no
close, no summary) leaves ``OUT.mcap.tmp`` that replays up to its last whole chunk, and the next
``robotd record`` to the same path keeps it instead of overwriting it."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from robotd.cli import main
from robotd.record import SessionReader
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
