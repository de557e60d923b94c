"""FastSLAM 1.0 and 2.0 with known correspondences, 2D and 3D (docs/math.md §9, §10).

One particle store, a struct of arrays:

- ``pose``    (P, dx)          particle poses, world frame (dx = 3 | 6)
- ``store``   the landmark Gaussians (dm = 2 | 3) of every particle, copy-on-write blocks
  (:class:`~robotd.slam._store.LandmarkStore`)
- ``log_w``   (P,)             normalised log weights

Landmark slots ``0 … n_slots-1`` are shared by all particles through the global
:class:`~robotd.slam._book.LandmarkBook` (ids -> slots); freed slots are reused.

The measurement step (every model, both dimensions, both versions) is the numba kernel
:func:`robotd.slam._kernels.fastslam_step_store`, which takes every random number as an argument
(``eps``) so that the tests hold it to its readable per-particle twin
(tests/support/reference_fastslam.py). This module keeps the filter's state and everything around
the step: motion, gating, resampling, pruning, outputs; persistence is in ``_fastslam_state.py``
and the fusion of gravity in ``_fastslam_gravity.py``.
"""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np

from robotd.core.errors import InputError, SingularityError
from robotd.core.geometry import euler_to_R, rot2
from robotd.core.msgs import LandmarkMap, MotionIncrement, PoseEstimate, UpdateReport
from robotd.slam._book import LandmarkBook, note_and_recognise
from robotd.slam._fastslam_gravity import gravity_update
from robotd.slam._fastslam_state import check_state, saved_state
from robotd.slam._linalg import sym
from robotd.slam._store import LandmarkStore
from robotd.slam.common import (
    NO_IDS,
    UpdateEntryPoints,
    check_finite,
    check_reset_pose,
    control_from_increment,
    gravity_inputs,
    lm_to_3d,
    measurement_model,
    pixel_noise,
    pose_cov_6x6,
    pose_to_xyz_rpy,
)
from robotd.slam.models import (
    COS_PITCH_MIN,
    MeasurementModel,
    motion3d,
    odometry2d,
    velocity2d,
    velocity2d_noise,
    wrap_pose,
)
from robotd.slam.params import SlamParams, VisibleFn
from robotd.slam.resampling import (
    effective_sample_size,
    low_variance_indices,
    normalize_log_weights,
    weighted_pose_mean,
)

logger = logging.getLogger(__name__)


def sample_poses(mu: np.ndarray, Sigma: np.ndarray, eps: np.ndarray, dim: int) -> np.ndarray:
    """x = μ + chol(Σ) ε per particle, angles wrapped. mu (P, dx), Sigma (P, dx, dx), eps (P, dx)."""
    try:
        L = np.linalg.cholesky(Sigma)
    except np.linalg.LinAlgError:
        # Round-off can leave a proposal covariance marginally indefinite: lift its spectrum.
        w, V = np.linalg.eigh(Sigma)
        L = V * np.sqrt(np.maximum(w, 0.0))[:, None, :]
    return wrap_pose(mu + np.einsum("pij,pj->pi", L, eps), dim)


def psd_sqrt(M: np.ndarray) -> np.ndarray:
    """A square root L with L L^T = M for a PSD matrix M (n, n) (zero rows allowed)."""
    w, V = np.linalg.eigh(0.5 * (M + M.T))
    return V * np.sqrt(np.maximum(w, 0.0))


def move_particles(
    pose: np.ndarray, u: np.ndarray, M: np.ndarray, extra: np.ndarray, dt: float | None, dim: int, want_S: bool
) -> tuple[np.ndarray, np.ndarray | None]:
    """Every particle through the motion model with the control ``u`` ((nu,) or one per particle
    (P, nu)), M (nu, nu) its covariance: (poses (P, dx), and with ``want_S`` the prior covariances
    S = V M V^T + diag(``extra``) (P, dx, dx)).

    ``dt`` None: the odometry-increment model (§6.2 / §6.3), else the 2D velocity model (§6.1). 3D:
    one compiled pass (``predict3_numba``, without the motion Jacobian G that FastSLAM does not use;
    the same formulas as ``motion3d``), SingularityError at the pitch singularity as ``motion3d``.
    """
    if dim == 3 and dt is None:
        from robotd.slam._kernels import predict3_numba

        x, S, bad = predict3_numba(pose, u, M, extra, want_S, COS_PITCH_MIN)
        if bad >= 0:
            deg = float(np.rad2deg(pose[bad, 4]))
            raise SingularityError(
                f"motion3d: pitch {deg:.3f} deg is at the ZYX singularity (±90 deg); cannot propagate"
            )
        return x, S
    u = np.broadcast_to(u, (pose.shape[0], u.shape[-1]))
    x, _, V = velocity2d(pose, u, dt) if dt is not None else (odometry2d(pose, u) if dim == 2 else motion3d(pose, u))
    return x, (sym(V @ M @ np.swapaxes(V, -1, -2)) + np.diag(extra) if want_S else None)


def chi2_gate(
    x: np.ndarray,
    S: np.ndarray | None,
    m: np.ndarray,
    C: np.ndarray,
    z: np.ndarray,
    Q: np.ndarray,
    model: MeasurementModel,
    params: SlamParams,
) -> np.ndarray:
    """(N,) bool: re-observations z (N, dz), Q of landmarks m (N, dm), C seen from pose x (dx,)
    consistent with it at the χ² gate (§8's test).

    The innovation covariance is H_x S H_x^T + H_m C H_m^T + Q (the FastSLAM 2.0 marginal of §10,
    with S the pending motion covariance where there is one, else None). FastSLAM's
    correspondences are shared by all particles, so the test is made once per frame, in the best
    particle; when it would reject more than half of them the pose is more likely wrong than the
    data, and nothing is gated.
    """
    n = m.shape[0]
    zhat, Hx, Hm = model.h(np.repeat(x[None], n, 0), m)
    L = Hm @ C @ np.swapaxes(Hm, -1, -2) + Q
    if S is not None:
        L = L + Hx @ S @ np.swapaxes(Hx, -1, -2)
    nu = model.innovation(z, zhat)
    d2 = np.einsum("ni,ni->n", nu, np.linalg.solve(L, nu[..., None])[..., 0])
    keep = d2 <= (params.gate_chi2_2d if model.dz == 2 else params.gate_chi2_3d)
    if np.count_nonzero(~keep) * 2 > n:
        return np.ones(n, bool)
    return keep


class FastSlam(UpdateEntryPoints):
    """FastSLAM 1.0 (``version=1``) or 2.0 (``version=2``). Build with ``make_estimator``."""

    def __init__(self, params: SlamParams, rng: np.random.Generator, visible: VisibleFn, version: int = 2) -> None:
        if version not in (1, 2):
            raise InputError(f"FastSlam: expected version 1 or 2, got {version}")
        self.params = params
        self.rng = rng
        self.visible = visible
        self.version = version
        self.name = "fastslam2" if version == 2 else "fastslam1"
        self.dim = params.dim
        self.dx = 3 if self.dim == 2 else 6
        self.dm = self.dim
        self.model: MeasurementModel = measurement_model(params)
        self.Q_px = pixel_noise(params) if self.model.intrinsics is not None else None
        P = int(params.n_particles)
        self.book = LandmarkBook()
        self.pose = np.zeros((P, self.dx))
        self.store = LandmarkStore(P, self.dm, params.landmark_block_size)
        self.log_w = np.full(P, -np.log(P))
        # FastSLAM 2.0: prior covariance S_t per particle since the last sampling; None = sampled
        self.pending_S: np.ndarray | None = None
        self.t_ns = 0
        self.best = 0  # index of the highest-weight particle
        self.neff = float(P)
        # the numba kernel (robotd.slam._kernels), loaded here: importing this module loads no numba
        from robotd.slam import _kernels

        self._step = _kernels.fastslam_step_store
        # Rao-Blackwellised pose estimate of the last update (weights before resampling, means,
        # covariances or None): see estimate(); None after a predict or a particle-set change
        self._post: tuple[np.ndarray, np.ndarray, np.ndarray | None] | None = None
        # the particles' poses and weights after the last update (None: drawn again since), and
        # the share of their spread the update after it kept (spread_kept)
        self._ancestors: tuple[np.ndarray, np.ndarray] | None = None
        self._kept = 0.0

    @property
    def n_particles(self) -> int:
        return int(self.pose.shape[0])

    # ----------------------------------------------------------------------------------- predict

    def predict(self, inc: MotionIncrement) -> None:
        """Motion update with the odometry-increment model (§6.2 / §6.3)."""
        u, M = control_from_increment(inc, self.params)
        self._propagate(u, M, None, 0.0)
        self.t_ns = int(inc.t1_ns)

    def predict_velocity(self, v: float, w: float, dt: float, t_ns: int | None = None) -> None:
        """Velocity-model motion update (§6.1), 2D only."""
        if self.dim != 2:
            raise InputError(f"predict_velocity: expected a 2D filter, got dim={self.dim}")
        check_finite("predict_velocity", v, w, dt)
        M, var_g = velocity2d_noise(float(v), float(w), float(dt), self.params.vel2d_alpha)
        self._propagate(np.array([v, w], float), M, float(dt), var_g)
        if t_ns is not None:
            self.t_ns = int(t_ns)

    def _propagate(self, u: np.ndarray, M: np.ndarray, dt: float | None, var_yaw: float) -> None:
        """Sample (1.0) or propagate the prior (2.0). ``var_yaw``: extra final-rotation variance (§6.1)."""
        self._post = None
        P, dx, nu = self.n_particles, self.dx, u.size
        extra = np.full(dx, self.params.process_cov_floor)
        extra[2 if self.dim == 2 else 5] += var_yaw
        if self.version == 1:
            eps = self.rng.standard_normal((P, nu + dx))
            x, _ = move_particles(self.pose, u + eps[:, :nu] @ psd_sqrt(M).T, M, extra, dt, self.dim, False)
            self.pose = wrap_pose(x + np.sqrt(extra) * eps[:, nu:], self.dim)
            return
        if self.pending_S is not None:
            # two predicts without an update: draw the pending prior before composing the next step
            self.pose = sample_poses(self.pose, self.pending_S, self.rng.standard_normal((P, dx)), self.dim)
        self.pose, self.pending_S = move_particles(self.pose, u, M, extra, dt, self.dim, True)

    def update_gravity(
        self, g_R: np.ndarray, g_W: np.ndarray, sigma_rad: float, reopen: bool = False
    ) -> tuple[bool, float]:
        """Fuse a measured direction of gravity ``g_R`` in the robot frame (3D only; docs/slam.md
        "Gravity"): ``g_R = R(η)^T g_W + n``, n ~ N(0, σ² I).

        2.0 with a pending prior: each particle's prior (x̂, S) takes the linear-Gaussian update,
        and its weight the marginal likelihood N(g_R; h(x̂), H S H^T + σ² I), as the proposal does
        with landmarks. 1.0 (or a prior already drawn): the weight takes N(g_R; h(x), σ² I).
        Gate: the normalised innovation squared of the particle mixture (its mean direction, with
        the particles' spread plus their prior covariances plus σ² I) against ``gate_chi2_2d`` (the
        innovation has two degrees of freedom: its component along h is of second order). A gated
        measurement changes nothing. ``reopen``: the filter's roll and pitch are the ones in doubt
        (the caller saw the gate refuse gravity for too long): their prior variance grows by the
        squared innovation angle (1.0: the particles spread by it), and the measurement is fused
        without the gate. Returns (fused, the NIS before any reopening).
        """
        g_R, g_W = gravity_inputs(self.dim, g_R, g_W, sigma_rad)
        gate = self.params.gate_chi2_2d if self.params.gate_enabled else None
        S = self.pending_S if self.version == 2 else None
        fused, nis, self.pose, S, self.log_w = gravity_update(
            self.pose, S, self.log_w, self.rng, g_R, g_W, sigma_rad, gate, reopen
        )
        if fused:
            self.pending_S = S if self.version == 2 else self.pending_S
            self._post = None
        return fused, nis

    # ------------------------------------------------------------------------------------ update

    def _update(
        self, z: np.ndarray, Q: np.ndarray, ids: np.ndarray, is_new: np.ndarray, model: MeasurementModel
    ) -> UpdateReport:
        old = ~is_new
        slots_seen = self.book.slots_of(ids[old])  # every re-observed landmark (existence counter)
        z_old, Q_old = z[old], Q[old]
        n_gated = 0
        slots_old = slots_seen
        if self.params.gate_enabled and self.params.fastslam_gate and slots_seen.size:
            k = self.best
            m, C = self.store.gather_particle(k, slots_seen)
            S_k = self.pending_S[k] if self.pending_S is not None else None
            keep = chi2_gate(self.pose[k], S_k, m, C, z_old, Q_old, model, self.params)
            n_gated = int(np.count_nonzero(~keep))
            if n_gated:
                slots_old, z_old, Q_old = slots_seen[keep], z_old[keep], Q_old[keep]
        P, dx = self.n_particles, self.dx
        # every random number of this step is drawn here, before any state changes
        eps = self.rng.standard_normal((P, dx)) if self.version == 2 else None
        u_resample = float(self.rng.random())

        S = None
        if self.version == 2:
            S = self.pending_S
            if S is None:
                S = np.tile(self.params.process_cov_floor * np.eye(dx), (P, 1, 1))
        slots_new = self.book.allocate(ids[is_new])
        self.store.ensure_capacity(self.book.n_slots)
        # FastSLAM 2.0's proposal means and covariances (the Rao-Blackwellised pose estimate)
        mu_x, S_x = (np.empty((P, dx)), np.empty((P, dx, dx))) if self.version == 2 else (None, None)
        # the kernel works in the copy-on-write store directly
        self.pose, dlogw = self._step(
            self.version,
            self.pose,
            S,
            self.store,
            slots_old,
            z_old,
            Q_old,
            slots_new,
            z[is_new],
            Q[is_new],
            eps,
            model,
            self.params.landmark_cov_floor,
            self.params.fs2_weights == "sequential",
            mu_x,
            S_x,
            int(self.params.numba_threads),
        )
        self.pending_S = None

        ln, w = normalize_log_weights(self.log_w + dlogw)
        self._kept = self._share_kept(w)
        self.neff = effective_sample_size(w)
        self.best = int(np.argmax(w))
        if self.params.pose_estimate == "mixture":
            # before resampling, which only adds Monte Carlo noise (and can leave every particle a
            # copy of one, i.e. a zero spread): 2.0's weights do not depend on the drawn pose, so
            # Σ_k w_k N(μ_x,k, Σ_x,k) is the filter's posterior of the pose (Rao-Blackwellised)
            self._post = (w, mu_x, S_x) if mu_x is not None else (w, self.pose.copy(), None)
        resampled = False
        if self.neff < self.params.resample_neff_ratio * P:
            idx = low_variance_indices(w, u_resample)
            self._select(idx)
            resampled = True
        else:
            self.log_w = ln
        self._ancestors = (self.pose.copy(), self.weights())

        pruned = self._prune(slots_seen, slots_new)
        return UpdateReport(
            n_updated=int(slots_old.size),
            n_new=int(slots_new.size),
            n_gated=n_gated,
            pruned_ids=pruned,
            neff=self.neff,
            resampled=resampled,
        )

    def _share_kept(self, w: np.ndarray) -> float:
        """The share of the spread the particles had after the previous update that they keep with
        the weights ``w`` of this one: the variance of their poses then, weighted now against
        weighted then, per axis, averaged (1: nothing singled out; near 0: one ancestor left)."""
        if self._ancestors is None or self._ancestors[0].shape != self.pose.shape:
            return 0.0
        pose, w_then = self._ancestors
        v_then = np.diag(weighted_pose_mean(pose, w_then, self.dim)[1])
        v_now = np.diag(weighted_pose_mean(pose, w, self.dim)[1])
        ok = v_then > 1e-18
        if not np.any(ok):
            return 0.0
        share = float(np.mean(v_now[ok] / v_then[ok]))
        return min(1.0, max(0.0, share)) if math.isfinite(share) else 0.0

    def spread_kept(self) -> float:
        """Estimator.spread_kept (:meth:`_share_kept` at the last update)."""
        return self._kept

    def _select(self, idx: np.ndarray) -> None:
        """Replace the particle set by ``particles[idx]`` (any count) with uniform weights.

        Landmarks are shared copy-on-write (:class:`~robotd.slam._store.LandmarkStore`): only the
        block table is gathered here.
        """
        self._ancestors = None
        best_old = self.best
        self.store.select(idx)
        self.pose = self.pose[idx]
        if self.pending_S is not None:
            self.pending_S = self.pending_S[idx]
        hits = np.flatnonzero(idx == best_old)
        # the best particle (w_max >= 1/P) always survives low-variance resampling
        self.best = int(hits[0]) if hits.size else 0
        self.log_w = np.full(idx.size, -np.log(idx.size))

    def _prune(self, observed: np.ndarray, born: np.ndarray) -> np.ndarray:
        """Existence counters (§8 bookkeeping), visibility judged in the best particle. Returns the
        ids of the deleted landmarks (K,) int64."""
        if not self.params.prune_enabled or self.book.n == 0:
            return NO_IDS
        active = self.book.active_slots()
        x = self.pose[self.best]
        R = euler_to_R(x[3:6]) if self.dim == 3 else rot2(x[2])
        p = self._best_view(active)
        in_view = np.asarray(self.visible(p), bool)
        expected = note_and_recognise(self.book, active, p, R, observed, born, in_view)
        dead = self.book.existence_update(observed, expected, born)
        if dead.size == 0:
            return NO_IDS
        dead_ids = self.book.slot_id[dead].copy()
        self.book.release(dead)
        logger.debug("FastSLAM pruned %d landmarks", dead.size)
        return dead_ids

    def _best_view(self, slots: np.ndarray) -> np.ndarray:
        """(N, dim) robot-frame positions z = R^T (m - p) of ``slots`` in the best particle (§7.1/§7.2).

        The Cartesian h without its Jacobians and with one rotation: pruning looks at the whole
        map every frame, and h's per-landmark Jacobians made that O(M) pass ~5× dearer.
        """
        x = self.pose[self.best]
        R = euler_to_R(x[3:6]) if self.dim == 3 else rot2(x[2])
        return (self.store.particle_means(self.best, slots) - x[: self.dim]) @ R

    # ------------------------------------------------------------------------------------ output

    def dense_landmarks(self) -> tuple[np.ndarray, np.ndarray]:
        """All particles' landmark slots as dense copies: mean (P, n_slots, dm), cov (P, n_slots, dm, dm)."""
        return self.store.dense(self.book.n_slots)

    def weights(self) -> np.ndarray:
        """(P,) normalised particle weights."""
        return normalize_log_weights(self.log_w)[1]

    def estimate(self) -> PoseEstimate:
        """Weighted mean (circular for angles) and covariance of the pose (§10 "Output").

        With ``pose_estimate="mixture"`` (default) and an update since the last predict: the
        mixture of the update's proposals Σ_k w_k N(μ_k, Σ_k) with the weights before resampling
        (FastSLAM 1.0: the weighted samples before resampling); otherwise the particles as they are.
        """
        if self._post is not None:
            w, x, spread = self._post
        else:
            # as the particles are; between a 2.0 predict and its update, plus the prior's spread
            w, x, spread = self.weights(), self.pose, self.pending_S
        mean, cov = weighted_pose_mean(x, w, self.dim)
        if spread is not None:
            cov = cov + np.einsum("p,pij->ij", w, spread)
        xyz, rpy = pose_to_xyz_rpy(mean, self.dim)
        return PoseEstimate(
            self.t_ns,
            xyz,
            rpy,
            pose_cov_6x6(cov, self.dim, self.params.pose_cov_floor_2d),
            neff=self.neff,
            n_particles=self.n_particles,
        )

    def landmark_ids(self) -> np.ndarray:
        return self.book.slot_id[self.book.active_slots()].copy()

    def landmarks(self) -> LandmarkMap:
        """The highest-weight particle's landmarks (§10 "Output")."""
        s = self.book.active_slots()
        m, C = lm_to_3d(*self.store.gather_particle(self.best, s), self.params.pose_cov_floor_2d)
        return LandmarkMap(self.book.slot_id[s].copy(), m, C)

    def hold_landmarks(self, below_id: int) -> None:
        """Estimator.hold_landmarks: the book's existence rule skips the ids below ``below_id``."""
        self.book.held_below = max(0, int(below_id))

    def reset_pose(self, x: np.ndarray, cov: np.ndarray | None = None) -> None:
        """Relocalisation: every particle's pose drawn from N(x, cov) (exactly x when ``cov`` is None).

        ``x``: (dx,) pose (2D: x, y, yaw; 3D: x, y, z, roll, pitch, yaw), ``cov``: (dx, dx). The
        particles keep their maps (in the world frame); the weights become uniform.
        """
        x, cov = check_reset_pose(x, cov, self.dx)
        P = self.pose.shape[0]
        if cov is None:
            self.pose = np.broadcast_to(x, (P, self.dx)).copy()
        else:
            L = np.linalg.cholesky(cov + 1e-12 * np.eye(self.dx))
            self.pose = wrap_pose(x + self.rng.standard_normal((P, self.dx)) @ L.T, self.dim)
        self.log_w = np.full(P, -np.log(P))
        self.neff = float(P)
        self.pending_S = None
        self._post = None
        self._ancestors, self._kept = None, 0.0

    def set_particles(self, n: int) -> int:
        """Resample to ``max(n, min(n_particles_min, n_particles))`` particles (low-variance); returns the count."""
        self._post = None
        n = max(int(n), min(int(self.params.n_particles_min), int(self.params.n_particles)))
        if n != self.n_particles:
            w = self.weights()
            self._select(low_variance_indices(w, float(self.rng.random()), n))
            self.neff = float(n)
            logger.debug("FastSLAM particle count -> %d", n)
        return n

    # ------------------------------------------------------------------------------ persistence

    def state_dict(self) -> dict[str, np.ndarray | float | int]:
        return saved_state(self)

    def check_state_dict(self, state: Any) -> dict[str, Any]:
        """Every key, type, shape and range of a saved state (:meth:`state_dict`), without
        touching the filter: PersistenceError naming the key (MapMismatchError for another filter
        or dimension). Returns the checked values for :meth:`load_state_dict`, ``ids`` (M,) the
        landmark ids it holds."""
        return check_state(self.name, self.dim, state)

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore from :meth:`state_dict`; the state is checked whole first (:meth:`check_state_dict`)
        and the filter is left as it was when it fails."""
        self.restore(self.check_state_dict(state))

    def restore(self, c: dict[str, Any]) -> None:
        """Take the values :meth:`check_state_dict` returned."""
        self._post = None
        self._ancestors, self._kept = None, 0.0
        self.store = LandmarkStore.from_dense(c["mean"], c["cov"], self.params.landmark_block_size)
        self.pose, self.log_w, self.book = c["pose"].copy(), c["log_w"].copy(), c["book"]
        self.pending_S = c["pending_S"].copy() if c["pending_S"].shape[0] else None
        self.best, self.neff, self.t_ns = c["best"], c["neff"], c["t_ns"]
