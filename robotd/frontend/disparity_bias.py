"""A constant disparity error, estimated online from the frame-to-frame motion (issue 26).

Why. A stereo rig's disparities can carry a constant error δ [px] that no pixel-noise model
covers: a principal point of the right camera off by a few tenths of a pixel after rectification,
a baseline that is slightly wrong, a matcher that leans one way. It is invisible on near points
(δ = −0.3 px is 0.75 % of depth at d = 40 px) and dominates far ones (6 % at 5 px, 15 % at 2 px).
Because a far point both sets the depth the motion is measured against and the disparity change
that motion causes, a negative δ makes the rover travel too far: forward translation from a far
point's flow scales with d/(d+δ), from its disparity change with (d/(d+δ))² (docs/frontend.md,
"Far points and the disparity offset"). On KITTI, δ = −0.3 px injected turns a 0.52 % drift into
1.6 % (scale 0.985) even with many near points; in open terrain, with few near points, it is the
whole error.

How. δ is observable whenever the same motion is seen by near and far points: near points fix the
translation (δ barely moves their depth), far points then disagree with it unless δ is right. So,
after the stereo PnP has found the motion T_prev_curr and its inliers, one more Gauss–Newton
solve runs over seven parameters (the motion's 6 and a correction ε to the current offset) on the
same symmetric stereo reprojection residuals the PnP minimises, with the points re-triangulated
from the pixels with ε applied to both frames' right columns. The marginal variance of ε from
that solve (inflated for the residuals' correlation) makes it one measurement of a scalar Kalman
filter with a slow random walk; its estimate corrects every right column the matcher outputs
(x_r ← x_r + δ̂, so d ← d − δ̂) before triangulation, so the PnP, the map's landmarks and the
filter's pixel measurements all see the corrected disparities.

Without near points the offset and the translation's scale cannot be told apart: the marginal
variance of ε is then large, the gain small, and δ̂ stays where it was (0 at the start). With
odometry, the images' motion is not estimated (the vehicle gives it) and δ̂ is held.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from robotd.errors import ConfigError
from robotd.geometry import so3_exp
from robotd.stereo import RectifiedStereo

logger = logging.getLogger(__name__)

MODES = ("online", "off")


@dataclass(frozen=True, slots=True)
class DisparityBiasParams:
    """Online disparity-offset estimation (config ``frontend.disparity_offset``).

    mode: "online" estimates δ from the visual motion; "off" keeps it at ``initial_px``.
    initial_px, prior_sigma_px: the offset assumed at start, and its uncertainty.
    walk_px: random walk of the offset per estimated frame (lets it follow a slow change).
    max_abs_px: |δ̂| bound (a larger estimate is clipped: something else is wrong).
    variance_inflation: the solve treats every residual as independent; real residuals are not,
      so ε's marginal variance is multiplied by this.
    gate_sigma: a frame's ε further than this many σ from the estimate is not fused (a moving
      vehicle, a bad motion).
    min_points: fewer PnP inliers: no measurement.
    iterations: Gauss–Newton passes of the seven-parameter solve.
    min_baseline_m: a measurement spans the motion from an anchor frame to the current one, at
      least this long (points are tracked through the frame-to-frame matches): consecutive frames
      of a 30 Hz camera are too close to tell a far point's depth, and solves over overlapping
      pairs share their errors.
    huber_px: robust weight threshold of a residual norm.
    """

    mode: str = "online"
    initial_px: float = 0.0
    prior_sigma_px: float = 0.5
    walk_px: float = 0.01
    max_abs_px: float = 2.0
    variance_inflation: float = 9.0
    gate_sigma: float = 4.0
    min_points: int = 12
    iterations: int = 2
    huber_px: float = 1.5
    min_baseline_m: float = 2.0

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ConfigError(f"frontend.disparity_offset: expected one of {MODES}, got {self.mode!r}")
        if not (self.prior_sigma_px > 0 and self.walk_px >= 0 and self.max_abs_px > 0):
            raise ConfigError("DisparityBiasParams: prior_sigma_px and max_abs_px must be > 0, walk_px >= 0")


def _triangulate(z: np.ndarray, rig: RectifiedStereo) -> np.ndarray:
    d = z[:, 0] - z[:, 1]
    b = rig.baseline_m
    with np.errstate(divide="ignore", invalid="ignore"):
        X = rig.fb / d
        Y = (z[:, 0] - rig.px) * b / d - b / 2.0
        Z = (z[:, 2] - rig.py) * b / d
    return np.stack([X, Y, Z], -1)


def _project(q: np.ndarray, rig: RectifiedStereo) -> np.ndarray:
    hb = rig.baseline_m / 2.0
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / q[:, 0]
    return np.stack(
        [
            rig.px + rig.f_px * (q[:, 1] + hb) * inv,
            rig.px + rig.f_px * (q[:, 1] - hb) * inv,
            rig.py + rig.f_px * q[:, 2] * inv,
        ],
        -1,
    )


def _residuals(
    theta: np.ndarray, R: np.ndarray, t: np.ndarray, zp: np.ndarray, zc: np.ndarray, rig: RectifiedStereo
) -> np.ndarray:
    """(2N·3,) stacked forward and backward residuals at parameters θ = (δt, δφ, ε)."""
    Rp = R @ so3_exp(theta[3:6])
    tp = t + theta[:3]
    sh = np.array([0.0, theta[6], 0.0])
    zp_e, zc_e = zp + sh, zc + sh
    P = _triangulate(zp_e, rig)  # in R(t−1)
    Q = _triangulate(zc_e, rig)  # in R(t)
    fwd = zc_e - _project((P - tp) @ Rp, rig)
    bwd = zp_e - _project(Q @ Rp.T + tp, rig)
    return np.concatenate([fwd, bwd], 0).ravel()


def solve_offset(
    zp: np.ndarray,
    zc: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    rig: RectifiedStereo,
    params: DisparityBiasParams,
    sigma_px: float,
) -> tuple[float, float] | None:
    """(ε, var ε) [px, px²]: the correction to the pixels' disparity offset that, with the motion
    re-fitted alongside, best explains the pairs (zp in frame t−1, zc in frame t, (N, 3) pixels
    (x_l, x_r, y)) given the motion T_prev_curr = [R t]; None when the solve is degenerate."""
    n = zp.shape[0]
    if n < params.min_points:
        return None
    theta = np.zeros(7)
    steps = np.array([1e-5, 1e-5, 1e-5, 1e-6, 1e-6, 1e-6, 1e-3])
    H = np.zeros((7, 7))
    for _ in range(max(1, params.iterations)):
        r0 = _residuals(theta, R, t, zp, zc, rig)
        J = np.empty((r0.size, 7))
        for k in range(7):
            th = theta.copy()
            th[k] += steps[k]
            J[:, k] = (_residuals(th, R, t, zp, zc, rig) - r0) / steps[k]
        # robust weights per pair-direction (the norm of its three residuals)
        rn = np.sqrt(np.sum(r0.reshape(-1, 3) ** 2, axis=1))
        w3 = np.where(rn <= params.huber_px, 1.0, params.huber_px / np.maximum(rn, 1e-12))
        ok3 = np.isfinite(rn)
        w = np.repeat(np.where(ok3, w3, 0.0), 3)
        r0 = np.where(np.isfinite(r0), r0, 0.0)
        J = np.where(np.isfinite(J), J, 0.0)
        Jw = J * w[:, None]
        H = Jw.T @ J
        g = Jw.T @ r0
        try:
            step = np.linalg.solve(H, g)
        except np.linalg.LinAlgError:
            return None
        theta = theta - step
    try:
        C = np.linalg.inv(H)
    except np.linalg.LinAlgError:
        return None
    var = float(C[6, 6]) * sigma_px**2 * params.variance_inflation
    eps = float(theta[6])
    if not (math.isfinite(eps) and math.isfinite(var) and var > 0):
        return None
    return eps, var


class DisparityBias:
    """The running estimate δ̂ of the rig's disparity offset (module docstring)."""

    def __init__(self, params: DisparityBiasParams | None = None) -> None:
        self.params = params or DisparityBiasParams()
        self.value_px = float(self.params.initial_px)
        self.var_px2 = float(self.params.prior_sigma_px) ** 2
        self.fused = 0
        self.rejected = 0
        # tracks back to the anchor frame: its pixels per previous-frame measurement (NaN: none),
        # the offset they were corrected with, and the motion T_anchor_prev
        self._anchor: np.ndarray | None = None
        self._anchor_delta = 0.0
        self._T_anchor_prev = np.eye(4)

    @property
    def sigma_px(self) -> float:
        return math.sqrt(self.var_px2)

    def correct_right(self, xr: np.ndarray) -> np.ndarray:
        """Right columns with the offset taken off the disparity (d − δ̂ = x_l − (x_r + δ̂))."""
        return xr + self.value_px if self.value_px else xr

    def reset_tracks(self, z_curr: np.ndarray | None = None, corrected_with: float | None = None) -> None:
        """Start the tracks again at the current frame (pixels ``z_curr`` (N, 3), corrected with the
        offset ``corrected_with``, the current estimate when None), or drop them."""
        self._anchor = None if z_curr is None else np.array(z_curr, dtype=float)
        self._anchor_delta = self.value_px if corrected_with is None else corrected_with
        self._T_anchor_prev = np.eye(4)

    def track(
        self,
        z_curr: np.ndarray,
        ic: np.ndarray,
        ip: np.ndarray,
        R: np.ndarray,
        t: np.ndarray,
        rig: RectifiedStereo,
        sigma_px: float,
    ) -> bool:
        """One frame's motion T_prev_curr = [R t] with its inlier pairs (current index ``ic``,
        previous index ``ip``) over the current frame's pixels ``z_curr`` (N, 3): extends the tracks
        and, once they span ``min_baseline_m``, fuses the anchor-to-current solve. True if fused."""
        p = self.params
        if p.mode != "online":
            return False
        n = z_curr.shape[0]
        if self._anchor is None:
            self.reset_tracks(z_curr)
            return False
        ok_idx = ip < self._anchor.shape[0]
        ic, ip = ic[ok_idx], ip[ok_idx]
        anchor = np.full((n, 3), np.nan)
        anchor[ic] = self._anchor[ip]
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, t
        T_ac = self._T_anchor_prev @ T
        valid = np.isfinite(anchor).all(1)
        if int(valid.sum()) < p.min_points:
            self.reset_tracks(z_curr)
            return False
        if float(np.linalg.norm(T_ac[:3, 3])) < p.min_baseline_m:
            self._anchor, self._T_anchor_prev = anchor, T_ac
            return False
        za = anchor[valid].copy()
        za[:, 1] += self.value_px - self._anchor_delta  # re-corrected with today's estimate
        used = self.value_px  # the current pixels were corrected with it
        fused = self.update(za, z_curr[valid], T_ac[:3, :3], T_ac[:3, 3], rig, sigma_px)
        self.reset_tracks(z_curr, used)
        return fused

    def update(
        self, zp: np.ndarray, zc: np.ndarray, R: np.ndarray, t: np.ndarray, rig: RectifiedStereo, sigma_px: float
    ) -> bool:
        """Fuse one frame's motion inliers (pixels already corrected with the current δ̂); True if fused."""
        p = self.params
        if p.mode != "online":
            return False
        m = solve_offset(zp, zc, R, t, rig, p, sigma_px)
        if m is None:
            return False
        eps, var = m
        logger.debug(
            "disparity offset: ε %+.3f ± %.3f px (n=%d), estimate %+.3f ± %.3f",
            eps,
            math.sqrt(var),
            zp.shape[0],
            self.value_px,
            self.sigma_px,
        )
        prior = self.var_px2 + p.walk_px**2
        if eps * eps > p.gate_sigma**2 * (prior + var):
            self.rejected += 1
            return False
        k = prior / (prior + var)
        self.value_px = float(np.clip(self.value_px + k * eps, -p.max_abs_px, p.max_abs_px))
        self.var_px2 = (1.0 - k) * prior
        self.fused += 1
        return True

    def stats(self) -> dict[str, float | int | str]:
        """For health and the replay summary: the estimate, its σ, the measurements fused and gated out."""
        return {
            "disparity_offset_mode": self.params.mode,
            "disparity_offset_px": round(self.value_px, 4),
            "disparity_offset_sigma_px": round(self.sigma_px, 4),
            "disparity_offset_fused": self.fused,
            "disparity_offset_rejected": self.rejected,
        }
