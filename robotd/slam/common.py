"""Helpers shared by the filters (EKF SLAM, FastSLAM): input checks, the control and its
covariance from a motion increment, the planar <-> 3D embeddings of poses and landmarks, the
saved-state header, and the two public update entry points.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from typing import Any

import numpy as np

from robotd.core.errors import InputError, MapMismatchError, PersistenceError
from robotd.core.msgs import MotionIncrement, Observations, UpdateReport
from robotd.core.statecheck import ANGLE_LIMIT_RAD, POSITION_LIMIT_M, T_NS_LIMIT, StateTable
from robotd.core.statecheck import check_finite as check_saved_finite
from robotd.core.stereo import project
from robotd.slam._book import LandmarkBook
from robotd.slam.models import (
    CARTESIAN_2D,
    CARTESIAN_3D,
    COS_PITCH_MIN,
    RANGE_BEARING_2D,
    MeasurementModel,
    motion3d_noise,
    odometry2d_noise,
    stereo_pixel_model,
)
from robotd.slam.params import SlamParams

NO_IDS = np.zeros(0, np.int64)  # an empty id list (read-only: shared)
NO_IDS.flags.writeable = False


def check_finite(name: str, *arrays: Any) -> None:
    """Raise InputError when any input value is NaN/inf (before the filter state is touched)."""
    for a in arrays:
        arr = np.asarray(a, dtype=float)
        if not np.all(np.isfinite(arr)):
            raise InputError(f"{name}: expected finite values, got {int(np.sum(~np.isfinite(arr)))} non-finite")


def check_reset_pose(x: Any, cov: Any, dx: int) -> tuple[np.ndarray, np.ndarray | None]:
    """Validate a relocalisation pose ``x`` (dx,) and its covariance ``cov`` (dx, dx) symmetric
    positive semi-definite, or None; raises InputError before any filter state is touched."""
    x = np.asarray(x, dtype=float)
    if x.shape != (dx,):
        raise InputError(f"reset_pose: expected a pose of shape ({dx},), got {x.shape}")
    check_finite("reset_pose x", x)
    if cov is None:
        return x, None
    cov = np.asarray(cov, dtype=float)
    if cov.shape != (dx, dx):
        raise InputError(f"reset_pose: expected a covariance of shape ({dx}, {dx}), got {cov.shape}")
    check_finite("reset_pose cov", cov)
    cov = 0.5 * (cov + cov.T)
    ev = np.linalg.eigvalsh(cov)
    if ev.min() < -1e-12 * max(1.0, float(np.abs(cov).max())):
        raise InputError(f"reset_pose: expected a positive semi-definite covariance, got eigenvalues {ev}")
    return x, cov


def control_from_increment(inc: MotionIncrement, params: SlamParams) -> tuple[np.ndarray, np.ndarray]:
    """The control u and its covariance M_t in control space for ``params.dim``.

    2D: u = (dp[0], dp[1], drot[2]) with the matching 3×3 block of ``inc.cov``; 3D: u = (dp, drot)
    with the 6×6 ``inc.cov``. ``motion_cov_source`` picks message vs model (module docstring).
    """
    check_finite("MotionIncrement", inc.dp_R_m, inc.drot_R_rad, inc.cov)
    if params.dim == 2:
        u = np.array([inc.dp_R_m[0], inc.dp_R_m[1], inc.drot_R_rad[2]], dtype=float)
        idx = [0, 1, 5]
        M_msg = np.asarray(inc.cov, dtype=float)[np.ix_(idx, idx)]
    else:
        u = np.concatenate([inc.dp_R_m, inc.drot_R_rad]).astype(float)
        M_msg = np.asarray(inc.cov, dtype=float)
    src = params.motion_cov_source
    if src == "message" or (src == "auto" and np.any(M_msg != 0.0)):
        M = 0.5 * (M_msg + M_msg.T)
        if np.any(np.linalg.eigvalsh(M) < -1e-12 * max(1.0, float(np.abs(M).max()))):
            raise InputError(
                f"MotionIncrement.cov: expected positive semi-definite, got eigenvalues {np.linalg.eigvalsh(M)}"
            )
        return u, M
    if params.dim == 2:
        return u, odometry2d_noise(u, params.odo2d_a)
    return u, motion3d_noise(
        u,
        params.motion3d_sigma_dp_m,
        params.motion3d_dp_rel,
        params.motion3d_sigma_rot_rad,
        params.motion3d_rot_per_m,
        params.motion3d_rot_rel,
    )


def model_cov6(inc: MotionIncrement, params: SlamParams) -> np.ndarray:
    """The motion model's covariance (6, 6) over (dp, drot) for ``inc``: what the filter takes
    for an increment that states no covariance (:func:`control_from_increment`, "auto"). 3D: the
    model of §6.3; 2D: §6.2's (x, y, yaw) block, the other axes from §6.3 (a 2D filter ignores
    them)."""
    u = np.concatenate([inc.dp_R_m, inc.drot_R_rad]).astype(float)
    M = motion3d_noise(
        u,
        params.motion3d_sigma_dp_m,
        params.motion3d_dp_rel,
        params.motion3d_sigma_rot_rad,
        params.motion3d_rot_per_m,
        params.motion3d_rot_rel,
    )
    if params.dim == 2:
        idx = [0, 1, 5]
        M[np.ix_(idx, idx)] = odometry2d_noise(u[idx], params.odo2d_a)
    return M


def measurement_model(params: SlamParams) -> MeasurementModel:
    """The filter's measurement model for ``params.measurement`` and ``params.dim``."""
    if params.measurement == "pixel":
        return stereo_pixel_model(params.dim, *params.stereo_intrinsics)
    return CARTESIAN_2D if params.dim == 2 else CARTESIAN_3D


def pixel_noise(params: SlamParams) -> np.ndarray:
    """The pixel model's measurement covariance (dz, dz): diag(σx², σx², σy²), 2D the columns' block."""
    sx, sy = params.pixel_sigma_px
    return np.diag([sx * sx, sx * sx, sy * sy])[: params.dim, : params.dim]


def split_observations(
    obs: Observations, dim: int, model: MeasurementModel | None = None, Q_px: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(z (N, dz), Q (N, dz, dz), ids (N,) int64, is_new (N,) bool) for a ``dim``-D filter.

    Cartesian (``model`` None or without intrinsics, docs/math.md §3.3): z = the first ``dim`` coordinates of
    the points, Q the matching block of their covariances. Pixel model: z = ``obs.uv_px`` (the
    projection of ``xyz_R_m`` when the message has no pixels), 2D its two columns, Q = ``Q_px``
    (dz, dz) for every row. Raises InputError on non-finite values, duplicate ids within the frame,
    or (pixel model) points without a positive disparity.
    """
    check_finite("Observations", obs.xyz_R_m, obs.cov_R)
    ids = np.asarray(obs.ids).astype(np.int64)
    if np.unique(ids).size != ids.size:
        raise InputError(
            f"Observations.ids: expected unique ids per frame, got {ids.size - np.unique(ids).size} duplicates"
        )
    is_new = np.asarray(obs.is_new, dtype=bool)
    if model is None or model.intrinsics is None:
        z = np.ascontiguousarray(obs.xyz_R_m[:, :dim], dtype=float)
        Q = np.ascontiguousarray(obs.cov_R[:, :dim, :dim], dtype=float)
        return z, Q, ids, is_new
    assert Q_px is not None
    if obs.uv_px is not None:
        uv = np.asarray(obs.uv_px, dtype=float)
        check_finite("Observations.uv_px", uv)
    else:
        if np.any(obs.xyz_R_m[:, 0] <= 0):
            raise InputError(
                f"Observations: the pixel model needs points in front of the rig (X > 0), got "
                f"{int(np.sum(obs.xyz_R_m[:, 0] <= 0))} with X <= 0"
            )
        f, px, py, b = model.intrinsics
        uv = np.stack(project(obs.xyz_R_m, f, px, py, b), -1)
    if np.any(uv[:, 0] - uv[:, 1] <= 0):
        raise InputError(
            f"Observations.uv_px: expected x_left > x_right, got {int(np.sum(uv[:, 0] <= uv[:, 1]))} rows without"
        )
    z = np.ascontiguousarray(uv[:, : model.dz])
    Q = np.ascontiguousarray(np.broadcast_to(Q_px, (ids.size, model.dz, model.dz)))
    return z, Q, ids, is_new


FILTER_CODE = {"ekf": 0, "fastslam1": 1, "fastslam2": 2}


def pose_cov_6x6(P: np.ndarray, dim: int, floor: float) -> np.ndarray:
    """Embed a (3, 3) planar pose covariance over (x, y, yaw) into (6, 6) over (x, y, z, r, p, yaw)."""
    if dim == 3:
        return P.copy()
    C = np.diag([0.0, 0.0, floor, floor, floor, 0.0])
    idx = [0, 1, 5]
    C[np.ix_(idx, idx)] = P
    return C


def pose_to_xyz_rpy(x: np.ndarray, dim: int) -> tuple[np.ndarray, np.ndarray]:
    """(x, y, yaw) or 6-vector -> (xyz (3,), rpy (3,))."""
    if dim == 3:
        return x[:3].copy(), x[3:6].copy()
    return np.array([x[0], x[1], 0.0]), np.array([0.0, 0.0, x[2]])


def lm_to_3d(m: np.ndarray, C: np.ndarray, floor: float) -> tuple[np.ndarray, np.ndarray]:
    """Planar landmarks (M, 2), (M, 2, 2) -> (M, 3), (M, 3, 3) with z = 0 and a floor variance on z."""
    if m.shape[1] == 3:
        return m, C
    M = m.shape[0]
    m3 = np.zeros((M, 3))
    m3[:, :2] = m
    C3 = np.zeros((M, 3, 3))
    C3[:, :2, :2] = C
    C3[:, 2, 2] = floor
    return m3, C3


class UpdateEntryPoints(ABC):
    """The two public update entry points every filter shares; the filter implements ``_update``.

    ``update`` fuses a frame of stereo observations with the filter's own model (the triangulated
    points, or their pixels: ``SlamParams.measurement``); ``update_range_bearing`` (2D only, §7.2)
    converts and validates, then fuses with that model.
    """

    dim: int
    book: LandmarkBook
    model: MeasurementModel
    Q_px: np.ndarray | None  # the pixel model's (dz, dz) noise; None with the Cartesian model
    t_ns: int

    @abstractmethod
    def _update(
        self, z: np.ndarray, Q: np.ndarray, ids: np.ndarray, is_new: np.ndarray, model: MeasurementModel
    ) -> UpdateReport:
        """Each filter's measurement step on (N, dz) measurements with (N, dz, dz) covariances."""

    def update(self, obs: Observations) -> UpdateReport:
        """Fuse one frame: identified landmarks update, new ones are added, then bookkeeping."""
        z, Q, ids, is_new = split_observations(obs, self.dim, self.model, self.Q_px)
        self.book.check(ids, is_new)
        rep = self._update(z, Q, ids, is_new, self.model)
        self.t_ns = int(obs.t_ns)
        return rep

    def update_range_bearing(
        self,
        ids: np.ndarray,
        r: np.ndarray,
        beta: np.ndarray,
        R_rb: np.ndarray,
        is_new: np.ndarray | None = None,
        t_ns: int | None = None,
    ) -> UpdateReport:
        """Range–bearing update (§7.2), 2D only. ``is_new`` defaults to "id not yet in the map"."""
        z, Q, ids, is_new = range_bearing_inputs(self.dim, self.book, ids, r, beta, R_rb, is_new)
        rep = self._update(z, Q, ids, is_new, RANGE_BEARING_2D)
        if t_ns is not None:
            self.t_ns = int(t_ns)
        return rep


def gravity_inputs(dim: int, g_R: np.ndarray, g_W: np.ndarray, sigma_rad: float) -> tuple[np.ndarray, np.ndarray]:
    """Checked unit vectors (g_R, g_W) of a gravity update (3D filters only); InputError otherwise."""
    if dim != 3:
        raise InputError(f"update_gravity: expected a 3D filter, got dim={dim}")
    out = []
    for name, v in (("g_R", g_R), ("g_W", g_W)):
        v = np.asarray(v, dtype=float).reshape(-1)
        n = float(np.linalg.norm(v)) if v.shape == (3,) and np.all(np.isfinite(v)) else float("nan")
        if not 0.5 <= n <= 1.5:  # NaN fails too
            raise InputError(f"update_gravity: {name} must be a finite 3-vector of norm about 1, got {v}")
        out.append(v / n)
    if not (math.isfinite(sigma_rad) and 1e-6 <= sigma_rad <= 1.0):
        raise InputError(f"update_gravity: sigma_rad must be in [1e-6, 1] rad, got {sigma_rad}")
    return out[0], out[1]


def check_header(st: StateTable, name: str, dim: int) -> int:
    """The saved filter state's ``filter_code`` and ``dim`` against this filter (MapMismatchError
    when they differ: the map is valid, only not this filter's); returns its ``t_ns``."""
    code = st.integer("filter_code", 0, max(FILTER_CODE.values()))
    d = st.integer("dim", 2, 3)
    if code != FILTER_CODE[name] or d != dim:
        raise MapMismatchError(f"{st.where}: expected filter_code={FILTER_CODE[name]}, dim={dim}; got {code}, {d}")
    return st.integer("t_ns", 0, T_NS_LIMIT)


def check_saved_poses(name: str, x: np.ndarray, dim: int) -> None:
    """Saved poses (..., dx): finite, positions within POSITION_LIMIT_M, angles within
    ANGLE_LIMIT_RAD and, in 3D, pitch away from the ZYX singularity (motion3d refuses it)."""
    check_saved_finite(name, x)
    npos = 2 if dim == 2 else 3
    check_saved_finite(f"{name} (position)", x[..., :npos], POSITION_LIMIT_M)
    check_saved_finite(f"{name} (angles)", x[..., npos:], ANGLE_LIMIT_RAD)
    if dim == 3 and x.size and np.any(np.abs(np.cos(x[..., 4])) < COS_PITCH_MIN):
        raise PersistenceError(f"{name}: a pitch at the ZYX singularity (±90 deg)")


def range_bearing_inputs(
    dim: int,
    book: LandmarkBook,
    ids: np.ndarray,
    r: np.ndarray,
    beta: np.ndarray,
    R_rb: np.ndarray,
    is_new: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Validate range–bearing inputs; returns z (N, 2), Q (N, 2, 2), ids, is_new."""
    if dim != 2:
        raise InputError(f"update_range_bearing: expected a 2D filter, got dim={dim}")
    ids = np.asarray(ids).astype(np.int64).ravel()
    r = np.asarray(r, float).ravel()
    beta = np.asarray(beta, float).ravel()
    n = ids.size
    if r.shape != (n,) or beta.shape != (n,):
        raise InputError(f"update_range_bearing: expected r, beta of shape ({n},), got {r.shape}, {beta.shape}")
    Q = np.asarray(R_rb, float)
    if Q.shape == (2, 2):
        Q = np.broadcast_to(Q, (n, 2, 2)).copy()
    if Q.shape != (n, 2, 2):
        raise InputError(f"update_range_bearing: expected R_rb of shape (2, 2) or ({n}, 2, 2), got {Q.shape}")
    check_finite("update_range_bearing", r, beta, Q)
    if np.any(r <= 0):
        raise InputError(f"update_range_bearing: expected ranges > 0, got min {float(r.min())}")
    if np.unique(ids).size != n:
        raise InputError("update_range_bearing: expected unique ids per call")
    if is_new is None:
        is_new = np.array([int(i) not in book.id_to_slot for i in ids], bool)
    is_new = np.asarray(is_new, bool).ravel()
    book.check(ids, is_new)
    return np.stack([r, beta], -1), Q, ids, is_new
