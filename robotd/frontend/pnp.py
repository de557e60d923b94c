"""Stereo PnP: the rigid motion that best reprojects known 3-D points into a rectified pair.

The visual-only motion prior of issue 13: the previous frame's triangulated points P_i (robot
frame R(t−1), FRD at the baseline centre) are matched to the current frame's stereo pixels
z_i = (x_l, x_r, y); the motion T_prev_curr = [R t] is the one whose reprojection

    ẑ_i = π(Rᵀ (P_i − t)),     π(X, Y, Z) = (p_x + f (Y + b/2)/X, p_x + f (Y − b/2)/X, p_y + f Z/X)

is closest to z_i **in pixels**, where the stereo noise is what the sensor actually has (a far
point's depth is uncertain, its pixels are not). Three stages:

1. RANSAC: a hypothesis from three pairs by the closed-form rigid fit of the current frame's
   own triangulated points onto P (Umeyama, no scale); every hypothesis of a batch is scored on
   every pair at once by its stereo reprojection error. The score is the number of image cells
   (a grid over the left image) holding an inlier, then the number of inliers: a moving vehicle
   filling part of the view rarely covers more of the image than the static background does, so
   it loses the consensus even when it carries more features.
2. Gauss–Newton on the inliers, minimising the squared pixel residuals over a right
   perturbation of the pose (δp in R(t), δθ); the inliers are chosen again after each pass.
3. The covariance (6×6 over (t, rotation vector)) from the Gauss–Newton information with the
   residual variance the fit actually left (never below the configured pixel noise).

A moving vehicle close to the camera can cover more of the image than the static background
(the simulated van covers up to 54 %), and then it wins any count of cells or inliers. What tells
the two apart is physics: the rover cannot change its velocity between two frames by more than
its largest acceleration allows. Given a constant-velocity prediction of the motion
(:class:`MotionPrior`), the prediction itself is scored as a hypothesis too, and the best
hypothesis within the physical bounds of the prediction wins over a larger implausible one when
its consensus is substantial (``prior_min_cells``, ``prior_cell_ratio`` of the best's cells). When
no plausible consensus is substantial (a bump, a collision, a wrong prediction), the best
hypothesis wins as before: the prediction decides between consensus sets, it never vetoes the
images.

Numpy, vectorised over hypotheses and pairs; the Gauss–Newton passes are a numba kernel
(robotd.frontend._pnp_kernels).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from robotd.core.errors import ConfigError
from robotd.core.geometry import so3_exp, so3_log, umeyama_batch
from robotd.core.outliers import iteration_budget, sample_indices
from robotd.core.stereo import RectifiedStereo, triangulate
from robotd.frontend import _pnp_kernels as _k


@dataclass(frozen=True, slots=True)
class PnpParams:
    """Stereo PnP RANSAC settings (config ``frontend.pnp_*``).

    inlier_px: a pair is an inlier when its reprojection error (norm over x_l, x_r, y) is below it.
    sigma_px: pixel noise floor of the covariance.
    max_iterations, batch, p_success: RANSAC budget (hypotheses scored per numpy call).
    min_iterations: hypotheses scored at least: the adaptive budget follows the best hypothesis's
      inlier ratio, and a moving vehicle's large early consensus must not end the search before
      samples of the static background were drawn.
    min_inliers: fewer inliers: no motion.
    grid_rows, grid_cols: the image cells of the consensus score.
    gn_iterations: Gauss–Newton passes on the inliers.
    cov_scale: the first-order covariance times this. The Gauss–Newton information treats every
      pair as independent and ignores the triangulation bias of far points; over random
      1 m motions of a 4–40 m scene it is optimistic by about 3× (mean NEES 16–18 for 6 dof,
      tests/robotd/frontend/test_pnp.py), and an over-trusted prior pulls the filter off the map.
    lo_hypotheses, lo_gn_iterations: local optimisation: the best hypotheses of each batch are
      re-fitted on their inliers (this many Gauss–Newton passes) before they compete.
    min_sample_dist_m: a sample whose points are closer than this to each other is degenerate.
    max_accel_mps2, max_angular_accel_radps2: the vehicle's physical limits, which bound how far
      the motion can be from the constant-velocity prediction (|Δt| ≤ a dt², |Δθ| ≤ α dt², plus
      the prediction's own uncertainty, :func:`motion_prior`).
    prior_min_cells, prior_cell_ratio: a consensus within those bounds wins over a larger one
      outside them when it holds an inlier in at least this many cells and this fraction of the
      larger one's cells.
    two_view_iterations: Gauss–Newton passes of :func:`two_view` on the final inliers (0: off).
    align_px: the current frame's pixels of each match are moved onto the previous frame's patch
      first, by at most this much (robotd.frontend.align; 0: off, the keypoints as detected).
    """

    inlier_px: float = 2.0
    sigma_px: float = 0.5
    max_iterations: int = 300
    min_iterations: int = 64
    batch: int = 64
    p_success: float = 0.999
    min_inliers: int = 8
    grid_rows: int = 4
    grid_cols: int = 8
    gn_iterations: int = 6
    lo_hypotheses: int = 2
    cov_scale: float = 3.0
    lo_gn_iterations: int = 2
    min_sample_dist_m: float = 0.05
    max_accel_mps2: float = 10.0
    max_angular_accel_radps2: float = 10.0
    prior_min_cells: int = 3
    prior_cell_ratio: float = 0.25
    two_view_iterations: int = 3
    align_px: float = 1.5

    def __post_init__(self) -> None:
        if not (self.inlier_px > 0 and self.sigma_px > 0 and self.cov_scale > 0):
            raise ConfigError(
                "pnp: expected inlier_px, sigma_px, cov_scale > 0, got "
                f"{self.inlier_px}, {self.sigma_px}, {self.cov_scale}"
            )
        if min(self.max_iterations, self.batch, self.min_inliers, self.grid_rows, self.grid_cols) < 1:
            raise ConfigError("pnp: expected max_iterations, batch, min_inliers, grid_rows, grid_cols >= 1")
        if not (self.align_px >= 0 and math.isfinite(self.align_px)):
            raise ConfigError(f"pnp: expected align_px >= 0, got {self.align_px}")
        if self.two_view_iterations < 0:
            raise ConfigError(f"pnp: expected two_view_iterations >= 0, got {self.two_view_iterations}")
        if not 0.0 < self.p_success < 1.0:
            raise ConfigError(f"pnp: expected p_success in (0, 1), got {self.p_success}")
        if not (self.max_accel_mps2 > 0 and self.max_angular_accel_radps2 > 0):
            raise ConfigError("pnp: expected max_accel_mps2, max_angular_accel_radps2 > 0")
        if not 0.0 <= self.prior_cell_ratio <= 1.0:
            raise ConfigError(f"pnp: expected prior_cell_ratio in [0, 1], got {self.prior_cell_ratio}")


@dataclass(frozen=True, slots=True, eq=False)
class MotionPrior:
    """The predicted motion T_prev_curr (R, t) and how far the true motion can physically be from
    it: |t − t_pred| ≤ tol_t_m and the angle of R_predᵀ R ≤ tol_rot_rad. ``binding``: the
    prediction is a measurement (the vehicle's odometry), so no consensus outside the bounds is
    taken, however large: it is a moving object."""

    R: np.ndarray
    t: np.ndarray
    tol_t_m: float
    tol_rot_rad: float
    binding: bool = False

    def plausible(self, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        """(K,) for hypotheses R (K, 3, 3), t (K, 3)."""
        dt = np.linalg.norm(t - self.t, axis=-1)
        # angle of R_predᵀ R from its trace
        c = (np.einsum("ij,kij->k", self.R, R.reshape(-1, 3, 3)) - 1.0) / 2.0
        ang = np.arccos(np.clip(c, -1.0, 1.0))
        return (dt <= self.tol_t_m) & (ang <= self.tol_rot_rad)


def motion_prior(
    R_last: np.ndarray,
    t_last: np.ndarray,
    dt_last_s: float,
    dt_s: float,
    p: PnpParams,
    sd_t_m: float = 0.0,
    sd_rot_rad: float = 0.0,
) -> MotionPrior:
    """The constant-velocity prediction of this interval's motion from the last one (R_last,
    t_last over dt_last_s, with standard deviations sd_t_m, sd_rot_rad), and its physical bounds:
    the acceleration limits over the interval (a dt², α dt²), plus 1σ of the last motion's own
    error, plus 5 % of the predicted motion and 5 mm / 0.2° for what that σ leaves out."""
    k = dt_s / max(dt_last_s, 1e-6)
    w = so3_log(R_last) * k
    t = t_last * k
    tol_t = p.max_accel_mps2 * dt_s * dt_s + sd_t_m * k + 0.05 * float(np.linalg.norm(t)) + 0.005
    tol_r = (
        p.max_angular_accel_radps2 * dt_s * dt_s + sd_rot_rad * k + 0.05 * float(np.linalg.norm(w)) + math.radians(0.2)
    )
    return MotionPrior(so3_exp(w), t, tol_t, tol_r)


@dataclass(frozen=True, slots=True, eq=False)
class PnpResult:
    """R (3, 3), t (3,): T_prev_curr (points of R(t) map into R(t−1) as R q + t); inliers (N,)
    bool; cov (6, 6) over (t, rotation vector) [m², rad²]; rms_px of the inliers' residuals;
    iterations: hypotheses scored; cells: image cells with an inlier."""

    R: np.ndarray
    t: np.ndarray
    inliers: np.ndarray
    cov: np.ndarray
    rms_px: float
    iterations: int
    cells: int


def project_stereo(q: np.ndarray, rig: RectifiedStereo) -> np.ndarray:
    """Points (..., 3) in the robot frame -> (..., 3) pixels (x_l, x_r, y); NaN behind the rig."""
    X = q[..., 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(X > 1e-6, 1.0 / X, np.nan)
    f, hb = rig.f_px, rig.baseline_m / 2.0
    out = np.empty(q.shape)
    out[..., 0] = rig.px + f * (q[..., 1] + hb) * inv
    out[..., 1] = rig.px + f * (q[..., 1] - hb) * inv
    out[..., 2] = rig.py + f * q[..., 2] * inv
    return out


def projection_jacobian(q: np.ndarray, rig: RectifiedStereo) -> np.ndarray:
    """∂π/∂q (N, 3, 3) of :func:`project_stereo` at points q (N, 3) with X > 0."""
    X, Y, Z = q[:, 0], q[:, 1], q[:, 2]
    f, hb = rig.f_px, rig.baseline_m / 2.0
    iX = 1.0 / X
    J = np.zeros((q.shape[0], 3, 3))
    J[:, 0, 0] = -f * (Y + hb) * iX * iX
    J[:, 0, 1] = f * iX
    J[:, 1, 0] = -f * (Y - hb) * iX * iX
    J[:, 1, 1] = f * iX
    J[:, 2, 0] = -f * Z * iX * iX
    J[:, 2, 2] = f * iX
    return J


def reprojection_residuals(
    R: np.ndarray, t: np.ndarray, P: np.ndarray, z: np.ndarray, rig: RectifiedStereo
) -> np.ndarray:
    """Residuals z − π(Rᵀ(P − t)) for K hypotheses: R (K, 3, 3), t (K, 3) -> (K, N, 3); NaN behind."""
    q = (P[None] - t[:, None, :]) @ R  # rows of Rᵀ (P − t)
    return z[None] - project_stereo(q, rig)


def _cells(z: np.ndarray, rig: RectifiedStereo, p: PnpParams) -> np.ndarray:
    col = np.clip((z[:, 0] * p.grid_cols / max(rig.width, 1)).astype(np.int64), 0, p.grid_cols - 1)
    row = np.clip((z[:, 2] * p.grid_rows / max(rig.height, 1)).astype(np.int64), 0, p.grid_rows - 1)
    return row * p.grid_cols + col


def _coverage(inl: np.ndarray, cell: np.ndarray, n_cells: int) -> np.ndarray:
    """(K,) number of distinct cells holding an inlier, for inlier masks (K, N)."""
    k = inl.shape[0]
    occ = np.zeros((k, n_cells), bool)
    kk, nn = np.nonzero(inl)
    occ[kk, cell[nn]] = True
    return occ.sum(axis=1)


def _sq_errors(
    R: np.ndarray, t: np.ndarray, P: np.ndarray, z: np.ndarray, Q: np.ndarray, zp: np.ndarray, rig: RectifiedStereo
) -> np.ndarray:
    """(N,) the larger of the two directions' squared reprojection errors (NaN behind the rig):
    z − π(Rᵀ(P − t)) for the previous points in the current pair, zp − π(R Q + t) for the
    current points in the previous pair."""
    return _k.sq_errors_kernel(  # type: ignore[no-any-return]
        _f64(R), _f64(t), _f64(P), _f64(z), _f64(Q), _f64(zp), rig.f_px, rig.px, rig.py, rig.baseline_m / 2.0
    )


def _f64(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float64)


def refine(
    R: np.ndarray,
    t: np.ndarray,
    P: np.ndarray,
    z: np.ndarray,
    Q: np.ndarray,
    zp: np.ndarray,
    rig: RectifiedStereo,
    p: PnpParams,
    inliers: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    """Gauss–Newton on the pixel residuals of the inliers, both directions (the previous points
    into the current pair, z − π(Rᵀ(P − t)), and the current points into the previous pair,
    zp − π(R Q + t): each direction alone is biased by the depth errors of the points it moves,
    a far point triangulated 1 % too far stretching the motion by 1 % of its depth, and the two
    biases cancel to first order), over a right perturbation of the pose (δp in R(t), δθ); the
    inliers are chosen again after each pass. Returns R, t, inliers, cov (6, 6) over (t, rotation
    vector), rms [px]. The passes run in a numba kernel (robotd.frontend._pnp_kernels; its numpy
    twin is tests/support/reference_pnp.py)."""
    R, t, inliers, H, rss, count = _k.gauss_newton_kernel(
        _f64(R),
        _f64(t),
        _f64(P),
        _f64(z),
        _f64(Q),
        _f64(zp),
        np.asarray(inliers, dtype=np.bool_),
        rig.f_px,
        rig.px,
        rig.py,
        rig.baseline_m / 2.0,
        int(p.gn_iterations),
        float(p.inlier_px**2),
    )
    rms = math.sqrt(rss / max(count, 1)) if np.any(inliers) else math.inf
    # a residual carries the noise of both frames' pixels (2σ² per coordinate); the inliers' own
    # spread underestimates it (the gate truncates the tails), so it is only used when larger.
    # Each pair is counted twice (both directions share its noise): information halved.
    s2 = max(rss / max(count - 6, 1), 2.0 * p.sigma_px**2)
    try:
        cov_d = 2.0 * p.cov_scale * s2 * np.linalg.inv(H)
    except np.linalg.LinAlgError:
        cov_d = np.full((6, 6), np.nan)
    # δp is in R(t): the translation t moves by R δp; the rotation vector by δθ to first order
    A = np.zeros((6, 6))
    A[:3, :3] = R
    A[3:, 3:] = np.eye(3)
    return R, t, inliers, A @ cov_d @ A.T, rms


def two_view(
    R: np.ndarray,
    t: np.ndarray,
    P: np.ndarray,
    z: np.ndarray,
    zp: np.ndarray,
    rig: RectifiedStereo,
    inliers: np.ndarray,
    iterations: int = 3,
) -> tuple[np.ndarray, np.ndarray]:
    """The motion re-estimated together with the inliers' positions (a two-view bundle
    adjustment): each point's position in the previous frame is a free parameter seen by both
    frames' pixels, zp − π(X) and z − π(Rᵀ(X − t)), instead of being fixed at its triangulation P.

    Why: :func:`refine` treats P as exact, and a far point's P is not: the image motion a
    translation causes is proportional to the point's inverse depth, whose noise σ_d/(f b) is the
    same at every depth, so for points of a few pixels of disparity the regressor is noisy by
    10-30 % and least squares shrinks the translation (errors in variables; both directions of
    :func:`refine` shrink it alike, so they do not cancel it). With far points dominating, the
    shrink is about 1.5 % of the translation at 2.5-5 px (docs/frontend.md "Far points in the
    motion"). Returns R, t; the covariance stays :func:`refine`'s. Unchanged (R, t) when the
    adjustment cannot run (fewer than 3 inliers, a point behind the rig or not finite, a non-finite
    pixel, a singular system)."""
    idx = np.flatnonzero(inliers)
    if idx.size < 3 or iterations < 1:
        return R, t
    R2, t2, S = _k.two_view_kernel(
        _f64(R),
        _f64(t),
        _f64(P),
        _f64(z),
        _f64(zp),
        idx.astype(np.int64),
        rig.f_px,
        rig.px,
        rig.py,
        rig.baseline_m / 2.0,
        int(iterations),
    )
    if not (np.all(np.isfinite(R2)) and np.all(np.isfinite(t2)) and np.all(np.isfinite(S))):
        return R, t
    return R2, t2


def offset_sensitivity(
    R: np.ndarray,
    t: np.ndarray,
    z: np.ndarray,
    zp: np.ndarray,
    rig: RectifiedStereo,
    p: PnpParams,
    inliers: np.ndarray,
    h_px: float = 0.1,
) -> np.ndarray:
    """(6,) d(t, rotation vector)/dδ [m/px, rad/px]: how the motion :func:`stereo_pnp` found from
    the inlier pairs (z in frame t, zp in frame t−1, (N, 3) pixels) moves per pixel of a disparity
    error δ common to both frames (every right column shifted by δ, the points triangulated
    again, the motion refined and adjusted again from (R, t)); central differences of ±``h_px``.
    NaN where the motion cannot be refined. A far point's depth is only as good as the rig's
    disparity offset, so a motion measured over a long jump mostly from far points moves with it
    (docs/frontend.md "Far points and the disparity offset")."""
    out = np.zeros((2, 6))
    for k, h in enumerate((h_px, -h_px)):
        zs, zps = z.copy(), zp.copy()
        zs[:, 1] -= h
        zps[:, 1] -= h
        with np.errstate(divide="ignore", invalid="ignore"):
            P = triangulate(zps[:, 0], zps[:, 1], zps[:, 2], rig.f_px, rig.px, rig.py, rig.baseline_m)
            Q = triangulate(zs[:, 0], zs[:, 1], zs[:, 2], rig.f_px, rig.px, rig.py, rig.baseline_m)
        ok = inliers & np.all(np.isfinite(P), axis=1) & np.all(np.isfinite(Q), axis=1) & (P[:, 0] > 0) & (Q[:, 0] > 0)
        if int(ok.sum()) < max(p.min_inliers, 3):
            return np.full(6, np.nan)
        R1, t1, inl, _, _ = refine(R, t, P, zs, Q, zps, rig, p, ok)
        if p.two_view_iterations > 0:
            R1, t1 = two_view(R1, t1, P, zs, zps, rig, inl, p.two_view_iterations)
        out[k, :3], out[k, 3:] = t1, so3_log(R.T @ R1)
    return (out[0] - out[1]) / (2.0 * h_px)


def warmup() -> None:
    """Compile or load the refinement's numba kernels now (tiny inputs, the daemon's dtypes)."""
    rig = RectifiedStereo(400.0, 320.0, 200.0, 0.075, 640, 400)
    P = np.array([[5.0, 0.0, 0.0], [6.0, 1.0, 0.5], [7.0, -1.0, -0.5], [8.0, 0.5, 0.2]])
    z = project_stereo(P, rig)
    refine(np.eye(3), np.zeros(3), P, z, P, z, rig, PnpParams(), np.ones(4, bool))
    two_view(np.eye(3), np.zeros(3), P, z, z, rig, np.ones(4, bool), 1)


def stereo_pnp(
    P: np.ndarray,
    z: np.ndarray,
    q_curr: np.ndarray,
    z_prev: np.ndarray,
    rig: RectifiedStereo,
    p: PnpParams,
    rng: np.random.Generator,
    prior: MotionPrior | None = None,
) -> PnpResult | None:
    """The motion T_prev_curr from pairs (P_i in R(t−1), z_i pixels of frame t), or None.

    P (N, 3) [m]: the previous frame's points; z (N, 3) [px] = (x_l, x_r, y) of frame t; q_curr
    (N, 3) [m]: the current frame's own triangulation of z; z_prev (N, 3) [px]: the pixels P came
    from. Hypotheses are scored, and refined, on the reprojection errors both ways. ``prior``: the
    predicted motion and its physical bounds (module docstring), or None.
    """
    n = P.shape[0]
    if n < max(p.min_inliers, 3):
        return None
    thr2 = p.inlier_px**2
    cell = _cells(z, rig, p)
    n_cells = p.grid_rows * p.grid_cols
    Score = tuple[int, int, float]  # (cells, inliers, −cost): compared lexicographically
    best: Score = (-1, -1, 0.0)
    best_Rt: tuple[np.ndarray, np.ndarray] | None = None
    best_pl: Score = (-1, -1, 0.0)  # the best within the prior's bounds
    best_pl_Rt: tuple[np.ndarray, np.ndarray] | None = None
    lo = dataclasses.replace(p, gn_iterations=p.lo_gn_iterations)

    def consider(R0: np.ndarray, t0: np.ndarray, inl0: np.ndarray) -> None:
        """Local optimisation of one hypothesis on its inliers, then the competition."""
        nonlocal best, best_Rt, best_pl, best_pl_Rt
        Rj, tj, _, _, _ = refine(R0, t0, P, z, q_curr, z_prev, rig, lo, inl0)
        e2j = _sq_errors(Rj, tj, P, z, q_curr, z_prev, rig)
        inl_j = np.isfinite(e2j) & (e2j < thr2)
        cand = (int(np.unique(cell[inl_j]).size), int(inl_j.sum()), -float(np.where(inl_j, e2j, thr2).sum()))
        if cand > best:
            best, best_Rt = cand, (Rj, tj)
        if prior is not None and cand > best_pl and bool(prior.plausible(Rj[None], tj[None])[0]):
            best_pl, best_pl_Rt = cand, (Rj, tj)

    def prior_wins() -> bool:
        return (
            best_pl_Rt is not None
            and best_pl[1] >= p.min_inliers
            and best_pl[0] >= max(p.prior_min_cells, p.prior_cell_ratio * best[0])
        )

    if prior is not None:
        # the prediction itself is a hypothesis (it finds the background a moving vehicle hides)
        e2p = np.sum(reprojection_residuals(prior.R[None], prior.t[None], P, z, rig)[0] ** 2, axis=1)
        inl_p = np.isfinite(e2p) & (e2p < thr2)
        if inl_p.sum() >= 3:
            consider(prior.R, prior.t, inl_p)
    # with binding odometry only the static points are asked for, and the odometry itself was
    # scored first: the minimum budget (a moving vehicle's consensus is never taken anyway)
    budget, done = (p.min_iterations if prior is not None and prior.binding else p.max_iterations), 0
    while done < budget:
        k = min(p.batch, budget - done)
        s = sample_indices(rng, n, 3, k)
        a, b = q_curr[s], P[s]
        d01 = np.linalg.norm(a[:, 1] - a[:, 0], axis=1)
        d02 = np.linalg.norm(a[:, 2] - a[:, 0], axis=1)
        d12 = np.linalg.norm(a[:, 2] - a[:, 1], axis=1)
        ok = np.minimum(np.minimum(d01, d02), d12) >= p.min_sample_dist_m
        done += k
        if not np.any(ok):
            continue
        _, R, t = umeyama_batch(a[ok], b[ok], with_scale=False)
        # hypotheses are scored one way (the previous points into the current pair); the local
        # optimisation and the final fit use both
        res = reprojection_residuals(R, t, P, z, rig)
        e2 = np.sum(res * res, axis=2)
        inl = np.isfinite(e2) & (e2 < thr2)
        cnt = inl.sum(axis=1)
        cov = _coverage(inl, cell, n_cells)
        cost = np.where(inl, e2, thr2).sum(axis=1)
        # lexicographic: cells, then inliers, then the smaller truncated cost
        key = cov.astype(np.float64) * (n + 1) * (thr2 * n + 1) + cnt * (thr2 * n + 1) - cost
        # local optimisation: the batch's leading hypotheses re-fitted on their inliers (a
        # three-point fit from noisy far points is rarely good enough to gather its whole consensus)
        lead = list(np.argsort(-key)[: p.lo_hypotheses])
        if prior is not None:
            # and the leading one within the prior's bounds
            pl = np.flatnonzero(prior.plausible(R, t) & (cnt >= 3))
            if pl.size:
                j = int(pl[np.argmax(key[pl])])
                if j not in lead:
                    lead.append(j)
        for j in lead:
            if cnt[j] >= 3:
                consider(R[j], t[j], inl[j])
        if best_Rt is not None:
            ratio = best[1] / n
            if prior is not None and best_pl_Rt is not best_Rt and not prior_wins():
                # a larger consensus outside the bounds: keep looking for the background
                ratio = max(best_pl[1], 0) / n
            need = max(p.min_iterations, iteration_budget(ratio, 3, p.p_success, p.max_iterations))
            budget = min(budget, max(done, need))
    chosen = best_pl_Rt if prior_wins() else best_Rt
    if chosen is None or (chosen is best_Rt and best[1] < p.min_inliers):
        return None
    if prior is not None and prior.binding and chosen is not best_pl_Rt:
        return None
    if (
        prior is not None
        and chosen is not best_pl_Rt
        and (best[0] < 2 * p.prior_min_cells or best[1] < 2 * p.min_inliers)
    ):
        # a jump the vehicle cannot make, supported by a handful of matches (a bare wall, a few
        # points on a vehicle): not a motion to trust; the constant-velocity prediction bridges
        return None
    R0, t0 = chosen
    e0 = _sq_errors(R0, t0, P, z, q_curr, z_prev, rig)
    R1, t1, inl, cov6, rms = refine(R0, t0, P, z, q_curr, z_prev, rig, p, np.isfinite(e0) & (e0 < thr2))
    if int(inl.sum()) < p.min_inliers or not np.all(np.isfinite(cov6)):
        return None
    if p.two_view_iterations > 0:
        R1, t1 = two_view(R1, t1, P, z, z_prev, rig, inl, p.two_view_iterations)
    return PnpResult(R1, t1, inl, cov6, rms, done, int(np.unique(cell[inl]).size))
