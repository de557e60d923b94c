"""A constant disparity error, estimated online from frames metres apart (issue 26).

Why. A stereo rig's disparities can carry a constant error δ [px] that no pixel-noise model
covers: a principal point of the right camera off by a few tenths of a pixel after rectification,
a baseline that is slightly wrong, a matcher that leans one way. It is invisible on near points
(δ = −0.3 px is 0.75 % of depth at d = 40 px) and dominates far ones (6 % at 5 px, 15 % at 2 px).
Because a far point both sets the depth the motion is measured against and the disparity change
that motion causes, a negative δ makes the rover travel too far: forward translation from a far
point's flow scales with d/(d+δ), from its disparity change with (d/(d+δ))² (docs/frontend.md,
"Far points and the disparity offset").

How. δ is observable whenever the same motion is seen by near and far points: near points fix the
translation (δ barely moves their depth), far points then disagree with it unless δ is right. The
front end keeps an anchor frame (its stereo pixels and descriptors, and the filter's pose of it).
Once the filter's pose is ``min_baseline_m`` from the anchor's, the two frames' measurements are
matched by descriptor, pairs the filter's motion does not carry within ``gate_px`` are dropped,
and one Gauss–Newton solve runs over seven parameters (the anchor-to-current motion and a
correction ε of the offset) on the symmetric stereo reprojection residuals, the points
re-triangulated from the pixels with ε applied to both frames' right columns. ε's marginal
variance from that solve (inflated: the residuals are not independent) makes it one measurement of
a scalar Kalman filter with a slow random walk; the current frame becomes the anchor. The estimate
corrects every right column the matcher outputs (x_r ← x_r + δ̂, so d ← d − δ̂) before the
limits and the triangulation, so the PnP, the map's landmarks and the filter's pixel measurements
all see corrected disparities. It works with and without odometry (the filter's poses give the
motion; the solve re-fits it).

Without near points the offset and the translation's scale cannot be told apart: the marginal
variance of ε is then large, the gain small, and δ̂ stays where it was (0 at the start). A camera
that does not move fuses nothing.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from robotd.core.errors import ConfigError, InputError
from robotd.core.geometry import so3_exp
from robotd.core.stereo import RectifiedStereo, triangulate
from robotd.frontend.pnp import project_stereo

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
      least this long (the stereo matches of both frames, matched by descriptor; the motion from
      the filter's poses, re-fitted by the solve): consecutive frames of a 30 Hz camera are too close to tell a
      far point's depth, and solves over overlapping pairs share their errors.
    max_baseline_m: a longer motion from the anchor (a relocalisation, a gap) starts again.
    gate_px: an anchor-to-current pair whose anchor point, carried by the filter's motion, lands
      further than this from where it is seen (column and row) is a wrong match. (A gate on the
      segment the point's ray is carried onto, which a wrong offset cannot leave, let in too many
      wrong matches: tried, worse everywhere.)
    huber_px: robust weight threshold of a residual norm.
    max_sigma_px: only stereo matches whose disparity the sub-pixel refinement places to this
      precision or better take part (``StereoMatches.sigma_d``; all do when no refinement ran). A
      flat cost valley leaves a disparity that is mostly right but now and then off by a pixel or
      more, leaning one way, and the solve fits those errors with the offset (docs/frontend.md
      "Which matches measure the offset").
    """

    mode: str = "online"
    initial_px: float = 0.0
    prior_sigma_px: float = 0.25
    walk_px: float = 0.01
    max_abs_px: float = 2.0
    variance_inflation: float = 9.0
    gate_sigma: float = 4.0
    min_points: int = 12
    iterations: int = 2
    huber_px: float = 1.5
    min_baseline_m: float = 2.0
    max_baseline_m: float = 8.0
    gate_px: float = 4.0
    max_sigma_px: float = 0.12

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ConfigError(f"frontend.disparity_offset: expected one of {MODES}, got {self.mode!r}")
        if not (self.prior_sigma_px > 0 and self.walk_px >= 0 and self.max_abs_px > 0 and self.max_sigma_px > 0):
            raise ConfigError(
                "DisparityBiasParams: prior_sigma_px, max_abs_px and max_sigma_px must be > 0, walk_px >= 0"
            )


def _triangulate(z: np.ndarray, rig: RectifiedStereo) -> np.ndarray:
    """Pixels (..., 3) = (x_l, x_r, y) -> points (..., 3) in the robot frame (robotd.core.stereo.triangulate)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return triangulate(z[..., 0], z[..., 1], z[..., 2], rig.f_px, rig.px, rig.py, rig.baseline_m)


def _residuals(
    thetas: np.ndarray, R: np.ndarray, t: np.ndarray, zp: np.ndarray, zc: np.ndarray, rig: RectifiedStereo
) -> np.ndarray:
    """(K, 2N·3) stacked forward and backward residuals at K parameter vectors θ = (δt, δφ, ε)
    (K, 7), all at once (the solve's finite differences are 8 evaluations of a few hundred pairs:
    one numpy pass each would be mostly call overhead)."""
    K = thetas.shape[0]
    Rp = R @ so3_exp(thetas[:, 3:6])  # (K, 3, 3)
    tp = t + thetas[:, :3]  # (K, 3)
    sh = np.zeros((K, 1, 3))
    sh[:, 0, 1] = thetas[:, 6]
    zp_e, zc_e = zp[None] + sh, zc[None] + sh  # (K, N, 3)
    P = _triangulate(zp_e, rig)  # in R(t−1)
    Q = _triangulate(zc_e, rig)  # in R(t)
    fwd = zc_e - project_stereo((P - tp[:, None, :]) @ Rp, rig)
    bwd = zp_e - project_stereo(Q @ Rp.transpose(0, 2, 1) + tp[:, None, :], rig)
    return np.concatenate([fwd, bwd], 1).reshape(K, -1)


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
        rr = _residuals(theta[None] + np.vstack([np.zeros(7), np.diag(steps)]), R, t, zp, zc, rig)
        r0 = rr[0]
        J = ((rr[1:] - r0) / steps[:, None]).T  # (2N·3, 7) finite differences
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
    # the noise the fit actually left (never below the configured pixel noise)
    r_end = _residuals(theta[None], R, t, zp, zc, rig).reshape(-1, 3)
    fin = np.isfinite(r_end).all(1)
    rms = 0.0
    if fin.any():
        rms = float(np.sqrt(np.mean(np.minimum(np.sum(r_end[fin] ** 2, 1) / 3.0, params.huber_px**2))))
    var = float(C[6, 6]) * max(sigma_px, rms) ** 2 * params.variance_inflation
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
        # the anchor frame: its landmarks' ids (sorted) and pixels, the offset they were corrected
        # with, and its pose in the world
        self.reset_tracks()

    @property
    def sigma_px(self) -> float:
        return math.sqrt(self.var_px2)

    def correct_right(self, xr: np.ndarray) -> np.ndarray:
        """Right columns with the offset taken off the disparity (d − δ̂ = x_l − (x_r + δ̂))."""
        return xr + self.value_px if self.value_px else xr

    def reset_tracks(self) -> None:
        """Forget the anchor frame (a new map, a relocalisation, a gap)."""
        self._anchor: tuple[np.ndarray, np.ndarray, bool, np.ndarray, float] | None = None

    def observe(
        self,
        z: np.ndarray,
        desc: np.ndarray,
        binary: bool,
        T_world_robot: np.ndarray,
        rig: RectifiedStereo,
        sigma_px: float,
        max_dist: float,
        ratio: float,
        sigma_d: np.ndarray | None = None,
    ) -> bool:
        """One frame's stereo measurements (``z`` (N, 3) pixels corrected with the current estimate,
        ``desc`` their normalised descriptors, ``sigma_d`` (N,) [px] their disparities' precision
        from the refinement or None) and the filter's pose of the frame; only measurements with
        ``sigma_d ≤ max_sigma_px`` take part. Once the pose is
        ``min_baseline_m`` from the anchor frame's, the measurements of both frames are matched by
        descriptor (ratio test and cross-check, ``max_dist`` and ``ratio`` as the frame-to-frame
        motion's), pairs that the filter's motion does not carry within ``gate_px`` are dropped, and
        the rest give one measurement of the offset; this frame becomes the anchor. True if fused."""
        from robotd.frontend.stereo_match import mutual_matches

        p = self.params
        if p.mode != "online":
            return False
        T = np.asarray(T_world_robot, dtype=float)
        z = np.asarray(z, dtype=float)
        if sigma_d is not None:
            sigma_d = np.asarray(sigma_d, dtype=float)
            if sigma_d.shape != (z.shape[0],):
                raise InputError(
                    f"DisparityBias.observe: expected sigma_d of shape ({z.shape[0]},), got {sigma_d.shape}"
                )
            sharp = sigma_d <= p.max_sigma_px  # NaN and inf: not sharp
            z, desc = z[sharp], desc[sharp]
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            self.reset_tracks()  # no usable pose: nothing to measure against, start again
            return False
        if self._anchor is None:
            self._anchor = (z, desc, binary, T.copy(), self.value_px)
            return False
        za_all, da, a_binary, T_wa, delta_a = self._anchor
        T_ac = np.linalg.inv(T_wa) @ T
        base = float(np.linalg.norm(T_ac[:3, 3]))
        if base < p.min_baseline_m:
            return False
        used = self.value_px  # this frame's pixels were corrected with it
        self._anchor = (z, desc, binary, T.copy(), used)
        if base > p.max_baseline_m or a_binary != binary or not len(za_all) or not len(z):
            return False  # a jump (relocalisation, a gap) or nothing to match: start again here
        ic, ia = mutual_matches(desc, da, binary, max_dist, ratio, second_in_row=False)
        if ic.size < p.min_points:
            return False
        za = za_all[ia].copy()
        za[:, 1] += self.value_px - delta_a  # re-corrected with today's estimate
        zc = z[ic]
        # pairs the filter's motion does not carry near where they are seen are wrong matches
        R, t = T_ac[:3, :3], T_ac[:3, 3]
        pred = project_stereo((_triangulate(za, rig) - t) @ R, rig)
        err = np.hypot(pred[:, 0] - zc[:, 0], pred[:, 2] - zc[:, 2])
        ok = np.isfinite(err) & (err < p.gate_px)
        if int(ok.sum()) < p.min_points:
            return False
        return self.update(za[ok], zc[ok], R, t, rig, sigma_px)

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
