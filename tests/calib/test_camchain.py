"""The camchain calibration file: exact round trip, Kalibr layout, clear errors."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from calib.camchain import calibration_from_dict, calibration_to_dict, load_calibration, save_calibration
from robotd.core.errors import CalibrationError
from robotd.core.stereo import StereoCalibration, camera_matrix


def _calib(rng: np.random.Generator, model: str = "radtan", n: int = 4, skew: float = 0.0) -> StereoCalibration:
    R, _ = cv2.Rodrigues(rng.normal(0, 0.02, 3))
    return StereoCalibration(
        K_left=camera_matrix(*rng.uniform([400, 400, 300, 200], [600, 600, 340, 260]), skew=skew),
        D_left=rng.normal(0, 0.1, n) * 1e-3 ** rng.integers(0, 3),
        K_right=camera_matrix(*rng.uniform([400, 400, 300, 200], [600, 600, 340, 260])),
        D_right=rng.normal(0, 0.1, n),
        R=R,
        T=np.array([-0.075, 1e-4, -3.3e-7]) + rng.normal(0, 1e-3, 3),
        image_size=(640, 400),
        distortion_model=model,
        source="unit test: ümlaut and 'quotes'",
        extra={"stereo_rms_px": float(rng.uniform()), "board": [9, 6]},
    )


@pytest.mark.parametrize(("model", "n", "skew"), [("radtan", 4, 0.0), ("radtan", 5, 0.7), ("rational", 14, 0.0)])
def test_round_trip_is_exact(model: str, n: int, skew: float, tmp_path: Path, rng: np.random.Generator) -> None:
    for i in range(5):
        c = _calib(rng, model, n, skew)
        p = save_calibration(c, tmp_path / f"c{i}.yaml")
        back = load_calibration(p)
        for name in ("K_left", "D_left", "K_right", "D_right", "R", "T"):
            assert np.array_equal(getattr(back, name), getattr(c, name)), name
        assert back.image_size == c.image_size
        assert back.distortion_model == c.distortion_model
        assert back.source == c.source
        assert back.extra == c.extra


def test_kalibr_layout(tmp_path: Path, rng: np.random.Generator) -> None:
    c = _calib(rng)
    doc = yaml.safe_load(save_calibration(c, tmp_path / "c.yaml").read_text())
    assert list(doc) == ["cam0", "cam1"]  # Kalibr counts every top-level key as a camera
    cam0, cam1 = doc["cam0"], doc["cam1"]
    assert cam0["robotd"]["calibration_version"] == 2 and cam0["robotd"]["kalibr_fields"] == "raw"
    assert cam0["camera_model"] == "pinhole" and cam0["distortion_model"] == "radtan"
    assert cam0["intrinsics"] == [c.K_left[0, 0], c.K_left[1, 1], c.K_left[0, 2], c.K_left[1, 2]]
    assert cam0["resolution"] == [640, 400] and "skew" not in cam0
    assert (cam0["rostopic"], cam1["rostopic"]) == ("/cam0/image_raw", "/cam1/image_raw")
    assert (cam0["cam_overlaps"], cam1["cam_overlaps"]) == ([1], [0])
    T = np.array(cam1["T_cn_cnm1"])
    # T_cn_cnm1 maps a left-camera point into the right camera
    x_left = np.array([0.3, -0.2, 2.0])
    assert np.allclose(T[:3, :3] @ x_left + T[:3, 3], c.R @ x_left + c.T)
    assert "T_cn_cnm1" not in cam0


def test_models_kalibr_lacks_go_under_robotd_raw(tmp_path: Path, rng: np.random.Generator) -> None:
    c = _calib(rng, "rational", 14)
    doc = yaml.safe_load(save_calibration(c, tmp_path / "c.yaml").read_text())
    assert doc["cam0"]["robotd"]["kalibr_fields"] == "rectified-opencv"
    assert doc["cam0"]["distortion_model"] == "radtan" and doc["cam0"]["distortion_coeffs"] == [0.0] * 4
    raw0, raw1 = doc["cam0"]["robotd"]["raw"], doc["cam1"]["robotd"]["raw"]
    assert raw0["distortion_model"] == "rational" and raw0["distortion_coeffs"] == c.D_left.tolist()
    assert np.array_equal(raw1["T_cn_cnm1"], c.T_right_left())
    skewed = _calib(rng, "radtan", 4, skew=0.7)  # Kalibr's pinhole has no skew; OpenCV ignores it
    doc = yaml.safe_load(save_calibration(skewed, tmp_path / "s.yaml").read_text())
    assert doc["cam0"]["robotd"]["kalibr_fields"] == "rectified-thesis"
    assert doc["cam0"]["robotd"]["raw"]["skew"] == 0.7


def _doc(rng: np.random.Generator) -> dict:
    return calibration_to_dict(_calib(rng))


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda d: d["cam0"]["robotd"].update(calibration_version=3), "calibration_version 3 is not supported"),
        (lambda d: d["cam0"]["robotd"].pop("calibration_version"), r"missing key cam0\.robotd\.'calibration_version'"),
        (lambda d: d["cam0"]["robotd"].update(kalibr_fields="scaled"), "kalibr_fields 'scaled' is not one of"),
        (lambda d: d["cam0"]["robotd"].update(kalibr_fields="rectified-opencv"), r"missing key cam0\.robotd\.'raw'"),
        (lambda d: d["cam0"].update(robotd=[1]), "cam0.robotd must be a mapping"),
        (lambda d: d.update(robotd_calibration_version=2), "robotd_calibration_version 2 is not supported"),
        (lambda d: d.update(robotd_source="x"), "missing key 'robotd_calibration_version'"),
        (lambda d: d.update(cam2={}), "cam0 and cam1 only at the top level; found cam2"),
        (lambda d: d.pop("cam1"), "missing key 'cam1'"),
        (lambda d: d["cam0"].pop("intrinsics"), r"missing key cam0\.'intrinsics'"),
        (lambda d: d["cam1"].pop("T_cn_cnm1"), r"missing key cam1\.'T_cn_cnm1'"),
        (lambda d: d["cam0"].update(distortion_model="equidistant"), "equidistant"),
        (lambda d: d["cam0"].update(distortion_coeffs=[0.1, 0.2]), "distortion_coeffs must hold 4 or 5"),
        (lambda d: d["cam0"].update(camera_model="omni"), "omni"),
        (lambda d: d["cam1"].update(resolution=[320, 200]), "resolutions differ"),
        (lambda d: d["cam1"]["T_cn_cnm1"].__setitem__(3, [0, 0, 1, 1]), "last row"),
    ],
)
def test_errors_name_key_and_file(mutate, message: str, tmp_path: Path, rng: np.random.Generator) -> None:
    d = _doc(rng)
    mutate(d)
    p = tmp_path / "bad.yaml"
    p.write_text(yaml.safe_dump(d))
    with pytest.raises(CalibrationError, match=message) as ei:
        load_calibration(p)
    assert str(p) in str(ei.value)


def test_unreadable_files(tmp_path: Path) -> None:
    with pytest.raises(CalibrationError, match="cannot read"):
        load_calibration(tmp_path / "absent.yaml")
    (tmp_path / "x.yaml").write_text("cam0: [unclosed")
    with pytest.raises(CalibrationError, match="not valid YAML"):
        load_calibration(tmp_path / "x.yaml")
    with pytest.raises(CalibrationError, match="top level"):
        calibration_from_dict([1, 2], "list.yaml")
    with pytest.raises(CalibrationError, match="cannot write"):
        save_calibration(_calib(np.random.default_rng(0)), tmp_path / "no" / "dir.yaml")
