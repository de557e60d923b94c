"""The front end: a rectified stereo pair -> identified landmark measurements (docs/math.md §2–§5).

Its stages are methods that the pipeline calls one by one, in data-flow order; the five it times
(detect, stereo, identify, outliers, motion) are decorated with their stage's name
(robotd.core.timing.stage) and time themselves into the front end's clock:

- :meth:`Frontend.detect`: features in both images;
- :meth:`Frontend.match_stereo`: stereo matches, triangulated with their covariance (§2–§3);
- :meth:`Frontend.identify`: putative matches to the map's landmarks by descriptor (§4.3);
- :meth:`Frontend.screen`: the outlier stage on those matches (§5; failures become REJECTED);
- :meth:`Frontend.visual_motion`: the frame-to-frame motion from the previous frame's
  measurements (the visual-odometry motion prior, when the vehicle gives none);
- :meth:`Frontend.commit`: identified landmarks take the new descriptors, the new landmarks the
  filter will initialise get their global ids, and the frame becomes "the previous frame".

:meth:`Frontend.process` runs all of them, as plain calls, for a caller without a filter
(benchmarks, tests), and reports the clock's timings.

Pure with respect to I/O: no threads, files or sockets (a worker thread detects the second image
at the same time); randomness from the injected generator. State between frames: the landmark
descriptors (global ids) and the previous frame's measurements.

Frames: measurements are in the robot frame R (FRD, baseline centre) of the current frame; map
landmarks are in the world frame W. The similarity fitted by the outlier stage maps W into R
(≈ T_robot_world); the frame-to-frame motion is T_prev_curr = T_{R(t−1) R(t)}.
"""

from __future__ import annotations

import concurrent.futures
import logging
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import partial

import numpy as np

from robotd.core.errors import InputError
from robotd.core.geometry import se3, se3_inverse, so3_log
from robotd.core.msgs import LandmarkMap, MotionIncrement, Observations
from robotd.core.outliers import (
    OutlierParams,
    OutlierResult,
    detect_outliers,
    fit_similarity_mahalanobis,
    ransac_similarity,
)
from robotd.core.stereo import RectifiedStereo, project, triangulate
from robotd.core.timing import StageClock, stage
from robotd.frontend.align import align_to_previous
from robotd.frontend.association import (
    IDENTIFIED,
    NEW,
    REJECTED,
    AssociationParams,
    Correspondences,
    LandmarkDescriptors,
)
from robotd.frontend.detectors import Detector, DetectorParams, check_image, make_detector
from robotd.frontend.disparity_bias import DisparityBias, DisparityBiasParams
from robotd.frontend.exposure import residual_spread
from robotd.frontend.features import Features
from robotd.frontend.pnp import MotionPrior, PnpParams, offset_sensitivity, reprojection_residuals, stereo_pnp
from robotd.frontend.stereo_match import (
    StereoMatches,
    StereoMatchParams,
    match_stereo,
    mutual_matches,
)

logger = logging.getLogger(__name__)

MapLandmarks = tuple[np.ndarray, np.ndarray, np.ndarray]  # ids (M,), xyz_W (M, 3) [m], cov_W (M, 3, 3) [m²]


@dataclass(frozen=True, slots=True)
class FrontendParams:
    """Front-end configuration (config key ``frontend``).

    detector, stereo, association, outliers: the stage parameters (their own defaults).
    motion: estimate the frame-to-frame motion (T_prev_curr) from the previous frame's measurements.
    motion_outliers: outlier stage of that estimate (default: similarity + Mahalanobis, §5).
    motion_gn_iterations: Gauss–Newton steps of the rigid Mahalanobis refinement of that motion.
    motion_method: "pnp" (default): stereo PnP RANSAC on pixel residuals (robotd.frontend.pnp);
      "similarity": the thesis's similarity/Mahalanobis RANSAC on triangulated points (§5).
    pnp: the stereo PnP settings.
    guided: identify map landmarks by guided matching around their projections from the
      predicted pose (falls back to descriptors alone when that finds too few).
    planar_map: the map has no heights (a 2-D filter): guided matching ignores the image row.
    fov_margin_px: a map landmark is predicted visible if it projects this far inside the image.
    parallel_detect: detect the left and right images on two threads (OpenCV and SURF release the GIL).
    disparity_bias: the online estimate of the rig's constant disparity error
      (robotd.frontend.disparity_bias; fed by :meth:`Frontend.observe_pose`).
    """

    detector: DetectorParams = field(default_factory=DetectorParams)
    stereo: StereoMatchParams = field(default_factory=StereoMatchParams)
    association: AssociationParams = field(default_factory=AssociationParams)
    outliers: OutlierParams = field(default_factory=OutlierParams)
    motion: bool = True
    motion_outliers: OutlierParams = field(default_factory=OutlierParams)
    motion_gn_iterations: int = 5
    motion_method: str = "pnp"
    guided: bool = True
    planar_map: bool = False
    pnp: PnpParams = field(default_factory=PnpParams)
    fov_margin_px: float = 0.0
    parallel_detect: bool = True
    disparity_bias: DisparityBiasParams = field(default_factory=DisparityBiasParams)


@dataclass(frozen=True, slots=True, eq=False)
class FeaturePair:
    """The detect stage's output: features of the left and right image."""

    left: Features
    right: Features


@dataclass(frozen=True, slots=True, eq=False)
class Identification:
    """The identify stage's output: putative correspondences of the frame's measurements to the
    reference landmarks (the map, or without one the previous frame's measurements).

    corr: status and id per measurement (the screen stage marks failures REJECTED, the commit
      stage writes the ids of new landmarks). ref_ids (K,), ref_xyz (K, 3) [m], ref_cov
      (K, 3, 3) [m²]: the reference set (world frame for the map, else the previous robot frame).
    candidates: ids searched (the map landmarks predicted in view, or all of the reference set).
    visible_predicted: True when ``candidates`` came from a pose prior.
    """

    corr: Correspondences
    ref_ids: np.ndarray
    ref_xyz: np.ndarray
    ref_cov: np.ndarray
    ref_is_map: bool
    candidates: np.ndarray
    visible_predicted: bool


@dataclass(frozen=True, slots=True, eq=False)
class Screening:
    """The outlier stage's output: its result on the identified candidates (None when there were
    none) and, when it accepted map matches, the similarity (4, 4) [sR t; 0 1] mapping world
    points into the robot frame (≈ T_robot_world)."""

    result: OutlierResult | None
    similarity: np.ndarray | None


@dataclass(frozen=True, slots=True, eq=False)
class VisualMotion:
    """The frame-to-frame motion stage's output.

    T_prev_curr: (4, 4) rigid motion T_{R(t−1) R(t)}, or None; increment: the same as a
    MotionIncrement (dp_R_m = translation in R(t−1), drot_R_rad = rotation vector, cov 6×6 over
    (dp, drot) from the Gauss–Newton information), or None; counts: motion_matches and
    motion_inliers (empty when the stage did not run); moving: indices of this frame's
    measurements that were matched to the previous frame but did not move with the rover (the
    outliers of its motion: a moving vehicle, or a false match), all the matched ones when the
    images gave no motion, None when the stage did not run or found no match;
    offset_sensitivity: computes (6,) d(dp, drot)/dδ, how the motion moves per pixel of a disparity
    offset common to both frames (robotd.frontend.pnp.offset_sensitivity; a refinement's cost,
    so only on demand: across a gap), or None (no PnP motion); spread_px2: the robust spread of
    every match's left-image residual under the PnP's motion (robotd.frontend.exposure
    .residual_spread), or None.
    """

    T_prev_curr: np.ndarray | None
    increment: MotionIncrement | None
    counts: dict[str, int]
    moving: np.ndarray | None = None
    offset_sensitivity: Callable[[], np.ndarray] | None = None
    spread_px2: float | None = None


NO_SCREENING = Screening(None, None)

# a stereo PnP that finds no consensus inside its inlier gate tries once more with the sharp gate
# (frontend.pnp_inlier_px) this many times wider, unless the blur allowed for had already widened
# it as far: a frame blurred beyond what the exposure known (or estimated) allows for
PNP_WIDE_GATE = 3.0


@dataclass(frozen=True, slots=True, eq=False)
class FrontendResult:
    """What the front end produced for one frame.

    observations: identified and new landmark measurements (robot frame) for ``Estimator.update``.
    timings_ms: stage -> ms (detect, stereo, identify, outliers, motion, total).
    counts: features_left, features_right, stereo_matches, map_candidates, map_matches, inliers,
      rejected, new, ransac_iterations, motion_matches, motion_inliers (and motion_wide_gate: 1
      when the PnP found the motion only at its wider second gate, 0 when that failed too).
    similarity: (4, 4) [sR t; 0 1] mapping world points into the robot frame (≈ T_robot_world),
      fitted on the accepted map matches; None when the outlier stage accepted none.
    outlier_result: the map-matching OutlierResult (None when there were no map matches).
    T_prev_curr: (4, 4) rigid frame-to-frame motion T_{R(t−1) R(t)}, or None.
    motion: the same as a MotionIncrement (dp_R_m = translation in R(t−1), drot_R_rad = rotation
      vector, cov 6×6 over (dp, drot) from the Gauss–Newton information), or None.
    measurements: every stereo measurement of the frame (for diagnostics and benchmarks).
    correspondences: status and id per measurement (IDENTIFIED / NEW / REJECTED).
    """

    observations: Observations
    timings_ms: dict[str, float]
    counts: dict[str, int]
    similarity: np.ndarray | None
    outlier_result: OutlierResult | None
    T_prev_curr: np.ndarray | None
    motion: MotionIncrement | None
    measurements: StereoMatches
    correspondences: Correspondences


@dataclass(frozen=True, slots=True, eq=False)
class _PrevFrame:
    t_ns: int
    meas: StereoMatches
    ids: np.ndarray  # (N,) global id per measurement, −1 if rejected
    left: np.ndarray | None = None  # its left image (the patches the next frame's matches align to)


def predicted_visible(
    rig: RectifiedStereo, xyz_W: np.ndarray, T_world_robot: np.ndarray, stereo: StereoMatchParams, margin_px: float
) -> tuple[np.ndarray, np.ndarray]:
    """Map landmarks seen from a pose: (M,) True for those that project inside both images within
    the disparity bounds, and (M, 3) their pixels (x_l, x_r, y) (meaningless where not visible)."""
    T_rw = se3_inverse(T_world_robot)
    xyz_R = xyz_W @ T_rw[:3, :3].T + T_rw[:3, 3]
    vis = xyz_R[:, 0] > 1e-6
    xl, xr, y = project(np.where(vis[:, None], xyz_R, 1.0), rig.f_px, rig.px, rig.py, rig.baseline_m)
    d_min, d_max = rig.disparity_bounds(stereo.depth_min_m, stereo.d_min_px)
    d = xl - xr
    m = margin_px
    vis &= (xl >= m) & (xl <= rig.width - 1 - m) & (xr >= m) & (y >= m) & (y <= rig.height - 1 - m)
    vis &= (d >= d_min) & (d <= d_max)
    return vis, np.c_[xl, xr, y]


def _check_map(map_landmarks_W: MapLandmarks | LandmarkMap) -> MapLandmarks:
    if isinstance(map_landmarks_W, LandmarkMap):
        return map_landmarks_W.ids, map_landmarks_W.xyz_W_m, map_landmarks_W.cov_W
    try:
        ids, xyz, cov = map_landmarks_W
    except (TypeError, ValueError) as exc:
        raise InputError(f"Frontend.process: expected map_landmarks_W = (ids, xyz_W, cov_W), got {exc}") from exc
    ids = np.asarray(ids, dtype=np.int64)
    xyz = np.asarray(xyz, dtype=float)
    cov = np.asarray(cov, dtype=float)
    m = ids.shape[0]
    if ids.ndim != 1 or xyz.shape != (m, 3) or cov.shape != (m, 3, 3):
        raise InputError(
            f"Frontend.process: expected map ids (M,), xyz (M, 3), cov (M, 3, 3), got {ids.shape}, {xyz.shape}, "
            f"{cov.shape}"
        )
    return ids, xyz, cov


_POOL: concurrent.futures.ThreadPoolExecutor | None = None


def _pool() -> concurrent.futures.ThreadPoolExecutor:
    global _POOL
    if _POOL is None:
        _POOL = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="robotd-detect")
    return _POOL


class Frontend:
    """Stateful shell over the pure stage functions; one instance per camera stream."""

    def __init__(
        self,
        rig: RectifiedStereo,
        params: FrontendParams | None = None,
        rng: np.random.Generator | None = None,
        descriptors: LandmarkDescriptors | None = None,
    ) -> None:
        self.rig = rig
        self.params = params or FrontendParams()
        self.rng = rng if rng is not None else np.random.default_rng(0)
        self.detector: Detector = make_detector(self.params.detector)
        self.descriptors = descriptors
        self._prev: _PrevFrame | None = None
        self._left: np.ndarray | None = None  # the last detected left image
        self.disparity_bias = DisparityBias(self.params.disparity_bias)
        # the clock the front end's stages time themselves into (robotd.core.timing.stage), which
        # process() reads; the step times the same calls into its own clock through its stages
        # (robotd/pipeline/stages/measure.py) and never reads this one
        self.clock = StageClock()

    def reset(self) -> None:
        """Forget the previous frame (after a gap or a relocalisation); keeps the descriptors."""
        self._prev = None
        self.disparity_bias.reset_tracks()

    # ---------------------------------------------------------------------------- the stages
    @stage("detect")
    def detect(self, left: np.ndarray, right: np.ndarray) -> FeaturePair:
        """Features of a rectified pair: ``left``/``right`` (H, W) uint8 images of the rig's size."""
        left = check_image(left, "left")
        right = check_image(right, "right")
        if left.shape != right.shape:
            raise InputError(
                f"Frontend.detect: expected left and right of one size, got {left.shape} and {right.shape}"
            )
        if left.shape != (self.rig.height, self.rig.width):
            raise InputError(
                f"Frontend.detect: expected images of the rig's size {(self.rig.height, self.rig.width)}, "
                f"got {left.shape}"
            )
        if self.params.parallel_detect:
            # OpenCV and the SURF kernels release the GIL: both images at once on two cores
            fut = _pool().submit(self.detector.detect, right)
            fl = self.detector.detect(left)
            fr = fut.result()
        else:
            fl = self.detector.detect(left)
            fr = self.detector.detect(right)
        # this frame's left image, for the next frame's alignment (robotd.frontend.align); none kept when off
        self._left = left.copy() if self.params.pnp.align_px > 0 else None
        if self.descriptors is None:
            dim = fl.desc.shape[1] if fl.n else (32 if self.detector.binary else fl.desc.shape[1])
            self.descriptors = LandmarkDescriptors(dim, self.detector.binary)
        return FeaturePair(fl, fr)

    @stage("stereo")
    def match_stereo(self, feats: FeaturePair, left: np.ndarray, right: np.ndarray) -> StereoMatches:
        """Stereo matches of the pair, triangulated in the robot frame with their covariance."""
        return match_stereo(
            feats.left, feats.right, self.rig, self.params.stereo, left, right, self.disparity_bias.value_px
        )

    @stage("identify")
    def identify(
        self,
        meas: StereoMatches,
        map_landmarks_W: MapLandmarks | LandmarkMap | None = None,
        T_world_robot_prior: np.ndarray | None = None,
    ) -> Identification:
        """Putative matches of the measurements to the reference landmarks by descriptor.

        ``map_landmarks_W``: the filter's map (ids (M,), xyz_W (M, 3) [m], cov_W (M, 3, 3) [m²]);
        None: identify against the previous frame's landmarks instead (frame-to-frame, §5.1).
        ``T_world_robot_prior``: (4, 4) predicted pose; restricts identification to landmarks
        predicted in view.
        """
        mp = _check_map(map_landmarks_W) if map_landmarks_W is not None else None
        if T_world_robot_prior is not None:
            T_world_robot_prior = np.asarray(T_world_robot_prior, dtype=float)
            if T_world_robot_prior.shape != (4, 4) or not np.all(np.isfinite(T_world_robot_prior)):
                raise InputError(
                    f"Frontend.identify: expected a finite (4, 4) T_world_robot_prior, got {T_world_robot_prior.shape}"
                )
        assert self.descriptors is not None, "Frontend.identify before Frontend.detect"
        ref_ids, ref_xyz, ref_cov, ref_is_map = self._reference(mp)
        cand = ref_ids
        predicted = mp is not None and T_world_robot_prior is not None and ref_ids.size > 0
        if predicted:
            assert T_world_robot_prior is not None
            p = self.params
            vis, px = predicted_visible(self.rig, ref_xyz, T_world_robot_prior, p.stereo, p.fov_margin_px)
            cand = ref_ids[vis]
        corr = None
        if predicted and self.params.guided and cand.size:
            corr = self._identify_guided(meas, cand, px[vis])
        if corr is None:
            corr = self.descriptors.identify(meas.desc, cand, self.params.association)
        return Identification(corr, ref_ids, ref_xyz, ref_cov, ref_is_map, cand, predicted)

    def _identify_guided(self, meas: StereoMatches, cand: np.ndarray, cand_px: np.ndarray) -> Correspondences | None:
        """Guided matching around the landmarks' projections ``cand_px`` (K, 3) from the predicted
        pose; None when it finds too few matches for the outlier stage (the prior is likely wrong:
        fall back to the descriptors alone)."""
        assert self.descriptors is not None
        corr = self.descriptors.identify_guided(
            meas.desc,
            np.c_[meas.xl, meas.xr, meas.y],
            cand,
            cand_px,
            self.params.association,
            rows_known=not self.params.planar_map,
        )
        if int(np.count_nonzero(corr.status == IDENTIFIED)) < self.params.outliers.min_inliers:
            return None
        return corr

    @stage("outliers")
    def screen(self, meas: StereoMatches, ident: Identification) -> Screening:
        """The outlier stage on the IDENTIFIED candidates; the failures become REJECTED."""
        corr = ident.corr
        cand = np.flatnonzero(corr.status == IDENTIFIED)
        if cand.size == 0:
            return NO_SCREENING
        order = np.argsort(ident.ref_ids)
        rows = order[np.searchsorted(ident.ref_ids[order], corr.ids[cand])]
        op = self.params.outliers
        if op.method == "fundamental":
            # needs both views: only landmarks also measured in the previous frame can be tested
            x1 = np.full((cand.size, 2), np.nan)
            if self._prev is not None:
                pv = self._prev
                pos = {int(k): i for i, k in enumerate(pv.ids) if k >= 0}
                for q, lid in enumerate(corr.ids[cand]):
                    i = pos.get(int(lid))
                    if i is not None:
                        x1[q] = (pv.meas.xl[i], pv.meas.y[i])
            testable = np.all(np.isfinite(x1), axis=1)
            x2 = np.c_[meas.xl[cand], meas.y[cand]]
            res = detect_outliers(op, self.rng, x1=x1[testable], x2=x2[testable])
            inl = np.zeros(cand.size, bool)
            inl[testable] = res.inliers
        else:
            A, B = ident.ref_cov[rows], meas.cov_R[cand]
            res = detect_outliers(op, self.rng, a=ident.ref_xyz[rows], b=meas.xyz_R[cand], A=A, B=B)
            inl = res.inliers
        corr.status[cand[~inl]] = REJECTED
        return Screening(res, res.T_b_a() if (res.accepted and ident.ref_is_map) else None)

    @stage("motion")
    def visual_motion(
        self,
        meas: StereoMatches,
        t_ns: int,
        wanted: bool = True,
        prior: MotionPrior | None = None,
        inlier_px: float | None = None,
    ) -> VisualMotion:
        """Frame-to-frame motion from direct descriptor matches to the previous frame's measurements
        (skipped when not ``wanted``: the vehicle gave odometry). ``prior``: the constant-velocity
        prediction of this motion with its physical bounds (PnP only: it picks the static
        background over a moving vehicle, robotd.frontend.pnp). ``inlier_px``: the PnP's inlier
        gate for this pair when wider than the configured one (motion blur,
        robotd.pipeline.stages.measure)."""
        if not wanted:
            return VisualMotion(None, None, {})
        counts = {"motion_matches": 0, "motion_inliers": 0}
        pv = self._prev
        if pv is None or pv.meas.n == 0 or meas.n == 0 or t_ns < pv.t_ns:
            return VisualMotion(None, None, counts)
        p = self.params
        binary = meas.binary
        max_d, ratio = p.association.limits(binary)
        # every current measurement against every previous one; a lone candidate must also beat
        # the ratio against its row's nearest non-candidate
        ic, ip = mutual_matches(meas.desc, pv.meas.desc, binary, max_d, ratio, second_in_row=True)
        counts["motion_matches"] = int(ic.size)
        if p.motion_method == "pnp":
            z = np.c_[meas.xl[ic], meas.xr[ic], meas.y[ic]]
            zp = np.c_[pv.meas.xl[ip], pv.meas.xr[ip], pv.meas.y[ip]]
            q = meas.xyz_R[ic]
            if (
                p.pnp.align_px > 0
                and pv.left is not None
                and self._left is not None
                and pv.left.shape == self._left.shape  # a camera reconfigured mid-run: the keypoints stay
            ):
                z, moved = align_to_previous(pv.left, self._left, zp, z, p.pnp.align_px)
                q = q.copy()
                r = self.rig
                q[moved] = triangulate(z[moved, 0], z[moved, 1], z[moved, 2], r.f_px, r.px, r.py, r.baseline_m)
                counts["motion_aligned"] = int(moved.sum())
            pp = p.pnp
            if inlier_px is not None and inlier_px > pp.inlier_px:
                pp = replace(pp, inlier_px=inlier_px)
            pnp = stereo_pnp(pv.meas.xyz_R[ip], z, q, zp, self.rig, pp, self.rng, prior)
            if pnp is None and ic.size >= pp.min_inliers and p.pnp.inlier_px * PNP_WIDE_GATE > pp.inlier_px:
                # no consensus inside the gate: once more at PNP_WIDE_GATE times the sharp one, when
                # the blur allowed for had not widened it as far (blur the exposure does not
                # account for; docs/frontend.md "Motion blur in the measurements")
                wide = replace(pp, inlier_px=p.pnp.inlier_px * PNP_WIDE_GATE)
                pnp = stereo_pnp(pv.meas.xyz_R[ip], z, q, zp, self.rig, wide, self.rng, prior)
                counts["motion_wide_gate"] = int(pnp is not None)
            if pnp is None:
                return VisualMotion(None, None, counts, ic if ic.size else None)
            counts["motion_inliers"] = int(pnp.inliers.sum())
            R, t, cov_tr = pnp.R, pnp.t, pnp.cov
            moving: np.ndarray | None = ic[~pnp.inliers]
            sens: Callable[[], np.ndarray] | None = partial(
                offset_sensitivity, R, t, z, zp, self.rig, p.pnp, pnp.inliers
            )
            res = reprojection_residuals(R[None], t[None], pv.meas.xyz_R[ip], z, self.rig)[0]
            spread: float | None = residual_spread(res)  # the blur's evidence (robotd.frontend.exposure)
        else:
            fit = self._similarity_motion(meas, pv.meas, ic, ip, counts)
            if fit is None:
                return VisualMotion(None, None, counts)
            R, t, cov_tr = fit
            moving = sens = spread = None
        inc = MotionIncrement(pv.t_ns, int(t_ns), t.copy(), so3_log(R), cov_tr)
        return VisualMotion(se3(R, t), inc, counts, moving, sens, spread)

    def _similarity_motion(
        self, meas: StereoMatches, prev: StereoMatches, ic: np.ndarray, ip: np.ndarray, counts: dict[str, int]
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The thesis's frame-to-frame motion: similarity/Mahalanobis RANSAC on the triangulated
        points, then a rigid Mahalanobis-weighted re-fit on the inliers."""
        p = self.params
        # b = s R a + t with a in R(t), b in R(t−1): the fitted transform is T_prev_curr
        res = ransac_similarity(
            meas.xyz_R[ic], prev.xyz_R[ip], meas.cov_R[ic], prev.cov_R[ip], p.motion_outliers, self.rng
        )
        if not res.accepted or res.R is None or res.t is None:
            return None
        inl = res.inliers
        counts["motion_inliers"] = int(inl.sum())
        # rigid (stereo fixes the scale), Mahalanobis-weighted re-fit on the inliers
        _, R, t, cov_tr = fit_similarity_mahalanobis(
            meas.xyz_R[ic][inl],
            prev.xyz_R[ip][inl],
            meas.cov_R[ic][inl],
            prev.cov_R[ip][inl],
            1.0,
            res.R,
            res.t,
            with_scale=False,
            iterations=p.motion_gn_iterations,
        )
        return R, t, cov_tr

    def commit(self, meas: StereoMatches, ident: Identification, t_ns: int, new: np.ndarray | None = None) -> None:
        """The frame's decisions: identified landmarks take the new descriptors, the NEW
        measurements at indices ``new`` (all of them when None) become landmarks with fresh global
        ids, and this frame becomes the previous frame."""
        assert self.descriptors is not None, "Frontend.commit before Frontend.detect"
        self.descriptors.commit(ident.corr, meas.desc, new)
        self._prev = _PrevFrame(int(t_ns), meas, ident.corr.ids.copy(), self._left)

    def forget(self, ids: np.ndarray) -> None:
        """The landmarks ``ids`` (K,) left the map (the filter pruned them, or never took them):
        their descriptors go. The front end's side of the landmark registry
        (robotd.slam.landmarks: the pipeline subscribes it)."""
        if self.descriptors is not None:
            self.descriptors.forget(ids)

    def observe_pose(self, T_world_robot: np.ndarray) -> bool:
        """The filter's pose of the frame just committed: its stereo measurements feed the
        disparity offset's estimate (robotd.frontend.disparity_bias). True if it fused one."""
        pv = self._prev
        if pv is None:
            return False
        p, m = self.params, pv.meas
        max_d, ratio = p.association.limits(m.binary)
        z = np.c_[m.xl, m.xr, m.y]
        return self.disparity_bias.observe(
            z, m.desc, m.binary, T_world_robot, self.rig, p.pnp.sigma_px, max_d, ratio, m.sigma_d
        )

    # ---------------------------------------------------------------------------- outputs
    @staticmethod
    def observations(
        meas: StereoMatches, ident: Identification, t_ns: int, idx: np.ndarray | None = None
    ) -> Observations:
        """Observations of the committed measurements at ``idx`` (all identified and initialised ones
        when None): identified ones update their landmark, new ones initialise theirs. They carry
        the pixels too, for the filters' pixel measurement model."""
        corr = ident.corr
        if idx is None:
            idx = np.flatnonzero((corr.status != REJECTED) & (corr.ids >= 0))
        uv = np.stack([meas.xl[idx], meas.xr[idx], meas.y[idx]], -1)
        return Observations(
            int(t_ns), meas.xyz_R[idx], meas.cov_R[idx], corr.ids[idx].copy(), corr.status[idx] == NEW, uv
        )

    @staticmethod
    def counts(
        feats: FeaturePair, meas: StereoMatches, ident: Identification, screen: Screening, motion: VisualMotion
    ) -> dict[str, int]:
        """Diagnostics of one frame (StepResult.counts; docs/topics.md)."""
        st = ident.corr.status
        res = screen.result
        return {
            "features_left": feats.left.n,
            "features_right": feats.right.n,
            "stereo_matches": meas.n,
            "map_candidates": int(ident.candidates.size),
            "map_matches": 0 if res is None else res.n_input,
            "inliers": int(np.sum(st == IDENTIFIED)),
            "rejected": int(np.sum(st == REJECTED)),
            "new": int(np.sum(st == NEW)),
            "ransac_iterations": 0 if res is None else res.iterations,
            **motion.counts,
        }

    def process(
        self,
        left: np.ndarray,
        right: np.ndarray,
        t_ns: int,
        map_landmarks_W: MapLandmarks | LandmarkMap | None = None,
        T_world_robot_prior: np.ndarray | None = None,
    ) -> FrontendResult:
        """Every stage on one rectified pair, for callers without a filter (benchmarks, tests): all
        new measurements become landmarks. Arguments as for :meth:`detect` and :meth:`identify`."""
        self.clock.start()
        feats = self.detect(left, right)
        meas = self.match_stereo(feats, left, right)
        ident = self.identify(meas, map_landmarks_W, T_world_robot_prior)
        screen = self.screen(meas, ident)
        motion = self.visual_motion(meas, t_ns, self.params.motion)
        self.commit(meas, ident, t_ns)
        timings = self.clock.finish()
        counts = self.counts(feats, meas, ident, screen, motion)
        logger.debug("frontend t=%d: %s; ms %s", t_ns, counts, {k: round(v, 2) for k, v in timings.items()})
        obs = self.observations(meas, ident, t_ns)
        return FrontendResult(
            obs,
            timings,
            counts,
            screen.similarity,
            screen.result,
            motion.T_prev_curr,
            motion.increment,
            meas,
            ident.corr,
        )

    # ----------------------------------------------------------------------------------------

    def _reference(self, mp: MapLandmarks | None) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
        """Landmarks with known positions to identify against: the map, else the previous frame's."""
        if mp is not None:
            return mp[0], mp[1], mp[2], True
        if self._prev is None:
            return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3, 3)), False
        pv = self._prev
        ok = pv.ids >= 0
        return pv.ids[ok], pv.meas.xyz_R[ok], pv.meas.cov_R[ok], False
