"""Particle weights, effective sample size, low-variance resampling, weighted pose statistics.

docs/math.md §10 "Resampling" and "Output"; Thrun et al. (2005) ch. 4 (low-variance sampler).
Weights are kept in the log domain and normalised with log-sum-exp.
"""

from __future__ import annotations

import numpy as np

from robotd.core.errors import EstimatorError
from robotd.core.geometry import wrap_angle
from robotd.slam._linalg import logsumexp


def normalize_log_weights(log_w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(P,) log weights -> (normalised log weights (P,), normalised weights (P,) summing to 1).

    Raises EstimatorError when every weight is zero or NaN (all particles impossible).
    """
    lse = logsumexp(log_w)
    if not np.isfinite(lse):
        raise EstimatorError(f"particle weights degenerate: log-sum-exp is {lse} over {log_w.size} particles")
    ln = log_w - lse
    return ln, np.exp(ln)


def effective_sample_size(w: np.ndarray) -> float:
    """N_eff = 1 / Σ w_k² for normalised weights w (P,)."""
    return float(1.0 / np.sum(w * w))


def low_variance_indices(w: np.ndarray, u: float, n_out: int | None = None) -> np.ndarray:
    """Low-variance (systematic) resampling (§10): ``n_out`` indices into w (P,).

    Positions ``r_k = (u + k) / n_out`` for k = 0 … n_out-1 with one uniform draw ``u ∈ [0, 1)``
    (passed in so that tests can replay it); each position picks the first particle whose
    cumulative weight exceeds it (``searchsorted``). A particle of weight w gets ⌊n_out·w⌋ or
    ⌈n_out·w⌉ copies, so the counts are unbiased and equal weights keep every particle once.
    """
    n = w.size if n_out is None else int(n_out)
    c = np.cumsum(w)
    c[-1] = 1.0  # guard the last bin against round-off so every position finds a particle
    r = (u + np.arange(n)) / n
    return np.minimum(np.searchsorted(c, r, side="right"), w.size - 1)


def weighted_pose_mean(pose: np.ndarray, w: np.ndarray, dim: int) -> tuple[np.ndarray, np.ndarray]:
    """Weighted mean and covariance of particle poses (§10 "Output").

    Args:
        pose: (P, 3|6) particle poses; angle entries are the last 1 (2D) or 3 (3D).
        w: (P,) normalised weights.

    Returns:
        mean (3|6,) with circular means ``atan2(Σ w sin, Σ w cos)`` for angles, covariance
        (3|6, 3|6) ``Σ w (x - x̄)(x - x̄)^T`` with wrapped angle differences.
    """
    a0 = 2 if dim == 2 else 3
    mean = w @ pose
    ang = pose[:, a0:]
    mean[a0:] = np.arctan2(w @ np.sin(ang), w @ np.cos(ang))
    d = pose - mean
    d[:, a0:] = wrap_angle(d[:, a0:])
    cov = (d * w[:, None]).T @ d
    return mean, 0.5 * (cov + cov.T)
