"""Rigid-body geometry: SE(2), SE(3), rotations, ZYX Euler angles, quaternions, Jacobian helpers.

Conventions, declared once here (docs/math.md §1):

- Robot frame ``R``: forward-right-down (FRD) at the baseline centre of the rectified rig.
  World frame ``W``: the robot frame at start-up, levelled (MAVLink LOCAL_FRD).
  Camera optical frame ``C``: x right, y down, z forward. ``R_robot_optical`` maps C into R.
- ``T_a_b`` maps points of frame b into frame a: ``x_a = T_a_b @ x_b``.
- Euler angles are ``rpy = (roll θ, pitch φ, yaw ψ)``, composed Z-Y-X:
  ``R(rpy) = Rz(yaw) @ Ry(pitch) @ Rx(roll)`` (robot-to-world).
- 6-vector poses are ``(x, y, z, roll, pitch, yaw)``; 3-vector planar poses ``(x, y, yaw)``.
- Quaternions are ``(w, x, y, z)`` with ``w >= 0`` on output.

Every function accepts a leading batch axis ``(..., )`` where it says so; the batch versions are
tested against one-at-a-time references.
"""

from __future__ import annotations

import numpy as np

# x_R = R_ROBOT_OPTICAL @ x_C  (X_r = Z_c, Y_r = X_c, Z_r = Y_c)
R_ROBOT_OPTICAL = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
# FLU (ROS) <-> FRD: (x, y, z) -> (x, -y, -z); its own inverse.
R_FRD_FLU = np.diag([1.0, -1.0, -1.0])


def wrap_angle(a: np.ndarray | float) -> np.ndarray:
    """Wrap angles to (-π, π]. Any shape."""
    a = np.asarray(a, dtype=float)
    w = np.mod(a + np.pi, 2.0 * np.pi) - np.pi
    # mod maps +π to -π; keep the interval half-open on the other side
    return np.where(w == -np.pi, np.pi, w)


# --------------------------------------------------------------------------------------------
# Elementary rotations and their derivatives (docs/math.md §1.3). Inputs (...,), outputs (..., 3, 3)


def rot_x(a: np.ndarray | float) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([o, z, z], -1), np.stack([z, c, -s], -1), np.stack([z, s, c], -1)], -2)


def rot_y(a: np.ndarray | float) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)


def rot_z(a: np.ndarray | float) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    c, s = np.cos(a), np.sin(a)
    o, z = np.ones_like(a), np.zeros_like(a)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def _drot_x(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    z = np.zeros_like(a)
    return np.stack([np.stack([z, z, z], -1), np.stack([z, -s, -c], -1), np.stack([z, c, -s], -1)], -2)


def _drot_y(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    z = np.zeros_like(a)
    return np.stack([np.stack([-s, z, c], -1), np.stack([z, z, z], -1), np.stack([-c, z, -s], -1)], -2)


def _drot_z(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    z = np.zeros_like(a)
    return np.stack([np.stack([-s, -c, z], -1), np.stack([c, -s, z], -1), np.stack([z, z, z], -1)], -2)


def euler_to_R(rpy: np.ndarray) -> np.ndarray:
    """(..., 3) roll, pitch, yaw -> (..., 3, 3) rotation Rz(yaw) Ry(pitch) Rx(roll)."""
    rpy = np.asarray(rpy, dtype=float)
    # the product written out (one allocation instead of three stacked matrices and two matmuls:
    # ≈ 8× faster for one pose, which the pipeline converts several times per frame)
    cr, sr = np.cos(rpy[..., 0]), np.sin(rpy[..., 0])
    cp, sp = np.cos(rpy[..., 1]), np.sin(rpy[..., 1])
    cy, sy = np.cos(rpy[..., 2]), np.sin(rpy[..., 2])
    R = np.empty((*rpy.shape[:-1], 3, 3))
    R[..., 0, 0] = cy * cp
    R[..., 0, 1] = cy * sp * sr - sy * cr
    R[..., 0, 2] = cy * sp * cr + sy * sr
    R[..., 1, 0] = sy * cp
    R[..., 1, 1] = sy * sp * sr + cy * cr
    R[..., 1, 2] = sy * sp * cr - cy * sr
    R[..., 2, 0] = -sp
    R[..., 2, 1] = cp * sr
    R[..., 2, 2] = cp * cr
    return R


def euler_to_R_derivatives(rpy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """∂R/∂roll, ∂R/∂pitch, ∂R/∂yaw, each (..., 3, 3) (docs/math.md §1.3)."""
    rpy = np.asarray(rpy, dtype=float)
    rx, ry, rz = rot_x(rpy[..., 0]), rot_y(rpy[..., 1]), rot_z(rpy[..., 2])
    return (
        rz @ ry @ _drot_x(rpy[..., 0]),
        rz @ _drot_y(rpy[..., 1]) @ rx,
        _drot_z(rpy[..., 2]) @ ry @ rx,
    )


def R_to_euler(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation -> (..., 3) roll, pitch, yaw with pitch in [-π/2, π/2]."""
    R = np.asarray(R, dtype=float)
    pitch = np.arcsin(np.clip(-R[..., 2, 0], -1.0, 1.0))
    roll = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    yaw = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    return np.stack([roll, pitch, yaw], -1)


def euler_rate_matrix(rpy: np.ndarray) -> np.ndarray:
    """E(roll, pitch): body rates -> ZYX Euler-angle rates, (..., 3, 3) (docs/math.md §6.3).

    Singular at pitch = ±90°; callers on a ground vehicle guard against it.
    """
    rpy = np.asarray(rpy, dtype=float)
    r, p = rpy[..., 0], rpy[..., 1]
    cr, sr, cp, tp = np.cos(r), np.sin(r), np.cos(p), np.tan(p)
    o, z = np.ones_like(r), np.zeros_like(r)
    return np.stack(
        [
            np.stack([o, sr * tp, cr * tp], -1),
            np.stack([z, cr, -sr], -1),
            np.stack([z, sr / cp, cr / cp], -1),
        ],
        -2,
    )


def euler_rate_matrix_inverse(rpy: np.ndarray) -> np.ndarray:
    """E⁻¹(roll, pitch): ZYX Euler-angle rates -> body rates, (..., 3, 3); defined at every pitch."""
    rpy = np.asarray(rpy, dtype=float)
    r, p = rpy[..., 0], rpy[..., 1]
    cr, sr, cp, sp = np.cos(r), np.sin(r), np.cos(p), np.sin(p)
    o, z = np.ones_like(r), np.zeros_like(r)
    return np.stack(
        [
            np.stack([o, z, -sp], -1),
            np.stack([z, cr, sr * cp], -1),
            np.stack([z, -sr, cr * cp], -1),
        ],
        -2,
    )


def euler_rate_jacobian(rpy: np.ndarray, omega: np.ndarray) -> np.ndarray:
    """∂(E(rpy) ω)/∂rpy, (..., 3, 3); the yaw column is zero (docs/math.md §6.3)."""
    rpy = np.asarray(rpy, dtype=float)
    omega = np.asarray(omega, dtype=float)
    r, p = rpy[..., 0], rpy[..., 1]
    wy, wz = omega[..., 1], omega[..., 2]
    cr, sr, cp, sp, tp = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.tan(p)
    a = wy * cr - wz * sr
    b = wy * sr + wz * cr
    z = np.zeros_like(a)
    return np.stack(
        [
            np.stack([tp * a, b / cp**2, z], -1),
            np.stack([-b, z, z], -1),
            np.stack([a / cp, b * sp / cp**2, z], -1),
        ],
        -2,
    )


# --------------------------------------------------------------------------------------------
# Quaternions (w, x, y, z)


def R_to_quat(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) -> (..., 4) unit quaternion (w, x, y, z) with w >= 0. Robust for all angles."""
    R = np.asarray(R, dtype=float)
    batch = R.shape[:-2]
    Rf = R.reshape(-1, 3, 3)
    q = np.empty((Rf.shape[0], 4))
    tr = np.trace(Rf, axis1=1, axis2=2)
    # Shepperd's method: pick the largest of (w, x, y, z) to divide by.
    cand = np.stack([tr, Rf[:, 0, 0], Rf[:, 1, 1], Rf[:, 2, 2]], 1)
    k = np.argmax(cand, 1)
    for i in range(4):
        m = k == i
        if not np.any(m):
            continue
        r = Rf[m]
        if i == 0:
            s = np.sqrt(1.0 + tr[m]) * 2.0
            q[m] = np.stack(
                [0.25 * s, (r[:, 2, 1] - r[:, 1, 2]) / s, (r[:, 0, 2] - r[:, 2, 0]) / s, (r[:, 1, 0] - r[:, 0, 1]) / s],
                1,
            )
        elif i == 1:
            s = np.sqrt(1.0 + r[:, 0, 0] - r[:, 1, 1] - r[:, 2, 2]) * 2.0
            q[m] = np.stack(
                [(r[:, 2, 1] - r[:, 1, 2]) / s, 0.25 * s, (r[:, 0, 1] + r[:, 1, 0]) / s, (r[:, 0, 2] + r[:, 2, 0]) / s],
                1,
            )
        elif i == 2:
            s = np.sqrt(1.0 + r[:, 1, 1] - r[:, 0, 0] - r[:, 2, 2]) * 2.0
            q[m] = np.stack(
                [(r[:, 0, 2] - r[:, 2, 0]) / s, (r[:, 0, 1] + r[:, 1, 0]) / s, 0.25 * s, (r[:, 1, 2] + r[:, 2, 1]) / s],
                1,
            )
        else:
            s = np.sqrt(1.0 + r[:, 2, 2] - r[:, 0, 0] - r[:, 1, 1]) * 2.0
            q[m] = np.stack(
                [(r[:, 1, 0] - r[:, 0, 1]) / s, (r[:, 0, 2] + r[:, 2, 0]) / s, (r[:, 1, 2] + r[:, 2, 1]) / s, 0.25 * s],
                1,
            )
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 0] < 0] *= -1.0
    return q.reshape(*batch, 4)


def quat_to_R(q: np.ndarray) -> np.ndarray:
    """(..., 4) quaternion (w, x, y, z), normalised here -> (..., 3, 3)."""
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def euler_to_quat(rpy: np.ndarray) -> np.ndarray:
    return R_to_quat(euler_to_R(rpy))


def quat_to_euler(q: np.ndarray) -> np.ndarray:
    return R_to_euler(quat_to_R(q))


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a ⊗ b, (..., 4); R(a ⊗ b) = R(a) R(b)."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        -1,
    )


# --------------------------------------------------------------------------------------------
# SO(3) exponential (small rotations from body rates)


def skew(v: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 3, 3) cross-product matrix."""
    v = np.asarray(v, dtype=float)
    z = np.zeros_like(v[..., 0])
    return np.stack(
        [
            np.stack([z, -v[..., 2], v[..., 1]], -1),
            np.stack([v[..., 2], z, -v[..., 0]], -1),
            np.stack([-v[..., 1], v[..., 0], z], -1),
        ],
        -2,
    )


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rotation vector (..., 3) -> (..., 3, 3) by Rodrigues' formula."""
    w = np.asarray(w, dtype=float)
    th = np.linalg.norm(w, axis=-1)[..., None, None]
    K = skew(w)
    small = th < 1e-8
    ths = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th**2 / 6.0, np.sin(ths) / ths)
    b = np.where(small, 0.5 - th**2 / 24.0, (1.0 - np.cos(ths)) / ths**2)
    return np.eye(3) + a * K + b * (K @ K)


def so3_right_jacobian(w: np.ndarray) -> np.ndarray:
    """J_r(w) (..., 3, 3): exp(w + δ) ≈ exp(w) exp(J_r(w) δ) for a small δ."""
    w = np.asarray(w, dtype=float)
    th = np.linalg.norm(w, axis=-1)[..., None, None]
    K = skew(w)
    small = th < 1e-4
    ths = np.where(small, 1.0, th)
    b = np.where(small, 0.5 - th**2 / 24.0, (1.0 - np.cos(ths)) / ths**2)
    c = np.where(small, 1.0 / 6.0 - th**2 / 120.0, (ths - np.sin(ths)) / ths**3)
    return np.eye(3) - b * K + c * (K @ K)  # type: ignore[no-any-return]


def so3_log(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) -> rotation vector (..., 3); angle in [0, π]."""
    R = np.asarray(R, dtype=float)
    cos = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    th = np.arccos(cos)
    v = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    s = np.sin(th)
    small = s < 1e-7
    scale = np.where(small, 0.5, th / (2.0 * np.where(small, 1.0, s)))
    out = v * scale[..., None]
    # near π the antisymmetric part vanishes: take the axis from the symmetric part
    near_pi = small & (th > 1.0)
    if np.any(near_pi):
        Rn = R[near_pi]
        B = (Rn + np.eye(3)) / 2.0
        idx = np.argmax(np.diagonal(B, axis1=-2, axis2=-1), -1)
        axis = B[np.arange(len(idx)), :, idx]
        axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
        out[near_pi] = axis * th[near_pi][..., None]
    return out


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """Angle (rad) of rotation matrices (..., 3, 3)."""
    return np.arccos(np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0))


# --------------------------------------------------------------------------------------------
# SE(3): 4x4 homogeneous matrices, and 6-vector poses (x, y, z, roll, pitch, yaw)


def se3(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Build (..., 4, 4) from rotation (..., 3, 3) and translation (..., 3)."""
    R = np.asarray(R, dtype=float)
    t = np.asarray(t, dtype=float)
    batch = np.broadcast_shapes(R.shape[:-2], t.shape[:-1])
    T = np.zeros((*batch, 4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def pose6_to_T(x: np.ndarray) -> np.ndarray:
    """(..., 6) (x, y, z, roll, pitch, yaw) -> (..., 4, 4) T_world_robot."""
    x = np.asarray(x, dtype=float)
    return se3(euler_to_R(x[..., 3:6]), x[..., :3])


def T_to_pose6(T: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=float)
    return np.concatenate([T[..., :3, 3], R_to_euler(T[..., :3, :3])], -1)


def se3_inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of (..., 4, 4) rigid transforms without a general matrix inverse."""
    T = np.asarray(T, dtype=float)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    return se3(Rt, -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3]))


def se3_compose(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """A ∘ B for (..., 4, 4) transforms (broadcasting)."""
    return np.asarray(A, dtype=float) @ np.asarray(B, dtype=float)


def transform_points(T: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Apply T (4, 4) or (N, 4, 4) to points (N, 3) -> (N, 3)."""
    T = np.asarray(T, dtype=float)
    pts = np.asarray(pts, dtype=float)
    return np.einsum("...ij,...j->...i", T[..., :3, :3], pts) + T[..., :3, 3]


def pose6_compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Compose 6-vector poses: T(a) T(b), (..., 6)."""
    return T_to_pose6(pose6_to_T(a) @ pose6_to_T(b))


def pose6_inverse(a: np.ndarray) -> np.ndarray:
    return T_to_pose6(se3_inverse(pose6_to_T(a)))


# --------------------------------------------------------------------------------------------
# SE(2): 3-vector poses (x, y, yaw) and 3x3 homogeneous matrices


def rot2(yaw: np.ndarray | float) -> np.ndarray:
    """(...,) -> (..., 2, 2)."""
    yaw = np.asarray(yaw, dtype=float)
    c, s = np.cos(yaw), np.sin(yaw)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def drot2(yaw: np.ndarray | float) -> np.ndarray:
    """∂R2/∂yaw, (..., 2, 2)."""
    yaw = np.asarray(yaw, dtype=float)
    c, s = np.cos(yaw), np.sin(yaw)
    return np.stack([np.stack([-s, -c], -1), np.stack([c, -s], -1)], -2)


def pose2_to_T(x: np.ndarray) -> np.ndarray:
    """(..., 3) (x, y, yaw) -> (..., 3, 3)."""
    x = np.asarray(x, dtype=float)
    T = np.zeros((*x.shape[:-1], 3, 3))
    T[..., :2, :2] = rot2(x[..., 2])
    T[..., :2, 2] = x[..., :2]
    T[..., 2, 2] = 1.0
    return T


def T_to_pose2(T: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=float)
    return np.stack([T[..., 0, 2], T[..., 1, 2], np.arctan2(T[..., 1, 0], T[..., 0, 0])], -1)


def pose2_compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a ⊕ b for (..., 3) planar poses; the yaw is wrapped."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    return np.stack(
        [
            a[..., 0] + c * b[..., 0] - s * b[..., 1],
            a[..., 1] + s * b[..., 0] + c * b[..., 1],
            wrap_angle(a[..., 2] + b[..., 2]),
        ],
        -1,
    )


def pose2_inverse(a: np.ndarray) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    return np.stack([-c * a[..., 0] - s * a[..., 1], s * a[..., 0] - c * a[..., 1], wrap_angle(-a[..., 2])], -1)


def pose2_compose_jacobians(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Jacobians of a ⊕ b with respect to a and b, each (..., 3, 3)."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    batch = np.broadcast_shapes(a.shape[:-1], b.shape[:-1])
    Ja = np.zeros((*batch, 3, 3))
    Ja[..., 0, 0] = 1.0
    Ja[..., 1, 1] = 1.0
    Ja[..., 2, 2] = 1.0
    Ja[..., 0, 2] = -s * b[..., 0] - c * b[..., 1]
    Ja[..., 1, 2] = c * b[..., 0] - s * b[..., 1]
    Jb = np.zeros((*batch, 3, 3))
    Jb[..., :2, :2] = rot2(a[..., 2])
    Jb[..., 2, 2] = 1.0
    return Ja, Jb


def transform_points2(x: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Planar pose (3,) applied to points (N, 2) -> (N, 2)."""
    x = np.asarray(x, dtype=float)
    return np.asarray(pts, dtype=float) @ rot2(x[2]).T + x[:2]


# --------------------------------------------------------------------------------------------
# Frame conversions at borders


def optical_to_robot_points(xyz_C: np.ndarray) -> np.ndarray:
    """Points in the optical frame (x right, y down, z fwd) -> FRD robot axes, (N, 3)."""
    return np.asarray(xyz_C, dtype=float) @ R_ROBOT_OPTICAL.T


def T_optical_to_robot(T_C0_C: np.ndarray) -> np.ndarray:
    """Re-express a camera-optical pose (e.g. KITTI, EuRoC left camera) in FRD axes.

    Both sides are transformed (docs/interfaces.md §1.3): T_R0_R = A T_C0_C A^T with A the axis map.
    """
    A = se3(R_ROBOT_OPTICAL, np.zeros(3))
    return A @ np.asarray(T_C0_C, dtype=float) @ se3_inverse(A)


# --------------------------------------------------------------------------------------------
# Numerical Jacobians (used by tests and by the checks of analytic Jacobians)


def numerical_jacobian(f, x: np.ndarray, eps: float = 1e-6, wrap: np.ndarray | None = None) -> np.ndarray:
    """Central-difference Jacobian of f: R^n -> R^m at x. ``wrap`` marks output rows that are angles."""
    x = np.asarray(x, dtype=float)
    f0 = np.asarray(f(x), dtype=float)
    J = np.zeros((f0.size, x.size))
    for i in range(x.size):
        dx = np.zeros_like(x)
        dx[i] = eps
        d = np.asarray(f(x + dx), dtype=float).ravel() - np.asarray(f(x - dx), dtype=float).ravel()
        if wrap is not None:
            d = np.where(wrap, wrap_angle(d), d)
        J[:, i] = d / (2.0 * eps)
    return J


# --------------------------------------------------------------------------------------------
# Point-set alignment (Umeyama 1991), used by RANSAC (docs/math.md §5.1) and evaluation (§11)


def umeyama(a: np.ndarray, b: np.ndarray, with_scale: bool = True) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares (s, R, t) with b ≈ s R a + t for point sets a, b of shape (n, d), d = 2 or 3.

    Closed form of Umeyama (1991): C_ab = UDV^T, S = diag(1, …, det U det V), R = U S V^T,
    s = tr(DS)/σ_a², t = μ_b − s R μ_a. With ``with_scale=False`` s is fixed to 1 (rigid).
    """
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    n, d = a.shape
    mu_a, mu_b = a.mean(0), b.mean(0)
    da, db = a - mu_a, b - mu_b
    var_a = float(np.sum(da * da) / n)
    C = db.T @ da / n
    U, D, Vt = np.linalg.svd(C)
    S = np.ones(d)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[-1] = -1.0
    R = (U * S) @ Vt
    s = float(np.sum(D * S) / var_a) if (with_scale and var_a > 0) else 1.0
    t = mu_b - s * R @ mu_a
    return s, R, t


def umeyama_batch(a: np.ndarray, b: np.ndarray, with_scale: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Umeyama over a batch of small samples: a, b (K, n, d) -> s (K,), R (K, d, d), t (K, d)."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    k, n, d = a.shape
    mu_a, mu_b = a.mean(1), b.mean(1)
    da, db = a - mu_a[:, None], b - mu_b[:, None]
    var_a = np.sum(da * da, axis=(1, 2)) / n
    C = np.einsum("kni,knj->kij", db, da) / n
    U, D, Vt = np.linalg.svd(C)
    S = np.ones((k, d))
    S[np.linalg.det(U) * np.linalg.det(Vt) < 0, -1] = -1.0
    R = (U * S[:, None, :]) @ Vt
    if with_scale:
        s = np.sum(D * S, 1) / np.where(var_a > 0, var_a, 1.0)
    else:
        s = np.ones(k)
    t = mu_b - s[:, None] * np.einsum("kij,kj->ki", R, mu_a)
    return s, R, t
