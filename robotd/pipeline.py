"""``Pipeline.step(frame, increment) -> StepResult``: the data flow of design.md §1 in a screenful.

Pure with respect to I/O: no threads, sockets, files or wall clocks inside (perf_counter only
measures stage times). The daemon, replay, the benchmarks and the tests call the same ``step``,
so a run replays bit for bit from its recorded inputs and seed.

Motion prior, in order of preference (algorithms.md §6, "Where the control comes from"): the
vehicle's odometry integrated to the frame time; without it (visual only, as the thesis ran),
the frame-to-frame motion the outlier stage recovered from the images; failing that, a
constant-velocity prediction. Ground truth never reaches the filter.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from robotd.autopilot import quality_from
from robotd.config import Config
from robotd.frontend.association import LandmarkDatabase
from robotd.frontend.detectors import DetectorParams, make_detector
from robotd.frontend.frontend import Frontend, FrontendParams, FrontendResult
from robotd.frontend.stereo_match import StereoMatchParams
from robotd.geometry import R_to_euler, euler_to_R, se3, se3_inverse
from robotd.msgs import MotionIncrement, Observations, PoseEstimate, StepResult, StereoFrame, UpdateReport
from robotd.outliers import OutlierParams, OutlierResult
from robotd.slam.estimator import Estimator
from robotd.slam.factory import make_estimator
from robotd.slam.measurement import covariance_at_prediction
from robotd.slam.params import SlamParams
from robotd.stereo import RectifiedStereo

logger = logging.getLogger(__name__)

LOST_AFTER_FRAMES = 5  # frames without accepted correspondences before tracking is declared lost
# Relocalisation against a loaded map (the saved pose may be stale: the rover moved while robotd was
# down, or a simulated rover restarted its path): identify against the whole map, and accept the
# RANSAC similarity only with this many inliers (sim://, map of 120 frames: 10-30 inliers, pose
# within 4-8 cm of the first run's); give up after this many frames
RELOC_MIN_INLIERS = 12
RELOC_MAX_FRAMES = 30


def frontend_params_from_config(cfg: Config, max_features: int | None = None) -> FrontendParams:
    f = cfg.frontend
    det = DetectorParams(
        name=f.detector,
        max_features=max_features or f.max_features,
        bucketing=f.bucketing,
        grid_rows=f.grid_rows,
        grid_cols=f.grid_cols,
    )
    stereo = StereoMatchParams(
        row_tol_px=f.row_tolerance_px,
        d_min_px=f.disparity_min_px,
        depth_min_m=f.depth_min_m,
        sigma_x_px=f.sigma_x_px,
        sigma_y_px=f.sigma_y_px,
        cov_inflation=f.cov_inflation,
        debias_depth=f.debias_depth,
    )
    method = f.outliers
    outl = OutlierParams(
        method="none" if method == "none" else method,
        confidence=f.consensus_confidence,
        max_iterations=f.ransac_max_iterations,
        min_inliers=f.min_inliers,
    )
    return FrontendParams(detector=det, stereo=stereo, outliers=outl, parallel_detect=f.parallel_detect)


def slam_params_from_config(cfg: Config, rig: RectifiedStereo | None = None) -> SlamParams:
    n_min = max(1, min(cfg.budget.min_particles, cfg.slam.n_particles))
    kw: dict[str, Any] = {
        "filter": cfg.slam.filter,
        "dim": cfg.slam.dim,
        "n_particles": cfg.slam.n_particles,
        "n_particles_min": n_min,
        "resample_neff_ratio": cfg.slam.resample_neff_ratio,
        "fs2_weights": cfg.slam.fs2_weights,
        "numba_threads": cfg.slam.numba_threads,
    }
    if rig is not None:
        # the pruning field of view and range follow the rig and the disparity limits (§2.2)
        kw["fov_h_rad"] = float(2 * np.arctan2(rig.width / 2.0, rig.f_px))
        kw["fov_v_rad"] = float(2 * np.arctan2(rig.height / 2.0, rig.f_px))
        kw["min_range_m"] = cfg.frontend.depth_min_m
        kw["max_range_m"] = max(cfg.frontend.depth_min_m * 1.01, rig.fb / cfg.frontend.disparity_min_px)
    return SlamParams(**kw)


def pose_to_T(pose: PoseEstimate) -> np.ndarray:
    return se3(euler_to_R(pose.rpy_rad), pose.xyz_W_m)


@dataclass
class PipelineCounters:
    frames: int = 0
    visual_priors: int = 0
    odometry_priors: int = 0
    constant_velocity_priors: int = 0
    frames_without_correspondences: int = 0
    lost_events: int = 0
    relocalisations: int = 0
    relocalisation_failures: int = 0


class Pipeline:
    """Frontend + estimator for one rig. ``step`` is called once per stereo frame."""

    def __init__(self, cfg: Config, rig: RectifiedStereo, rng: np.random.Generator) -> None:
        self.cfg = cfg
        self.rig = rig
        self.rng = rng
        self.frontend = Frontend(rig, frontend_params_from_config(cfg), rng=rng)
        self._restrict_fov = cfg.frontend.restrict_to_fov
        self.estimator: Estimator = make_estimator(slam_params_from_config(cfg, rig), rng)
        self.counters = PipelineCounters()
        self._last_t_ns: int | None = None
        self._last_T: np.ndarray | None = None  # T_world_robot of the previous output
        self._last_inc: MotionIncrement | None = None
        self._no_corr = 0
        self.tracking = True
        self.max_features = cfg.frontend.max_features
        self._reloc_frames_left = 0  # > 0: relocalise against the map before trusting the pose

    # ---------------------------------------------------------------- degradation hooks
    def set_max_features(self, n: int) -> None:
        n = int(n)
        if n != self.max_features:
            self.max_features = n
            self.frontend.detector = make_detector(frontend_params_from_config(self.cfg, n).detector)

    def set_particles(self, n: int) -> int:
        return self.estimator.set_particles(int(n))

    # ---------------------------------------------------------------- the step
    def step(self, frame: StereoFrame, increment: MotionIncrement | None = None) -> StepResult:
        t_start = time.perf_counter()
        timings: dict[str, float] = {}
        lm = self.estimator.landmarks()
        prior = self.estimator.estimate()
        # the images' own motion estimate is only needed when the vehicle gives none
        want_motion = increment is None
        if self.frontend.params.motion != want_motion:
            self.frontend.params = replace(self.frontend.params, motion=want_motion)
        reloc = self._reloc_frames_left > 0 and lm.n > 0
        fr = self.frontend.process(
            frame.left,
            frame.right,
            frame.t_ns,
            lm,
            # relocalising: no pose prior, so identification considers the whole map
            pose_to_T(prior) if self._restrict_fov and lm.n and not reloc else None,
        )
        timings.update(fr.timings_ms)
        relocalised = False
        if reloc:
            relocalised = self._relocalise(fr)
            if not relocalised:
                return self._reloc_wait(frame, fr, timings, t_start)
        obs = self._limit(fr.observations)

        t0 = time.perf_counter()
        if self._last_t_ns is not None and not relocalised:
            inc = self._choose_increment(increment, fr, frame.t_ns)
            if inc is not None:
                self.estimator.predict(inc)
                self._last_inc = inc
        f = self.cfg.frontend
        if f.cov_at == "predicted" and lm.n:
            # Q of re-observations at the predicted point, not the noisy pixels (docs/slam.md)
            obs = covariance_at_prediction(
                obs,
                self.estimator.estimate(),
                lm,
                self.rig.f_px,
                self.rig.baseline_m,
                f.sigma_x_px,
                f.sigma_y_px,
                f.cov_inflation,
                f.depth_min_m,
                planar=self.cfg.slam.dim == 2,
            )
        report = self.estimator.update(obs)
        db = self.frontend.database
        if report.n_pruned and db is not None:
            # the filter's existence counter is the master; the descriptor database follows it
            db.remove(np.setdiff1d(db.ids, self.estimator.landmark_ids(), assume_unique=True))
        timings["filter"] = (time.perf_counter() - t0) * 1e3

        pose = self.estimator.estimate()
        n_identified = int(np.count_nonzero(~obs.is_new))
        has_map = lm.n > 0
        if has_map and n_identified == 0:
            self._no_corr += 1
            self.counters.frames_without_correspondences += 1
        else:
            self._no_corr = 0
        was_tracking = self.tracking
        self.tracking = self._no_corr < LOST_AFTER_FRAMES and bool(np.all(np.isfinite(pose.cov)))
        if was_tracking and not self.tracking:
            self.counters.lost_events += 1
            logger.warning("tracking lost: no accepted correspondences for %d frames", self._no_corr)

        self._last_t_ns = frame.t_ns
        self._last_T = pose_to_T(pose)
        self.counters.frames += 1
        timings["total"] = (time.perf_counter() - t_start) * 1e3
        counts = dict(fr.counts)
        counts["landmarks"] = int(self.estimator.landmark_ids().shape[0])
        counts["identified"] = n_identified
        return StepResult(frame.t_ns, pose, report, timings, counts, self.tracking)

    def _relocalise(self, fr: FrontendResult) -> bool:
        """Put the filter's pose where the frame's map correspondences say (after a 3-D map load).

        The outlier stage's similarity b = sRa + t maps world landmarks a into this frame's robot
        frame; with at least RELOC_MIN_INLIERS inliers its inverse is the pose. Returns True when
        the pose was reset; counts down the attempts otherwise.
        """
        res = fr.outlier_result
        n_in = 0 if res is None or fr.similarity is None else int(res.n_inliers)
        fix = _pose_from_similarity(res) if res is not None and n_in >= RELOC_MIN_INLIERS else None
        if fix is None:
            self._reloc_frames_left -= 1
            if self._reloc_frames_left == 0:
                self.counters.relocalisation_failures += 1
                logger.warning(
                    "relocalisation against the loaded map failed for %d frames (last: %d inliers); "
                    "continuing from the saved pose",
                    RELOC_MAX_FRAMES,
                    n_in,
                )
            return False
        self.estimator.reset_pose(fix, np.diag([0.05**2] * 3 + [0.02**2] * 3))
        self._reloc_frames_left = 0
        self._last_inc = None
        self.counters.relocalisations += 1
        logger.info(
            "relocalised against the map: %d inliers of %d, pose x %.2f y %.2f z %.2f m",
            n_in,
            res.n_input if res is not None else 0,
            fix[0],
            fix[1],
            fix[2],
        )
        return True

    def _reloc_wait(
        self, frame: StereoFrame, fr: FrontendResult, timings: dict[str, float], t_start: float
    ) -> StepResult:
        """A frame that did not relocalise: the map is left as it is (no update, the new
        descriptors are taken back out of the database), and the step reports not tracking."""
        obs = fr.observations
        db = self.frontend.database
        if db is not None and obs.n:
            db.remove(obs.ids[obs.is_new])
        self.tracking = False
        self._last_t_ns = frame.t_ns
        pose = self.estimator.estimate()
        self._last_T = pose_to_T(pose)
        self.counters.frames += 1
        timings["filter"] = 0.0
        timings["total"] = (time.perf_counter() - t_start) * 1e3
        counts = dict(fr.counts)
        counts["landmarks"] = int(self.estimator.landmark_ids().shape[0])
        counts["identified"] = 0
        report = UpdateReport()
        return StepResult(frame.t_ns, pose, report, timings, counts, False)

    def _limit(self, obs: Observations) -> Observations:
        """Cap the filter's work per frame: a spread subset of the identified measurements, and the
        nearest new ones (smallest covariance: the most precise landmarks to start from). New
        landmarks that are not initialised are also removed from the descriptor database."""
        k_upd, k_new = self.cfg.slam.max_updates_per_frame, self.cfg.slam.max_new_per_frame
        old = np.flatnonzero(~obs.is_new)
        new = np.flatnonzero(obs.is_new)
        if old.size <= k_upd and new.size <= k_new:
            return obs
        if old.size > k_upd:
            old = np.sort(self.rng.choice(old, size=k_upd, replace=False))
        if new.size > k_new:
            tr = np.trace(obs.cov_R[new], axis1=1, axis2=2)
            keep_new = np.sort(new[np.argsort(tr, kind="stable")[:k_new]])
            dropped = np.setdiff1d(new, keep_new, assume_unique=True)
            if self.frontend.database is not None:
                self.frontend.database.remove(obs.ids[dropped])
            new = keep_new
        idx = np.sort(np.concatenate([old, new]))
        return Observations(obs.t_ns, obs.xyz_R_m[idx], obs.cov_R[idx], obs.ids[idx], obs.is_new[idx])

    def _choose_increment(self, odo: MotionIncrement | None, fr: Any, t_ns: int) -> MotionIncrement | None:
        assert self._last_t_ns is not None
        if odo is not None:
            self.counters.odometry_priors += 1
            return odo
        vis = fr.motion
        if vis is not None and vis.t0_ns == self._last_t_ns:
            self.counters.visual_priors += 1
            return vis
        if self._last_inc is not None:
            # constant velocity: repeat the last increment, scaled to this interval
            self.counters.constant_velocity_priors += 1
            dt_last = max(self._last_inc.t1_ns - self._last_inc.t0_ns, 1)
            k = (t_ns - self._last_t_ns) / dt_last
            return MotionIncrement(
                self._last_t_ns, t_ns, self._last_inc.dp_R_m * k, self._last_inc.drot_R_rad * k, np.zeros((6, 6))
            )
        return None

    # ---------------------------------------------------------------- quality and persistence
    def quality(self, result: StepResult) -> int:
        """MAVLink quality (robotd.autopilot.quality_from): -1 lost, else 1..100 from the accepted
        correspondences and N_eff/N."""
        pose = result.pose
        return quality_from(
            result.tracking,
            result.counts.get("identified", 0),
            pose.neff,
            pose.n_particles,
            min_inliers=self.cfg.frontend.min_inliers,
        )

    def state_dict(self) -> dict[str, Any]:
        return {
            "estimator_name": self.estimator.name,
            "dim": self.estimator.dim,
            "estimator": self.estimator.state_dict(),
            "database": _db_state(self.frontend.database),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        from robotd.errors import PersistenceError

        if state.get("estimator_name") != self.estimator.name or state.get("dim") != self.estimator.dim:
            raise PersistenceError(
                f"saved map is from {state.get('estimator_name')!r} in {state.get('dim')}D, "
                f"this run uses {self.estimator.name!r} in {self.estimator.dim}D"
            )
        self.estimator.load_state_dict(state["estimator"])
        db = state.get("database")
        if db:
            self.frontend.database = _db_from_state(db)
        self.frontend.reset()
        # the saved pose may be stale (the rover moved while robotd was down): find it in the map.
        # 3-D maps only: a planar map has no landmark heights, and the 3-D consensus against it
        # found 0-10 inliers on sim:// (a planar resume continues from the saved pose, as before)
        self._reloc_frames_left = RELOC_MAX_FRAMES if self.cfg.slam.dim == 3 else 0
        self._last_t_ns = None

    def relative_to_last(self, T_world_robot: np.ndarray) -> np.ndarray | None:
        if self._last_T is None:
            return None
        return se3_inverse(self._last_T) @ T_world_robot


def _pose_from_similarity(res: OutlierResult) -> np.ndarray | None:
    """(x, y, z, roll, pitch, yaw) of the robot from the similarity b = sRa + t that maps world
    points a into the robot frame (its inverse at b = 0); None when it is missing or not finite."""
    if res.s is None or res.R is None or res.t is None or not res.s > 0:
        return None
    R_wr = np.asarray(res.R, dtype=float).T  # the robot's orientation in the world
    p = -R_wr @ np.asarray(res.t, dtype=float) / float(res.s)
    x = np.r_[p, R_to_euler(R_wr)]
    return x if np.all(np.isfinite(x)) else None


def _db_state(db: LandmarkDatabase | None) -> dict[str, Any]:
    if db is None:
        return {}
    return {
        "dim": db.dim,
        "binary": db.binary,
        "ids": db.ids.copy(),
        "desc": db.desc.copy(),
        "existence": db.existence.copy(),
        "next_id": db.next_id,
    }


def _db_from_state(st: dict[str, Any]) -> LandmarkDatabase:
    from robotd.errors import PersistenceError

    try:
        db = LandmarkDatabase(int(st["dim"]), bool(st["binary"]), first_id=int(st["next_id"]))
        db.ids = np.asarray(st["ids"], np.int64)
        db.desc = np.asarray(st["desc"], db.desc.dtype)
        db.existence = np.asarray(st["existence"], np.int32)
    except (KeyError, TypeError, ValueError) as exc:
        raise PersistenceError(f"saved landmark database is incomplete: {exc}") from exc
    if db.desc.shape != (db.ids.shape[0], db.dim) or db.existence.shape != db.ids.shape:
        raise PersistenceError("saved landmark database: ids, descriptors and counters disagree in length")
    return db
