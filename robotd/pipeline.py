"""``Pipeline.step(frame, increment) -> StepResult``: the data flow of docs/architecture.md "Data flow" in a screenful.

Pure with respect to I/O: no sockets, files or wall clocks inside (perf_counter only measures
stage times); the one thread is the front end's detect worker, which only computes. The daemon,
replay, the benchmarks and the tests call the same ``step``, so a run replays bit for bit from its
recorded inputs and seed.

Motion prior, in order of preference (docs/math.md §6 "Where the control comes from"): the
vehicle's odometry integrated to the frame time; without it (visual only, as the thesis ran),
the frame-to-frame motion the front end recovered from the images; failing that, a
constant-velocity prediction. Ground truth never reaches the filter.

Landmark existence has one owner, the filter (its existence counter): the front end's descriptor
store allocates the ids of the new landmarks the filter is given, and the landmark registry
(robotd.slam.landmarks) takes the landmarks the filter pruned or did not take out of every store
that subscribed to it (the descriptors, the reported covariance's anchors).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from robotd.choices import MEASUREMENTS
from robotd.config import Config
from robotd.config_params import frontend_params_from_config, slam_params_from_config
from robotd.errors import MapMismatchError, PersistenceError, SingularityError
from robotd.frontend.association import IDENTIFIED, NEW, LandmarkDescriptors
from robotd.frontend.detectors import make_detector
from robotd.frontend.frontend import Frontend, Identification, Screening, VisualMotion
from robotd.frontend.pnp import MotionPrior, motion_prior
from robotd.frontend.stereo_match import StereoMatches
from robotd.geometry import R_to_euler, euler_to_R, se3, se3_inverse, so3_exp, so3_log
from robotd.msgs import LandmarkMap, MotionIncrement, Observations, PoseEstimate, StepResult, StereoFrame, UpdateReport
from robotd.relocalise import MIN_INLIERS, RESET_COV, Relocaliser, pose_from_similarity
from robotd.slam.common import measurement_model, model_cov6, pixel_noise
from robotd.slam.estimator import Estimator, persistent
from robotd.slam.factory import ESTIMATORS, estimator_kind, make_estimator
from robotd.slam.landmarks import LandmarkRegistry
from robotd.slam.measurement import covariance_at_prediction
from robotd.slam.uncertainty import ReportedCovariance
from robotd.stall import GapDetector, Reach, blind_motion, plausible, reach, still_prior
from robotd.statecheck import StateTable
from robotd.stereo import RectifiedStereo
from robotd.timing import StageClock

logger = logging.getLogger(__name__)

# The filter's gate may refuse the measured gravity for this long before its roll and pitch are
# reopened to it (Pipeline._fuse_gravity): longer than a bump or a glitch, short of a visible tilt.
GRAVITY_REOPEN_S = 1.0
# time constant of the gravity bias's low-pass (GravityBias): several laps of a small loop
GRAVITY_BIAS_TAU_S = 60.0
# the largest bias it takes (3°): an IMU mounted further off is a calibration to fix, and a cap keeps
# a filter that is far off (after a stall, say) from being taken for the sensor's bias
GRAVITY_BIAS_MAX_RAD = math.radians(3.0)

# the odometry and the images' motion over one interval are fused when they agree within this
# Mahalanobis distance (χ²(6) at 0.999)
FUSE_CHI2 = 22.458
LOST_AFTER_FRAMES = 5  # frames without anything constraining the pose before tracking is declared lost
VELOCITY_INTERVALS = 3  # measured intervals the constant-velocity model averages
NO_NEW = np.zeros(0, np.int64)  # no new landmarks this frame
# the filter's noise for a motion it is given as a guess (a gap nothing measured): the nominal
# 1 cm and 0.5° of one interval, so the particles move together (robotd.stall)
RIGID_COV = np.diag([1e-4 / 3] * 3 + [math.radians(0.5) ** 2 / 3] * 3)


@dataclass
class PipelineCounters:
    frames: int = 0
    visual_priors: int = 0
    odometry_priors: int = 0
    # odometry increments the images' own motion over the same interval was fused into, and those
    # where the two disagreed (the odometry alone was used)
    fused_priors: int = 0
    fusion_refused: int = 0
    constant_velocity_priors: int = 0
    frames_without_correspondences: int = 0
    lost_events: int = 0
    relocalisations: int = 0
    relocalisation_failures: int = 0
    # gaps between frames that no odometry covered (robotd.stall), and what bridged each
    gaps: int = 0
    gaps_by_images: int = 0
    gaps_by_map: int = 0
    gaps_guessed: int = 0
    # measured gravity directions fused (3D; slam.gravity), and those the filter's gate refused
    gravity_fused: int = 0
    gravity_rejected: int = 0
    gravity_reopened: int = 0  # fused with roll and pitch reopened after GRAVITY_REOPEN_S of refusals
    gravity_implausible: int = 0  # tilted beyond vehicle.max_tilt_deg: never fused
    # 3D: the filter's attitude tilted beyond vehicle.max_tilt_deg (or at the ZYX singularity):
    # roll and pitch reset to level, the frame reported lost (Pipeline._reset_attitude)
    attitude_resets: int = 0


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


class TrackingMonitor:
    """Tracking is lost after ``LOST_AFTER_FRAMES`` frames with a map in which nothing constrained
    the pose (no accepted map correspondence, no visual motion, no odometry), or when the pose
    covariance is no longer finite. While the stereo matches hold, the visual motion or the map
    constrain every frame, so tracking holds; it returns with the first constrained frame."""

    def __init__(self, counters: PipelineCounters) -> None:
        self.counters = counters
        self.tracking = True
        self._no_corr = 0

    def update(self, has_map: bool, constrained: bool, pose: PoseEstimate) -> bool:
        if has_map and not constrained:
            self._no_corr += 1
            self.counters.frames_without_correspondences += 1
        else:
            self._no_corr = 0
        was = self.tracking
        self.tracking = self._no_corr < LOST_AFTER_FRAMES and bool(np.all(np.isfinite(pose.cov)))
        if was and not self.tracking:
            self.counters.lost_events += 1
            logger.warning("tracking lost: nothing constrained the pose for %d frames", self._no_corr)
        return self.tracking

    def lose(self, why: str) -> bool:
        """Lost this frame for a reason of its own (``why``, logged): a lost event when it was
        tracking; tracking returns with the next constrained frame."""
        if self.tracking:
            self.counters.lost_events += 1
            logger.warning("tracking lost: %s", why)
        self.tracking = False
        return False

    def suspend(self) -> bool:
        """Not tracking this frame (relocalising), whatever the correspondences."""
        self.tracking = False
        return False


class Pipeline:
    """Front end + estimator for one rig. ``step`` is called once per stereo frame."""

    def __init__(self, cfg: Config, rig: RectifiedStereo, rng: np.random.Generator) -> None:
        self.cfg = cfg
        self.rig = rig
        self.rng = rng
        self.frontend = Frontend(rig, frontend_params_from_config(cfg), rng=rng)
        params = slam_params_from_config(cfg, rig)
        self._slam_params = params
        self.estimator: Estimator = make_estimator(params, rng)
        self.kind = estimator_kind(params.filter)  # what the filter declared (particles, ...)
        # the reported covariance (robotd.slam.uncertainty): anchors for the filters that declare
        # them (the particle filters, whose own covariance is only the last fix; the EKF's joint
        # covariance carries the map already)
        model = measurement_model(params)
        self.covariance = ReportedCovariance(
            cfg.slam.covariance, self.kind.anchored_covariance, model, pixel_noise(params) if model.intrinsics else None
        )
        # the map's landmark ids, and the stores that follow the filter's: the descriptors, the anchors
        self.registry = LandmarkRegistry(self.estimator)
        self.registry.subscribe(self.frontend)
        self.registry.subscribe(self.covariance)
        self.counters = PipelineCounters()
        self.tracker = TrackingMonitor(self.counters)
        self.relocaliser = Relocaliser()
        self.max_features = cfg.frontend.max_features
        self._last_t_ns: int | None = None
        self.gaps = GapDetector()
        self._vehicle_limits = (cfg.vehicle.max_speed_mps, cfg.vehicle.max_rate_radps)
        # the constant-velocity model: the filter's last pose (t_ns, T_world_robot) and its motion
        # over the last measured interval (R, t, dt_s); whether this frame's prior was measured
        self._last_pose: tuple[int, np.ndarray] | None = None
        self._velocity: tuple[np.ndarray, np.ndarray, float, float, float] | None = None
        self._measured: MotionIncrement | None = None
        # the map fixed the last frame's pose (at least relocalise.MIN_INLIERS landmarks identified,
        # what a pose from the map alone needs): the images' motion is then not fused into the
        # odometry (Pipeline._fuse_motion)
        self._map_fixed = False
        self._attitude_reset_at: int | None = None  # t_ns of the frame whose attitude was last reset
        # the last measured intervals: (rotation rate, velocity, weight of each, dt_s)
        self._rates: list[tuple[np.ndarray, np.ndarray, float, float]] = []
        # the direction of gravity in the world frame (3D, slam.gravity): from the first measurement
        self._gravity_W: np.ndarray | None = None
        self._gravity_refused_since: int | None = None  # t_ns of the first of the refusals in a row
        self._gravity_bias = GravityBias(GRAVITY_BIAS_TAU_S if cfg.slam.gravity_bias else 0.0)

    @property
    def tracking(self) -> bool:
        return self.tracker.tracking

    # ---------------------------------------------------------------- the step
    def step(self, frame: StereoFrame, increment: MotionIncrement | None = None) -> StepResult:
        """One stereo frame through the stages in data-flow order: measure, identify, screen
        outliers, predict, update. ``increment``: the vehicle's motion since the previous frame
        (None: visual only). Each stage is timed by one clock (``StepResult.timings_ms``)."""
        clock, fe, t_ns = StageClock(), self.frontend, frame.t_ns
        landmarks = self.estimator.landmarks()
        relocalising = self.relocaliser.active and landmarks.n > 0
        pnp = self.cfg.frontend.motion == "pnp"
        # measure: features in both images, stereo matches triangulated with their covariance
        feats = clock.run("detect", fe.detect, frame.left, frame.right)
        meas = clock.run("stereo", fe.match_stereo, feats, frame.left, frame.right)
        # the images' own motion, checked against the motion prior (or across a gap no odometry covers)
        gap, prior = self._gap_and_prior(t_ns, increment, relocalising, pnp)
        visual = clock.run("motion", fe.visual_motion, meas, t_ns, increment is None or pnp, prior)
        # the motion the filter predicts with: across the gap, else odometry, visual motion or constant velocity
        inc: MotionIncrement | None
        if gap is not None:
            inc = clock.run("gap", self._across_gap, gap, meas, visual, landmarks, t_ns)
        else:
            inc = None if relocalising else self._choose_increment(increment, visual.increment, t_ns)
        # identify against the map (guided by the predicted pose), then screen out the outliers
        view = None if relocalising else self._view_prior(landmarks, inc)
        ident = clock.run("identify", fe.identify, meas, landmarks, view)
        screen = clock.run("outliers", fe.screen, meas, ident)
        counts = fe.counts(feats, meas, ident, screen, visual)
        if relocalising and not clock.run("relocalise", self._relocalise, screen):
            return self._not_relocalised(frame, clock, meas, ident, counts)
        # points seen to move since the previous frame are not mapped; on vision alone, when the
        # images gave no motion, nothing is known to move (the bare stretch needs its landmarks)
        moved = visual.increment is not None or increment is not None
        # the frame's new landmarks reach the filter and every store, or none (robotd.slam.landmarks)
        with self.registry.frame():
            obs = clock.run("select", self._select, meas, ident, t_ns, visual.moving if moved else None)
            # predict with the motion prior, then fuse the frame's observations
            clock.run("predict", self._predict, inc)
            if self.covariance.enabled:
                clock.run("consistency", self.covariance.observe, self.estimator.estimate(), obs, landmarks)
            report = clock.run("update", self._update, obs, landmarks)
        pose, tracking, n_identified = self._after_update(t_ns, obs, landmarks, moved, relocalising)
        return self._result(frame, clock, counts, report, pose, tracking, n_identified, relocalising, obs)

    # ---------------------------------------------------------------- the stages
    def _gap_and_prior(
        self, t_ns: int, increment: MotionIncrement | None, relocalising: bool, pnp: bool
    ) -> tuple[Reach | None, MotionPrior | None]:
        """Before the images' motion: a gap no odometry covers (a stall, robotd.stall; the motion
        across it then comes from evidence), and the motion prior the images are checked against:
        at rest across a gap, else the odometry, else the constant-velocity prediction (None
        without PnP). With odometry too, the images' outliers are points that moved, on a vehicle,
        and are not mapped. Every interval goes through the gap detector, odometry or not."""
        gap = None if relocalising else self._gap_reach(t_ns)
        gap = gap if increment is None else None
        if not pnp:
            return gap, None
        if gap is not None:
            return gap, still_prior(gap)
        return gap, self._motion_prior(t_ns) if increment is None else self._odometry_prior(increment)

    def _not_relocalised(
        self, frame: StereoFrame, clock: StageClock, meas: StereoMatches, ident: Identification, counts: dict[str, int]
    ) -> StepResult:
        """The relocalising path's end while the map is not found yet: the measurements committed
        with no new landmarks (the map left as it is), tracking suspended."""
        self.frontend.commit(meas, ident, frame.t_ns, NO_NEW)
        return self._result(frame, clock, counts, UpdateReport(), self.estimator.estimate(), self.tracker.suspend(), 0)

    def _after_update(
        self, t_ns: int, obs: Observations, landmarks: LandmarkMap, moved: bool, relocalising: bool
    ) -> tuple[PoseEstimate, bool, int]:
        """After the update: an implausible attitude reset to level (the frame is then lost), the
        reported pose, tracking, the rig's disparity offset from the pose while tracking (the
        measurements seen again metres later, docs/frontend.md) and the constant-velocity model.
        Returns (pose, tracking, number of identified observations)."""
        if self._attitude_implausible() is not None:
            self._reset_attitude(t_ns)
        pose = self.covariance.report(self.estimator.estimate(), obs)
        n_identified = int(np.count_nonzero(~obs.is_new))
        tracking = self.tracker.update(landmarks.n > 0, n_identified > 0 or moved, pose)
        if self._attitude_reset_at == t_ns:
            tracking = self.tracker.lose("the attitude was reset")  # a guess this frame
        self._map_fixed = n_identified >= MIN_INLIERS
        if tracking:
            self.frontend.observe_pose(pose.T_world_robot)
        self._track_velocity(t_ns, pose.T_world_robot, relocalising)
        return pose, tracking, n_identified

    def _motion_prior(self, t_ns: int) -> MotionPrior | None:
        """The constant-velocity prediction of the motion since the last frame, with the vehicle's
        physical bounds (robotd.frontend.pnp.motion_prior): the filter's motion over the last
        measured interval (odometry or visual motion), scaled to this one."""
        if self._velocity is None or self._last_pose is None or t_ns <= self._last_pose[0]:
            return None
        R, t, dt_s, sd_t, sd_r = self._velocity
        return motion_prior(R, t, dt_s, (t_ns - self._last_pose[0]) * 1e-9, self.frontend.params.pnp, sd_t, sd_r)

    def _gap_reach(self, t_ns: int) -> Reach | None:
        """The vehicle's physical reach when the interval since the last frame is a gap (None
        otherwise, and before the first frame). Every interval goes through the detector, so it
        knows the frame rate whether or not odometry covers the frames."""
        if self._last_t_ns is None or t_ns <= self._last_t_ns:
            return None
        dt = (t_ns - self._last_t_ns) * 1e-9
        if not self.gaps.gap(dt):
            return None
        v0 = w0 = 0.0
        if self._velocity is not None:
            R, t, dt_v, _, _ = self._velocity
            v0 = float(np.linalg.norm(t)) / dt_v
            w0 = float(np.linalg.norm(so3_log(R))) / dt_v
        return reach(dt, v0, w0, *self._vehicle_limits, self.frontend.params.pnp)

    def _across_gap(
        self, r: Reach, meas: StereoMatches, visual: VisualMotion, landmarks: LandmarkMap, t_ns: int
    ) -> MotionIncrement:
        """The motion across a gap nothing measured (robotd.stall): the images' own motion across
        it, else the pose found in the whole map, else the constant-velocity guess (the filter
        moved rigidly, the guess's bound handed to the reported covariance)."""
        assert self._last_t_ns is not None
        t0 = self._last_t_ns
        self._measured = None
        self.counters.gaps += 1
        dt = (t_ns - t0) * 1e-9
        vis = visual.increment
        # across a gap the views are far apart: twice the inliers a normal frame needs (as PnP
        # asks of a jump outside its prior's bounds), so a few chance matches cannot decide it
        enough = visual.counts.get("motion_inliers", 0) >= 2 * self.frontend.params.pnp.min_inliers
        if vis is not None and vis.t0_ns == t0 and enough and plausible(r, vis.dp_R_m, so3_exp(vis.drot_R_rad)):
            self.counters.gaps_by_images += 1
            self._measured = vis
            logger.info("gap of %.1f s bridged by the images: moved %.2f m", dt, float(np.linalg.norm(vis.dp_R_m)))
            return vis
        T_last = self.estimator.estimate().T_world_robot
        T_fix = self._find_in_map(meas, landmarks) if landmarks.n else None
        if T_fix is not None:
            T = se3_inverse(T_last) @ T_fix
            if plausible(r, T[:3, 3], T[:3, :3]):
                self.counters.gaps_by_map += 1
                inc = MotionIncrement(t0, t_ns, T[:3, 3].copy(), so3_log(T[:3, :3]), RESET_COV.copy())
                self._measured = inc
                logger.info("gap of %.1f s bridged by the map: moved %.2f m", dt, float(np.linalg.norm(T[:3, 3])))
                return inc
        self.counters.gaps_guessed += 1
        R, t = np.eye(3), np.zeros(3)
        if self._velocity is not None:
            R_v, t_v, dt_v, _, _ = self._velocity
            R, t = blind_motion(R_v, t_v, dt_v, dt)
        self.covariance.add_uncertainty(r.guess_cov())
        logger.warning(
            "gap of %.1f s: nothing in the images or the map fixes the motion across it; the last speed "
            "assumed (%.2f m), uncertain by up to %.1f m and %.0f deg",
            dt,
            float(np.linalg.norm(t)),
            r.dev_t_m,
            math.degrees(r.dev_rot_rad),
        )
        return MotionIncrement(t0, t_ns, t, so3_log(R), RIGID_COV.copy())

    def _find_in_map(self, meas: StereoMatches, landmarks: LandmarkMap) -> np.ndarray | None:
        """This frame's pose T_world_robot (4, 4) from its features matched against the whole map
        by descriptor (no pose prior) and the outlier stage's similarity, or None with fewer than
        ``relocalise.MIN_INLIERS`` inliers."""
        ident = self.frontend.identify(meas, landmarks, None)
        screen = self.frontend.screen(meas, ident)
        res = screen.result
        if res is None or screen.similarity is None or int(res.n_inliers) < MIN_INLIERS:
            return None
        x = pose_from_similarity(res)
        if x is None:
            return None
        return se3(euler_to_R(x[3:6]), x[:3])

    def _odometry_prior(self, odo: MotionIncrement) -> MotionPrior:
        """The odometry's increment as the motion the images are checked against: within 3σ of
        its covariance, plus the acceleration bounds over the interval (a zero covariance: the
        bounds alone)."""
        p = self.frontend.params.pnp
        dt = max(odo.t1_ns - odo.t0_ns, 0) * 1e-9
        C = np.asarray(odo.cov, float)
        tol_t = 3.0 * math.sqrt(max(float(np.trace(C[:3, :3])), 0.0)) + p.max_accel_mps2 * dt * dt + 0.005
        tol_r = 3.0 * math.sqrt(max(float(np.trace(C[3:, 3:])), 0.0)) + p.max_angular_accel_radps2 * dt * dt
        R = so3_exp(odo.drot_R_rad)
        return MotionPrior(R, np.asarray(odo.dp_R_m, float), tol_t, tol_r + math.radians(0.2), binding=True)

    def _track_velocity(self, t_ns: int, T: np.ndarray, relocalising: bool) -> None:
        """After the update: the velocity is the mean of the last measured increments (odometry or
        visual motion, up to ``VELOCITY_INTERVALS``), each weighted by its information; an
        interval without a measured increment keeps the velocity, so one frame without measured
        motion or one poor map update cannot become the model for the next frames."""
        if relocalising:
            self._last_pose, self._velocity, self._rates = None, None, []
            return
        inc = self._measured
        if inc is not None and inc.t1_ns > inc.t0_ns:
            dt = (inc.t1_ns - inc.t0_ns) * 1e-9
            C = np.asarray(inc.cov, float)
            if not np.any(C):  # the motion model's noise: a nominal 1 cm and 0.5° per interval
                C = np.diag([1e-4 / 3] * 3 + [math.radians(0.5) ** 2 / 3] * 3)
            # rates per second, weighted by their information (var of a rate: trace(C) / dt²)
            w_t = dt * dt / max(float(np.trace(C[:3, :3])), 1e-12)
            w_r = dt * dt / max(float(np.trace(C[3:, 3:])), 1e-14)
            rate = (np.asarray(inc.drot_R_rad, float) / dt, np.asarray(inc.dp_R_m, float) / dt, w_r, w_t)
            self._rates = [*self._rates[-(VELOCITY_INTERVALS - 1) :], rate]
            wr = np.array([r[2] for r in self._rates])
            wt = np.array([r[3] for r in self._rates])
            omega = (wr[:, None] * np.array([r[0] for r in self._rates])).sum(0) / wr.sum()
            vel = (wt[:, None] * np.array([r[1] for r in self._rates])).sum(0) / wt.sum()
            # over the last interval, with the σ of the weighted means
            self._velocity = (so3_exp(omega * dt), vel * dt, dt, dt / math.sqrt(wt.sum()), dt / math.sqrt(wr.sum()))
        self._last_pose = (t_ns, T)

    def _view_prior(self, landmarks: LandmarkMap, inc: MotionIncrement | None) -> np.ndarray | None:
        """The predicted pose (the last estimate moved by the motion prior) that restricts
        identification to the landmarks predicted in view and guides the search for them."""
        if not self.cfg.frontend.restrict_to_fov or landmarks.n == 0:
            return None
        T = self.estimator.estimate().T_world_robot
        if inc is not None:
            T = T @ se3(so3_exp(inc.drot_R_rad), inc.dp_R_m)
        return T

    def _relocalise(self, screen: Screening) -> bool:
        fixed = self.relocaliser.attempt(screen.result, screen.similarity, self.estimator)
        self._last_pose, self._velocity, self._rates = None, None, []
        if fixed:
            self.counters.relocalisations += 1
        elif not self.relocaliser.active:
            self.counters.relocalisation_failures += 1
        return fixed

    def _select(
        self, meas: StereoMatches, ident: Identification, t_ns: int, moving: np.ndarray | None = None
    ) -> Observations:
        """Cap the filter's work per frame (slam.max_updates_per_frame, slam.max_new_per_frame): a
        spread subset of the identified measurements, and the nearest new ones (smallest
        covariance: the most precise landmarks to start from). The chosen new measurements become
        landmarks (global ids); the others are left out. ``moving``: measurements seen to move
        since the previous frame (the outliers of the rover's motion) do not become landmarks:
        the nearest points, first in line, are often on a vehicle."""
        status = ident.corr.status
        k_upd, k_new = self.cfg.slam.max_updates_per_frame, self.cfg.slam.max_new_per_frame
        old, new = np.flatnonzero(status == IDENTIFIED), np.flatnonzero(status == NEW)
        if moving is not None:
            new = new[~np.isin(new, moving)]
            old = old[~np.isin(old, moving)]
        if old.size > k_upd:
            old = np.sort(self.rng.choice(old, size=k_upd, replace=False))
        if new.size > k_new:
            tr = np.trace(meas.cov_R[new], axis1=1, axis2=2)
            new = np.sort(new[np.argsort(tr, kind="stable")[:k_new]])
        self.frontend.commit(meas, ident, t_ns, new)
        self.registry.propose(ident.corr.ids[new])
        return self.frontend.observations(meas, ident, t_ns, np.sort(np.concatenate([old, new])))

    def _predict(self, inc: MotionIncrement | None) -> None:
        if inc is not None:
            k = self.cfg.slam.motion_noise_scale
            if k != 1.0:
                inc = dataclasses.replace(inc, cov=inc.cov * k)
            try:
                self.estimator.predict(inc)
            except SingularityError:
                # a pose (a particle) at pitch ±90°: no rover is there, and the model cannot move
                # it, so every later frame would fail the same way; level it and go on
                self._reset_attitude(inc.t1_ns)
                self.estimator.predict(inc)
            if inc.gravity_R is not None and self.cfg.slam.gravity and self.cfg.slam.dim == 3:
                self._fuse_gravity(inc.gravity_R, inc.gravity_sigma_rad, inc.t1_ns)

    def _fuse_gravity(self, g_R: np.ndarray, sigma_rad: float, t_ns: int) -> None:
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
        if self._gravity_W is None:
            self._gravity_W = R_est @ g_R
            logger.info("gravity in the world frame: %s (the first measurement)", self._gravity_W.round(4))
        g_R = self._gravity_bias.correct(g_R, R_est.T @ self._gravity_W, t_ns)
        since = self._gravity_refused_since
        reopen = since is not None and t_ns - since >= GRAVITY_REOPEN_S * 1e9
        fused, nis = self.estimator.update_gravity(g_R, self._gravity_W, sigma_rad, reopen=reopen)
        if not fused:
            self.counters.gravity_rejected += 1
            if since is None:
                self._gravity_refused_since = t_ns
            return
        self.counters.gravity_fused += 1
        self._gravity_refused_since = None
        if reopen and since is not None:
            self.counters.gravity_reopened += 1
            logger.warning("gravity refused for %.1f s: roll and pitch reopened (NIS %.0f)", (t_ns - since) / 1e9, nis)

    def _attitude_implausible(self) -> float | None:
        """3D: the estimate's tilt [deg] (its vertical against the world's, the measured gravity's
        when there is one) when it is beyond ``vehicle.max_tilt_deg``, where no rover drives;
        else None."""
        if self.cfg.slam.dim != 3:
            return None
        R = self.estimator.estimate().T_world_robot[:3, :3]
        down = self._gravity_W if self._gravity_W is not None else np.array([0.0, 0.0, 1.0])
        tilt = math.degrees(math.acos(max(-1.0, min(1.0, float(R[:, 2] @ down)))))
        return tilt if tilt > self.cfg.vehicle.max_tilt_deg or not math.isfinite(tilt) else None

    def _reset_attitude(self, t_ns: int) -> None:
        """The filter's roll and pitch were implausible (:meth:`_attitude_implausible`) or at the
        ZYX singularity: put the pose level against the world's vertical, keeping its position
        and heading (``RESET_COV`` about it), and report the frame lost. Nothing measured the
        tilt it had (vision alone has no absolute vertical), so level is the rover's likeliest
        attitude; a vehicle's gravity, when it has one, then holds it."""
        self.frontend.disparity_bias.reset_tracks()  # the anchor's pose is no longer this map's
        est = self.estimator.estimate()
        T = est.T_world_robot
        R = T[:3, :3]
        down = self._gravity_W if self._gravity_W is not None else np.array([0.0, 0.0, 1.0])
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
        self._attitude_reset_at = t_ns
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
        self._last_pose = None

    def _update(self, obs: Observations, landmarks: LandmarkMap) -> UpdateReport:
        f = self.cfg.frontend
        if f.cov_at == "predicted" and landmarks.n and self.cfg.slam.measurement == "cartesian":
            # Q of re-observations at the predicted point, not the noisy pixels (docs/slam.md); the
            # pixel model's noise is constant
            obs = covariance_at_prediction(
                obs,
                self.estimator.estimate(),
                landmarks,
                self.rig.f_px,
                self.rig.baseline_m,
                f.sigma_x_px,
                f.sigma_y_px,
                f.cov_inflation,
                f.depth_min_m,
                planar=self.cfg.slam.dim == 2,
            )
        # the filter owns existence; what it pruned leaves the descriptors and the anchors with it
        return self.registry.update(obs)

    def _choose_increment(
        self, odo: MotionIncrement | None, vis: MotionIncrement | None, t_ns: int
    ) -> MotionIncrement | None:
        self._measured = None
        if self._last_t_ns is None:
            return None
        if odo is not None:
            self.counters.odometry_priors += 1
            if vis is not None and vis.t0_ns == odo.t0_ns and vis.t1_ns == odo.t1_ns and not self._map_fixed:
                odo = self._fuse_motion(odo, vis)
            self._measured = odo
            return odo
        if vis is not None and vis.t0_ns == self._last_t_ns:
            self.counters.visual_priors += 1
            self._measured = vis
            return vis
        cv = self._motion_prior(t_ns)
        if cv is not None:
            # constant velocity: the mean of the last measured increments, scaled to this interval,
            # uncertain by what the vehicle's acceleration limits allow
            self.counters.constant_velocity_priors += 1
            sd = np.r_[np.full(3, cv.tol_t_m / 2.0), np.full(3, cv.tol_rot_rad / 2.0)]
            return MotionIncrement(self._last_t_ns, t_ns, cv.t, so3_log(cv.R), np.diag(sd * sd))
        return None

    def _fuse_motion(self, odo: MotionIncrement, vis: MotionIncrement) -> MotionIncrement:
        """The odometry's increment and the images' own motion over the same interval (both
        measurements of it, independent) fused by their covariances, in the increment's tangent
        space (dp, drot) about the odometry's. The odometry's covariance is its stated one, else
        the filter's motion model's, which is what the filter would take for it. When the two
        disagree beyond ``FUSE_CHI2`` (a scene that moved, a wheel that slipped), the odometry
        alone, as before.

        Called only while the map does not fix the pose (``_map_fixed``): the images' motion then
        carries what nothing else does. Before, it was thrown away whenever odometry came, and at a
        car's metre a frame, where the map identifies nothing, the filter moved its particles by
        the motion model's noise alone (5 cm and 2° of yaw a frame) until they spread over metres.
        Where the map fixes the pose its update uses the same images, and fusing there was measured
        worse (docs/slam.md "Odometry and the images' motion")."""
        C_o = np.asarray(odo.cov, float)
        if not np.any(C_o):
            C_o = model_cov6(odo, self._slam_params)
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

    def _result(
        self,
        frame: StereoFrame,
        clock: StageClock,
        counts: dict[str, int],
        report: UpdateReport,
        pose: PoseEstimate,
        tracking: bool,
        n_identified: int,
        relocalised: bool = False,
        obs: Observations | None = None,
    ) -> StepResult:
        self._last_t_ns = frame.t_ns
        self.counters.frames += 1
        counts["landmarks"] = int(self.estimator.landmark_ids().shape[0])
        counts["identified"] = n_identified
        return StepResult(
            frame.t_ns,
            pose,
            report,
            clock.finish(),
            counts,
            tracking,
            relocalised,
            consistency=self.covariance.health(),
            observations=obs,
            attitude_reset=self._attitude_reset_at == frame.t_ns,
        )

    # ---------------------------------------------------------------- degradation hooks
    def set_max_features(self, n: int) -> None:
        n = int(n)
        if n != self.max_features:
            self.max_features = n
            self.frontend.detector = make_detector(frontend_params_from_config(self.cfg, n).detector)

    def set_particles(self, n: int) -> int:
        return self.estimator.set_particles(int(n))

    # ---------------------------------------------------------------- start-up and persistence
    @staticmethod
    def warmup(measurements: tuple[str, ...] = MEASUREMENTS) -> float:
        """Compile or load every numba kernel a step uses, so the first frame is not delayed
        (compiling takes ~30 s on a 2-core machine, ~20 s with one measurement model; loading
        the cache ~1–2 s). ``measurements``: the FastSLAM measurement models to prepare (the
        daemon passes its own). Returns seconds. Needs no pipeline: the daemon calls it before it
        opens the devices."""
        import time

        from robotd import outliers
        from robotd.frontend import detectors, pnp, stereo_match
        from robotd.slam.factory import warmup as warmup_filters

        t0 = time.perf_counter()
        warmup_filters(measurements)
        detectors.warmup()
        stereo_match.warmup()
        pnp.warmup()
        outliers.warmup()
        return time.perf_counter() - t0

    def state_dict(self) -> dict[str, Any]:
        descriptors = self.frontend.descriptors
        return {
            "estimator_name": self.estimator.name,
            "dim": self.estimator.dim,
            "estimator": persistent(self.estimator).state_dict(),
            "database": descriptors.state_dict() if descriptors is not None else {},
        }

    def check_state_dict(self, state: Any) -> tuple[dict[str, Any], LandmarkDescriptors | None]:
        """Check a saved state (:meth:`state_dict`) whole, every key, type, shape and range, and
        that the filter and the descriptor store hold the same landmarks, without touching this
        pipeline. Raises MapMismatchError when the map is valid but made for another filter,
        dimension or detector, PersistenceError (naming the key) when it is invalid. Returns the
        filter's checked values (``Estimator.restore``) and the saved descriptor store (None when
        the map has none)."""
        st = StateTable(state, "state")
        name = st.choice("estimator_name", tuple(ESTIMATORS))
        dim = st.choice("dim", (2, 3))
        if name != self.estimator.name or dim != self.estimator.dim:
            raise MapMismatchError(
                f"saved map is from {name!r} in {dim}D, this run uses {self.estimator.name!r} in {self.estimator.dim}D"
            )
        checked = persistent(self.estimator).check_state_dict(st.table("estimator").data)
        filter_ids = checked["ids"]
        saved_db = st.table("database")
        if not saved_db.data:  # no frame was detected before the save
            if filter_ids.size:
                raise PersistenceError(f"state.database: empty, but the filter holds {filter_ids.size} landmarks")
            return checked, None
        descriptors = LandmarkDescriptors.from_state_dict(saved_db.data)
        probe = self.frontend.detector.detect(np.zeros((8, 8), np.uint8), 0)  # an empty set of this kind
        dim_here = int(probe.desc.shape[1])
        if descriptors.binary != self.frontend.detector.binary or descriptors.dim != dim_here:
            kind = {True: "binary", False: "float"}
            raise MapMismatchError(
                f"saved map has {kind[descriptors.binary]} descriptors of {descriptors.dim}, this run's detector "
                f"{self.cfg.frontend.detector!r} makes {kind[self.frontend.detector.binary]} descriptors of {dim_here}"
            )
        if not np.array_equal(np.sort(filter_ids), descriptors.ids):
            raise PersistenceError(
                f"state.database.ids: {descriptors.n} landmarks with descriptors, the filter holds {filter_ids.size} "
                "and the two sets differ"
            )
        return checked, descriptors

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Resume from a saved state, checked whole first (:meth:`check_state_dict`): when it
        fails, nothing of this pipeline has changed."""
        checked, descriptors = self.check_state_dict(state)
        persistent(self.estimator).restore(checked)
        self.registry.reset(checked["ids"])  # the old map leaves the descriptors and the anchors
        if descriptors is not None:
            self.frontend.descriptors = descriptors
        self.frontend.reset()
        # the saved pose may be stale (the rover moved while robotd was down): find it in the map
        self.relocaliser.arm(None if self.cfg.slam.dim == 3 else 0)
        self._last_t_ns = None
        self.gaps.reset()
        self._last_pose, self._velocity, self._rates = None, None, []
        # the saved map is the world now: its landmarks anchor at zero covariance
        self.covariance.reset()
