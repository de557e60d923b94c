"""The relocalising path of the step: the frames after a map load, until the map is found.

The frame is identified against the whole map (no pose prior) and screened as usual; then the
stage ``relocalise`` resets the filter's pose from the screen's similarity when it rests on
enough inliers (robotd.pipeline.relocalise). Until then the step ends there: the measurements committed
with no new landmarks, the map left as it is, tracking suspended. When that window ends without a
fix, the stage ``search`` goes on looking for the loaded map in the frames the step tracks as
usual, and resets the pose after the update when two finds agree.
"""

from __future__ import annotations

import logging

import numpy as np

from robotd.core.geometry import pose6_to_T
from robotd.core.msgs import LandmarkMap, PoseEstimate
from robotd.core.timing import StageClock, stage
from robotd.frontend.frontend import Frontend, Identification, Screening
from robotd.frontend.stereo_match import StereoMatches
from robotd.pipeline.relocalise import (
    CONFIRM_M,
    MIN_INLIERS,
    RESET_COV,
    SEARCH_FRAMES,
    Relocaliser,
    pose_from_similarity,
)
from robotd.pipeline.stages.motion import MotionModel
from robotd.pipeline.stages.tracking import PipelineCounters, TrackingMonitor
from robotd.slam.estimator import Estimator

NO_NEW = np.zeros(0, np.int64)  # no new landmarks this frame
logger = logging.getLogger("robotd.relocalise")


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
        within the frames allowed (robotd.pipeline.relocalise.MAX_FRAMES)."""
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

    def handed_over(self) -> None:
        """The pose came from elsewhere (robotd.daemon.handover: the autopilot's motion across a
        restart): no relocalising window, the map tracked from that pose at once; the loaded map
        is still searched for, as after a window that found nothing."""
        r = self.relocaliser
        r.frames_left = 0
        r.search_left = SEARCH_FRAMES if r.loaded_ids.size and self.estimator.dim == 3 else 0  # as arm()
        self.motion.forget()

    def tracked(self, landmarks: LandmarkMap) -> LandmarkMap:
        """The landmarks the step tracks with (all of them); while the search goes on, the filter
        holds the loaded map's (Estimator.hold_landmarks). The pose is then a guess in the loaded
        map's frame, and counting the loaded landmarks missed from it deleted the map being
        searched (ArduPilot's SITL: 2,687 -> 2,024 landmarks in 5 s, and no find after)."""
        r = self.relocaliser
        if r.searching and r.loaded_ids.size:
            self.estimator.hold_landmarks(int(r.loaded_ids[-1]) + 1)
        elif r.loaded_ids.size and not r.active:
            r.loaded_ids = np.zeros(0, np.int64)  # the search ended: the map is one map again
            self.estimator.hold_landmarks(0)
        return landmarks

    def searching(self) -> bool:
        """The stage ``search`` looks in this frame (after the relocalising window, one frame in
        robotd.pipeline.relocalise.SEARCH_EVERY)."""
        return self.relocaliser.search_due()

    @stage("search")
    def search(self, meas: StereoMatches) -> bool:
        """The frame against the loaded map's landmarks alone (no pose prior); when the pose found
        agrees with the last find (robotd.pipeline.relocalise.Relocaliser.agrees), the filter's pose is
        reset to it. True when it was (a discontinuity: the step reports it as relocalised)."""
        r = self.relocaliser
        landmarks = self.estimator.landmarks()
        keep = np.isin(landmarks.ids, r.loaded_ids)
        if int(np.count_nonzero(keep)) < MIN_INLIERS:
            return False
        loaded = LandmarkMap(landmarks.ids[keep], landmarks.xyz_W_m[keep], landmarks.cov_W[keep])
        screen = self.frontend.screen(meas, self.frontend.identify(meas, loaded, None))
        n_in = 0 if screen.result is None or screen.similarity is None else int(screen.result.n_inliers)
        fix = pose_from_similarity(screen.result) if screen.result is not None and n_in >= MIN_INLIERS else None
        logger.debug("search: %d inliers against %d landmarks of the loaded map", n_in, loaded.n)
        T_tracked = self.estimator.estimate().T_world_robot
        if fix is None or not r.agrees(pose6_to_T(fix), T_tracked):
            return False
        left = r.search_left
        r.found()
        if r.confirms(pose6_to_T(fix), T_tracked):
            # the tracked pose is in the loaded map already (a pose handed over, robotd.daemon.handover):
            # tracking corrects the rest, and a jump would cost the autopilot a reset for nothing
            logger.info(
                "the loaded map confirms the tracked pose %d frames after the window (%d inliers, within %.2f m)",
                SEARCH_FRAMES - left,
                n_in,
                CONFIRM_M,
            )
            return False
        self.estimator.reset_pose(fix, RESET_COV)
        self.motion.forget()
        self.counters.relocalisations += 1
        logger.info(
            "found the loaded map %d frames after the relocalising window (%d inliers, two finds agree): "
            "pose x %.2f y %.2f z %.2f m",
            SEARCH_FRAMES - left,
            n_in,
            *fix[:3],
        )
        return True

    def not_found(self, meas: StereoMatches, ident: Identification, t_ns: int) -> tuple[PoseEstimate, bool]:
        """The step's end while the map is not found yet: the measurements committed with no new
        landmarks (the map left as it is), tracking suspended. Returns (the filter's pose, tracking)."""
        self.frontend.commit(meas, ident, t_ns, NO_NEW)
        return self.estimator.estimate(), self.tracker.suspend()
