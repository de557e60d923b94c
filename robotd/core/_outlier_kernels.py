"""numba kernels of the outlier stage (docs/math.md §5.2–§5.3); numpy twins: tests/support/reference_outliers.py.

- :func:`similarity_d2_kernel`: the Mahalanobis consensus of a batch of hypotheses × all pairs.
  numpy builds (K, N, 3, 3) covariance stacks and several (K, N, 3) temporaries for it; here
  each (hypothesis, pair) is one pass over registers.
- :func:`gn_weights`, :func:`gn_fit`: the Mahalanobis-weighted similarity re-fit (LO-RANSAC and
  the final re-fit): the weights by closed-form inverses and the whole Gauss–Newton loop in one
  call, 0.03 / 0.11 ms at 30 / 200 pairs against 0.13 / 0.30 ms in numpy, most of which was
  per-iteration call overhead.

``similarity_d2_kernel`` and ``gn_weights`` both build C = B + s²RARᵀ and its symmetric
adjugate inline. Shared helpers were tried: as plain or ``inline="always"`` numba functions (the
adjugate returned as a tuple) they made the consensus kernel 20–30 % slower (0.50 → 0.58–0.67 ms
for 24 hypotheses × 400 pairs), so the few lines stay written out twice.

Same formulas as the references, so the results agree to rounding
(``tests/robotd/core/test_outliers.py``). At the daemon's sizes the outlier stage went from 2.6 to
≈ 1.2 ms per ORB frame. Compiled by :func:`robotd.core.jit.jit` (disk cache, GIL released).
"""

from __future__ import annotations

import numpy as np

from robotd.core.jit import jit


@jit
def similarity_d2_kernel(
    s: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    a: np.ndarray,
    b: np.ndarray,
    A: np.ndarray,
    B: np.ndarray,
    has_a: bool,
    has_b: bool,
    out: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """out[k, i] = eᵀ C⁻¹ e, e = b_i − (s_k R_k a_i + t_k), C = [B_i] + [s_k² R_k A_i R_kᵀ]; d = 2 or 3.

    ``A``/``B`` are read only where ``has_a``/``has_b``. A C with det ≤ 0 gives +inf.
    """
    n_k = s.shape[0]
    n = a.shape[0]
    d = a.shape[1]
    e = np.empty(3)
    C = np.zeros((3, 3))
    M = np.empty((3, 3))
    for k in range(n_k):
        sk = s[k]
        s2 = sk * sk
        for i in range(n):
            for r in range(d):
                acc = 0.0
                for c in range(d):
                    acc += R[k, r, c] * a[i, c]
                e[r] = b[i, r] - (sk * acc + t[k, r])
            for r in range(d):
                for c in range(d):
                    C[r, c] = B[i, r, c] if has_b else 0.0
            if has_a:
                # M = R A, then C += s² M Rᵀ
                for r in range(d):
                    for c in range(d):
                        acc = 0.0
                        for q in range(d):
                            acc += R[k, r, q] * A[i, q, c]
                        M[r, c] = acc
                for r in range(d):
                    for c in range(d):
                        acc = 0.0
                        for q in range(d):
                            acc += M[r, q] * R[k, c, q]
                        C[r, c] += s2 * acc
            if d == 3:
                c00, c01, c02 = C[0, 0], C[0, 1], C[0, 2]
                c11, c12, c22 = C[1, 1], C[1, 2], C[2, 2]
                a00 = c11 * c22 - c12 * c12
                a01 = c02 * c12 - c01 * c22
                a02 = c01 * c12 - c02 * c11
                a11 = c00 * c22 - c02 * c02
                a12 = c01 * c02 - c00 * c12
                a22 = c00 * c11 - c01 * c01
                det = c00 * a00 + c01 * a01 + c02 * a02
                x, y, z = e[0], e[1], e[2]
                q = a00 * x * x + a11 * y * y + a22 * z * z + 2.0 * (a01 * x * y + a02 * x * z + a12 * y * z)
            else:
                c00, c01, c11 = C[0, 0], C[0, 1], C[1, 1]
                det = c00 * c11 - c01 * c01
                x, y = e[0], e[1]
                q = c11 * x * x - 2.0 * c01 * x * y + c00 * y * y
            out[k, i] = q / det if det > 0 else np.inf


@jit
def gn_normal_equations(
    a: np.ndarray,
    b: np.ndarray,
    W: np.ndarray,
    s: float,
    R: np.ndarray,
    t: np.ndarray,
    with_scale: bool,
    H: np.ndarray,
    g: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """H = Σ Jᵢᵀ Wᵢ Jᵢ and g = Σ Jᵢᵀ Wᵢ eᵢ of the weighted similarity fit (``outliers.fit_similarity_mahalanobis``).

    eᵢ = bᵢ − (s R aᵢ + t); parameters (δt, δθ[, δσ]) with ∂e/∂δt = −I, ∂e/∂δθ = [v]× (3-D) or
    (v_y, −v_x) (2-D) for v = s R aᵢ, ∂e/∂δσ = −v. ``H`` (npar, npar) and ``g`` (npar,) are
    overwritten; npar = d + (3 or 1) + with_scale.
    """
    n, d = a.shape
    npar = H.shape[0]
    H[:, :] = 0.0
    g[:] = 0.0
    J = np.zeros((3, 7))
    WJ = np.empty((3, 7))
    We = np.empty(3)
    v = np.empty(3)
    e = np.empty(3)
    for r in range(d):
        J[r, r] = -1.0
    for i in range(n):
        for r in range(d):
            acc = 0.0
            for c in range(d):
                acc += R[r, c] * a[i, c]
            v[r] = s * acc
            e[r] = b[i, r] - (v[r] + t[r])
        if d == 3:
            x, y, z = v[0], v[1], v[2]
            J[0, 3], J[0, 4], J[0, 5] = 0.0, -z, y
            J[1, 3], J[1, 4], J[1, 5] = z, 0.0, -x
            J[2, 3], J[2, 4], J[2, 5] = -y, x, 0.0
        else:
            J[0, 2], J[1, 2] = v[1], -v[0]
        if with_scale:
            for r in range(d):
                J[r, npar - 1] = -v[r]
        # WJ = Wᵢ J and We = Wᵢ e; H += Jᵀ WJ, g += Jᵀ We
        for r in range(d):
            for p in range(npar):
                acc = 0.0
                for q in range(d):
                    acc += W[i, r, q] * J[q, p]
                WJ[r, p] = acc
            acc = 0.0
            for q in range(d):
                acc += W[i, r, q] * e[q]
            We[r] = acc
        for p in range(npar):
            for p2 in range(npar):
                acc = 0.0
                for r in range(d):
                    acc += J[r, p] * WJ[r, p2]
                H[p, p2] += acc
            acc = 0.0
            for r in range(d):
                acc += J[r, p] * We[r]
            g[p] += acc


@jit
def gn_weights(
    A: np.ndarray, B: np.ndarray, s0: float, R0: np.ndarray, has_a: bool, has_b: bool, W: np.ndarray
) -> None:  # pragma: no cover - compiled
    """W_i = C_i⁻¹, C_i = [B_i] + [s0² R0 A_i R0ᵀ] (d = 2 or 3), by the closed-form inverse of a
    symmetric matrix; a C_i with det ≤ 0 (not positive definite) gets W_i = 0, so the pair is left
    out of the fit."""
    n, d = W.shape[0], W.shape[1]
    C = np.zeros((3, 3))
    M = np.empty((3, 3))
    s2 = s0 * s0
    for i in range(n):
        for r in range(d):
            for c in range(d):
                C[r, c] = B[i, r, c] if has_b else 0.0
        if has_a:
            for r in range(d):
                for c in range(d):
                    acc = 0.0
                    for q in range(d):
                        acc += R0[r, q] * A[i, q, c]
                    M[r, c] = acc
            for r in range(d):
                for c in range(d):
                    acc = 0.0
                    for q in range(d):
                        acc += M[r, q] * R0[c, q]
                    C[r, c] += s2 * acc
        if d == 3:
            # symmetrised: the adjugate formula below assumes C = Cᵀ
            c00, c11, c22 = C[0, 0], C[1, 1], C[2, 2]
            c01 = 0.5 * (C[0, 1] + C[1, 0])
            c02 = 0.5 * (C[0, 2] + C[2, 0])
            c12 = 0.5 * (C[1, 2] + C[2, 1])
            a00 = c11 * c22 - c12 * c12
            a01 = c02 * c12 - c01 * c22
            a02 = c01 * c12 - c02 * c11
            a11 = c00 * c22 - c02 * c02
            a12 = c01 * c02 - c00 * c12
            a22 = c00 * c11 - c01 * c01
            det = c00 * a00 + c01 * a01 + c02 * a02
            if det > 0:
                inv = 1.0 / det
                W[i, 0, 0], W[i, 1, 1], W[i, 2, 2] = a00 * inv, a11 * inv, a22 * inv
                W[i, 0, 1] = W[i, 1, 0] = a01 * inv
                W[i, 0, 2] = W[i, 2, 0] = a02 * inv
                W[i, 1, 2] = W[i, 2, 1] = a12 * inv
            else:
                W[i, :, :] = 0.0
        else:
            c00, c11 = C[0, 0], C[1, 1]
            c01 = 0.5 * (C[0, 1] + C[1, 0])
            det = c00 * c11 - c01 * c01
            if det > 0:
                inv = 1.0 / det
                W[i, 0, 0], W[i, 1, 1] = c11 * inv, c00 * inv
                W[i, 0, 1] = W[i, 1, 0] = -c01 * inv
            else:
                W[i, :, :] = 0.0


@jit
def _solve_small(H: np.ndarray, g: np.ndarray, x: np.ndarray) -> bool:  # pragma: no cover - compiled
    """x = H⁻¹ g by Gaussian elimination with partial pivoting (H is at most 7 × 7); False when a
    pivot is exactly zero (singular H, where numpy's solve raises)."""
    n = H.shape[0]
    M = H.copy()
    y = g.copy()
    for c in range(n):
        p = c
        for r in range(c + 1, n):
            if abs(M[r, c]) > abs(M[p, c]):
                p = r
        if M[p, c] == 0.0:
            return False
        if p != c:
            for q in range(n):
                M[c, q], M[p, q] = M[p, q], M[c, q]
            y[c], y[p] = y[p], y[c]
        for r in range(c + 1, n):
            f = M[r, c] / M[c, c]
            for q in range(c, n):
                M[r, q] -= f * M[c, q]
            y[r] -= f * y[c]
    for c in range(n - 1, -1, -1):
        acc = y[c]
        for q in range(c + 1, n):
            acc -= M[c, q] * x[q]
        x[c] = acc / M[c, c]
    return True


@jit
def gn_fit(
    a: np.ndarray,
    b: np.ndarray,
    W: np.ndarray,
    s: float,
    R: np.ndarray,
    t: np.ndarray,
    with_scale: bool,
    iterations: int,
    tol: float,
    H: np.ndarray,
) -> tuple[float, np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """Gauss–Newton iterations of ``outliers.fit_similarity_mahalanobis`` from (s, R, t).

    Each step solves H δ = −g (:func:`gn_normal_equations`), then t += δt, R ← exp(δθ) R,
    s ← s·e^{δσ}; stops after ``iterations`` steps, when |δ| < ``tol``, or at a singular H.
    Returns (s, R, t); ``H`` holds the information of the last linearisation.
    """
    d = a.shape[1]
    k_rot = 3 if d == 3 else 1
    npar = H.shape[0]
    g = np.empty(npar)
    delta = np.empty(npar)
    R = R.copy()
    t = t.copy()
    Rn = np.empty_like(R)
    E = np.eye(d)
    for _ in range(max(1, iterations)):
        gn_normal_equations(a, b, W, s, R, t, with_scale, H, g)
        if not _solve_small(H, g, delta):
            break
        norm2 = 0.0
        for p in range(npar):
            delta[p] = -delta[p]
            norm2 += delta[p] * delta[p]
        for r in range(d):
            t[r] += delta[r]
        # exp(δθ): Rodrigues in 3-D, a planar rotation in 2-D
        if d == 3:
            wx, wy, wz = delta[3], delta[4], delta[5]
            th = np.sqrt(wx * wx + wy * wy + wz * wz)
            if th < 1e-12:
                E[:, :] = np.eye(3)
            else:
                kx, ky, kz = wx / th, wy / th, wz / th
                sn, cs = np.sin(th), 1.0 - np.cos(th)
                E[0, 0] = 1.0 + cs * (-ky * ky - kz * kz)
                E[0, 1] = -sn * kz + cs * kx * ky
                E[0, 2] = sn * ky + cs * kx * kz
                E[1, 0] = sn * kz + cs * kx * ky
                E[1, 1] = 1.0 + cs * (-kx * kx - kz * kz)
                E[1, 2] = -sn * kx + cs * ky * kz
                E[2, 0] = -sn * ky + cs * kx * kz
                E[2, 1] = sn * kx + cs * ky * kz
                E[2, 2] = 1.0 + cs * (-kx * kx - ky * ky)
        else:
            c, sn = np.cos(delta[2]), np.sin(delta[2])
            E[0, 0], E[0, 1], E[1, 0], E[1, 1] = c, -sn, sn, c
        for r in range(d):
            for c2 in range(d):
                acc = 0.0
                for q in range(d):
                    acc += E[r, q] * R[q, c2]
                Rn[r, c2] = acc
        R[:, :] = Rn
        if with_scale:
            s = s * np.exp(delta[d + k_rot])
        if np.sqrt(norm2) < tol:
            break
    return s, R, t
