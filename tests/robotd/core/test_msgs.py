"""Border validation of the messages: expected vs got, never silently accepted NaN."""

from __future__ import annotations

import numpy as np
import pytest

from robotd.core.errors import InputError
from robotd.core.msgs import MotionIncrement, Observations, Odometry, PoseEstimate, StereoFrame


def test_stereo_frame_validation() -> None:
    img = np.zeros((4, 6), np.uint8)
    StereoFrame(1, 0, img, img)
    with pytest.raises(InputError, match="expected dtype uint8, got float64"):
        StereoFrame(1, 0, img.astype(float), img)
    with pytest.raises(InputError, match="one size"):
        StereoFrame(1, 0, img, np.zeros((4, 5), np.uint8))
    with pytest.raises(InputError, match="integer nanoseconds, got float"):
        StereoFrame(1.5, 0, img, img)  # type: ignore[arg-type]
    with pytest.raises(InputError, match=r"truth_T_world_robot: expected shape \(4, 4\)"):
        StereoFrame(1, 0, img, img, truth_T_world_robot=np.eye(3))
    assert StereoFrame(1, 0, img, img, exposure_ns=8_000_000).exposure_ns == 8_000_000
    for bad in (-1, 2.5, True):
        with pytest.raises(InputError, match="exposure_ns: expected integer nanoseconds >= 0"):
            StereoFrame(1, 0, img, img, exposure_ns=bad)  # type: ignore[arg-type]


def test_odometry_rejects_nan() -> None:
    with pytest.raises(InputError, match="Odometry.vel_R_mps: expected finite values, got 1 non-finite"):
        Odometry(0, np.array([np.nan, 0.0, 0.0]), np.zeros(3))
    with pytest.raises(InputError, match=r"expected shape \(3,\), got \(2,\)"):
        Odometry(0, np.zeros(2), np.zeros(3))


def test_motion_increment_checks_time_order() -> None:
    with pytest.raises(InputError, match="t1_ns >= t0_ns"):
        MotionIncrement(10, 5, np.zeros(3), np.zeros(3), np.eye(6))
    inc = MotionIncrement(0, 500_000_000, np.zeros(3), np.zeros(3), np.eye(6))
    assert inc.dt_s == pytest.approx(0.5)


def test_observations_shapes() -> None:
    obs = Observations.empty(3)
    assert obs.n == 0
    with pytest.raises(InputError, match=r"Observations.cov_R: expected shape \(2, 3, 3\)"):
        Observations(0, np.zeros((2, 3)), np.zeros((3, 3, 3)), np.zeros(2, np.int64), np.zeros(2, bool))
    with pytest.raises(InputError, match="integer dtype"):
        Observations(0, np.zeros((1, 3)), np.zeros((1, 3, 3)), np.zeros(1), np.zeros(1, bool))
    with pytest.raises(InputError, match="non-finite"):
        Observations(0, np.full((1, 3), np.inf), np.zeros((1, 3, 3)), np.zeros(1, np.int64), np.zeros(1, bool))


def test_observations_pixels_are_optional_and_checked() -> None:
    xyz, cov, ids, new = np.ones((2, 3)), np.tile(np.eye(3), (2, 1, 1)), np.arange(2), np.ones(2, bool)
    assert Observations(0, xyz, cov, ids, new).uv_px is None
    uv = np.array([[310.0, 300.0, 200.0], [100.0, 80.0, 50.0]])
    obs = Observations(0, xyz, cov, ids, new, uv)
    np.testing.assert_array_equal(obs.subset(np.array([1])).uv_px, uv[1:])
    with pytest.raises(InputError, match=r"Observations.uv_px: expected shape \(2, 3\)"):
        Observations(0, xyz, cov, ids, new, uv[:1])
    with pytest.raises(InputError, match="x_left > x_right"):
        Observations(0, xyz, cov, ids, new, uv[:, [1, 0, 2]])
    with pytest.raises(InputError, match="non-finite"):
        Observations(0, xyz, cov, ids, new, np.full((2, 3), np.nan))


def test_pose_estimate_shapes() -> None:
    PoseEstimate(0, np.zeros(3), np.zeros(3), np.eye(6))
    with pytest.raises(InputError, match=r"PoseEstimate.cov: expected shape \(6, 6\), got \(3, 3\)"):
        PoseEstimate(0, np.zeros(3), np.zeros(3), np.eye(3))
