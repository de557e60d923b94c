"""``dev.py run`` as a newcomer, a service manager or ``timeout`` uses it: a signal sent to the
dev.py process alone (not to its process group) stops robotd cleanly, with the map saved."""

from __future__ import annotations

import hashlib
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from tests.support.net import free_port
from tests.support.paths import REPO

STOP_WITHIN_S = 5.0  # the bound on a clean stop after the signal


@pytest.fixture
def clone(tmp_path: Path) -> Path:
    """dev.py and pyproject.toml in a fresh folder, sharing this checkout's installed .venv.

    Only when dev.py stamped that .venv as installed for this very pyproject.toml: otherwise
    dev.py in the copy would re-install robotd into the shared .venv from a folder without the
    package (as ``python3 dev.py test`` leaves it, which is how CI runs)."""
    venv = REPO / ".venv"
    stamp = venv / ".robotd-installed"
    digest = hashlib.sha256((REPO / "pyproject.toml").read_bytes()).hexdigest()
    if not (venv / "bin" / "robotd").exists() or not stamp.exists() or stamp.read_text().split()[:1] != [digest]:
        pytest.skip(f"{venv} is not installed by dev.py for this pyproject.toml (run python3 dev.py test)")
    root = tmp_path / "robotd"
    root.mkdir()
    shutil.copy(REPO / "dev.py", root / "dev.py")
    shutil.copy(REPO / "pyproject.toml", root / "pyproject.toml")
    (root / ".venv").symlink_to(venv)
    return root


def _start(root: Path, tmp: Path) -> tuple[subprocess.Popen[str], list[str]]:
    cfg = tmp / "robotd.toml"
    cfg.write_text(
        f'[camera]\nurl = "sim://?fps=10"\n[vehicle]\nurl = "sim://?fps=10"\n'
        f'[zenoh]\nlisten = ["tcp/127.0.0.1:{free_port()}"]\n'
        f'[persistence]\nstate_dir = "{tmp / "state"}"\n'
    )
    proc = subprocess.Popen(
        [sys.executable, str(root / "dev.py"), "run", "--config", str(cfg)],
        cwd=root,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,  # its own process group: nothing reaches robotd unless dev.py passes it on
    )
    lines: list[str] = []

    def read() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.append(line)

    threading.Thread(target=read, daemon=True).start()
    t_end = time.monotonic() + 120
    while not any("ready:" in x for x in lines):
        if proc.poll() is not None or time.monotonic() > t_end:
            proc.kill()
            pytest.fail("robotd did not become ready under dev.py run:\n" + "".join(lines[-40:]))
        time.sleep(0.1)
    return proc, lines


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_a_signal_to_dev_py_alone_stops_robotd_cleanly(clone: Path, tmp_path: Path, sig: signal.Signals) -> None:
    proc, lines = _start(clone, tmp_path)
    time.sleep(1.0)  # a few steps, so there is a map to save
    t0 = time.monotonic()
    proc.send_signal(sig)  # to the dev.py pid only
    try:
        code = proc.wait(timeout=STOP_WITHIN_S + 5)
    except subprocess.TimeoutExpired:
        proc.kill()
        pytest.fail(f"dev.py run did not stop within {STOP_WITHIN_S + 5} s of {sig.name}:\n" + "".join(lines[-20:]))
    took = time.monotonic() - t0
    out = "".join(lines)
    assert code == 0, out[-2000:]
    assert took < STOP_WITHIN_S, f"stop took {took:.1f} s"
    assert f"shutting down ({sig.name})" in out and "map saved to" in out, out[-2000:]
    assert (tmp_path / "state" / "map.robotd").exists()


def _dev_module():  # dev.py is a script at the repository's root, not a package module
    import importlib.util

    spec = importlib.util.spec_from_file_location("robotd_dev_script", REPO / "dev.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.parametrize(
    ("args", "cpus", "expected"),
    [
        ([], 2, ["-n", "2"]),
        ([], 16, ["-n", "2"]),  # two: the concurrency the suite is checked at
        ([], 1, []),  # one CPU: one process
        (["-n", "0"], 2, []),  # the caller's choice wins
        (["-n4", "tests/test_docs.py"], 2, []),
        (["--numprocesses=3"], 2, []),
        (["-p", "no:xdist"], 2, []),
        (["-k", "not slow", "--durations=20"], 2, ["-n", "2"]),
    ],
)
def test_dev_py_test_runs_two_workers_unless_told_or_on_one_cpu(
    monkeypatch: pytest.MonkeyPatch, args: list[str], cpus: int, expected: list[str]
) -> None:
    dev = _dev_module()
    monkeypatch.setattr(dev.os, "sched_getaffinity", lambda _pid: set(range(cpus)))
    assert dev._workers(args) == expected
