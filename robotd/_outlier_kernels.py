"""numba kernel of the RANSAC consensus (algorithms.md §5.2); the numpy reference is ``outliers.similarity_d2_numpy``.

Scoring a batch of hypotheses against every pair is the outlier stage's inner loop. In numpy it
builds (K, N, 3, 3) covariance stacks and several (K, N, 3) temporaries; here each (hypothesis,
pair) is one pass over registers: ≈ 5× faster at the daemon's sizes (a batch of 16-32 hypotheses,
100-600 pairs). Same formulas, same closed-form inverse, so the results agree to rounding
(``tests/test_outliers_ransac.py``). Disk caching as in ``frontend/_surf_kernels``.
"""

from __future__ import annotations

import numpy as np

from robotd.frontend._surf_kernels import _jit


@_jit
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
