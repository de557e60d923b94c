"""Two robotd on one host, as a newcomer tries it: a second ``robotd run`` with the same config fails
at once in one line naming the key to change; with its own Zenoh port (and state dir) it runs
beside the first; so does a ``robotd record``, whose recording is written."""

from __future__ import annotations

import subprocess
import sys
import threading
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


class Lines:
    """A process's merged output, read line by line on a thread (so its pipe never fills), and an
    event set at the first line containing ``marker``."""

    def __init__(self, proc: subprocess.Popen[str], marker: str) -> None:
        self.lines: list[str] = []
        self.seen = threading.Event()
        self._marker = marker
        self._thread = threading.Thread(target=self._read, args=(proc,), daemon=True)
        self._thread.start()

    def _read(self, proc: subprocess.Popen[str]) -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            self.lines.append(line)
            if self._marker in line:
                self.seen.set()
        self.seen.set()  # the process ended (the caller checks that it still runs)

    def text(self) -> str:
        self._thread.join(timeout=30)
        return "".join(self.lines)


# how long a run may take to load its kernels and open its devices on a busy machine before the
# test calls it hung (an event, the first one's "ready:" line, ends the wait as soon as it comes)
STARTUP_TIMEOUT_S = 120.0
RUN_TIMEOUT_S = 150.0


@pytest.mark.slow
def test_a_second_instance_fails_in_one_line_or_runs_beside_with_its_own_port(tmp_path: Path) -> None:
    port = free_port()
    # runs until stopped in `finally`, however long the three runs below take on a loaded machine
    first = _robotd("run", "--config", str(_config(tmp_path, "a", port)))
    first_out = Lines(first, "ready:")
    others: list[subprocess.Popen[str]] = []  # killed in `finally` if a failed check left them running
    try:
        # the first one is up and holds the port: its Zenoh session is open before its first step
        assert first_out.seen.wait(STARTUP_TIMEOUT_S) and first.poll() is None, "".join(first_out.lines)[-2000:]
        same = _robotd("run", "--config", str(_config(tmp_path, "b", port)), "--duration", "5")
        others.append(same)
        out, _ = same.communicate(timeout=RUN_TIMEOUT_S)
        errors = [x for x in out.splitlines() if "ERROR" in x]
        assert same.returncode == 2, out[-2000:]
        assert len(errors) == 1 and f"zenoh.listen: tcp/127.0.0.1:{port} is already in use" in errors[0]
        # with its own port it runs beside the first; a recording beside both is written
        # (it runs until it is ready, an event, then stops as systemd stops it)
        beside = _robotd("run", "--config", str(_config(tmp_path, "c", free_port())))
        beside_out = Lines(beside, "ready:")
        others.append(beside)
        rec_out = tmp_path / "beside.mcap"
        rec = _robotd("record", str(rec_out), "--config", str(_config(tmp_path, "d", free_port())), "--duration", "3")
        others.append(rec)
        ready = beside_out.seen.wait(STARTUP_TIMEOUT_S) and beside.poll() is None
        beside.terminate()
        beside.wait(timeout=60)
        out_beside = beside_out.text()
        out_rec, _ = rec.communicate(timeout=RUN_TIMEOUT_S)
        assert ready and beside.returncode == 0 and "ready:" in out_beside, out_beside[-2000:]
        assert rec.returncode == 0 and rec_out.exists() and rec_out.stat().st_size > 0, out_rec[-2000:]
        assert first.poll() is None  # the first one was never disturbed
    finally:
        for proc in others:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        first.terminate()
        first.wait(timeout=60)
    out_first = first_out.text()
    assert first.returncode == 0 and "map saved" in out_first, out_first[-2000:]
