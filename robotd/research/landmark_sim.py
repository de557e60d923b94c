"""Landmark-world simulation for the filters (docs/math.md §12): worlds, trajectories, stereo noise, odometry.

This is the point-landmark simulator the filter experiments use (not the rendered-image rover of
``drivers/sim.py``). It produces, per frame, exactly what the estimator consumes — a
:class:`robotd.core.msgs.MotionIncrement` and :class:`robotd.core.msgs.Observations` — plus the truth kept
alongside for evaluation (true pose, true landmark ids, which correspondences are wrong).

Frames (docs/math.md §1.2): world ``W`` is the robot frame at the first pose (forward-right-down,
so the start pose is the identity); robot ``R`` is FRD at the baseline centre. Poses are 6-vectors
``(x, y, z, roll, pitch, yaw)`` with R = Rz(yaw) Ry(pitch) Rx(roll) (ZYX); 2D worlds keep
z = roll = pitch = 0 and landmarks in the camera's plane (Z_W = 0).

Measurements follow §12's recipe so that the noise is the real stereo noise, not a Gaussian in 3D:
project each landmark to the rectified pixels (robotd.core.stereo.project), add pixel noise
(σ_x on x_L and x_R, σ_x on each row so the mean row has σ_x/√2), keep those inside the image and
the disparity limits of §2.2, triangulate (eq. 3.2.14) and attach the first-order covariance Q_i
(§3.1). Depth error therefore grows with range².

For consistency studies (§11's NEES) ``noise_model`` swaps that recipe for noise the filters'
model assumes exactly, with the same visibility: ``"gaussian"`` draws z ~ N(z_true, Q(z_true)) with
the first-order stereo covariance at the true point (the ellipsoid's shape, no bias, no
weight/error correlation), ``"isotropic"`` draws z ~ N(z_true, σ²I) with σ = ``isotropic_sigma_m``.
Comparing the three separates what the stereo noise does to a filter from what the filter does.

Odometry follows the increment models of §6.2 (2D) and §6.3 (3D): the true increment between
consecutive poses plus Gaussian noise whose covariance M_t is reported in ``MotionIncrement.cov``.
In 3D the rotation increment is ω = E(η_{t-1})⁻¹ (η_t − η_{t-1}), so the noiseless increment fed
through the §6.3 model reproduces the true pose exactly.

Everything random is drawn from the injected ``np.random.Generator``: the same seed gives the same
run bit for bit.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial import cKDTree

from robotd.core.errors import ConfigError
from robotd.core.geometry import R_to_euler, euler_to_R, pose2_compose, pose2_inverse, so3_exp, so3_log, wrap_angle
from robotd.core.msgs import MotionIncrement, Observations
from robotd.core.stereo import gate_selection_shift, project, triangulate, triangulation_covariance

logger = logging.getLogger(__name__)

TRAJECTORIES = ("loop", "figure8", "line")
NOISE_MODELS = ("stereo", "gaussian", "isotropic")

# Variance given to the control components a 2D run does not use (z, roll, pitch), so the 6×6
# control covariance stays positive definite for code that factors it.
_UNUSED_VAR = 1e-12


@dataclass(frozen=True, slots=True)
class SimConfig:
    """Everything that defines a simulated run (defaults: docs/math.md §12 "Simulation world").

    Lengths in metres, angles in degrees where the name says ``_deg``, pixel quantities in px.
    """

    dim: int = 2  # 2: planar field, 3: terrain with roll/pitch and landmark heights
    trajectory: str = "loop"  # one of TRAJECTORIES
    path_length_m: float = 200.0
    speed_mps: float = 1.0
    rate_hz: float = 10.0
    # landmark field: uniform density inside a band around the path (unseen landmarks cost nothing)
    landmark_density_per_m2: float = 1.0
    band_m: float = 7.0  # landmarks farther than this from the path are never generated
    clearance_m: float = 0.3  # no landmark closer than this to the path (the rover drives there)
    landmark_height_m: tuple[float, float] = (0.0, 3.0)  # 3D: height above the ground
    camera_height_m: float = 0.5  # 3D: the rig above the ground
    max_tilt_deg: float = 5.0  # 3D: terrain scaled so |roll|, |pitch| stay below this
    # stereo rig (OAK-D at 640×400) and front-end limits (§2.2)
    f_px: float = 430.0
    baseline_m: float = 0.0755
    width: int = 640
    height: int = 400
    sigma_px: float = 0.5  # per pixel coordinate; the mean row has sigma_px/√2
    d_min_px: float = 5.0
    # correct the kept disparities for the gate's selection, as the front end can
    # (frontend.debias_limits, off by default like there; robotd.core.stereo.gate_selection_shift);
    # stereo noise only
    debias_limits: bool = False
    # "stereo": pixel noise then triangulation (§12, the default); "gaussian" / "isotropic": a 3D
    # Gaussian matching the filters' model exactly (consistency studies; see the module docstring)
    noise_model: str = "stereo"
    isotropic_sigma_m: float = 0.05
    depth_min_m: float = 0.3
    max_observations: int = 0  # 0: keep all visible; else the nearest ones (a front end's feature cap)
    # odometry noise (§6.2): σ = frac·distance + floor; heading σ = deg_per_m·distance + floor
    odo_trans_frac: float = 0.05
    odo_heading_deg_per_m: float = 2.0
    odo_rot_frac: float = 0.05  # rad of σ per rad turned
    odo_trans_floor_m: float = 1e-3
    odo_rot_floor_deg: float = 0.01
    # data association errors (§12.3)
    mismatch_rate: float = 0.0  # fraction of re-observations given a wrong landmark id
    mismatch_near_frac: float = 0.5  # of those, the fraction sent to a landmark within near_radius
    mismatch_near_radius_m: float = 1.0

    def __post_init__(self) -> None:
        if self.dim not in (2, 3):
            raise ConfigError(f"sim.dim: expected 2 or 3, got {self.dim}")
        if self.noise_model not in NOISE_MODELS:
            raise ConfigError(f"sim.noise_model: expected one of {NOISE_MODELS}, got {self.noise_model!r}")
        if not self.isotropic_sigma_m > 0:
            raise ConfigError(f"sim.isotropic_sigma_m: expected > 0, got {self.isotropic_sigma_m}")
        if self.trajectory not in TRAJECTORIES:
            raise ConfigError(f"sim.trajectory: expected one of {TRAJECTORIES}, got {self.trajectory!r}")
        for name in ("path_length_m", "speed_mps", "rate_hz", "f_px", "baseline_m", "sigma_px", "band_m"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"sim.{name}: expected > 0, got {getattr(self, name)}")
        if not 0.0 <= self.mismatch_rate <= 1.0:
            raise ConfigError(f"sim.mismatch_rate: expected in [0, 1], got {self.mismatch_rate}")
        if not 0.0 <= self.mismatch_near_frac <= 1.0:
            raise ConfigError(f"sim.mismatch_near_frac: expected in [0, 1], got {self.mismatch_near_frac}")
        if self.landmark_density_per_m2 < 0:
            raise ConfigError(f"sim.landmark_density_per_m2: expected >= 0, got {self.landmark_density_per_m2}")

    @property
    def n_frames(self) -> int:
        return round(self.path_length_m / self.speed_mps * self.rate_hz) + 1

    @property
    def px(self) -> float:
        return (self.width - 1) / 2.0

    @property
    def py(self) -> float:
        return (self.height - 1) / 2.0


@dataclass(frozen=True, slots=True, eq=False)
class SimTruth:
    """Ground truth of one frame (for evaluation only; never given to a filter)."""

    pose_W: np.ndarray  # (6,) x, y, z [m], roll, pitch, yaw [rad] of T_world_robot
    true_ids: np.ndarray  # (N,) int64 landmark each measurement really comes from
    wrong: np.ndarray  # (N,) bool: Observations.ids[i] != true_ids[i] (injected mismatch)
    near: np.ndarray  # (N,) bool: the wrong id is a landmark within mismatch_near_radius_m


@dataclass(frozen=True, slots=True, eq=False)
class SimStep:
    """One frame: the control since the previous frame (None for the first), the measurements, the truth."""

    t_ns: int
    motion: MotionIncrement | None
    observations: Observations
    truth: SimTruth


@dataclass(frozen=True, slots=True, eq=False)
class SimRun:
    """A whole simulated run: configuration, world, trajectory and the per-frame steps."""

    config: SimConfig
    landmarks_W: np.ndarray  # (M, 3) true landmark positions; global id = row index
    poses_W: np.ndarray  # (K, 6) true poses at the frames
    t_ns: np.ndarray  # (K,) int64 frame times
    steps: list[SimStep] = field(default_factory=list)

    @property
    def dim(self) -> int:
        return self.config.dim

    def poses_2d(self) -> np.ndarray:
        """(K, 3) planar true poses (x, y, yaw)."""
        return self.poses_W[:, [0, 1, 5]]


# --------------------------------------------------------------------------------------------
# Trajectories


def _curve(kind: str, n: int) -> np.ndarray:
    """A closed (or open) smooth planar curve sampled at n parameter values, (n, 2), arbitrary scale."""
    t = np.linspace(0.0, 2.0 * np.pi, n)
    if kind == "loop":
        # an ellipse with a gentle wobble: turns of varying sharpness, closes on itself
        return np.stack([1.6 * np.cos(t) + 0.15 * np.cos(3 * t), np.sin(t) + 0.1 * np.sin(2 * t)], 1)
    if kind == "figure8":
        return np.stack([np.sin(t), 0.6 * np.sin(2.0 * t)], 1)
    return np.stack([t, np.zeros_like(t)], 1)


def planar_path(kind: str, length_m: float, n_frames: int) -> np.ndarray:
    """Constant-speed planar path, (n_frames, 3) of (x, y, yaw) starting at the origin with yaw 0.

    The curve is re-parametrised by arc length so consecutive frames are length/(n_frames-1) apart;
    then moved so the first pose is the identity (the world frame is the start pose, §1.2).
    """
    dense = _curve(kind, 20001)
    seg = np.linalg.norm(np.diff(dense, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    dense = dense * (length_m / s[-1])
    s = s * (length_m / s[-1])
    s_q = np.linspace(0.0, length_m, n_frames)
    xy = np.stack([np.interp(s_q, s, dense[:, 0]), np.interp(s_q, s, dense[:, 1])], 1)
    # heading from the dense tangent (finite differences of the dense curve, periodic at the ends)
    tang = np.gradient(dense, s, axis=0)
    if kind in ("loop", "figure8"):
        tang[0] = tang[-1] = dense[1] - dense[-2]
    yaw_dense = np.unwrap(np.arctan2(tang[:, 1], tang[:, 0]))
    yaw = np.interp(s_q, s, yaw_dense)
    # move the start pose to the identity
    c, sn = np.cos(yaw[0]), np.sin(yaw[0])
    d = xy - xy[0]
    xy0 = np.stack([c * d[:, 0] + sn * d[:, 1], -sn * d[:, 0] + c * d[:, 1]], 1)
    return np.column_stack([xy0, wrap_angle(yaw - yaw[0])])


class Terrain:
    """Smooth ground height h(x, y) [m, up] with h = 0 and ∇h = 0 at the start, slopes bounded.

    A sum of sinusoids multiplied by a window 1 − exp(−|p|²/r²) that is quadratic at the origin, so
    the rover starts level at the world origin (§1.2) and tilts as it drives away.
    """

    def __init__(self, rng: np.random.Generator, scale_m: float = 1.0, window_m: float = 8.0) -> None:
        self.k = rng.uniform(0.08, 0.25, size=(4, 2)) * rng.choice([-1.0, 1.0], size=(4, 2))
        self.phase = rng.uniform(0.0, 2.0 * np.pi, size=4)
        self.amp = rng.uniform(0.5, 1.0, size=4)
        self.scale_m = scale_m
        self.window_m = window_m

    def height(self, xy: np.ndarray) -> np.ndarray:
        """(..., 2) -> (...,) height above the datum [m] (positive up)."""
        xy = np.asarray(xy, dtype=float)
        arg = np.einsum("...j,kj->...k", xy, self.k) + self.phase
        base = np.sin(arg) @ self.amp
        base0 = float(np.sin(self.phase) @ self.amp)
        r2 = np.sum(xy * xy, axis=-1)
        return self.scale_m * (base - base0) * (1.0 - np.exp(-r2 / self.window_m**2))

    def gradient(self, xy: np.ndarray, eps: float = 1e-4) -> np.ndarray:
        """(..., 2) -> (..., 2) ∇h by central differences."""
        xy = np.asarray(xy, dtype=float)
        ex, ey = np.array([eps, 0.0]), np.array([0.0, eps])
        gx = (self.height(xy + ex) - self.height(xy - ex)) / (2 * eps)
        gy = (self.height(xy + ey) - self.height(xy - ey)) / (2 * eps)
        return np.stack([gx, gy], -1)


def terrain_poses(path2: np.ndarray, terrain: Terrain) -> np.ndarray:
    """Planar path (K, 3) on the terrain -> (K, 6) poses (x, y, z, roll, pitch, yaw) in FRD.

    z is down, so z = −h (the camera height cancels because the world origin is the start pose).
    Pitch is nose-up positive (R_y maps forward to (cos φ, 0, −sin φ)), so climbing gives φ > 0;
    roll is right-side-down positive.
    """
    xy, yaw = path2[:, :2], path2[:, 2]
    g = terrain.gradient(xy)
    fwd = np.stack([np.cos(yaw), np.sin(yaw)], 1)
    right = np.stack([-np.sin(yaw), np.cos(yaw)], 1)
    slope_f = np.sum(g * fwd, 1)  # dh/ds ahead: up-hill > 0
    slope_r = np.sum(g * right, 1)  # dh/ds to the right: right side higher > 0
    pitch = np.arctan(slope_f)
    roll = -np.arctan(slope_r * np.cos(pitch))
    z = -terrain.height(xy)
    return np.column_stack([xy, z, roll, pitch, yaw])


# --------------------------------------------------------------------------------------------
# World


def make_landmarks(
    config: SimConfig, path2: np.ndarray, rng: np.random.Generator, terrain: Terrain | None
) -> np.ndarray:
    """Uniform landmarks in a band around the path, (M, 3) in the world frame (FRD, z down)."""
    lo = path2[:, :2].min(0) - config.band_m
    hi = path2[:, :2].max(0) + config.band_m
    area = float(np.prod(hi - lo))
    n = rng.poisson(config.landmark_density_per_m2 * area)
    xy = rng.uniform(lo, hi, size=(n, 2))
    # densify the path so the band test is a nearest-neighbour query
    seg = np.linalg.norm(np.diff(path2[:, :2], axis=0), axis=1).max(initial=0.0)
    tree = cKDTree(path2[:, :2])
    dist, _ = tree.query(xy)
    keep = (dist <= config.band_m) & (dist >= config.clearance_m + 0.5 * seg)
    xy = xy[keep]
    if config.dim == 2:
        return np.column_stack([xy, np.zeros(len(xy))])
    assert terrain is not None
    h_lo, h_hi = config.landmark_height_m
    height = rng.uniform(h_lo, h_hi, size=len(xy))
    # z down; the camera is camera_height_m above the ground at the origin, which is z = 0
    z = -(terrain.height(xy) + height) + config.camera_height_m
    return np.column_stack([xy, z])


def make_world(config: SimConfig, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """True trajectory and landmarks: (t_ns (K,), poses_W (K, 6), landmarks_W (M, 3))."""
    k = config.n_frames
    path2 = planar_path(config.trajectory, config.path_length_m, k)
    terrain: Terrain | None = None
    if config.dim == 3:
        terrain = Terrain(rng)
        poses = terrain_poses(path2, terrain)
        tilt = np.abs(poses[:, 3:5]).max()
        # scale the terrain so the steepest attitude on the path is just inside the limit
        target = np.deg2rad(config.max_tilt_deg) * 0.95
        if tilt > 0:
            terrain.scale_m *= np.tan(target) / np.tan(tilt)
        poses = terrain_poses(path2, terrain)
    else:
        poses = np.column_stack([path2[:, :2], np.zeros((k, 3)), path2[:, 2]])
    landmarks = make_landmarks(config, path2, rng, terrain)
    t_ns = np.round(np.arange(k) * (1e9 / config.rate_hz)).astype(np.int64)
    return t_ns, poses, landmarks


# --------------------------------------------------------------------------------------------
# Sensors


def true_increment(pose0: np.ndarray, pose1: np.ndarray, dim: int) -> tuple[np.ndarray, np.ndarray]:
    """Control (dp_R (3,), drot_R (3,)) that takes pose0 to pose1 under the §6.2 / §6.3 models.

    2D: (Δx_b, Δy_b, Δψ) = x0⁻¹ ⊕ x1. 3D: Δp_b = R(η0)ᵀ(p1 − p0) and ω = log(R(η0)ᵀ R(η1)).
    """
    if dim == 2:
        d = pose2_compose(pose2_inverse(pose0[[0, 1, 5]]), pose1[[0, 1, 5]])
        return np.array([d[0], d[1], 0.0]), np.array([0.0, 0.0, d[2]])
    R0 = euler_to_R(pose0[3:6])
    dp = R0.T @ (pose1[:3] - pose0[:3])
    return dp, so3_log(R0.T @ euler_to_R(pose1[3:6]))


def odometry_covariance(dp: np.ndarray, drot: np.ndarray, config: SimConfig) -> np.ndarray:
    """Control covariance M_t (6, 6) for an increment (§6.2 form: σ grows with the distance driven)."""
    dist = float(np.linalg.norm(dp))
    s_t = config.odo_trans_frac * dist + config.odo_trans_floor_m
    s_r = (
        np.deg2rad(config.odo_heading_deg_per_m) * dist
        + config.odo_rot_frac * float(np.abs(drot).max())
        + np.deg2rad(config.odo_rot_floor_deg)
    )
    if config.dim == 2:
        return np.diag([s_t**2, s_t**2, _UNUSED_VAR, _UNUSED_VAR, _UNUSED_VAR, s_r**2])
    return np.diag([s_t**2] * 3 + [s_r**2] * 3)


def measure_frame(
    pose_W: np.ndarray, landmarks_W: np.ndarray, config: SimConfig, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stereo measurements of the visible landmarks from one pose.

    Returns (ids (N,), xyz_R (N, 3), Q (N, 3, 3)): noisy triangulated points in the robot frame and
    their first-order covariance computed from the noisy pixels, as a real front end would (§3.1).
    Visibility: in front, both projections inside the image, disparity in [d_min, fb/X_min] (§2.2)
    — tested on the noisy pixels too, since that is what a front end sees.
    """
    f, b, px, py = config.f_px, config.baseline_m, config.px, config.py
    R = euler_to_R(pose_W[3:6])
    z = (landmarks_W - pose_W[:3]) @ R  # rows: Rᵀ(m − p), eq. §7.1
    d_max = f * b / config.depth_min_m
    front = z[:, 0] > f * b / (d_max * 4.0)
    ids = np.flatnonzero(front)
    z = z[front]
    xl, xr, y = project(z, f, px, py, b)
    vis = (
        (xl >= 0)
        & (xl <= config.width - 1)
        & (xr >= 0)
        & (xr <= config.width - 1)
        & (y >= 0)
        & (y <= config.height - 1)
        & (xl - xr >= config.d_min_px)
        & (xl - xr <= d_max)
    )
    ids, z, xl, xr, y = ids[vis], z[vis], xl[vis], xr[vis], y[vis]
    if config.max_observations and len(ids) > config.max_observations:
        near = np.argsort(z[:, 0], kind="stable")[: config.max_observations]
        near.sort()
        ids, z, xl, xr, y = ids[near], z[near], xl[near], xr[near], y[near]
    n = len(ids)
    s = config.sigma_px
    if config.noise_model != "stereo":
        return ids.astype(np.int64), *_model_noise(z, xl, xr, y, config, rng)
    nxl = xl + s * rng.standard_normal(n)
    nxr = xr + s * rng.standard_normal(n)
    # each row is measured with σ; the triangulation uses their mean (σ/√2), §2.2/§3.1
    ny = y + s * rng.standard_normal((n, 2)).mean(1)
    d = nxl - nxr
    ok = (d >= config.d_min_px) & (d <= d_max) & (nxl >= 0) & (nxl <= config.width - 1)
    ok &= (nxr >= 0) & (nxr <= config.width - 1) & (ny >= 0) & (ny <= config.height - 1)
    ids, nxl, nxr, ny = ids[ok], nxl[ok], nxr[ok], ny[ok]
    if config.debias_limits:
        shift = gate_selection_shift(nxl - nxr, config.d_min_px, d_max, s * np.sqrt(2.0))
        nxl, nxr = nxl - 0.5 * shift, nxr + 0.5 * shift
    xyz = triangulate(nxl, nxr, ny, f, px, py, b)
    Q = triangulation_covariance(nxl, nxr, ny, f, px, py, b, sigma_x_px=s, sigma_y_px=s / np.sqrt(2.0))
    return ids.astype(np.int64), xyz.reshape(-1, 3), Q.reshape(-1, 3, 3)


def _model_noise(
    z: np.ndarray, xl: np.ndarray, xr: np.ndarray, y: np.ndarray, config: SimConfig, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """(xyz (N, 3), Q (N, 3, 3)) for the "gaussian" and "isotropic" noise models: z ~ N(z_true, Q)."""
    n = len(z)
    if config.noise_model == "isotropic":
        Q = np.tile(np.eye(3) * config.isotropic_sigma_m**2, (n, 1, 1))
    else:
        s = config.sigma_px
        Q = triangulation_covariance(
            xl, xr, y, config.f_px, config.px, config.py, config.baseline_m, sigma_x_px=s, sigma_y_px=s / np.sqrt(2.0)
        ).reshape(-1, 3, 3)
    L = np.linalg.cholesky(Q)
    return z + np.einsum("nij,nj->ni", L, rng.standard_normal((n, 3))), Q


# --------------------------------------------------------------------------------------------
# Whole runs


def simulate(config: SimConfig, rng: np.random.Generator) -> SimRun:
    """Generate a world, a trajectory and every frame's control, measurements and truth.

    Frame 0 has no motion; frame k > 0 carries the noisy increment from k−1 to k. Observation ids
    are global landmark ids (row of ``landmarks_W``); ``is_new`` is True the first time a landmark
    is measured. Mismatches are injected afterwards at ``config.mismatch_rate`` (see
    :func:`inject_mismatches`), so a run with rate 0 and one with rate r share all other noise.
    """
    t_ns, poses, landmarks = make_world(config, rng)
    seen = np.zeros(len(landmarks), bool)
    steps: list[SimStep] = []
    for k in range(len(t_ns)):
        motion = None
        if k > 0:
            dp, drot = true_increment(poses[k - 1], poses[k], config.dim)
            M = odometry_covariance(dp, drot, config)
            # M_t is diagonal (independent components), so σ·N(0, 1) samples it exactly
            noise = np.sqrt(np.diag(M)) * rng.standard_normal(6)
            if config.dim == 2:
                noise[[2, 3, 4]] = 0.0
            motion = MotionIncrement(int(t_ns[k - 1]), int(t_ns[k]), dp + noise[:3], drot + noise[3:], M)
        ids, xyz, Q = measure_frame(poses[k], landmarks, config, rng)
        is_new = ~seen[ids]
        seen[ids] = True
        obs = Observations(int(t_ns[k]), xyz, Q, ids.copy(), is_new)
        n = len(ids)
        truth = SimTruth(poses[k].copy(), ids, np.zeros(n, bool), np.zeros(n, bool))
        steps.append(SimStep(int(t_ns[k]), motion, obs, truth))
    run = SimRun(config, landmarks, poses, t_ns, steps)
    n_obs = np.array([s.observations.n for s in steps])
    logger.debug(
        "simulated %d frames, %d landmarks, %.1f observations/frame (min %d, max %d)",
        len(steps),
        len(landmarks),
        n_obs.mean(),
        n_obs.min(),
        n_obs.max(),
    )
    if config.mismatch_rate > 0:
        run = inject_mismatches(run, config.mismatch_rate, rng)
    return run


def inject_mismatches(run: SimRun, rate: float, rng: np.random.Generator) -> SimRun:
    """Return a copy of ``run`` whose re-observations get a wrong landmark id at ``rate``.

    Per frame, Binomial(n_reobserved, rate) wrong links are made; a fraction ``mismatch_near_frac``
    of them go to an already-mapped landmark within ``mismatch_near_radius_m`` of the true one
    (repeated texture, §12.3), the rest to any mapped landmark. A frame never carries one id twice:
    a near landmark that is itself measured in the frame is *swapped* with it (two wrong links,
    the typical confusion of two similar neighbours). When no near landmark exists the mismatch
    goes to a random mapped one instead (and does not count as near). First observations are
    never corrupted: they create landmarks, a mismatch is a wrong link to the map.
    """
    cfg = replace(run.config, mismatch_rate=rate)
    lm = run.landmarks_W
    pts = lm[:, :2] if cfg.dim == 2 else lm
    tree = cKDTree(pts)
    seen = np.zeros(len(lm), bool)
    steps: list[SimStep] = []
    for st in run.steps:
        obs, tr = st.observations, st.truth
        true_ids = tr.true_ids
        ids = true_ids.copy()
        wrong = np.zeros(len(ids), bool)
        near = np.zeros(len(ids), bool)
        old = np.flatnonzero(~obs.is_new)
        n_target = int(rng.binomial(len(old), rate)) if len(old) else 0
        n_near_target = int(rng.binomial(n_target, cfg.mismatch_near_frac))
        row_of = {int(j): i for i, j in enumerate(true_ids.tolist())}
        pool = np.flatnonzero(seen)
        order = rng.permutation(old)
        swap_only: list[tuple[int, int]] = []
        # pass 1: near mismatches
        for i in order:
            if near.sum() >= n_near_target:
                break
            if wrong[i]:
                continue
            j = int(true_ids[i])
            used = set(ids.tolist())
            nb = [int(c) for c in tree.query_ball_point(pts[j], cfg.mismatch_near_radius_m) if c != j and seen[c]]
            outside = [c for c in nb if c not in used]
            swappable = [c for c in nb if c in row_of and not wrong[row_of[c]]]
            if outside:
                ids[i] = outside[int(rng.integers(len(outside)))]
                wrong[i] = near[i] = True
            elif swappable:
                c = swappable[int(rng.integers(len(swappable)))]
                if n_near_target - near.sum() >= 2:
                    i2 = row_of[c]
                    ids[i], ids[i2] = c, j
                    wrong[[i, i2]] = near[[i, i2]] = True
                else:
                    swap_only.append((int(i), c))
        if near.sum() < n_near_target and swap_only and rng.random() < 0.5:
            # one near mismatch still wanted but only a swap (two) is possible: do it half the
            # time so the expected number of near mismatches stays right
            i, c = swap_only[0]
            i2 = row_of[c]
            if not wrong[i] and not wrong[i2]:
                ids[i], ids[i2] = c, int(true_ids[i])
                wrong[[i, i2]] = near[[i, i2]] = True
        # pass 2: far (random) mismatches to mapped landmarks not measured in this frame
        for i in order:
            if wrong.sum() >= n_target:
                break
            if wrong[i] or not len(pool):
                continue
            j = int(true_ids[i])
            used = set(ids.tolist())
            for _ in range(20):
                c = int(pool[int(rng.integers(len(pool)))])
                if c != j and c not in used:
                    ids[i] = c
                    wrong[i] = True
                    break
        seen[true_ids] = True
        new_obs = Observations(obs.t_ns, obs.xyz_R_m, obs.cov_R, ids, obs.is_new.copy())
        steps.append(SimStep(st.t_ns, st.motion, new_obs, SimTruth(tr.pose_W, true_ids, wrong, near)))
    return SimRun(cfg, run.landmarks_W, run.poses_W, run.t_ns, steps)


def dead_reckoning(run: SimRun) -> np.ndarray:
    """Integrate the noisy controls from the true start pose: (K, 6) poses (the filters' prior)."""
    poses = np.zeros_like(run.poses_W)
    poses[0] = run.poses_W[0]
    for k, st in enumerate(run.steps[1:], start=1):
        assert st.motion is not None
        poses[k] = apply_increment(poses[k - 1], st.motion.dp_R_m, st.motion.drot_R_rad, run.dim)
    return poses


def apply_increment(pose: np.ndarray, dp: np.ndarray, drot: np.ndarray, dim: int) -> np.ndarray:
    """The noiseless motion model g of §6.2 (2D) or §6.3 (3D) on a (6,) pose."""
    out = pose.copy()
    if dim == 2:
        x2 = pose2_compose(pose[[0, 1, 5]], np.array([dp[0], dp[1], drot[2]]))
        out[[0, 1, 5]] = x2
        return out
    out[:3] = pose[:3] + euler_to_R(pose[3:6]) @ dp
    out[3:6] = wrap_angle(R_to_euler(euler_to_R(pose[3:6]) @ so3_exp(drot)))
    return out
