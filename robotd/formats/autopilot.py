"""SLAM pose -> MAVLink external-navigation field values (pure; no pymavlink here).

Implements docs/interfaces.md §1.2–§1.6 (robotd's choices: docs/mavlink.md §2, §5): ``ODOMETRY``
with ``frame_id = MAV_FRAME_LOCAL_FRD`` (20) and ``child_frame_id = MAV_FRAME_BODY_FRD`` (12).
robotd's world frame is LOCAL_FRD and its robot frame is BODY_FRD (docs/math.md §1.2), so position
and attitude pass through without axis changes: ``q`` (w, x, y, z) is the quaternion of
R(rpy) = Rz(yaw) Ry(pitch) Rx(roll).

Also here, as pure functions or thin state over them:

- the 21-element upper-triangle covariance (row-major; diagonal at 0, 6, 11, 15, 18, 20) of the
  reported pose covariance (robotd.slam.uncertainty), through the same (identity) frame transform
  as the pose, with floors on the diagonal only so it is never zero (ArduPilot PR 8730),
  NaN-first for "unknown";
- ``quality`` from the RANSAC inlier count, N_eff/N for FastSLAM, the reported position sigma and
  the consistency monitor's state (−1 when tracking is lost);
- the ``reset_counter`` policy: the map-frame pose, the counter bumped on relocalisation, map
  load, filter restart, a stall nothing measured, and a jump no vehicle motion explains (the
  prediction keeps the vehicle's velocity across bumps); and the body velocity ODOMETRY carries;
- the TIMESYNC offset filter (mavlink.io timesync service: offset = tc1 − (t0 + t1)/2, keep the
  shortest round trips).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from robotd.core.geometry import R_to_euler, euler_to_quat, euler_to_R, so3_exp, so3_log, wrap_angle
from robotd.core.msgs import MotionIncrement, PoseEstimate

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
    ATTITUDE_RESET = "attitude_reset"  # an attitude no rover can have was reset to level


@dataclass
class ResetCounterPolicy:
    """Publish the map-frame pose; bump ``reset_counter`` only at a real discontinuity.

    ``update(pose, event, odometry)`` returns the counter (uint8, wraps) to send with ``pose``. It
    bumps when an ``event`` is given (relocalisation, map load, filter restart, loop closure, a
    stall nothing measured, an implausible attitude reset to level) and when the pose lands further
    from its prediction than a moving vehicle can explain. The prediction is, in this order:

    1. the vehicle's odometry integrated from the last pose to this one (``odometry``, a
       :class:`~robotd.core.msgs.MotionIncrement` whose interval is exactly last pose → this pose);
    2. the last pose moved on by the vehicle's twist (body velocity and body rates, fitted by least
       squares to the poses of the last ``window_s``), which is **kept across a bump**: the pose
       after a jump starts a new segment, but the motion goes on;
    3. nothing, before any twist is known (the first poses after start-up): no jump test.

    The tolerance grows with what the prediction cannot know: ``jump_m`` (0.1 m, the reference
    T265 bridge's step) + ``jump_frac`` of the predicted step (an error of the twist) +
    ½·``accel_max``·Δt² (a vehicle braking or accelerating since the last pose) + ``jump_sigmas``
    times the last pose's own reported σ (the autopilot fused it with that uncertainty, so a
    correction within it is inside EKF3's innovation gate: a pose handed over after a restart
    with σ 0.29 m converged 0.26 m in one step, in SITL); the same for yaw.
    A vehicle moving smoothly at 0.5–10 m/s, published at 5–30 Hz, never bumps; one jump bumps
    once (docs/mavlink.md §5). A pose more than ``max_gap_s`` after the last one starts a new
    segment too: the autopilot dead-reckoned across the gap, and robotd's pose after it may lie
    outside its innovation gate (EKF3 would refuse it, then fall back to DCM after 10 s).

    :attr:`velocity_R` is the body-frame (FRD) velocity [m/s] of the same twist: what ODOMETRY's
    vx, vy, vz carry. It is zero until two poses are seen (robotd starts at rest) and is kept,
    not zeroed, across a bump.
    """

    jump_m: float = 0.1
    jump_yaw_rad: float = 0.2
    jump_frac: float = 0.25
    accel_max_mps2: float = 4.0
    jump_sigmas: float = 2.0
    yaw_accel_max_radps2: float = 6.0
    window_s: float = 0.2
    max_gap_s: float = 1.0
    counter: int = 0
    bumps: int = 0
    last_reason: str = ""  # why the last bump happened (an event's name, or "jump 0.42 m")
    # the run's last bumps, (counter, reason), oldest first: the health topic's ``reset_bumps``
    history: deque[tuple[int, str]] = field(default_factory=lambda: deque(maxlen=16))
    _seg: deque[PoseEstimate] = field(default_factory=lambda: deque(maxlen=64))
    _v_R: np.ndarray = field(default_factory=lambda: np.zeros(3))
    _w_R: np.ndarray = field(default_factory=lambda: np.zeros(3))
    _twist_known: bool = False

    @property
    def velocity_R(self) -> np.ndarray:
        """Body-frame velocity [m/s] (3,) of the last fitted twist (a copy)."""
        return self._v_R.copy()

    @property
    def rates_R(self) -> np.ndarray:
        """Body rates [rad/s] (3,) of the last fitted twist (a copy)."""
        return self._w_R.copy()

    def predict(self, t_ns: int, odometry: MotionIncrement | None = None) -> tuple[np.ndarray, np.ndarray] | None:
        """Predicted (position (3,), R (3, 3)) at ``t_ns`` from the last pose, or None when no
        prediction can be made (no pose yet, or no twist and no odometry for the interval)."""
        if not self._seg:
            return None
        last = self._seg[-1]
        p0 = np.asarray(last.xyz_W_m, float)
        R0 = euler_to_R(np.asarray(last.rpy_rad, float))
        if odometry is not None and odometry.t0_ns == last.t_ns and odometry.t1_ns == t_ns:
            return p0 + R0 @ odometry.dp_R_m, R0 @ so3_exp(odometry.drot_R_rad)
        if not self._twist_known:
            return None
        dt = (t_ns - last.t_ns) * 1e-9
        R_mid = R0 @ so3_exp(self._w_R * dt / 2.0)
        return p0 + R_mid @ (self._v_R * dt), R0 @ so3_exp(self._w_R * dt)

    def update(self, pose: PoseEstimate, event: str | None = None, odometry: MotionIncrement | None = None) -> int:
        reason = event
        last = self._seg[-1] if self._seg else None
        if reason is None and last is not None and pose.t_ns > last.t_ns:
            gap_s = (pose.t_ns - last.t_ns) * 1e-9
            if gap_s > self.max_gap_s:
                # the autopilot dead-reckoned meanwhile and may have drifted further than its
                # innovation gate lets the next pose through: a new segment (it snaps to robotd)
                reason = f"gap {gap_s:.1f} s"
            else:
                pred = self.predict(pose.t_ns, odometry)
                if pred is not None:
                    reason = self._jump(last, pose, *pred)
        if reason is not None:
            self.counter = (self.counter + 1) & 0xFF
            self.bumps += 1
            self.last_reason = reason
            self.history.append((self.counter, reason))
            self._seg.clear()  # a new segment: never fit a twist across the discontinuity
        self._seg.append(pose)
        self._fit_twist()
        return self.counter

    def _jump(self, last: PoseEstimate, pose: PoseEstimate, p_pred: np.ndarray, R_pred: np.ndarray) -> str | None:
        """A description of the jump when ``pose`` is beyond the tolerance around the prediction."""
        dt = (pose.t_ns - last.t_ns) * 1e-9
        step = float(np.linalg.norm(p_pred - last.xyz_W_m))
        cov = np.asarray(last.cov, float)
        sigma_m = math.sqrt(max(float(np.trace(cov[:3, :3])), 0.0))
        sigma_yaw = math.sqrt(max(float(cov[5, 5]), 0.0))
        tol = self.jump_m + self.jump_frac * step + 0.5 * self.accel_max_mps2 * dt * dt + self.jump_sigmas * sigma_m
        d = float(np.linalg.norm(pose.xyz_W_m - p_pred))
        yaw_pred = float(R_to_euler(R_pred)[2])
        turn = abs(float(wrap_angle(yaw_pred - last.rpy_rad[2])))
        tol_yaw = (
            self.jump_yaw_rad
            + self.jump_frac * turn
            + 0.5 * self.yaw_accel_max_radps2 * dt * dt
            + self.jump_sigmas * sigma_yaw
        )
        dyaw = abs(float(wrap_angle(pose.rpy_rad[2] - yaw_pred)))
        if d > tol:
            return f"jump {d:.2f} m (tolerance {tol:.2f} m)"
        if dyaw > tol_yaw:
            return f"jump {math.degrees(dyaw):.1f} deg (tolerance {math.degrees(tol_yaw):.1f} deg)"
        return None

    def _fit_twist(self) -> None:
        """Least-squares twist over the segment's poses within ``window_s`` of the newest (at least
        the newest two); unchanged with fewer than two."""
        seg = self._seg
        if len(seg) < 2:
            return
        t_new = seg[-1].t_ns
        n = 2
        while n < len(seg) and (t_new - seg[-n - 1].t_ns) * 1e-9 <= self.window_s + 1e-9:
            n += 1
        poses = list(seg)[-n:]
        t = np.array([(p.t_ns - t_new) * 1e-9 for p in poses])
        span = t[-1] - t[0]
        if span <= 0:
            return
        P = np.array([p.xyz_W_m for p in poses], float)
        tc = t - t.mean()
        v_W = tc @ (P - P.mean(0)) / float(tc @ tc)
        R_first = euler_to_R(np.asarray(poses[0].rpy_rad, float))
        R_last = euler_to_R(np.asarray(poses[-1].rpy_rad, float))
        rot = so3_log(R_first.T @ R_last)
        R_mid = R_first @ so3_exp(rot / 2.0)
        if not (np.all(np.isfinite(v_W)) and np.all(np.isfinite(rot))):
            return
        self._v_R = R_mid.T @ v_W
        self._w_R = rot / span
        self._twist_known = True


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
