"""The gap path of the step: an interval since the last frame that no odometry covers and that
is longer than the frame rate explains (a stall, robotd.pipeline.stall), and the stage that bridges it.

Every interval goes through the gap detector, odometry or not, so it knows the frame rate. Across
a gap nothing measured, the motion comes from evidence: the images' own motion across it, else
the pose found in the whole map, else the constant-velocity guess, the guess's bound handed to
the reported covariance (docs/reliability.md).
"""

from __future__ import annotations

import logging
import math

import numpy as np

from robotd.config import Config
from robotd.core.geometry import euler_to_R, se3, se3_inverse, so3_exp, so3_log
from robotd.core.msgs import LandmarkMap, MotionIncrement
from robotd.core.timing import StageClock, stage
from robotd.frontend.frontend import Frontend, VisualMotion
from robotd.frontend.stereo_match import StereoMatches
from robotd.pipeline.relocalise import MIN_INLIERS, RESET_COV, pose_from_similarity
from robotd.pipeline.stages.motion import MotionModel
from robotd.pipeline.stages.tracking import PipelineCounters
from robotd.pipeline.stall import GapDetector, Reach, blind_motion, plausible, reach
from robotd.slam.estimator import Estimator
from robotd.slam.uncertainty import ReportedCovariance

logger = logging.getLogger("robotd.pipeline")  # the step's lines keep the name users filter them by

# the filter's noise for a motion it is given as a guess (a gap nothing measured): the nominal
# 1 cm and 0.5° of one interval, so the particles move together (robotd.pipeline.stall)
RIGID_COV = np.diag([1e-4 / 3] * 3 + [math.radians(0.5) ** 2 / 3] * 3)


class Gap:
    """Finds the gaps (:meth:`find`) and bridges each (the stage ``gap``, :meth:`across`)."""

    def __init__(
        self,
        cfg: Config,
        frontend: Frontend,
        estimator: Estimator,
        covariance: ReportedCovariance,
        motion: MotionModel,
        counters: PipelineCounters,
        clock: StageClock,
    ) -> None:
        self.frontend = frontend
        self.estimator = estimator
        self.covariance = covariance
        self.motion = motion
        self.counters = counters
        self.clock = clock
        self.detector = GapDetector()
        self._vehicle_limits = (cfg.vehicle.max_speed_mps, cfg.vehicle.max_rate_radps)

    def reset(self) -> None:
        """Forget the frame rate learnt so far (a map loaded)."""
        self.detector.reset()

    def find(self, t_ns: int, increment: MotionIncrement | None, relocalising: bool) -> Reach | None:
        """The vehicle's physical reach when the interval since the last frame is a gap that no
        odometry ``increment`` covers; None otherwise, before the first frame and while
        relocalising (the map gives the pose)."""
        if relocalising:
            return None
        r = self._reach(t_ns)  # every interval: the detector learns the frame rate
        return r if increment is None else None

    def _reach(self, t_ns: int) -> Reach | None:
        last_t_ns = self.motion.last_t_ns
        if last_t_ns is None or t_ns <= last_t_ns:
            return None
        dt = (t_ns - last_t_ns) * 1e-9
        if not self.detector.gap(dt):
            return None
        v0 = w0 = 0.0
        if self.motion.velocity is not None:
            R, t, dt_v, _, _ = self.motion.velocity
            v0 = float(np.linalg.norm(t)) / dt_v
            w0 = float(np.linalg.norm(so3_log(R))) / dt_v
        return reach(dt, v0, w0, *self._vehicle_limits, self.frontend.params.pnp)

    @stage("gap")
    def across(
        self, r: Reach, meas: StereoMatches, visual: VisualMotion, landmarks: LandmarkMap, t_ns: int
    ) -> MotionIncrement:
        """The motion across a gap nothing measured (robotd.pipeline.stall): the images' own motion across
        it, else the pose found in the whole map, else the constant-velocity guess (the filter
        moved rigidly, the guess's bound handed to the reported covariance)."""
        motion = self.motion
        assert motion.last_t_ns is not None
        t0 = motion.last_t_ns
        motion.measured = None
        self.counters.gaps += 1
        dt = (t_ns - t0) * 1e-9
        vis = visual.increment
        # across a gap the views are far apart: twice the inliers a normal frame needs (as PnP
        # asks of a jump outside its prior's bounds), so a few chance matches cannot decide it
        enough = visual.counts.get("motion_inliers", 0) >= 2 * self.frontend.params.pnp.min_inliers
        if vis is not None and vis.t0_ns == t0 and enough and plausible(r, vis.dp_R_m, so3_exp(vis.drot_R_rad)):
            self.counters.gaps_by_images += 1
            motion.measured = vis
            logger.info("gap of %.1f s bridged by the images: moved %.2f m", dt, float(np.linalg.norm(vis.dp_R_m)))
            self._offset_uncertainty(visual)
            return vis
        T_last = self.estimator.estimate().T_world_robot
        T_fix = self._find_in_map(meas, landmarks) if landmarks.n else None
        if T_fix is not None:
            T = se3_inverse(T_last) @ T_fix
            if plausible(r, T[:3, 3], T[:3, :3]):
                self.counters.gaps_by_map += 1
                inc = MotionIncrement(t0, t_ns, T[:3, 3].copy(), so3_log(T[:3, :3]), RESET_COV.copy())
                motion.measured = inc
                logger.info("gap of %.1f s bridged by the map: moved %.2f m", dt, float(np.linalg.norm(T[:3, 3])))
                return inc
        self.counters.gaps_guessed += 1
        R, t = np.eye(3), np.zeros(3)
        if motion.velocity is not None:
            R_v, t_v, dt_v, _, _ = motion.velocity
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

    def _offset_uncertainty(self, visual: VisualMotion) -> None:
        """A motion across a gap is measured over metres, mostly by far points, whose depth is only
        as good as the rig's disparity offset (its online estimate's σ, robotd.frontend.disparity_bias):
        a constant error the motion's pixel covariance does not hold. Its effect, the motion's
        sensitivity to the offset times that σ, is handed to the reported covariance (in the
        world, as the other errors the filter is not told of)."""
        if visual.offset_sensitivity is None:
            return
        J = visual.offset_sensitivity()
        if not np.all(np.isfinite(J)):
            return
        C = np.outer(J, J) * self.frontend.disparity_bias.sigma_px**2  # over (dp in R(t−1), drot)
        self.covariance.add_increment_uncertainty(C, self.estimator.estimate())
        logger.info(
            "the motion across the gap moves %.2f m per pixel of disparity offset (offset known to %.2f px)",
            float(np.linalg.norm(J[:3])),
            self.frontend.disparity_bias.sigma_px,
        )

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
