"""OAK-D factory calibration import through the real depthai library, without a device."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from calib.camchain import load_calibration
from calib.cli import main
from drivers.oak import import_oak_calibration, load_oak_eeprom_json, open_oak_camera, read_device_calibration
from robotd.core.errors import CalibrationError, DriverError
from robotd.core.stereo import Rectifier
from tests.support.tolerances import FLOAT32_ROUNDING_TOL

# the README quotes the factory translation to 0.001 cm (1e-5 m)
README_T_ATOL_M = 2e-5
OAK_JSON = ("oakd-calibration", "BW1098OBC_14442C10218CCCD200.json")


def test_eeprom_json_at_640x400(shared_data) -> None:
    c = load_oak_eeprom_json(shared_data(*OAK_JSON), 640, 400)
    assert c.baseline_m == pytest.approx(0.075, abs=0.001)
    assert c.K_left[0, 0] == pytest.approx(430.3, abs=0.1)
    assert c.K_left[1, 1] == pytest.approx(430.21, abs=0.1)
    assert c.K_left[0, 2] == pytest.approx(322.05, abs=0.1)
    assert c.K_left[1, 2] == pytest.approx(199.18, abs=0.1)
    # centimetres converted once: README translation (-7.550, -0.117, 0.050) cm
    assert np.allclose(c.T, [-0.07550, -0.00117, 0.00050], atol=README_T_ATOL_M)
    assert c.distortion_model == "rational" and c.D_left.size == 14
    assert c.image_size == (640, 400)
    # at full resolution fx doubles: intrinsics really follow the requested size
    full = load_oak_eeprom_json(shared_data(*OAK_JSON), 1280, 800)
    assert full.K_left[0, 0] == pytest.approx(2 * c.K_left[0, 0], rel=FLOAT32_ROUNDING_TOL)  # float32 EEPROM
    # the rectified rig is the one docs/math.md §2.2 quotes: fb ≈ 32.5 px·m
    assert Rectifier(c, method="thesis").model.fb == pytest.approx(32.5, rel=0.03)


def test_cli_import_oak_json(shared_data, tmp_path: Path, capsys) -> None:
    out = tmp_path / "oak.yaml"
    rc = main(["import-oak", str(shared_data(*OAK_JSON)), "--size", "640x400", "--out", str(out), "--json"])
    assert rc == 0
    res = json.loads(capsys.readouterr().out)
    assert res["baseline_m"] == pytest.approx(0.075, abs=0.001)
    assert res["fx"] == pytest.approx(430.3, abs=0.1)
    assert {"fy", "cx", "cy"} <= set(res)
    back = load_calibration(out)
    assert back.K_left[0, 0] == res["fx"] and back.distortion_model == "rational"


def test_no_device_fails_fast_and_clearly() -> None:
    t0 = time.monotonic()
    with pytest.raises(DriverError, match="no OAK device found"):
        read_device_calibration("14442C10218CCCD200")
    assert time.monotonic() - t0 < 3.0  # never dai.Pipeline()'s 11 s wait


def test_bad_sources(tmp_path: Path) -> None:
    with pytest.raises(CalibrationError, match="not found"):
        import_oak_calibration(str(tmp_path / "missing.json"))
    (tmp_path / "junk.json").write_text("not json")
    with pytest.raises(CalibrationError, match="cannot read it"):
        import_oak_calibration(str(tmp_path / "junk.json"))
    (tmp_path / "empty.json").write_text("{}")
    with pytest.raises(CalibrationError, match="no camera calibration"):
        import_oak_calibration(str(tmp_path / "empty.json"))


def test_open_oak_camera_without_camera_module(monkeypatch: pytest.MonkeyPatch) -> None:
    # a None entry makes the import fail as if drivers/oak/camera.py were absent
    monkeypatch.setitem(sys.modules, "drivers.oak.camera", None)
    with pytest.raises(DriverError, match=r"drivers\.oak\.camera"):
        open_oak_camera("oak://")


def test_json_stdout_is_one_object_in_a_fresh_process(shared_data, tmp_path: Path) -> None:
    """depthai prints import-time warnings on stdout; --json output must stay parseable."""
    import subprocess

    argv = ["import-oak", str(shared_data(*OAK_JSON)), "--out", str(tmp_path / "o.yaml"), "--json"]
    r = subprocess.run([sys.executable, "-m", "calib.cli", *argv], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["baseline_m"] == pytest.approx(0.0755, abs=0.001)
