"""The numpy twin of robotd.frontend._pnp_kernels: the stereo PnP's Gauss–Newton refinement as
it was written before it was compiled, readable and vectorised over points. Tests compare the
kernel with it (tests/robotd/frontend/test_pnp.py)."""

from __future__ import annotations

import math

import numpy as np

from robotd.core.geometry import skew, so3_exp
from robotd.core.stereo import RectifiedStereo
from robotd.frontend.pnp import PnpParams, project_stereo, projection_jacobian


def residuals_jacobian(
    R: np.ndarray, t: np.ndarray, P: np.ndarray, z: np.ndarray, Q: np.ndarray, zp: np.ndarray, rig: RectifiedStereo
) -> tuple[np.ndarray, np.ndarray]:
    """Stacked residuals (n, 6) and their Jacobian (n, 6, 6) wrt the right perturbation (δp, δθ).

    Both directions: the previous points into the current pair, z − π(Rᵀ(P − t)), and the current
    points into the previous pair, z_prev − π(R Q + t). Each direction alone is biased by the depth
    errors of the points it moves (a far point triangulated 1 % too far stretches the motion by
    1 % of its depth); the two biases have opposite signs and cancel to first order.
    """
    q = (P - t) @ R  # Rᵀ (P − t) row-wise
    b = Q @ R.T + t  # R Q + t
    r = np.concatenate([z - project_stereo(q, rig), zp - project_stereo(b, rig)], axis=1)
    Jq = projection_jacobian(q, rig)
    Jb = projection_jacobian(b, rig)
    J = np.empty((P.shape[0], 6, 6))
    # q = Exp(−δθ) Rᵀ (P − t − R δp): ∂q/∂δp = −I, ∂q/∂δθ = [q]×
    J[:, :3, :3] = -Jq
    J[:, :3, 3:] = Jq @ skew(q)
    # b = R Exp(δθ) Q + t + R δp: ∂b/∂δp = R, ∂b/∂δθ = −R [Q]×
    J[:, 3:, :3] = Jb @ R
    J[:, 3:, 3:] = -(Jb @ R) @ skew(Q)
    return r, J


def sq_errors(
    R: np.ndarray, t: np.ndarray, P: np.ndarray, z: np.ndarray, Q: np.ndarray, zp: np.ndarray, rig: RectifiedStereo
) -> np.ndarray:
    """(N,) the larger of the two directions' squared reprojection errors (NaN behind the rig)."""
    r1 = z - project_stereo((P - t) @ R, rig)
    r2 = zp - project_stereo(Q @ R.T + t, rig)
    return np.maximum(np.einsum("ni,ni->n", r1, r1), np.einsum("ni,ni->n", r2, r2))


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
    """Gauss–Newton on the pixel residuals of the inliers (both directions), the inliers re-chosen
    after each pass. Returns R, t, inliers, cov (6, 6) over (t, rotation vector), rms [px]."""
    thr2 = p.inlier_px**2
    H = np.eye(6)
    for _ in range(p.gn_iterations):
        idx = np.flatnonzero(inliers)
        if idx.size < 3:
            break
        r, J = residuals_jacobian(R, t, P[idx], z[idx], Q[idx], zp[idx], rig)
        ok = np.all(np.isfinite(r), axis=1)
        r, J = r[ok], J[ok]
        Jf = J.reshape(-1, 6)
        H = Jf.T @ Jf
        g = Jf.T @ r.ravel()
        try:
            # ẑ(δ) ≈ ẑ + J δ and r = z − ẑ: least squares J δ = r
            d = np.linalg.solve(H + 1e-9 * np.eye(6), g)
        except np.linalg.LinAlgError:
            break
        t = t + R @ d[:3]
        R = R @ so3_exp(d[3:])
        e2 = sq_errors(R, t, P, z, Q, zp, rig)
        inliers = np.isfinite(e2) & (e2 < thr2)
        if float(np.linalg.norm(d)) < 1e-9:
            break
    idx = np.flatnonzero(inliers)
    r_in, J = residuals_jacobian(R, t, P[idx], z[idx], Q[idx], zp[idx], rig)
    Jf = J.reshape(-1, 6)
    H = Jf.T @ Jf
    rss = float(np.sum(r_in * r_in))
    rms = math.sqrt(rss / max(r_in.size, 1)) if idx.size else math.inf
    # a residual carries the noise of both frames' pixels (2σ² per coordinate); the inliers' own
    # spread underestimates it (the gate truncates the tails), so it is only used when larger.
    # Each pair is counted twice (both directions share its noise): information halved.
    s2 = max(rss / max(r_in.size - 6, 1), 2.0 * p.sigma_px**2)
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
    R: np.ndarray, t: np.ndarray, P: np.ndarray, z: np.ndarray, zp: np.ndarray, rig: RectifiedStereo, iterations: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The two-view adjustment of robotd.frontend._pnp_kernels.two_view_kernel on all of P,
    vectorised over the points: Gauss–Newton over the motion (δp, δθ) and every point's position
    X, the points eliminated by their Schur complement. Returns R, t and the last pass's reduced
    information S (6, 6)."""
    X = np.array(P, dtype=float)
    R, t = np.array(R, dtype=float), np.array(t, dtype=float)
    S = np.zeros((6, 6))
    for it in range(iterations + 1):
        Y = (X - t) @ R  # Rᵀ(X − t) row-wise
        r1 = zp - project_stereo(X, rig)
        r2 = z - project_stereo(Y, rig)
        J1X = projection_jacobian(X, rig)
        JY = projection_jacobian(Y, rig)
        K = np.concatenate([np.broadcast_to(-np.eye(3), (len(Y), 3, 3)), np.stack([skew(y) for y in Y])], axis=2)
        J2e = JY @ K  # (n, 3, 6)
        J2X = JY @ R.T  # (n, 3, 3)
        HeX = np.einsum("nij,nik->njk", J2e, J2X)
        HXXi = np.linalg.inv(np.einsum("nij,nik->njk", J1X, J1X) + np.einsum("nij,nik->njk", J2X, J2X))
        gX = np.einsum("nij,ni->nj", J1X, r1) + np.einsum("nij,ni->nj", J2X, r2)
        A = HeX @ HXXi
        S = np.einsum("nij,nik->jk", J2e, J2e) - np.einsum("nij,nkj->ik", A, HeX)
        b = np.einsum("nij,ni->j", J2e, r2) - np.einsum("nij,nj->i", A, gX)
        if it == iterations:
            break
        d = np.linalg.solve(S + 1e-9 * np.eye(6), b)
        X = X + np.einsum("nij,nj->ni", HXXi, gX - np.einsum("nji,j->ni", HeX, d))
        t = t + R @ d[:3]
        R = R @ so3_exp(d[3:])
    return R, t, S
