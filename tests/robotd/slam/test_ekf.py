"""EKF SLAM: covariance health, χ² gate, augmentation against a dense reference, pruning."""

from __future__ import annotations

import numpy as np
import pytest

from robotd.core.msgs import Observations
from robotd.slam import models as md
from robotd.slam.ekf import EkfSlam
from robotd.slam.factory import make_estimator
from robotd.slam.params import SlamParams
from tests.support.slam_world import World
from tests.support.tolerances import CONDITIONED_ATOL, ROUNDOFF_ATOL, ULP_ATOL


@pytest.mark.parametrize("dim", [2, 3])
def test_covariance_stays_symmetric_psd(dim: int) -> None:
    world = World(dim, np.random.default_rng(0), sigma_z=0.03, sigma_odo=0.01)
    est = make_estimator(SlamParams(filter="ekf", dim=dim), np.random.default_rng(0))
    assert isinstance(est, EkfSlam)
    est.update(world.observe())
    for _ in range(30):
        est.predict(world.step())
        est.update(world.observe())
        S = est.covariance()
        assert np.array_equal(S, S.T)
        assert np.linalg.eigvalsh(S).min() > -ROUNDOFF_ATOL
    assert est.landmarks().n > 10


def test_update_matches_dense_joseph_ekf() -> None:
    """The O(n²) sparse-H Joseph update equals the textbook dense one (docs/math.md §8)."""
    world = World(3, np.random.default_rng(1), sigma_z=0.03, sigma_odo=0.01)
    est = make_estimator(SlamParams(filter="ekf", dim=3, prune_enabled=False), np.random.default_rng(0))
    assert isinstance(est, EkfSlam)
    est.update(world.observe())
    est.predict(world.step())
    obs = world.observe()
    old = ~obs.is_new
    i = int(np.flatnonzero(old)[0])
    one = Observations(
        obs.t_ns, obs.xyz_R_m[i : i + 1], obs.cov_R[i : i + 1], obs.ids[i : i + 1], obs.is_new[i : i + 1]
    )
    mu, Sig = est.mu.copy(), est.Sigma.copy()
    j = 6 + 3 * est.book.id_to_slot[int(obs.ids[i])]
    z, Hx, Hm = md.meas3d(mu[None, :6], mu[None, j : j + 3])
    H = np.zeros((3, mu.size))
    H[:, :6], H[:, j : j + 3] = Hx[0], Hm[0]
    Q = obs.cov_R[i]
    Psi = H @ Sig @ H.T + Q
    K = Sig @ H.T @ np.linalg.inv(Psi)
    mu_ref = mu + K @ (obs.xyz_R_m[i] - z[0])
    IKH = np.eye(mu.size) - K @ H
    Sig_ref = IKH @ Sig @ IKH.T + K @ Q @ K.T
    rep = est.update(one)
    assert rep.n_updated == 1
    # through the inverse of Ψ: CONDITIONED_ATOL (1e-10 before; measured 1.4e-16)
    np.testing.assert_allclose(est.mu, mu_ref, atol=CONDITIONED_ATOL)
    np.testing.assert_allclose(est.Sigma, Sig_ref, atol=CONDITIONED_ATOL)


def test_gate_counts_outliers() -> None:
    world = World(2, np.random.default_rng(2), sigma_z=0.02, sigma_odo=0.005)
    est = make_estimator(SlamParams(filter="ekf", dim=2, prune_enabled=False), np.random.default_rng(0))
    est.update(world.observe())
    est.predict(world.step())
    obs = world.observe()
    z = obs.xyz_R_m.copy()
    old = np.flatnonzero(~obs.is_new)
    z[old[:2], 0] += 2.0  # two gross mismatches
    rep = est.update(Observations(obs.t_ns, z, obs.cov_R, obs.ids, obs.is_new))
    assert rep.n_gated == 2
    assert rep.n_updated == old.size - 2
    with pytest.raises(Exception, match="slam.gate|expected"):
        SlamParams(gate_chi2_2d=float("nan"))


def test_augmentation_cross_covariance() -> None:
    """A new landmark's covariance is J_x Σxx J_x^T + J_z Q J_z^T and it is correlated with the pose."""
    est = make_estimator(SlamParams(filter="ekf", dim=2, motion_cov_source="model"), np.random.default_rng(0))
    assert isinstance(est, EkfSlam)
    est.Sigma[:3, :3] = np.diag([0.01, 0.02, 0.003])
    est.mu[:3] = [1.0, 2.0, 0.5]
    z = np.array([[3.0, -1.0, 0.0]])
    Q = np.diag([0.04, 0.01, 1.0])[None]
    est.update(Observations(0, z, Q, np.array([5]), np.array([True])))
    m, Jx, Jz = md.meas2d_inverse(np.array([[1.0, 2.0, 0.5]]), z[:, :2])
    np.testing.assert_allclose(est.mu[3:], m[0])
    Sxx = np.diag([0.01, 0.02, 0.003])
    # the filter adds landmark_cov_floor (1e-12) to a new landmark's covariance
    floor_atol = 10 * SlamParams().landmark_cov_floor
    np.testing.assert_allclose(
        est.Sigma[3:, 3:], Jx[0] @ Sxx @ Jx[0].T + Jz[0] @ Q[0, :2, :2] @ Jz[0].T, atol=floor_atol
    )
    np.testing.assert_allclose(est.Sigma[3:, :3], Jx[0] @ Sxx, atol=ULP_ATOL)


def test_pruning_removes_rows_and_columns() -> None:
    est = make_estimator(SlamParams(filter="ekf", dim=3, max_range_m=30.0), np.random.default_rng(0))
    assert isinstance(est, EkfSlam)
    z = np.array([[3.0, 0.0, 0.0], [4.0, 1.0, 0.2], [5.0, -1.0, 0.1]])
    cov = np.tile(np.eye(3) * 1e-3, (3, 1, 1))
    est.update(Observations(0, z, cov, np.array([1, 2, 3]), np.ones(3, bool)))
    keep = np.array([True, False, True])
    for t in (1, 2):
        rep = est.update(Observations(t, z[keep], cov[keep], np.array([1, 3]), np.zeros(2, bool)))
    assert rep.n_pruned == 1
    np.testing.assert_array_equal(est.landmark_ids(), [1, 3])
    assert est.mu.shape == (12,) and est.Sigma.shape == (12, 12)
    np.testing.assert_allclose(est.landmarks().xyz_W_m, z[keep], atol=CONDITIONED_ATOL)
