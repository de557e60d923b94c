"""Messages that cross package borders.

Every message is a frozen dataclass with integer-nanosecond timestamps on the host monotonic
clock (``t_ns``), units in field names and array shapes/frames in comments. ``__post_init__``
validates at the border and raises :class:`robotd.core.errors.InputError` with "expected vs got";
code inside the core trusts these messages.

Frames (see ``robotd.core.geometry``): robot ``R`` is forward-right-down at the baseline centre of
the rectified rig, world ``W`` is the robot frame at start-up (MAVLink LOCAL_FRD).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from robotd.core.errors import InputError
from robotd.core.geometry import euler_to_R, se3

FloatArray = np.ndarray  # alias used in annotations; shapes are given in comments


def _check_array(name: str, a: Any, shape: tuple[int | None, ...], finite: bool = True) -> np.ndarray:
    """Validate ``a`` against ``shape`` (None = any length); return it as an ndarray."""
    if not isinstance(a, np.ndarray):
        raise InputError(f"{name}: expected numpy array of shape {shape}, got {type(a).__name__}")
    if a.ndim != len(shape) or any(s is not None and s != g for s, g in zip(shape, a.shape)):
        raise InputError(f"{name}: expected shape {shape}, got {a.shape}")
    if finite and a.dtype.kind == "f" and a.size and not np.all(np.isfinite(a)):
        raise InputError(f"{name}: expected finite values, got {int(np.sum(~np.isfinite(a)))} non-finite")
    return a


def _check_gravity(owner: str, g: Any, sigma: float) -> None:
    if g is None:
        return
    _check_array(f"{owner}.gravity_R", g, (3,))
    n = math.hypot(*(float(v) for v in g))  # no overflow warning for a link's 3e38 in float32
    if not 0.5 <= n <= 1.5:
        raise InputError(f"{owner}.gravity_R: expected a direction (norm about 1), got norm {n:.3g}")
    if not (isinstance(sigma, float | int) and math.isfinite(sigma) and 0.0 < sigma <= 1.0):
        raise InputError(f"{owner}.gravity_sigma_rad: expected a noise in (0, 1] rad, got {sigma!r}")


def _check_time(name: str, t_ns: Any) -> None:
    if not isinstance(t_ns, int | np.integer) or isinstance(t_ns, bool):
        raise InputError(f"{name}: expected integer nanoseconds, got {type(t_ns).__name__}")


@dataclass(frozen=True, slots=True, eq=False)
class StereoFrame:
    """One hardware-synchronised stereo pair.

    ``left``/``right``: (H, W) uint8 grey images; rectified when ``rectified`` is True.
    ``truth_T_world_robot``: (4, 4) ground-truth pose when a simulator or dataset knows it; it is
    for evaluation only and never reaches the filter. ``exposure_ns``: how long the images were
    exposed, when the camera says (the OAK-D's frames and the simulator's do; datasets do not); the
    motion's blur is judged by it (docs/slam.md "Reported covariance", motion blur).
    """

    t_ns: int  # capture time (middle of exposure), host monotonic clock
    seq: int  # sequence number from the source; gaps reveal dropped frames
    left: np.ndarray  # (H, W) uint8
    right: np.ndarray  # (H, W) uint8
    rectified: bool = True
    truth_T_world_robot: np.ndarray | None = None  # (4, 4) [m], evaluation only
    exposure_ns: int = 0  # the exposure time the camera reports; 0 = not reported

    def __post_init__(self) -> None:
        _check_time("StereoFrame.t_ns", self.t_ns)
        e = self.exposure_ns
        if isinstance(e, bool) or not isinstance(e, (int, np.integer)) or e < 0:
            raise InputError(f"StereoFrame.exposure_ns: expected integer nanoseconds >= 0, got {self.exposure_ns!r}")
        for side in ("left", "right"):
            img = getattr(self, side)
            _check_array(f"StereoFrame.{side}", img, (None, None), finite=False)
            if img.dtype != np.uint8:
                raise InputError(f"StereoFrame.{side}: expected dtype uint8, got {img.dtype}")
        if self.left.shape != self.right.shape:
            raise InputError(
                f"StereoFrame: expected left and right of one size, got {self.left.shape} and {self.right.shape}"
            )
        if self.truth_T_world_robot is not None:
            _check_array("StereoFrame.truth_T_world_robot", self.truth_T_world_robot, (4, 4))


@dataclass(frozen=True, slots=True, eq=False)
class Odometry:
    """One sample of the vehicle's motion, as measured (wheels, autopilot) in the robot frame.

    A velocity sample: linear velocity and body rates, both in the robot frame (FRD), valid at
    ``t_ns``. Drivers that count wheel ticks convert them to velocities at their border.
    ``cov``: the sample's noise when the source states it, over (vel_R_mps, rate_R_radps), each
    sample's error independent of the others'; the integrator carries it into
    ``MotionIncrement.cov``. None: not stated (the filter's motion model then sets the noise).
    """

    t_ns: int  # time the motion was measured, host monotonic clock
    vel_R_mps: np.ndarray  # (3,) [m/s] forward, right, down
    rate_R_radps: np.ndarray  # (3,) [rad/s] roll, pitch, yaw rates (positive yaw turns right)
    source: str = "unknown"  # "wheels", "mavlink", "serial", "sim", "visual", "oxts", ...
    cov: np.ndarray | None = None  # (6, 6) [m²/s², m·rad/s², rad²/s²] over (vel, rate), or None
    # the direction of gravity (down) in the robot frame at t_ns, from an accelerometer or the
    # autopilot's attitude (its roll and pitch), with its angular noise σ [rad]; None: not measured
    gravity_R: np.ndarray | None = None
    gravity_sigma_rad: float = 0.0

    def __post_init__(self) -> None:
        _check_time("Odometry.t_ns", self.t_ns)
        _check_array("Odometry.vel_R_mps", self.vel_R_mps, (3,))
        _check_array("Odometry.rate_R_radps", self.rate_R_radps, (3,))
        if self.cov is not None:
            _check_array("Odometry.cov", self.cov, (6, 6))
            if not np.allclose(self.cov, self.cov.T) or np.any(np.diag(self.cov) < 0):
                raise InputError("Odometry.cov: expected a symmetric matrix with a non-negative diagonal")
        _check_gravity("Odometry", self.gravity_R, self.gravity_sigma_rad)


@dataclass(frozen=True, slots=True, eq=False)
class MotionIncrement:
    """The control input of the motion models: the motion between two frames.

    ``dp_R_m`` is the translation expressed in the robot frame at ``t0_ns``; ``drot_R_rad`` the
    body rotation increment (body rate × Δt; docs/math.md §6.3). ``cov`` is the 6×6 covariance
    of (dp, drot) in control space (M_t). The 2D filters use (dp[0], dp[1], drot[2]).
    """

    t0_ns: int
    t1_ns: int
    dp_R_m: np.ndarray  # (3,)
    drot_R_rad: np.ndarray  # (3,)
    cov: np.ndarray  # (6, 6)
    # the latest measured direction of gravity in the robot frame at t1 (Odometry.gravity_R), or None
    gravity_R: np.ndarray | None = None
    gravity_sigma_rad: float = 0.0

    def __post_init__(self) -> None:
        _check_time("MotionIncrement.t0_ns", self.t0_ns)
        _check_time("MotionIncrement.t1_ns", self.t1_ns)
        if self.t1_ns < self.t0_ns:
            raise InputError(f"MotionIncrement: expected t1_ns >= t0_ns, got {self.t0_ns} > {self.t1_ns}")
        _check_array("MotionIncrement.dp_R_m", self.dp_R_m, (3,))
        _check_array("MotionIncrement.drot_R_rad", self.drot_R_rad, (3,))
        _check_array("MotionIncrement.cov", self.cov, (6, 6))
        _check_gravity("MotionIncrement", self.gravity_R, self.gravity_sigma_rad)

    @property
    def dt_s(self) -> float:
        return (self.t1_ns - self.t0_ns) * 1e-9


@dataclass(frozen=True, slots=True, eq=False)
class Observations:
    """Identified landmark measurements of one frame, input of ``Estimator.update``.

    ``ids`` are global landmark ids (shared by all particles). ``is_new`` marks measurements that
    initialise a landmark; the others update the landmark with that id.

    ``uv_px`` are the measured pixels the points were triangulated from, for the filters' pixel
    measurement model (``slam.measurement = "pixel"``); None when the producer has no images
    (simulators, tests): the pixel model then projects ``xyz_R_m`` instead.
    """

    t_ns: int
    xyz_R_m: np.ndarray  # (N, 3) [m] triangulated points in the robot frame
    cov_R: np.ndarray  # (N, 3, 3) [m²] first-order covariance of each point
    ids: np.ndarray  # (N,) int64 global landmark ids
    is_new: np.ndarray  # (N,) bool
    uv_px: np.ndarray | None = None  # (N, 3) [px] (x_left, x_right, y) in the rectified pair, x_left > x_right

    def __post_init__(self) -> None:
        _check_time("Observations.t_ns", self.t_ns)
        n = _check_array("Observations.xyz_R_m", self.xyz_R_m, (None, 3)).shape[0]
        _check_array("Observations.cov_R", self.cov_R, (n, 3, 3))
        _check_array("Observations.ids", self.ids, (n,))
        _check_array("Observations.is_new", self.is_new, (n,))
        if self.ids.dtype.kind not in "iu":
            raise InputError(f"Observations.ids: expected integer dtype, got {self.ids.dtype}")
        if self.is_new.dtype != np.bool_:
            raise InputError(f"Observations.is_new: expected bool dtype, got {self.is_new.dtype}")
        if self.uv_px is not None:
            uv = _check_array("Observations.uv_px", self.uv_px, (n, 3))
            if n and not np.all(uv[:, 0] > uv[:, 1]):
                raise InputError(
                    f"Observations.uv_px: expected x_left > x_right (positive disparity), got "
                    f"{int(np.sum(~(uv[:, 0] > uv[:, 1])))} rows without"
                )

    @property
    def n(self) -> int:
        return int(self.xyz_R_m.shape[0])

    def subset(self, idx: np.ndarray) -> Observations:
        """The observations at ``idx`` (indices or a boolean mask), pixels included."""
        uv = None if self.uv_px is None else self.uv_px[idx]
        return Observations(self.t_ns, self.xyz_R_m[idx], self.cov_R[idx], self.ids[idx], self.is_new[idx], uv)

    @staticmethod
    def empty(t_ns: int) -> Observations:
        return Observations(
            t_ns,
            np.zeros((0, 3)),
            np.zeros((0, 3, 3)),
            np.zeros(0, np.int64),
            np.zeros(0, bool),
        )


@dataclass(frozen=True, slots=True, eq=False)
class PoseEstimate:
    """The filter's pose of the robot in the world frame (LOCAL_FRD), with its covariance.

    ``cov`` is 6×6 over (x, y, z, roll, pitch, yaw); a 2D filter fills z/roll/pitch with zeros
    in the mean and a small floor on the diagonal.
    """

    t_ns: int
    xyz_W_m: np.ndarray  # (3,)
    rpy_rad: np.ndarray  # (3,) roll, pitch, yaw (ZYX: R = Rz(yaw) Ry(pitch) Rx(roll))
    cov: np.ndarray  # (6, 6)
    neff: float = float("nan")  # FastSLAM effective sample size; NaN for EKF
    n_particles: int = 0

    def __post_init__(self) -> None:
        _check_time("PoseEstimate.t_ns", self.t_ns)
        _check_array("PoseEstimate.xyz_W_m", self.xyz_W_m, (3,))
        _check_array("PoseEstimate.rpy_rad", self.rpy_rad, (3,))
        _check_array("PoseEstimate.cov", self.cov, (6, 6))

    @property
    def T_world_robot(self) -> np.ndarray:
        """(4, 4) homogeneous pose: maps robot-frame points into the world frame."""
        return se3(euler_to_R(self.rpy_rad), self.xyz_W_m)


@dataclass(frozen=True, slots=True, eq=False)
class LandmarkMap:
    """A landmark map in the world frame (EKF marginals, or the best FastSLAM particle's)."""

    ids: np.ndarray  # (M,) int64 global ids
    xyz_W_m: np.ndarray  # (M, 3)
    cov_W: np.ndarray  # (M, 3, 3)

    def __post_init__(self) -> None:
        m = _check_array("LandmarkMap.ids", self.ids, (None,)).shape[0]
        _check_array("LandmarkMap.xyz_W_m", self.xyz_W_m, (m, 3))
        _check_array("LandmarkMap.cov_W", self.cov_W, (m, 3, 3))

    @property
    def n(self) -> int:
        return int(self.ids.shape[0])


@dataclass(frozen=True, slots=True, eq=False)
class UpdateReport:
    """What one ``Estimator.update`` did.

    ``pruned_ids`` is how the rest of the system learns that landmarks left the map: the filter's
    existence counter is the one owner of landmark existence, and every store that keeps
    something per landmark (the front end's descriptors, the reported covariance's anchors)
    forgets exactly these ids, through the landmark registry (robotd.slam.landmarks).
    """

    n_updated: int = 0  # measurements fused into existing landmarks
    n_new: int = 0  # landmarks initialised
    n_gated: int = 0  # measurements rejected by the filter-side χ² gate (EKF)
    pruned_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # (K,) int64, deleted by the counter
    neff: float = float("nan")
    resampled: bool = False

    @property
    def n_pruned(self) -> int:
        """Landmarks deleted by the existence counter in this update."""
        return int(self.pruned_ids.shape[0])


@dataclass(frozen=True, slots=True, eq=False)
class StepResult:
    """Everything ``Pipeline.step`` produced for one frame."""

    t_ns: int
    pose: PoseEstimate
    report: UpdateReport
    timings_ms: dict[str, float] = field(default_factory=dict)  # stage name -> milliseconds
    counts: dict[str, int] = field(default_factory=dict)  # features, stereo_matches, map_matches, inliers...
    tracking: bool = True  # False when no correspondences were accepted for several frames
    relocalised: bool = False  # the pose was reset against a loaded map in this step (a discontinuity)
    # the reported covariance's consistency monitor (robotd.slam.uncertainty): state, nis_ratio, scale
    consistency: dict[str, Any] = field(default_factory=dict)
    observations: Observations | None = None  # what the filter took this frame (ids, pixels): for display
    # 3D: the filter's roll and pitch were implausible (beyond vehicle.max_tilt_deg, or at the ZYX
    # singularity) and were reset to level this step (a discontinuity; the frame is reported lost)
    attitude_reset: bool = False
