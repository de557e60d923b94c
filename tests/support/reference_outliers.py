"""Readable numpy twins of the outlier stage's numba kernels (robotd/core/_outlier_kernels.py).

- :func:`similarity_d2_numpy`: the Mahalanobis consensus of ``robotd.core.outliers.similarity_d2``.
- :func:`fit_similarity_mahalanobis_numpy`: the weighted re-fit ``robotd.core.outliers.fit_similarity_mahalanobis``.

Moved here unchanged from robotd/core/outliers.py (with :func:`_exp_rot`, which only the twin used). The
pieces the runtime shares with the twin are imported from robotd.core.outliers, not copied, so both
compute the residuals, the Gauss–Newton stopping tolerance and the fit's covariance alike.
"""

from __future__ import annotations

import math

import numpy as np

from robotd.core.outliers import GN_STEP_TOL, _fit_covariance, mahalanobis_sq, similarity_residuals


def similarity_d2_numpy(
    s: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    a: np.ndarray,
    b: np.ndarray,
    A: np.ndarray | None,
    B: np.ndarray | None,
    euclidean: bool = False,
) -> np.ndarray:
    """Readable twin of :func:`robotd.core.outliers.similarity_d2` and its Mahalanobis kernel
    ``_outlier_kernels.similarity_d2_kernel``: the same formulas on stacked (K, N, d, d) covariances
    and :func:`robotd.core.outliers.mahalanobis_sq`.

    Agreement: rtol 1e-10 for d = 2, 3 with A and B, A only, B only
    (tests/robotd/core/test_outliers.py::test_d2_kernel_matches_numpy_reference).
    """
    e = similarity_residuals(s, R, t, a, b)
    if euclidean:
        return np.einsum("kni,kni->kn", e, e)
    dim = a.shape[1]
    if A is not None:
        # s² R A_i Rᵀ for every (hypothesis, pair): stacked matmuls, (K, N, d, d)
        C = (R[:, None] @ A[None]) @ np.swapaxes(R, 1, 2)[:, None]
        C *= (s * s)[:, None, None, None]
        if B is not None:
            C += B[None]
    elif B is not None:
        C = np.broadcast_to(B[None], (s.shape[0], *B.shape))
    else:
        C = np.zeros((s.shape[0], a.shape[0], dim, dim))
    return mahalanobis_sq(e, C)


def _exp_rot(w: np.ndarray) -> np.ndarray:
    """Rotation from a 3-vector (3-D) or a 1-vector angle (2-D)."""
    if w.size == 1:
        c, s = math.cos(float(w[0])), math.sin(float(w[0]))
        return np.array([[c, -s], [s, c]])
    th = float(np.linalg.norm(w))
    if th < 1e-12:
        return np.eye(3)
    k = w / th
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(th) * K + (1.0 - math.cos(th)) * (K @ K)


def fit_similarity_mahalanobis_numpy(
    a: np.ndarray,
    b: np.ndarray,
    A: np.ndarray | None,
    B: np.ndarray | None,
    s0: float,
    R0: np.ndarray,
    t0: np.ndarray,
    with_scale: bool = True,
    iterations: int = 5,
) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """Readable twin of :func:`robotd.core.outliers.fit_similarity_mahalanobis` and its kernels
    ``_outlier_kernels.gn_weights`` and ``gn_fit``: the weights by ``np.linalg.inv`` and the
    Gauss–Newton loop on stacked Jacobians, with the same start, perturbations, stopping rule
    (``GN_STEP_TOL``) and covariance (``robotd.core.outliers._fit_covariance``, shared).

    Agreement: s, R, t and cov to rtol 1e-9, atol 1e-12, in 2-D and 3-D, with and without scale
    (tests/robotd/core/test_outliers.py::test_weighted_fit_kernel_matches_numpy_reference).
    """
    n, d = a.shape
    C = np.zeros((n, d, d))
    if A is not None:
        C += s0 * s0 * (R0 @ A @ R0.T)
    if B is not None:
        C += B
    W = np.linalg.inv(C) if (A is not None or B is not None) else np.broadcast_to(np.eye(d), (n, d, d))
    s, R, t = float(s0), R0.copy(), t0.copy()
    k_rot = 3 if d == 3 else 1
    npar = d + k_rot + (1 if with_scale else 0)
    H = np.eye(npar)
    # J (N, d, npar) is rebuilt in place; its ∂e/∂δt = −I block never changes
    J = np.zeros((n, d, npar))
    J[:, np.arange(d), np.arange(d)] = -1.0
    for _ in range(max(1, iterations)):
        sRa = s * (a @ R.T)
        e = b - (sRa + t)
        # e decreases by the model's increment: ∂e/∂δt = −I, ∂e/∂δθ = −∂(exp(δθ) sRa)/∂δθ, ∂e/∂δσ = −sRa
        # ∂e/∂δθ = −∂(exp(δθ) v)/∂δθ = [v]× for v = sRa in 3-D, (v_y, −v_x) in 2-D, written in place
        if d == 3:
            x, y, z = sRa[:, 0], sRa[:, 1], sRa[:, 2]
            J[:, 0, 4], J[:, 0, 5] = -z, y
            J[:, 1, 3], J[:, 1, 5] = z, -x
            J[:, 2, 3], J[:, 2, 4] = -y, x
        else:
            J[:, 0, 2], J[:, 1, 2] = sRa[:, 1], -sRa[:, 0]
        if with_scale:
            J[:, :, -1] = -sRa
        # H = Σ Jᵢᵀ Wᵢ Jᵢ and g = Σ Jᵢᵀ Wᵢ eᵢ as two flat products over the stacked (N·d) rows
        JW = np.matmul(J.transpose(0, 2, 1), W).transpose(1, 0, 2).reshape(npar, n * d)
        H = JW @ J.reshape(n * d, npar)
        g = JW @ e.reshape(n * d)
        try:
            delta = -np.linalg.solve(H, g)
        except np.linalg.LinAlgError:
            break
        t = t + delta[:d]
        R = _exp_rot(delta[d : d + k_rot]) @ R
        if with_scale:
            s = s * math.exp(float(delta[-1]))
        if float(np.linalg.norm(delta)) < GN_STEP_TOL:
            break
    return s, R, t, _fit_covariance(H)
