"""FastSLAM's fusion of a measured direction of gravity (3D; docs/slam.md "Gravity"), on the
particle arrays: :func:`gravity_update` (what :meth:`robotd.slam.fastslam.FastSlam.update_gravity`
does) and :func:`gravity_terms`."""

from __future__ import annotations

import math

import numpy as np

from robotd.slam._linalg import gauss_logpdf, inv_det_small, sym
from robotd.slam.models import gravity3d_tilt, wrap_pose
from robotd.slam.resampling import normalize_log_weights


def gravity_update(
    pose: np.ndarray,
    S: np.ndarray | None,
    log_w: np.ndarray,
    rng: np.random.Generator,
    g_R: np.ndarray,
    g_W: np.ndarray,
    sigma_rad: float,
    gate_chi2: float | None,
    reopen: bool,
) -> tuple[bool, float, np.ndarray, np.ndarray | None, np.ndarray]:
    """Fuse ``g_R = R(η)^T g_W + n``, n ~ N(0, σ² I), into particles ``pose`` (P, 6) with FastSLAM
    2.0's pending prior covariances ``S`` (P, 6, 6) (None: the poses are drawn) and ``log_w`` (P,).

    With ``S``: each particle's prior takes the linear-Gaussian update and its weight the marginal
    likelihood N(g_R; h(x̂), H S H^T + σ² I); without: the weight takes N(g_R; h(x), σ² I). Gate:
    the mixture's NIS (:func:`gravity_terms`) against ``gate_chi2`` (None: no gate); a gated
    measurement changes nothing. ``reopen``: the prior roll and pitch variances grow by the squared
    innovation angle (drawn poses: the particles spread by it; ``pose`` is changed in place), and the
    measurement is fused without the gate.

    Returns:
        (fused, the NIS before any reopening, pose, S, log_w); the inputs themselves when not fused.
    """
    w = normalize_log_weights(log_w)[1]
    y, PHt, Psi, nis = gravity_terms(pose, S, w, g_R, g_W, sigma_rad)
    gated = not np.isfinite(nis) or (gate_chi2 is not None and nis > gate_chi2)
    if gated and not reopen:
        return False, nis, pose, S, log_w
    if reopen:
        a2 = float(np.sum((w @ y) ** 2))  # ≈ the tilt error², rad²
        if S is not None:
            S = S.copy()
            S[:, 3, 3] += a2
            S[:, 4, 4] += a2
        else:
            pose[:, 3:5] += math.sqrt(a2) * rng.standard_normal((pose.shape[0], 2))
        y, PHt, Psi, _ = gravity_terms(pose, S, w, g_R, g_W, sigma_rad)
    Psi_inv, Psi_det = inv_det_small(Psi)
    if PHt is not None and S is not None:
        K = PHt @ Psi_inv  # (P, 6, 3)
        pose = wrap_pose(pose + np.einsum("pij,pj->pi", K, y), 3)
        S = sym(S - K @ np.swapaxes(PHt, 1, 2))
    log_w = normalize_log_weights(log_w + gauss_logpdf(y, Psi_inv, Psi_det))[0]
    return True, nis, pose, S, log_w


def gravity_terms(
    pose: np.ndarray, S: np.ndarray | None, w: np.ndarray, g_R: np.ndarray, g_W: np.ndarray, sigma_rad: float
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray, float]:
    """Innovations y (P, 3), S H^T (P, 6, 3) or None (no ``S``), their covariances (P, 3, 3) and the
    NIS of the particle mixture with weights ``w``: its mean innovation against the particles'
    spread plus their innovation covariances (the innovation has two degrees of freedom: its
    component along h is of second order)."""
    yaw = float(np.arctan2(w @ np.sin(pose[:, 5]), w @ np.cos(pose[:, 5])))
    h, H = gravity3d_tilt(pose, g_W, yaw)
    y = g_R[None, :] - h
    Rm = sigma_rad**2 * np.eye(3)
    PHt = None
    if S is not None:
        PHt = S @ np.swapaxes(H, 1, 2)
        Psi = sym(H @ PHt + Rm)
    else:
        Psi = np.broadcast_to(Rm, (pose.shape[0], 3, 3))
    y_bar = w @ y
    dy = y - y_bar
    C = np.einsum("p,pi,pj->ij", w, dy, dy) + np.einsum("p,pij->ij", w, Psi)
    try:
        nis = float(y_bar @ np.linalg.solve(C, y_bar))
    except np.linalg.LinAlgError:
        nis = float("nan")
    return y, PHt, Psi, nis
