"""Evaluation metrics and trajectory files (docs/math.md §11).

Pure functions over arrays of poses; the only I/O is the explicit file readers/writers and
:func:`plot_trajectory` (matplotlib, Agg backend, imported lazily).

Poses are (N, 4, 4) homogeneous ``T_world_body`` matrices unless stated otherwise. Planar (SE(2))
evaluation uses the x, y and yaw of the same matrices. Times are float seconds.

- ATE after a rigid alignment (Umeyama with s ≡ 1, §5.1/§11; Sturm et al. 2012).
- RPE over a fixed frame offset Δ (translation RMSE [m], rotation RMSE [deg]).
- Drift in % of the ground-truth path length after aligning the first pose only.
- Segment drift as KITTI's odometry benchmark defines it (:func:`segment_drift`): the relative
  pose error over every stretch of L metres of true path, in % of L and deg/m.
- NEES per step and ANEES with its two-sided 95 % χ² band (Bar-Shalom et al. 2001); the position
  NEES after aligning the first pose, or by positions over the first M metres
  (:func:`positions_aligned_nees`).
- Map RMSE after alignment.
- TUM trajectory files (``t x y z qx qy qz qw``, what evo reads) and KITTI pose files (12 numbers
  per row, the row-major 3×4 [R|t] of the left camera, optical frame), read as robot-frame truth
  at the baseline centre and stamped from the ``times.txt`` beside them, as a replay carries them;
  written (:func:`write_kitti_poses`) from robot-frame poses as the left camera's, so that tools
  that read KITTI files (evo_ape kitti) compare like with like.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.stats import chi2

from robotd.core.errors import DatasetError, InputError
from robotd.core.geometry import (
    R_ROBOT_OPTICAL,
    R_to_quat,
    quat_to_R,
    rot_z,
    rotation_angle,
    se3,
    se3_inverse,
    so3_exp,
    so3_log,
    umeyama,
    wrap_angle,
)

logger = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True, eq=False)
class Trajectory:
    """A timed trajectory: ``t_s`` (N,) seconds and ``T`` (N, 4, 4) T_world_body.

    ``timed`` is False when the stamps are made up rather than recorded (a KITTI pose file without
    its ``times.txt``: index / 10 Hz); :func:`associate_trajectories` then pairs by index when
    both trajectories have one pose per frame.
    """

    t_s: np.ndarray
    T: np.ndarray
    timed: bool = True

    def __post_init__(self) -> None:
        if self.T.ndim != 3 or self.T.shape[1:] != (4, 4) or self.t_s.shape != (self.T.shape[0],):
            raise InputError(f"Trajectory: expected t_s (N,) and T (N, 4, 4), got {self.t_s.shape} and {self.T.shape}")

    @property
    def xyz(self) -> np.ndarray:
        return self.T[:, :3, 3]

    def __len__(self) -> int:
        return int(self.t_s.shape[0])


# --------------------------------------------------------------------------------------------
# Conversions


def poses_to_T(poses: np.ndarray) -> np.ndarray:
    """(N, 3) planar (x, y, yaw), (N, 6) (x, y, z, roll, pitch, yaw) or (N, 4, 4) -> (N, 4, 4)."""
    from robotd.core.geometry import pose6_to_T

    p = np.asarray(poses, dtype=float)
    if p.ndim == 3 and p.shape[1:] == (4, 4):
        return p
    if p.ndim == 2 and p.shape[1] == 3:
        return se3(rot_z(p[:, 2]), np.column_stack([p[:, :2], np.zeros(len(p))]))
    if p.ndim == 2 and p.shape[1] == 6:
        return pose6_to_T(p)
    raise InputError(f"poses: expected (N, 3), (N, 6) or (N, 4, 4), got {p.shape}")


def _planar(T: np.ndarray) -> np.ndarray:
    """(N, 4, 4) -> (N, 4, 4) keeping only x, y and yaw (for SE(2) evaluation)."""
    yaw = np.arctan2(T[:, 1, 0], T[:, 0, 0])
    return se3(rot_z(yaw), np.column_stack([T[:, :2, 3], np.zeros(len(T))]))


# --------------------------------------------------------------------------------------------
# Alignment and association


def associate(t_est: np.ndarray, t_gt: np.ndarray, max_dt_s: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Match each estimate to the nearest ground-truth time within ``max_dt_s``.

    Returns index arrays (idx_est, idx_gt) of equal length. ``max_dt_s`` defaults to half the
    median ground-truth frame period (§11: nearest within half a frame period). Each ground-truth
    sample is used at most once (the closest estimate wins).
    """
    t_est = np.asarray(t_est, dtype=float)
    t_gt = np.asarray(t_gt, dtype=float)
    if len(t_est) == 0 or len(t_gt) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    order = np.argsort(t_gt, kind="stable")
    tg = t_gt[order]
    if max_dt_s is None:
        max_dt_s = 0.5 * float(np.median(np.diff(tg))) if len(tg) > 1 else np.inf
    pos = np.clip(np.searchsorted(tg, t_est), 1, max(len(tg) - 1, 1))
    left = np.clip(pos - 1, 0, len(tg) - 1)
    right = np.clip(pos, 0, len(tg) - 1)
    pick = np.where(np.abs(tg[left] - t_est) <= np.abs(tg[right] - t_est), left, right)
    dt = np.abs(tg[pick] - t_est)
    ok = dt <= max_dt_s + 1e-12
    ie = np.flatnonzero(ok)
    ig = pick[ok]
    # one estimate per ground-truth sample: keep the closest
    best: dict[int, int] = {}
    for e, g in zip(ie, ig):
        if g not in best or dt[e] < dt[best[g]]:
            best[int(g)] = int(e)
    ig_u = np.array(sorted(best), dtype=np.int64)
    ie_u = np.array([best[g] for g in ig_u], dtype=np.int64)
    srt = np.argsort(ie_u, kind="stable")
    return ie_u[srt], order[ig_u[srt]]


# a replay of a KITTI folder without times.txt stamps frame i at exactly i × 0.1 s; written to a
# TUM file with 9 decimals it comes back within nanoseconds, so 1 ms tells "on that grid" apart
NOMINAL_GRID_TOL_S = 1e-3


def associate_trajectories(est: Trajectory, gt: Trajectory) -> tuple[np.ndarray, np.ndarray, str]:
    """Pair the poses of an estimate and a ground truth: (idx_est, idx_gt, how).

    By time (``how = "time"``, :func:`associate`) when both carry recorded stamps. When one does
    not (``timed`` False: a KITTI poses.txt without times.txt, stamped index / 10 Hz):

    - the same count on both sides (one pose per frame): by index (``"index"``); the made-up
      stamps may not be the frame times (KITTI raw runs at ~9.66 Hz);
    - different counts: by time only when the other side's stamps lie on that 10 Hz grid (what a
      replay of such a folder writes, e.g. a part of it), else an InputError: there is no telling
      which frame an off-grid stamp belongs to.
    """
    if est.timed and gt.timed:
        ie, ig = associate(est.t_s, gt.t_s)
        return ie, ig, "time"
    if len(est) == len(gt):
        idx = np.arange(len(est), dtype=np.int64)
        return idx, idx.copy(), "index"
    grid, other = (gt, est) if not gt.timed else (est, gt)
    pos = np.clip(np.searchsorted(grid.t_s, other.t_s), 1, max(len(grid) - 1, 1))
    off = np.minimum(
        np.abs(grid.t_s[pos - 1] - other.t_s), np.abs(grid.t_s[np.minimum(pos, len(grid) - 1)] - other.t_s)
    )
    if np.any(off > NOMINAL_GRID_TOL_S):
        k = int(np.argmax(off > NOMINAL_GRID_TOL_S))
        raise InputError(
            f"evaluate: {len(est)} estimated and {len(gt)} true poses, one side without recorded times "
            f"(a KITTI poses.txt without times.txt), and stamp {other.t_s[k]:.6f} s is not on its 10 Hz "
            "grid: give the poses.txt its times.txt, or an estimate with one pose per frame"
        )
    ie, ig = associate(est.t_s, gt.t_s)
    return ie, ig, "time"


def align_rigid(est: np.ndarray, gt: np.ndarray, planar: bool = False) -> np.ndarray:
    """The rigid transform T (4, 4) minimising Σ‖gt_i − T est_i‖² over positions (Umeyama, s ≡ 1).

    ``est``, ``gt``: (N, 3) positions. ``planar``: SE(2) alignment in x, y (z left unchanged).
    """
    est = np.asarray(est, dtype=float)
    gt = np.asarray(gt, dtype=float)
    if est.shape != gt.shape or len(est) < 2:
        raise InputError(f"align_rigid: expected two (N>=2, 3) arrays, got {est.shape} and {gt.shape}")
    if planar:
        _, R2, t2 = umeyama(est[:, :2], gt[:, :2], with_scale=False)
        R = np.eye(3)
        R[:2, :2] = R2
        return se3(R, np.array([t2[0], t2[1], 0.0]))
    _, R, t = umeyama(est, gt, with_scale=False)
    return se3(R, t)


def similarity_scale(est: np.ndarray, gt: np.ndarray) -> float:
    """Scale of the similarity alignment est -> gt; a diagnostic only, since stereo fixes scale (§11)."""
    s, _, _ = umeyama(np.asarray(est, float), np.asarray(gt, float), with_scale=True)
    return float(s)


# --------------------------------------------------------------------------------------------
# Metrics


def path_length(xyz: np.ndarray) -> float:
    """Length [m] of a polyline (N, d)."""
    xyz = np.asarray(xyz, dtype=float)
    return float(np.sum(np.linalg.norm(np.diff(xyz, axis=0), axis=1))) if len(xyz) > 1 else 0.0


def ate(est_T: np.ndarray, gt_T: np.ndarray, planar: bool = False, align: bool = True) -> dict[str, float]:
    """Absolute trajectory error after a rigid alignment (§11), associated pose pairs (N, 4, 4).

    ``ate_rmse_m = sqrt(mean ‖trans(Q_i⁻¹ T P_i)‖²)``; also mean, median and max of the
    per-pose translation error, and the heading RMSE [deg] (yaw error in the plane for planar
    runs, the full rotation angle otherwise). ``planar`` aligns in SE(2). On a straight path the
    positions leave the rotation about it undetermined and T takes it from the orientations, on a
    stationary one all of T's rotation; ``ate_umeyama_rmse_m`` is the RMSE after the plain
    Umeyama fit of positions instead (evo_ape's ``-a``), equal to ``ate_rmse_m`` on other paths.
    """
    P = np.asarray(est_T, dtype=float)
    Q = np.asarray(gt_T, dtype=float)
    if P.shape != Q.shape or P.ndim != 3 or len(P) == 0:
        raise InputError(f"ate: expected two (N, 4, 4) arrays, got {P.shape} and {Q.shape}")
    if planar:
        P, Q = _planar(P), _planar(Q)
    T = align_rigid(P[:, :3, 3], Q[:, :3, 3], planar=planar) if (align and len(P) > 1) else np.eye(4)
    # the plain least-squares fit of positions (what evo_ape -a reports): on a straight or
    # stationary path it takes the rotation the positions leave open from their noise
    e_umeyama = np.linalg.norm((se3_inverse(Q) @ T @ P)[:, :3, 3], axis=1)
    if align and len(P) > 1 and not planar:
        kind = _positions_degenerate(P[:, :3, 3])
        if kind == "stationary":
            T = _align_by_orientation(P, Q)
        elif kind == "collinear":
            T = _fix_roll_about_path(T, P, Q)
    E = se3_inverse(Q) @ T @ P
    e = np.linalg.norm(E[:, :3, 3], axis=1)
    if planar:
        rot = np.abs(np.arctan2(E[:, 1, 0], E[:, 0, 0]))
    else:
        rot = rotation_angle(E[:, :3, :3])
    return {
        "ate_rmse_m": float(np.sqrt(np.mean(e**2))),
        "ate_mean_m": float(np.mean(e)),
        "ate_median_m": float(np.median(e)),
        "ate_max_m": float(np.max(e)),
        "heading_rmse_deg": float(np.rad2deg(np.sqrt(np.mean(rot**2)))),
        "final_error_m": float(e[-1]),
        "ate_umeyama_rmse_m": float(np.sqrt(np.mean(e_umeyama**2))),
    }


def _positions_degenerate(p: np.ndarray, ratio: float = 0.05, min_spread_m: float = 0.1) -> str:
    """ "stationary", "collinear" or "" for positions (N, 3). A rigid fit to collinear positions
    leaves the rotation about the path to noise (a straight KITTI drive); to stationary ones, every
    rotation (the EuRoC piece)."""
    c = p - p.mean(0)
    sv = np.linalg.svd(c, compute_uv=False)
    if float(sv[0] / np.sqrt(len(p))) < min_spread_m:
        return "stationary"
    return "collinear" if sv[1] < ratio * sv[0] else ""


def _fix_roll_about_path(T: np.ndarray, P: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """Replace the rotation of T about the path axis (undetermined by collinear positions) by the
    one the orientations give: the mean world-frame orientation error, projected on the axis."""
    q = Q[:, :3, 3]
    c = q.mean(0)
    axis = np.linalg.svd(q - c)[2][0]
    W = (T[:3, :3] @ P[:, :3, :3]) @ np.swapaxes(Q[:, :3, :3], 1, 2)  # world-frame error rotations
    phi = -float(np.mean(so3_log(W) @ axis))
    S = se3(so3_exp(axis * phi), c - so3_exp(axis * phi) @ c)
    return S @ T


def _align_by_orientation(P: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """Rigid alignment whose rotation is the chordal mean of Q_i P_i⁻¹ (orientations, not
    positions), translation from the centroids; used where positions cannot fix the rotation."""
    M = np.einsum("nij,nkj->ik", Q[:, :3, :3], P[:, :3, :3])
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = U @ D @ Vt
    t = Q[:, :3, 3].mean(0) - R @ P[:, :3, 3].mean(0)
    return se3(R, t)


def ate_errors(est_T: np.ndarray, gt_T: np.ndarray, planar: bool = False) -> np.ndarray:
    """Per-pose translation error (N,) [m] after the rigid alignment used by :func:`ate`."""
    P, Q = np.asarray(est_T, float), np.asarray(gt_T, float)
    if planar:
        P, Q = _planar(P), _planar(Q)
    T = align_rigid(P[:, :3, 3], Q[:, :3, 3], planar=planar)
    return np.linalg.norm((se3_inverse(Q) @ T @ P)[:, :3, 3], axis=1)


def rpe(est_T: np.ndarray, gt_T: np.ndarray, delta: int = 1, planar: bool = False) -> dict[str, float]:
    """Relative pose error over a frame offset Δ (§11): E_i = (Q_i⁻¹Q_{i+Δ})⁻¹ (P_i⁻¹P_{i+Δ}).

    Returns the RMSE of the translation [m] and of the rotation angle [deg] of E_i.
    """
    P = np.asarray(est_T, dtype=float)
    Q = np.asarray(gt_T, dtype=float)
    if planar:
        P, Q = _planar(P), _planar(Q)
    if len(P) <= delta:
        return {"rpe_trans_m": math.nan, "rpe_rot_deg": math.nan}
    dP = se3_inverse(P[:-delta]) @ P[delta:]
    dQ = se3_inverse(Q[:-delta]) @ Q[delta:]
    E = se3_inverse(dQ) @ dP
    t = np.linalg.norm(E[:, :3, 3], axis=1)
    r = rotation_angle(E[:, :3, :3])
    return {
        "rpe_trans_m": float(np.sqrt(np.mean(t**2))),
        "rpe_rot_deg": float(np.rad2deg(np.sqrt(np.mean(r**2)))),
    }


# Below this ground-truth path length [m] the relative figures are reported as NaN (null in JSON):
# drift in % of the path length divides by a (nearly) zero length, and the similarity scale fits a
# scale to positions that are mostly noise, so a stationary EuRoC cut read "drift 24 %, scale 0.28".
# 1 m is well above a stationary platform's ground-truth jitter (mm) and below any real drive's path.
MIN_PATH_FOR_RELATIVE_M = 1.0


def drift_m(est_T: np.ndarray, gt_T: np.ndarray) -> float:
    """End-point position error [m] after aligning the first poses only (the numerator of
    :func:`drift_pct`); meaningful on any path, stationary included."""
    P = np.asarray(est_T, dtype=float)
    Q = np.asarray(gt_T, dtype=float)
    P = Q[0] @ se3_inverse(P[0]) @ P
    return float(np.linalg.norm(P[-1, :3, 3] - Q[-1, :3, 3]))


def drift_pct(est_T: np.ndarray, gt_T: np.ndarray) -> float:
    """End-point drift in % of the ground-truth path length, first pose aligned only (§11)."""
    P = np.asarray(est_T, dtype=float)
    Q = np.asarray(gt_T, dtype=float)
    L = path_length(Q[:, :3, 3])
    if L <= 0:
        return math.nan
    P = Q[0] @ se3_inverse(P[0]) @ P
    return float(100.0 * np.linalg.norm(P[-1, :3, 3] - Q[-1, :3, 3]) / L)


# the steps travel_offset_deg measures over: 2 m of true path, at least 1 m straight-line
TRAVEL_SPAN_M = 2.0


def travel_offset_deg(est_T: np.ndarray, gt_T: np.ndarray, span_m: float = TRAVEL_SPAN_M) -> tuple[float, float]:
    """The median angle [deg] between each trajectory's heading and its direction of travel:
    (estimate's, truth's), over steps of ``span_m`` of true path, each in its own body frame
    (atan2 of the lateral over the forward part of the step, less half the step's turn, since the
    chord of an arc points half way round it; steps backwards or shorter than half of ``span_m`` in
    a straight line left out). NaN when fewer than 3 steps qualify.

    A vehicle's camera sees the same mount on any drive, so the two agree when both are right. When
    they do not, the truth's orientation and its positions disagree by the difference or the
    estimate's do, and :func:`drift_pct`, which aligns by the first orientation, carries that
    difference × path as lateral error: kitti-raw-0009's OXTS truth travels 1.2° to the side of its
    heading, robotd's estimate −0.2° there with ORB and SIFT alike, and −0.3° to −0.4° on kitti-seq1,
    whose truth says −0.2° (docs/benchmarks.md)."""
    P = np.asarray(est_T, dtype=float)
    Q = np.asarray(gt_T, dtype=float)
    s = cumulative_path(Q[:, :3, 3])
    j = np.searchsorted(s, s + span_m)
    i = np.flatnonzero(j < len(Q))
    j = j[i]
    out = []
    for T in (P, Q):
        d = np.einsum("nji,nj->ni", T[i, :3, :3], T[j, :3, 3] - T[i, :3, 3])  # R_iᵀ (p_j − p_i)
        Rij = np.einsum("nki,nkj->nij", T[i, :3, :3], T[j, :3, :3])
        half_turn = 0.5 * np.arctan2(Rij[:, 1, 0], Rij[:, 0, 0])  # a chord of an arc points half way
        ok = (d[:, 0] > 0) & (np.linalg.norm(d, axis=1) >= 0.5 * span_m)
        a = wrap_angle(np.arctan2(d[ok, 1], d[ok, 0]) - half_turn[ok])
        out.append(float(np.degrees(np.median(a))) if np.sum(ok) >= 3 else math.nan)
    return out[0], out[1]


def _metres_text(v: float) -> str:
    """A path length for a sentence: to 0.1 m, or to the millimetre below a metre."""
    return f"{v:.1f}" if v >= 1.0 else f"{v:.3f}"


def cumulative_path(xyz: np.ndarray) -> np.ndarray:
    """(N,) path length [m] from the first position to each position of a polyline (N, d)."""
    xyz = np.asarray(xyz, dtype=float)
    steps = np.linalg.norm(np.diff(xyz, axis=0), axis=1) if len(xyz) > 1 else np.zeros(0)
    return np.concatenate([[0.0], np.cumsum(steps)])


# KITTI's odometry benchmark: segments of 100, 200, ..., 800 m of true path, one starting every 10 frames
KITTI_SEGMENT_LENGTHS_M: tuple[float, ...] = (100.0, 200.0, 300.0, 400.0, 500.0, 600.0, 700.0, 800.0)
SEGMENT_STEP_FRAMES = 10


def segment_drift(
    est_T: np.ndarray,
    gt_T: np.ndarray,
    lengths_m: Sequence[float] = KITTI_SEGMENT_LENGTHS_M,
    step_frames: int = SEGMENT_STEP_FRAMES,
    planar: bool = False,
) -> dict[str, Any]:
    """Segment drift as the KITTI odometry benchmark defines it, over associated poses (N, 4, 4).

    A segment starts at every ``step_frames``-th pose i (0, 10, 20, ...) and, for each length L,
    ends at the first pose j at which the true path length from i reaches L (none when the path
    after i is shorter). Its error is the relative pose error E = (P_i⁻¹ P_j)⁻¹ (Q_i⁻¹ Q_j): the
    translation ‖t(E)‖ in % of L and the rotation angle of E in degrees per metre of L. Each length
    averages its segments; the overall figures average every segment of every length (so a length
    with more segments weighs more, as in the benchmark's own summary).

    Returns ``segment_drift_pct``, ``segment_rot_deg_per_m`` and ``segment_count`` (overall),
    ``segments`` (one dict per length: ``length_m``, ``count``, ``drift_pct``, ``rot_deg_per_m``),
    ``segment_lengths_m``, ``segment_step_frames`` and ``segment_note``: None, or why there is no
    segment (a true path shorter than the shortest length). Undefined figures are NaN.
    ``planar``: x, y and yaw only (SE(2) runs).
    """
    P = poses_to_T(est_T)
    Q = poses_to_T(gt_T)
    if P.shape != Q.shape or len(P) == 0:
        raise InputError(f"segment_drift: expected two (N, 4, 4) arrays, got {P.shape} and {Q.shape}")
    if planar:
        P, Q = _planar(P), _planar(Q)
    lengths = [float(v) for v in lengths_m]
    if not lengths or not all(math.isfinite(v) and v > 0 for v in lengths):
        raise InputError(f"segment lengths: expected positive metres, got {list(lengths_m)}")
    if step_frames < 1:
        raise InputError(f"segment step: expected at least 1 frame, got {step_frames}")
    s = cumulative_path(Q[:, :3, 3])
    starts = np.arange(0, len(Q), step_frames)
    rows: list[dict[str, Any]] = []
    trans_all: list[np.ndarray] = []
    rot_all: list[np.ndarray] = []
    for L in lengths:
        # s never decreases, so the first pose at which the path from a start reaches L is a search
        ends = np.searchsorted(s, s[starts] + L, side="left")
        ok = ends < len(Q)
        i, j = starts[ok], ends[ok]
        E = se3_inverse(se3_inverse(P[i]) @ P[j]) @ (se3_inverse(Q[i]) @ Q[j])
        trans = 100.0 * np.linalg.norm(E[:, :3, 3], axis=1) / L
        rot = np.rad2deg(rotation_angle(E[:, :3, :3])) / L
        trans_all.append(trans)
        rot_all.append(rot)
        rows.append(
            {
                "length_m": L,
                "count": len(i),
                "drift_pct": float(np.mean(trans)) if len(i) else math.nan,
                "rot_deg_per_m": float(np.mean(rot)) if len(i) else math.nan,
            }
        )
    trans_cat, rot_cat = np.concatenate(trans_all), np.concatenate(rot_all)
    note = None
    if not len(trans_cat):
        note = (
            f"no segment: the true path ({_metres_text(s[-1])} m) is shorter than the shortest segment "
            f"({min(lengths):g} m)"
        )
    return {
        "segment_drift_pct": float(np.mean(trans_cat)) if len(trans_cat) else math.nan,
        "segment_rot_deg_per_m": float(np.mean(rot_cat)) if len(rot_cat) else math.nan,
        "segment_count": len(trans_cat),
        "segments": rows,
        "segment_lengths_m": lengths,
        "segment_step_frames": int(step_frames),
        "segment_note": note,
    }


def nees(err: np.ndarray, cov: np.ndarray, angle_dims: Sequence[int] = ()) -> np.ndarray:
    """Normalised estimation error squared ε_t = e_tᵀ P_t⁻¹ e_t (§11), per step.

    ``err``: (T, n) truth − estimate; ``cov``: (T, n, n). Components listed in ``angle_dims``
    are wrapped to (−π, π] first. Uses a linear solve, not an explicit inverse.
    """
    e = np.array(err, dtype=float, copy=True)
    for i in angle_dims:
        e[:, i] = wrap_angle(e[:, i])
    x = np.linalg.solve(np.asarray(cov, dtype=float), e[..., None])[..., 0]
    return np.einsum("ti,ti->t", e, x)


def position_nees(est_T: np.ndarray, gt_T: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Per-pose position NEES ε = eᵀ P⁻¹ e of a replay against truth, first poses aligned.

    ``est_T``, ``gt_T``: (N, 4, 4) associated poses; ``cov``: (N, 6, 6) the estimate's reported
    covariance (world frame, position block first). The estimate is moved by the alignment
    A = Q₀ P₀⁻¹ (the drift convention, :func:`drift_m`) and its position covariance rotated with
    it; e is the 3-D position error. The first pose (the alignment itself) and poses whose
    position covariance is not positive definite get NaN.
    """
    P = poses_to_T(est_T)
    Q = poses_to_T(gt_T)
    skip = np.zeros(len(P), dtype=bool)
    skip[0] = True
    return _position_nees_aligned_by(Q[0] @ se3_inverse(P[0]), P, Q, cov, skip)


def _position_nees_aligned_by(
    A: np.ndarray, P: np.ndarray, Q: np.ndarray, cov: np.ndarray, skip: np.ndarray
) -> np.ndarray:
    """Per-pose position NEES after moving the estimate by the rigid A (4, 4) and rotating its
    position covariance with it; NaN where ``skip`` or where that covariance is not positive
    definite."""
    C = np.asarray(cov, dtype=float)[:, :3, :3]
    e = Q[:, :3, 3] - (P[:, :3, 3] @ A[:3, :3].T + A[:3, 3])
    C = A[:3, :3] @ C @ A[:3, :3].T
    C = 0.5 * (C + np.swapaxes(C, 1, 2))
    out = np.full(len(P), np.nan)
    ok = np.linalg.eigvalsh(C)[:, 0] > 1e-12  # 1 µm standard deviation: anything less is "exact"
    ok &= ~skip
    if np.any(ok):
        out[ok] = nees(e[ok], C[ok])
    return out


# The M of the positions-aligned NEES in a replay's summary (truth_aligned_*) and so in
# bench/accuracy.py's rows: 9-10 frames of a KITTI car (about 1.1 m a frame at 10 Hz), enough
# positions for a fit, and most of a 50-frame piece (55-60 m) is left to judge.
ALIGN_POSITIONS_M = 10.0


@dataclass(frozen=True, slots=True)
class PositionAlignment:
    """How :func:`align_by_positions` aligned an estimate to the truth.

    ``T`` (4, 4) maps the estimate's world to the truth's; ``fit`` (N,) marks the poses within the
    first ``over_m`` metres of true path, the ones it was fitted to; ``kind`` is "positions",
    "positions+first-pose-roll" or "first-pose" and ``note`` says why in words.
    """

    T: np.ndarray
    fit: np.ndarray
    over_m: float
    kind: str
    note: str


def align_by_positions(est_T: np.ndarray, gt_T: np.ndarray, over_m: float) -> PositionAlignment:
    """Rigid alignment (no scale) of an estimate to the truth by the positions of the poses within
    the first ``over_m`` metres of true path only (associated poses (N, 4, 4)).

    - Those positions span a plane or a volume: the least-squares rigid fit of positions
      (Umeyama, s ≡ 1); kind "positions".
    - They lie on a line (a straight start: the second singular value of the centred positions
      under 5 % of the first): the fit fixes all but the rotation about that line, which then
      comes from the first pose, whose orientation the estimate and the truth share by
      construction: the twist about the line of the rotation between the aligned estimate's first
      orientation and the truth's is removed; kind "positions+first-pose-roll".
    - They stay within 0.1 m (RMS about their mean), or only the first pose is within ``over_m``:
      positions fix no rotation, and the estimate is aligned by its first pose, as drift is
      (A = Q₀ P₀⁻¹); kind "first-pose".
    """
    P = poses_to_T(est_T)
    Q = poses_to_T(gt_T)
    if P.shape != Q.shape or len(P) == 0:
        raise InputError(f"align_by_positions: expected two (N, 4, 4) arrays, got {P.shape} and {Q.shape}")
    if not (math.isfinite(over_m) and over_m > 0):
        raise InputError(f"align by positions: expected a positive length in metres, got {over_m}")
    fit = cumulative_path(Q[:, :3, 3]) <= over_m
    n = int(np.sum(fit))
    qf, pf = Q[fit, :3, 3], P[fit, :3, 3]
    kind = _positions_degenerate(qf) if n >= 2 else "single"
    where = f"the {n} poses of the first {over_m:g} m of true path"
    if kind == "":
        return PositionAlignment(align_rigid(pf, qf), fit, over_m, "positions", f"rigid fit of {where}")
    if kind == "collinear":
        T = _roll_from_first_pose(align_rigid(pf, qf), P[0], Q[0], qf)
        note = (
            f"{where} lie on a line: rigid fit of their positions, and the rotation about that line "
            "from the first pose's orientation"
        )
        return PositionAlignment(T, fit, over_m, "positions+first-pose-roll", note)
    if kind == "stationary":
        why = f"{where} stay within 0.1 m (RMS about their mean): positions fix no rotation"
    else:
        why = f"no pose but the first within the first {over_m:g} m of true path"
    return PositionAlignment(Q[0] @ se3_inverse(P[0]), fit, over_m, "first-pose", f"{why}; aligned by the first pose")


def _roll_from_first_pose(T: np.ndarray, P0: np.ndarray, Q0: np.ndarray, line: np.ndarray) -> np.ndarray:
    """T with its rotation about the line through the positions ``line`` (M, 3), which collinear
    positions leave open, set so that the aligned first estimated orientation has no twist about the
    line relative to the true one (swing-twist split of the rotation between them)."""
    c = line.mean(0)
    axis = np.linalg.svd(line - c)[2][0]
    W = Q0[:3, :3] @ (T[:3, :3] @ P0[:3, :3]).T  # the aligned estimate's first orientation -> the truth's
    q = R_to_quat(W)  # (w, x, y, z); W = swing · twist, the twist about ``axis`` by this angle:
    twist = 2.0 * math.atan2(float(q[1:] @ axis), float(q[0]))
    R = so3_exp(axis * twist)
    return se3(R, c - R @ c) @ T


def positions_aligned_nees(
    est_T: np.ndarray, gt_T: np.ndarray, cov: np.ndarray, over_m: float = ALIGN_POSITIONS_M
) -> tuple[np.ndarray, dict[str, Any]]:
    """Per-pose position NEES (N,) after :func:`align_by_positions` over the first ``over_m`` metres,
    NaN on the poses it was fitted to, and its summary: ``aligned_nees_pos_mean``,
    ``aligned_nees_pos_in_band_frac``, ``aligned_nees_pos_frames`` (:func:`nees_summary` over the
    poses past ``over_m`` metres), ``aligned_fit_frames``, ``align_positions_m``, ``alignment``
    (the kind) and ``alignment_note`` (why; also when no pose is left to judge).

    ``cov`` (N, 6, 6): the estimate's reported covariance, position block first, rotated with the
    alignment. Unlike :func:`position_nees` the figure does not rest on the first pose's orientation,
    which a straight start can get wrong by a fraction of a degree that grows into decimetres.
    """
    P = poses_to_T(est_T)
    Q = poses_to_T(gt_T)
    C = np.asarray(cov, dtype=float)
    if C.ndim != 3 or C.shape[0] != len(P) or C.shape[1] < 3 or C.shape[1] != C.shape[2]:
        raise InputError(f"positions_aligned_nees: expected ({len(P)}, 6, 6) covariances, got {C.shape}")
    al = align_by_positions(P, Q, over_m)
    eps = _position_nees_aligned_by(al.T, P, Q, C, al.fit)
    s = nees_summary(eps)
    note = al.note
    if al.fit.all():
        note += (
            f"; the true path ({_metres_text(path_length(Q[:, :3, 3]))} m) does not go past {over_m:g} m: "
            "no pose to judge"
        )
    out: dict[str, Any] = {f"aligned_{k}": v for k, v in s.items()}
    out["aligned_nees_pos_frames"] = int(s["nees_pos_frames"])
    out.update(
        aligned_fit_frames=int(np.sum(al.fit)), align_positions_m=float(over_m), alignment=al.kind, alignment_note=note
    )
    return eps, out


def nees_band_3(p: float = 0.95) -> tuple[float, float]:
    """The two-sided ``p`` interval of χ²(3), the band one position NEES lies in when consistent."""
    return anees_band(3, 1, p)


def nees_summary(eps: np.ndarray) -> dict[str, float]:
    """``nees_pos_mean`` and ``nees_pos_in_band_frac`` (share inside the 95 % χ²(3) interval) over
    the poses with a NEES; ``nees_pos_frames`` says how many."""
    v = np.asarray(eps, dtype=float)
    v = v[np.isfinite(v)]
    lo, hi = nees_band_3()
    if not len(v):
        return {"nees_pos_mean": math.nan, "nees_pos_in_band_frac": math.nan, "nees_pos_frames": 0.0}
    return {
        "nees_pos_mean": float(np.mean(v)),
        "nees_pos_in_band_frac": float(np.mean((v >= lo) & (v <= hi))),
        "nees_pos_frames": float(len(v)),
    }


def anees_band(n: int, runs: int, p: float = 0.95) -> tuple[float, float]:
    """Two-sided χ² band for the ANEES of ``runs`` Monte Carlo runs of an n-dim state (§11)."""
    a = (1.0 - p) / 2.0
    return float(chi2.ppf(a, n * runs) / runs), float(chi2.ppf(1.0 - a, n * runs) / runs)


def anees(nees_runs: np.ndarray) -> np.ndarray:
    """(R, T) NEES of R runs -> (T,) ANEES per step (mean over runs)."""
    return np.mean(np.asarray(nees_runs, dtype=float), axis=0)


def map_rmse(
    est_xyz: np.ndarray, gt_xyz: np.ndarray, T_align: np.ndarray | None = None, planar: bool = False
) -> dict[str, float | np.ndarray]:
    """Landmark map error (M corresponding rows) after alignment.

    With ``T_align`` (4, 4) the estimate is first mapped by it (e.g. the trajectory alignment);
    otherwise the maps are aligned to each other rigidly. Returns ``map_rmse_m`` and
    ``per_landmark_m`` (M,).
    """
    a = np.asarray(est_xyz, dtype=float)
    g = np.asarray(gt_xyz, dtype=float)
    if a.shape != g.shape or len(a) == 0:
        raise InputError(f"map_rmse: expected two (M, 3) arrays, got {a.shape} and {g.shape}")
    if planar:
        a = np.column_stack([a[:, :2], np.zeros(len(a))])
        g = np.column_stack([g[:, :2], np.zeros(len(g))])
    if T_align is None:
        T_align = align_rigid(a, g, planar=planar) if len(a) >= 3 else np.eye(4)
    a2 = a @ T_align[:3, :3].T + T_align[:3, 3]
    e = np.linalg.norm(a2 - g, axis=1)
    return {"map_rmse_m": float(np.sqrt(np.mean(e**2))), "per_landmark_m": e}


# --------------------------------------------------------------------------------------------
# Files


def write_tum(path: str | Path, t_s: np.ndarray, T: np.ndarray) -> None:
    """Write a TUM trajectory: one line ``t x y z qx qy qz qw`` per pose (evo reads it)."""
    T = poses_to_T(T)
    q = R_to_quat(T[:, :3, :3])  # (w, x, y, z)
    rows = np.column_stack([np.asarray(t_s, dtype=float), T[:, :3, 3], q[:, 1:], q[:, :1]])
    with open(path, "w", encoding="ascii") as fh:
        fh.write("# timestamp tx ty tz qx qy qz qw\n")
        for r in rows:
            fh.write(" ".join(f"{v:.9f}" if i == 0 else f"{v:.9g}" for i, v in enumerate(r)) + "\n")


def T_robot_left_camera(baseline_m: float) -> np.ndarray:
    """The left rectified camera's optical frame (x right, y down, z forward) in robotd's robot
    frame (FRD at the stereo baseline centre, the camera b/2 to its left): x_R = M x_C. It is the
    map of :func:`drivers.dataset.kitti_truth_to_robot`: T_R0_R = M T_C0_C M⁻¹."""
    return se3(R_ROBOT_OPTICAL, np.array([0.0, -0.5 * float(baseline_m), 0.0]))


def robot_to_left_camera(T_world_robot: np.ndarray, baseline_m: float) -> np.ndarray:
    """Robot-frame poses (..., 4, 4), world = the robot at the first pose, as KITTI gives its poses:
    the left camera's optical frame relative to the left camera at the first pose, T_C0_C = M⁻¹ T M."""
    M = T_robot_left_camera(baseline_m)
    return se3_inverse(M) @ np.asarray(T_world_robot, dtype=float) @ M


def write_kitti_poses(path: str | Path, T_world_robot: np.ndarray, baseline_m: float) -> None:
    """Write robot-frame poses as a KITTI odometry pose file: per pose one row of the 12 numbers of
    the row-major 3×4 [R|t] of the left camera (:func:`robot_to_left_camera`), no stamps, no
    header (KITTI's devkit and evo_ape kitti read it as they read a poses.txt)."""
    C = robot_to_left_camera(poses_to_T(T_world_robot), baseline_m)
    with open(path, "w", encoding="ascii") as fh:
        for row in C[:, :3, :].reshape(len(C), 12):
            fh.write(" ".join(f"{v:.9g}" for v in row) + "\n")


TRAJECTORY_FORMATS = ("tum", "kitti")


def write_trajectory(path: str | Path, t_s: np.ndarray, T_world_robot: np.ndarray, fmt: str, baseline_m: float) -> None:
    """A trajectory file in ``fmt``: "tum" (robot frame, stamped: :func:`write_tum`) or "kitti" (the
    left camera, one row per pose: :func:`write_kitti_poses`)."""
    if fmt == "tum":
        write_tum(path, t_s, T_world_robot)
    elif fmt == "kitti":
        write_kitti_poses(path, T_world_robot, baseline_m)
    else:
        raise InputError(f"trajectory format {fmt!r}: expected one of {list(TRAJECTORY_FORMATS)}")


# The pose covariance beside a TUM file (``robotd replay --out T.txt`` writes ``T.cov.txt``): one
# row per pose, ``t`` then the 21 upper-triangle entries (row-major) of the 6×6 covariance over
# (x, y, z, roll, pitch, yaw) in the world frame (LOCAL_FRD), in m², m·rad and rad², the angles
# being the ZYX Euler angles of the TUM pose. TUM itself stays plain, so evo reads it unchanged.
_COV_IU = np.triu_indices(6)
COV_HEADER = "# timestamp then upper triangle (row-major) of the 6x6 pose covariance over x y z roll pitch yaw [m, rad]"


def cov_path_for(traj_path: str | Path) -> Path:
    """Where the pose covariance of trajectory ``traj_path`` lives: ``T.txt`` -> ``T.cov.txt``
    (``T`` -> ``T.cov``)."""
    p = Path(traj_path)
    return p.with_name(f"{p.stem}.cov{p.suffix}") if p.suffix else p.with_name(p.name + ".cov")


def write_pose_cov(path: str | Path, t_s: np.ndarray, cov: np.ndarray) -> None:
    """Write per-pose 6×6 covariances (see ``COV_HEADER``) with the same stamps as the TUM file."""
    C = np.asarray(cov, dtype=float)
    if C.ndim != 3 or C.shape[1:] != (6, 6) or len(C) != len(t_s):
        raise InputError(f"pose covariance: expected ({len(t_s)}, 6, 6), got {C.shape}")
    rows = np.column_stack([np.asarray(t_s, dtype=float), C[:, _COV_IU[0], _COV_IU[1]]])
    with open(path, "w", encoding="ascii") as fh:
        fh.write(COV_HEADER + "\n")
        for r in rows:
            fh.write(" ".join(f"{v:.9f}" if i == 0 else f"{v:.9g}" for i, v in enumerate(r)) + "\n")


def read_pose_cov(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a pose-covariance file -> (t_s (N,), cov (N, 6, 6)); symmetric by construction."""
    a = _read_rows(Path(path), 22, "pose covariance")
    C = np.zeros((len(a), 6, 6))
    C[:, _COV_IU[0], _COV_IU[1]] = a[:, 1:]
    C = C + np.swapaxes(C, 1, 2) - C * np.eye(6)
    return a[:, 0].copy(), C


def _read_rows(path: Path, ncols: int, what: str) -> np.ndarray:
    if not path.is_file():
        raise DatasetError(f"{what}: no such file {path}")
    rows = []
    with open(path, encoding="utf-8") as fh:
        for lineno, line in enumerate(fh, start=1):
            s = line.strip()
            if not s or s.startswith("#"):
                continue
            parts = s.replace(",", " ").split()
            if len(parts) != ncols:
                raise DatasetError(f"{what} {path}:{lineno}: expected {ncols} numbers, got {len(parts)}")
            try:
                rows.append([float(p) for p in parts])
            except ValueError as exc:
                raise DatasetError(f"{what} {path}:{lineno}: not a number ({exc})") from None
    if not rows:
        raise DatasetError(f"{what} {path}: no poses")
    a = np.array(rows)
    if not np.all(np.isfinite(a)):
        raise DatasetError(f"{what} {path}: non-finite values")
    return a


def read_tum(path: str | Path) -> Trajectory:
    """Read a TUM trajectory file (``t x y z qx qy qz qw``; '#' comments) -> Trajectory."""
    a = _read_rows(Path(path), 8, "TUM trajectory")
    quat_wxyz = np.column_stack([a[:, 7], a[:, 4:7]])
    if np.any(np.abs(np.linalg.norm(quat_wxyz, axis=1) - 1.0) > 1e-3):
        bad = int(np.argmax(np.abs(np.linalg.norm(quat_wxyz, axis=1) - 1.0)))
        raise DatasetError(f"TUM trajectory {path}: quaternion of pose {bad} is not unit")
    return Trajectory(a[:, 0].copy(), se3(quat_to_R(quat_wxyz), a[:, 1:4]))


def read_kitti_poses(path: str | Path, rate_hz: float = 10.0) -> Trajectory:
    """Read a KITTI odometry pose file: 12 numbers per row, row-major [R|t] of the left camera.

    The poses stay as they are in the file: the left camera in its optical frame (x right, y down,
    z forward) relative to frame 0; :func:`read_kitti_truth` moves them to robotd's robot frame.
    Stamps: the ``times.txt`` beside the file when there is one (the frame times, in seconds: what
    a replay stamps its trajectory with), else index / ``rate_hz`` with ``timed`` False.
    """
    from drivers.dataset import kitti_pose_rows, kitti_times_ns

    path = Path(path)
    T = kitti_pose_rows(_read_rows(path, 12, "KITTI poses"))  # rotations made orthonormal
    times = path.parent / "times.txt"
    if times.is_file():
        return Trajectory(kitti_times_ns(times, len(T)) / 1e9, T)
    return Trajectory(np.arange(len(T)) / rate_hz, T, timed=False)


def read_kitti_truth(path: str | Path, calib_fallback: str | Path | None = None) -> Trajectory:
    """A KITTI poses.txt as robot-frame truth, exactly as a replay of its folder carries it.

    The left-camera optical-frame poses become the robot frame (FRD) at the stereo baseline centre
    (``drivers.dataset.kitti_truth_to_robot``, baseline from P1 of the ``calib.txt`` beside the
    file, else of ``calib_fallback``: the other trajectory's, for a ``robotd replay --format kitti``
    output written elsewhere), relative to frame 0; stamps as :func:`read_kitti_poses`. Without a
    calib.txt the origin stays at the left camera (a warning says so): the lever arm b/2 then shows
    in any turn.
    """
    from drivers.dataset import kitti_baseline_m, kitti_truth_to_robot

    path = Path(path)
    tr = read_kitti_poses(path)
    calib = path.parent / "calib.txt"
    if not calib.is_file() and calib_fallback is not None:
        calib = Path(calib_fallback)
    if calib.is_file():
        b = kitti_baseline_m(calib)
    else:
        b = 0.0
        logger.warning("%s: no calib.txt beside it, so no baseline: truth stays at the left camera", path)
    T = se3_inverse(tr.T[0]) @ tr.T
    return Trajectory(tr.t_s, kitti_truth_to_robot(T, b), tr.timed)


def read_trajectory(path: str | Path, calib_fallback: str | Path | None = None) -> Trajectory:
    """TUM (8 columns) or KITTI (12 columns) by the first data row, in robotd's robot frame.

    A TUM file is taken as it is (robotd writes robot-frame TUM); a KITTI pose file is moved to the
    robot frame at the baseline centre and stamped from its times.txt (:func:`read_kitti_truth`,
    with the calib.txt beside it, else ``calib_fallback``).
    """
    p = Path(path)
    if not p.is_file():
        raise DatasetError(f"trajectory: no such file {p}")
    with open(p, encoding="utf-8") as fh:
        for line in fh:
            s = line.strip()
            if s and not s.startswith("#"):
                n = len(s.replace(",", " ").split())
                break
        else:
            raise DatasetError(f"trajectory {p}: no poses")
    if n == 8:
        return read_tum(p)
    if n == 12:
        return read_kitti_truth(p, calib_fallback)
    raise DatasetError(f"trajectory {p}: expected 8 (TUM) or 12 (KITTI) columns, got {n}")


def evaluate_trajectories(
    est: Trajectory, gt: Trajectory, planar: bool = False, cov: np.ndarray | None = None
) -> dict[str, float]:
    """All trajectory metrics of §11 for two trajectories, paired by :func:`associate_trajectories`
    (nearest time; by index when one side has no recorded times and the counts match). With
    ``cov`` ((N, 6, 6), the estimate's reported pose covariance, one per estimated pose) also the
    position NEES figures of :func:`nees_summary`."""
    ie, ig, _ = associate_trajectories(est, gt)
    if len(ie) < 2:
        raise InputError(
            f"evaluate: only {len(ie)} poses associate within half a frame period "
            f"(estimate {est.t_s[0]:.3f}…{est.t_s[-1]:.3f} s, ground truth {gt.t_s[0]:.3f}…{gt.t_s[-1]:.3f} s)"
        )
    P, Q = est.T[ie], gt.T[ig]
    out: dict[str, float] = {"frames": float(len(ie))}
    out.update(ate(P, Q, planar=planar))
    out.update(rpe(P, Q, 1, planar=planar))
    out["drift_pct"] = drift_pct(P, Q)
    out["drift_m"] = drift_m(P, Q)
    out["path_length_m"] = path_length(Q[:, :3, 3])
    out["similarity_scale"] = similarity_scale(P[:, :3, 3], Q[:, :3, 3]) if len(P) >= 3 else math.nan
    out["travel_offset_deg"], out["gt_travel_offset_deg"] = travel_offset_deg(P, Q)
    if cov is not None:
        out.update(nees_summary(position_nees(P, Q, np.asarray(cov)[ie])))
    if out["path_length_m"] < MIN_PATH_FOR_RELATIVE_M:
        # undefined on a (nearly) stationary path: see MIN_PATH_FOR_RELATIVE_M; drift_m still says it
        out["drift_pct"] = math.nan
        out["similarity_scale"] = math.nan
    return out


def evaluate_files(traj_path: str | Path, gt_path: str | Path, planar: bool = False) -> dict[str, float]:
    """Metrics of an estimated trajectory file against a ground-truth file (TUM or KITTI each).

    Keys: frames, ate_rmse_m, ate_mean_m, ate_median_m, ate_max_m, heading_rmse_deg,
    final_error_m, rpe_trans_m, rpe_rot_deg (Δ = 1 frame), drift_pct, drift_m, path_length_m,
    similarity_scale. drift_pct and similarity_scale are NaN when the ground-truth path is shorter
    than ``MIN_PATH_FOR_RELATIVE_M`` (undefined there); drift_m (the end-point error after aligning
    the first poses) is always given. TUM files are taken in robotd's robot frame; a KITTI pose
    file is moved there first (:func:`read_trajectory`), so a replay's TUM output evaluates against
    its folder's poses.txt exactly as the replay's own ``truth_*`` figures.
    """
    est = read_trajectory(traj_path)
    gt = read_trajectory(gt_path)
    out = evaluate_trajectories(est, gt, planar=planar)
    out["frames"] = int(out["frames"])
    logger.info(
        "evaluated %s against %s: ATE %.3f m over %d frames", traj_path, gt_path, out["ate_rmse_m"], out["frames"]
    )
    return out


# --------------------------------------------------------------------------------------------
# Plot


def plot_trajectory(
    est: np.ndarray | Trajectory,
    gt: np.ndarray | Trajectory | None,
    landmarks: np.ndarray | None,
    out_png: str | Path,
    *,
    gt_landmarks: np.ndarray | None = None,
    title: str = "",
    align: bool = True,
) -> Path:
    """Top view (x right-hand, y) of the estimate against ground truth, with landmarks; writes a PNG.

    ``est``/``gt``: (N, 3|6) poses, (N, 4, 4) or Trajectory (same length when ``align``; the
    estimate is rigidly aligned to the ground truth first, §11); ``landmarks``: (M, ≥2) estimated
    map in the estimate's frame (aligned with it). Returns the path written.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    P = poses_to_T(est.T if isinstance(est, Trajectory) else est)
    Q = None if gt is None else poses_to_T(gt.T if isinstance(gt, Trajectory) else gt)
    T = np.eye(4)
    if Q is not None and align and len(Q) == len(P) and len(P) > 1:
        T = align_rigid(P[:, :3, 3], Q[:, :3, 3])
    pe = P[:, :3, 3] @ T[:3, :3].T + T[:3, 3]
    fig, ax = plt.subplots(figsize=(6.4, 5.6), dpi=100)
    # FRD world: x forward, y right; plot y to the right and x up so turns look as driven
    if gt_landmarks is not None and len(gt_landmarks):
        g = np.asarray(gt_landmarks, dtype=float)
        ax.scatter(g[:, 1], g[:, 0], s=18, marker="x", c="0.6", lw=0.8, label="landmarks (truth)")
    if landmarks is not None and len(landmarks):
        lm = np.asarray(landmarks, dtype=float)
        lm3 = np.column_stack([lm[:, :2], lm[:, 2] if lm.shape[1] > 2 else np.zeros(len(lm))])
        lm3 = lm3 @ T[:3, :3].T + T[:3, 3]
        ax.scatter(lm3[:, 1], lm3[:, 0], s=4, c="tab:orange", label="landmarks (estimate)")
    if Q is not None:
        ax.plot(Q[:, 1, 3], Q[:, 0, 3], "k-", lw=1.2, label="ground truth")
    ax.plot(pe[:, 1], pe[:, 0], "-", c="tab:blue", lw=1.0, label="estimate")
    ax.set_xlabel("y [m] (right)")
    ax.set_ylabel("x [m] (forward at start)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(True, lw=0.3)
    ax.legend(loc="best", fontsize=7)
    if title:
        ax.set_title(title, fontsize=9)
    fig.tight_layout()
    out = Path(out_png)
    fig.savefig(out)
    plt.close(fig)
    return out


def plot_nees(t_s: np.ndarray, eps: np.ndarray, out_png: str | Path, *, title: str = "") -> Path:
    """The position NEES over time (log scale) with the two-sided 95 % χ²(3) band; writes a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lo, hi = nees_band_3()
    v = np.asarray(eps, dtype=float)
    ok = np.isfinite(v)
    fig, ax = plt.subplots(figsize=(6.4, 3.6), dpi=100)
    ax.axhspan(lo, hi, color="tab:green", alpha=0.15, label=f"95 % band [{lo:.3g}, {hi:.3g}]")
    ax.axhline(3.0, color="tab:green", lw=0.8, ls="--", label="E[ε] = 3")
    ax.semilogy(np.asarray(t_s)[ok], np.maximum(v[ok], 1e-3), ".-", c="tab:blue", lw=0.8, ms=3, label="ε (position)")
    s = nees_summary(v)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("position NEES")
    ax.set_title(
        f"{title}  mean {s['nees_pos_mean']:.3g}, in band {100 * s['nees_pos_in_band_frac']:.0f} %".strip(), fontsize=9
    )
    ax.grid(True, which="both", lw=0.3)
    ax.legend(loc="best", fontsize=7)
    fig.tight_layout()
    out = Path(out_png)
    fig.savefig(out)
    plt.close(fig)
    return out
