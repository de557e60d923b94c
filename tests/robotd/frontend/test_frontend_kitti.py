"""The front end end to end on real KITTI frames (skips without ../shared/data/kitti-seq1)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from robotd.core.errors import InputError
from robotd.core.geometry import R_ROBOT_OPTICAL, se3, se3_inverse
from robotd.core.msgs import Observations
from robotd.core.outliers import OutlierParams
from robotd.core.stereo import RectifiedStereo
from robotd.frontend.detectors import DetectorParams, surf_available
from robotd.frontend.frontend import Frontend, FrontendParams

DETECTORS = ["orb", "sift", pytest.param("surf", marks=pytest.mark.skipif(not surf_available(), reason="no SURF"))]


def _kitti(root: Path) -> tuple[RectifiedStereo, np.ndarray]:
    """Rig from calib.txt (P0/P1 rows) and ground truth as robot-frame poses T_R0_Rk (N, 4, 4)."""
    rows = []
    for line in (root / "calib.txt").read_text().splitlines():
        vals = line.split(":", 1)[-1].split()
        if len(vals) == 12:
            rows.append(np.array(vals, dtype=float).reshape(3, 4))
    P0, P1 = rows[0], rows[1]
    b = -P1[0, 3] / P1[0, 0]
    h, w = cv2.imread(str(root / "image_l" / "000000.png"), cv2.IMREAD_GRAYSCALE).shape
    rig = RectifiedStereo(P0[0, 0], P0[0, 2], P0[1, 2], b, w, h)
    poses = np.loadtxt(root / "poses.txt").reshape(-1, 3, 4)
    T_C0_C = np.tile(np.eye(4), (poses.shape[0], 1, 1))
    T_C0_C[:, :3, :] = poses
    # the robot frame sits at the baseline centre (b/2 along the left camera's x) with FRD axes
    T_C_R = se3(R_ROBOT_OPTICAL.T, np.array([b / 2.0, 0.0, 0.0]))
    return rig, se3_inverse(T_C_R) @ se3_inverse(T_C0_C[0]) @ T_C0_C @ T_C_R


def _pair(root: Path, k: int) -> tuple[np.ndarray, np.ndarray]:
    return (
        cv2.imread(str(root / "image_l" / f"{k:06d}.png"), cv2.IMREAD_GRAYSCALE),
        cv2.imread(str(root / "image_r" / f"{k:06d}.png"), cv2.IMREAD_GRAYSCALE),
    )


@pytest.mark.parametrize("name", DETECTORS)
def test_two_frames_identify_landmarks_and_recover_motion(shared_data, name):
    root = shared_data("kitti-seq1")
    rig, T_gt = _kitti(root)
    fe = Frontend(rig, FrontendParams(detector=DetectorParams(name=name)), np.random.default_rng(1))
    r0 = fe.process(*_pair(root, 10), 1_000_000_000)
    assert r0.counts["stereo_matches"] > 100
    assert r0.observations.n == r0.counts["new"] and r0.observations.is_new.all()
    r1 = fe.process(*_pair(root, 11), 1_100_000_000)
    # landmarks of frame 10 are identified in frame 11 (frame-to-frame reference)
    assert r1.counts["inliers"] >= 30
    ident = ~r1.observations.is_new
    assert np.all(np.isin(r1.observations.ids[ident], r0.observations.ids))
    assert not np.any(np.isin(r1.observations.ids[~ident], r0.observations.ids))  # new ids are fresh
    # the frame-to-frame motion is within 5 % of ground truth (≈1.2 m per frame)
    gt = se3_inverse(T_gt[10]) @ T_gt[11]
    assert r1.T_prev_curr is not None and r1.motion is not None
    t_err = np.linalg.norm(r1.T_prev_curr[:3, 3] - gt[:3, 3]) / np.linalg.norm(gt[:3, 3])
    assert t_err < 0.05, t_err
    rot_err = np.degrees(np.linalg.norm(cv2.Rodrigues(r1.T_prev_curr[:3, :3] @ gt[:3, :3].T)[0]))
    assert rot_err < 0.5
    np.testing.assert_allclose(r1.motion.dp_R_m, r1.T_prev_curr[:3, 3])
    assert set(r1.timings_ms) >= {"detect", "stereo", "identify", "outliers", "motion"}


def test_identification_against_a_world_map(shared_data):
    # map = frame 20's landmarks placed in the world with the ground-truth pose; the similarity the
    # outlier stage fits on frame 21 is then ≈ T_robot_world (ground truth)
    root = shared_data("kitti-seq1")
    rig, T_gt = _kitti(root)
    fe = Frontend(rig, FrontendParams(detector=DetectorParams(name="orb")), np.random.default_rng(2))
    r0 = fe.process(*_pair(root, 20), 0)
    o = r0.observations
    Tw = T_gt[20]
    xyz_W = o.xyz_R_m @ Tw[:3, :3].T + Tw[:3, 3]
    cov_W = Tw[:3, :3] @ o.cov_R @ Tw[:3, :3].T
    fe.reset()  # identification must come from the map, not from the previous frame
    r1 = fe.process(*_pair(root, 21), 100_000_000, (o.ids, xyz_W, cov_W), T_gt[21])
    assert r1.counts["inliers"] >= 30
    assert r1.similarity is not None and r1.outlier_result is not None
    # the robot's position the similarity implies (p = -(sR)^-1 t), against the ground truth
    sR, t = r1.similarity[:3, :3], r1.similarity[:3, 3]
    p_est = -np.linalg.solve(sR, t)
    assert np.linalg.norm(p_est - T_gt[21][:3, 3]) < 0.1
    # predicted-visible restriction: candidates are at most the map
    assert 0 < r1.counts["map_candidates"] <= o.n
    # the fundamental-matrix baseline runs through the same stage
    fe_f = Frontend(
        rig,
        FrontendParams(detector=DetectorParams(name="orb"), outliers=OutlierParams(method="fundamental")),
        np.random.default_rng(3),
    )
    fe_f.process(*_pair(root, 20), 0)
    rf = fe_f.process(*_pair(root, 21), 100_000_000)
    assert rf.outlier_result is not None and rf.outlier_result.method == "fundamental"
    assert rf.counts["inliers"] > 0


def test_bad_inputs_give_clear_errors_or_empty_results():
    rig = RectifiedStereo(430.0, 319.5, 199.5, 0.0755, 640, 400)
    fe = Frontend(rig, rng=np.random.default_rng(0))
    black = np.zeros((400, 640), np.uint8)
    r = fe.process(black, black, 0)
    assert isinstance(r.observations, Observations) and r.observations.n == 0
    assert r.T_prev_curr is None and r.similarity is None
    r = fe.process(black, black, 1, (np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3, 3))), np.eye(4))
    assert r.observations.n == 0
    with pytest.raises(InputError, match=r"one size.*\(400, 640\).*\(400, 600\)"):
        fe.process(black, np.zeros((400, 600), np.uint8), 2)
    with pytest.raises(InputError, match=r"rig's size \(400, 640\), got \(0, 0\)"):
        fe.process(np.zeros((0, 0), np.uint8), np.zeros((0, 0), np.uint8), 3)
    with pytest.raises(InputError, match="uint8"):
        fe.process(black.astype(np.float32), black, 4)
    with pytest.raises(InputError, match="map ids"):
        fe.process(black, black, 5, (np.zeros(3, np.int64), np.zeros((2, 3)), np.zeros((3, 3, 3))))
    with pytest.raises(InputError, match="T_world_robot_prior"):
        fe.process(black, black, 6, None, np.eye(3))
    # the front end keeps working after bad input
    assert fe.process(black, black, 7).observations.n == 0
