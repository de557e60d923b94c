"""A second robotd on the host: the Zenoh port it wants is taken. One line naming the key to
change, no Rust source paths, and no output file left from the failed start."""

from __future__ import annotations

import socket
from collections.abc import Iterator
from pathlib import Path

import pytest

from robotd.config import ZenohConfig
from robotd.core.errors import DriverError
from robotd.outputs.zenoh import ZenohOutput
from robotd.tools.cli import main


@pytest.fixture
def busy_port() -> Iterator[int]:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        yield int(s.getsockname()[1])


def test_a_taken_listen_port_fails_in_one_line_naming_the_key(busy_port: int) -> None:
    with pytest.raises(DriverError) as e:
        ZenohOutput(ZenohConfig(listen=[f"tcp/127.0.0.1:{busy_port}"]), "r1")
    msg = str(e.value)
    assert msg.startswith(f"zenoh.listen: tcp/127.0.0.1:{busy_port} is already in use")
    assert "[zenoh] listen" in msg and ".rs" not in msg and "\n" not in msg


def test_record_beside_a_run_leaves_no_file_when_it_cannot_start(
    busy_port: int, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    cfg = tmp_path / "robotd.toml"
    cfg.write_text(
        f'[zenoh]\nlisten = ["tcp/127.0.0.1:{busy_port}"]\n[persistence]\nstate_dir = "{tmp_path / "state"}"\n'
    )
    out = tmp_path / "s.mcap"
    assert main(["record", str(out), "--config", str(cfg), "--duration", "2"]) == 2
    assert not out.exists() and not out.with_name("s.mcap.tmp").exists()
    assert any("startup failed: zenoh.listen" in r.message for r in caplog.records)


def test_a_recording_that_got_no_frame_is_not_written(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    from robotd.core.stereo import RectifiedStereo
    from robotd.outputs.recorder import RecorderOutput

    out = tmp_path / "empty.mcap"
    rec = RecorderOutput(str(out), RectifiedStereo(400.0, 320.0, 200.0, 0.075, 640, 400), {})
    rec.close()
    assert not out.exists() and not out.with_name("empty.mcap.tmp").exists()
    assert "no frame was recorded" in caplog.text
