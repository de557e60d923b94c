"""The relocalising path of the step: the frames after a map load, until the map is found.

The frame is identified against the whole map (no pose prior) and screened as usual; then the
stage ``relocalise`` resets the filter's pose from the screen's similarity when it rests on
enough inliers (robotd.relocalise). Until then the step ends there: the measurements committed
with no new landmarks, the map left as it is, tracking suspended.
"""

from __future__ import annotations

import numpy as np

from robotd.frontend.frontend import Frontend, Identification, Screening
from robotd.frontend.stereo_match import StereoMatches
from robotd.msgs import LandmarkMap, PoseEstimate
from robotd.relocalise import Relocaliser
from robotd.slam.estimator import Estimator
from robotd.stages.motion import MotionModel
from robotd.stages.tracking import PipelineCounters, TrackingMonitor
from robotd.timing import StageClock, stage

NO_NEW = np.zeros(0, np.int64)  # no new landmarks this frame


class Relocalising:
    """Whether the step relocalises (:meth:`active`), the attempt (the stage ``relocalise``) and
    the step's end while the map is not found (:meth:`not_found`)."""

    def __init__(
        self,
        frontend: Frontend,
        estimator: Estimator,
        motion: MotionModel,
        tracker: TrackingMonitor,
        counters: PipelineCounters,
        clock: StageClock,
    ) -> None:
        self.frontend = frontend
        self.estimator = estimator
        self.motion = motion
        self.tracker = tracker
        self.counters = counters
        self.clock = clock
        self.relocaliser = Relocaliser()

    def active(self, landmarks: LandmarkMap) -> bool:
        """This frame relocalises: a map was loaded, it holds landmarks, and it was not found yet
        within the frames allowed (robotd.relocalise.MAX_FRAMES)."""
        return self.relocaliser.active and landmarks.n > 0

    @stage("relocalise")
    def attempt(self, screen: Screening) -> bool:
        """The filter's pose reset from the screen against the whole map, when it fixes it; the
        constant-velocity model starts again either way. True when relocalised."""
        fixed = self.relocaliser.attempt(screen.result, screen.similarity, self.estimator)
        self.motion.forget()
        if fixed:
            self.counters.relocalisations += 1
        elif not self.relocaliser.active:
            self.counters.relocalisation_failures += 1
        return fixed

    def not_found(self, meas: StereoMatches, ident: Identification, t_ns: int) -> tuple[PoseEstimate, bool]:
        """The step's end while the map is not found yet: the measurements committed with no new
        landmarks (the map left as it is), tracking suspended. Returns (the filter's pose, tracking)."""
        self.frontend.commit(meas, ident, t_ns, NO_NEW)
        return self.estimator.estimate(), self.tracker.suspend()
