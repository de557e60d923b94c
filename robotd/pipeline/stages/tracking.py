"""What the step counts (:class:`PipelineCounters`: the health topic and the replay summary read
them) and whether it is tracking (:class:`TrackingMonitor`)."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from robotd.core.msgs import PoseEstimate

logger = logging.getLogger("robotd.pipeline")  # the step's lines keep the name users filter them by

LOST_AFTER_FRAMES = 5  # frames without anything constraining the pose before tracking is declared lost


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
    # gaps between frames that no odometry covered (robotd.pipeline.stall), and what bridged each
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
    # roll and pitch reset to level, the frame reported lost (robotd.pipeline.stages.attitude)
    attitude_resets: int = 0
    # map fixes refused: the outlier stage's consensus put the robot farther from the predicted pose
    # than the prediction's own uncertainty and the filter's linear reach allow (robotd.pipeline.stages.motion)
    implausible_fixes: int = 0


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
