"""A minimal inline landmark world for the SLAM core's scenario tests (not robotd.research.landmark_sim).

Ground truth poses along a gentle arc, landmarks on a ring around the path, measurements of the
landmarks within ``max_range`` in front of the robot, with optional Gaussian noise in the robot frame;
or, with a stereo ``rig``, Gaussian noise on the landmarks' pixels in the rectified pair, triangulated
(the front end's measurements: points, their first-order covariances and the pixels).
"""

from __future__ import annotations

import numpy as np

from robotd.core.geometry import euler_to_R, wrap_angle
from robotd.core.msgs import MotionIncrement, Observations
from robotd.core.stereo import project, triangulate, triangulation_covariance

# a KITTI-like rectified rig (f [px], p_x [px], p_y [px], baseline [m]) for the pixel-noise worlds
KITTI_RIG = (718.0, 607.0, 185.0, 0.54)


class World:
    def __init__(
        self,
        dim: int,
        rng: np.random.Generator,
        n_landmarks: int = 60,
        step_m: float = 0.2,
        yaw_step: float = 0.03,
        max_range: float = 6.0,
        sigma_z: float = 0.0,
        sigma_odo: float = 0.0,
        rig: tuple[float, float, float, float] | None = None,
        sigma_px: float = 0.0,
    ) -> None:
        self.dim, self.rng = dim, rng
        self.rig, self.sigma_px = rig, sigma_px
        self.step_m, self.yaw_step, self.max_range = step_m, yaw_step, max_range
        self.sigma_z, self.sigma_odo = sigma_z, sigma_odo
        ang = rng.uniform(0, 2 * np.pi, n_landmarks)
        rad = rng.uniform(2.0, 10.0, n_landmarks)
        self.L = np.stack([rad * np.cos(ang) + 3.0, rad * np.sin(ang) + 3.0, rng.uniform(-1.5, 0.5, n_landmarks)], 1)
        if dim == 2:
            self.L[:, 2] = 0.0
        self.ids = np.arange(n_landmarks, dtype=np.int64) * 1_000_003 + 7  # large, sparse ids
        self.x = np.zeros(6)  # true pose (x, y, z, roll, pitch, yaw)
        self.seen: set[int] = set()
        self.t = 0

    def step(self) -> MotionIncrement:
        dp = np.array([self.step_m, 0.0, 0.0])
        dr = np.array([0.0, 0.0, self.yaw_step])
        if self.dim == 3:
            # small roll/pitch oscillation of a vehicle on uneven ground
            dr[0] = 0.01 * np.cos(0.3 * self.t)
            dr[1] = 0.01 * np.sin(0.2 * self.t)
            dp[2] = 0.01 * np.sin(0.25 * self.t)
        R = euler_to_R(self.x[3:])
        from robotd.core.geometry import R_to_euler, so3_exp

        self.x[:3] += R @ dp
        self.x[3:] = wrap_angle(R_to_euler(R @ so3_exp(dr)))  # the §6.3 model (docs/math.md)
        self.t += 1
        n = self.rng.normal(0.0, self.sigma_odo, 6) if self.sigma_odo > 0 else np.zeros(6)
        if self.dim == 2:
            n[[2, 3, 4]] = 0.0
        cov = np.diag(np.full(6, max(self.sigma_odo, 0.0) ** 2))
        return MotionIncrement(self.t - 1, self.t, dp + n[:3], dr + n[3:], cov)

    def observe(self, sigma_z: float | None = None) -> Observations:
        s = self.sigma_z if sigma_z is None else sigma_z
        R = euler_to_R(self.x[3:])
        z = (self.L - self.x[:3]) @ R
        vis = (z[:, 0] > 0.5) & (np.linalg.norm(z, axis=1) < self.max_range)
        z = z[vis]
        ids = self.ids[vis]
        is_new = np.array([int(i) not in self.seen for i in ids], bool)
        if self.rig is not None:
            return self._observe_pixels(z, ids, is_new)
        if s > 0:
            z = z + self.rng.normal(0.0, s, z.shape)
        if self.dim == 2:
            z[:, 2] = 0.0
        cov = np.tile(np.eye(3) * max(s, 1e-3) ** 2, (len(ids), 1, 1))
        self.seen |= set(ids.tolist())
        return Observations(self.t, z, cov, ids, is_new)

    def _observe_pixels(self, z: np.ndarray, ids: np.ndarray, is_new: np.ndarray) -> Observations:
        """Pixels (x_L, x_R, y) of the true points plus N(0, σ²) noise per coordinate (the row σ/√2,
        the mean of two rows), triangulated with their first-order covariance."""
        assert self.rig is not None
        f, px, py, b = self.rig
        s = self.sigma_px
        uv = np.stack(project(z, f, px, py, b), -1)
        if s > 0:
            uv = uv + self.rng.normal(0.0, 1.0, uv.shape) * np.array([s, s, s / np.sqrt(2.0)])
        xyz = triangulate(uv[:, 0], uv[:, 1], uv[:, 2], f, px, py, b)
        sx = max(s, 1e-3)
        cov = triangulation_covariance(uv[:, 0], uv[:, 1], uv[:, 2], f, px, py, b, sx, sx / np.sqrt(2.0))
        self.seen |= set(ids.tolist())
        return Observations(self.t, xyz, cov, ids, is_new, uv)

    def pose(self) -> np.ndarray:
        return self.x[[0, 1, 5]].copy() if self.dim == 2 else self.x.copy()
