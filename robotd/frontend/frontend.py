"""The front end: a rectified stereo pair -> identified landmark measurements (algorithms.md §2–§5).

``Frontend.process`` runs detect → stereo match + triangulate → identify against the map →
outlier stage → commit (new ids, descriptor updates), and, beside it, a frame-to-frame motion
estimate from the previous frame's measurements (a visual-odometry motion prior).

Pure with respect to I/O: no threads, files or sockets; ``time.perf_counter`` only for the stage
timings; randomness from the injected generator. State between frames: the landmark database
(global ids and descriptors) and the previous frame's measurements.

Frames: measurements are in the robot frame R (FRD, baseline centre) of the current frame; map
landmarks are in the world frame W. The similarity fitted by the outlier stage maps W into R
(≈ T_robot_world); the frame-to-frame motion is T_prev_curr = T_{R(t−1) R(t)}.
"""

from __future__ import annotations

import concurrent.futures
import logging
import time
from dataclasses import dataclass, field

import numpy as np

from robotd.errors import InputError
from robotd.frontend.association import (
    IDENTIFIED,
    NEW,
    REJECTED,
    AssociationParams,
    Correspondences,
    LandmarkDatabase,
)
from robotd.frontend.detectors import Detector, DetectorParams, check_image, make_detector
from robotd.frontend.stereo_match import (
    StereoMatches,
    StereoMatchParams,
    distance_matrix,
    match_stereo,
    ratio_and_cross_check,
)
from robotd.geometry import se3, se3_inverse, so3_log
from robotd.msgs import LandmarkMap, MotionIncrement, Observations
from robotd.outliers import (
    OutlierParams,
    OutlierResult,
    detect_outliers,
    fit_similarity_mahalanobis,
    ransac_similarity,
)
from robotd.stereo import RectifiedStereo, project

logger = logging.getLogger(__name__)

MapLandmarks = tuple[np.ndarray, np.ndarray, np.ndarray]  # ids (M,), xyz_W (M, 3) [m], cov_W (M, 3, 3) [m²]


@dataclass(frozen=True, slots=True)
class FrontendParams:
    """Front-end configuration (config key ``frontend``).

    detector, stereo, association, outliers: the stage parameters (their own defaults).
    motion: estimate the frame-to-frame motion (T_prev_curr) from the previous frame's measurements.
    motion_outliers: outlier stage of that estimate (default: similarity + Mahalanobis, §5).
    motion_gn_iterations: Gauss–Newton steps of the rigid Mahalanobis refinement of that motion.
    fov_margin_px: a map landmark is predicted visible if it projects this far inside the image.
    parallel_detect: detect the left and right images on two threads (OpenCV and SURF release the GIL).
    """

    detector: DetectorParams = field(default_factory=DetectorParams)
    stereo: StereoMatchParams = field(default_factory=StereoMatchParams)
    association: AssociationParams = field(default_factory=AssociationParams)
    outliers: OutlierParams = field(default_factory=OutlierParams)
    motion: bool = True
    motion_outliers: OutlierParams = field(default_factory=OutlierParams)
    motion_gn_iterations: int = 5
    fov_margin_px: float = 0.0
    parallel_detect: bool = True


@dataclass(frozen=True, slots=True, eq=False)
class FrontendResult:
    """What the front end produced for one frame.

    observations: identified and new landmark measurements (robot frame) for ``Estimator.update``.
    timings_ms: stage -> ms (detect, stereo, identify, outliers, motion, total).
    counts: features_left, features_right, stereo_matches, map_candidates, map_matches, inliers,
      rejected, new, ransac_iterations, motion_matches, motion_inliers.
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


def predicted_visible(
    rig: RectifiedStereo, xyz_W: np.ndarray, T_world_robot: np.ndarray, stereo: StereoMatchParams, margin_px: float
) -> np.ndarray:
    """(M,) True for map landmarks that project inside both images within the disparity bounds."""
    T_rw = se3_inverse(T_world_robot)
    xyz_R = xyz_W @ T_rw[:3, :3].T + T_rw[:3, 3]
    vis = xyz_R[:, 0] > 1e-6
    if not np.any(vis):
        return vis
    xl, xr, y = project(np.where(vis[:, None], xyz_R, 1.0), rig.f_px, rig.px, rig.py, rig.baseline_m)
    d_min, d_max = rig.disparity_bounds(stereo.depth_min_m, stereo.d_min_px)
    d = xl - xr
    m = margin_px
    vis &= (xl >= m) & (xl <= rig.width - 1 - m) & (xr >= m) & (y >= m) & (y <= rig.height - 1 - m)
    vis &= (d >= d_min) & (d <= d_max)
    return vis


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
        database: LandmarkDatabase | None = None,
    ) -> None:
        self.rig = rig
        self.params = params or FrontendParams()
        self.rng = rng if rng is not None else np.random.default_rng(0)
        self.detector: Detector = make_detector(self.params.detector)
        self.database = database
        self._prev: _PrevFrame | None = None

    def reset(self) -> None:
        """Forget the previous frame (after a gap or a relocalisation); keeps the database."""
        self._prev = None

    def process(
        self,
        left: np.ndarray,
        right: np.ndarray,
        t_ns: int,
        map_landmarks_W: MapLandmarks | LandmarkMap | None = None,
        T_world_robot_prior: np.ndarray | None = None,
    ) -> FrontendResult:
        """Turn one rectified pair into Observations (module doc).

        ``left``/``right``: (H, W) uint8 rectified images of the rig's size. ``map_landmarks_W``:
        the filter's map (ids (M,), xyz_W (M, 3) [m], cov_W (M, 3, 3) [m²]); None: identify
        against the previous frame's landmarks instead (frame-to-frame, §5.1). ``T_world_robot_prior``:
        (4, 4) predicted pose; restricts identification to landmarks predicted in view.
        """
        p = self.params
        timings: dict[str, float] = {}
        t_start = time.perf_counter()
        left = check_image(left, "left")
        right = check_image(right, "right")
        if left.shape != right.shape:
            raise InputError(
                f"Frontend.process: expected left and right of one size, got {left.shape} and {right.shape}"
            )
        if left.shape != (self.rig.height, self.rig.width):
            raise InputError(
                f"Frontend.process: expected images of the rig's size {(self.rig.height, self.rig.width)}, "
                f"got {left.shape}"
            )
        mp = _check_map(map_landmarks_W) if map_landmarks_W is not None else None
        if T_world_robot_prior is not None:
            T_world_robot_prior = np.asarray(T_world_robot_prior, dtype=float)
            if T_world_robot_prior.shape != (4, 4) or not np.all(np.isfinite(T_world_robot_prior)):
                raise InputError(
                    f"Frontend.process: expected a finite (4, 4) T_world_robot_prior, got {T_world_robot_prior.shape}"
                )

        # --- detect
        t0 = time.perf_counter()
        if self.params.parallel_detect:
            # OpenCV and the SURF kernels release the GIL: both images at once on two cores
            fut = _pool().submit(self.detector.detect, right)
            fl = self.detector.detect(left)
            fr = fut.result()
        else:
            fl = self.detector.detect(left)
            fr = self.detector.detect(right)
        timings["detect"] = (time.perf_counter() - t0) * 1e3
        if self.database is None:
            dim = fl.desc.shape[1] if fl.n else (32 if self.detector.binary else fl.desc.shape[1])
            self.database = LandmarkDatabase(dim, self.detector.binary)
        db = self.database

        # --- stereo
        t0 = time.perf_counter()
        meas = match_stereo(fl, fr, self.rig, p.stereo, left, right)
        timings["stereo"] = (time.perf_counter() - t0) * 1e3

        # --- identify against the reference set (the map, or the previous frame's landmarks)
        t0 = time.perf_counter()
        ref_ids, ref_xyz, ref_cov, ref_is_map = self._reference(mp)
        cand = ref_ids
        n_visible_pred = -1
        if mp is not None and T_world_robot_prior is not None and ref_ids.size:
            vis = predicted_visible(self.rig, ref_xyz, T_world_robot_prior, p.stereo, p.fov_margin_px)
            cand = ref_ids[vis]
            n_visible_pred = int(vis.sum())
        corr = db.identify(meas.desc, cand, p.association)
        timings["identify"] = (time.perf_counter() - t0) * 1e3

        # --- outlier stage on the putative matches
        t0 = time.perf_counter()
        res, similarity = self._outliers(meas, corr, ref_ids, ref_xyz, ref_cov, ref_is_map)
        timings["outliers"] = (time.perf_counter() - t0) * 1e3

        if n_visible_pred >= 0:
            identified = corr.ids[corr.status == IDENTIFIED]
            db.mark_missed(np.setdiff1d(cand, identified, assume_unique=True))  # ids are unique
        db.commit(corr, meas.desc)

        # --- frame-to-frame motion (visual-odometry prior)
        t0 = time.perf_counter()
        T_pc, motion, m_counts = self._motion(meas, t_ns) if p.motion else (None, None, {})
        timings["motion"] = (time.perf_counter() - t0) * 1e3

        keep = corr.status != REJECTED
        obs = Observations(
            int(t_ns),
            meas.xyz_R[keep],
            meas.cov_R[keep],
            corr.ids[keep].copy(),
            (corr.status[keep] == NEW),
        )
        self._prev = _PrevFrame(int(t_ns), meas, corr.ids.copy())
        timings["total"] = (time.perf_counter() - t_start) * 1e3
        counts = {
            "features_left": fl.n,
            "features_right": fr.n,
            "stereo_matches": meas.n,
            "map_candidates": int(cand.size),
            "map_matches": int(corr.matched.sum()) if res is None else res.n_input,
            "inliers": int(np.sum(corr.status == IDENTIFIED)),
            "rejected": int(np.sum(corr.status == REJECTED)),
            "new": int(np.sum(corr.status == NEW)),
            "ransac_iterations": 0 if res is None else res.iterations,
            **m_counts,
        }
        logger.debug("frontend t=%d: %s; ms %s", t_ns, counts, {k: round(v, 2) for k, v in timings.items()})
        return FrontendResult(obs, timings, counts, similarity, res, T_pc, motion, meas, corr)

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

    def _outliers(
        self,
        meas: StereoMatches,
        corr: Correspondences,
        ref_ids: np.ndarray,
        ref_xyz: np.ndarray,
        ref_cov: np.ndarray,
        ref_is_map: bool,
    ) -> tuple[OutlierResult | None, np.ndarray | None]:
        """Run the outlier stage on the IDENTIFIED candidates; failures become REJECTED."""
        cand = np.flatnonzero(corr.status == IDENTIFIED)
        if cand.size == 0:
            return None, None
        order = np.argsort(ref_ids)
        rows = order[np.searchsorted(ref_ids[order], corr.ids[cand])]
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
            res = detect_outliers(
                op, self.rng, a=ref_xyz[rows], b=meas.xyz_R[cand], A=ref_cov[rows], B=meas.cov_R[cand]
            )
            inl = res.inliers
        corr.status[cand[~inl]] = REJECTED
        sim = res.T_b_a() if (res.accepted and ref_is_map) else None
        return res, sim

    def _motion(self, meas: StereoMatches, t_ns: int) -> tuple[np.ndarray | None, MotionIncrement | None, dict]:
        """Frame-to-frame motion from direct descriptor matches to the previous frame's measurements."""
        counts = {"motion_matches": 0, "motion_inliers": 0}
        pv = self._prev
        if pv is None or pv.meas.n == 0 or meas.n == 0 or t_ns < pv.t_ns:
            return None, None, counts
        p = self.params
        binary = meas.binary
        D = distance_matrix(meas.desc, pv.meas.desc, binary)  # (N_curr, N_prev)
        max_d = p.association.max_dist_binary if binary else p.association.max_dist_float
        ratio = p.association.ratio if p.association.ratio is not None else (0.75 if binary else 0.8)
        ii, jj = np.nonzero(D <= max_d)
        sel, _ = ratio_and_cross_check(ii, jj, D[ii, jj], pv.meas.n, ratio, max_d, True)
        ic, ip = ii[sel], jj[sel]
        if D.shape[1] > 1:
            second = np.partition(D, 1, axis=1)[:, 1]
            ok = D[ic, ip] < ratio * second[ic]
            ic, ip = ic[ok], ip[ok]
        counts["motion_matches"] = int(ic.size)
        # b = s R a + t with a in R(t), b in R(t−1): the fitted transform is T_prev_curr
        res = ransac_similarity(
            meas.xyz_R[ic], pv.meas.xyz_R[ip], meas.cov_R[ic], pv.meas.cov_R[ip], p.motion_outliers, self.rng
        )
        if not res.accepted or res.R is None or res.t is None:
            return None, None, counts
        inl = res.inliers
        counts["motion_inliers"] = int(inl.sum())
        # rigid (stereo fixes the scale), Mahalanobis-weighted re-fit on the inliers
        _, R, t, cov_tr = fit_similarity_mahalanobis(
            meas.xyz_R[ic][inl],
            pv.meas.xyz_R[ip][inl],
            meas.cov_R[ic][inl],
            pv.meas.cov_R[ip][inl],
            1.0,
            res.R,
            res.t,
            with_scale=False,
            iterations=p.motion_gn_iterations,
        )
        T_pc = se3(R, t)
        motion = MotionIncrement(pv.t_ns, int(t_ns), t.copy(), so3_log(R), cov_tr)
        return T_pc, motion, counts
