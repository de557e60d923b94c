"""Relocalisation against a loaded map (after ``persistence.resume``).

The saved pose may be stale: the rover moved while robotd was down, or a watchdog restarted it in
the middle of a drive, or a simulated rover started its path again. So the first frames after a
map load are identified against the whole map (no pose prior), and the outlier stage's similarity
b = sRa + t, which maps world landmarks a into this frame's robot frame, gives the pose once it
rests on ``MIN_INLIERS`` inliers. Until then the pipeline leaves the map untouched and reports not
tracking; after ``MAX_FRAMES`` frames without a fix it carries on from the saved pose and says so.

A rover restarted while it drives may see ground the loaded map does not hold for those frames,
and then drive back into ground it does (docs/sitl.md: the map of a loop, restarted 2–3 m on). So
the search goes on after that, while the pipeline tracks and maps as usual: every
``SEARCH_EVERY``-th frame for ``SEARCH_FRAMES`` frames, the frame is identified against the loaded
map's landmarks alone. A single consensus of a dozen matches can be wrong (on kitti-seq1 two
consensuses 0.6 m and 2 m from a right pose reprojected within 2 px at their own pose), so a find
is taken only when the next find agrees with it: the two poses found differ by the motion the
filter tracked between the two frames, within ``AGREE_M`` and ``AGREE_DEG``.

3-D maps only: a planar map has no landmark heights, and the 3-D consensus against it found 0–10
inliers on the simulated rover (a planar resume continues from the saved pose).
"""

from __future__ import annotations

import logging

import numpy as np

from robotd.core.geometry import R_to_euler, rotation_angle, se3_inverse
from robotd.core.outliers import OutlierResult
from robotd.slam.estimator import Estimator

logger = logging.getLogger("robotd.relocalise")  # its name before the layer packages: users filter by it

# the simulated rover, map of 120 frames: 10–30 inliers, pose within 4–8 cm of the first run's
MIN_INLIERS = 12
MAX_FRAMES = 30
# the search after MAX_FRAMES: 30 s at 30 frames/s, one frame in 5 (a whole-map identification
# and a RANSAC: 13 ms against a map of 2,200 landmarks on the 2-core VM, 20 ms with the stage's
# overheads, so the budget may step down on those frames), two finds agreeing with the tracked
# motion to 0.5 m and 5° (a find of a dozen inliers is good to 0.1-0.2 m and 1-2°; two wrong
# consensuses, each a pose anywhere, agree that well by chance almost never)
SEARCH_FRAMES = 900
SEARCH_EVERY = 5
AGREE_M = 0.5
AGREE_DEG = 5.0
# a find this close to the tracked pose confirms it (no reset): it is no better than the pose
# (a find of a dozen inliers is good to 0.1-0.2 m). Not wider: a pose handed over 0.5° off and
# carried over 150 frames of new ground was 0.2-0.25 m off when the map was found, and tracking
# does not correct that against a first lap it rarely re-observes (docs/slam.md)
CONFIRM_M = 0.1
CONFIRM_DEG = 1.0
# the covariance a relocalised pose starts from: 5 cm, 0.02 rad (1.1°)
RESET_COV = np.diag([0.05**2] * 3 + [0.02**2] * 3)


class Relocaliser:
    """Counts down the frames allowed to relocalise after a map load; resets the filter's pose
    when a frame's map correspondences fix it."""

    def __init__(self) -> None:
        self.frames_left = 0
        self.search_left = 0  # frames the loaded map is still searched in, after MAX_FRAMES
        self.loaded_ids = np.zeros(0, np.int64)  # the landmarks of the loaded map
        self._find: tuple[np.ndarray, np.ndarray] | None = None  # the last find: (T found, T tracked)

    @property
    def active(self) -> bool:
        return self.frames_left > 0

    @property
    def searching(self) -> bool:
        return self.search_left > 0

    def arm(self, frames: int | None = None, loaded_ids: np.ndarray | None = None) -> None:
        """Relocalise during the next ``frames`` frames (None: ``MAX_FRAMES``; 0: do not), then
        search the map of ``loaded_ids`` (none: do not)."""
        self.frames_left = MAX_FRAMES if frames is None else int(frames)
        self.loaded_ids = np.sort(np.asarray(loaded_ids if loaded_ids is not None else [], np.int64))
        self.search_left = 0
        self._find = None

    def search_due(self) -> bool:
        """Counts the search down; True on the frames it looks (one in ``SEARCH_EVERY``)."""
        if self.search_left <= 0:
            return False
        self.search_left -= 1
        if self.search_left == 0:
            logger.warning("the loaded map was not found in %d frames after the first %d", SEARCH_FRAMES, MAX_FRAMES)
        return self.search_left % SEARCH_EVERY == 0

    def agrees(self, T_found: np.ndarray, T_tracked: np.ndarray) -> bool:
        """A find (the pose in the loaded map, and the filter's pose, of one frame) agrees with
        the last one: the motion between the two finds is the motion tracked between them, within
        ``AGREE_M`` and ``AGREE_DEG``. Remembers this find for the next."""
        last, self._find = self._find, (T_found, T_tracked)
        if last is None:
            return False
        D = se3_inverse(se3_inverse(last[0]) @ T_found) @ (se3_inverse(last[1]) @ T_tracked)
        ang = float(np.degrees(rotation_angle(D[:3, :3])))
        dist = float(np.linalg.norm(D[:3, 3]))
        logger.debug("search: two finds differ from the tracked motion by %.2f m, %.1f deg", dist, ang)
        return bool(dist <= AGREE_M and ang <= AGREE_DEG)

    @staticmethod
    def confirms(T_found: np.ndarray, T_tracked: np.ndarray) -> bool:
        """The find and the tracked pose of the same frame are within CONFIRM_M and CONFIRM_DEG."""
        D = se3_inverse(T_found) @ T_tracked
        return bool(np.linalg.norm(D[:3, 3]) <= CONFIRM_M and np.degrees(rotation_angle(D[:3, :3])) <= CONFIRM_DEG)

    def found(self) -> None:
        """The search ended with a find."""
        self.search_left = 0
        self._find = None

    def _count_down(self, n_in: int = 0) -> bool:
        """A frame of the window without a fix (``n_in`` inliers); after the last, the search."""
        self.frames_left -= 1
        if self.frames_left == 0:
            self.search_left = SEARCH_FRAMES if self.loaded_ids.size else 0
            logger.warning(
                "relocalisation against the loaded map failed for %d frames (last: %d inliers); "
                "continuing from the saved pose%s",
                MAX_FRAMES,
                n_in,
                ", still searching the map" if self.search_left else "",
            )
        return False

    def attempt(self, outliers: OutlierResult | None, similarity: np.ndarray | None, estimator: Estimator) -> bool:
        """Reset ``estimator``'s pose from the frame's outlier result when it is good enough.

        ``outliers``/``similarity``: the screen stage's result against the whole map. Returns True
        when the pose was reset; counts the attempt down otherwise.
        """
        n_in = 0 if outliers is None or similarity is None else int(outliers.n_inliers)
        fix = pose_from_similarity(outliers) if outliers is not None and n_in >= MIN_INLIERS else None
        if fix is None:
            return self._count_down(n_in)
        estimator.reset_pose(fix, RESET_COV)
        self.frames_left = 0
        logger.info(
            "relocalised against the map: %d inliers of %d, pose x %.2f y %.2f z %.2f m",
            n_in,
            outliers.n_input if outliers is not None else 0,
            fix[0],
            fix[1],
            fix[2],
        )
        return True


def pose_from_similarity(res: OutlierResult) -> np.ndarray | None:
    """(x, y, z, roll, pitch, yaw) of the robot from the similarity b = sRa + t that maps world
    points a into the robot frame (its inverse at b = 0); None when it is missing or not finite."""
    if res.s is None or res.R is None or res.t is None or not res.s > 0:
        return None
    R_wr = np.asarray(res.R, dtype=float).T  # the robot's orientation in the world
    p = -R_wr @ np.asarray(res.t, dtype=float) / float(res.s)
    x = np.r_[p, R_to_euler(R_wr)]
    return x if np.all(np.isfinite(x)) else None
