"""Tuning of the SLAM core: ``SlamParams`` (every default documented in docs/slam.md) and the
default field-of-view test the filters prune landmarks with.

Which motion covariance wins (``SlamParams.motion_cov_source``):

- ``"auto"`` (default): the ``MotionIncrement.cov`` of the message when it has any non-zero
  entry, otherwise the parametric noise model of docs/math.md §6.2 (2D) / §6.3 (3D);
- ``"message"``: always the message's covariance (zeros allowed: a deterministic motion);
- ``"model"``: always the parametric model.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from robotd.core.choices import MEASUREMENTS
from robotd.core.errors import ConfigError

MOTION_COV_SOURCES = ("auto", "message", "model")

# Visibility test for landmark pruning: landmark positions in the robot frame, (M, dim) -> (M,) bool
VisibleFn = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True, slots=True)
class SlamParams:
    """Tuning of the SLAM core. Every default is documented in docs/slam.md.

    Units: metres, radians. Tuples of six are the a0…a5 / α1…α6 coefficients of the 2D models.
    """

    filter: str = "fastslam2"  # a registered name (robotd.slam.factory): make_estimator refuses others
    dim: int = 3  # 2 (x, y, yaw) or 3 (x, y, z, roll, pitch, yaw)
    n_particles: int = 100  # FastSLAM particle count N (docs/math.md §10)
    n_particles_min: int = 10  # floor for set_particles: min(n_particles_min, n_particles)
    resample_neff_ratio: float = 0.5  # resample when N_eff < ratio·N
    motion_cov_source: str = "auto"  # "auto" | "message" | "model" (see module docstring)
    # 2D odometry-increment model, §6.2: (a0 [m|rad], a1 [-], a2 [-], a3 [rad/m], a4 [-], a5 [rad])
    odo2d_a: tuple[float, float, float, float, float, float] = (0.002, 0.05, 0.02, 0.035, 0.05, 0.001)
    # 2D velocity model, §6.1: Thrun's α1…α6 (variances per squared control)
    vel2d_alpha: tuple[float, float, float, float, float, float] = (0.0025, 1e-4, 3e-4, 0.0025, 1e-4, 1e-4)
    # 3D model, §6.3: σ_dp,i = dp_rel_i·|Δp| + sigma_dp_m_i; σ_ω,i = rot_per_m_i·|Δp| + rot_rel·|ω_i| + sigma_rot_rad_i
    motion3d_sigma_dp_m: tuple[float, float, float] = (0.002, 0.002, 0.002)
    motion3d_dp_rel: tuple[float, float, float] = (0.05, 0.02, 0.02)
    motion3d_sigma_rot_rad: tuple[float, float, float] = (0.001, 0.001, 0.001)
    motion3d_rot_per_m: tuple[float, float, float] = (0.01, 0.01, 0.035)
    motion3d_rot_rel: float = 0.05
    # EKF χ² gate on the innovation (§8): χ²_{3,0.99} and χ²_{2,0.99}
    gate_enabled: bool = True
    gate_chi2_3d: float = 11.345
    gate_chi2_2d: float = 9.210
    # FastSLAM: drop a frame's re-observations whose innovation at the best particle exceeds the χ²
    # gate (pose prior + landmark + measurement covariance); skipped when it would drop over half.
    # Off by default: the pipeline's RANSAC stage already screens correspondences, and with the
    # visual-only prior (whose covariance is optimistic) the gate raised kitti-seq1 drift from
    # 0.98 % to 1.64 %. Without an outlier stage it helps a lot (5 % mismatches: 5.1 m -> 0.6 m).
    fastslam_gate: bool = False
    # FastSLAM 2.0 importance weight (docs/slam.md "Weights and pose estimate"): "prior" is §10's
    # product of per-observation marginals at x̂ with S; "sequential" the chain rule from the
    # proposal's own innovations (exact to first order, no extra cost)
    fs2_weights: str = "sequential"
    # FastSLAM pose output: "mixture" = the Rao-Blackwellised estimate (2.0: weights before
    # resampling over the proposals N(μ_x, Σ_x); 1.0: the weighted samples before resampling);
    # "particles" = §10's weighted mean and spread of the particles as they are after the step
    pose_estimate: str = "mixture"
    # Landmark existence counter (§8 bookkeeping) and the default field-of-view test
    prune_enabled: bool = True
    fov_h_rad: float = math.radians(73.0)  # horizontal field of view (OAK-D at 640×400)
    fov_v_rad: float = math.radians(50.0)  # vertical field of view (3D only)
    min_range_m: float = 0.3  # X_min of §2.2
    max_range_m: float = 6.5  # far limit of §2.2 for the OAK-D (fb / d_min)
    # Covariance floors (variances added to diagonals to keep Cholesky factors defined)
    process_cov_floor: float = 1e-10  # on S_t (FastSLAM 2.0 needs a full-rank proposal prior)
    landmark_cov_floor: float = 1e-12  # on new landmark covariances
    pose_cov_floor_2d: float = 1e-6  # z/roll/pitch variances a 2D filter reports in its 6×6
    landmark_block_size: int = 64  # FastSLAM copy-on-write block of landmark slots (docs/slam.md)
    # Measurement model (docs/slam.md "Measurement models"): "cartesian" = the triangulated point in the
    # robot frame with its first-order covariance (§7.1/§7.2, the thesis's); "pixel" = the landmark's
    # pixels in the rectified pair, z = (x_L, x_R, y) in 3D and (x_L, x_R) in 2D, constant noise
    measurement: str = "cartesian"
    # the rectified rig the pixel model projects with: (f [px], p_x [px], p_y [px], baseline [m])
    stereo_intrinsics: tuple[float, ...] = ()
    # pixel model noise: σ of each column (x_L, x_R) and of the row y [px] (independent)
    pixel_sigma_px: tuple[float, float] = (0.5, 0.5 / math.sqrt(2.0))
    numba_threads: int = 0  # threads of the numba kernel; 0 = numba's default (all cores)

    def __post_init__(self) -> None:
        def bad(key: str, expected: str, got: Any) -> ConfigError:
            return ConfigError(f"slam.{key}: expected {expected}, got {got!r}")

        if self.dim not in (2, 3):
            raise bad("dim", "2 or 3", self.dim)
        if int(self.n_particles) < 1:
            raise bad("n_particles", ">= 1", self.n_particles)
        if int(self.landmark_block_size) < 1:
            raise bad("landmark_block_size", ">= 1", self.landmark_block_size)
        if int(self.numba_threads) < 0:
            raise bad("numba_threads", ">= 0", self.numba_threads)
        if int(self.n_particles_min) < 1:
            raise bad("n_particles_min", ">= 1", self.n_particles_min)
        if not 0.0 <= self.resample_neff_ratio <= 1.0:
            raise bad("resample_neff_ratio", "in [0, 1]", self.resample_neff_ratio)
        if self.fs2_weights not in ("prior", "sequential"):
            raise bad("fs2_weights", "prior | sequential", self.fs2_weights)
        if self.pose_estimate not in ("mixture", "particles"):
            raise bad("pose_estimate", "mixture | particles", self.pose_estimate)
        if self.measurement not in MEASUREMENTS:
            raise bad("measurement", " | ".join(MEASUREMENTS), self.measurement)
        if self.measurement == "pixel":
            si = self.stereo_intrinsics
            if len(si) != 4 or not (si[0] > 0 and si[3] > 0):
                raise bad("stereo_intrinsics", "(f_px > 0, px, py, baseline_m > 0) for measurement = pixel", si)
            if len(self.pixel_sigma_px) != 2 or min(self.pixel_sigma_px) <= 0:
                raise bad("pixel_sigma_px", "(σ columns, σ row) > 0", self.pixel_sigma_px)
        if self.motion_cov_source not in MOTION_COV_SOURCES:
            raise bad("motion_cov_source", " | ".join(MOTION_COV_SOURCES), self.motion_cov_source)
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, tuple):
                if not all(isinstance(e, int | float) and math.isfinite(e) and e >= 0 for e in v):
                    raise bad(f.name, "finite non-negative numbers", v)
            elif isinstance(v, float) and not (math.isfinite(v) and v >= 0):
                raise bad(f.name, "a finite non-negative number", v)
        if not (0 < self.fov_h_rad < 2 * math.pi and 0 < self.fov_v_rad < math.pi):
            raise bad("fov_h_rad/fov_v_rad", "in (0, 2π) / (0, π)", (self.fov_h_rad, self.fov_v_rad))
        if self.max_range_m <= self.min_range_m:
            raise bad("max_range_m", f"> min_range_m={self.min_range_m}", self.max_range_m)


def fov_visibility(params: SlamParams) -> VisibleFn:
    """Default field-of-view test: in range [min, max] and within the horizontal (and, in 3D, vertical) FOV.

    Points are in the robot frame (FRD): X forward, Y right, Z down.
    """
    tan_h = math.tan(min(params.fov_h_rad, math.pi - 1e-6) / 2.0)
    tan_v = math.tan(params.fov_v_rad / 2.0)
    rmin, rmax = params.min_range_m, params.max_range_m

    def visible(p: np.ndarray) -> np.ndarray:
        X = p[:, 0]
        rng_ = np.linalg.norm(p, axis=1)
        ok = (X > 0) & (np.abs(p[:, 1]) <= tan_h * X) & (rng_ >= rmin) & (rng_ <= rmax)
        if p.shape[1] == 3:
            ok &= np.abs(p[:, 2]) <= tan_v * X
        return ok

    return visible
