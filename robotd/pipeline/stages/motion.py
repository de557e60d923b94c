"""The motion between two frames: the prior the images' own motion is checked against, and the
increment the filter predicts with.

In order of preference (docs/math.md §6 "Where the control comes from"): the vehicle's odometry
integrated to the frame time (fused with the images' motion while the map does not fix the pose);
without it (visual only, as the thesis ran), the frame-to-frame motion the front end recovered
from the images; failing that, a constant-velocity prediction. Ground truth never reaches the
filter. Across a gap no odometry covers, robotd.pipeline.stages.gap decides instead.
"""

from __future__ import annotations

import dataclasses
import logging
import math

import numpy as np

from robotd.config import Config
from robotd.core.geometry import se3, so3_exp, so3_log
from robotd.core.msgs import LandmarkMap, MotionIncrement
from robotd.frontend.association import IDENTIFIED
from robotd.frontend.frontend import Identification, Screening
from robotd.frontend.pnp import MotionPrior, PnpParams, motion_prior
from robotd.pipeline.stages.tracking import PipelineCounters
from robotd.pipeline.stall import Reach, still_prior
from robotd.slam.common import model_cov6
from robotd.slam.estimator import Estimator
from robotd.slam.params import SlamParams

logger = logging.getLogger("robotd.pipeline")

# the odometry and the images' motion over one interval are fused when they agree within this
# Mahalanobis distance (χ²(6) at 0.999)
FUSE_CHI2 = 22.458
VELOCITY_INTERVALS = 3  # measured intervals the constant-velocity model averages
# a map fix is refused when the pose its consensus implies is farther from the prediction than
# FIX_SIGMAS standard deviations of the prediction and than the reach of the filter's update,
# which is linearised at the prediction: on the open-terrain lap a right consensus 17 m and 6°
# away became a pose 85 m and 58° off (docs/slam.md "Map fixes the prediction cannot explain")
FIX_SIGMAS = 5.0
FIX_REACH_M = 1.0
FIX_REACH_RAD = math.radians(5.0)


class MotionModel:
    """The motion priors, the choice of the filter's increment, and the constant-velocity model.

    State between frames: the last frame's time ``last_t_ns`` (None before the first frame and
    after a map load), the filter's last pose ``last_pose`` (t_ns, T_world_robot) and its motion
    over the last measured interval ``velocity`` (R, t, dt_s, σ_t, σ_rot), the last measured
    intervals ``rates`` it averages, the increment this frame measured (``measured``; None when
    it was a guess), and whether the map fixed the last frame's pose (``map_fixed``).
    """

    def __init__(
        self,
        cfg: Config,
        slam_params: SlamParams,
        pnp: PnpParams,
        estimator: Estimator,
        counters: PipelineCounters,
    ) -> None:
        self.cfg = cfg
        self.slam_params = slam_params
        self.pnp = pnp
        self.estimator = estimator
        self.counters = counters
        self.last_t_ns: int | None = None
        self.last_pose: tuple[int, np.ndarray] | None = None
        self.velocity: tuple[np.ndarray, np.ndarray, float, float, float] | None = None
        self.measured: MotionIncrement | None = None
        # the map fixed the last frame's pose (at least relocalise.MIN_INLIERS landmarks identified,
        # what a pose from the map alone needs): the images' motion is then not fused into the
        # odometry (:meth:`fuse`)
        self.map_fixed = False
        # the last measured intervals: (rotation rate, velocity, weight of each, dt_s)
        self.rates: list[tuple[np.ndarray, np.ndarray, float, float]] = []

    def forget(self) -> None:
        """Start the constant-velocity model again (the pose jumped: relocalised, a map loaded)."""
        self.last_pose, self.velocity, self.rates = None, None, []

    # ---------------------------------------------------------------- before the images' motion
    def recent_rate(self) -> float:
        """The largest turn rate [rad/s] of the last measured intervals (0 before the first): what
        blurs this frame, as far as is known before its motion is (robotd.pipeline.stages.measure)."""
        return max((float(np.linalg.norm(r[0])) for r in self.rates), default=0.0)

    def prior(self, t_ns: int, increment: MotionIncrement | None, gap: Reach | None) -> MotionPrior | None:
        """The motion prior the images are checked against: at rest across a ``gap``, else the
        odometry ``increment``, else the constant-velocity prediction (None without PnP). With
        odometry too, the images' outliers are points that moved, on a vehicle, and are not mapped."""
        if self.cfg.frontend.motion != "pnp":
            return None
        if gap is not None:
            return still_prior(gap)
        return self.constant_velocity(t_ns) if increment is None else self.odometry_prior(increment)

    def constant_velocity(self, t_ns: int) -> MotionPrior | None:
        """The constant-velocity prediction of the motion since the last frame, with the vehicle's
        physical bounds (robotd.frontend.pnp.motion_prior): the filter's motion over the last
        measured interval (odometry or visual motion), scaled to this one."""
        if self.velocity is None or self.last_pose is None or t_ns <= self.last_pose[0]:
            return None
        R, t, dt_s, sd_t, sd_r = self.velocity
        return motion_prior(R, t, dt_s, (t_ns - self.last_pose[0]) * 1e-9, self.pnp, sd_t, sd_r)

    def odometry_prior(self, odo: MotionIncrement) -> MotionPrior:
        """The odometry's increment as the motion the images are checked against: within 3σ of
        its covariance, plus the acceleration bounds over the interval (a zero covariance: the
        bounds alone)."""
        p = self.pnp
        dt = max(odo.t1_ns - odo.t0_ns, 0) * 1e-9
        C = np.asarray(odo.cov, float)
        tol_t = 3.0 * math.sqrt(max(float(np.trace(C[:3, :3])), 0.0)) + p.max_accel_mps2 * dt * dt + 0.005
        tol_r = 3.0 * math.sqrt(max(float(np.trace(C[3:, 3:])), 0.0)) + p.max_angular_accel_radps2 * dt * dt
        R = so3_exp(odo.drot_R_rad)
        return MotionPrior(R, np.asarray(odo.dp_R_m, float), tol_t, tol_r + math.radians(0.2), binding=True)

    # ---------------------------------------------------------------- the filter's increment
    def choose(
        self, odo: MotionIncrement | None, vis: MotionIncrement | None, t_ns: int, relocalising: bool
    ) -> MotionIncrement | None:
        """The increment the filter predicts with (no gap): the odometry ``odo`` (fused with the
        images' motion ``vis`` over the same interval while the map does not fix the pose), else
        ``vis``, else constant velocity; None before the first frame, and while relocalising (the
        pose comes from the map)."""
        if relocalising:
            return None
        self.measured = None
        if self.last_t_ns is None:
            return None
        if odo is not None:
            self.counters.odometry_priors += 1
            if vis is not None and vis.t0_ns == odo.t0_ns and vis.t1_ns == odo.t1_ns and not self.map_fixed:
                odo = self.fuse(odo, vis)
            self.measured = odo
            return odo
        if vis is not None and vis.t0_ns == self.last_t_ns:
            self.counters.visual_priors += 1
            self.measured = vis
            return vis
        cv = self.constant_velocity(t_ns)
        if cv is not None:
            # constant velocity: the mean of the last measured increments, scaled to this interval,
            # uncertain by what the vehicle's acceleration limits allow
            self.counters.constant_velocity_priors += 1
            sd = np.r_[np.full(3, cv.tol_t_m / 2.0), np.full(3, cv.tol_rot_rad / 2.0)]
            return MotionIncrement(self.last_t_ns, t_ns, cv.t, so3_log(cv.R), np.diag(sd * sd))
        return None

    def fuse(self, odo: MotionIncrement, vis: MotionIncrement) -> MotionIncrement:
        """The odometry's increment and the images' own motion over the same interval (both
        measurements of it, independent) fused by their covariances, in the increment's tangent
        space (dp, drot) about the odometry's. The odometry's covariance is its stated one, else
        the filter's motion model's, which is what the filter would take for it. When the two
        disagree beyond ``FUSE_CHI2`` (a scene that moved, a wheel that slipped), the odometry
        alone, as before.

        Called only while the map does not fix the pose (``map_fixed``): the images' motion then
        carries what nothing else does. Before, it was thrown away whenever odometry came, and at a
        car's metre a frame, where the map identifies nothing, the filter moved its particles by
        the motion model's noise alone (5 cm and 2° of yaw a frame) until they spread over metres.
        Where the map fixes the pose its update uses the same images, and fusing there was measured
        worse (docs/slam.md "Odometry and the images' motion")."""
        C_o = np.asarray(odo.cov, float)
        if not np.any(C_o):
            C_o = model_cov6(odo, self.slam_params)
        C_v = np.asarray(vis.cov, float)
        d = np.r_[np.asarray(vis.dp_R_m, float) - odo.dp_R_m, np.asarray(vis.drot_R_rad, float) - odo.drot_R_rad]
        S = C_o + C_v
        try:
            d2 = float(d @ np.linalg.solve(S, d))
            K = np.linalg.solve(S.T, C_o.T).T  # C_o S⁻¹
        except np.linalg.LinAlgError:
            return odo
        if not (math.isfinite(d2) and np.all(np.isfinite(K))) or d2 > FUSE_CHI2:
            self.counters.fusion_refused += 1
            return odo
        x = np.r_[odo.dp_R_m, odo.drot_R_rad] + K @ d
        C = C_o - K @ C_o
        self.counters.fused_priors += 1
        return dataclasses.replace(odo, dp_R_m=x[:3], drot_R_rad=x[3:], cov=0.5 * (C + C.T))

    def view(self, landmarks: LandmarkMap, inc: MotionIncrement | None) -> np.ndarray | None:
        """The predicted pose (the last estimate moved by the increment) that restricts
        identification to the landmarks predicted in view and guides the search for them."""
        if not self.cfg.frontend.restrict_to_fov or landmarks.n == 0:
            return None
        T = self.estimator.estimate().T_world_robot
        if inc is not None:
            T = T @ se3(so3_exp(inc.drot_R_rad), inc.dp_R_m)
        return T

    def check_fix(
        self,
        ident: Identification,
        screen: Screening,
        view: np.ndarray | None,
        inc: MotionIncrement | None,
        measured: bool,
        t_ns: int,
        tracking: bool,
    ) -> Screening:
        """``screen``, unless, while ``tracking``, the pose its consensus implies is one the
        prediction ``view`` cannot explain (:meth:`fix_is_plausible`): then its matches are neither
        fused nor mapped again this frame (``ident``'s identified correspondences are rejected),
        and the pose follows the prediction. Lost, or without a prediction, any fix is welcome."""
        if view is None or not tracking:
            return screen
        if self.fix_is_plausible(screen.similarity, view, inc, measured, t_ns):
            return screen
        ident.corr.reject(ident.corr.status == IDENTIFIED)
        return Screening(screen.result, None)

    def fix_is_plausible(
        self,
        similarity: np.ndarray | None,
        view: np.ndarray,
        inc: MotionIncrement | None,
        measured: bool,
        t_ns: int,
    ) -> bool:
        """Whether the pose the outlier stage's consensus implies (``similarity`` maps world points
        into the robot frame) may be fused, given the predicted pose ``view``: within
        ``FIX_SIGMAS`` standard deviations of the prediction (the increment's own covariance when
        ``measured`` by odometry or the images, else what the vehicle's speed and turn-rate limits
        allow since the last frame), or within the update's reach (``FIX_REACH_M``,
        ``FIX_REACH_RAD``). Beyond both, the consensus is a wrong one that agrees with itself (a
        repeated texture, few matches in a degenerate layout: on kitti-seq1, 1.9 m and 21° off
        a right prediction) or a loop closed after a long drive, which the update, linearised at
        the prediction, cannot take in one step; either way it is not fused."""
        if similarity is None or self.last_t_ns is None:
            return True
        A = np.asarray(similarity, dtype=float)
        s = float(np.cbrt(np.linalg.det(A[:3, :3])))
        if not (math.isfinite(s) and s > 0):
            return True
        R_wr = (A[:3, :3] / s).T
        p_wr = -R_wr @ A[:3, 3] / s
        dp = float(np.linalg.norm(p_wr - view[:3, 3]))
        dang = float(np.linalg.norm(so3_log(view[:3, :3].T @ R_wr)))
        if dp <= FIX_REACH_M and dang <= FIX_REACH_RAD:
            return True
        if measured and inc is not None and np.any(inc.cov):
            C = np.asarray(inc.cov, dtype=float)
            sp, sr = math.sqrt(float(np.trace(C[:3, :3]))), math.sqrt(float(np.trace(C[3:, 3:])))
        else:
            dt = max(0.0, (t_ns - self.last_t_ns) * 1e-9)
            sp = self.cfg.vehicle.max_speed_mps * dt / FIX_SIGMAS
            sr = self.cfg.vehicle.max_rate_radps * dt / FIX_SIGMAS
        if dp <= max(FIX_REACH_M, FIX_SIGMAS * sp) and dang <= max(FIX_REACH_RAD, FIX_SIGMAS * sr):
            return True
        self.counters.implausible_fixes += 1
        if self.counters.implausible_fixes in (1, 10, 100, 1000):
            logger.warning(
                "map fix refused (%d so far): its matches put the robot %.2f m and %.1f° from the "
                "predicted pose, beyond the prediction's uncertainty and the update's reach",
                self.counters.implausible_fixes,
                dp,
                math.degrees(dang),
            )
        return False

    # ---------------------------------------------------------------- after the update
    def track(self, t_ns: int, T: np.ndarray, relocalising: bool) -> None:
        """After the update: the velocity is the mean of the last measured increments (odometry or
        visual motion, up to ``VELOCITY_INTERVALS``), each weighted by its information; an
        interval without a measured increment keeps the velocity, so one frame without measured
        motion or one poor map update cannot become the model for the next frames."""
        if relocalising:
            self.forget()
            return
        inc = self.measured
        if inc is not None and inc.t1_ns > inc.t0_ns:
            dt = (inc.t1_ns - inc.t0_ns) * 1e-9
            C = np.asarray(inc.cov, float)
            if not np.any(C):  # the motion model's noise: a nominal 1 cm and 0.5° per interval
                C = np.diag([1e-4 / 3] * 3 + [math.radians(0.5) ** 2 / 3] * 3)
            # rates per second, weighted by their information (var of a rate: trace(C) / dt²)
            w_t = dt * dt / max(float(np.trace(C[:3, :3])), 1e-12)
            w_r = dt * dt / max(float(np.trace(C[3:, 3:])), 1e-14)
            rate = (np.asarray(inc.drot_R_rad, float) / dt, np.asarray(inc.dp_R_m, float) / dt, w_r, w_t)
            self.rates = [*self.rates[-(VELOCITY_INTERVALS - 1) :], rate]
            wr = np.array([r[2] for r in self.rates])
            wt = np.array([r[3] for r in self.rates])
            omega = (wr[:, None] * np.array([r[0] for r in self.rates])).sum(0) / wr.sum()
            vel = (wt[:, None] * np.array([r[1] for r in self.rates])).sum(0) / wt.sum()
            # over the last interval, with the σ of the weighted means
            self.velocity = (so3_exp(omega * dt), vel * dt, dt, dt / math.sqrt(wt.sum()), dt / math.sqrt(wr.sum()))
        self.last_pose = (t_ns, T)
