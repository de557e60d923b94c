"""The pose covariance robotd reports: consistent with its real error (docs/slam.md "Reported covariance").

A FastSLAM particle set cannot carry the map's own uncertainty for long: after a few resampling
rounds every particle descends from one ancestor, and the spread of their poses is only the last
fix against that ancestor's map (Bailey, Nieto and Nebot 2006; docs/experiments/consistency.md).
The error of the pose in the world, though, is the error of the map it was fixed against plus the
error of the fix. Two parts make the reported covariance honest:

:class:`AnchoredCovariance`
    Every landmark remembers the world covariance of the pose it was first mapped from (its
    *anchor*). A pose fixed against landmarks inherits their anchors' covariance, transported
    rigidly to where the robot is now (a heading error at the anchor is a lateral error here), and
    adds the filter's own covariance of the fix. With landmarks of several anchors it takes their
    convex combination, weighted by how many of each were used, which bounds the covariance of the
    weighted combination of correlated errors from above (the errors of anchors share their
    history). New landmarks then anchor at the pose's reported covariance, so the uncertainty
    grows like the real drift while the rover explores and falls back to an old anchor's when it
    re-observes old landmarks.

:class:`ConsistencyMonitor`
    The normalised innovation squared (NIS) of each frame's re-observations at the predicted pose,
    νᵀ S⁻¹ ν with S the filter's own innovation covariance, has a χ²(d) distribution when the noise
    model is right. The monitor keeps a running robust estimate of NIS / E[NIS] (medians, so the
    few outliers the screens let through do not dominate) and scales the fix's covariance by it
    when the filter is over-confident. Its state is in the health topic.

Errors are handled in the world-frame error state (δp, δθ): δp the position error [m], δθ the
small rotation [rad] with R_true = exp([δθ]×) R. The reported 6×6 covariance is over
(x, y, z, roll, pitch, yaw); :func:`euler_error_jacobian` converts between the two.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.special import chdtri  # chi2 quantiles; scipy.stats costs 1 s of start-up

from robotd.core.msgs import LandmarkMap, Observations, PoseEstimate
from robotd.core.stereo import streak_px
from robotd.slam.models import MeasurementModel

# The χ² medians the robust NIS ratio divides by, per measurement size.
_CHI2_MEDIAN = {d: float(chdtri(d, 0.5)) for d in (1, 2, 3, 4, 6)}


def euler_error_jacobian(rpy: np.ndarray) -> np.ndarray:
    """E (3, 3) with δθ = E δ(roll, pitch, yaw): ZYX Euler-angle errors -> world-frame rotation.

    R = Rz(ψ) Ry(θ) Rx(φ), so δR Rᵀ = [ω]× with ω = Rz Ry e_x δφ + Rz e_y δθ + e_z δψ.
    """
    _, p, y = (float(v) for v in rpy)
    cy, sy, cp, sp = math.cos(y), math.sin(y), math.cos(p), math.sin(p)
    return np.array([[cy * cp, -sy, 0.0], [sy * cp, cy, 0.0], [-sp, 0.0, 1.0]])


def _to_world_error(cov6: np.ndarray, rpy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(G C Gᵀ, G): a covariance over (x, y, z, roll, pitch, yaw) in the (δp, δθ) error state."""
    G = np.eye(6)
    G[3:, 3:] = euler_error_jacobian(rpy)
    return G @ cov6 @ G.T, G


def _from_world_error(C: np.ndarray, G: np.ndarray) -> np.ndarray:
    """Inverse of :func:`_to_world_error` (pinv near the ZYX singularity, where ±90° pitch has no yaw)."""
    Gi = np.linalg.pinv(G) if abs(np.linalg.det(G)) < 1e-6 else np.linalg.inv(G)
    out = Gi @ C @ Gi.T
    return 0.5 * (out + out.T)


def transport(C: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Covariances (A, 6, 6) in (δp, δθ) at anchors moved rigidly by d (A, 3) = p_now − p_anchor:
    δp_now = δp + δθ × d = δp − [d]× δθ, δθ_now = δθ (the map turns about the anchor with its error)."""
    A = C.shape[0]
    J = np.broadcast_to(np.eye(6), (A, 6, 6)).copy()
    J[:, 0, 4], J[:, 0, 5] = d[:, 2], -d[:, 1]
    J[:, 1, 3], J[:, 1, 5] = -d[:, 2], d[:, 0]
    J[:, 2, 3], J[:, 2, 4] = d[:, 1], -d[:, 0]
    return J @ C @ np.swapaxes(J, 1, 2)


def _psd_part(C: np.ndarray) -> np.ndarray:
    """The positive semi-definite part of a symmetric matrix (its negative eigenvalues set to 0)."""
    w, V = np.linalg.eigh(0.5 * (C + C.T))
    return (V * np.maximum(w, 0.0)) @ V.T


class AnchoredCovariance:
    """The world covariance of the pose from the anchors of the landmarks it was fixed against.

    Each landmark keeps the position and (δp, δθ) covariance of the pose it was created at; ids
    not known here (a resumed map, or beyond ``max_landmarks``, where the lowest ids go first) are
    taken as the map's frame itself: zero covariance, the world being defined by that map.

    Storage: one table, rows sorted by id. The filter's ids only grow, so a frame's new landmarks
    are appended (capacity doubling) and a forgotten one is marked dead, the table compacted once
    half of it is; inserting into sorted arrays copied every anchor every frame (4.7 ms a frame at
    28 000 anchors).
    """

    def __init__(self, max_landmarks: int = 200_000, min_support: int = 3, drift_per_m: float = 0.0) -> None:
        if not (math.isfinite(drift_per_m) and drift_per_m >= 0.0):
            raise ValueError(f"drift per metre: expected a finite value >= 0, got {drift_per_m}")
        self.max_landmarks = int(max_landmarks)
        self.min_support = int(min_support)
        self.drift_per_m = float(drift_per_m)
        self.reset()

    def reset(self) -> None:
        """Forget every anchor (a new map; after relocalisation the saved map is the world)."""
        self._size = 0  # rows in use, alive or dead, sorted by id
        self._dead = 0
        self._id = np.zeros(0, np.int64)
        self._alive = np.zeros(0, bool)
        self._p = np.zeros((0, 3))  # the pose each landmark was last fixed from
        self._C = np.zeros((0, 6, 6))  # its reported covariance then
        self._n = np.zeros(0)  # observations fused per landmark
        self._u = np.zeros(0)  # the explored path behind each landmark's creation [m]
        self._pc = np.zeros((0, 3))  # where each landmark was created
        # (p, C, u, S) of the previous frame
        self._last: tuple[np.ndarray, np.ndarray, float, np.ndarray] | None = None
        self.explored_m = 0.0  # the explored path behind this frame's pose (:meth:`step`)

    @property
    def n_anchored(self) -> int:
        """Landmarks with an anchor."""
        return self._size - self._dead

    @property
    def anchored_ids(self) -> np.ndarray:
        """The ids of the landmarks with an anchor, ascending."""
        return self._id[: self._size][self._alive[: self._size]].copy()

    def _find(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(rows, present): for each id, its row and whether the table holds it (alive or dead)."""
        if not self._size or not ids.size:
            return np.zeros(ids.size, np.int64), np.zeros(ids.size, bool)
        table = self._id[: self._size]
        rows = np.minimum(np.searchsorted(table, ids), self._size - 1)
        return rows, table[rows] == ids

    def step(
        self,
        xyz: np.ndarray,
        rpy: np.ndarray,
        cov_fix: np.ndarray,
        used_ids: np.ndarray,
        new_ids: np.ndarray,
        spread_kept: float = 0.0,
        extra: np.ndarray | None = None,
    ) -> np.ndarray:
        """The reported (6, 6) covariance over (x, y, z, roll, pitch, yaw) of this frame's pose.

        ``xyz``, ``rpy``: the pose; ``cov_fix``: the filter's (6, 6) covariance of it given its map
        (FastSLAM: the particles' mixture), already scaled by the consistency monitor;
        ``used_ids``: the map landmarks this frame's update re-observed; ``new_ids``: the landmarks
        it created (they anchor here); ``spread_kept``: the share of the filter's spread after its
        previous update that it still carries (``Estimator.spread_kept``); ``extra``: (6, 6) over
        (x, y, z, roll, pitch, yaw), an error the filter was not told of
        (:meth:`ReportedCovariance.add_uncertainty`): added, and never counted as the filter's
        spread.

        Where too little of the map is seen, the pose is relative to the previous frame's, and the
        filter's covariance is not all new: a particle filter's spread is the spread its particles
        had at the previous frame, times the share of it this update kept (``spread_kept``), plus
        what it gained since. The previous frame's reported covariance carries the first part
        already, so only the rest (the positive semi-definite part of the difference) is added.
        Counting the whole spread at every frame made a drive with no landmark seen twice (nothing
        resampled: the particles spread like a random walk) report the sum of that walk's
        variances over every frame, 46× its variance on a 764 m lap. Against landmarks the
        filter's whole covariance is added as before: taking the anchors' share out there too
        (tried) made the map-rich loops of bench/consistency.py, over-confident already, more so
        (docs/slam.md "Reported covariance").
        """
        p = np.asarray(xyz, dtype=float)
        C_fix, G = _to_world_error(np.asarray(cov_fix, dtype=float), rpy)
        used = np.asarray(used_ids, dtype=np.int64)
        kept = min(1.0, max(float(spread_kept), 0.0)) if math.isfinite(spread_kept) else 0.0
        k = np.zeros(0, np.int64)
        if used.size >= self.min_support or self._last is None:
            C_map = np.zeros((6, 6))
            carried = np.zeros((6, 6))
            u = 0.0
            rows, present = self._find(used)
            k = rows[present]
            k = k[self._alive[k]]  # the others anchor in the map's frame: zero
            if k.size:
                # the convex combination, each landmark weighing 1 / (landmarks used)
                Ck = transport(self._C[k], p - self._p[k])
                C_map = Ck.sum(axis=0) / float(used.size)
                # the same combination of the path explored up to each landmark and on from it
                reach = self._u[k] + np.linalg.norm(p - self._pc[k], axis=1)
                u = float(reach.sum()) / float(used.size)
        else:
            # too little of the map was seen: the fix is relative to the previous pose
            p0, C0, u0, S0 = self._last
            C_map = transport(C0[None], (p - p0)[None])[0]
            carried = transport(S0[None], (p - p0)[None])[0] * kept
            u = u0 + float(np.linalg.norm(p - p0))
        C = C_map + _psd_part(C_fix - carried)
        if extra is not None:
            C = C + _to_world_error(np.asarray(extra, dtype=float), rpy)[0]
        C = 0.5 * (C + C.T)
        self._last = (p.copy(), C, u, C_fix)
        self.explored_m = u
        if k.size:
            # the filter moved each re-observed landmark towards where this pose sees it: its error
            # now shares this pose's, by this observation's share of its information (1/n after n)
            a = (1.0 / (self._n[k] + 1.0))[:, None, None]
            self._C[k] = (1.0 - a) * Ck + a * C
            self._p[k] = p
            self._n[k] += 1.0
        self._anchor(np.unique(np.asarray(new_ids, dtype=np.int64)), p, C, u)
        if self.drift_per_m > 0.0 and u > 0.0:
            # the error no pixel model holds (calibration, timing, the far points' depth): a
            # fraction of the explored path, in every direction; kept out of the anchors, which
            # carry the path itself (u), so it is not counted twice
            C = C.copy()
            C[:3, :3] += np.eye(3) * (self.drift_per_m * u) ** 2
        return _from_world_error(C, G)

    def forget(self, ids: np.ndarray) -> None:
        """Drop the anchors of landmarks the filter deleted (``UpdateReport.pruned_ids``; ids are
        never reused). Without it the anchors of every landmark ever made piled up to
        ``max_landmarks``: 66 MB, and a 40 ms copy per frame at 200 000 (found by bench/soak.py)."""
        ids = np.asarray(ids, dtype=np.int64)
        if not ids.size or not self._size:
            return
        rows, present = self._find(ids)
        rows = np.unique(rows[present])
        rows = rows[self._alive[rows]]
        self._alive[rows] = False
        self._dead += int(rows.size)
        if self._dead > max(1024, self._size // 2):
            self._compact()

    def _compact(self) -> None:
        keep = np.flatnonzero(self._alive[: self._size])
        m = keep.size
        for name in ("_id", "_alive", "_p", "_C", "_n", "_u", "_pc"):
            arr = getattr(self, name)
            arr[:m] = arr[keep]
        self._size, self._dead = m, 0

    def _reserve(self, rows: int) -> None:
        cap = self._id.shape[0]
        if rows <= cap:
            return
        cap = max(1024, 2 * rows)
        for name in ("_id", "_alive", "_p", "_C", "_n", "_u", "_pc"):
            arr = getattr(self, name)
            grown = np.zeros((cap, *arr.shape[1:]), arr.dtype)
            grown[: self._size] = arr[: self._size]
            setattr(self, name, grown)

    def _anchor(self, new: np.ndarray, p: np.ndarray, C: np.ndarray, u: float) -> None:
        """Anchor the landmarks ``new`` (unique ids) at the pose ``p`` with reported covariance ``C``
        and explored path ``u``; an id held already is anchored again."""
        if not new.size:
            return
        rows, present = self._find(new)
        again = rows[present]  # an id created again (or forgotten, then created): its anchor is this pose
        if again.size:
            self._dead -= int(np.count_nonzero(~self._alive[again]))
            self._alive[again] = True
            self._p[again], self._C[again] = p, C
            self._n[again], self._u[again], self._pc[again] = 1.0, u, p
        add = new[~present]
        if add.size:
            in_order = self._size == 0 or add[0] > self._id[self._size - 1]
            a, b = self._size, self._size + add.size
            self._reserve(b)
            self._id[a:b], self._alive[a:b] = add, True
            self._p[a:b], self._C[a:b] = p, C
            self._n[a:b], self._u[a:b], self._pc[a:b] = 1.0, u, p
            self._size = b
            if not in_order:  # ids below the newest: sort the rows again (not the filter's way)
                order = np.argsort(self._id[:b], kind="stable")
                for name in ("_id", "_alive", "_p", "_C", "_n", "_u", "_pc"):
                    arr = getattr(self, name)
                    arr[:b] = arr[order]
        extra = self.n_anchored - self.max_landmarks
        if extra > 0:  # the lowest ids go first
            alive = np.flatnonzero(self._alive[: self._size])[:extra]
            self._alive[alive] = False
            self._dead += int(alive.size)
            if self._dead > max(1024, self._size // 2):
                self._compact()


@dataclass
class ConsistencyMonitor:
    """Running robust NIS ratio of the re-observations; the factor the fix's covariance is scaled by.

    ``window``: frames of the exponential average (of the log ratio); ``min_measurements``: fewer
    re-observations in a frame say nothing; ``overconfident_above``: the ratio from which the
    health topic says "overconfident" (the scale is applied from 1 up, whatever the state).
    """

    window: int = 20
    min_measurements: int = 8
    overconfident_above: float = 2.0
    max_scale: float = 1.0e4
    log_ratio: float = 0.0
    frames: int = 0
    last_ratio: float = math.nan

    def observe(self, nis: np.ndarray, dz: int) -> None:
        """One frame's per-measurement NIS values (any outliers included) of measurements of size dz."""
        v = np.asarray(nis, dtype=float)
        v = v[np.isfinite(v)]
        if v.size < self.min_measurements:
            return
        r = float(np.median(v)) / _CHI2_MEDIAN.get(dz, float(chdtri(dz, 0.5)))
        self.last_ratio = r
        lr = math.log(min(max(r, 1e-6), self.max_scale))
        self.frames += 1
        a = max(1.0 / self.window, 1.0 / self.frames)  # the first frames average what there is
        self.log_ratio += a * (lr - self.log_ratio)

    @property
    def ratio(self) -> float:
        """The averaged NIS / E[NIS] (1 when consistent; nan before any frame)."""
        return math.exp(self.log_ratio) if self.frames else math.nan

    @property
    def scale(self) -> float:
        """The factor applied to the filter's covariance of each fix: the ratio, at least 1."""
        return min(self.max_scale, max(1.0, self.ratio)) if self.frames else 1.0

    @property
    def state(self) -> str:
        if not self.frames:
            return "unknown"
        return "overconfident" if self.ratio > self.overconfident_above else "ok"

    def health(self) -> dict[str, float | int | str]:
        return {
            "state": self.state,
            "nis_ratio": round(self.ratio, 3) if self.frames else None,  # type: ignore[dict-item]
            "scale": round(self.scale, 3),
            "frames": self.frames,
        }

    def reset(self) -> None:
        self.log_ratio, self.frames, self.last_ratio = 0.0, 0, math.nan


def innovation_nis(
    h: object,
    x: np.ndarray,
    P: np.ndarray,
    m: np.ndarray,
    Sigma: np.ndarray,
    z: np.ndarray,
    Q: np.ndarray,
) -> np.ndarray:
    """Per-measurement NIS νᵀ S⁻¹ ν, S = H_x P H_xᵀ + H_m Σ H_mᵀ + Q, at the pose prior (x, P).

    ``h``: the filter's measurement function (x (B, dx), m (B, dm)) -> (z, H_x, H_m);
    ``m``/``Sigma``: (B, dm)/(B, dm, dm) the re-observed landmarks; ``z``/``Q``: (B, dz)/(B, dz, dz).
    """
    B = m.shape[0]
    zhat, Hx, Hm = h(np.broadcast_to(x, (B, x.shape[0])), m)  # type: ignore[operator]
    S = Hx @ P @ np.swapaxes(Hx, 1, 2) + Hm @ Sigma @ np.swapaxes(Hm, 1, 2) + Q
    nu = z - zhat
    try:
        sol = np.linalg.solve(S, nu[..., None])[..., 0]
    except np.linalg.LinAlgError:
        return np.full(B, np.nan)
    return np.einsum("bi,bi->b", nu, sol)


class ReportedCovariance:
    """The covariance robotd reports for each pose (``slam.covariance``): the pipeline's and the
    simulation studies' one implementation.

    ``mode``: "consistent" (monitor + anchors) or "filter" (the filter's own, unchanged);
    ``anchored``: use :class:`AnchoredCovariance` (the particle filters; the EKF's joint
    covariance carries the map already); ``model``/``q_px``: the filter's measurement model and,
    for the pixel model, its constant pixel covariance.
    """

    def __init__(
        self, mode: str, anchored: bool, model: MeasurementModel, q_px: np.ndarray | None, drift_per_m: float = 0.0
    ) -> None:
        if mode not in ("consistent", "filter"):
            raise ValueError(f"covariance mode: expected consistent or filter, got {mode!r}")
        self.mode = mode
        self.model = model
        self.q_px = q_px
        self.monitor = ConsistencyMonitor()
        self.anchors = AnchoredCovariance(drift_per_m=drift_per_m) if anchored else None
        # a filter whose own covariance carries the map (the EKF) still misses what no pixel model
        # holds: the drift term, from the path explored as the anchors count it (their covariances
        # all zero, so the term is all they add)
        self.path = AnchoredCovariance(drift_per_m=drift_per_m) if not anchored and drift_per_m > 0 else None
        self._extra = np.zeros((6, 6))  # added to the next report (:meth:`add_uncertainty`)

    @property
    def enabled(self) -> bool:
        return self.mode == "consistent"

    def reset(self) -> None:
        """A map loaded from disk is the world: its landmarks anchor at zero covariance."""
        for a in (self.anchors, self.path):
            if a is not None:
                a.reset()
        self.monitor.reset()

    def observe(self, prior: PoseEstimate, obs: Observations, landmarks: LandmarkMap) -> None:
        """Before the update: the NIS of the frame's re-observations at the predicted pose ``prior``
        against ``landmarks`` (the map before this frame), for the monitor."""
        from robotd.slam.common import split_observations

        if not self.enabled:
            return
        mon, dim = self.monitor, 3 if self.model.dx == 6 else 2
        ident = np.flatnonzero(~obs.is_new)
        if ident.size < mon.min_measurements or not landmarks.n:
            return
        order = np.argsort(landmarks.ids, kind="stable")
        pos = np.minimum(np.searchsorted(landmarks.ids[order], obs.ids[ident]), order.size - 1)
        found = landmarks.ids[order[pos]] == obs.ids[ident]
        ident, li = ident[found], order[pos[found]]
        if ident.size < mon.min_measurements:
            return
        z, Q, _, _ = split_observations(obs.subset(ident), dim, self.model, self.q_px)
        if dim == 3:
            x, P = np.r_[prior.xyz_W_m, prior.rpy_rad], prior.cov
            m, Sigma = landmarks.xyz_W_m[li], landmarks.cov_W[li]
        else:
            k = [0, 1, 5]
            x, P = np.r_[prior.xyz_W_m[:2], prior.rpy_rad[2]], prior.cov[np.ix_(k, k)]
            m, Sigma = landmarks.xyz_W_m[li, :2], landmarks.cov_W[li, :2, :2]
        if np.all(np.isfinite(P)) and np.all(np.isfinite(x)):
            mon.observe(innovation_nis(self.model.h, x, P, m, Sigma, z, Q), self.model.dz)

    def forget(self, ids: np.ndarray) -> None:
        """These landmarks left the map: their anchors go too (:meth:`AnchoredCovariance.forget`). The
        pipeline subscribes the reported covariance to the landmark registry (robotd.slam.landmarks),
        which calls this."""
        for a in (self.anchors, self.path):
            if a is not None:
                a.forget(ids)

    def add_increment_uncertainty(self, cov_inc: np.ndarray, pose: PoseEstimate) -> None:
        """:meth:`add_uncertainty` for an error of a motion increment, ``cov_inc`` (6, 6) over (dp
        in the robot frame R(t−1), rotation vector), ``pose`` the estimate at t−1: turned into the
        world's (x, y, z) and the pose's (roll, pitch, yaw)."""
        R_w = pose.T_world_robot[:3, :3]
        G = np.zeros((6, 6))
        G[:3, :3] = R_w
        G[3:, 3:] = np.linalg.pinv(euler_error_jacobian(pose.rpy_rad)) @ R_w
        self.add_uncertainty(G @ np.asarray(cov_inc, dtype=float) @ G.T)

    def add_uncertainty(self, cov6: np.ndarray) -> None:
        """An error the filter was not told of, over (x, y, z, roll, pitch, yaw) (6, 6): the motion
        across a stall that nothing measured (the pipeline moves the filter by its best guess and
        says how far off that guess may be). It is added to the next reported covariance, and
        through the anchors to every pose fixed against the landmarks mapped after it."""
        self._extra = self._extra + np.asarray(cov6, dtype=float)

    def report(self, pose: PoseEstimate, obs: Observations, spread_kept: float = 0.0) -> PoseEstimate:
        """After the update: ``pose`` with the reported covariance; ``obs`` the frame's fused
        observations (identified ones re-observed map landmarks, new ones were created);
        ``spread_kept``: the estimator's ``spread_kept()`` (:meth:`AnchoredCovariance.step`)."""
        extra, self._extra = self._extra, np.zeros((6, 6))
        if not self.enabled:
            if not np.any(extra):
                return pose  # (a PoseEstimate's mean and covariance are finite: robotd.core.msgs refuses others)
            return PoseEstimate(pose.t_ns, pose.xyz_W_m, pose.rpy_rad, pose.cov + extra, pose.neff, pose.n_particles)
        cov_fix = pose.cov * self.monitor.scale
        cov = cov_fix + extra
        if self.anchors is not None:
            used, new = obs.ids[~obs.is_new], obs.ids[obs.is_new]
            cov = self.anchors.step(pose.xyz_W_m, pose.rpy_rad, cov_fix, used, new, spread_kept, extra)
            if not np.all(np.isfinite(cov)):
                # never let one bad value live on in the anchors (every later covariance would be
                # non-finite, which a PoseEstimate refuses: every step would fail): start them again
                self.anchors.reset()
                cov = cov_fix + extra
        if self.path is not None:
            zero = np.zeros((6, 6))
            cov = cov + self.path.step(pose.xyz_W_m, pose.rpy_rad, zero, obs.ids[~obs.is_new], obs.ids[obs.is_new])
        return PoseEstimate(pose.t_ns, pose.xyz_W_m, pose.rpy_rad, cov, pose.neff, pose.n_particles)

    def health(self) -> dict[str, object]:
        """The health topic's ``consistency`` section."""
        h: dict[str, object] = {"mode": self.mode, **self.monitor.health()}
        if self.anchors is not None:
            h["anchored_landmarks"] = self.anchors.n_anchored
        track = self.anchors or self.path
        if track is not None:
            h["explored_m"] = round(track.explored_m, 2)
            h["drift_per_m"] = track.drift_per_m
        return h


def blur_share(drot_rad: np.ndarray, dt_s: float, exposure_s: float, f_px: float, blur_px: float) -> float:
    """How much of a visual motion's own covariance its images' blur adds, (b / ``blur_px``)²,
    b = |rotation| / ``dt_s`` × ``exposure_s`` × ``f_px`` the streak [px] a rotation at that rate
    draws in one exposure; 0 when there is no exposure, no interval or ``blur_px`` is 0 (off).

    Why: a blurred corner is found somewhere along its streak, and at a frame's rate every streak
    of the frame runs the same way, so the error is common to every point and looks like motion:
    the PnP's covariance, built on independent pixel noise and shrinking with the number of
    points, does not hold it. Measured on the simulated hand-held camera (shaken, exposed): the
    motion's rotation NEES has a median of 1.0 under 2 px of streak, 2.0 at 2-4 px, 3.6 at 4-6,
    11 at 6-8, 15 at 8-12, 24 at 12-20 px; 1 + (b / 3 px)² takes it back to about 1
    (docs/slam.md "Reported covariance", motion blur)."""
    if not (blur_px > 0.0 and exposure_s > 0.0 and dt_s > 0.0 and f_px > 0.0):
        return 0.0
    b = streak_px(float(np.linalg.norm(np.asarray(drot_rad, dtype=float))) / dt_s, exposure_s, f_px)
    return (b / blur_px) ** 2
