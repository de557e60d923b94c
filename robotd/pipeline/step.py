"""``Pipeline.step(frame, increment) -> StepResult``: the data flow of docs/architecture.md "Data flow" in a screenful.

Pure with respect to I/O: no sockets, files or wall clocks inside (perf_counter only measures
stage times); the one thread is the front end's detect worker, which only computes. The daemon,
replay, the benchmarks and the tests call the same ``step``, so a run replays bit for bit from its
recorded inputs and seed.

The step is a list of plain calls to its stages, the objects of robotd/pipeline/stages/ that the pipeline
builds once and wires together here: a stage the step times is a method decorated with its name
(robotd.core.timing.stage), timed into the pipeline's one clock. The motion prior, in order of
preference: the vehicle's odometry, the images' own motion, constant velocity
(robotd.pipeline.stages.motion); across a gap no odometry covers, evidence (robotd.pipeline.stages.gap); after a
map load, the pose found in the map (robotd.pipeline.stages.relocalising). Ground truth never reaches the
filter.

Landmark existence has one owner, the filter (its existence counter): the front end's descriptor
store allocates the ids of the new landmarks the filter is given, and the landmark registry
(robotd.slam.landmarks) takes the landmarks the filter pruned or did not take out of every store
that subscribed to it (the descriptors, the reported covariance's anchors).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

from robotd.config import Config
from robotd.config.params import frontend_params_from_config, slam_params_from_config
from robotd.core.choices import MEASUREMENTS
from robotd.core.errors import InputError, MapMismatchError, PersistenceError
from robotd.core.msgs import (
    LandmarkMap,
    MotionIncrement,
    Observations,
    PoseEstimate,
    StepResult,
    StereoFrame,
    UpdateReport,
)
from robotd.core.statecheck import StateTable
from robotd.core.stereo import RectifiedStereo
from robotd.core.timing import StageClock
from robotd.frontend.association import LandmarkDescriptors
from robotd.frontend.detectors import make_detector
from robotd.frontend.frontend import Frontend, Identification
from robotd.frontend.stereo_match import StereoMatches
from robotd.pipeline.relocalise import MIN_INLIERS
from robotd.pipeline.stages.attitude import Attitude
from robotd.pipeline.stages.fuse import Fuse
from robotd.pipeline.stages.gap import Gap
from robotd.pipeline.stages.measure import Measure
from robotd.pipeline.stages.motion import MotionModel
from robotd.pipeline.stages.relocalising import Relocalising
from robotd.pipeline.stages.tracking import PipelineCounters, TrackingMonitor
from robotd.slam.common import measurement_model, pixel_noise
from robotd.slam.estimator import Estimator, persistent
from robotd.slam.factory import ESTIMATORS, estimator_kind, make_estimator
from robotd.slam.landmarks import LandmarkRegistry
from robotd.slam.uncertainty import ReportedCovariance


class Pipeline:
    """Front end + estimator for one rig. ``step`` is called once per stereo frame."""

    def __init__(self, cfg: Config, rig: RectifiedStereo, rng: np.random.Generator) -> None:
        self.cfg = cfg
        self.rig = rig
        self.rng = rng
        self.frontend = Frontend(rig, frontend_params_from_config(cfg), rng=rng)
        params = slam_params_from_config(cfg, rig)
        self.estimator: Estimator = make_estimator(params, rng)
        self.kind = estimator_kind(params.filter)  # what the filter declared (particles, ...)
        # the reported covariance (robotd.slam.uncertainty): anchors for the filters that declare
        # them (the particle filters, whose own covariance is only the last fix; the EKF's joint
        # covariance carries the map already)
        model = measurement_model(params)
        self.covariance = ReportedCovariance(
            cfg.slam.covariance,
            self.kind.anchored_covariance,
            model,
            pixel_noise(params) if model.intrinsics else None,
            cfg.slam.covariance_drift,
        )
        # the map's landmark ids, and the stores that follow the filter's: the descriptors, the anchors
        self.registry = LandmarkRegistry(self.estimator)
        self.registry.subscribe(self.frontend)
        self.registry.subscribe(self.covariance)
        self.counters = PipelineCounters()
        self.tracker = TrackingMonitor(self.counters)
        self.max_features = cfg.frontend.max_features
        # the stages (robotd/pipeline/stages/), timed into one clock
        self.clock = clock = StageClock()
        fe, est = self.frontend, self.estimator
        self.measure = Measure(cfg, fe, rng, self.registry, clock)
        self.motion = MotionModel(cfg, params, fe.params.pnp, est, self.counters)
        self.gap = Gap(cfg, fe, est, self.covariance, self.motion, self.counters, clock)
        self.relocalising = Relocalising(fe, est, self.motion, self.tracker, self.counters, clock)
        self.relocaliser = self.relocalising.relocaliser  # armed by a map load
        self.attitude = Attitude(cfg, fe, est, self.motion, self.counters)
        self.fuse = Fuse(cfg, rig, est, self.registry, self.covariance, self.attitude, clock)

    @property
    def tracking(self) -> bool:
        return self.tracker.tracking

    # ---------------------------------------------------------------- the step
    def step(self, frame: StereoFrame, increment: MotionIncrement | None = None) -> StepResult:
        """One stereo frame through the stages in data-flow order: measure, identify, screen
        outliers, predict, update. ``increment``: the vehicle's motion since the previous frame
        (None: visual only). Each stage is timed by one clock (``StepResult.timings_ms``)."""
        self.clock.start()
        fe, motion, t_ns = self.measure, self.motion, frame.t_ns
        fe.offset()  # the last step's deferred work, when the caller did not run it (after_step)
        landmarks = self.relocalising.tracked(self.estimator.landmarks())
        relocalising = self.relocalising.active(landmarks)
        # measure: features in both images, stereo matches triangulated with their covariance
        feats = fe.detect(frame)
        meas = fe.stereo(feats, frame)
        # the images' own motion, checked against the motion prior (or across a gap no odometry covers)
        gap = self.gap.find(t_ns, increment, relocalising)
        visual = fe.motion(meas, frame, increment, motion.prior(t_ns, increment, gap), motion.recent_rate())
        # the motion the filter predicts with: across the gap, else odometry, visual motion or constant velocity
        inc: MotionIncrement | None
        if gap is not None:
            inc = self.gap.across(gap, meas, visual, landmarks, t_ns)
        else:
            inc = motion.choose(increment, visual.increment, t_ns, relocalising)
            if inc is not None and inc is visual.increment:
                self.fuse.blur(inc, fe.exposure_ns(frame))  # the images' motion as the prior: its blur
        meas = fe.blurred(meas, inc, fe.exposure_ns(frame))  # the streak of this motion in the points' covariance
        # identify against the map (guided by the predicted pose), then screen out the outliers
        view = None if relocalising else motion.view(landmarks, inc)
        ident = fe.identify(meas, landmarks, view)
        # points seen to move since the previous frame are not mapped; on vision alone, when the
        # images gave no motion, nothing is known to move (the bare stretch needs its landmarks)
        moved = visual.increment is not None or increment is not None
        screen = motion.check_fix(ident, fe.outliers(meas, ident), view, inc, moved, t_ns, self.tracking)
        counts = self.frontend.counts(feats, meas, ident, screen, visual)
        if relocalising and not self.relocalising.attempt(screen):
            return self._not_relocalised(frame, meas, ident, counts)
        # the frame's new landmarks reach the filter and every store, or none (robotd.slam.landmarks)
        with self.registry.frame():
            obs = fe.select(meas, ident, t_ns, visual.moving if moved else None)
            # predict with the motion prior, then fuse the frame's observations
            self.fuse.predict(inc)
            if self.covariance.enabled:
                self.fuse.consistency(obs, landmarks)
            report = self.fuse.update(obs, landmarks)
        found = self.relocalising.searching() and self.relocalising.search(meas)  # a late find
        pose, tracking, n_identified = self._after_update(t_ns, obs, landmarks, moved, relocalising or found)
        return self._result(frame, counts, report, pose, tracking, n_identified, relocalising or found, obs)

    def after_step(self) -> float:
        """The work of the last step that its result does not wait for: the disparity offset's
        measurement from the committed pose (``Measure.offset``: a descriptor matching against
        the anchor frame and a small solve, 3 ms a frame on kitti-seq1, every other frame). The
        daemon's SLAM thread calls it once the pose is queued for publication, so the pose goes
        out that much sooner; otherwise the next :meth:`step` runs it first, timed as its stage
        ``offset``. Either way the next frame's stereo stage sees the same offset. Returns the
        milliseconds it took (0 when nothing waited)."""
        if self.measure.pending_offset is None:
            return 0.0
        t0 = time.perf_counter()
        self.measure.offset()
        return (time.perf_counter() - t0) * 1e3

    # ---------------------------------------------------------------- the step's two ends
    def _not_relocalised(
        self, frame: StereoFrame, meas: StereoMatches, ident: Identification, counts: dict[str, int]
    ) -> StepResult:
        """The relocalising path's end while the map is not found yet (robotd.pipeline.stages.relocalising)."""
        pose, tracking = self.relocalising.not_found(meas, ident, frame.t_ns)
        return self._result(frame, counts, UpdateReport(), pose, tracking, 0)

    def _after_update(
        self, t_ns: int, obs: Observations, landmarks: LandmarkMap, moved: bool, relocalising: bool
    ) -> tuple[PoseEstimate, bool, int]:
        """After the update: an implausible attitude reset to level (the frame is then lost), the
        reported pose, tracking, the rig's disparity offset from the pose while tracking (the
        measurements seen again metres later, docs/frontend.md) and the constant-velocity model.
        Returns (pose, tracking, number of identified observations)."""
        if self.attitude.implausible() is not None:
            self.attitude.level(t_ns)
        pose = self.covariance.report(self.estimator.estimate(), obs, self.estimator.spread_kept())
        n_identified = int(np.count_nonzero(~obs.is_new))
        tracking = self.tracker.update(landmarks.n > 0, n_identified > 0 or moved, pose)
        if self.attitude.reset_at == t_ns:
            tracking = self.tracker.lose("the attitude was reset")  # a guess this frame
        self.motion.map_fixed = n_identified >= MIN_INLIERS
        if tracking:
            # the disparity offset's measurement is the next frame's business (its stereo stage
            # corrects with it): deferred past the pose's publication (:meth:`after_step`)
            self.measure.pending_offset = pose.T_world_robot.copy()
        self.motion.track(t_ns, pose.T_world_robot, relocalising)
        return pose, tracking, n_identified

    def _result(
        self,
        frame: StereoFrame,
        counts: dict[str, int],
        report: UpdateReport,
        pose: PoseEstimate,
        tracking: bool,
        n_identified: int,
        relocalised: bool = False,
        obs: Observations | None = None,
    ) -> StepResult:
        self.motion.last_t_ns = frame.t_ns
        self.counters.frames += 1
        counts["landmarks"] = int(self.estimator.landmark_ids().shape[0])
        counts["identified"] = n_identified
        return StepResult(
            frame.t_ns,
            pose,
            report,
            self.clock.finish(),
            counts,
            tracking,
            relocalised,
            consistency=self.covariance.health(),
            observations=obs,
            attitude_reset=self.attitude.reset_at == frame.t_ns,
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
    def warmup(measurements: tuple[str, ...] = MEASUREMENTS, dims: tuple[int, ...] = (2, 3)) -> float:
        """Compile or load every numba kernel a step uses, so the first frame is not delayed
        (compiling takes ~25 s on a 2-core machine for every model and dimension, about a third
        of that for one of each; loading the cache ~1–2 s). ``measurements``, ``dims``: the
        FastSLAM measurement models and dimensions to prepare (the daemon passes its own).
        Returns seconds. Needs no pipeline: the daemon calls it before it opens the devices."""
        import time

        from robotd.core import outliers
        from robotd.frontend import align, detectors, pnp, stereo_match
        from robotd.slam.factory import warmup as warmup_filters

        t0 = time.perf_counter()
        warmup_filters(measurements, dims)
        detectors.warmup()
        stereo_match.warmup()
        pnp.warmup()
        align.warmup()
        outliers.warmup()
        return time.perf_counter() - t0

    def hand_over(self, x: np.ndarray, cov: np.ndarray) -> None:
        """After a resume, the filter's pose reset to ``x`` (dx,) with covariance ``cov``, a pose
        carried across robotd's downtime by the autopilot's motion (robotd.daemon.handover); the
        loaded map is tracked from it at once (robotd.pipeline.stages.relocalising).

        A particle filter's particles all start at ``x``, and ``cov`` goes to the reported
        covariance's anchors instead. The error of a carried pose is absolute: no landmark of new
        ground can tell the particles apart (each maps the ground from its own pose), so a spread
        never collapses there, and it cost the tracking. Spread by the whole carried uncertainty
        (decimetres, degrees), no landmark was ever re-identified (the pose was odometry alone)
        while the reported covariance summed the spread again every frame (4 m after 7 m); spread
        by a relocalisation's 5 cm and 1°, the best particle, whose map is the one identified
        against, mapped the ground up to 0.25 m away from where the mean pose predicts it, and
        tracking stopped after 20 frames. The loaded map, when it is found, fixes the absolute
        error (docs/slam.md "Relocalisation in a loaded map"). The EKF's joint covariance carries
        it, so the EKF is reset with ``cov``. Raises InputError, the filter untouched, on a pose or
        covariance of the wrong shape, not finite, or not symmetric positive semi-definite.
        """
        x, cov = np.asarray(x, dtype=float), np.asarray(cov, dtype=float)
        dx = 6 if self.estimator.dim == 3 else 3
        if x.shape != (dx,) or not np.all(np.isfinite(x)):
            raise InputError(f"handover: expected a finite pose of {dx} values, got {x.shape} {x}")
        if cov.shape != (dx, dx) or not np.all(np.isfinite(cov)):
            raise InputError(f"handover: expected a finite ({dx}, {dx}) covariance, got shape {cov.shape}")
        scale = max(1.0, float(np.abs(cov).max()))
        if not np.allclose(cov, cov.T, rtol=0.0, atol=1e-12 * scale) or np.linalg.eigvalsh(cov).min() < -1e-12 * scale:
            raise InputError("handover: the covariance is not symmetric positive semi-definite")
        self.after_step()  # the last step's deferred work first, as if it had run in that step
        if self.covariance.anchors is None:
            self.estimator.reset_pose(x, cov)
        else:
            self.estimator.reset_pose(x, None)
            k = np.arange(6) if dx == 6 else np.array([0, 1, 5])
            carried = np.zeros((6, 6))
            carried[np.ix_(k, k)] = cov
            self.covariance.add_uncertainty(carried)
        self.relocalising.handed_over()

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
        self.after_step()  # the last step's deferred work first, as if it had run in that step
        persistent(self.estimator).restore(checked)
        self.registry.reset(checked["ids"])  # the old map leaves the descriptors and the anchors
        if descriptors is not None:
            self.frontend.descriptors = descriptors
        self.frontend.reset()
        # the saved pose may be stale (the rover moved while robotd was down): find it in the map
        self.relocaliser.arm(None if self.cfg.slam.dim == 3 else 0, checked["ids"])
        self.motion.last_t_ns = None
        self.gap.reset()
        self.motion.forget()
        # the saved map is the world now: its landmarks anchor at zero covariance
        self.covariance.reset()
