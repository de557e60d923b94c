"""A plain OpenCV stereo PnP visual odometry: the baseline robotd's accuracy is judged against (issue 13).

Deliberately simple, and nothing of robotd's own front end or filter: per frame, ORB features in
both rectified images, stereo matches restricted to the same row (|Δy| ≤ ``row_tol_px``) with
positive disparity, triangulated in the left camera; the previous frame's 3D points are matched by
descriptor (Lowe's ratio test) to the current left features and ``cv2.solvePnPRansac`` gives the
frame-to-frame motion, which is chained. No map, no filter, no keyframes. A frame where PnP fails
(too few matches or inliers) is counted lost and repeats the previous motion (constant velocity).

Frames come through robotd's own drivers (``drivers.open_camera``), so the baseline sees the same
images, rig and truth as a replay, and its poses are in the replay's convention: robot frame FRD
at the baseline centre, world = robot frame at the first frame. :func:`run_pnp` evaluates them with
the replay's own truth metrics.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

import drivers
from robotd.core.errors import RobotdError
from robotd.core.geometry import R_ROBOT_OPTICAL, se3, se3_inverse
from robotd.core.stereo import RectifiedStereo


@dataclass(frozen=True, slots=True)
class PnPParams:
    n_features: int = 2000  # ORB features per image
    row_tol_px: float = 1.5  # stereo: |y_left - y_right| allowed on the rectified pair
    min_disparity_px: float = 1.0  # stereo: points nearer than infinity only
    max_hamming: int = 64  # stereo: best match in the row band must be at least this close
    ratio: float = 0.8  # temporal: Lowe's ratio test
    reproj_px: float = 2.0  # RANSAC inlier threshold
    iterations: int = 200
    min_inliers: int = 12


class PnPOdometry:
    """Frame-to-frame stereo PnP. :meth:`step` takes a rectified pair and returns T_world_robot."""

    def __init__(self, rig: RectifiedStereo, params: PnPParams = PnPParams()) -> None:
        self.rig, self.p = rig, params
        self.orb = cv2.ORB.create(nfeatures=params.n_features)
        self.bf = cv2.BFMatcher(cv2.NORM_HAMMING)
        self.K = np.array([[rig.f_px, 0.0, rig.px], [0.0, rig.f_px, rig.py], [0.0, 0.0, 1.0]])
        # robot frame (FRD, baseline centre) <- left optical frame; the left camera is at y = -b/2
        self.T_R_C = se3(R_ROBOT_OPTICAL, np.array([0.0, -rig.baseline_m / 2.0, 0.0]))
        self.T_W_C = self.T_R_C.copy()  # the left camera in the world (= robot frame at the first frame)
        self.motion = np.eye(4)  # last T_prev_curr of the left camera (constant-velocity fallback)
        self.prev: tuple[np.ndarray, np.ndarray] | None = None  # (descriptors, 3D points in the camera)
        self.lost = 0

    def _detect(self, img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        kps, desc = self.orb.detectAndCompute(img, None)
        if desc is None:
            return np.zeros((0, 2), np.float32), np.zeros((0, 32), np.uint8)
        return np.array([k.pt for k in kps], np.float32), desc

    def _stereo(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Left pixels and descriptors of every left feature, and (descriptors, camera-frame
        points) of those with a row-constrained stereo match."""
        uv_l, d_l = self._detect(left)
        uv_r, d_r = self._detect(right)
        empty = (np.zeros((0, 32), np.uint8), np.zeros((0, 3)))
        if len(uv_l) == 0 or len(uv_r) == 0:
            return uv_l, d_l, *empty
        disp = uv_l[:, None, 0] - uv_r[None, :, 0]
        mask = (np.abs(uv_l[:, None, 1] - uv_r[None, :, 1]) <= self.p.row_tol_px) & (disp >= self.p.min_disparity_px)
        matches = [m for m in self.bf.match(d_l, d_r, mask.astype(np.uint8)) if m.distance <= self.p.max_hamming]
        if not matches:
            return uv_l, d_l, *empty
        il = np.array([m.queryIdx for m in matches])
        ir = np.array([m.trainIdx for m in matches])
        d = (uv_l[il, 0] - uv_r[ir, 0]).astype(float)
        Z = self.rig.fb / d
        v = 0.5 * (uv_l[il, 1] + uv_r[ir, 1])
        X = np.column_stack([(uv_l[il, 0] - self.rig.px) * Z / self.rig.f_px, (v - self.rig.py) * Z / self.rig.f_px, Z])
        return uv_l, d_l, d_l[il], X

    def _pnp(self, uv: np.ndarray, desc: np.ndarray) -> np.ndarray | None:
        """T_prev_curr of the left camera from the previous frame's points, or None (lost)."""
        assert self.prev is not None
        d_prev, X_prev = self.prev
        if len(d_prev) < self.p.min_inliers or len(desc) < 2:
            return None
        pairs = self.bf.knnMatch(d_prev, desc, k=2)
        good = [m[0] for m in pairs if len(m) == 2 and m[0].distance < self.p.ratio * m[1].distance]
        if len(good) < self.p.min_inliers:
            return None
        obj = X_prev[[m.queryIdx for m in good]]
        img = uv[[m.trainIdx for m in good]].astype(np.float64)
        ok, rvec, tvec, inliers = cv2.solvePnPRansac(
            obj, img, self.K, None, iterationsCount=self.p.iterations, reprojectionError=self.p.reproj_px,
            confidence=0.999, flags=cv2.SOLVEPNP_ITERATIVE,
        )  # fmt: skip
        if not ok or inliers is None or len(inliers) < self.p.min_inliers:
            return None
        T_curr_prev = se3(cv2.Rodrigues(rvec)[0], tvec.ravel())
        return se3_inverse(T_curr_prev)

    def step(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, bool]:
        """(T_world_robot, tracked) after this pair; the first pair sets the origin."""
        uv, desc, d3, X = self._stereo(left, right)
        tracked = True
        if self.prev is not None:
            T = self._pnp(uv, desc)
            if T is None:
                tracked = False
                self.lost += 1
            else:
                self.motion = T
            self.T_W_C = self.T_W_C @ self.motion
        self.prev = (d3, X)
        return self.T_W_C @ se3_inverse(self.T_R_C), tracked


def run_pnp(source: str, max_frames: int = 0, params: PnPParams = PnPParams()) -> dict[str, Any]:
    """Run the baseline over ``source`` (any camera URL robotd replays); a summary with the keys of
    :func:`robotd.tools.replay.replay`'s that apply (frames, lost_frames, step_ms_p50/p95, wall_s and the
    ``truth_*`` metrics when the source carries truth)."""
    # the replay's own evaluation (truth relative to its first pose, evaluate_trajectories), so the
    # baseline and robotd are judged by the same code
    from robotd.tools.replay import _truth_metrics

    stamps: list[int] = []
    poses: list[np.ndarray] = []
    truths: list[tuple[int, np.ndarray]] = []
    ms: list[float] = []
    t_wall = time.monotonic()
    with drivers.open_camera(source) as camera:
        vo = PnPOdometry(camera.rectified_model(), params)
        for frame in camera.frames(timeout_s=1.0):
            t0 = time.perf_counter()
            T, _ = vo.step(frame.left, frame.right)
            ms.append(1e3 * (time.perf_counter() - t0))
            stamps.append(frame.t_ns)
            poses.append(T)
            if frame.truth_T_world_robot is not None:
                truths.append((frame.t_ns, frame.truth_T_world_robot))
            if max_frames and len(poses) >= max_frames:
                break
    if not poses:
        raise RobotdError(f"{source}: no frame was processed")
    summary: dict[str, Any] = {
        "source": source,
        "frames": len(poses),
        "lost_frames": vo.lost,
        "step_ms_p50": float(np.percentile(ms, 50)),
        "step_ms_p95": float(np.percentile(ms, 95)),
        "wall_s": time.monotonic() - t_wall,
    }
    if truths:
        summary.update(_truth_metrics(np.array(stamps, np.int64), np.stack(poses), truths))
    return summary
