"""EuRoC replay on the real micro cut: pairing, missing files, rectification, truth; and layout errors."""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from calib.camchain import load_calibration, save_calibration
from drivers import open_camera
from drivers.dataset import EurocCamera, read_euroc_truth
from robotd.core.errors import CalibrationError, DatasetError
from tests.conftest import data_path
from tests.support.tolerances import ROUNDOFF_ATOL


@pytest.fixture(scope="module")
def euroc_frames():
    root = data_path("euroc-v101-micro")
    with EurocCamera(f"euroc://{root}") as cam:
        return cam, list(cam.frames())


def test_euroc_pairs_by_timestamp_and_counts_missing_files(euroc_frames) -> None:
    cam, frames = euroc_frames
    assert len(frames) == 95
    assert cam.stats()["missing_files"] == 4  # cam1/data.csv lists 4 stamps without images
    t = np.array([f.t_ns for f in frames])
    assert t[0] == 1403715273262142976  # dataset time kept, exact to the nanosecond
    assert np.all(np.diff(t) > 0)
    assert np.median(np.diff(t)) == pytest.approx(50e6, rel=1e-3)
    assert all(f.rectified and f.left.shape == (480, 752) for f in frames)


def test_euroc_rectification_aligns_rows(euroc_frames) -> None:
    cam, frames = euroc_frames
    m = cam.rectified_model()
    assert m.baseline_m == pytest.approx(0.1101, abs=2e-4)
    orb = cv2.ORB.create(1000)
    dy = []
    for f in frames[::30]:
        kl, dl = orb.detectAndCompute(f.left, None)
        kr, dr = orb.detectAndCompute(f.right, None)
        for mt in cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(dl, dr):
            (xl, yl), (xr, yr) = kl[mt.queryIdx].pt, kr[mt.trainIdx].pt
            if mt.distance < 40 and 0 < xl - xr < 100:
                dy.append(yl - yr)
    assert len(dy) > 100
    assert abs(float(np.median(dy))) < 0.3  # docs/math.md §2.1 check


def test_euroc_truth_is_stationary_in_robot_frame(euroc_frames) -> None:
    _, frames = euroc_frames
    truth = [f.truth_T_world_robot for f in frames if f.truth_T_world_robot is not None]
    assert len(truth) == 74  # README: 74 ground-truth rows inside the image window
    np.testing.assert_allclose(truth[0], np.eye(4), atol=ROUNDOFF_ATOL)
    assert max(np.linalg.norm(T[:3, 3]) for T in truth) < 0.005  # stationary within 3.3 mm (README)


def test_euroc_truth_quaternion_convention_matches_gravity(shared_data) -> None:
    """The stored quaternion is the conjugate: with R_world_cam = R(q)ᵀ, world up agrees with the IMU."""
    root = shared_data("euroc-v101-micro")
    t, T_W_C = read_euroc_truth(root / "groundtruth_orbslam3" / "V101_GT_left_cam.txt")
    assert t.dtype == np.int64 and t[0] == 1403715274312143104
    imu = np.loadtxt(root / "mav0" / "imu0" / "data.csv", delimiter=",", skiprows=1, max_rows=200)
    up_B = imu[:, 4:7].mean(0)  # at rest the accelerometer reads +g along world up
    up_B /= np.linalg.norm(up_B)
    text = (root / "mav0" / "cam0" / "sensor.yaml").read_text().replace("%YAML:1.0", "")
    T_BS = np.array(yaml.safe_load(text)["T_BS"]["data"]).reshape(4, 4)
    up_C = T_BS[:3, :3].T @ up_B
    world_up_in_cam = T_W_C[0][:3, :3].T @ np.array([0.0, 0.0, 1.0])  # Vicon world is z-up
    assert np.degrees(np.arccos(np.clip(up_C @ world_up_in_cam, -1, 1))) < 3.0


def test_euroc_layout_errors(tmp_path: Path, shared_data) -> None:
    with pytest.raises(DatasetError, match="not a directory"):
        open_camera(f"euroc://{tmp_path / 'none'}")
    (tmp_path / "a" / "mav0" / "cam0").mkdir(parents=True)
    with pytest.raises(DatasetError, match="cam1"):
        open_camera(f"euroc://{tmp_path / 'a'}")
    # a copy without cam1's sensor.yaml
    src = shared_data("euroc-v101-micro")
    dst = tmp_path / "b" / "mav0"
    for cam in ("cam0", "cam1"):
        (dst / cam).mkdir(parents=True)
        shutil.copy(src / "mav0" / cam / "data.csv", dst / cam / "data.csv")
    shutil.copy(src / "mav0" / "cam0" / "sensor.yaml", dst / "cam0" / "sensor.yaml")
    with pytest.raises(DatasetError, match=r"cam1/sensor.yaml"):
        open_camera(f"euroc://{tmp_path / 'b'}")


# -- a calibration file (camera.calibration) instead of sensor.yaml ---------------------------------


def test_euroc_rectifies_with_a_calibration_file_instead_of_sensor_yaml(euroc_frames, tmp_path: Path) -> None:
    """The folder's own rig written as the camchain robotd-calib writes, then read back: the same
    frames bit for bit. A file with another rig (the principal point moved, the baseline 10 %
    longer) changes the images and the rectified rig: it, not sensor.yaml, is what rectifies."""
    cam, frames = euroc_frames
    root = data_path("euroc-v101-micro")
    same = load_calibration(save_calibration(cam.calibration, tmp_path / "euroc.yaml"))
    with open_camera(f"euroc://{root}?stop=3", calibration=same) as c:
        assert c.rectified_model() == cam.rectified_model()
        for f, g in zip(c.frames(), frames[:3], strict=True):
            assert np.array_equal(f.left, g.left) and np.array_equal(f.right, g.right)
    K = same.K_left.copy()
    K[0, 2] += 6.0
    other = dataclasses.replace(same, K_left=K, T=same.T * 1.1)
    moved = load_calibration(save_calibration(other, tmp_path / "moved.yaml"))
    with open_camera(f"euroc://{root}?stop=1", calibration=moved) as c:
        m = c.rectified_model()
        assert m.baseline_m == pytest.approx(1.1 * cam.rectified_model().baseline_m, rel=1e-9)
        assert not np.array_equal(next(iter(c.frames())).left, frames[0].left)
        assert c.calibration is moved


def test_euroc_refuses_a_calibration_file_for_another_image_size(euroc_frames) -> None:
    cam, _ = euroc_frames
    small = dataclasses.replace(cam.calibration, image_size=(640, 480))
    with pytest.raises(CalibrationError, match=r"for 640x480 images but the camera gives 752x480"):
        open_camera(f"euroc://{data_path('euroc-v101-micro')}", calibration=small)
