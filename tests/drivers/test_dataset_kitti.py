"""KITTI replay: layout reading, dataset time, selection, pacing, truth in the robot frame, errors."""

from __future__ import annotations

import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from drivers import StereoCamera, open_camera
from drivers.dataset import KittiCamera, kitti_truth_to_robot, open_kitti_vehicle
from robotd.core.errors import DatasetError, DriverError
from robotd.core.geometry import R_ROBOT_OPTICAL, pose6_to_T, se3
from tests.support.tolerances import CONDITIONED_ATOL, ROUNDOFF_ATOL

F, CX, CY, B = 700.0, 16.0, 8.0, 0.5


def make_kitti(root: Path, n: int = 5, labelled: bool = True, times: bool = False, poses: bool = True) -> Path:
    """A tiny synthetic sequence in the KITTI odometry layout; the camera moves 1 m/frame along z_optical."""
    (root / "image_0").mkdir(parents=True)
    (root / "image_1").mkdir()
    rng = np.random.default_rng(3)
    for i in range(n):
        cv2.imwrite(str(root / "image_0" / f"{i:06d}.png"), rng.integers(0, 255, (16, 32), dtype=np.uint8))
        cv2.imwrite(str(root / "image_1" / f"{i:06d}.png"), rng.integers(0, 255, (16, 32), dtype=np.uint8))
    P0 = f"{F} 0 {CX} 0 0 {F} {CY} 0 0 0 1 0"
    P1 = f"{F} 0 {CX} {-F * B} 0 {F} {CY} 0 0 0 1 0"
    (root / "calib.txt").write_text(f"P0: {P0}\nP1: {P1}\n" if labelled else f"{P0}\n{P1}\n")
    if times:
        (root / "times.txt").write_text("".join(f"{0.05 * i:.6e}\n" for i in range(n)))
    if poses:
        (root / "poses.txt").write_text("".join(f"1 0 0 0 0 1 0 0 0 0 1 {float(i)}\n" for i in range(n)))
    return root


def test_kitti_synthetic_layout_times_and_truth(tmp_path: Path) -> None:
    root = make_kitti(tmp_path / "seq", labelled=False)
    with open_camera(f"kitti://{root}") as cam:
        assert isinstance(cam, StereoCamera)
        m = cam.rectified_model()
        assert (m.f_px, m.px, m.py, m.width, m.height) == (F, CX, CY, 32, 16)
        assert m.baseline_m == pytest.approx(B)
        frames = list(cam.frames())
    assert [f.seq for f in frames] == list(range(5))
    assert [f.t_ns for f in frames] == [i * 100_000_000 for i in range(5)]  # 0.1 s × index without times.txt
    assert all(f.rectified and f.left.dtype == np.uint8 for f in frames)
    # forward along the optical axis is +x in FRD; the baseline-centre origin does not move sideways
    for i, f in enumerate(frames):
        assert f.truth_T_world_robot is not None
        np.testing.assert_allclose(f.truth_T_world_robot, se3(np.eye(3), [float(i), 0.0, 0.0]), atol=ROUNDOFF_ATOL)


def test_kitti_times_txt_and_selection(tmp_path: Path) -> None:
    root = make_kitti(tmp_path / "seq", n=7, times=True)
    cam = open_camera(f"kitti://{root}?start=1&stop=6&stride=2")
    with cam:
        frames = list(cam.frames())
    assert [f.seq for f in frames] == [1, 3, 5]
    assert [f.t_ns for f in frames] == [50_000_000, 150_000_000, 250_000_000]


def test_kitti_realtime_pacing(tmp_path: Path) -> None:
    root = make_kitti(tmp_path / "seq", n=5)
    t0 = time.monotonic()
    with KittiCamera(f"kitti://{root}", realtime=True, speed=10.0) as cam:
        n = sum(1 for _ in cam.frames())
    elapsed = time.monotonic() - t0
    assert n == 5
    assert elapsed >= 0.4 * 0.1 - 0.005  # 4 intervals of 0.1 s at 10× speed


def test_truth_conversion_keeps_the_baseline_centre(rng: np.random.Generator) -> None:
    """The robot origin is the baseline centre: its world position follows from the left-camera pose."""
    b = 0.54
    for _ in range(20):
        T_C0_C = pose6_to_T(np.concatenate([rng.normal(0, 3, 3), rng.normal(0, 0.5, 3)]))
        T = kitti_truth_to_robot(T_C0_C, b)
        centre_C0 = T_C0_C[:3, :3] @ np.array([b / 2, 0, 0]) + T_C0_C[:3, 3]
        np.testing.assert_allclose(T[:3, 3], R_ROBOT_OPTICAL @ centre_C0 - np.array([0, b / 2, 0]), atol=ROUNDOFF_ATOL)
        np.testing.assert_allclose(T[:3, :3], R_ROBOT_OPTICAL @ T_C0_C[:3, :3] @ R_ROBOT_OPTICAL.T, atol=ROUNDOFF_ATOL)


def test_kitti_gt_odometry_is_marked_and_visual_only_is_empty(tmp_path: Path) -> None:
    root = make_kitti(tmp_path / "seq", n=4)
    assert list(open_kitti_vehicle(f"kitti://{root}").odometry()) == []
    assert open_kitti_vehicle(f"kitti://{root}").autopilot is None  # replay takes no pose
    odo = list(open_kitti_vehicle(f"kitti://{root}?gt_odometry=1&sigma_vel_mps=0&sigma_rate_radps=0").odometry())
    assert len(odo) == 3 and all(o.source == "gt-synthetic" for o in odo)
    for o in odo:  # 1 m per 0.1 s forward
        np.testing.assert_allclose(o.vel_R_mps, [10.0, 0.0, 0.0], atol=CONDITIONED_ATOL)
        np.testing.assert_allclose(o.rate_R_radps, 0.0, atol=CONDITIONED_ATOL)


def test_kitti_errors_name_the_path(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="is not a directory"):
        open_camera(f"kitti://{tmp_path / 'nope'}")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match=r"image_l/ \+ image_r/"):
        open_camera(f"kitti://{tmp_path / 'empty'}")
    root = make_kitti(tmp_path / "seq")
    (root / "calib.txt").write_text("P0: 1 2 3\n")
    with pytest.raises(DatasetError, match="calib.txt"):
        open_camera(f"kitti://{root}")
    with pytest.raises(DriverError, match="unknown option"):
        open_camera(f"kitti://{root}?bogus=1")
    with pytest.raises(DriverError, match="stride"):
        open_camera(f"kitti://{root}?stride=0")


def test_kitti_real_sequence(shared_data) -> None:
    root = shared_data("kitti-seq1")
    with open_camera(f"kitti://{root}?stride=10") as cam:
        m = cam.rectified_model()
        frames = list(cam.frames())
    assert m.f_px == pytest.approx(707.0912) and m.baseline_m == pytest.approx(0.5372, abs=1e-4)
    assert [f.seq for f in frames] == [0, 10, 20, 30, 40, 50]
    assert frames[0].left.shape == (370, 1226)
    T_end = frames[-1].truth_T_world_robot
    assert T_end is not None
    # README: 59.9 m almost straight ahead; in FRD that is +x with small y, z
    assert 58.0 < T_end[0, 3] < 61.0 and abs(T_end[1, 3]) < 2.0 and abs(T_end[2, 3]) < 2.0


def test_kitti_drop_leaves_out_a_range_of_frames_as_a_stall_would(tmp_path: Path) -> None:
    root = make_kitti(tmp_path / "seq", n=9)
    with open_camera(f"kitti://{root}?drop=2-6") as cam:
        assert [f.seq for f in cam.frames()] == [0, 1, 6, 7, 8]
        assert cam.stats()["selected"] == 5
    for bad in ("6-2", "3", "a-b", "-1-4"):
        with pytest.raises(DriverError, match="drop"):
            open_camera(f"kitti://{root}?drop={bad}")
