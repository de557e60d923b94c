"""SLAM pose -> MAVLink external-navigation field values (pure; no pymavlink here).

Implements interfaces.md §1.2–§1.6: ``ODOMETRY`` with ``frame_id = MAV_FRAME_LOCAL_FRD`` (20) and
``child_frame_id = MAV_FRAME_BODY_FRD`` (12). robotd's world frame is LOCAL_FRD and its robot frame
is BODY_FRD (algorithms.md §1.2), so position and attitude pass through without axis changes:
``q`` (w, x, y, z) is the quaternion of R(rpy) = Rz(yaw) Ry(pitch) Rx(roll).

Also here, as pure functions or thin state over them:

- the 21-element upper-triangle covariance (row-major; diagonal at 0, 6, 11, 15, 18, 20) of the
  reported pose covariance (robotd.slam.uncertainty), through the same (identity) frame transform
  as the pose, with floors on the diagonal only so it is never zero (ArduPilot PR 8730),
  NaN-first for "unknown";
- ``quality`` from the RANSAC inlier count, N_eff/N for FastSLAM, the reported position sigma and
  the consistency monitor's state (−1 when tracking is lost);
- the ``reset_counter`` policy (b) of interfaces.md §1.5: bump on relocalisation, map load,
  filter restart, and whenever the pose moves more than the motion explains (0.1 m beyond the
  prediction by default, as in the reference T265 bridge);
- the TIMESYNC offset filter (mavlink.io timesync service: offset = tc1 − (t0 + t1)/2, keep the
  shortest round trips).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from robotd.geometry import euler_to_quat, euler_to_R, wrap_angle
from robotd.msgs import PoseEstimate

# MAVLink enum values used here, so this module needs no pymavlink (tests check them against it).
MAV_FRAME_LOCAL_FRD = 20
MAV_FRAME_BODY_FRD = 12
MAV_ESTIMATOR_TYPE_VIO = 3

# Upper-triangle (row-major) index of element (i, j), i <= j, of a 6x6 matrix.
TRIU_ROWS, TRIU_COLS = np.triu_indices(6)
DIAG_INDEX = (0, 6, 11, 15, 18, 20)
NAN21: tuple[float, ...] = (math.nan,) + (0.0,) * 20


def pose_covariance_local_frd(cov: np.ndarray) -> np.ndarray:
    """The (6, 6) pose covariance over (x, y, z, roll, pitch, yaw) in robotd's frames -> MAVLink's.

    ODOMETRY's ``pose_covariance`` is over (x, y, z) in ``frame_id`` (LOCAL_FRD) and the
    roll, pitch, yaw of ``q`` (body FRD -> LOCAL_FRD, ZYX). :func:`odometry_fields` sends the pose
    with the identity transform (world = LOCAL_FRD, robot = BODY_FRD, R = Rz Ry Rx on both sides),
    so its Jacobian is the identity and the covariance passes through unchanged: no rotation into
    the body frame (the pose block is not in the child frame) and no change of angle order. This
    is the one place that would change if the pose's frames ever did (tests/drivers check it
    against pymavlink's own quaternion -> Euler over loopback UDP).
    """
    c = np.asarray(cov, dtype=float)
    if c.shape != (6, 6):
        raise ValueError(f"covariance: expected shape (6, 6), got {c.shape}")
    return c.copy()


def cov6_to_upper21(cov: np.ndarray, floor_diag: np.ndarray | None = None) -> list[float]:
    """(6, 6) covariance -> the 21 MAVLink values, upper triangle, row-major.

    The matrix is symmetrised (averaging the triangles) and its diagonal raised to ``floor_diag``
    (6,) so the message never carries a zero or negative variance. A non-finite input gives
    "unknown": first element NaN.
    """
    c = np.asarray(cov, dtype=float)
    if c.shape != (6, 6):
        raise ValueError(f"covariance: expected shape (6, 6), got {c.shape}")
    if not np.all(np.isfinite(c)):
        return list(NAN21)
    c = 0.5 * (c + c.T)
    if floor_diag is not None:
        d = np.maximum(np.diag(c), floor_diag)
        np.fill_diagonal(c, d)
    return [float(v) for v in c[TRIU_ROWS, TRIU_COLS]]


def upper21_to_cov6(v: list[float] | np.ndarray) -> np.ndarray:
    """Inverse of :func:`cov6_to_upper21` (for tests and the mock autopilot)."""
    c = np.zeros((6, 6))
    c[TRIU_ROWS, TRIU_COLS] = np.asarray(v, dtype=float)
    return c + np.triu(c, 1).T


@dataclass(frozen=True, slots=True)
class CovarianceFloors:
    """Smallest variances sent: position [m²] and attitude [rad²] (1 mm and 0.06° by default).

    They only keep zeros out of the message (an old EKF3 fault came from posErr = 0, ArduPilot PR
    8730): the reported covariance is sent as it is wherever it is above them. The autopilots
    floor the errors they derive at their own parameters (VISO_POS_M_NSE / VISO_YAW_M_NSE,
    EKF2_EVP_NOISE / EKF2_EVA_NOISE; docs/mavlink.md §8), far above these.
    """

    pos_m2: float = 1e-6
    ang_rad2: float = 1e-6

    def diag(self) -> np.ndarray:
        return np.array([self.pos_m2] * 3 + [self.ang_rad2] * 3)


@dataclass(frozen=True, slots=True)
class OdometryFields:
    """Field values of MAVLink ODOMETRY (331), in the order of ``odometry_send``."""

    time_usec: int
    frame_id: int
    child_frame_id: int
    x: float
    y: float
    z: float
    q: tuple[float, float, float, float]  # w, x, y, z: body -> local
    vx: float
    vy: float
    vz: float
    rollspeed: float
    pitchspeed: float
    yawspeed: float
    pose_covariance: list[float]
    velocity_covariance: list[float]
    reset_counter: int
    estimator_type: int
    quality: int

    def as_args(self) -> tuple:
        return (
            self.time_usec,
            self.frame_id,
            self.child_frame_id,
            self.x,
            self.y,
            self.z,
            list(self.q),
            self.vx,
            self.vy,
            self.vz,
            self.rollspeed,
            self.pitchspeed,
            self.yawspeed,
            self.pose_covariance,
            self.velocity_covariance,
            self.reset_counter,
            self.estimator_type,
            self.quality,
        )


def odometry_fields(
    pose: PoseEstimate,
    quality: int,
    reset_counter: int,
    vel_R_mps: np.ndarray | None = None,
    floors: CovarianceFloors = CovarianceFloors(),
) -> OdometryFields:
    """Build ODOMETRY from a pose (LOCAL_FRD) and an optional body-frame (FRD) velocity (3,) [m/s].

    ``time_usec`` is the capture time of the frame (host monotonic clock, µs): monotonic and from
    one clock, as ArduPilot's jitter filter needs. Body rates are NaN (unknown: PX4 uses them only
    when all three are finite). The velocity covariance is unknown (NaN first), so the autopilot
    applies its own noise parameter (VISO_VEL_M_NSE / EKF2_EVV_NOISE).
    """
    q = euler_to_quat(np.asarray(pose.rpy_rad, dtype=float))
    q = q / np.linalg.norm(q)
    v = np.full(3, math.nan) if vel_R_mps is None else np.asarray(vel_R_mps, dtype=float)
    return OdometryFields(
        time_usec=int(pose.t_ns) // 1000,
        frame_id=MAV_FRAME_LOCAL_FRD,
        child_frame_id=MAV_FRAME_BODY_FRD,
        x=float(pose.xyz_W_m[0]),
        y=float(pose.xyz_W_m[1]),
        z=float(pose.xyz_W_m[2]),
        q=(float(q[0]), float(q[1]), float(q[2]), float(q[3])),
        vx=float(v[0]),
        vy=float(v[1]),
        vz=float(v[2]),
        rollspeed=math.nan,
        pitchspeed=math.nan,
        yawspeed=math.nan,
        pose_covariance=cov6_to_upper21(pose_covariance_local_frd(pose.cov), floors.diag()),
        velocity_covariance=list(NAN21),
        reset_counter=int(reset_counter) & 0xFF,
        estimator_type=MAV_ESTIMATOR_TYPE_VIO,
        quality=clamp_quality(quality),
    )


@dataclass(frozen=True, slots=True)
class VisionPositionFields:
    """VISION_POSITION_ESTIMATE (102) values: the MAVLink-1 / old-firmware fallback."""

    usec: int
    x: float
    y: float
    z: float
    roll: float
    pitch: float
    yaw: float
    covariance: list[float]
    reset_counter: int

    def as_args(self) -> tuple:
        return (
            self.usec,
            self.x,
            self.y,
            self.z,
            self.roll,
            self.pitch,
            self.yaw,
            self.covariance,
            self.reset_counter,
        )


def vision_position_fields(
    pose: PoseEstimate, reset_counter: int, floors: CovarianceFloors = CovarianceFloors()
) -> VisionPositionFields:
    """Same pose as :func:`odometry_fields`, as Euler angles (roll, pitch, yaw; ZYX) in LOCAL_FRD."""
    r = np.asarray(pose.rpy_rad, dtype=float)
    return VisionPositionFields(
        usec=int(pose.t_ns) // 1000,
        x=float(pose.xyz_W_m[0]),
        y=float(pose.xyz_W_m[1]),
        z=float(pose.xyz_W_m[2]),
        roll=float(r[0]),
        pitch=float(r[1]),
        yaw=float(wrap_angle(r[2])),
        covariance=cov6_to_upper21(pose_covariance_local_frd(pose.cov), floors.diag()),
        reset_counter=int(reset_counter) & 0xFF,
    )


# ---------------------------------------------------------------------------------------------
# quality


def clamp_quality(q: int) -> int:
    """MAVLink quality: −1 failed, 0 unknown, 1 worst … 100 best."""
    return -1 if q < 0 else min(100, int(q))


def position_sigma_m(cov: np.ndarray) -> float:
    """√(trace) of the position block of a (6, 6) pose covariance [m] (health's ``pose_sigma_m``);
    inf when it is not finite or negative."""
    tr = float(np.trace(np.asarray(cov, dtype=float)[:3, :3]))
    return math.sqrt(tr) if math.isfinite(tr) and tr >= 0 else math.inf


def quality_from(
    tracking: bool,
    n_inliers: int,
    neff: float = math.nan,
    n_particles: int = 0,
    min_inliers: int = 6,
    good_inliers: int = 60,
    *,
    pos_sigma_m: float | None = None,
    good_sigma_m: float = 0.2,
    consistency_state: str = "unknown",
    nis_ratio: float = math.nan,
) -> int:
    """Quality 1–100 of a tracked pose, −1 when tracking is lost (docs/mavlink.md §5).

    quality = 1 + 99 · q_in · q_pf · q_σ · q_nis, each term in [0, 1]:

    - q_in: the RANSAC inliers, rising linearly from ``min_inliers`` (→ 0) to ``good_inliers`` (→ 1);
    - q_pf: N_eff/N (1 for the EKF, where ``neff`` is NaN);
    - q_σ: how the reported position sigma ``pos_sigma_m`` (√trace of the position block, see
      :func:`position_sigma_m`) compares with ``good_sigma_m``: min(1, good / σ), so 1 up to the
      good sigma and 0.1 at ten times it; 0 for a non-finite sigma; 1 when not given;
    - q_nis: 1 unless the consistency monitor says ``overconfident`` (its NIS ratio above 2); then
      1 / ratio: the covariance was already scaled up by the ratio, but a noise model that far off
      makes the covariance itself less trustworthy.

    A tracked-but-poor pose is 1 (worst), never 0 (which means "unknown").
    """
    if not tracking:
        return -1
    span = max(1, good_inliers - min_inliers)
    q_in = min(1.0, max(0.0, (n_inliers - min_inliers) / span))
    q_pf = 1.0
    if n_particles > 0 and math.isfinite(neff):
        q_pf = min(1.0, max(0.0, neff / n_particles))
    q_sigma = 1.0
    if pos_sigma_m is not None:
        s = float(pos_sigma_m)
        q_sigma = min(1.0, good_sigma_m / s) if math.isfinite(s) and s > 0 else (1.0 if s == 0 else 0.0)
    q_nis = 1.0
    if consistency_state == "overconfident":
        r = float(nis_ratio)
        q_nis = 1.0 / r if math.isfinite(r) and r > 1.0 else 0.5
    return round(1 + 99 * q_in * q_pf * q_sigma * q_nis)


# ---------------------------------------------------------------------------------------------
# reset_counter policy


class ResetEvent:
    RELOCALISATION = "relocalisation"
    MAP_LOAD = "map_load"
    FILTER_RESTART = "filter_restart"
    LOOP_CLOSURE = "loop_closure"
    STALL = "stall"  # frames stopped for longer than a stall and no odometry covered the gap


@dataclass
class ResetCounterPolicy:
    """Policy (b) of interfaces.md §1.5: publish the map-frame pose, bump on discontinuities.

    ``update(pose, event)`` returns the counter to send with ``pose``. It bumps (mod 256) when an
    ``event`` is given (relocalisation, map load, filter restart, loop closure) and when the
    position differs from the prediction by more than ``jump_m`` (default 0.1 m, the reference
    T265 bridge's step) or the yaw by more than ``jump_yaw_rad``. The prediction is
    ``predicted_xyz`` when the caller has one (e.g. odometry integrated since the last pose),
    otherwise a constant-velocity extrapolation of the last two published poses.
    """

    jump_m: float = 0.1
    jump_yaw_rad: float = 0.2
    counter: int = 0
    bumps: int = 0
    _hist: deque[PoseEstimate] = field(default_factory=lambda: deque(maxlen=2))

    def predict(self, t_ns: int) -> tuple[np.ndarray, float] | None:
        """Constant-velocity prediction (xyz (3,), yaw) at ``t_ns`` from the last two poses."""
        if not self._hist:
            return None
        last = self._hist[-1]
        if len(self._hist) < 2:
            return np.asarray(last.xyz_W_m, float), float(last.rpy_rad[2])
        prev = self._hist[0]
        dt = (last.t_ns - prev.t_ns) * 1e-9
        if dt <= 0:
            return np.asarray(last.xyz_W_m, float), float(last.rpy_rad[2])
        k = (t_ns - last.t_ns) * 1e-9 / dt
        xyz = last.xyz_W_m + k * (last.xyz_W_m - prev.xyz_W_m)
        yaw = float(last.rpy_rad[2] + k * wrap_angle(last.rpy_rad[2] - prev.rpy_rad[2]))
        return np.asarray(xyz, float), yaw

    def update(self, pose: PoseEstimate, event: str | None = None, predicted_xyz: np.ndarray | None = None) -> int:
        jump = False
        if event is not None:
            jump = True
        else:
            pred = self.predict(pose.t_ns)
            if pred is not None:
                xyz_pred = pred[0] if predicted_xyz is None else np.asarray(predicted_xyz, float)
                d = float(np.linalg.norm(pose.xyz_W_m - xyz_pred))
                dyaw = abs(float(wrap_angle(pose.rpy_rad[2] - pred[1])))
                jump = d > self.jump_m or dyaw > self.jump_yaw_rad
        if jump:
            self.counter = (self.counter + 1) & 0xFF
            self.bumps += 1
            # a new segment: do not extrapolate across the discontinuity
            self._hist.clear()
        self._hist.append(pose)
        return self.counter


# ---------------------------------------------------------------------------------------------
# body-frame velocity from successive poses


@dataclass
class VelocityFromPoses:
    """Body-frame (FRD) velocity [m/s] by differencing successive published poses.

    v_W = (p_k − p_{k−1}) / Δt, v_R = R(rpy_k)ᵀ v_W. ArduPilot fuses ODOMETRY's velocity
    (GCS_MAVLINK::handle_odometry rotates it with ``q``) and has no NaN check on that path, so a
    finite value is sent: on the first pose it is zero (robotd starts at rest) and right after a
    reset the last good value is held, since differencing across a jump is meaningless.
    """

    max_dt_s: float = 0.5
    _last: PoseEstimate | None = None
    _last_reset: int | None = None
    _vel: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def update(self, pose: PoseEstimate, reset_counter: int) -> np.ndarray:
        last = self._last
        if last is not None and reset_counter == self._last_reset:
            dt = (pose.t_ns - last.t_ns) * 1e-9
            if 0 < dt <= self.max_dt_s:
                v_W = (np.asarray(pose.xyz_W_m) - np.asarray(last.xyz_W_m)) / dt
                self._vel = euler_to_R(np.asarray(pose.rpy_rad, float)).T @ v_W
        self._last = pose
        self._last_reset = reset_counter
        return self._vel.copy()


# ---------------------------------------------------------------------------------------------
# TIMESYNC


@dataclass
class TimesyncFilter:
    """Offset between the autopilot's clock and ours from our own TIMESYNC requests [ns].

    A request leaves at host time t0 (its ``ts1``), the reply (``tc1`` = autopilot time) arrives
    at t1. With symmetric delays, offset = tc1 − (t0 + t1)/2 (mavlink.io timesync service); the
    error is at most half the round trip, so of the last ``window`` samples the one with the
    shortest round trip is used. Samples with a round trip above ``max_rtt_ns`` are rejected.
    ``autopilot_to_host(t_ap_ns) = t_ap_ns − offset``.
    """

    window: int = 32
    max_rtt_ns: int = 200_000_000
    _samples: deque[tuple[int, int]] = field(default_factory=deque)  # (rtt_ns, offset_ns)
    accepted: int = 0
    rejected: int = 0

    def add(self, t0_ns: int, t1_ns: int, tc1_ns: int) -> bool:
        rtt = t1_ns - t0_ns
        if rtt < 0 or rtt > self.max_rtt_ns or tc1_ns <= 0:
            self.rejected += 1
            return False
        self._samples.append((rtt, tc1_ns - (t0_ns + t1_ns) // 2))
        while len(self._samples) > self.window:
            self._samples.popleft()
        self.accepted += 1
        return True

    def reset(self) -> None:
        """Forget the samples (the autopilot rebooted: its clock restarted)."""
        self._samples.clear()

    @property
    def offset_ns(self) -> int | None:
        if not self._samples:
            return None
        return min(self._samples)[1]

    @property
    def rtt_ns(self) -> int | None:
        return min(self._samples)[0] if self._samples else None

    def autopilot_to_host(self, t_ap_ns: int) -> int | None:
        off = self.offset_ns
        return None if off is None else t_ap_ns - off
