"""Small batched linear algebra for the filters' hot paths.

The innovation covariances of FastSLAM are stacks of 2×2 or 3×3 SPD matrices; closed-form
adjugate inverses are several times faster than ``np.linalg.inv``/``solve`` on such stacks and
exact enough for well-conditioned covariances (stereo covariances have condition numbers of at
most ~1e6). Larger matrices (the 6×6 proposal) go through ``np.linalg``.
"""

from __future__ import annotations

import numpy as np

LOG_2PI = float(np.log(2.0 * np.pi))


def sym(A: np.ndarray) -> np.ndarray:
    """(A + A^T)/2 over the last two axes."""
    return 0.5 * (A + np.swapaxes(A, -1, -2))


def inv_det_small(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closed-form inverse and determinant of a stack of 1×1, 2×2 or 3×3 matrices.

    Args:
        A: (..., n, n) with n in {1, 2, 3}.

    Returns:
        (inverse (..., n, n), determinant (...)). Other n fall back to ``np.linalg``.
    """
    n = A.shape[-1]
    if n == 1:
        d = A[..., 0, 0]
        return (1.0 / d)[..., None, None], d
    if n == 2:
        a, b, c, e = A[..., 0, 0], A[..., 0, 1], A[..., 1, 0], A[..., 1, 1]
        d = a * e - b * c
        inv = np.stack([np.stack([e, -b], -1), np.stack([-c, a], -1)], -2) / d[..., None, None]
        return inv, d
    if n == 3:
        a = A
        c00 = a[..., 1, 1] * a[..., 2, 2] - a[..., 1, 2] * a[..., 2, 1]
        c01 = a[..., 1, 2] * a[..., 2, 0] - a[..., 1, 0] * a[..., 2, 2]
        c02 = a[..., 1, 0] * a[..., 2, 1] - a[..., 1, 1] * a[..., 2, 0]
        c10 = a[..., 0, 2] * a[..., 2, 1] - a[..., 0, 1] * a[..., 2, 2]
        c11 = a[..., 0, 0] * a[..., 2, 2] - a[..., 0, 2] * a[..., 2, 0]
        c12 = a[..., 0, 1] * a[..., 2, 0] - a[..., 0, 0] * a[..., 2, 1]
        c20 = a[..., 0, 1] * a[..., 1, 2] - a[..., 0, 2] * a[..., 1, 1]
        c21 = a[..., 0, 2] * a[..., 1, 0] - a[..., 0, 0] * a[..., 1, 2]
        c22 = a[..., 0, 0] * a[..., 1, 1] - a[..., 0, 1] * a[..., 1, 0]
        d = a[..., 0, 0] * c00 + a[..., 0, 1] * c01 + a[..., 0, 2] * c02
        # adjugate = transpose of the cofactor matrix
        adj = np.stack(
            [np.stack([c00, c10, c20], -1), np.stack([c01, c11, c21], -1), np.stack([c02, c12, c22], -1)], -2
        )
        return adj / d[..., None, None], d
    return np.linalg.inv(A), np.linalg.det(A)


def gauss_logpdf(nu: np.ndarray, S_inv: np.ndarray, S_det: np.ndarray) -> np.ndarray:
    """log N(nu; 0, S) for stacks: nu (..., n), S^{-1} (..., n, n), det S (...) -> (...)."""
    n = nu.shape[-1]
    maha = np.einsum("...i,...ij,...j->...", nu, S_inv, nu)
    return -0.5 * (maha + np.log(S_det) + n * LOG_2PI)


def logsumexp(a: np.ndarray) -> float:
    """log Σ exp(a) of a 1-D array, stable for very negative entries."""
    m = float(np.max(a))
    if not np.isfinite(m):
        return m
    return m + float(np.log(np.sum(np.exp(a - m))))
