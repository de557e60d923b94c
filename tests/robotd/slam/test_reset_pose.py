"""reset_pose (relocalisation): every filter puts its pose where told and keeps tracking its map."""

from __future__ import annotations

import numpy as np
import pytest

from robotd.slam.factory import make_estimator
from robotd.slam.params import SlamParams
from tests.support.slam_world import World
from tests.support.tolerances import ROUNDOFF_ATOL


def _vec(est) -> np.ndarray:
    p = est.estimate()
    return np.r_[p.xyz_W_m[:2], p.rpy_rad[2]] if est.dim == 2 else np.r_[p.xyz_W_m, p.rpy_rad]


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("name", ["ekf", "fastslam1", "fastslam2"])
def test_reset_pose_then_track_from_there(name: str, dim: int) -> None:
    world = World(dim, np.random.default_rng(1), sigma_z=0.02, sigma_odo=0.005)
    est = make_estimator(SlamParams(filter=name, dim=dim, n_particles=50), np.random.default_rng(2))
    est.update(world.observe())
    for _ in range(15):
        est.predict(world.step())
        est.update(world.observe())
    # the robot moves 12 steps while the filter hears nothing (robotd was down), then is found
    for _ in range(12):
        world.step()
    x = world.pose()
    assert np.linalg.norm(_vec(est)[:2] - x[:2]) > 1.5  # the filter's pose is stale
    dx = 3 if dim == 2 else 6
    est.reset_pose(x, None if name == "ekf" else np.diag([1e-4] * dx))
    assert np.linalg.norm(_vec(est)[:2] - x[:2]) < 0.03
    if name == "ekf":
        S = est.covariance()
        assert np.all(S[:dx, dx:] == 0) and np.all(S[dx:, :dx] == 0)  # no stale correlations
        assert np.linalg.eigvalsh(S).min() > -ROUNDOFF_ATOL
    else:
        w = est.weights()
        np.testing.assert_allclose(w, 1.0 / w.size)
    n_lm = est.landmarks().n
    for _ in range(5):
        est.predict(world.step())
        est.update(world.observe())
    assert np.linalg.norm(_vec(est)[:2] - world.pose()[:2]) < 0.1
    assert est.landmarks().n >= n_lm  # the map was kept


@pytest.mark.parametrize("name", ["ekf", "fastslam2"])
def test_reset_pose_refuses_bad_input_and_changes_nothing(name: str) -> None:
    from robotd.core.errors import InputError

    world = World(3, np.random.default_rng(1), sigma_z=0.02)
    est = make_estimator(SlamParams(filter=name, dim=3, n_particles=20), np.random.default_rng(2))
    est.update(world.observe())
    before = _vec(est)
    bad = [
        (np.r_[1.0, np.nan, 0, 0, 0, 0], None, "finite"),
        (np.zeros(3), None, r"shape \(6,\)"),
        (np.zeros(6), np.eye(3), r"shape \(6, 6\)"),
        (np.zeros(6), -np.eye(6), "positive semi-definite"),
        (np.zeros(6), np.full((6, 6), np.inf), "finite"),
    ]
    for x, cov, msg in bad:
        with pytest.raises(InputError, match=msg):
            est.reset_pose(x, cov)
        np.testing.assert_array_equal(_vec(est), before)


def test_pose_from_a_similarity_that_is_not_finite_is_none() -> None:
    from robotd.core.outliers import OutlierResult
    from robotd.pipeline.relocalise import pose_from_similarity

    def res(s, R, t):
        return OutlierResult(
            "similarity_mahalanobis", np.ones(3, bool), True, 3, 3, 1, 0, 0, 0.0, 1.0, np.zeros(3), s, R, t
        )

    assert pose_from_similarity(res(1.0, np.eye(3), np.array([np.nan, 0, 0]))) is None
    assert pose_from_similarity(res(0.0, np.eye(3), np.zeros(3))) is None
    assert pose_from_similarity(res(None, None, None)) is None
    x = pose_from_similarity(res(1.0, np.eye(3), np.array([-1.0, 2.0, 0.0])))  # world → robot shift
    np.testing.assert_allclose(x, [1.0, -2.0, 0.0, 0.0, 0.0, 0.0], atol=ROUNDOFF_ATOL)
