"""The direction of gravity as a measurement of roll and pitch (docs/slam.md "Gravity"): the
model's Jacobian, each 3D filter's update, its gate and its input checks."""

from __future__ import annotations

import numpy as np
import pytest

from robotd.core.errors import InputError
from robotd.core.geometry import euler_to_R, numerical_jacobian
from robotd.core.msgs import MotionIncrement, Odometry
from robotd.slam import models as md
from robotd.slam.factory import make_estimator
from robotd.slam.params import SlamParams
from tests.support.tolerances import CENTRAL_DIFF_ATOL, ROUNDOFF_ATOL

FILTERS = ("ekf", "fastslam1", "fastslam2")
DOWN = np.array([0.0, 0.0, 1.0])


@pytest.mark.parametrize(
    "x, g_W",
    [
        ([1.0, -2.0, 0.3, 0.2, -0.4, 2.5], DOWN),
        ([0.0, 0.0, 0.0, -1.1, 0.7, -3.0], DOWN),
        # a world that is not level (the rover started on a slope): yaw matters too
        ([3.0, 1.0, -0.5, 0.1, 0.05, 0.9], np.array([0.2, -0.1, 0.97]) / np.linalg.norm([0.2, -0.1, 0.97])),
    ],
)
def test_gravity_model_and_its_jacobian(x: list[float], g_W: np.ndarray) -> None:
    xa = np.asarray(x)
    h, H = md.gravity3d(xa[None], g_W)
    np.testing.assert_allclose(h[0], euler_to_R(xa[3:]).T @ g_W, atol=ROUNDOFF_ATOL)
    Hn = numerical_jacobian(lambda a: md.gravity3d(a[None], g_W)[0][0], xa)
    np.testing.assert_allclose(H[0], Hn, atol=CENTRAL_DIFF_ATOL)
    np.testing.assert_array_equal(H[0][:, :3], 0.0)  # position does not enter


def _still(t0: int, t1: int) -> MotionIncrement:
    return MotionIncrement(t0, t1, np.zeros(3), np.zeros(3), np.diag([1e-6] * 3 + [1e-6] * 3))


def _tilted_filter(name: str) -> tuple[object, np.ndarray]:
    est = make_estimator(SlamParams(filter=name, dim=3, n_particles=200), np.random.default_rng(3))
    x0 = np.array([1.0, 2.0, 0.0, 0.15, -0.12, 0.8])  # 8.6° and -6.9° off level
    est.reset_pose(x0, np.diag([1e-4] * 3 + [0.1**2] * 3))
    return est, x0


@pytest.mark.parametrize("name", FILTERS)
def test_each_filter_levels_a_tilted_pose_and_keeps_position_and_yaw(name: str) -> None:
    est, x0 = _tilted_filter(name)
    level = np.array([0.0, 0.0, x0[5]])
    g_R = euler_to_R(level).T @ DOWN  # what the IMU of a level rover measures
    for k in range(40):
        est.predict(_still(k * 100_000_000, (k + 1) * 100_000_000))
        fused, nis = est.update_gravity(g_R, DOWN, 0.01)
        assert fused and np.isfinite(nis)
    e = est.estimate()
    # FastSLAM 1.0 only reweights its samples (nothing resamples here): it can get no nearer than
    # its particles lie, 200 of them spread over 0.1 rad in roll and pitch
    bound = np.radians(2.5 if name == "fastslam1" else 1.0)
    assert abs(e.rpy_rad[0]) < bound and abs(e.rpy_rad[1]) < bound
    # yaw is not observed by gravity in a level world; position not at all
    assert abs(e.rpy_rad[2] - x0[5]) < 0.3
    np.testing.assert_allclose(e.xyz_W_m, x0[:3], atol=0.05)


@pytest.mark.parametrize("name", FILTERS)
def test_a_measurement_far_outside_the_gate_changes_nothing(name: str) -> None:
    est, _ = _tilted_filter(name)
    est.predict(_still(0, 100_000_000))
    before = est.estimate()
    g_R = euler_to_R(np.array([0.0, 1.2, 0.0])).T @ DOWN  # 69° of pitch away from 0.1 rad of spread
    fused, nis = est.update_gravity(g_R, DOWN, 0.01)
    assert not fused and nis > SlamParams().gate_chi2_2d
    after = est.estimate()
    np.testing.assert_array_equal(after.xyz_W_m, before.xyz_W_m)
    np.testing.assert_array_equal(after.rpy_rad, before.rpy_rad)


@pytest.mark.parametrize("name", FILTERS)
@pytest.mark.parametrize(
    "g_R, sigma, text",
    [
        (np.array([0.0, np.nan, 1.0]), 0.01, "g_R must be a finite 3-vector"),
        (np.array([0.0, 0.0, 3.0]), 0.01, "norm about 1"),
        (DOWN, 0.0, "sigma_rad must be in"),
        (DOWN, float("inf"), "sigma_rad must be in"),
    ],
)
def test_bad_gravity_input_is_refused_with_its_reason(name: str, g_R: np.ndarray, sigma: float, text: str) -> None:
    est, _ = _tilted_filter(name)
    with pytest.raises(InputError, match=text):
        est.update_gravity(g_R, DOWN, sigma)


@pytest.mark.parametrize("name", FILTERS)
def test_a_2d_filter_refuses_gravity(name: str) -> None:
    est = make_estimator(SlamParams(filter=name, dim=2), np.random.default_rng(0))
    with pytest.raises(InputError, match="3D filter"):
        est.update_gravity(DOWN, DOWN, 0.01)


def test_odometry_and_increment_check_their_gravity() -> None:
    t = 1_000
    with pytest.raises(InputError, match="gravity_R"):
        Odometry(t, np.zeros(3), np.zeros(3), "x", None, np.array([0.0, 0.0, 0.1]), 0.01)
    with pytest.raises(InputError, match="gravity_sigma_rad"):
        Odometry(t, np.zeros(3), np.zeros(3), "x", None, DOWN, 0.0)
    with pytest.raises(InputError, match="gravity_sigma_rad"):
        MotionIncrement(0, t, np.zeros(3), np.zeros(3), np.zeros((6, 6)), DOWN, float("nan"))
    Odometry(t, np.zeros(3), np.zeros(3), "x", None, DOWN, 0.01)  # valid


@pytest.mark.parametrize("name", FILTERS)
def test_reopen_lets_gravity_correct_a_filter_too_sure_of_a_wrong_tilt(name: str) -> None:
    """An unmodelled gyro bias leaves the filter sure of a wrong tilt: the gate then refuses the
    right measurement for good. Reopened, roll and pitch take it (robotd.pipeline.stages.attitude's
    Attitude.fuse_gravity does so after GRAVITY_REOPEN_S of refusals)."""
    est = make_estimator(SlamParams(filter=name, dim=3, n_particles=200), np.random.default_rng(5))
    x0 = np.array([0.0, 0.0, 0.0, 0.12, -0.1, 0.3])  # 6.9° and -5.7° off level, σ 0.06°
    est.reset_pose(x0, np.diag([1e-4] * 3 + [1e-3**2] * 3))
    g_R = euler_to_R(np.array([0.0, 0.0, x0[5]])).T @ DOWN
    est.predict(_still(0, 100_000_000))
    fused, _ = est.update_gravity(g_R, DOWN, 0.01)
    assert not fused
    fused, nis = est.update_gravity(g_R, DOWN, 0.01, reopen=True)
    assert fused and nis > SlamParams().gate_chi2_2d
    rpy = est.estimate().rpy_rad
    assert np.hypot(rpy[0], rpy[1]) < np.radians(1.5), np.degrees(rpy)


def _turning(t_s: float, tilt_W: np.ndarray | None = None) -> np.ndarray:
    """R_world_robot of a level rover turning at 0.5 rad/s, the world optionally tilted by a
    small rotation vector ``tilt_W`` (an error of the filter's attitude, fixed in the world)."""
    from robotd.core.geometry import so3_exp

    R = euler_to_R(np.array([0.0, 0.0, 0.5 * t_s]))
    return R if tilt_W is None else so3_exp(tilt_W) @ R


def test_gravity_bias_fixed_in_the_robot_is_learnt_as_the_rover_turns() -> None:
    from robotd.pipeline.stages.attitude import GravityBias

    b = np.array([0.005, -0.004, 0.0])  # a tilted IMU: 0.37° across the vertical
    gb = GravityBias(60.0)
    for k in range(3000):  # 300 s at 10 Hz
        R = _turning(0.1 * k)
        g_true = R.T @ DOWN
        g_meas = (g_true + b) / np.linalg.norm(g_true + b)
        corrected = gb.correct(g_meas, g_true, k * 100_000_000)  # the filter has the true attitude
    np.testing.assert_allclose(gb.b, b, atol=0.1 * np.linalg.norm(b))
    assert np.degrees(np.arccos(np.clip(corrected @ g_true, -1, 1))) < 0.05


def test_gravity_bias_leaves_a_world_fixed_attitude_error_to_the_filter() -> None:
    from robotd.pipeline.stages.attitude import GravityBias

    tilt = np.array([0.01, -0.008, 0.0])  # the filter's world is 0.73° off the vertical
    gb = GravityBias(60.0)
    for k in range(3000):
        g_meas = _turning(0.1 * k).T @ DOWN  # an unbiased IMU
        g_est = _turning(0.1 * k, tilt).T @ DOWN
        gb.correct(g_meas, g_est, k * 100_000_000)
    # the residual turns in the robot frame: it averages out instead of being taken for a bias
    assert np.linalg.norm(gb.b) < 0.1 * np.linalg.norm(tilt)


def test_gravity_bias_off_is_the_identity() -> None:
    from robotd.pipeline.stages.attitude import GravityBias

    g = np.array([0.1, 0.0, 1.0]) / np.linalg.norm([0.1, 0.0, 1.0])
    gb = GravityBias(0.0)
    for k in range(10):
        assert gb.correct(g, DOWN, k) is g


def test_gravity_leaves_the_heading_alone_in_a_tilted_world() -> None:
    """g_W comes from one measurement, its noise and the sensor's bias included: in a world whose
    z is not the vertical its yaw column would be false heading information at every frame. (The
    EKF, deterministic; FastSLAM's particles evaluate h at their mean heading, models.gravity3d_tilt.)"""
    g_W = euler_to_R(np.array([0.05, -0.04, 0.0])) @ DOWN  # the world 3.7° off the vertical
    est = make_estimator(SlamParams(filter="ekf", dim=3), np.random.default_rng(2))
    x0 = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.4])  # heading 0.4 rad off the truth's 0
    est.reset_pose(x0, np.diag([1e-4] * 3 + [0.01**2, 0.01**2, 0.1**2]))
    g_R = euler_to_R(np.zeros(3)).T @ g_W  # the truth: level in the world, heading 0
    for k in range(50):
        est.predict(_still(k * 100_000_000, (k + 1) * 100_000_000))
        est.update_gravity(g_R, g_W, 0.01)
    # the full model's yaw column moves the heading by a quarter of the way to 0 (measured 0.4 -> 0.29)
    assert abs(est.estimate().rpy_rad[2] - x0[5]) < 0.03
    _, H = md.gravity3d_tilt(x0[None], g_W)
    np.testing.assert_array_equal(H[0][:, 5], 0.0)


def test_gravity_bias_is_capped_at_a_mounting_error() -> None:
    from robotd.pipeline.stages.attitude import GRAVITY_BIAS_MAX_RAD, GravityBias

    gb = GravityBias(60.0)
    g_meas = euler_to_R(np.array([0.2, 0.0, 0.0])).T @ DOWN  # 11° off what the filter expects
    for k in range(3000):
        gb.correct(g_meas, DOWN, k * 100_000_000)
    assert np.linalg.norm(gb.b) == pytest.approx(GRAVITY_BIAS_MAX_RAD)
