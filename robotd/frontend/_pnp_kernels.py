"""Numba kernel of the stereo PnP's Gauss–Newton refinement (robotd.frontend.pnp.refine).

The same arithmetic as ``pnp._residuals_jacobian`` / ``pnp._sq_errors`` / the loop of
``pnp.refine``, one point at a time with the 6×6 normal equations accumulated in place: the numpy
version builds (n, 6, 6) Jacobians and calls small matrix products hundreds of times per frame,
which cost 4–5 ms of the ~6 ms motion stage; this costs a few hundred microseconds. The numpy
twin stays in ``tests/support/reference_pnp.py`` and the tests compare the two.
"""

from __future__ import annotations

import math

import numpy as np

from robotd.core.jit import jit


@jit(inline="always")
def _so3_exp(w: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    """Rodrigues' formula (as robotd.core.geometry.so3_exp)."""
    th = math.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2])
    K = np.zeros((3, 3))
    K[0, 1], K[0, 2] = -w[2], w[1]
    K[1, 0], K[1, 2] = w[2], -w[0]
    K[2, 0], K[2, 1] = -w[1], w[0]
    if th < 1e-12:
        return np.eye(3) + K
    a = math.sin(th) / th
    b = (1.0 - math.cos(th)) / (th * th)
    return np.eye(3) + a * K + b * (K @ K)


@jit(inline="always")
def _project(q0: float, q1: float, q2: float, f: float, px: float, py: float, hb: float) -> tuple:  # pragma: no cover
    """π of pnp.project_stereo for one point: (x_l, x_r, y), NaN behind the rig."""
    if not q0 > 1e-6:
        return math.nan, math.nan, math.nan
    inv = 1.0 / q0
    return px + f * (q1 + hb) * inv, px + f * (q1 - hb) * inv, py + f * q2 * inv


@jit(inline="always")
def _jac_into(J: np.ndarray, q0: float, q1: float, q2: float, f: float, hb: float) -> None:  # pragma: no cover
    """∂π/∂q (3, 3) at q with X > 0 (pnp.projection_jacobian), written into ``J``."""
    iX = 1.0 / q0
    J[0, 0] = -f * (q1 + hb) * iX * iX
    J[0, 1] = f * iX
    J[0, 2] = 0.0
    J[1, 0] = -f * (q1 - hb) * iX * iX
    J[1, 1] = f * iX
    J[1, 2] = 0.0
    J[2, 0] = -f * q2 * iX * iX
    J[2, 1] = 0.0
    J[2, 2] = f * iX


@jit(inline="always")
def _times_skew_into(out: np.ndarray, A: np.ndarray, v0: float, v1: float, v2: float) -> None:  # pragma: no cover
    """out = A @ [v]× for (3, 3) A, [v]× = ((0, −v2, v1), (v2, 0, −v0), (−v1, v0, 0))."""
    for r in range(3):
        out[r, 0] = A[r, 1] * v2 - A[r, 2] * v1
        out[r, 1] = -A[r, 0] * v2 + A[r, 2] * v0
        out[r, 2] = A[r, 0] * v1 - A[r, 1] * v0


@jit
def sq_errors_kernel(
    R: np.ndarray,
    t: np.ndarray,
    P: np.ndarray,
    z: np.ndarray,
    Q: np.ndarray,
    zp: np.ndarray,
    f: float,
    px: float,
    py: float,
    hb: float,
) -> np.ndarray:  # pragma: no cover - compiled
    """(N,) the larger of the two directions' squared reprojection errors, NaN behind the rig."""
    n = P.shape[0]
    out = np.empty(n)
    for i in range(n):
        d0, d1, d2 = P[i, 0] - t[0], P[i, 1] - t[1], P[i, 2] - t[2]
        q0 = R[0, 0] * d0 + R[1, 0] * d1 + R[2, 0] * d2
        q1 = R[0, 1] * d0 + R[1, 1] * d1 + R[2, 1] * d2
        q2 = R[0, 2] * d0 + R[1, 2] * d1 + R[2, 2] * d2
        a0, a1, a2 = _project(q0, q1, q2, f, px, py, hb)
        b0 = R[0, 0] * Q[i, 0] + R[0, 1] * Q[i, 1] + R[0, 2] * Q[i, 2] + t[0]
        b1 = R[1, 0] * Q[i, 0] + R[1, 1] * Q[i, 1] + R[1, 2] * Q[i, 2] + t[1]
        b2 = R[2, 0] * Q[i, 0] + R[2, 1] * Q[i, 1] + R[2, 2] * Q[i, 2] + t[2]
        c0, c1, c2 = _project(b0, b1, b2, f, px, py, hb)
        e1 = (z[i, 0] - a0) ** 2 + (z[i, 1] - a1) ** 2 + (z[i, 2] - a2) ** 2
        e2 = (zp[i, 0] - c0) ** 2 + (zp[i, 1] - c1) ** 2 + (zp[i, 2] - c2) ** 2
        # as numpy's maximum: NaN when either is NaN
        out[i] = math.nan if (e1 != e1 or e2 != e2) else max(e1, e2)
    return out


@jit
def normal_equations_kernel(
    R: np.ndarray,
    t: np.ndarray,
    P: np.ndarray,
    z: np.ndarray,
    Q: np.ndarray,
    zp: np.ndarray,
    idx: np.ndarray,
    f: float,
    px: float,
    py: float,
    hb: float,
) -> tuple:  # pragma: no cover - compiled
    """H = Σ JᵢᵀJᵢ (6, 6), g = Σ Jᵢᵀrᵢ (6,), Σ|rᵢ|² and the residual count (6 per point) over the
    points ``idx`` whose six residuals (both directions) are finite (pnp._residuals_jacobian)."""
    H = np.zeros((6, 6))
    g = np.zeros(6)
    rss = 0.0
    count = 0
    r = np.empty(6)
    J = np.empty((6, 6))
    Jq = np.empty((3, 3))
    Jb = np.empty((3, 3))
    JbR = np.empty((3, 3))
    S = np.empty((3, 3))
    for k in range(idx.shape[0]):
        i = idx[k]
        d0, d1, d2 = P[i, 0] - t[0], P[i, 1] - t[1], P[i, 2] - t[2]
        q0 = R[0, 0] * d0 + R[1, 0] * d1 + R[2, 0] * d2
        q1 = R[0, 1] * d0 + R[1, 1] * d1 + R[2, 1] * d2
        q2 = R[0, 2] * d0 + R[1, 2] * d1 + R[2, 2] * d2
        Q0, Q1, Q2 = Q[i, 0], Q[i, 1], Q[i, 2]
        b0 = R[0, 0] * Q0 + R[0, 1] * Q1 + R[0, 2] * Q2 + t[0]
        b1 = R[1, 0] * Q0 + R[1, 1] * Q1 + R[1, 2] * Q2 + t[1]
        b2 = R[2, 0] * Q0 + R[2, 1] * Q1 + R[2, 2] * Q2 + t[2]
        a0, a1, a2 = _project(q0, q1, q2, f, px, py, hb)
        c0, c1, c2 = _project(b0, b1, b2, f, px, py, hb)
        r[0], r[1], r[2] = z[i, 0] - a0, z[i, 1] - a1, z[i, 2] - a2
        r[3], r[4], r[5] = zp[i, 0] - c0, zp[i, 1] - c1, zp[i, 2] - c2
        finite = True
        for a in range(6):
            if not math.isfinite(r[a]):
                finite = False
        if not finite:
            continue
        _jac_into(Jq, q0, q1, q2, f, hb)
        _jac_into(Jb, b0, b1, b2, f, hb)
        # q = Exp(−δθ) Rᵀ (P − t − R δp): ∂q/∂δp = −I, ∂q/∂δθ = [q]×
        # b = R Exp(δθ) Q + t + R δp: ∂b/∂δp = R, ∂b/∂δθ = −R [Q]×
        _times_skew_into(S, Jq, q0, q1, q2)
        for row in range(3):
            for col in range(3):
                JbR[row, col] = Jb[row, 0] * R[0, col] + Jb[row, 1] * R[1, col] + Jb[row, 2] * R[2, col]
        for row in range(3):
            for col in range(3):
                J[row, col] = -Jq[row, col]
                J[row, 3 + col] = S[row, col]
                J[3 + row, col] = JbR[row, col]
        _times_skew_into(S, JbR, Q0, Q1, Q2)
        for row in range(3):
            for col in range(3):
                J[3 + row, 3 + col] = -S[row, col]
        for u in range(6):
            for v in range(u, 6):
                acc = 0.0
                for m in range(6):
                    acc += J[m, u] * J[m, v]
                H[u, v] += acc
            acc = 0.0
            for m in range(6):
                acc += J[m, u] * r[m]
            g[u] += acc
        for m in range(6):
            rss += r[m] * r[m]
        count += 6
    for u in range(6):
        for v in range(u):
            H[u, v] = H[v, u]
    return H, g, rss, count


@jit
def gauss_newton_kernel(
    R: np.ndarray,
    t: np.ndarray,
    P: np.ndarray,
    z: np.ndarray,
    Q: np.ndarray,
    zp: np.ndarray,
    inliers: np.ndarray,
    f: float,
    px: float,
    py: float,
    hb: float,
    iterations: int,
    thr2: float,
) -> tuple:  # pragma: no cover - compiled
    """The loop of pnp.refine: Gauss–Newton passes on the inliers (both directions), the inliers
    chosen again after each pass. Returns R, t, inliers and the final pass's H (6, 6), Σ|r|² and
    residual count over the final inliers."""
    R = R.copy()
    t = t.copy()
    inl = inliers.copy()
    eye = np.eye(6)
    for _ in range(iterations):
        idx = np.flatnonzero(inl)
        if idx.shape[0] < 3:
            break
        H, g, _, _ = normal_equations_kernel(R, t, P, z, Q, zp, idx, f, px, py, hb)
        A = H + 1e-9 * eye
        if not np.all(np.isfinite(A)) or abs(np.linalg.det(A)) < 1e-300:
            break
        d = np.linalg.solve(A, g)
        t = t + R @ d[:3]
        R = R @ _so3_exp(d[3:])
        e2 = sq_errors_kernel(R, t, P, z, Q, zp, f, px, py, hb)
        for i in range(e2.shape[0]):
            inl[i] = math.isfinite(e2[i]) and e2[i] < thr2
        if math.sqrt(d[0] ** 2 + d[1] ** 2 + d[2] ** 2 + d[3] ** 2 + d[4] ** 2 + d[5] ** 2) < 1e-9:
            break
    idx = np.flatnonzero(inl)
    H, _, rss, count = normal_equations_kernel(R, t, P, z, Q, zp, idx, f, px, py, hb)
    return R, t, inl, H, rss, count


@jit(inline="always")
def _inv33_into(out: np.ndarray, A: np.ndarray) -> bool:  # pragma: no cover - compiled
    """out = A⁻¹ for a (3, 3) A by cofactors; False (out untouched) when A is singular."""
    c00 = A[1, 1] * A[2, 2] - A[1, 2] * A[2, 1]
    c01 = A[1, 2] * A[2, 0] - A[1, 0] * A[2, 2]
    c02 = A[1, 0] * A[2, 1] - A[1, 1] * A[2, 0]
    det = A[0, 0] * c00 + A[0, 1] * c01 + A[0, 2] * c02
    if not abs(det) > 1e-300:
        return False
    inv = 1.0 / det
    out[0, 0] = c00 * inv
    out[1, 0] = c01 * inv
    out[2, 0] = c02 * inv
    out[0, 1] = (A[0, 2] * A[2, 1] - A[0, 1] * A[2, 2]) * inv
    out[1, 1] = (A[0, 0] * A[2, 2] - A[0, 2] * A[2, 0]) * inv
    out[2, 1] = (A[0, 1] * A[2, 0] - A[0, 0] * A[2, 1]) * inv
    out[0, 2] = (A[0, 1] * A[1, 2] - A[0, 2] * A[1, 1]) * inv
    out[1, 2] = (A[0, 2] * A[1, 0] - A[0, 0] * A[1, 2]) * inv
    out[2, 2] = (A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]) * inv
    return True


@jit
def two_view_kernel(
    R: np.ndarray,
    t: np.ndarray,
    P: np.ndarray,
    z: np.ndarray,
    zp: np.ndarray,
    idx: np.ndarray,
    f: float,
    px: float,
    py: float,
    hb: float,
    iterations: int,
) -> tuple:  # pragma: no cover - compiled
    """The two-view adjustment of pnp.two_view: Gauss–Newton over the motion (right perturbation
    δp, δθ) and the position X_i of every point ``idx`` in the previous frame, on the residuals
    zp_i − π(X_i) and z_i − π(Rᵀ(X_i − t)); the points are eliminated per point (Schur complement
    of their 3×3 blocks), so a pass is linear in the points. X_i starts at P_i. Returns R, t and
    the final pass's reduced information S (6, 6) over (δp, δθ).
    Every product is written out over preallocated scratch: no allocation per point."""
    R = R.copy()
    t = t.copy()
    n = idx.shape[0]
    X = np.empty((n, 3))
    for k in range(n):
        X[k] = P[idx[k]]
    Jx = np.empty((3, 3))
    Jy = np.empty((3, 3))
    W = np.empty((3, 3))
    J2X = np.empty((3, 3))
    J2e = np.empty((3, 6))
    HXX = np.empty((3, 3))
    A = np.empty((6, 3))
    r1 = np.empty(3)
    r2 = np.empty(3)
    HXXi = np.empty((n, 3, 3))
    HeX = np.empty((n, 6, 3))
    gX = np.empty((n, 3))
    S = np.zeros((6, 6))
    b = np.zeros(6)
    Sr = np.empty((6, 6))
    for it in range(iterations + 1):
        S[:] = 0.0
        b[:] = 0.0
        ok = True
        for k in range(n):
            i = idx[k]
            d0, d1, d2 = X[k, 0] - t[0], X[k, 1] - t[1], X[k, 2] - t[2]
            y0 = R[0, 0] * d0 + R[1, 0] * d1 + R[2, 0] * d2
            y1 = R[0, 1] * d0 + R[1, 1] * d1 + R[2, 1] * d2
            y2 = R[0, 2] * d0 + R[1, 2] * d1 + R[2, 2] * d2
            if not (X[k, 0] > 1e-6 and y0 > 1e-6):
                ok = False
                break
            a0, a1, a2 = _project(X[k, 0], X[k, 1], X[k, 2], f, px, py, hb)
            c0, c1, c2 = _project(y0, y1, y2, f, px, py, hb)
            r1[0], r1[1], r1[2] = zp[i, 0] - a0, zp[i, 1] - a1, zp[i, 2] - a2
            r2[0], r2[1], r2[2] = z[i, 0] - c0, z[i, 1] - c1, z[i, 2] - c2
            _jac_into(Jx, X[k, 0], X[k, 1], X[k, 2], f, hb)
            _jac_into(Jy, y0, y1, y2, f, hb)
            # ∂y/∂X = Rᵀ, ∂y/∂δp = −I, ∂y/∂δθ = [y]×
            _times_skew_into(W, Jy, y0, y1, y2)
            for r in range(3):
                for c in range(3):
                    J2X[r, c] = Jy[r, 0] * R[c, 0] + Jy[r, 1] * R[c, 1] + Jy[r, 2] * R[c, 2]
                    J2e[r, c] = -Jy[r, c]
                    J2e[r, 3 + c] = W[r, c]
            for r in range(3):
                for c in range(3):
                    HXX[r, c] = (
                        Jx[0, r] * Jx[0, c]
                        + Jx[1, r] * Jx[1, c]
                        + Jx[2, r] * Jx[2, c]
                        + J2X[0, r] * J2X[0, c]
                        + J2X[1, r] * J2X[1, c]
                        + J2X[2, r] * J2X[2, c]
                    )
                gX[k, r] = (
                    Jx[0, r] * r1[0]
                    + Jx[1, r] * r1[1]
                    + Jx[2, r] * r1[2]
                    + J2X[0, r] * r2[0]
                    + J2X[1, r] * r2[1]
                    + J2X[2, r] * r2[2]
                )
            if not _inv33_into(HXXi[k], HXX):
                ok = False
                break
            for r in range(6):
                for c in range(3):
                    HeX[k, r, c] = J2e[0, r] * J2X[0, c] + J2e[1, r] * J2X[1, c] + J2e[2, r] * J2X[2, c]
            for r in range(6):
                for c in range(3):
                    A[r, c] = HeX[k, r, 0] * HXXi[k, 0, c] + HeX[k, r, 1] * HXXi[k, 1, c] + HeX[k, r, 2] * HXXi[k, 2, c]
            for r in range(6):
                for c in range(6):
                    S[r, c] += (
                        J2e[0, r] * J2e[0, c]
                        + J2e[1, r] * J2e[1, c]
                        + J2e[2, r] * J2e[2, c]
                        - A[r, 0] * HeX[k, c, 0]
                        - A[r, 1] * HeX[k, c, 1]
                        - A[r, 2] * HeX[k, c, 2]
                    )
                b[r] += (
                    J2e[0, r] * r2[0]
                    + J2e[1, r] * r2[1]
                    + J2e[2, r] * r2[2]
                    - A[r, 0] * gX[k, 0]
                    - A[r, 1] * gX[k, 1]
                    - A[r, 2] * gX[k, 2]
                )
        if not ok or it == iterations:
            break
        for r in range(6):
            for c in range(6):
                Sr[r, c] = S[r, c] + (1e-9 if r == c else 0.0)
        # a non-finite pixel makes b non-finite (S does not see residuals): no step, motion unchanged
        if not (np.all(np.isfinite(Sr)) and np.all(np.isfinite(b))) or abs(np.linalg.det(Sr)) < 1e-300:
            break
        d = np.linalg.solve(Sr, b)
        for k in range(n):
            for r in range(3):
                u = gX[k, r] - (HeX[k, 0, r] * d[0] + HeX[k, 1, r] * d[1] + HeX[k, 2, r] * d[2])
                u -= HeX[k, 3, r] * d[3] + HeX[k, 4, r] * d[4] + HeX[k, 5, r] * d[5]
                A[0, r] = u  # scratch: the point's reduced gradient
            for r in range(3):
                X[k, r] += HXXi[k, r, 0] * A[0, 0] + HXXi[k, r, 1] * A[0, 1] + HXXi[k, r, 2] * A[0, 2]
        t = t + R @ d[:3]
        R = R @ _so3_exp(d[3:])
        if math.sqrt(d[0] ** 2 + d[1] ** 2 + d[2] ** 2 + d[3] ** 2 + d[4] ** 2 + d[5] ** 2) < 1e-9:
            break
    return R, t, S
