"""Calibration files other tools read: Kalibr's camchain rules and ROS camera_info YAMLs.

The readers are our own re-implementations of the other tools' reading rules
(tests/support/kalibr_camchain.py, tests/support/ros_camera_info.py); the checks on the ROS files
go through OpenCV with nothing but the files' numbers, as image_geometry does.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from calib.camchain import load_calibration, save_calibration
from calib.cli import main
from robotd.core.stereo import StereoCalibration, camera_matrix, rectify_opencv
from tests.support.kalibr_camchain import KALIBR_CAMERA_KEYS, KalibrError, read_camchain
from tests.support.paths import REPO
from tests.support.ros_camera_info import read_camera_info
from tests.support.tolerances import CONDITIONED_ATOL, CONDITIONED_RTOL

# calibration files as robotd wrote them before the Kalibr-readable format (version 1)
DATA = REPO / "tests" / "support" / "data" / "calibration_v1"
OAK_JSON = ("oakd-calibration", "BW1098OBC_14442C10218CCCD200.json")
# rectified rows of one point in both cameras: undistortion iterates, so agreement to 1e-6 px
ROW_ATOL_PX = 1e-6
UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)


def _check_kalibr_pair(path: Path) -> list:
    cams = read_camchain(path)
    assert len(cams) == 2
    for n, cam in enumerate(cams):
        assert cam.camera_model == "pinhole" and cam.distortion_model == "radtan"
        assert cam.rostopic == f"/cam{n}/image_raw"
    doc = yaml.safe_load(path.read_text())
    assert set(doc) == {"cam0", "cam1"}
    # robotd's keys sit where Kalibr never looks
    assert set(doc["cam0"]) - KALIBR_CAMERA_KEYS == {"robotd"}
    assert set(doc["cam1"]) - KALIBR_CAMERA_KEYS <= {"robotd"}
    return cams


def test_the_kalibr_reader_refuses_what_robotd_wrote_before() -> None:
    """The defect: the top-level robotd_* keys are counted as cameras 2..4."""
    with pytest.raises(KalibrError, match="Field 'cam2' missing"):
        read_camchain(DATA / "v1_chessboard.yaml")


def test_stereo_output_is_a_kalibr_camchain_with_the_raw_cameras(shared_data, tmp_path: Path, capsys) -> None:
    board = shared_data("stereo-calib", "opencv-chessboard-stereo")
    out = tmp_path / "rig.yaml"
    assert main(["stereo", str(board), "--board", "9x6", "--square", "0.025", "--out", str(out), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    cams = _check_kalibr_pair(out)
    calib = load_calibration(out)
    # radtan with 4 coefficients is Kalibr's own model: its fields are robotd's model, exactly
    assert yaml.safe_load(out.read_text())["cam0"]["robotd"]["kalibr_fields"] == "raw"
    assert cams[0].intrinsics == [calib.K_left[0, 0], calib.K_left[1, 1], calib.K_left[0, 2], calib.K_left[1, 2]]
    assert cams[1].distortion_coeffs == calib.D_right.tolist()
    assert np.array_equal(cams[1].T_cn_cnm1, calib.T_right_left())
    assert np.linalg.norm(cams[1].T_cn_cnm1[:3, 3]) == pytest.approx(res["baseline"], rel=CONDITIONED_RTOL)
    # the ROS YAMLs beside it
    assert res["ros_yaml"] == [str(tmp_path / "rig_left.yaml"), str(tmp_path / "rig_right.yaml")]
    _check_ros_pair(calib, tmp_path / "rig_left.yaml", tmp_path / "rig_right.yaml")


def test_import_oak_output_is_a_kalibr_camchain_of_the_rectified_pair(shared_data, tmp_path: Path, capsys) -> None:
    out = tmp_path / "oak.yaml"
    assert main(["import-oak", str(shared_data(*OAK_JSON)), "--size", "640x400", "--out", str(out), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    cams = _check_kalibr_pair(out)
    calib = load_calibration(out)
    # robotd keeps the factory model exactly
    assert calib.distortion_model == "rational" and calib.D_left.size == 14
    assert calib.K_left[0, 0] == res["fx"] and calib.baseline_m == res["baseline_m"]
    # Kalibr gets the rectified pinhole pair robotd works on
    m = rectify_opencv(calib, alpha=0.0).model
    for cam in cams:
        assert cam.intrinsics == [m.f_px, m.f_px, m.px, m.py]
        assert cam.distortion_coeffs == [0.0, 0.0, 0.0, 0.0]
        assert cam.resolution == (640, 400)
    T = cams[1].T_cn_cnm1
    assert np.array_equal(T[:3, :3], np.eye(3)) and T[1:3, 3].tolist() == [0.0, 0.0]
    assert -T[0, 3] == pytest.approx(m.baseline_m, rel=CONDITIONED_RTOL)
    assert m.baseline_m == pytest.approx(0.0755, abs=1e-4)
    assert yaml.safe_load(out.read_text())["cam0"]["robotd"]["kalibr_fields"] == "rectified-opencv"
    # and ROS YAMLs whose rectified pair is the same one
    left, right = _check_ros_pair(calib, tmp_path / "oak_left.yaml", tmp_path / "oak_right.yaml")
    assert left.distortion_model == "rational_polynomial" and left.D.tolist() == calib.D_left[:8].tolist()
    assert right.P[0, 0] == cams[1].intrinsics[0] and -right.P[0, 3] / right.P[0, 0] == pytest.approx(-T[0, 3])


def _check_ros_pair(calib: StereoCalibration, left_path: Path, right_path: Path):
    left, right = read_camera_info(left_path), read_camera_info(right_path)
    assert (left.camera_name, right.camera_name) == ("left", "right")
    w, h = calib.image_size
    for info, K in ((left, calib.K_left), (right, calib.K_right)):
        assert (info.width, info.height) == (w, h)
        assert np.array_equal(info.K, K)
        assert np.allclose(info.R @ info.R.T, np.eye(3), atol=CONDITIONED_ATOL)
    # P: the same f and principal point on both sides; Tx = 0 left, -f b right (b > 0, metres)
    assert left.P[0, 3] == 0.0 and right.P[1, 3] == 0.0 and right.P[2, 3] == 0.0
    assert np.array_equal(left.P[:, :3], right.P[:, :3])
    b = -right.P[0, 3] / right.P[0, 0]
    assert b == pytest.approx(calib.baseline_m, rel=0.01)  # the rectified baseline: |T| up to the rotation
    # a point seen by both raw cameras lands on one row of the rectified pair, at disparity f b / Z
    rng = np.random.default_rng(5)
    X_left = np.column_stack([rng.uniform(-0.5, 0.5, 20), rng.uniform(-0.3, 0.3, 20), rng.uniform(1.0, 4.0, 20)])
    X_right = X_left @ calib.R.T + calib.T
    rect = []
    for info, X, K in ((left, X_left, calib.K_left), (right, X_right, calib.K_right)):
        D_cv = calib.D_left if info is left else calib.D_right  # project with robotd's exact model
        uv, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), K, D_cv)
        rect.append(cv2.undistortPoints(uv, info.K, info.D, R=info.R, P=info.P, criteria=UNDISTORT_CRITERIA)[:, 0])
    (ul, vl), (ur, vr) = rect[0].T, rect[1].T
    assert np.allclose(vl, vr, atol=ROW_ATOL_PX)
    Z_rect = (X_left @ left.R.T)[:, 2]
    assert np.allclose(ul - ur, left.P[0, 0] * b / Z_rect, atol=ROW_ATOL_PX)
    return left, right


def test_ros_yaml_subcommand_from_an_existing_file(tmp_path: Path, capsys) -> None:
    assert main(["ros-yaml", str(DATA / "v1_radtan5_skew.yaml"), "--out-dir", str(tmp_path), "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["ros_yaml"] == [str(tmp_path / f"v1_radtan5_skew_{side}.yaml") for side in ("left", "right")]
    calib = load_calibration(DATA / "v1_radtan5_skew.yaml")
    left = read_camera_info(tmp_path / "v1_radtan5_skew_left.yaml")
    assert left.distortion_model == "plumb_bob" and left.D.tolist() == calib.D_left.tolist()
    assert main(["ros-yaml", str(DATA / "v1_radtan5_skew.yaml"), "--out-dir", str(tmp_path / "absent")]) == 2
    assert "cannot write" in capsys.readouterr().err


@pytest.mark.parametrize("name", ["v1_chessboard.yaml", "v1_oak_640x400.yaml", "v1_radtan5_skew.yaml"])
def test_files_robotd_wrote_before_still_load_and_upgrade(name: str, tmp_path: Path, capsys) -> None:
    old = load_calibration(DATA / name)
    legacy = yaml.safe_load((DATA / name).read_text())
    assert legacy["robotd_calibration_version"] == 1
    assert old.K_left.tolist()[0][0] == legacy["cam0"]["intrinsics"][0]
    assert old.D_right.tolist() == legacy["cam1"]["distortion_coeffs"]
    assert old.source == legacy["robotd_source"] and old.extra == (legacy.get("robotd_info") or {})
    new = tmp_path / "new.yaml"
    assert main(["upgrade", str(DATA / name), "--out", str(new)]) == 0
    _check_kalibr_pair(new)
    back = load_calibration(new)
    for field in ("K_left", "D_left", "K_right", "D_right", "R", "T"):
        assert np.array_equal(getattr(back, field), getattr(old, field)), field
    assert (back.source, back.extra, back.distortion_model) == (old.source, old.extra, old.distortion_model)
    assert (tmp_path / "new_left.yaml").exists() and "written to" in capsys.readouterr().out


def test_a_plain_kalibr_camchain_is_read(tmp_path: Path) -> None:
    doc = {
        "cam0": {"camera_model": "pinhole", "intrinsics": [450.0, 451.0, 320.5, 240.5], "distortion_model": "none",
                 "distortion_coeffs": [], "resolution": [640, 480], "rostopic": "/a"},
        "cam1": {"camera_model": "pinhole", "intrinsics": [449.0, 450.0, 319.5, 241.5], "distortion_model": "radtan",
                 "distortion_coeffs": [0.01, -0.02, 0.0, 0.0], "resolution": [640, 480], "rostopic": "/b",
                 "T_cn_cnm1": [[1.0, 0, 0, -0.1], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]]},
    }  # fmt: skip
    p = tmp_path / "kalibr-camchain.yaml"
    p.write_text(yaml.safe_dump(doc))
    assert len(read_camchain(p)) == 2
    c = load_calibration(p)
    assert c.D_left.tolist() == [0.0] * 4 and c.D_right.tolist() == [0.01, -0.02, 0.0, 0.0]
    assert c.baseline_m == pytest.approx(0.1) and "Kalibr camchain" in c.source
    doc["cam2"] = doc["cam1"]
    p.write_text(yaml.safe_dump(doc))
    with pytest.raises(Exception, match="cam0 and cam1 only at the top level; found cam2"):
        load_calibration(p)


def test_rostopics_are_set_per_camera(tmp_path: Path) -> None:
    calib = StereoCalibration(
        K_left=camera_matrix(500.0, 500.0, 320.0, 240.0), D_left=np.zeros(4),
        K_right=camera_matrix(500.0, 500.0, 320.0, 240.0), D_right=np.zeros(4),
        R=np.eye(3), T=np.array([-0.1, 0.0, 0.0]), image_size=(640, 480),
    )  # fmt: skip
    p = save_calibration(calib, tmp_path / "c.yaml", rostopics=("/oak/left/image_raw", "/oak/right/image_raw"))
    cams = read_camchain(p)
    assert [c.rostopic for c in cams] == ["/oak/left/image_raw", "/oak/right/image_raw"]
    # integral focal lengths still reach Kalibr as floats (its reader checks isinstance(float))
    assert all(isinstance(v, float) for v in cams[0].intrinsics)
