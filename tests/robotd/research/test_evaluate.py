"""Evaluation metrics and trajectory files (robotd.research.evaluate, docs/math.md §11)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robotd.core.errors import DatasetError, InputError
from robotd.core.geometry import pose6_to_T, rot_z, se3, so3_exp
from robotd.research.evaluate import (
    MIN_PATH_FOR_RELATIVE_M,
    Trajectory,
    anees_band,
    associate,
    ate,
    drift_pct,
    evaluate_files,
    evaluate_trajectories,
    map_rmse,
    nees,
    path_length,
    plot_trajectory,
    poses_to_T,
    read_kitti_poses,
    read_trajectory,
    read_tum,
    rpe,
    similarity_scale,
    travel_offset_deg,
    write_tum,
)
from tests.support.tolerances import ANGLE_FROM_COSINE_FLOOR_DEG, CONDITIONED_ATOL, CONDITIONED_RTOL

# write_tum prints times with 9 decimals, but near t = 1.7e9 s float64 resolves only 2.4e-7 s
TUM_TIME_ATOL_S = 1e-6
# and poses with 9 significant digits: ≤ 5e-8 m on positions up to 10 m (measured 4.9e-9)
TUM_POSE_ATOL = 1e-7


def _wiggly(n: int = 200, rng: np.random.Generator | None = None) -> np.ndarray:
    """(n, 4, 4) a non-planar, non-degenerate trajectory."""
    t = np.linspace(0, 2 * np.pi, n)
    x6 = np.column_stack(
        [10 * np.cos(t), 6 * np.sin(t), 0.5 * np.sin(3 * t), 0.05 * np.sin(t), 0.03 * np.cos(2 * t), t]
    )
    return pose6_to_T(x6)


def test_ate_zero_after_rigid_motion_of_the_whole_trajectory():
    gt = _wiggly()
    G = se3(so3_exp(np.array([0.3, -0.2, 1.1])), np.array([4.0, -3.0, 2.0]))
    est = G @ gt
    r = ate(est, gt)
    assert r["ate_rmse_m"] < CONDITIONED_ATOL
    # the heading error is an arccos of (tr E − 1)/2: for E = I up to round-off it reads as up to
    # √(2·16 EPS) rad, not 0 (1.17e-6 deg on x86-64, so a 1e-6 deg bound held on one CPU only)
    assert r["heading_rmse_deg"] < ANGLE_FROM_COSINE_FLOOR_DEG
    # planar version of the same property
    gt2 = poses_to_T(np.column_stack([np.cos(np.linspace(0, 3, 50)), np.linspace(0, 5, 50), np.linspace(0, 1, 50)]))
    G2 = se3(rot_z(0.7), np.array([1.0, 2.0, 0.0]))
    assert ate(G2 @ gt2, gt2, planar=True)["ate_rmse_m"] < CONDITIONED_ATOL


def test_known_offset_gives_known_rmse():
    """Errors ±d along z alternately cannot be aligned away: RMSE is exactly d."""
    gt = _wiggly(100)
    est = gt.copy()
    d = 0.25
    sign = np.where(np.arange(100) % 2 == 0, 1.0, -1.0)
    # offsets along the world z axis, in alternate directions, mean zero
    est[:, 2, 3] += d * sign
    r = ate(est, gt, align=False)
    assert r["ate_rmse_m"] == pytest.approx(d, abs=CONDITIONED_ATOL)
    assert r["ate_max_m"] == pytest.approx(d, abs=CONDITIONED_ATOL)
    assert r["ate_median_m"] == pytest.approx(d, abs=CONDITIONED_ATOL)
    # a constant offset is removed by the alignment, but not without it
    est2 = gt.copy()
    est2[:, :3, 3] += np.array([0.3, 0.4, 0.0])
    assert ate(est2, gt, align=False)["ate_rmse_m"] == pytest.approx(0.5, abs=CONDITIONED_ATOL)
    assert ate(est2, gt)["ate_rmse_m"] < CONDITIONED_ATOL


def test_rpe_of_a_constant_per_step_error():
    n = 50
    gt = poses_to_T(np.column_stack([np.arange(n) * 1.0, np.zeros(n), np.zeros(n)]))
    est = poses_to_T(np.column_stack([np.arange(n) * 1.1, np.zeros(n), np.zeros(n)]))
    r = rpe(est, gt, 1)
    assert r["rpe_trans_m"] == pytest.approx(0.1, abs=CONDITIONED_ATOL)
    assert r["rpe_rot_deg"] == pytest.approx(0.0, abs=ANGLE_FROM_COSINE_FLOOR_DEG)  # arccos near 1, as above
    # a constant turn-rate error of 1° per step
    est2 = poses_to_T(np.column_stack([np.arange(n) * 1.0, np.zeros(n), np.deg2rad(np.arange(n))]))
    assert rpe(est2, gt, 1, planar=True)["rpe_rot_deg"] == pytest.approx(1.0, abs=CONDITIONED_ATOL)


def test_drift_of_known_trajectory():
    # 100 m straight along x; the estimate ends 2 m to the side after a first-pose alignment
    n = 101
    gt = poses_to_T(np.column_stack([np.linspace(0, 100, n), np.zeros(n), np.zeros(n)]))
    est = poses_to_T(np.column_stack([np.linspace(0, 100, n), np.linspace(0, 2, n), np.zeros(n)]))
    assert path_length(gt[:, :3, 3]) == pytest.approx(100.0)
    assert drift_pct(est, gt) == pytest.approx(2.0, abs=CONDITIONED_ATOL)
    # the estimate expressed in another start frame drifts the same (first-pose alignment)
    G = se3(rot_z(1.0), np.array([5.0, 5.0, 0.0]))
    assert drift_pct(G @ est, gt) == pytest.approx(2.0, abs=CONDITIONED_ATOL)


def test_tum_round_trip(tmp_path):
    T = _wiggly(30)
    t = 1.7e9 + np.arange(30) * 0.1
    p = tmp_path / "traj.tum"
    write_tum(p, t, T)
    tr = read_tum(p)
    assert np.allclose(tr.t_s, t, atol=TUM_TIME_ATOL_S)
    assert np.allclose(tr.T, T, atol=TUM_POSE_ATOL)
    line = next(li for li in p.read_text().splitlines() if not li.startswith("#"))
    assert len(line.split()) == 8


def test_kitti_poses_parse(tmp_path):
    T = _wiggly(5)
    p = tmp_path / "poses.txt"
    np.savetxt(p, T[:, :3, :].reshape(5, 12))
    tr = read_kitti_poses(p)
    assert np.allclose(tr.T, T)
    assert np.allclose(tr.t_s, np.arange(5) * 0.1)
    assert read_trajectory(p).T.shape == (5, 4, 4)


def test_kitti_seq1_ground_truth_parses(shared_data):
    tr = read_kitti_poses(shared_data("kitti-seq1", "poses.txt"))
    assert len(tr) == 51
    assert path_length(tr.xyz) == pytest.approx(59.9, abs=0.3)


def test_bad_files_give_clear_errors(tmp_path):
    p = tmp_path / "bad.txt"
    p.write_text("0 1 2 3\n")
    with pytest.raises(DatasetError, match="expected 8"):
        read_trajectory(p)
    p.write_text("0 1 2 3 0 0 0 2\n")
    with pytest.raises(DatasetError, match="not unit"):
        read_tum(p)
    with pytest.raises(DatasetError, match="no such file"):
        read_tum(tmp_path / "missing.tum")


def test_association_nearest_within_half_period():
    t_gt = np.arange(0.0, 10.0, 0.1)
    t_est = np.array([0.01, 0.52, 0.56, 3.0, 20.0])
    ie, ig = associate(t_est, t_gt)
    assert ie.tolist() == [0, 1, 2, 3]
    assert np.allclose(t_gt[ig], [0.0, 0.5, 0.6, 3.0])


def test_evaluate_files_against_itself_and_with_noise(tmp_path):
    gt = _wiggly(100)
    t = np.arange(100) * 0.1
    rng = np.random.default_rng(0)
    est = gt.copy()
    est[:, :3, 3] += 0.05 * rng.standard_normal((100, 3))
    write_tum(tmp_path / "gt.tum", t, gt)
    write_tum(tmp_path / "est.tum", t + 0.01, se3(rot_z(0.5), np.array([1.0, 2.0, 3.0])) @ est)
    r = evaluate_files(tmp_path / "est.tum", tmp_path / "gt.tum")
    for k in ("ate_rmse_m", "rpe_trans_m", "drift_pct", "path_length_m", "frames"):
        assert k in r
    assert r["frames"] == 100
    assert 0.05 * np.sqrt(3) * 0.8 < r["ate_rmse_m"] < 0.05 * np.sqrt(3) * 1.2
    write_tum(tmp_path / "far.tum", t + 100.0, est)
    with pytest.raises(InputError, match="associate"):
        evaluate_files(tmp_path / "far.tum", tmp_path / "gt.tum")


def test_nees_and_anees_band():
    rng = np.random.default_rng(3)
    P = np.array([[4.0, 1.0, 0.0], [1.0, 2.0, 0.0], [0.0, 0.0, 0.01]])
    L = np.linalg.cholesky(P)
    e = rng.standard_normal((20000, 3)) @ L.T
    eps = nees(e, np.broadcast_to(P, (20000, 3, 3)), angle_dims=[2])
    assert eps.mean() == pytest.approx(3.0, rel=0.03)
    lo, hi = anees_band(3, 20)
    assert lo == pytest.approx(2.02, abs=0.01) and hi == pytest.approx(4.17, abs=0.01)
    lo, hi = anees_band(6, 50)
    assert lo == pytest.approx(5.08, abs=0.01) and hi == pytest.approx(7.00, abs=0.01)


def test_map_rmse_after_alignment():
    rng = np.random.default_rng(4)
    gt = rng.uniform(-10, 10, (30, 3))
    G = se3(so3_exp(np.array([0.0, 0.0, 0.8])), np.array([3.0, 1.0, 0.0]))
    est = gt @ G[:3, :3].T + G[:3, 3]
    assert map_rmse(est, gt)["map_rmse_m"] < CONDITIONED_ATOL
    est[0] += np.array([0.0, 0.0, 1.0])
    r = map_rmse(est, gt, T_align=np.linalg.inv(G))
    assert r["per_landmark_m"][0] == pytest.approx(1.0)
    assert r["map_rmse_m"] == pytest.approx(np.sqrt(1 / 30))


def test_plot_writes_png(tmp_path):
    gt = _wiggly(50)
    out = plot_trajectory(gt, gt, np.zeros((3, 3)), tmp_path / "p.png", gt_landmarks=np.ones((3, 3)), title="t")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_short_path_leaves_relative_figures_undefined_and_gives_drift_m():
    # a platform standing still with mm ground-truth jitter: % of a ~0 path and a fitted scale are
    # meaningless (the EuRoC micro cut read "drift 24 %, scale 0.28"), the end-point error is not
    rng = np.random.default_rng(1)
    n = 50
    gt = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
    gt[:, :3, 3] = 0.001 * rng.standard_normal((n, 3))
    est = gt.copy()
    est[:, :3, 3] += np.linspace(0, 1, n)[:, None] * np.array([0.003, 0.004, 0.0])  # drifts 5 mm
    t = np.arange(n) * 0.05
    m = evaluate_trajectories(Trajectory(t, est), Trajectory(t, gt))
    assert m["path_length_m"] < MIN_PATH_FOR_RELATIVE_M
    assert math.isnan(m["drift_pct"]) and math.isnan(m["similarity_scale"])
    assert m["drift_m"] == pytest.approx(0.005, abs=CONDITIONED_ATOL)


def test_normal_path_figures_unchanged_and_drift_m_is_drift_pct_numerator():
    gt = _wiggly(100)
    est = gt.copy()
    est[:, :3, 3] += np.linspace(0, 1, 100)[:, None] * np.array([0.3, -0.2, 0.1])
    t = np.arange(100) * 0.1
    m = evaluate_trajectories(Trajectory(t, est), Trajectory(t, gt))
    assert m["path_length_m"] > MIN_PATH_FOR_RELATIVE_M
    # exactly the values of the metric functions (nothing changed for a normal path)
    assert m["drift_pct"] == drift_pct(est, gt)
    assert m["similarity_scale"] == similarity_scale(est[:, :3, 3], gt[:, :3, 3])
    assert m["drift_m"] == pytest.approx(np.linalg.norm([0.3, -0.2, 0.1]), abs=CONDITIONED_ATOL)
    assert m["drift_pct"] == pytest.approx(100 * m["drift_m"] / m["path_length_m"], rel=CONDITIONED_RTOL)


# --------------------------------------------------------------------------------------------
# KITTI pose files as ground truth: frame times and the robot frame (issue 13, item 6)

KITTI_B_M = 0.54  # a KITTI-like stereo baseline
RAW_PERIOD_S = 0.1035  # KITTI raw's real frame period (~9.66 Hz), not the 0.1 s of the odometry benchmark


def _kitti_folder(root, n=60, times=True, calib=True):
    """A KITTI folder with a turning left-camera trajectory; returns (poses.txt, the frame times,
    the truth a replay of this folder carries: robot frame, FRD, at the baseline centre)."""
    from drivers.dataset import kitti_truth_to_robot

    root.mkdir(parents=True, exist_ok=True)
    k = np.arange(n)
    # optical frame (x right, y down, z forward): forward along z, turning about -y (to the left)
    yaw = 0.03 * k
    x6 = np.column_stack([2 * np.sin(yaw) * 10, 0.02 * np.sin(k), 10 * (1 - np.cos(yaw)) * 2, 0 * k, -yaw, 0 * k])
    T_C0_C = pose6_to_T(x6[:, [0, 1, 2, 3, 4, 5]])
    T_C0_C = np.linalg.inv(T_C0_C[0]) @ T_C0_C
    np.savetxt(root / "poses.txt", T_C0_C[:, :3, :].reshape(n, 12), fmt="%.12e")
    t_s = k * RAW_PERIOD_S + 0.001 * np.sin(k)  # irregular, like a real capture clock
    if times:
        np.savetxt(root / "times.txt", t_s, fmt="%.6e")
    if calib:
        P0 = [700.0, 0, 600.0, 0, 0, 700.0, 180.0, 0, 0, 0, 1, 0]
        P1 = [700.0, 0, 600.0, -700.0 * KITTI_B_M, 0, 700.0, 180.0, 0, 0, 0, 1, 0]
        (root / "calib.txt").write_text(f"P0: {' '.join(map(str, P0))}\nP1: {' '.join(map(str, P1))}\n")
    return root / "poses.txt", np.round(t_s, 6), kitti_truth_to_robot(T_C0_C, KITTI_B_M)


def test_kitti_truth_is_read_with_its_times_and_in_the_robot_frame(tmp_path):
    poses, t_s, G = _kitti_folder(tmp_path / "seq")
    write_tum(tmp_path / "est.txt", t_s, G)  # what a perfect replay of the folder writes
    r = evaluate_files(tmp_path / "est.txt", poses)
    assert r["frames"] == len(G), "every frame pairs with its own truth (times.txt, not 0.1 s × index)"
    assert r["ate_rmse_m"] < TUM_POSE_ATOL and r["drift_m"] < TUM_POSE_ATOL and r["rpe_trans_m"] < TUM_POSE_ATOL
    # the same estimate against truth left at the left camera (only the axes changed) errs by the
    # lever arm b/2 swinging through the turn: the comparison the robot frame fixes
    from robotd.core.geometry import T_optical_to_robot

    tr = read_kitti_poses(poses)
    m = evaluate_trajectories(Trajectory(tr.t_s, G), Trajectory(tr.t_s, T_optical_to_robot(tr.T)))
    assert m["drift_m"] > 0.3, "b/2 = 0.27 m turned through 100 degrees"
    # the old stamping (0.1 s × index) against these 9.66 Hz frames drops and mis-pairs frames
    ie, _ = associate(t_s, np.arange(len(G)) * 0.1)
    assert len(ie) < len(G)


def test_kitti_truth_without_times_pairs_by_index_when_counts_match(tmp_path):
    poses, t_s, G = _kitti_folder(tmp_path / "seq", times=False)
    tr = read_trajectory(poses)
    assert not tr.timed and np.allclose(tr.t_s, np.arange(len(G)) * 0.1)
    write_tum(tmp_path / "est.txt", t_s, G)  # a 9.66 Hz clock the file does not know
    r = evaluate_files(tmp_path / "est.txt", poses)
    assert r["frames"] == len(G) and r["ate_rmse_m"] < TUM_POSE_ATOL
    # a different count: the nominal 10 Hz stamps, which a replay of such a folder writes (a prefix)
    write_tum(tmp_path / "part.txt", np.arange(12) * 0.1, G[:12])
    r = evaluate_files(tmp_path / "part.txt", poses)
    assert r["frames"] == 12 and r["ate_rmse_m"] < TUM_POSE_ATOL
    # a different count off that grid: no telling which frame each pose is, so a clear error
    # (pairing by nearest 10 Hz stamp would silently mis-pair every frame after the 15th)
    write_tum(tmp_path / "slow.txt", t_s[:40], G[:40])
    with pytest.raises(InputError, match=r"not on its 10 Hz grid: give the poses.txt its times.txt"):
        evaluate_files(tmp_path / "slow.txt", poses)


def test_kitti_truth_errors_and_a_missing_calibration(tmp_path, caplog):
    poses, t_s, _ = _kitti_folder(tmp_path / "short", n=20)
    np.savetxt(poses.parent / "times.txt", t_s[:15], fmt="%.6e")
    with pytest.raises(DatasetError, match=r"times\.txt: expected 20 stamps"):
        read_trajectory(poses)
    poses, t_s, _ = _kitti_folder(tmp_path / "nocalib", calib=False)
    with caplog.at_level("WARNING", logger="robotd.research.evaluate"):
        tr = read_trajectory(poses)
    assert "no calib.txt" in caplog.text
    from robotd.core.geometry import T_optical_to_robot

    assert np.allclose(tr.T, T_optical_to_robot(read_kitti_poses(poses).T), atol=1e-12)


def test_pose_covariance_file_round_trips_and_sits_beside_the_trajectory(tmp_path):
    from robotd.research.evaluate import cov_path_for, read_pose_cov, write_pose_cov

    assert cov_path_for(tmp_path / "T.txt") == tmp_path / "T.cov.txt"
    assert cov_path_for(tmp_path / "T") == tmp_path / "T.cov"
    rng = np.random.default_rng(0)
    A = rng.normal(size=(4, 6, 6))
    C = A @ np.swapaxes(A, 1, 2)
    t = np.array([0.0, 0.1, 0.2, 0.3])
    write_pose_cov(tmp_path / "c.txt", t, C)
    t2, C2 = read_pose_cov(tmp_path / "c.txt")
    np.testing.assert_allclose(t2, t)
    np.testing.assert_allclose(C2, C, rtol=1e-8)
    (tmp_path / "bad.txt").write_text("0.0 1 2 3\n")
    with pytest.raises(DatasetError, match="expected 22 numbers"):
        read_pose_cov(tmp_path / "bad.txt")


def test_position_nees_by_hand_after_first_pose_alignment():
    from robotd.research.evaluate import nees_summary, position_nees

    # truth: straight along x; the estimate starts rotated by 90° (its own world frame) and is 0.2 m
    # off sideways at the end: after the alignment the error is (0, 0.2, 0) in the truth's frame
    Q = np.stack([se3(np.eye(3), np.array([k, 0.0, 0.0])) for k in range(3)])
    Rz = rot_z(math.pi / 2)
    P = np.stack([se3(Rz, Rz @ np.array([k, 0.0, 0.0])) for k in range(3)])
    P[2, :3, 3] = Rz @ np.array([2.0, 0.2, 0.0])
    C = np.zeros((3, 6, 6))
    C[:, :3, :3] = np.diag([0.01, 0.04, 0.09])  # in the estimate's frame: its y is the truth's x
    eps = position_nees(P, Q, C)
    assert math.isnan(eps[0])  # the alignment pose itself
    assert eps[1] == pytest.approx(0.0, abs=1e-12)
    # rotated: the estimate's x variance (0.01) is now along the truth's y
    assert eps[2] == pytest.approx(0.2**2 / 0.01, rel=1e-9)
    s = nees_summary(eps)
    assert s["nees_pos_frames"] == 2 and s["nees_pos_in_band_frac"] == 0.5  # 0 is below the band, 4.0 inside


def test_a_kitti_file_written_from_robot_poses_holds_the_left_cameras_and_reads_back(tmp_path):
    """robotd replay --format kitti (issue 27, item 7): the robot frame's poses (FRD, baseline
    centre) written as KITTI's, the left camera's optical frame: the folder's own poses.txt again."""
    from robotd.research.evaluate import robot_to_left_camera, write_kitti_poses

    poses, _, G = _kitti_folder(tmp_path / "seq")  # G: the robot-frame truth of the folder's camera poses
    write_kitti_poses(tmp_path / "est.txt", G, KITTI_B_M)
    text = (tmp_path / "est.txt").read_text()
    assert not text.startswith("#") and all(len(r.split(" ")) == 12 for r in text.splitlines())
    assert np.allclose(np.loadtxt(tmp_path / "est.txt"), np.loadtxt(poses), atol=1e-8), "KITTI's own frame"
    # and back: the other file's calib.txt gives the baseline of one written elsewhere
    tr = read_trajectory(tmp_path / "est.txt", calib_fallback=poses.parent / "calib.txt")
    assert np.allclose(tr.T, G, atol=1e-8)
    # independently of the matrices: the camera sits b/2 to the robot's left, axes x right, y down, z forward
    C = robot_to_left_camera(G, KITTI_B_M)
    lever = np.array([0.0, -KITTI_B_M / 2, 0.0])
    p_cam_in_robot_world = G[:, :3, 3] + G[:, :3, :3] @ lever - lever  # relative to the first camera
    axes = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])  # robot (x fwd, y right, z down) -> optical
    assert np.allclose(C[:, :3, 3], p_cam_in_robot_world @ axes.T, atol=1e-12)


def _plain_umeyama_rmse(P: np.ndarray, Q: np.ndarray) -> float:
    """APE after the least-squares rigid fit of positions (Umeyama 1991), written out here as evo_ape
    -a does it, independent of robotd.core.geometry."""
    p, q = P[:, :3, 3], Q[:, :3, 3]
    mp, mq = p.mean(0), q.mean(0)
    U, _, Vt = np.linalg.svd((q - mq).T @ (p - mp) / len(p))
    S = np.diag([1.0, 1.0, np.sign(np.linalg.det(U) * np.linalg.det(Vt))])
    R = U @ S @ Vt
    return float(np.sqrt(np.mean(np.sum((p @ R.T + (mq - R @ mp) - q) ** 2, axis=1))))


def test_ate_umeyama_is_the_plain_fit_that_evo_reports_and_differs_only_on_a_straight_path():
    rng = np.random.default_rng(4)
    n = 50
    straight = np.tile(np.eye(4), (n, 1, 1))
    straight[:, 0, 3] = np.linspace(0.0, 60.0, n)  # a KITTI-like straight drive, bowing 0.5 m sideways
    straight[:, 1, 3] = 0.5 * np.sin(np.linspace(0.0, np.pi, n))
    est = straight.copy()
    # positions rolled 3 degrees about the path, orientations not: the plain fit of positions
    # takes the roll back out, the orientations say there is none
    est[:, :3, 3] = straight[:, :3, 3] @ so3_exp(np.array([0.05, 0.0, 0.0])).T + rng.normal(0.0, 0.005, (n, 3))
    est[:, :3, :3] = so3_exp(rng.normal(0.0, 0.002, (n, 3)))
    m = ate(est, straight)
    assert m["ate_umeyama_rmse_m"] == pytest.approx(_plain_umeyama_rmse(est, straight), rel=1e-9)
    # on a straight path the roll about it comes from the orientations: a different (larger) figure
    assert m["ate_rmse_m"] > 1.01 * m["ate_umeyama_rmse_m"]
    turning = np.stack([se3(rot_z(0.05 * k), [10 * np.sin(0.05 * k), 10 * (1 - np.cos(0.05 * k)), 0.0])
                        for k in range(n)])  # fmt: skip
    est = turning.copy()
    est[:, :3, 3] += rng.normal(0.0, 0.05, (n, 3))
    m = ate(est, turning)
    assert m["ate_umeyama_rmse_m"] == pytest.approx(m["ate_rmse_m"], rel=1e-12)
    assert m["ate_umeyama_rmse_m"] == pytest.approx(_plain_umeyama_rmse(est, turning), rel=1e-9)


def test_kitti_rotations_printed_to_seven_digits_are_read_orthonormal(tmp_path):
    """KITTI's poses.txt has 7 significant digits; taken as they are, the trace-based angle of a
    frame-to-frame rotation read 0.03 degrees more on kitti-seq1 than evo, which orthonormalises."""
    n = 40
    G = np.stack([se3(so3_exp(np.array([0.0, 0.0009 * k, 0.0002 * k])), [0.0, 0.0, 1.2 * k]) for k in range(n)])
    np.savetxt(tmp_path / "poses.txt", G[:, :3, :].reshape(n, 12), fmt="%.6e")
    T = read_kitti_poses(tmp_path / "poses.txt").T
    R = T[:, :3, :3]
    assert np.allclose(R @ np.swapaxes(R, 1, 2), np.eye(3), atol=1e-12) and np.allclose(np.linalg.det(R), 1.0)
    assert np.allclose(T[:, :3, 3], np.round(G[:, :3, 3], 5), atol=1e-5)
    assert rpe(T, G)["rpe_rot_deg"] < 1e-3, "rounding alone (1e-7) is not a 0.01-degree rotation error"


def _crabbing(offset_deg: float, n: int = 60, yaw0: float = 0.3) -> np.ndarray:
    """A drive along a gentle curve, 1 m a pose, travelling ``offset_deg`` to the left of its heading."""
    yaw = yaw0 + np.linspace(0.0, 0.4, n)
    travel = 0.5 * (yaw[:-1] + yaw[1:]) + math.radians(offset_deg)  # each step at its mid heading
    steps = np.column_stack([np.cos(travel), np.sin(travel), np.zeros(n - 1)])
    p = np.vstack([np.zeros(3), np.cumsum(steps, axis=0)])
    return np.stack([se3(rot_z(y), q) for y, q in zip(yaw, p)])


def test_travel_offset_is_the_angle_between_heading_and_travel_for_each_side():
    est, gt = _crabbing(-0.2), _crabbing(1.2, yaw0=-1.0)
    e, g = travel_offset_deg(est, gt)
    assert e == pytest.approx(-0.2, abs=0.02) and g == pytest.approx(1.2, abs=0.02)
    # going backwards, or standing still, says nothing
    assert all(math.isnan(v) for v in travel_offset_deg(est[::-1], gt[::-1]))
    still = np.repeat(gt[:1], 20, axis=0)
    assert all(math.isnan(v) for v in travel_offset_deg(still, still))


def test_a_truth_turned_against_its_positions_shows_as_drift_and_as_travel_offset():
    """The estimate exact but the truth's orientations all 1.4° off its positions: the first-pose
    drift reads about 1.4° × path (2.4 %), the travel offsets differ by 1.4° and say why."""
    gt = _crabbing(0.0)
    est = gt.copy()
    bad = gt.copy()
    bad[:, :3, :3] = gt[:, :3, :3] @ rot_z(math.radians(-1.4))
    e, g = travel_offset_deg(est, bad)
    assert e == pytest.approx(0.0, abs=0.01) and g == pytest.approx(1.4, abs=0.01)
    from robotd.research.evaluate import drift_pct

    assert drift_pct(est, bad) == pytest.approx(100 * math.radians(1.4), rel=0.05)
