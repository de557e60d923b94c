"""Plain per-particle FastSLAM (docs/math.md §9, §10): the readable reference twin of the numba kernel.

One particle and one observation at a time, general ``np.linalg`` solves, no closed-form inverses,
the robot-frame formulas of §9/§10 through the measurement model's own ``h``, ``inverse`` and
``innovation``. ``fastslam_step_reference`` has the signature and the effects of the kernel
:func:`robotd.slam._kernels.fastslam_step`, and ``fastslam_step_store_reference`` those of
:func:`robotd.slam._kernels.fastslam_step_store` (the filter's call: a FastSlam whose ``_step`` is
this one runs the whole filter on the reference). robotd has no other implementation of the step
(the vectorised numpy one it had was removed with issue 28); this one is far too slow for the
daemon (~0.7 s per 2D step at 100 particles × 100 observations), so it lives with the tests.

Agreement: given the same random draws ``eps``, poses, log-weight increments, landmark means and
covariances (and the 2.0 proposal outputs) agree to 1e-9 absolute (``KERNEL_TWIN_ATOL`` in
tests/support/tolerances.py, used by tests/robotd/slam/test_fastslam.py and test_fastslam_numba.py),
in 2D and 3D, FastSLAM 1.0 and 2.0, every measurement model, also at large roll/pitch and any yaw.
"""

from __future__ import annotations

import numpy as np

from robotd.slam._store import LandmarkStore
from robotd.slam.models import MeasurementModel, wrap_pose


def _logpdf(nu: np.ndarray, S: np.ndarray) -> float:
    _, logdet = np.linalg.slogdet(S)
    return float(-0.5 * (nu @ np.linalg.solve(S, nu) + logdet + nu.size * np.log(2.0 * np.pi)))


def _h(model: MeasurementModel, x: np.ndarray, m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    z, Hx, Hm = model.h(x[None], m[None])
    return z[0], Hx[0], Hm[0]


def fastslam_step_reference(
    version: int,
    pose: np.ndarray,
    S: np.ndarray | None,
    lm_mean: np.ndarray,
    lm_cov: np.ndarray,
    slots_old: np.ndarray,
    z_old: np.ndarray,
    Q_old: np.ndarray,
    slots_new: np.ndarray,
    z_new: np.ndarray,
    Q_new: np.ndarray,
    eps: np.ndarray | None,
    model: MeasurementModel,
    floor: float,
    seq_weights: bool = False,
    out_mu: np.ndarray | None = None,
    out_Sx: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Per-particle loop version of the kernel's ``fastslam_step`` (same arguments, same in-place
    effects); the tests hold the kernel to it to 1e-9 (module docstring)."""
    dim = 2 if model.dx == 3 else 3
    P = pose.shape[0]
    out_pose = pose.copy()
    dlogw = np.zeros(P)
    for k in range(P):
        x = pose[k].copy()
        if version == 2:
            assert S is not None and eps is not None
            # importance weight at the prior x̂ and the landmarks before the update (§10)
            for j, s in enumerate(slots_old if not seq_weights else []):
                zhat, Hx, Hm = _h(model, x, lm_mean[k, s])
                nu = model.innovation(z_old[j].copy(), zhat)
                L = Hx @ S[k] @ Hx.T + Hm @ lm_cov[k, s] @ Hm.T + Q_old[j]
                dlogw[k] += _logpdf(nu, L)
            # proposal, one observation at a time (Kalman form)
            mu_x, Sx = x.copy(), S[k].copy()
            for j, s in enumerate(slots_old):
                zhat, Hx, Hm = _h(model, mu_x, lm_mean[k, s])
                nu = model.innovation(z_old[j].copy(), zhat)
                Psi = Hx @ Sx @ Hx.T + Hm @ lm_cov[k, s] @ Hm.T + Q_old[j]
                if seq_weights:  # chain rule: p(z_j | z_<j) under the proposal so far
                    dlogw[k] += _logpdf(nu, Psi)
                K = np.linalg.solve(Psi, Hx @ Sx).T  # Σ_x H_x^T Ψ^{-1} (Ψ, Σ_x symmetric)
                mu_x = wrap_pose(mu_x + K @ nu, dim)
                Sx = (np.eye(model.dx) - K @ Hx) @ Sx
                Sx = 0.5 * (Sx + Sx.T)
            if out_mu is not None and out_Sx is not None:
                out_mu[k], out_Sx[k] = mu_x, Sx
            try:
                Lc = np.linalg.cholesky(Sx)
            except np.linalg.LinAlgError:
                w, V = np.linalg.eigh(Sx)
                Lc = V * np.sqrt(np.maximum(w, 0.0))
            x = wrap_pose(mu_x + Lc @ eps[k], dim)
        # landmark EKFs at the sampled pose (§9 step 2)
        for j, s in enumerate(slots_old):
            zhat, _, Hm = _h(model, x, lm_mean[k, s])
            nu = model.innovation(z_old[j].copy(), zhat)
            C = lm_cov[k, s]
            Psi = Hm @ C @ Hm.T + Q_old[j]
            K = np.linalg.solve(Psi, Hm @ C).T
            lm_mean[k, s] = lm_mean[k, s] + K @ nu
            IKH = np.eye(model.dm) - K @ Hm
            Cn = IKH @ C @ IKH.T + K @ Q_old[j] @ K.T
            lm_cov[k, s] = 0.5 * (Cn + Cn.T)
            if version == 1:
                dlogw[k] += _logpdf(nu, Psi)
        # new landmarks (§9 step 3)
        for j, s in enumerate(slots_new):
            m, _, Jz = model.inverse(x[None], z_new[j][None])
            lm_mean[k, s] = m[0]
            C = Jz[0] @ Q_new[j] @ Jz[0].T
            lm_cov[k, s] = 0.5 * (C + C.T) + floor * np.eye(model.dm)
        out_pose[k] = x
    return out_pose, dlogw


def fastslam_step_store_reference(
    version: int,
    pose: np.ndarray,
    S: np.ndarray | None,
    store: LandmarkStore,
    slots_old: np.ndarray,
    z_old: np.ndarray,
    Q_old: np.ndarray,
    slots_new: np.ndarray,
    z_new: np.ndarray,
    Q_new: np.ndarray,
    eps: np.ndarray | None,
    model: MeasurementModel,
    floor: float,
    seq_weights: bool = False,
    out_mu: np.ndarray | None = None,
    out_Sx: np.ndarray | None = None,
    threads: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """``fastslam_step_reference`` on a copy-on-write store, as the kernel's ``fastslam_step_store``:
    dense copies of the touched landmarks, the reference step on them, written back (copy on write)."""
    n_old, n_new = slots_old.size, slots_new.size
    P, dm = pose.shape[0], store.dm
    mean = np.empty((P, n_old + n_new, dm))
    cov = np.empty((P, n_old + n_new, dm, dm))
    mean[:, :n_old], cov[:, :n_old] = store.gather(slots_old)
    out = fastslam_step_reference(
        version,
        pose,
        S,
        mean,
        cov,
        np.arange(n_old),
        z_old,
        Q_old,
        np.arange(n_old, n_old + n_new),
        z_new,
        Q_new,
        eps,
        model,
        floor,
        seq_weights,
        out_mu,
        out_Sx,
    )
    store.scatter(np.concatenate([slots_old, slots_new]), mean, cov)
    return out
