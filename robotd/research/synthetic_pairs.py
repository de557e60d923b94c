"""Synthetic landmark correspondences with known truth, for the outlier stage's tests and benchmark.

One frame of docs/math.md §12.3: a robot at a random pose sees ``n`` landmarks; each measurement
is made the stereo way (project to pixels, add σ = 0.5 px noise, triangulate, covariance of §3.1),
so its noise is the true stereo noise, not a 3-D Gaussian. Map landmarks carry their own
covariance A_i (a fused estimate: the stereo covariance of an earlier, closer view, in the world
frame) and a mean drawn from it. A fraction of the pairs is then corrupted: half of the wrong
partners are "near" landmarks 0.25–1 m from the true one (repeated texture), half are random
other landmarks of the map. The left-image pixels of each pair at t−1 and t are produced too, so
the fundamental-matrix baseline sees the same correspondences (§5.4).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from robotd.core.geometry import euler_to_R, se3, se3_inverse
from robotd.core.stereo import RectifiedStereo, project, triangulate, triangulation_covariance

# the project's OAK-D rig at 640×400 (docs/math.md §12)
OAKD_RIG = RectifiedStereo(f_px=430.0, px=319.5, py=199.5, baseline_m=0.0755, width=640, height=400)


@dataclass(frozen=True, slots=True, eq=False)
class SyntheticPairs:
    """Putative correspondences with truth.

    a: (N, 3) map landmarks (world) with covariances A (N, 3, 3); b: (N, 3) measurements (robot
    frame) with B (N, 3, 3); x1, x2: (N, 2) left-image pixels of each pair at t−1 and t;
    is_mismatch: (N,) truth; T_world_robot: (4, 4) the true pose at t.
    """

    a: np.ndarray
    A: np.ndarray
    b: np.ndarray
    B: np.ndarray
    x1: np.ndarray
    x2: np.ndarray
    is_mismatch: np.ndarray
    T_world_robot: np.ndarray


def _stereo_measure(
    xyz_R: np.ndarray, rig: RectifiedStereo, sigma_px: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Noisy stereo measurement of robot-frame points: (xyz (N, 3), cov (N, 3, 3), left pixels (N, 2))."""
    f, px, py, b = rig.f_px, rig.px, rig.py, rig.baseline_m
    xl, xr, y = project(xyz_R, f, px, py, b)
    n = xyz_R.shape[0]
    xl = xl + rng.normal(0.0, sigma_px, n)
    xr = xr + rng.normal(0.0, sigma_px, n)
    # the two rows are measured separately; triangulation uses their mean (σ/√2)
    y = y + rng.normal(0.0, sigma_px, n) / np.sqrt(2.0)
    xr = np.minimum(xr, xl - 1e-3)  # keep disparity positive even at the far limit
    xyz = triangulate(xl, xr, y, f, px, py, b)
    cov = triangulation_covariance(xl, xr, y, f, px, py, b, sigma_px, sigma_px / np.sqrt(2.0))
    return xyz, cov, np.c_[xl, y]


def simulate_pairs(
    rng: np.random.Generator,
    n: int = 40,
    mismatch_rate: float = 0.2,
    rig: RectifiedStereo = OAKD_RIG,
    depth_range_m: tuple[float, float] = (0.5, 5.0),
    sigma_px: float = 0.5,
    map_cov_scale: float = 0.5,
    near_fraction: float = 0.5,
    near_range_m: tuple[float, float] = (0.25, 1.0),
    step_m: float = 0.1,
) -> SyntheticPairs:
    """One frame of putative correspondences (module doc). ``step_m``: forward motion since t−1."""
    # landmarks uniform in the view frustum, depth uniform in the range
    X = rng.uniform(*depth_range_m, n)
    u = rng.uniform(0.05 * rig.width, 0.95 * rig.width, n)
    v = rng.uniform(0.05 * rig.height, 0.95 * rig.height, n)
    xyz_R = np.c_[X, (u - rig.px) * X / rig.f_px, (v - rig.py) * X / rig.f_px]
    yaw = rng.uniform(-np.pi, np.pi)
    rp = rng.normal(0.0, 0.05, 2)
    T_wr = se3(euler_to_R(np.array([rp[0], rp[1], yaw])), rng.normal(0.0, 5.0, 3) * np.array([1.0, 1.0, 0.1]))
    Rw, tw = T_wr[:3, :3], T_wr[:3, 3]
    xyz_W = xyz_R @ Rw.T + tw
    # map estimates: covariance of a closer earlier view (fused, scaled), rotated into the world
    _, Q_prev, _ = _stereo_measure(xyz_R * 0.9, rig, sigma_px, rng)
    A = map_cov_scale * np.einsum("ij,njk,lk->nil", Rw, Q_prev, Rw)
    a = xyz_W + np.einsum("nij,nj->ni", np.linalg.cholesky(A), rng.normal(size=(n, 3)))
    b, B, x2 = _stereo_measure(xyz_R, rig, sigma_px, rng)
    # the previous pose: step_m behind along the robot's X, with a small yaw change
    T_prev = T_wr @ se3(euler_to_R(np.array([0.0, 0.0, rng.normal(0.0, 0.02)])), np.array([-step_m, 0.0, 0.0]))
    T_prev_w = se3_inverse(T_prev)

    def left_px_prev(p_W: np.ndarray) -> np.ndarray:
        p = p_W @ T_prev_w[:3, :3].T + T_prev_w[:3, 3]
        xl, _, y = project(np.where(p[:, :1] > 0.05, p, 0.05), rig.f_px, rig.px, rig.py, rig.baseline_m)
        return np.c_[xl, y] + rng.normal(0.0, sigma_px, (p.shape[0], 2))

    x1 = left_px_prev(xyz_W)
    bad = np.zeros(n, bool)
    k = round(mismatch_rate * n)
    if k:
        idx = rng.choice(n, size=k, replace=False)
        bad[idx] = True
        n_near = round(near_fraction * k)
        near, far = idx[:n_near], idx[n_near:]
        # near: a different landmark 0.25–1 m away from the true one, with its own estimate
        d = rng.normal(size=(near.size, 3))
        d *= (rng.uniform(*near_range_m, near.size) / np.linalg.norm(d, axis=1))[:, None]
        p_true = xyz_W[near] + d
        a[near] = p_true + np.einsum("nij,nj->ni", np.linalg.cholesky(A[near]), rng.normal(size=(near.size, 3)))
        x1[near] = left_px_prev(p_true)
        # far: a random other landmark of the map (a derangement within the corrupted set)
        if far.size:
            others = rng.permutation(np.setdiff1d(np.arange(n), far))[: far.size] if n - far.size >= far.size else None
            partner = others if others is not None else np.roll(far, 1)
            a_new, A_new, x1_new = a[partner].copy(), A[partner].copy(), x1[partner].copy()
            a[far], A[far], x1[far] = a_new, A_new, x1_new
    return SyntheticPairs(a, A, b, B, x1, x2, bad, T_wr)
