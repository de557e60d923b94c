"""Smoke tests of the MCU simulator as a program (``python -m drivers.mcu_sim`` / ``robotd mcu-sim``)."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest

from drivers.mcu_sim import main
from drivers.serial_link import SerialVehicle
from tests.support.tolerances import FLOAT32_ROUNDING_TOL


def test_mcu_sim_program_streams_to_a_stable_link(tmp_path: Path) -> None:
    link_path = tmp_path / "ttyMCU"
    proc = subprocess.Popen(
        [sys.executable, "-m", "drivers.mcu_sim", "--duration", "2.5", "--speed", "0.8", "--link", str(link_path)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        url = proc.stdout.readline().strip()
        assert url.startswith(f"serial://{link_path}?baud=")
        with SerialVehicle(url, wheel_source="velocity") as link:
            samples = []
            t_end = time.monotonic() + 1.0
            while time.monotonic() < t_end and len(samples) < 20:
                samples += link.drain()
                time.sleep(0.02)
        assert len(samples) >= 20
        assert all(s.vel_R_mps[0] == pytest.approx(0.8, abs=FLOAT32_ROUNDING_TOL) for s in samples)
        _, err = proc.communicate(timeout=10)
        assert proc.returncode == 0
        assert "from the host" in err
        assert not link_path.exists()  # the symlink is removed on exit
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_mcu_sim_rejects_bad_geometry(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--track-width", "0", "--duration", "0"]) == 2
    assert "track_width_m" in capsys.readouterr().err
