"""The front end's stages as the step times them, and select.

:class:`robotd.frontend.frontend.Frontend` does the work of detect, stereo, motion, identify and
outliers; each method here is the one call of it the step makes, under the stage's name. Select is
the pipeline's: it caps the filter's work per frame and commits the frame's decisions, numbering
the new landmarks, which the landmark registry then holds as pending until the filter takes them
(robotd.slam.landmarks).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from robotd.config import Config
from robotd.core.msgs import LandmarkMap, MotionIncrement, Observations, StereoFrame
from robotd.core.stereo import blur_covariance, streak_px
from robotd.core.timing import StageClock, stage
from robotd.frontend.association import IDENTIFIED, NEW
from robotd.frontend.exposure import ExposureEstimate
from robotd.frontend.frontend import FeaturePair, Frontend, Identification, Screening, VisualMotion
from robotd.frontend.pnp import MotionPrior
from robotd.frontend.stereo_match import StereoMatches
from robotd.slam.landmarks import LandmarkRegistry


def exposure_s(cfg: Config, exposure_ns: int) -> float:
    """A frame's exposure [s]: the one it reports, else ``camera.exposure_ms`` (0: unknown)."""
    return exposure_ns * 1e-9 if exposure_ns else cfg.camera.exposure_ms * 1e-3


# the share of the streak the PnP's inlier gate allows each match beyond the sharp gate
BLUR_GATE_SHARE = 0.5

# a frame that re-observed fewer map landmarks than this (the outlier stage's minimum) cannot be
# fixed by the map: with slam.new_landmarks = "adaptive" its new landmarks are spread over depth
ADAPTIVE_MIN_REOBSERVED = 6


class Measure:
    """The measuring stages of the step: ``frontend``'s, then select."""

    def __init__(
        self,
        cfg: Config,
        frontend: Frontend,
        rng: np.random.Generator,
        registry: LandmarkRegistry,
        clock: StageClock,
    ) -> None:
        self.cfg = cfg
        self.frontend = frontend
        self.rng = rng
        self.registry = registry
        self.clock = clock
        self.pending_offset: np.ndarray | None = None  # the last committed pose, for :meth:`offset`
        self.exposure = ExposureEstimate()  # for sources that report none (robotd.frontend.exposure)

    def exposure_ns(self, frame: StereoFrame) -> int:
        """The exposure the blur model takes for ``frame`` [ns]: the one it reports; else, with no
        ``camera.exposure_ms`` set and ``frontend.exposure_estimate`` on, the one estimated from the
        images so far (0 until the data fix it); else 0 (``exposure_s`` then falls back to the
        configured one)."""
        if frame.exposure_ns or self.cfg.camera.exposure_ms > 0.0 or not self.cfg.frontend.exposure_estimate:
            return frame.exposure_ns
        return round(self.exposure.exposure_s() * 1e9)

    def blur_health(self) -> dict[str, float | int]:
        """Health's view of the estimated exposure: its value [ms] and the frame pairs it rests on."""
        e = self.exposure
        return {"exposure_estimated_ms": round(e.exposure_s() * 1e3, 3), "exposure_pairs": e.frames}

    @stage("offset")
    def offset(self) -> None:
        """The disparity offset's measurement from the last step's committed pose (robotd.frontend
        .disparity_bias, through ``Frontend.observe_pose``), deferred past that step's result
        (``Pipeline.after_step``); nothing when none is pending."""
        T, self.pending_offset = self.pending_offset, None
        if T is not None:
            self.frontend.observe_pose(T)

    @stage("detect")
    def detect(self, frame: StereoFrame) -> FeaturePair:
        """Features in both images (with ``frontend.parallel_detect``, the right one on the
        front end's worker meanwhile)."""
        return self.frontend.detect(frame.left, frame.right)

    @stage("stereo")
    def stereo(self, feats: FeaturePair, frame: StereoFrame) -> StereoMatches:
        """Row matches triangulated with their covariance, in the robot frame."""
        return self.frontend.match_stereo(feats, frame.left, frame.right)

    @stage("motion")
    def motion(
        self,
        meas: StereoMatches,
        frame: StereoFrame,
        increment: MotionIncrement | None,
        prior: MotionPrior | None,
        rate_radps: float = 0.0,
    ) -> VisualMotion:
        """The images' own motion since the last ``frame``, checked against ``prior``: wanted on
        vision alone (no odometry ``increment``) and with PnP, whose outliers against the prior
        are the points that moved. With ``frontend.motion_blur`` and an exposure, the PnP's inlier
        gate widens by half the streak b the camera's recent turn rate ``rate_radps`` draws,
        √(gate² + (b/2)²): each of the two frames finds a corner up to b/2 from the streak's
        centre (docs/frontend.md "Motion blur in the measurements"). Each PnP motion's residual
        spread feeds the exposure's estimate (:meth:`exposure_ns`)."""
        wanted = increment is None or self.cfg.frontend.motion == "pnp"
        gate = None
        if self.cfg.frontend.motion_blur:
            b = streak_px(rate_radps, exposure_s(self.cfg, self.exposure_ns(frame)), self.frontend.rig.f_px)
            gate = math.hypot(self.cfg.frontend.pnp_inlier_px, BLUR_GATE_SHARE * b) if b > 0.0 else None
        visual = self.frontend.visual_motion(meas, frame.t_ns, wanted, prior, gate)
        if self.cfg.frontend.exposure_estimate and visual.increment is not None and visual.spread_px2 is not None:
            self.exposure.add(visual.increment, self.frontend.rig.f_px, visual.spread_px2)
        return visual

    def blurred(self, meas: StereoMatches, inc: MotionIncrement | None, exposure_ns: int) -> StereoMatches:
        """``meas`` with the covariance the streak of this frame's motion ``inc`` adds to each
        point (robotd.core.stereo.blur_covariance); ``meas`` itself without ``frontend.motion_blur``,
        an exposure or a motion."""
        if not self.cfg.frontend.motion_blur or inc is None or inc.t1_ns <= inc.t0_ns or meas.n == 0:
            return meas
        rate = float(np.linalg.norm(inc.drot_R_rad)) / ((inc.t1_ns - inc.t0_ns) * 1e-9)
        rig = self.frontend.rig
        b = streak_px(rate, exposure_s(self.cfg, exposure_ns), rig.f_px)
        if b <= 0.0:
            return meas
        return replace(meas, cov_R=meas.cov_R + blur_covariance(meas.xl, meas.xr, meas.y, rig, b))

    @stage("identify")
    def identify(self, meas: StereoMatches, landmarks: LandmarkMap, view: np.ndarray | None) -> Identification:
        """The measurements against the map's landmarks, those predicted in ``view`` (the predicted
        pose T_world_robot (4, 4); None: the whole map)."""
        return self.frontend.identify(meas, landmarks, view)

    @stage("outliers")
    def outliers(self, meas: StereoMatches, ident: Identification) -> Screening:
        """The outlier stage on the putative matches (robotd.core.outliers); failures become REJECTED."""
        return self.frontend.screen(meas, ident)

    @stage("select")
    def select(
        self, meas: StereoMatches, ident: Identification, t_ns: int, moving: np.ndarray | None = None
    ) -> Observations:
        """Cap the filter's work per frame (slam.max_updates_per_frame, slam.max_new_per_frame): a
        spread subset of the identified measurements, and the nearest new ones (smallest
        covariance: the most precise landmarks to start from). The chosen new measurements become
        landmarks (global ids, proposed to the landmark registry); the others are left out.
        ``moving``: measurements seen to move since the previous frame (the outliers of the rover's
        motion) do not become landmarks: the nearest points, first in line, are often on a vehicle."""
        status = ident.corr.status
        k_upd, k_new = self.cfg.slam.max_updates_per_frame, self.cfg.slam.max_new_per_frame
        old, new = np.flatnonzero(status == IDENTIFIED), np.flatnonzero(status == NEW)
        if moving is not None:
            new = new[~np.isin(new, moving)]
            old = old[~np.isin(old, moving)]
        if old.size > k_upd:
            old = np.sort(self.rng.choice(old, size=k_upd, replace=False))
        if new.size > k_new:
            new = self._pick_new(meas, new, k_new, reobserved=old.size)
        self.frontend.commit(meas, ident, t_ns, new)
        self.registry.propose(ident.corr.ids[new])
        return self.frontend.observations(meas, ident, t_ns, np.sort(np.concatenate([old, new])))

    def _pick_new(self, meas: StereoMatches, new: np.ndarray, k: int, reobserved: int) -> np.ndarray:
        """``k`` of the ``new`` measurements (indices, sorted) to become landmarks, by precision
        (the trace of their covariance): the most precise; with ``slam.new_landmarks = "adaptive"``
        in a frame that re-observed fewer than ``ADAPTIVE_MIN_REOBSERVED`` landmarks, ``k`` spread
        evenly over the precision ranks instead (near to far)."""
        order = np.argsort(np.trace(meas.cov_R[new], axis1=1, axis2=2), kind="stable")
        if self.cfg.slam.new_landmarks == "adaptive" and reobserved < ADAPTIVE_MIN_REOBSERVED:
            pick = order[np.unique(np.linspace(0, order.size - 1, k).round().astype(np.int64))]
        else:
            pick = order[:k]
        return np.sort(new[pick])
