"""EKF SLAM with known correspondences (docs/math.md §8; Thrun et al. 2005 ch. 10).

State ``y = (x, m_1, …, m_M)`` of size ``dx + dm·M`` (2D: 3 + 2M, 3D: 6 + 3M) with full covariance.
Landmark ``k`` of the book occupies ``y[dx + dm·k : dx + dm·(k+1)]``; deletion compacts the state.

- Predict touches only the pose rows/columns: O(M).
- Update is sequential per identified landmark with freshly evaluated Jacobians, Cholesky solves,
  a χ² gate (counted), the Joseph form evaluated in O(n²) using the sparsity of H, and
  symmetrisation.
- New landmarks augment the state (Durrant-Whyte & Bailey 2006) with their cross-covariances.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
import scipy.linalg
import scipy.linalg.blas

from robotd.core.errors import EstimatorError, InputError
from robotd.core.geometry import euler_to_R, rot2, wrap_angle
from robotd.core.msgs import LandmarkMap, MotionIncrement, PoseEstimate, UpdateReport
from robotd.core.statecheck import POSITION_LIMIT_M, StateTable, check_covariances
from robotd.core.statecheck import check_finite as check_saved_finite
from robotd.slam._book import LandmarkBook, note_and_recognise
from robotd.slam._linalg import sym
from robotd.slam.common import (
    FILTER_CODE,
    NO_IDS,
    UpdateEntryPoints,
    check_finite,
    check_header,
    check_reset_pose,
    check_saved_poses,
    control_from_increment,
    gravity_inputs,
    lm_to_3d,
    measurement_model,
    pixel_noise,
    pose_cov_6x6,
    pose_to_xyz_rpy,
)
from robotd.slam.models import (
    CARTESIAN_2D,
    CARTESIAN_3D,
    MeasurementModel,
    gravity3d_tilt,
    motion3d,
    odometry2d,
    pose_angle_slice,
    velocity2d,
    velocity2d_noise,
)
from robotd.slam.params import SlamParams, VisibleFn

logger = logging.getLogger(__name__)


class EkfSlam(UpdateEntryPoints):
    """EKF SLAM in 2D or 3D. Build it with :func:`robotd.slam.factory.make_estimator`."""

    name = "ekf"

    def __init__(self, params: SlamParams, visible: VisibleFn) -> None:
        self.params = params
        self.dim = params.dim
        self.visible = visible
        self.dx = 3 if self.dim == 2 else 6
        self.dm = self.dim
        self.model: MeasurementModel = measurement_model(params)
        self.Q_px = pixel_noise(params) if self.model.intrinsics is not None else None
        self.mu = np.zeros(self.dx)  # (n,) state mean
        self.Sigma = np.zeros((self.dx, self.dx))  # (n, n) state covariance
        self.book = LandmarkBook()
        self.t_ns = 0
        self.gate = params.gate_chi2_2d if self.dim == 2 else params.gate_chi2_3d

    # ----------------------------------------------------------------------------------- predict

    def _apply_motion(self, x_new: np.ndarray, G: np.ndarray, S: np.ndarray) -> None:
        """Σxx ← GΣxxG^T + S, Σxm ← GΣxm (§8 predict, O(M))."""
        dx = self.dx
        self.mu[:dx] = x_new
        Sig = self.Sigma
        Sig[:dx, :dx] = sym(G @ Sig[:dx, :dx] @ G.T + S)
        if Sig.shape[0] > dx:
            Sig[:dx, dx:] = G @ Sig[:dx, dx:]
            Sig[dx:, :dx] = Sig[:dx, dx:].T

    def predict(self, inc: MotionIncrement) -> None:
        """Odometry-increment predict (§6.2 / §6.3); state untouched when the input is invalid."""
        u, M = control_from_increment(inc, self.params)
        x = self.mu[None, : self.dx]
        if self.dim == 2:
            x_new, G, V = odometry2d(x, u[None])
        else:
            x_new, G, V = motion3d(x, u[None])
        S = V[0] @ M @ V[0].T + self.params.process_cov_floor * np.eye(self.dx)
        self._apply_motion(x_new[0], G[0], S)
        self.t_ns = int(inc.t1_ns)

    def predict_velocity(self, v: float, w: float, dt: float, t_ns: int | None = None) -> None:
        """Velocity-model predict (§6.1), 2D only; S_t = V M V^T plus the final-rotation noise."""
        if self.dim != 2:
            raise InputError(f"predict_velocity: expected a 2D filter, got dim={self.dim}")
        check_finite("predict_velocity", v, w, dt)
        x_new, G, V = velocity2d(self.mu[None, :3], np.array([[v, w]], float), float(dt))
        M, var_g = velocity2d_noise(float(v), float(w), float(dt), self.params.vel2d_alpha)
        S = V[0] @ M @ V[0].T + np.diag([0.0, 0.0, var_g]) + self.params.process_cov_floor * np.eye(3)
        self._apply_motion(x_new[0], G[0], S)
        if t_ns is not None:
            self.t_ns = int(t_ns)

    def update_gravity(
        self, g_R: np.ndarray, g_W: np.ndarray, sigma_rad: float, reopen: bool = False
    ) -> tuple[bool, float]:
        """Fuse a measured direction of gravity in the robot frame (3D only; as
        :meth:`robotd.slam.fastslam.FastSlam.update_gravity`): one Kalman update of the whole state
        (the landmarks move with the pose through their correlations). ``reopen``: the roll and
        pitch variances grow by the squared innovation angle first, and the gate is skipped.
        Returns (fused, NIS before any reopening)."""
        g_R, g_W = gravity_inputs(self.dim, g_R, g_W, sigma_rad)
        dx = self.dx
        h, H = gravity3d_tilt(self.mu[None, :dx], g_W)
        nu = g_R - h[0]
        Hx = H[0]  # (3, 6)
        PHt = self.Sigma[:, :dx] @ Hx.T  # (n, 3)
        Psi = sym(Hx @ PHt[:dx] + sigma_rad**2 * np.eye(3))
        try:
            cf = scipy.linalg.cho_factor(Psi, lower=True)
        except np.linalg.LinAlgError:
            return False, float("nan")
        d2 = float(nu @ scipy.linalg.cho_solve(cf, nu))
        gated = not np.isfinite(d2) or (self.params.gate_enabled and d2 > self.params.gate_chi2_2d)
        if gated and not reopen:
            return False, d2
        if reopen:
            a2 = float(nu @ nu)
            self.Sigma[3, 3] += a2
            self.Sigma[4, 4] += a2
            PHt = self.Sigma[:, :dx] @ Hx.T
            Psi = sym(Hx @ PHt[:dx] + sigma_rad**2 * np.eye(3))
            cf = scipy.linalg.cho_factor(Psi, lower=True)
        K = scipy.linalg.cho_solve(cf, PHt.T).T
        self.mu += K @ nu
        ang = pose_angle_slice(self.dim)
        self.mu[ang] = wrap_angle(self.mu[ang])
        self._joseph(K, PHt, Psi)
        return True, d2

    # ------------------------------------------------------------------------------------ update

    def _update(
        self, z: np.ndarray, Q: np.ndarray, ids: np.ndarray, is_new: np.ndarray, model: MeasurementModel
    ) -> UpdateReport:
        dx, dm = self.dx, self.dm
        ang = pose_angle_slice(self.dim)
        n_upd = n_gated = 0
        observed_slots = []
        for i in np.flatnonzero(~is_new):
            s = self.book.id_to_slot[int(ids[i])]
            j = dx + dm * s
            idx = np.r_[0:dx, j : j + dm]
            zhat, Hx, Hm = model.h(self.mu[None, :dx], self.mu[None, j : j + dm])
            H = np.concatenate([Hx[0], Hm[0]], 1)  # (dz, dx+dm): the non-zero columns of H
            nu = model.innovation(z[i], zhat[0])
            PHt = self.Sigma[:, idx] @ H.T  # (n, dz) = Σ H^T
            Psi = sym(H @ PHt[idx] + Q[i])
            try:
                cf = scipy.linalg.cho_factor(Psi, lower=True)
            except np.linalg.LinAlgError:
                raise EstimatorError(
                    f"EKF: innovation covariance of landmark {int(ids[i])} not positive definite"
                ) from None
            d2 = float(nu @ scipy.linalg.cho_solve(cf, nu))
            observed_slots.append(s)
            if self.params.gate_enabled and d2 > self.gate:
                n_gated += 1
                logger.debug("EKF gate: landmark %d d²=%.2f > %.3f", int(ids[i]), d2, self.gate)
                continue
            K = scipy.linalg.cho_solve(cf, PHt.T).T  # (n, dz) = Σ H^T Ψ^{-1}
            self.mu += K @ nu
            self.mu[ang] = wrap_angle(self.mu[ang])
            self._joseph(K, PHt, Psi)
            n_upd += 1
        new_idx = np.flatnonzero(is_new)
        born = np.zeros(0, np.int64)
        if new_idx.size:
            born = self._augment(z[new_idx], Q[new_idx], ids[new_idx], model)
        pruned = self._prune(np.asarray(observed_slots, np.int64), born)
        return UpdateReport(n_updated=n_upd, n_new=int(new_idx.size), n_gated=n_gated, pruned_ids=pruned)

    def _joseph(self, K: np.ndarray, PHt: np.ndarray, Psi: np.ndarray) -> None:
        """Σ ← (I-KH)Σ(I-KH)^T + KQK^T (Joseph form, §8) as one in-place rank-3·dz update, then symmetrise.

        With PHt = ΣH^T and Ψ = HΣH^T + Q the Joseph form expands exactly (no optimal-gain assumption) to
        Σ - K PHt^T - PHt K^T + K Ψ K^T, so a single BLAS call updates the n×n matrix in place instead
        of four n×n temporaries. The product is accumulated into Σ^T (Fortran view of the C array).
        """
        W1 = np.ascontiguousarray(np.concatenate([-K, -PHt, K @ Psi], 1))  # (n, 3·dz)
        W2 = np.ascontiguousarray(np.concatenate([PHt, K, K], 1))
        St = self.Sigma.T  # F-contiguous view: updating it updates Σ
        # St += W2 @ W1^T  ⇔  Σ += W1 @ W2^T
        out = scipy.linalg.blas.dgemm(1.0, W2, W1, beta=1.0, c=St, trans_b=True, overwrite_c=True)
        if out is not St and not np.shares_memory(out, St):  # BLAS could not work in place
            self.Sigma = np.ascontiguousarray(out.T)
        S = self.Sigma
        S += S.T.copy()
        S *= 0.5

    def _augment(self, z: np.ndarray, Q: np.ndarray, ids: np.ndarray, model: MeasurementModel) -> np.ndarray:
        """State augmentation (§8): μ_new = inverse model, Σnn = JxΣxxJx^T + JzQJz^T, Σn· = JxΣx·."""
        dx, dm = self.dx, self.dm
        k = len(ids)
        x = np.repeat(self.mu[None, :dx], k, 0)
        m, Jx, Jz = model.inverse(x, z)
        n = self.mu.size
        JxA = Jx.reshape(k * dm, dx)  # stacked Jacobians of all new landmarks w.r.t. the pose
        cross = JxA @ self.Sigma[:dx, :]  # (k·dm, n)
        nn = JxA @ self.Sigma[:dx, :dx] @ JxA.T
        JQJ = np.einsum("kij,kjl,kml->kim", Jz, Q, Jz) + self.params.landmark_cov_floor * np.eye(dm)
        for a in range(k):
            nn[a * dm : (a + 1) * dm, a * dm : (a + 1) * dm] += JQJ[a]
        Sig = np.empty((n + k * dm, n + k * dm))
        Sig[:n, :n] = self.Sigma
        Sig[n:, :n] = cross
        Sig[:n, n:] = cross.T
        Sig[n:, n:] = sym(nn)
        self.Sigma = Sig
        self.mu = np.concatenate([self.mu, m.ravel()])
        slots = self.book.allocate(ids, reuse=False)
        return slots

    def _prune(self, observed: np.ndarray, born: np.ndarray) -> np.ndarray:
        """Existence counter (§8 bookkeeping); deletion removes the landmark's rows and columns.
        Returns the ids of the deleted landmarks (K,) int64."""
        if not self.params.prune_enabled or self.book.n == 0:
            return NO_IDS
        M = self.book.n_slots
        m = self.mu[self.dx :].reshape(M, self.dm)
        zc, _, _ = (CARTESIAN_2D if self.dim == 2 else CARTESIAN_3D).h(np.repeat(self.mu[None, : self.dx], M, 0), m)
        x = self.mu[: self.dx]
        R = euler_to_R(x[3:6]) if self.dim == 3 else rot2(x[2])
        slots = np.arange(M)
        in_view = np.asarray(self.visible(zc), bool)
        expected = note_and_recognise(self.book, slots, zc, R, observed, born, in_view)
        dead = self.book.existence_update(observed, expected, born)
        if dead.size == 0:
            return NO_IDS
        dead_ids = self.book.slot_id[dead].copy()
        self.book.release(dead)
        keep_slots = self.book.compact()
        keep = np.r_[np.arange(self.dx), (self.dx + self.dm * keep_slots[:, None] + np.arange(self.dm)).ravel()]
        self.mu = self.mu[keep]
        self.Sigma = self.Sigma[np.ix_(keep, keep)]
        logger.debug("EKF pruned %d landmarks", dead.size)
        return dead_ids

    # ------------------------------------------------------------------------------------ output

    def estimate(self) -> PoseEstimate:
        xyz, rpy = pose_to_xyz_rpy(self.mu[: self.dx], self.dim)
        cov = pose_cov_6x6(self.Sigma[: self.dx, : self.dx], self.dim, self.params.pose_cov_floor_2d)
        return PoseEstimate(self.t_ns, xyz, rpy, cov)

    def landmark_ids(self) -> np.ndarray:
        return self.book.slot_id[: self.book.n_slots].copy()

    def landmarks(self) -> LandmarkMap:
        M, dx, dm = self.book.n_slots, self.dx, self.dm
        m = self.mu[dx:].reshape(M, dm).copy()
        idx = dx + dm * np.arange(M)[:, None] + np.arange(dm)  # (M, dm)
        C = self.Sigma[idx[:, :, None], idx[:, None, :]]
        m3, C3 = lm_to_3d(m, C, self.params.pose_cov_floor_2d)
        return LandmarkMap(self.landmark_ids(), m3, C3)

    def hold_landmarks(self, below_id: int) -> None:
        """Estimator.hold_landmarks: the book's existence rule skips the ids below ``below_id``."""
        self.book.held_below = max(0, int(below_id))

    def spread_kept(self) -> float:
        """Estimator.spread_kept: no particles (the joint covariance carries the map itself)."""
        return 0.0

    def reset_pose(self, x: np.ndarray, cov: np.ndarray | None = None) -> None:
        """Relocalisation: the pose mean becomes ``x`` (dx,), its covariance ``cov`` (default: a
        1 cm / 0.1° floor) and its correlations with the landmarks zero; the landmarks are kept."""
        dx = self.dx
        x, cov = check_reset_pose(x, cov, dx)
        self.mu[:dx] = x
        self.Sigma[:dx, :] = 0.0
        self.Sigma[:, :dx] = 0.0
        floor = np.diag([1e-4] * (dx // 2 if dx == 6 else 2) + [3e-6] * (3 if dx == 6 else 1))
        self.Sigma[:dx, :dx] = floor if cov is None else cov

    def set_particles(self, n: int) -> int:
        """The EKF has no particles; returns 0."""
        return 0

    def covariance(self) -> np.ndarray:
        """The full (n, n) state covariance (a view)."""
        return self.Sigma

    # ------------------------------------------------------------------------------ persistence

    def state_dict(self) -> dict[str, np.ndarray | float | int]:
        d: dict[str, np.ndarray | float | int] = {
            "filter_code": FILTER_CODE["ekf"],
            "dim": self.dim,
            "t_ns": self.t_ns,
            "mu": self.mu.copy(),
            "Sigma": self.Sigma.copy(),
        }
        d.update(self.book.state_dict())
        return d

    def check_state_dict(self, state: Any) -> dict[str, Any]:
        """Every key, type, shape and range of a saved state (:meth:`state_dict`), without
        touching the filter: PersistenceError naming the key (MapMismatchError for another filter
        or dimension). Returns the checked values for :meth:`load_state_dict`, ``ids`` (M,) the
        landmark ids it holds."""
        st = StateTable(state, "ekf state")
        t_ns = check_header(st, "ekf", self.dim)
        book = LandmarkBook.from_state(st, compact=True)
        n = self.dx + self.dm * book.n_slots
        mu = st.array("mu", "<f8", (n,))
        Sig = st.array("Sigma", "<f8", (n, n))
        check_saved_poses(st.name("mu"), mu[: self.dx], self.dim)
        check_saved_finite(st.name("mu"), mu[self.dx :], POSITION_LIMIT_M)
        check_covariances(st.name("Sigma"), Sig)
        return {"t_ns": t_ns, "book": book, "mu": mu, "Sigma": Sig, "ids": book.slot_id[: book.n_slots].copy()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore from :meth:`state_dict`; the state is checked whole first (:meth:`check_state_dict`)
        and the filter is left as it was when it fails."""
        self.restore(self.check_state_dict(state))

    def restore(self, c: dict[str, Any]) -> None:
        """Take the values :meth:`check_state_dict` returned."""
        self.mu, self.Sigma, self.book, self.t_ns = c["mu"].copy(), c["Sigma"].copy(), c["book"], c["t_ns"]
