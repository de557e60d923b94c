"""Two robotd on one host, as a newcomer tries it: a second ``robotd run`` with the same config fails
at once in one line naming the key to change; with its own Zenoh port (and state dir) it runs
beside the first; so does a ``robotd record``, whose recording is written."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.support.net import free_port
from tests.support.paths import REPO


def _config(tmp: Path, name: str, port: int) -> Path:
    cfg = tmp / f"{name}.toml"
    cfg.write_text(
        f'[camera]\nurl = "sim://?fps=10"\n[vehicle]\nurl = "sim://?fps=10"\n'
        f'[zenoh]\nlisten = ["tcp/127.0.0.1:{port}"]\n[persistence]\nstate_dir = "{tmp / name}"\n'
    )
    return cfg


def _robotd(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "robotd", *args],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


@pytest.mark.slow
def test_a_second_instance_fails_in_one_line_or_runs_beside_with_its_own_port(tmp_path: Path) -> None:
    port = free_port()
    # long enough to outlast the three runs below on a loaded machine; it is stopped in `finally`
    first = _robotd("run", "--config", str(_config(tmp_path, "a", port)), "--duration", "120")
    try:
        time.sleep(4.0)  # the first one is up and holds the port
        assert first.poll() is None
        same = _robotd("run", "--config", str(_config(tmp_path, "b", port)), "--duration", "5")
        out, _ = same.communicate(timeout=60)
        errors = [x for x in out.splitlines() if "ERROR" in x]
        assert same.returncode == 2, out[-2000:]
        assert len(errors) == 1 and f"zenoh.listen: tcp/127.0.0.1:{port} is already in use" in errors[0]
        # with its own port it runs beside the first; a recording beside both is written
        beside = _robotd("run", "--config", str(_config(tmp_path, "c", free_port())), "--duration", "3")
        rec_out = tmp_path / "beside.mcap"
        rec = _robotd("record", str(rec_out), "--config", str(_config(tmp_path, "d", free_port())), "--duration", "3")
        out_beside, _ = beside.communicate(timeout=60)
        out_rec, _ = rec.communicate(timeout=60)
        assert beside.returncode == 0 and "ready:" in out_beside, out_beside[-2000:]
        assert rec.returncode == 0 and rec_out.exists() and rec_out.stat().st_size > 0, out_rec[-2000:]
        assert first.poll() is None  # the first one was never disturbed
    finally:
        first.terminate()
        out_first, _ = first.communicate(timeout=30)
    assert first.returncode == 0 and "map saved" in out_first, out_first[-2000:]
