"""Motion and measurement models of the SLAM filters, with every Jacobian (docs/math.md §6, §7).

All functions are pure and vectorised over a leading batch axis ``B`` (particles, or particles ×
observations); the EKF calls them with ``B = 1``. Frames: poses are robot-in-world
(``x = (x, y, yaw)`` in 2D, ``(x, y, z, roll, pitch, yaw)`` in 3D, ZYX Euler, docs/math.md §1.3);
landmarks ``m`` are world-frame points; measurements ``z`` are in the robot frame (Cartesian models)
or pixels of the rectified stereo pair (the pixel models).

Angles in returned poses are wrapped to (-π, π]. Innovations of angle-valued measurement rows
(the bearing of the range–bearing model) must be wrapped by the caller; the :class:`MeasurementModel`
record says which rows those are.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial

import numpy as np

from robotd.core.errors import EstimatorError, SingularityError
from robotd.core.geometry import (
    R_to_euler,
    drot2,
    euler_rate_matrix,
    euler_rate_matrix_inverse,
    rot2,
    so3_exp,
    so3_right_jacobian,
    wrap_angle,
)

MeasResult = tuple[np.ndarray, np.ndarray, np.ndarray]
MeasFn = Callable[[np.ndarray, np.ndarray], MeasResult]

# ω below this is a straight line for the velocity model (docs/math.md §6.1)
OMEGA_STRAIGHT = 1e-6
# |cos(pitch)| below this makes E(θ, φ) singular (pitch ±90°, docs/math.md §6.3)
COS_PITCH_MIN = 1e-3


def _rot3_all(eta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """R(η) = Rz Ry Rx and ∂R/∂roll, ∂R/∂pitch, ∂R/∂yaw for η (B, 3); each (B, 3, 3).

    The products of docs/math.md §1.3 expanded in closed form and written into preallocated
    arrays: on the filters' hot path this is ~5× cheaper than composing stacked elementary
    rotations (``robotd.core.geometry.euler_to_R_derivatives``, which the tests compare against).
    """
    cr, sr = np.cos(eta[:, 0]), np.sin(eta[:, 0])
    cp, sp = np.cos(eta[:, 1]), np.sin(eta[:, 1])
    cy, sy = np.cos(eta[:, 2]), np.sin(eta[:, 2])
    out = np.zeros((4, eta.shape[0], 3, 3))
    R, Rr, Rp, Ry = out
    spsr, spcr = sp * sr, sp * cr
    R[:, 0, 0], R[:, 0, 1], R[:, 0, 2] = cy * cp, cy * spsr - sy * cr, cy * spcr + sy * sr
    R[:, 1, 0], R[:, 1, 1], R[:, 1, 2] = sy * cp, sy * spsr + cy * cr, sy * spcr - cy * sr
    R[:, 2, 0], R[:, 2, 1], R[:, 2, 2] = -sp, cp * sr, cp * cr
    Rr[:, 0, 1], Rr[:, 0, 2] = cy * spcr + sy * sr, -cy * spsr + sy * cr
    Rr[:, 1, 1], Rr[:, 1, 2] = sy * spcr - cy * sr, -sy * spsr - cy * cr
    Rr[:, 2, 1], Rr[:, 2, 2] = cp * cr, -cp * sr
    Rp[:, 0, 0], Rp[:, 0, 1], Rp[:, 0, 2] = -cy * sp, cy * cp * sr, cy * cp * cr
    Rp[:, 1, 0], Rp[:, 1, 1], Rp[:, 1, 2] = -sy * sp, sy * cp * sr, sy * cp * cr
    Rp[:, 2, 0], Rp[:, 2, 1], Rp[:, 2, 2] = -cp, -spsr, -spcr
    Ry[:, 0, 0], Ry[:, 0, 1], Ry[:, 0, 2] = -sy * cp, -sy * spsr - cy * cr, -sy * spcr + cy * sr
    Ry[:, 1, 0], Ry[:, 1, 1], Ry[:, 1, 2] = cy * cp, cy * spsr - sy * cr, cy * spcr + sy * sr
    return R, Rr, Rp, Ry


# --------------------------------------------------------------------------------------------
# 2D motion models


def velocity2d(x: np.ndarray, u: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """2D velocity motion model (docs/math.md §6.1, Thrun et al. 2005 ch. 5).

    Args:
        x: (B, 3) poses (x, y, yaw) [m, m, rad] at t-1, world frame.
        u: (B, 2) controls (v [m/s], ω [rad/s]); positive ω turns X towards Y.
        dt: step [s].

    Returns:
        x_new (B, 3) with wrapped yaw, G = ∂g/∂x (B, 3, 3), V = ∂g/∂u (B, 3, 2).
    """
    x = np.asarray(x, dtype=float)
    u = np.asarray(u, dtype=float)
    v, w = u[:, 0], u[:, 1]
    psi = x[:, 2]
    s0, c0 = np.sin(psi), np.cos(psi)
    straight = np.abs(w) < OMEGA_STRAIGHT
    ws = np.where(straight, 1.0, w)  # safe divisor; the straight rows are overwritten below
    s1, c1 = np.sin(psi + ws * dt), np.cos(psi + ws * dt)
    r = v / ws
    dx = np.where(straight, v * dt * c0, -r * s0 + r * s1)
    dy = np.where(straight, v * dt * s0, r * c0 - r * c1)
    x_new = np.stack([x[:, 0] + dx, x[:, 1] + dy, wrap_angle(psi + w * dt)], -1)

    B = x.shape[0]
    G = np.tile(np.eye(3), (B, 1, 1))
    G[:, 0, 2] = np.where(straight, -v * dt * s0, r * (c1 - c0))
    G[:, 1, 2] = np.where(straight, v * dt * c0, r * (s1 - s0))

    V = np.zeros((B, 3, 2))
    V[:, 0, 0] = np.where(straight, dt * c0, (s1 - s0) / ws)
    V[:, 1, 0] = np.where(straight, dt * s0, (c0 - c1) / ws)
    V[:, 0, 1] = np.where(straight, -0.5 * v * dt**2 * s0, v * (s0 - s1) / ws**2 + v * c1 * dt / ws)
    V[:, 1, 1] = np.where(straight, 0.5 * v * dt**2 * c0, -v * (c0 - c1) / ws**2 + v * s1 * dt / ws)
    V[:, 2, 1] = dt
    return x_new, G, V


def velocity2d_noise(v: float, w: float, dt: float, alpha: tuple[float, ...]) -> tuple[np.ndarray, float]:
    """Control noise of the velocity model (docs/math.md §6.1).

    Args:
        alpha: (α1, …, α6) as in Thrun et al. (2005) Table 5.3.

    Returns:
        M (2, 2) covariance of (v, ω) and the variance [rad²] of the extra final rotation γ·dt,
        which makes S_t full rank (needed by the FastSLAM 2.0 proposal).
    """
    a1, a2, a3, a4, a5, a6 = alpha
    M = np.diag([a1 * v * v + a2 * w * w, a3 * v * v + a4 * w * w])
    var_gamma = (a5 * v * v + a6 * w * w) * dt * dt
    return M, float(var_gamma)


def odometry2d(x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """2D odometry-increment model (docs/math.md §6.2).

    Args:
        x: (B, 3) poses (x, y, yaw) at t-1, world frame.
        u: (B, 3) increments (Δx_b, Δy_b, Δψ) in the robot frame at t-1 [m, m, rad].

    Returns:
        x_new (B, 3) (yaw wrapped), G (B, 3, 3), V (B, 3, 3).
    """
    x = np.asarray(x, dtype=float)
    u = np.asarray(u, dtype=float)
    c, s = np.cos(x[:, 2]), np.sin(x[:, 2])
    x_new = np.stack(
        [
            x[:, 0] + u[:, 0] * c - u[:, 1] * s,
            x[:, 1] + u[:, 0] * s + u[:, 1] * c,
            wrap_angle(x[:, 2] + u[:, 2]),
        ],
        -1,
    )
    B = x.shape[0]
    G = np.tile(np.eye(3), (B, 1, 1))
    G[:, 0, 2] = -u[:, 0] * s - u[:, 1] * c
    G[:, 1, 2] = u[:, 0] * c - u[:, 1] * s
    V = np.zeros((B, 3, 3))
    V[:, :2, :2] = rot2(x[:, 2])
    V[:, 2, 2] = 1.0
    return x_new, G, V


def odometry2d_noise(u: np.ndarray, a: tuple[float, ...]) -> np.ndarray:
    """M_t of the odometry-increment model (docs/math.md §6.2).

    ``M = diag((a1|Δx|+a0)², (a2|Δx|+a0)², (a3|Δx|+a4|Δψ|+a5)²)`` with ``a = (a0, …, a5)``.
    Returns (3, 3).
    """
    a0, a1, a2, a3, a4, a5 = a
    dx, dpsi = abs(float(u[0])), abs(float(u[2]))
    return np.diag([(a1 * dx + a0) ** 2, (a2 * dx + a0) ** 2, (a3 * dx + a4 * dpsi + a5) ** 2])


# --------------------------------------------------------------------------------------------
# 3D motion model


def motion3d(x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """6-DOF increment model (docs/math.md §6.3).

    ``p_t = p + R(η) Δp_b``, ``R(η_t) = R(η) exp([ω]×)``: the body rotation is composed exactly.
    (The first-order ``η_t = η + E(θ, φ) ω`` it replaces is an explicit Euler step of the attitude:
    under a turn of ω per increment it scales any tilt by √(1 + |ω|²), 15 % a frame at 0.56 rad,
    and took a 5 m/s run round the sim yard at 5 fps to pitch 90°.)

    Args:
        x: (B, 6) poses (x, y, z, roll, pitch, yaw) at t-1, world frame.
        u: (B, 6) controls (Δp_b [m] in the robot frame at t-1, body rotation increment ω [rad]).

    Returns:
        x_new (B, 6) with wrapped angles, G (B, 6, 6), V (B, 6, 6): ∂x_new/∂x and ∂x_new/∂u, with
        the rotation blocks ``E(η_t) exp(ω)ᵀ E(η)⁻¹`` and ``E(η_t) J_r(ω)`` (docs/math.md §6.3).

    Raises:
        SingularityError (an EstimatorError): when a pose is within ~0.06° of pitch ±90° (E is singular there).
    """
    x = np.asarray(x, dtype=float)
    u = np.asarray(u, dtype=float)
    eta = x[:, 3:6]
    cp = np.cos(eta[:, 1])
    if np.any(np.abs(cp) < COS_PITCH_MIN):
        bad = float(np.rad2deg(eta[np.argmin(np.abs(cp)), 1]))
        raise SingularityError(f"motion3d: pitch {bad:.3f} deg is at the ZYX singularity (±90 deg); cannot propagate")
    R, Rr, Rp, Ry = _rot3_all(eta)
    dp, om = u[:, :3], u[:, 3:6]
    Rw = so3_exp(om)
    eta_new = R_to_euler(R @ Rw)
    x_new = np.empty_like(x)
    x_new[:, :3] = x[:, :3] + np.einsum("bij,bj->bi", R, dp)
    x_new[:, 3:6] = wrap_angle(eta_new)

    # E at the new attitude: a pose the increment takes to the singularity gets a large, finite
    # E (the next propagation refuses it)
    e_new = eta_new.copy()
    c_new = np.cos(e_new[:, 1])
    near = np.abs(c_new) < COS_PITCH_MIN
    if np.any(near):
        e_new[near, 1] = np.sign(e_new[near, 1]) * math.acos(COS_PITCH_MIN)
    E_new = euler_rate_matrix(e_new)
    B = x.shape[0]
    G = np.tile(np.eye(6), (B, 1, 1))
    G[:, :3, 3] = np.einsum("bij,bj->bi", Rr, dp)
    G[:, :3, 4] = np.einsum("bij,bj->bi", Rp, dp)
    G[:, :3, 5] = np.einsum("bij,bj->bi", Ry, dp)
    G[:, 3:6, 3:6] = E_new @ np.swapaxes(Rw, -1, -2) @ euler_rate_matrix_inverse(eta)
    V = np.zeros((B, 6, 6))
    V[:, :3, :3] = R
    V[:, 3:6, 3:6] = E_new @ so3_right_jacobian(om)
    return x_new, G, V


def motion3d_noise(
    u: np.ndarray,
    sigma_dp_m: tuple[float, float, float],
    dp_rel: tuple[float, float, float],
    sigma_rot_rad: tuple[float, float, float],
    rot_per_m: tuple[float, float, float],
    rot_rel: float,
) -> np.ndarray:
    """M_t (6, 6) for the 3D model: per-axis standard deviations that grow with the increment.

    ``σ_dp,i = dp_rel_i·|Δp| + sigma_dp_m_i`` and
    ``σ_ω,i = rot_per_m_i·|Δp| + rot_rel·|ω_i| + sigma_rot_rad_i`` (docs/math.md §6.3 leaves the
    coefficients open; robotd's defaults are in :class:`robotd.slam.estimator.SlamParams`).
    """
    u = np.asarray(u, dtype=float)
    dist = float(np.linalg.norm(u[:3]))
    sp = np.asarray(dp_rel) * dist + np.asarray(sigma_dp_m)
    sr = np.asarray(rot_per_m) * dist + rot_rel * np.abs(u[3:6]) + np.asarray(sigma_rot_rad)
    return np.diag(np.concatenate([sp, sr]) ** 2)


def gravity3d(x: np.ndarray, g_W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The direction of gravity in the robot frame, as an accelerometer or an AHRS gives it.

    ``h(x) = R(η)^T g_W`` with ``g_W`` the (unit) direction of gravity in the world frame: it
    depends on roll and pitch (and on yaw only when the world's z is not the vertical), never on
    position. This is what holds the absolute roll and pitch that vision and a gyro leave free.

    Args:
        x: (B, 6) poses.
        g_W: (3,) unit vector.

    Returns:
        h (B, 3) and H = ∂h/∂x (B, 3, 6) (zero in the position columns).
    """
    x = np.asarray(x, dtype=float)
    g = np.asarray(g_W, dtype=float)
    R, Rr, Rp, Ry = _rot3_all(x[:, 3:6])
    h = np.einsum("bji,j->bi", R, g)
    H = np.zeros((x.shape[0], 3, 6))
    H[:, :, 3] = np.einsum("bji,j->bi", Rr, g)
    H[:, :, 4] = np.einsum("bji,j->bi", Rp, g)
    H[:, :, 5] = np.einsum("bji,j->bi", Ry, g)
    return h, H


def gravity3d_tilt(x: np.ndarray, g_W: np.ndarray, yaw: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`gravity3d` as the filters fuse it: a measurement of roll and pitch only. The yaw
    column of H is zeroed and, given ``yaw`` (a particle filter's mean heading), every pose is
    evaluated at that heading, so the particles' weights do not tell headings apart either.
    Gravity says nothing about the heading; it would only when the world's z is not the vertical,
    and g_W comes from one measurement (its noise and the sensor's bias included), so that would
    be false heading information, accumulated at every frame."""
    x = np.asarray(x, dtype=float)
    if yaw is not None:
        x = x.copy()
        x[:, 5] = yaw
    h, H = gravity3d(x, g_W)
    H[:, :, 5] = 0.0
    return h, H


# --------------------------------------------------------------------------------------------
# Measurement models (docs/math.md §7)


def meas3d(x: np.ndarray, m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """3D point measurement ``z = R(η)^T (m - p)`` (docs/math.md §7.1).

    Args:
        x: (B, 6) poses; m: (B, 3) world landmarks.

    Returns:
        z (B, 3) robot frame, H_x (B, 3, 6), H_m = R^T (B, 3, 3).
    """
    x = np.asarray(x, dtype=float)
    m = np.asarray(m, dtype=float)
    R, Rr, Rp, Ry = _rot3_all(x[:, 3:6])
    Rt = np.swapaxes(R, -1, -2)
    d = m - x[:, :3]
    z = np.einsum("bij,bj->bi", Rt, d)
    Hx = np.empty((x.shape[0], 3, 6))
    Hx[:, :, :3] = -Rt
    # ∂(R^T d)/∂angle = (∂R/∂angle)^T d
    Hx[:, :, 3] = np.einsum("bji,bj->bi", Rr, d)
    Hx[:, :, 4] = np.einsum("bji,bj->bi", Rp, d)
    Hx[:, :, 5] = np.einsum("bji,bj->bi", Ry, d)
    return z, Hx, Rt


def meas3d_inverse(x: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Landmark initialisation ``m = p + R z`` (docs/math.md §7.1).

    Returns m (B, 3) world, J_x = [I, R_θ z, R_φ z, R_ψ z] (B, 3, 6), J_z = R (B, 3, 3).
    """
    x = np.asarray(x, dtype=float)
    z = np.asarray(z, dtype=float)
    R, Rr, Rp, Ry = _rot3_all(x[:, 3:6])
    m = x[:, :3] + np.einsum("bij,bj->bi", R, z)
    Jx = np.empty((x.shape[0], 3, 6))
    Jx[:, :, :3] = np.eye(3)
    Jx[:, :, 3] = np.einsum("bij,bj->bi", Rr, z)
    Jx[:, :, 4] = np.einsum("bij,bj->bi", Rp, z)
    Jx[:, :, 5] = np.einsum("bij,bj->bi", Ry, z)
    return m, Jx, R


def meas2d(x: np.ndarray, m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """2D Cartesian measurement ``z = R2(ψ)^T (m - p)`` (docs/math.md §7.2).

    Args:
        x: (B, 3) poses; m: (B, 2) landmarks.

    Returns:
        z (B, 2), H_x (B, 2, 3), H_m = R2^T (B, 2, 2).
    """
    x = np.asarray(x, dtype=float)
    m = np.asarray(m, dtype=float)
    c, s = np.cos(x[:, 2]), np.sin(x[:, 2])
    dx, dy = m[:, 0] - x[:, 0], m[:, 1] - x[:, 1]
    z = np.stack([c * dx + s * dy, -s * dx + c * dy], -1)
    Hx = np.empty((x.shape[0], 2, 3))
    Hx[:, 0, 0] = -c
    Hx[:, 0, 1] = -s
    Hx[:, 0, 2] = -s * dx + c * dy
    Hx[:, 1, 0] = s
    Hx[:, 1, 1] = -c
    Hx[:, 1, 2] = -c * dx - s * dy
    Hm = np.swapaxes(rot2(x[:, 2]), -1, -2)
    return z, Hx, Hm


def meas2d_inverse(x: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``m = p + R2(ψ) z``; returns m (B, 2), J_x = [I2, R2'(ψ) z] (B, 2, 3), J_z = R2 (B, 2, 2)."""
    x = np.asarray(x, dtype=float)
    z = np.asarray(z, dtype=float)
    R = rot2(x[:, 2])
    m = x[:, :2] + np.einsum("bij,bj->bi", R, z)
    Jx = np.zeros((x.shape[0], 2, 3))
    Jx[:, 0, 0] = 1.0
    Jx[:, 1, 1] = 1.0
    Jx[:, :, 2] = np.einsum("bij,bj->bi", drot2(x[:, 2]), z)
    return m, Jx, R


def range_bearing(x: np.ndarray, m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Range–bearing ``(r, β) = (|Δ|, atan2(Δy, Δx) - ψ)`` (docs/math.md §7.2), β wrapped.

    Returns z (B, 2), H_x (B, 2, 3), H_m (B, 2, 2). Undefined at r = 0 (landmark on the robot).
    """
    x = np.asarray(x, dtype=float)
    m = np.asarray(m, dtype=float)
    dx, dy = m[:, 0] - x[:, 0], m[:, 1] - x[:, 1]
    q = dx * dx + dy * dy
    r = np.sqrt(q)
    z = np.stack([r, wrap_angle(np.arctan2(dy, dx) - x[:, 2])], -1)
    Hx = np.empty((x.shape[0], 2, 3))
    Hx[:, 0, 0] = -dx / r
    Hx[:, 0, 1] = -dy / r
    Hx[:, 0, 2] = 0.0
    Hx[:, 1, 0] = dy / q
    Hx[:, 1, 1] = -dx / q
    Hx[:, 1, 2] = -1.0
    Hm = -Hx[:, :, :2]
    return z, Hx, Hm


def range_bearing_inverse(x: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``m = p + r (cos(ψ+β), sin(ψ+β))``; returns m (B, 2), J_x (B, 2, 3), J_z (B, 2, 2)."""
    x = np.asarray(x, dtype=float)
    z = np.asarray(z, dtype=float)
    r, a = z[:, 0], x[:, 2] + z[:, 1]
    c, s = np.cos(a), np.sin(a)
    m = np.stack([x[:, 0] + r * c, x[:, 1] + r * s], -1)
    Jx = np.zeros((x.shape[0], 2, 3))
    Jx[:, 0, 0] = 1.0
    Jx[:, 1, 1] = 1.0
    Jx[:, 0, 2] = -r * s
    Jx[:, 1, 2] = r * c
    Jz = np.empty((x.shape[0], 2, 2))
    Jz[:, 0, 0] = c
    Jz[:, 0, 1] = -r * s
    Jz[:, 1, 0] = s
    Jz[:, 1, 1] = r * c
    return m, Jx, Jz


# --------------------------------------------------------------------------------------------
# Stereo pixel measurement (docs/slam.md "Measurement models"): z = π(R(η)ᵀ(m − p)), the landmark's
# columns in the left and right rectified images and its row, π the rectified projection of
# robotd.core.stereo.project. 3D: z = (x_L, x_R, y); 2D: z = (x_L, x_R) (no height, the columns do not
# depend on it). The Jacobians chain π's through the Cartesian models': H = J_π(q) · H_cart.

# Predicted depths are clamped to at least this: h stays finite for a landmark that a (wrong)
# pose puts at or behind the rig. J_π is then π's Jacobian at the clamped point.
PIXEL_MIN_DEPTH_M = 0.05


def stereo_projection(q: np.ndarray, f: float, px: float, py: float, b: float) -> tuple[np.ndarray, np.ndarray]:
    """π of robot-frame points and its Jacobian: q (B, 3) -> (x_L, x_R, y) (B, 3), J_π (B, 3, 3);
    q (B, 2) (X, Y) -> (x_L, x_R) (B, 2), J_π (B, 2, 2). Depths below PIXEL_MIN_DEPTH_M are clamped.

    x_L = p_x + f (Y + b/2)/X, x_R = p_x + f (Y − b/2)/X, y = p_y + f Z/X (robotd.core.stereo.project).
    """
    q = np.asarray(q, dtype=float)
    n = q.shape[-1]
    X = np.maximum(q[:, 0], PIXEL_MIN_DEPTH_M)
    iX = 1.0 / X
    fx = f * iX
    Yl, Yr = q[:, 1] + 0.5 * b, q[:, 1] - 0.5 * b
    z = np.empty_like(q)
    J = np.zeros((q.shape[0], n, n))
    z[:, 0] = px + fx * Yl
    z[:, 1] = px + fx * Yr
    J[:, 0, 0] = -fx * Yl * iX
    J[:, 1, 0] = -fx * Yr * iX
    J[:, 0, 1] = fx
    J[:, 1, 1] = fx
    if n == 3:
        z[:, 2] = py + fx * q[:, 2]
        J[:, 2, 0] = -fx * q[:, 2] * iX
        J[:, 2, 2] = fx
    return z, J


def stereo_triangulation(z: np.ndarray, f: float, px: float, py: float, b: float) -> tuple[np.ndarray, np.ndarray]:
    """π⁻¹ and its Jacobian: z (B, 3) (x_L, x_R, y) -> q (B, 3), J (B, 3, 3) = ∂q/∂z (= J_π⁻¹);
    z (B, 2) (x_L, x_R) -> (X, Y) (B, 2), J (B, 2, 2). The disparity x_L − x_R must be positive.

    robotd.core.stereo.triangulate (eq. 3.2.14) and its Jacobian (docs/math.md §3.1) written in q:
    J = X/(f b) · [[−X, X, 0], [−(Y − b/2), Y + b/2, 0], [−Z, Z, b]].
    """
    z = np.asarray(z, dtype=float)
    n = z.shape[-1]
    d = z[:, 0] - z[:, 1]
    X = f * b / d
    q = np.empty_like(z)
    q[:, 0] = X
    q[:, 1] = (z[:, 0] - px) * b / d - 0.5 * b
    s = X / (f * b)
    J = np.zeros((z.shape[0], n, n))
    J[:, 0, 0] = -s * X
    J[:, 0, 1] = s * X
    J[:, 1, 0] = -s * (q[:, 1] - 0.5 * b)
    J[:, 1, 1] = s * (q[:, 1] + 0.5 * b)
    if n == 3:
        q[:, 2] = (z[:, 2] - py) * b / d
        J[:, 2, 0] = -s * q[:, 2]
        J[:, 2, 1] = s * q[:, 2]
        J[:, 2, 2] = s * b
    return q, J


def _pixel_h(cart: MeasFn, rig: tuple[float, float, float, float], x: np.ndarray, m: np.ndarray) -> MeasResult:
    q, Hx, Hm = cart(x, m)
    z, J = stereo_projection(q, *rig)
    return z, J @ Hx, J @ Hm


def _pixel_inverse(
    cart_inv: MeasFn, rig: tuple[float, float, float, float], x: np.ndarray, z: np.ndarray
) -> MeasResult:
    q, Jt = stereo_triangulation(z, *rig)
    m, Jx, Jz = cart_inv(x, q)
    return m, Jx, Jz @ Jt


# --------------------------------------------------------------------------------------------
# Records that let the filters treat the models generically


@dataclass(frozen=True, slots=True)
class MeasurementModel:
    """A measurement model with its inverse: sizes, functions and which z rows are angles."""

    name: str
    dx: int  # pose size (3 or 6)
    dm: int  # landmark size (2 or 3)
    dz: int  # measurement size
    h: MeasFn  # (x (B, dx), m (B, dm)) -> z (B, dz), H_x (B, dz, dx), H_m (B, dz, dm)
    inverse: MeasFn  # (x (B, dx), z (B, dz)) -> m (B, dm), J_x (B, dm, dx), J_z (B, dm, dz)
    angle_rows: tuple[int, ...] = ()  # rows of z whose innovations are wrapped
    # the stereo pixel models: (f [px], p_x [px], p_y [px], baseline [m]) of the rectified rig
    intrinsics: tuple[float, float, float, float] | None = None

    def innovation(self, z: np.ndarray, zhat: np.ndarray) -> np.ndarray:
        """z - zhat (..., dz) with angle rows wrapped to (-π, π]."""
        nu = z - zhat
        for r in self.angle_rows:
            nu[..., r] = wrap_angle(nu[..., r])
        return nu


CARTESIAN_3D = MeasurementModel("cartesian3d", 6, 3, 3, meas3d, meas3d_inverse)
CARTESIAN_2D = MeasurementModel("cartesian2d", 3, 2, 2, meas2d, meas2d_inverse)
RANGE_BEARING_2D = MeasurementModel("range_bearing2d", 3, 2, 2, range_bearing, range_bearing_inverse, (1,))


def stereo_pixel_model(dim: int, f_px: float, px: float, py: float, baseline_m: float) -> MeasurementModel:
    """The stereo pixel model of a rectified rig: 3D z = (x_L, x_R, y), 2D z = (x_L, x_R) [px]."""
    rig = (float(f_px), float(px), float(py), float(baseline_m))
    if not (rig[0] > 0 and rig[3] > 0 and all(math.isfinite(v) for v in rig)):
        raise EstimatorError(f"stereo_pixel_model: expected finite f_px > 0 and baseline_m > 0, got {rig}")
    if dim == 3:
        return MeasurementModel(
            "pixel3d", 6, 3, 3, partial(_pixel_h, meas3d, rig), partial(_pixel_inverse, meas3d_inverse, rig), (), rig
        )
    if dim == 2:
        return MeasurementModel(
            "pixel2d", 3, 2, 2, partial(_pixel_h, meas2d, rig), partial(_pixel_inverse, meas2d_inverse, rig), (), rig
        )
    raise EstimatorError(f"stereo_pixel_model: expected dim 2 or 3, got {dim}")


def pose_angle_slice(dim: int) -> slice:
    """Slice of the angle entries of a pose vector: yaw in 2D, roll/pitch/yaw in 3D."""
    return slice(2, 3) if dim == 2 else slice(3, 6)


def wrap_pose(x: np.ndarray, dim: int) -> np.ndarray:
    """Wrap the angle entries of poses (..., 3|6) in place and return them."""
    sl = pose_angle_slice(dim)
    x[..., sl] = wrap_angle(x[..., sl])
    return x
