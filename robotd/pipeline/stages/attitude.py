"""The filter's attitude against the world's vertical (3D): the vehicle's measured gravity fused
into the filter (docs/slam.md "Gravity"), and an attitude no rover can have reset to level
(docs/reliability.md)."""

from __future__ import annotations

import logging
import math

import numpy as np

from robotd.config import Config
from robotd.core.geometry import R_to_euler
from robotd.frontend.frontend import Frontend
from robotd.pipeline.relocalise import RESET_COV
from robotd.pipeline.stages.motion import MotionModel
from robotd.pipeline.stages.tracking import PipelineCounters
from robotd.slam.estimator import Estimator

logger = logging.getLogger("robotd.pipeline")  # the step's lines keep the name users filter them by

# The filter's gate may refuse the measured gravity for this long before its roll and pitch are
# reopened to it (Attitude.fuse_gravity): longer than a bump or a glitch, short of a visible tilt.
GRAVITY_REOPEN_S = 1.0
# time constant of the gravity bias's low-pass (GravityBias): several laps of a small loop
GRAVITY_BIAS_TAU_S = 60.0
# the largest bias it takes (3°): an IMU mounted further off is a calibration to fix, and a cap keeps
# a filter that is far off (after a stall, say) from being taken for the sensor's bias
GRAVITY_BIAS_MAX_RAD = math.radians(3.0)


class GravityBias:
    """The measured direction of gravity's bias in the robot frame (a tilted or uncalibrated IMU),
    learnt from the residual against the filter's own attitude, g_R − R̂ᵀ g_W, by a first-order
    low-pass of time constant ``tau_s`` (0: off), and taken off each measurement.

    A bias fixed in the robot frame tilts every measurement the same way in that frame; an error
    of the filter's attitude (of the map's) is fixed in the world and turns in the robot frame as
    the rover turns, so over a few turns the mean residual is the bias. Fused uncorrected, a bias
    of b rad pulls the pose's pitch off the map's by b, and z drifts by b per metre driven (0.5 %
    for the simulator's 0.005 rad). On a straight drive the two cannot be told apart, and the
    low-pass takes in slow attitude drift as well: tau_s is long against a turn."""

    def __init__(self, tau_s: float) -> None:
        self.tau_s = tau_s
        self.b = np.zeros(3)
        self._t_ns: int | None = None

    def correct(self, g_R: np.ndarray, h_R: np.ndarray, t_ns: int) -> np.ndarray:
        if self.tau_s <= 0:
            return g_R
        if self._t_ns is not None and t_ns > self._t_ns:
            a = min(1.0, (t_ns - self._t_ns) * 1e-9 / self.tau_s)
            r = g_R - h_R
            r -= (r @ g_R) * g_R  # across the direction
            self.b += a * (r - self.b)
            n = float(np.linalg.norm(self.b))
            if n > GRAVITY_BIAS_MAX_RAD:  # a mounting error, not the filter's whole attitude error
                self.b *= GRAVITY_BIAS_MAX_RAD / n
        self._t_ns = t_ns
        g = g_R - (self.b - (self.b @ g_R) * g_R)
        return g / np.linalg.norm(g)  # type: ignore[no-any-return]


class Attitude:
    """The vehicle's gravity into the filter (:meth:`fuse_gravity`), and the check and reset of
    an implausible attitude (:meth:`implausible`, :meth:`level`). ``reset_at``: the t_ns of the
    frame whose attitude was last reset (that frame is reported lost)."""

    def __init__(
        self,
        cfg: Config,
        frontend: Frontend,
        estimator: Estimator,
        motion: MotionModel,
        counters: PipelineCounters,
    ) -> None:
        self.cfg = cfg
        self.frontend = frontend
        self.estimator = estimator
        self.motion = motion
        self.counters = counters
        self.reset_at: int | None = None
        # the direction of gravity in the world frame (3D, slam.gravity): from the first measurement
        self.gravity_W: np.ndarray | None = None
        self._refused_since: int | None = None  # t_ns of the first of the refusals in a row
        self._bias = GravityBias(GRAVITY_BIAS_TAU_S if cfg.slam.gravity_bias else 0.0)

    def fuse_gravity(self, g_R: np.ndarray, sigma_rad: float, t_ns: int) -> None:
        """The vehicle's measured direction of gravity into the filter (docs/slam.md "Gravity").
        The world frame is the robot's at the start, not necessarily level: gravity's direction in
        it is taken once, from the first measurement and the pose then, and held.

        The filter's gate refuses a measurement that does not fit its roll and pitch (a glitch, a
        hard bump). When it has refused every one for ``GRAVITY_REOPEN_S``, the filter is the one
        that is wrong (over-confident after an unmodelled gyro bias): the next is fused with roll
        and pitch reopened, so the gate cannot lock the reference out for good."""
        g_R = g_R / np.linalg.norm(g_R)
        if g_R[2] < math.cos(math.radians(self.cfg.vehicle.max_tilt_deg)):
            # implausible for a rover (and a pitch of 90° is the filter's singularity): never fused,
            # never counted toward reopening
            self.counters.gravity_implausible += 1
            if self.counters.gravity_implausible in (1, 10, 100, 1000):
                logger.warning(
                    "gravity refused (%d so far): tilted %.1f° from the robot's vertical, beyond vehicle.max_tilt_deg",
                    self.counters.gravity_implausible,
                    math.degrees(math.acos(max(-1.0, min(1.0, float(g_R[2]))))),
                )
            return
        R_est = self.estimator.estimate().T_world_robot[:3, :3]
        if self.gravity_W is None:
            self.gravity_W = R_est @ g_R
            logger.info("gravity in the world frame: %s (the first measurement)", self.gravity_W.round(4))
        g_R = self._bias.correct(g_R, R_est.T @ self.gravity_W, t_ns)
        since = self._refused_since
        reopen = since is not None and t_ns - since >= GRAVITY_REOPEN_S * 1e9
        fused, nis = self.estimator.update_gravity(g_R, self.gravity_W, sigma_rad, reopen=reopen)
        if not fused:
            self.counters.gravity_rejected += 1
            if since is None:
                self._refused_since = t_ns
            return
        self.counters.gravity_fused += 1
        self._refused_since = None
        if reopen and since is not None:
            self.counters.gravity_reopened += 1
            logger.warning("gravity refused for %.1f s: roll and pitch reopened (NIS %.0f)", (t_ns - since) / 1e9, nis)

    def implausible(self) -> float | None:
        """3D: the estimate's tilt [deg] (its vertical against the world's, the measured gravity's
        when there is one) when it is beyond ``vehicle.max_tilt_deg``, where no rover drives;
        else None."""
        if self.cfg.slam.dim != 3:
            return None
        R = self.estimator.estimate().T_world_robot[:3, :3]
        down = self.gravity_W if self.gravity_W is not None else np.array([0.0, 0.0, 1.0])
        tilt = math.degrees(math.acos(max(-1.0, min(1.0, float(R[:, 2] @ down)))))
        return tilt if tilt > self.cfg.vehicle.max_tilt_deg or not math.isfinite(tilt) else None

    def level(self, t_ns: int) -> None:
        """The filter's roll and pitch were implausible (:meth:`implausible`) or at the ZYX
        singularity: put the pose level against the world's vertical, keeping its position and
        heading (``RESET_COV`` about it), and report the frame lost. Nothing measured the tilt it
        had (vision alone has no absolute vertical), so level is the rover's likeliest attitude; a
        vehicle's gravity, when it has one, then holds it."""
        self.frontend.disparity_bias.reset_tracks()  # the anchor's pose is no longer this map's
        est = self.estimator.estimate()
        T = est.T_world_robot
        R = T[:3, :3]
        down = self.gravity_W if self.gravity_W is not None else np.array([0.0, 0.0, 1.0])
        x_ax, z_ax = R[:, 0], R[:, 2]
        # the heading: the forward axis across the vertical; near pitch ±90° the vertical axis
        # gives it (nose up: z points where the nose did)
        h = (x_ax - (x_ax @ down) * down) - (x_ax @ down) * (z_ax - (z_ax @ down) * down)
        if float(np.linalg.norm(h)) < 1e-6:
            h = np.cross(down, [0.0, 1.0, 0.0]) if abs(down[1]) < 0.9 else np.cross(down, [1.0, 0.0, 0.0])
        h = h / np.linalg.norm(h)
        R_level = np.column_stack([h, np.cross(down, h), down])
        rpy = R_to_euler(R_level)
        tilt = math.degrees(math.acos(max(-1.0, min(1.0, float(z_ax @ down)))))
        self.counters.attitude_resets += 1
        self.reset_at = t_ns
        logger.warning(
            "attitude implausible (tilted %.1f° from the vertical, roll %.1f° pitch %.1f°; vehicle.max_tilt_deg %.0f°):"
            " roll and pitch reset to level, heading %.1f° and position kept (%d so far)",
            tilt,
            math.degrees(est.rpy_rad[0]),
            math.degrees(est.rpy_rad[1]),
            self.cfg.vehicle.max_tilt_deg,
            math.degrees(rpy[2]),
            self.counters.attitude_resets,
        )
        x = np.r_[T[:3, 3], rpy] if self.estimator.dim == 3 else np.r_[T[:2, 3], rpy[2]]
        self.estimator.reset_pose(x, RESET_COV if self.estimator.dim == 3 else RESET_COV[np.ix_([0, 1, 5], [0, 1, 5])])
        # the constant-velocity model's last pose is the implausible one
        self.motion.last_pose = None
