"""Landmark-world simulator (robotd.research.landmark_sim): determinism, stereo noise, odometry, mismatches."""

from __future__ import annotations

import numpy as np
import pytest

from robotd.core.errors import ConfigError
from robotd.core.geometry import euler_to_R
from robotd.core.stereo import gate_selection_shift
from robotd.research.landmark_sim import SimConfig, apply_increment, dead_reckoning, inject_mismatches, simulate
from tests.support.tolerances import CONDITIONED_ATOL

SHORT2 = SimConfig(dim=2, path_length_m=40.0, landmark_density_per_m2=1.2)
SHORT3 = SimConfig(dim=3, path_length_m=40.0, landmark_density_per_m2=1.2)


def test_same_seed_same_run_different_seed_differs():
    a = simulate(SHORT2, np.random.default_rng(7))
    b = simulate(SHORT2, np.random.default_rng(7))
    c = simulate(SHORT2, np.random.default_rng(8))
    assert np.array_equal(a.landmarks_W, b.landmarks_W)
    for sa, sb in zip(a.steps, b.steps):
        assert np.array_equal(sa.observations.xyz_R_m, sb.observations.xyz_R_m)
        assert np.array_equal(sa.observations.ids, sb.observations.ids)
        if sa.motion is not None:
            assert sb.motion is not None
            assert np.array_equal(sa.motion.dp_R_m, sb.motion.dp_R_m)
    assert not np.array_equal(a.landmarks_W, c.landmarks_W)


@pytest.mark.parametrize("cfg", [SHORT2, SHORT3], ids=["2d", "3d"])
def test_trajectory_starts_at_identity_with_constant_speed(cfg):
    run = simulate(cfg, np.random.default_rng(1))
    assert np.allclose(run.poses_W[0], 0.0, atol=CONDITIONED_ATOL)
    step = np.linalg.norm(np.diff(run.poses_W[:, :3], axis=0), axis=1)
    # 1 m/s at 10 Hz is 0.1 m per frame (3D: slightly more, climbing)
    assert np.allclose(step, 0.1, rtol=0.02)
    assert len(run.steps) == cfg.n_frames == 401


def test_terrain_tilt_bounded_and_landmark_heights():
    run = simulate(SHORT3, np.random.default_rng(3))
    tilt = np.rad2deg(np.abs(run.poses_W[:, 3:5]))
    assert tilt.max() <= 5.0
    assert tilt.max() > 1.0  # there is terrain
    # landmarks between 0 and 3 m above the ground: in FRD (z down) relative to the rover's camera
    assert np.all(run.landmarks_W[:, 2] <= 0.5 + CONDITIONED_ATOL + 2.0)  # below the camera by ≤ 0.5 m + terrain


@pytest.mark.parametrize("cfg", [SHORT2, SHORT3], ids=["2d", "3d"])
def test_measurement_noise_has_covariance_q(cfg):
    """Normalised errors (z − h(x, m))ᵀ Q⁻¹ (…) follow χ²₃: mean ≈ 3, 95 % quantile ≈ 7.8."""
    run = simulate(cfg, np.random.default_rng(11))
    eps = []
    for st in run.steps:
        o, tr = st.observations, st.truth
        R = euler_to_R(tr.pose_W[3:6])
        z_true = (run.landmarks_W[tr.true_ids] - tr.pose_W[:3]) @ R
        e = o.xyz_R_m - z_true
        eps.append(np.einsum("ni,ni->n", e, np.linalg.solve(o.cov_R, e[..., None])[..., 0]))
    eps_all = np.concatenate(eps)
    assert len(eps_all) > 3000
    # first-order Q is slightly optimistic at small disparity (docs/math.md §3.3): allow +8 %
    assert 2.85 < eps_all.mean() < 3.25
    assert 7.0 < np.quantile(eps_all, 0.95) < 9.0


def test_visible_counts_and_depth_limits():
    cfg = SimConfig(dim=2, path_length_m=60.0, landmark_density_per_m2=1.5)
    run = simulate(cfg, np.random.default_rng(2))
    n = np.array([s.observations.n for s in run.steps])
    assert 20 <= n.mean() <= 50
    X = np.concatenate([s.observations.xyz_R_m[:, 0] for s in run.steps])
    fb = cfg.f_px * cfg.baseline_m
    # the gate is on the measured disparity; the kept ones near the far limit are then corrected
    # for its selection (at most by the shift at the limit itself)
    d_max = fb / cfg.depth_min_m
    s_far = gate_selection_shift(np.array([cfg.d_min_px]), cfg.d_min_px, d_max, cfg.sigma_px * np.sqrt(2.0))[0]
    assert X.min() >= cfg.depth_min_m - CONDITIONED_ATOL
    assert X.max() <= fb / (cfg.d_min_px - s_far) + CONDITIONED_ATOL


def test_is_new_marks_first_sighting_only():
    run = simulate(SHORT2, np.random.default_rng(4))
    seen: set[int] = set()
    for st in run.steps:
        for i, new in zip(st.observations.ids.tolist(), st.observations.is_new.tolist()):
            assert new == (i not in seen)
        seen.update(st.observations.ids.tolist())


@pytest.mark.parametrize("cfg", [SHORT2, SHORT3], ids=["2d", "3d"])
def test_noiseless_increments_reproduce_truth(cfg):
    quiet = SimConfig(
        dim=cfg.dim,
        path_length_m=cfg.path_length_m,
        odo_trans_frac=0.0,
        odo_heading_deg_per_m=0.0,
        odo_rot_frac=0.0,
        odo_trans_floor_m=0.0,
        odo_rot_floor_deg=0.0,
    )
    run = simulate(quiet, np.random.default_rng(5))
    dr = dead_reckoning(run)
    assert np.abs(dr[:, :3] - run.poses_W[:, :3]).max() < CONDITIONED_ATOL


def test_odometry_noise_matches_reported_covariance():
    run = simulate(SHORT2, np.random.default_rng(6))
    e = []
    for k, st in enumerate(run.steps[1:], start=1):
        assert st.motion is not None
        exact = apply_increment(run.poses_W[k - 1], np.zeros(3), np.zeros(3), 2)
        del exact
        from robotd.research.landmark_sim import true_increment

        dp, dr = true_increment(run.poses_W[k - 1], run.poses_W[k], 2)
        d = np.array([st.motion.dp_R_m[0] - dp[0], st.motion.dp_R_m[1] - dp[1], st.motion.drot_R_rad[2] - dr[2]])
        M = st.motion.cov[np.ix_([0, 1, 5], [0, 1, 5])]
        e.append(d @ np.linalg.solve(M, d))
    assert 2.7 < np.mean(e) < 3.3
    # ≈ 5 % of distance: σ of forward noise over 0.1 m steps
    assert np.isclose(np.sqrt(run.steps[5].motion.cov[0, 0]), 0.05 * 0.1 + 1e-3, rtol=0.05)


@pytest.mark.parametrize("rate", [0.1, 0.3])
def test_mismatches_injected_at_requested_rate(rate):
    base = simulate(SimConfig(dim=2, path_length_m=60.0), np.random.default_rng(9))
    run = inject_mismatches(base, rate, np.random.default_rng(10))
    n_old = sum(int((~s.observations.is_new).sum()) for s in run.steps)
    n_wrong = sum(int(s.truth.wrong.sum()) for s in run.steps)
    n_near = sum(int(s.truth.near.sum()) for s in run.steps)
    near_d = []
    assert n_old > 5000
    assert abs(n_wrong / n_old - rate) < 0.02
    assert abs(n_near / n_wrong - 0.5) < 0.05
    for s in run.steps:
        o, tr = s.observations, s.truth
        assert np.array_equal(o.ids != tr.true_ids, tr.wrong)
        assert not np.any(tr.wrong & o.is_new)
        assert len(np.unique(o.ids)) == o.n  # never one id twice in a frame
        near_d.append(np.linalg.norm(run.landmarks_W[o.ids[tr.near]] - run.landmarks_W[tr.true_ids[tr.near]], axis=1))
    # near mismatches point to a landmark within 1 m of the true one (rare fallbacks farther)
    assert np.mean(np.concatenate(near_d) <= 1.0) > 0.9
    # the measurements themselves are unchanged
    assert np.array_equal(run.steps[50].observations.xyz_R_m, base.steps[50].observations.xyz_R_m)


def test_bad_config_is_rejected_with_key():
    with pytest.raises(ConfigError, match="sim.dim"):
        SimConfig(dim=4)
    with pytest.raises(ConfigError, match="mismatch_rate"):
        SimConfig(mismatch_rate=1.5)
    with pytest.raises(ConfigError, match="sim.noise_model"):
        SimConfig(noise_model="laplace")
    with pytest.raises(ConfigError, match="sim.isotropic_sigma_m"):
        SimConfig(noise_model="isotropic", isotropic_sigma_m=0.0)
