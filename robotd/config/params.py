"""The configuration (robotd.config) translated into the core's parameter objects.

The core modules take their own frozen parameter dataclasses (FrontendParams, SlamParams) and never
see the config tree; this is the one place that maps config keys onto them.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from robotd.config import Config
from robotd.core.errors import ConfigError
from robotd.core.outliers import OutlierParams
from robotd.core.stereo import RectifiedStereo
from robotd.frontend.association import AssociationParams
from robotd.frontend.detectors import DetectorParams
from robotd.frontend.disparity_bias import DisparityBiasParams
from robotd.frontend.frontend import FrontendParams
from robotd.frontend.pnp import PnpParams
from robotd.frontend.stereo_match import StereoMatchParams
from robotd.pipeline.odometry import OdometryLimits
from robotd.slam.params import SlamParams


def frontend_params_from_config(cfg: Config, max_features: int | None = None) -> FrontendParams:
    """``frontend.*`` keys; ``max_features`` overrides ``frontend.max_features`` (the latency budget)."""
    f = cfg.frontend
    det = DetectorParams(
        name=f.detector,
        max_features=max_features or f.max_features,
        bucketing=f.bucketing,
        grid_rows=f.grid_rows,
        grid_cols=f.grid_cols,
    )
    stereo = StereoMatchParams(
        row_tol_px=f.row_tolerance_px,
        d_min_px=f.disparity_min_px,
        depth_min_m=f.depth_min_m,
        sigma_x_px=f.sigma_x_px,
        sigma_y_px=f.sigma_y_px,
        cov_inflation=f.cov_inflation,
        debias_depth=f.debias_depth,
        debias_limits=f.debias_limits,
    )
    outl = OutlierParams(
        method=f.outliers,
        confidence=f.consensus_confidence,
        max_iterations=f.ransac_max_iterations,
        min_inliers=f.min_inliers,
    )
    assoc = AssociationParams(guided_radius_px=f.guided_radius_px)
    return FrontendParams(
        detector=det,
        stereo=stereo,
        association=assoc,
        outliers=outl,
        parallel_detect=f.parallel_detect,
        motion_method=f.motion,
        pnp=PnpParams(
            inlier_px=f.pnp_inlier_px,
            sigma_px=f.sigma_x_px,
            two_view_iterations=f.pnp_two_view_iterations,
            align_px=f.pnp_align_px,
        ),
        guided=f.guided_matching,
        planar_map=cfg.slam.dim == 2,
        disparity_bias=DisparityBiasParams(
            mode=f.disparity_offset, walk_px=f.disparity_offset_walk_px, max_sigma_px=f.disparity_offset_max_sigma_px
        ),
    )


def slam_params_from_config(cfg: Config, rig: RectifiedStereo | None = None) -> SlamParams:
    """``slam.*`` keys (and the particle floor of ``budget.min_particles``); with a ``rig``, the
    pruning field of view and range follow the rig and the disparity limits (docs/math.md §2.2). The pixel
    measurement model (``slam.measurement = "pixel"``) needs the rig: it projects with its
    intrinsics, with the front end's pixel noise σ·√cov_inflation."""
    n_min = max(1, min(cfg.budget.min_particles, cfg.slam.n_particles))
    f = cfg.frontend
    inflate = float(np.sqrt(f.cov_inflation))
    kw: dict[str, Any] = {
        "filter": cfg.slam.filter,
        "dim": cfg.slam.dim,
        "n_particles": cfg.slam.n_particles,
        "n_particles_min": n_min,
        "resample_neff_ratio": cfg.slam.resample_neff_ratio,
        "fs2_weights": cfg.slam.fs2_weights,
        "numba_threads": cfg.slam.numba_threads,
        "measurement": cfg.slam.measurement,
        "pixel_sigma_px": (f.sigma_x_px * inflate, f.sigma_y_px * inflate),
    }
    if rig is not None:
        kw["fov_h_rad"] = float(2 * np.arctan2(rig.width / 2.0, rig.f_px))
        kw["fov_v_rad"] = float(2 * np.arctan2(rig.height / 2.0, rig.f_px))
        kw["min_range_m"] = f.depth_min_m
        kw["max_range_m"] = max(f.depth_min_m * 1.01, rig.fb / f.disparity_min_px)
        kw["stereo_intrinsics"] = (rig.f_px, rig.px, rig.py, rig.baseline_m)
    elif cfg.slam.measurement == "pixel":
        raise ConfigError("slam.measurement: 'pixel' needs the stereo rig's intrinsics, and none was given")
    return SlamParams(**kw)


def odometry_limits_from_config(cfg: Config) -> OdometryLimits:
    """``vehicle.max_*``: what a vehicle sample may be before it is refused."""
    v = cfg.vehicle
    return OdometryLimits(v.max_speed_mps, v.max_accel_mps2, v.max_rate_radps, v.max_future_s)
