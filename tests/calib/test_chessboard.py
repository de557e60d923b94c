"""Acceptance on OpenCV's 13 real chessboard stereo pairs (stereo-calib/opencv-chessboard-stereo).

The rig is calibrated once per module. Square size is undocumented upstream, so lengths are in
squares (--square 1). Measured (OpenCV 5.0): pair 02 is dropped (per-view RMS 1.22 px), stereo RMS
0.296 px over 12 views, fx_left 535.25; pooled over all 13 pairs, SIFT matches verified by an
F-RANSAC have median |Δy| 0.30 px (OpenCV rectification) and 0.29 px (thesis rectification).
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from calib.camchain import load_calibration
from calib.check import row_offsets
from calib.chessboard import StereoCalibrationReport, calibrate_directory, detect_corners, find_pairs
from calib.cli import main
from robotd.core.stereo import Rectifier, rectify_opencv, rectify_thesis, triangulate
from tests.support.tolerances import CONDITIONED_RTOL, ROUNDOFF_RTOL

SET = ("stereo-calib", "opencv-chessboard-stereo")


@pytest.fixture(scope="module")
def board_dir() -> Path:
    from tests.conftest import data_path

    return data_path(*SET)


@pytest.fixture(scope="module")
def report(board_dir: Path) -> StereoCalibrationReport:
    return calibrate_directory(board_dir, board=(9, 6), square_m=1.0)


@pytest.fixture(scope="module")
def pairs(board_dir: Path) -> list[tuple[str, np.ndarray, np.ndarray]]:
    found, _ = find_pairs(board_dir)
    return [
        (k, cv2.imread(str(lp), cv2.IMREAD_GRAYSCALE), cv2.imread(str(rp), cv2.IMREAD_GRAYSCALE)) for k, lp, rp in found
    ]


def test_calibration_accuracy(report: StereoCalibrationReport) -> None:
    assert report.stereo_rms_px < 0.5
    assert report.calibration.K_left[0, 0] == pytest.approx(536.0, rel=0.01)
    assert report.calibration.K_left[1, 1] == pytest.approx(536.0, rel=0.01)
    # the right camera sits ≈ 3.34 squares to the right (README reference T ≈ (-3.34, 0.04, 0.05))
    assert report.calibration.T[0] == pytest.approx(-3.34, abs=0.05)
    assert len(report.views) + len(report.dropped) == 13


def test_outlier_view_dropped_with_numbers(report: StereoCalibrationReport) -> None:
    dropped = dict(report.dropped)
    assert "02" in dropped, report.dropped
    assert "per-view RMS" in dropped["02"] and "px" in dropped["02"]
    assert all(v.rms_px < 0.8 for v in report.views)
    assert report.rounds >= 2


@pytest.mark.parametrize("method", ["opencv", "thesis"])
def test_rectified_matches_share_rows(method: str, report: StereoCalibrationReport, pairs) -> None:
    rect = Rectifier(report.calibration, method=method)
    dys = [row_offsets(*rect.rectify(left, right))[0] for _, left, right in pairs]
    dy = np.abs(np.concatenate(dys))
    assert len(dy) > 1000
    assert np.median(dy) < 0.5, f"{method}: median |dy| {np.median(dy):.3f} px over {len(dy)} matches"
    assert np.mean(dy <= 1.0) > 0.8


def test_thesis_and_opencv_agree_on_fb(report: StereoCalibrationReport) -> None:
    thesis = rectify_thesis(report.calibration).model
    # alpha = -1 is OpenCV's default scaling (no zoom), comparable with K = ½(K_L + K_R)
    default = rectify_opencv(report.calibration, alpha=-1).model
    assert thesis.fb == pytest.approx(default.fb, rel=0.01)
    # alpha = 0 (robotd's default, valid pixels only) zooms in by a few %: f changes, b does not
    zoomed = rectify_opencv(report.calibration, alpha=0).model
    assert zoomed.fb == pytest.approx(thesis.fb, rel=0.05)
    assert zoomed.baseline_m == pytest.approx(thesis.baseline_m, rel=CONDITIONED_RTOL)


@pytest.mark.parametrize("method", ["opencv", "thesis"])
def test_board_triangulates_to_its_square_size(method: str, report: StereoCalibrationReport, pairs) -> None:
    """A target of known size: neighbouring corners triangulate 1 square apart (median within 1 %)."""
    rect = Rectifier(report.calibration, method=method)
    m = rect.model
    spacings = []
    for _, left, right in pairs:
        rl, rr = rect.rectify(left, right)
        cl, cr = detect_corners(rl, (9, 6)), detect_corners(rr, (9, 6))
        if cl is None or cr is None:
            continue
        pts = triangulate(cl[:, 0], cr[:, 0], 0.5 * (cl[:, 1] + cr[:, 1]), m.f_px, m.px, m.py, m.baseline_m)
        grid = pts.reshape(6, 9, 3)
        spacings.append(np.linalg.norm(np.diff(grid, axis=1), axis=-1).ravel())
        # corners found in both rectified images lie on the same rows
        assert np.median(np.abs(cl[:, 1] - cr[:, 1])) < 0.5
    assert len(spacings) >= 10
    assert np.median(np.concatenate(spacings)) == pytest.approx(1.0, rel=0.01)


def test_cli_stereo_end_to_end(board_dir: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "rig.yaml"
    rc = main(["stereo", str(board_dir), "--board", "9x6", "--square", "0.025", "--out", str(out), "--json"])
    assert rc == 0
    res = json.loads(capsys.readouterr().out)
    assert res["stereo_rms_px"] < 0.5
    assert res["fx_left"] == pytest.approx(536.0, rel=0.01)
    assert res["views_used"] == 12
    assert res["baseline"] == pytest.approx(3.34 * 0.025, rel=0.02)
    assert {d["view"] for d in res["dropped"]} == {"02"}
    assert set(res["per_view_rms_px"]) == {"01", "03", "04", "05", "06", "07", "08", "09", "11", "12", "13", "14"}
    calib = load_calibration(out)
    assert calib.baseline_m == pytest.approx(res["baseline"], rel=ROUNDOFF_RTOL)
    # and the check subcommand on one pair of the same set
    rc = main(["check", str(out), str(board_dir / "left01.jpg"), str(board_dir / "right01.jpg"), "--json"])
    assert rc == 0
    chk = json.loads(capsys.readouterr().out)
    assert chk["median_abs_dy_px"] < 0.5 and chk["n_matches"] > 100 and chk["share_within_1px"] > 0.8
