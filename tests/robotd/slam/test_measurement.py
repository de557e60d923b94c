"""Re-observation covariance evaluated at the filter's prediction (covariance_at_prediction)."""

from __future__ import annotations

import numpy as np

from robotd.core.geometry import euler_to_R
from robotd.core.msgs import LandmarkMap, Observations, PoseEstimate
from robotd.core.stereo import covariance_from_points
from robotd.research.batch import solve_sim
from robotd.research.evaluate import ate, poses_to_T
from robotd.research.experiments import run_filter
from robotd.research.landmark_sim import SimConfig, simulate
from robotd.slam.measurement import covariance_at_prediction
from tests.support.tolerances import ROUNDOFF_RTOL

F, B, SX, SY = 430.0, 0.0755, 0.5, 0.5 / np.sqrt(2.0)


def _pose(xyz, rpy) -> PoseEstimate:
    return PoseEstimate(0, np.asarray(xyz, float), np.asarray(rpy, float), np.eye(6))


def test_exact_prediction_gives_the_covariance_at_the_true_point() -> None:
    rng = np.random.default_rng(0)
    m = np.column_stack([rng.uniform(2, 6, 8), rng.uniform(-1.5, 1.5, 8), rng.uniform(-1, 1, 8)]) + np.array(
        [2.0, 1.0, 0.0]
    )
    ids = np.arange(8, dtype=np.int64) * 7 + 3
    pose = _pose([2.0, 1.0, 0.0], [0.02, -0.03, 0.4])

    z_true = (m - pose.xyz_W_m) @ euler_to_R(pose.rpy_rad)
    z_meas = z_true * (1 + 0.1 * rng.standard_normal((8, 1)))  # noisy depths along the ray
    Q_meas = covariance_from_points(z_meas, F, B, SX, SY)
    is_new = np.zeros(8, bool)
    is_new[[1, 5]] = True
    obs = Observations(0, z_meas, Q_meas, ids, is_new)
    lm = LandmarkMap(ids[::-1].copy(), m[::-1].copy(), np.tile(np.eye(3), (8, 1, 1)))  # any order
    out = covariance_at_prediction(obs, pose, lm, F, B, SX, SY, inflation=2.0)
    old = ~is_new
    np.testing.assert_allclose(
        out.cov_R[old], 2.0 * covariance_from_points(z_true[old], F, B, SX, SY), rtol=ROUNDOFF_RTOL
    )
    np.testing.assert_array_equal(out.cov_R[is_new], Q_meas[is_new])  # new landmarks keep Q(z)
    np.testing.assert_array_equal(out.xyz_R_m, obs.xyz_R_m)  # the measurement itself is unchanged
    np.testing.assert_array_equal(obs.cov_R, Q_meas)  # input not modified


def test_unknown_ids_keep_their_covariance_and_depth_is_clamped() -> None:
    z = np.array([[3.0, 0.2, 0.1], [2.0, -0.3, 0.0]])
    Q = covariance_from_points(z, F, B, SX, SY)
    obs = Observations(0, z, Q, np.array([1, 2], np.int64), np.zeros(2, bool))
    behind = LandmarkMap(np.array([1], np.int64), np.array([[-1.0, 0.0, 0.0]]), np.eye(3)[None])
    out = covariance_at_prediction(obs, _pose([0, 0, 0], [0, 0, 0]), behind, F, B, SX, SY, min_depth_m=0.3)
    assert np.all(np.isfinite(out.cov_R)) and np.linalg.eigvalsh(out.cov_R[0]).min() > 0
    np.testing.assert_array_equal(out.cov_R[1], Q[1])  # id 2 is not in the map


def test_predicted_covariance_removes_most_of_the_stereo_bias() -> None:
    """docs/math.md §12's stereo noise with Q from the noisy pixels biases every estimator; Q at the prediction
    makes EKF SLAM and the batch solution several times more accurate on the same data."""
    cfg = SimConfig(dim=2, trajectory="loop", path_length_m=20.0, landmark_density_per_m2=0.5)
    for seed in (0, 1):
        run = simulate(cfg, np.random.default_rng(seed))
        gt = poses_to_T(run.poses_W)
        b = {
            c: ate(poses_to_T(solve_sim(run, cov_at=c).poses_W), gt, planar=True)["ate_rmse_m"]
            for c in ("measured", "predicted")
        }
        e = {c: run_filter(run, "ekf", seed, cov_at=c).ate_rmse_m for c in ("measured", "predicted")}
        assert b["predicted"] < 0.5 * b["measured"], b
        assert e["predicted"] < 0.7 * e["measured"], e


def test_non_finite_prediction_keeps_the_measured_covariance() -> None:
    """NaN cannot reach it (the message types refuse it), but an absurd map point can overflow."""
    z = np.array([[3.0, 0.2, 0.1], [2.0, -0.3, 0.0]])
    Q = covariance_from_points(z, F, B, SX, SY)
    obs = Observations(0, z, Q, np.array([1, 2], np.int64), np.zeros(2, bool))
    lm = LandmarkMap(
        np.array([1, 2], np.int64), np.array([[1e200, 0.0, 0.0], [4.0, 0.0, 0.0]]), np.tile(np.eye(3), (2, 1, 1))
    )
    out = covariance_at_prediction(obs, _pose([0, 0, 0], [0, 0, 0]), lm, F, B, SX, SY)
    np.testing.assert_array_equal(out.cov_R[0], Q[0])  # overflowed prediction: measured Q kept
    assert np.all(np.isfinite(out.cov_R))
    assert not np.allclose(out.cov_R[1], Q[1])  # the other one is re-evaluated


def test_planar_keeps_the_measured_height() -> None:
    z = np.array([[3.0, 0.2, 0.4]])
    obs = Observations(0, z, covariance_from_points(z, F, B, SX, SY), np.array([5], np.int64), np.zeros(1, bool))
    lm = LandmarkMap(np.array([5], np.int64), np.array([[3.0, 0.2, 0.0]]), np.eye(3)[None])
    out = covariance_at_prediction(obs, _pose([0, 0, 0], [0, 0, 0]), lm, F, B, SX, SY, planar=True)
    np.testing.assert_allclose(out.cov_R[0], covariance_from_points(z, F, B, SX, SY)[0], rtol=ROUNDOFF_RTOL)
    flat = covariance_at_prediction(obs, _pose([0, 0, 0], [0, 0, 0]), lm, F, B, SX, SY)
    assert not np.allclose(flat.cov_R[0], out.cov_R[0])  # 3D: the map's height 0 is used
