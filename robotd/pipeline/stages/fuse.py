"""The filter's stages of the step: predict with the motion prior (and, in 3D, the vehicle's
gravity), the consistency monitor's look at the frame before the update, and the update, which
hands the filter the frame's observations through the landmark registry (robotd.slam.landmarks)."""

from __future__ import annotations

import dataclasses

import numpy as np

from robotd.config import Config
from robotd.core.errors import SingularityError
from robotd.core.msgs import LandmarkMap, MotionIncrement, Observations, UpdateReport
from robotd.core.stereo import RectifiedStereo, streak_px
from robotd.core.timing import StageClock, stage
from robotd.pipeline.stages.attitude import Attitude
from robotd.pipeline.stages.measure import exposure_s
from robotd.slam.estimator import Estimator
from robotd.slam.landmarks import LandmarkRegistry
from robotd.slam.measurement import covariance_at_prediction
from robotd.slam.uncertainty import ReportedCovariance, blur_share


class Fuse:
    """The stages ``predict``, ``consistency`` and ``update`` on ``estimator``."""

    def __init__(
        self,
        cfg: Config,
        rig: RectifiedStereo,
        estimator: Estimator,
        registry: LandmarkRegistry,
        covariance: ReportedCovariance,
        attitude: Attitude,
        clock: StageClock,
    ) -> None:
        self.cfg = cfg
        self.rig = rig
        self.estimator = estimator
        self.registry = registry
        self.covariance = covariance
        self.attitude = attitude
        self.clock = clock
        # the images' blur (:meth:`blur`): the last exposure and streak, the largest streak, and
        # how many motions widened the reported covariance
        self.blur_stats: dict[str, float | int] = {
            "exposure_ms": 0.0,
            "streak_px": 0.0,
            "streak_px_max": 0.0,
            "widened": 0,
        }

    def blur(self, inc: MotionIncrement, exposure_ns: int) -> None:
        """The images' motion ``inc``, taken as the prior, was measured from images blurred by the
        motion itself: its streak (rate × exposure × f) goes to ``blur_stats`` (health's
        ``motion_blur``), and, with ``frontend.motion_blur`` off, the share of its covariance the
        blur adds (robotd.slam.uncertainty.blur_share, ``slam.covariance_blur_px``) goes to the
        reported covariance, the estimate untouched. With the measurements' blur model on, the
        PnP's gate admits the streaked matches and its covariance, from their residuals, already
        holds the blur (docs/slam.md "Reported covariance", motion blur). The exposure is the
        step's (``Measure.exposure_ns``: the frame's, else the one estimated from the images),
        else ``camera.exposure_ms``. Before :meth:`predict` (the increment is in the last pose's
        frame)."""
        dt_s = (inc.t1_ns - inc.t0_ns) * 1e-9
        if not self.covariance.enabled or dt_s <= 0.0 or not np.all(np.isfinite(inc.cov)):
            return
        exposure = exposure_s(self.cfg, exposure_ns)
        b = streak_px(float(np.linalg.norm(inc.drot_R_rad)) / dt_s, exposure, self.rig.f_px)
        if b <= 0.0:
            return
        st = self.blur_stats
        st["exposure_ms"], st["streak_px"] = round(exposure * 1e3, 3), round(b, 2)
        st["streak_px_max"] = max(float(st["streak_px_max"]), round(b, 2))
        k = blur_share(inc.drot_R_rad, dt_s, exposure, self.rig.f_px, self.cfg.slam.covariance_blur_px)
        if k > 0.0 and not self.cfg.frontend.motion_blur:
            self.covariance.add_increment_uncertainty(k * np.asarray(inc.cov, dtype=float), self.estimator.estimate())
            st["widened"] = int(st["widened"]) + 1

    @stage("predict")
    def predict(self, inc: MotionIncrement | None) -> None:
        """The filter moved by ``inc`` (None: not moved), its covariance scaled by
        ``slam.motion_noise_scale``; then, in 3D, the vehicle's gravity fused (slam.gravity)."""
        if inc is not None:
            k = self.cfg.slam.motion_noise_scale
            if k != 1.0:
                inc = dataclasses.replace(inc, cov=inc.cov * k)
            try:
                self.estimator.predict(inc)
            except SingularityError:
                # a pose (a particle) at pitch ±90°: no rover is there, and the model cannot move
                # it, so every later frame would fail the same way; level it and go on
                self.attitude.level(inc.t1_ns)
                self.estimator.predict(inc)
            if inc.gravity_R is not None and self.cfg.slam.gravity and self.cfg.slam.dim == 3:
                self.attitude.fuse_gravity(inc.gravity_R, inc.gravity_sigma_rad, inc.t1_ns)

    @stage("consistency")
    def consistency(self, obs: Observations, landmarks: LandmarkMap) -> None:
        """Before the update: the NIS of the frame's re-observations at the predicted pose, for
        the reported covariance's consistency monitor (slam.covariance = "consistent")."""
        self.covariance.observe(self.estimator.estimate(), obs, landmarks)

    @stage("update")
    def update(self, obs: Observations, landmarks: LandmarkMap) -> UpdateReport:
        """The frame's observations into the filter, through the landmark registry: the landmarks
        the filter prunes leave every store that keeps something for them."""
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
        return self.registry.update(obs)
