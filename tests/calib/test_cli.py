"""Smoke tests of robotd-calib: every subcommand, and clear errors with exit status != 0."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from calib.camchain import save_calibration
from calib.cli import main
from robotd.core.stereo import StereoCalibration, camera_matrix


def _write_synthetic_pair(tmp_path: Path) -> tuple[Path, Path, Path]:
    """A textured plane seen by an ideal, already-rectified rig: the check must find |dy| ≈ 0."""
    rng = np.random.default_rng(3)
    tex = cv2.GaussianBlur((rng.random((480, 700)) * 255).astype(np.uint8), (0, 0), 2.5)
    left = tex[:, 40:680].copy()
    right = tex[:, 20:660].copy()  # 20 px disparity, same rows
    lp, rp = tmp_path / "l.png", tmp_path / "r.png"
    cv2.imwrite(str(lp), left)
    cv2.imwrite(str(rp), right)
    calib = StereoCalibration(
        K_left=camera_matrix(500, 500, 320, 240),
        D_left=np.zeros(4),
        K_right=camera_matrix(500, 500, 320, 240),
        D_right=np.zeros(4),
        R=np.eye(3),
        T=np.array([-0.1, 0.0, 0.0]),
        image_size=(640, 480),
    )
    cp = save_calibration(calib, tmp_path / "ideal.yaml")
    return cp, lp, rp


def test_check_on_synthetic_pair(tmp_path: Path, capsys) -> None:
    cp, lp, rp = _write_synthetic_pair(tmp_path)
    assert main(["check", str(cp), str(lp), str(rp), "--method", "thesis", "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["n_matches"] > 50
    assert res["median_abs_dy_px"] < 0.1 and res["share_within_1px"] > 0.95
    assert main(["check", str(cp), str(lp), str(rp), "--detector", "orb"]) == 0
    assert "median |dy|" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["stereo", "/nonexistent/dir", "--out", "x.yaml"], "not a directory"),
        (["stereo", ".", "--board", "9by6", "--out", "x.yaml"], "--board"),
        (["import-oak", "/nonexistent/eeprom.json", "--out", "x.yaml"], "not found"),
        (["check", "/nonexistent/calib.yaml", "l.png", "r.png"], "cannot read"),
        (["ros-yaml", "/nonexistent/calib.yaml"], "cannot read"),
        (["upgrade", "/nonexistent/calib.yaml", "--out", "/nonexistent/dir/new.yaml"], "does not exist"),
    ],
)
def test_errors_are_one_clear_line(argv: list[str], message: str, capsys) -> None:
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


def test_stereo_directory_without_pairs(tmp_path: Path, capsys) -> None:
    (tmp_path / "left01.png").write_bytes(b"")
    assert main(["stereo", str(tmp_path), "--out", str(tmp_path / "c.yaml")]) == 2
    assert "no left*/right* image pairs" in capsys.readouterr().err


def test_stereo_too_few_boards(tmp_path: Path, capsys) -> None:
    blank = np.full((120, 160), 128, np.uint8)
    for i in range(3):
        cv2.imwrite(str(tmp_path / f"left{i}.png"), blank)
        cv2.imwrite(str(tmp_path / f"right{i}.png"), blank)
    assert main(["stereo", str(tmp_path), "--out", str(tmp_path / "c.yaml")]) == 2
    err = capsys.readouterr().err
    assert "only 0 usable board views" in err and "board 9x6 not found in both sides" in err


def test_check_wrong_image_size(tmp_path: Path, capsys) -> None:
    cp, lp, _ = _write_synthetic_pair(tmp_path)
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.zeros((100, 100), np.uint8))
    assert main(["check", str(cp), str(lp), str(small)]) == 2
    assert "100x100" in capsys.readouterr().err


def test_argument_errors_exit_nonzero(capsys) -> None:
    assert main([]) != 0
    assert main(["import-oak", "x.json", "--size", "640by400", "--out", "o.yaml"]) != 0
    assert "WIDTHxHEIGHT" in capsys.readouterr().err
    assert main(["stereo", "."]) != 0  # --out is required


def test_console_script_help() -> None:
    """The installed entry point runs (python -m keeps it independent of PATH)."""
    r = subprocess.run([sys.executable, "-m", "calib.cli", "--help"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and "import-oak" in r.stdout
