"""The FastSLAM step in numba: one per-particle algorithm for 2D and 3D and every measurement model.

:func:`fastslam_step` (dense landmark arrays) and :func:`fastslam_step_store` (the copy-on-write
:class:`~robotd.slam._store.LandmarkStore` the filter keeps) run FastSLAM 1.0 or 2.0's measurement
step (docs/math.md §9, §10) for the Cartesian models (§7.1, §7.2), the 2D range–bearing model (§7.2)
and the stereo pixel models (docs/slam.md "Measurement models", with their constant noise). They
have the signature and the effects of the readable per-particle twin ``fastslam_step_reference``
(tests/support/reference_fastslam.py) and agree with it to 1e-9 given the same ``eps``; robotd has no
other implementation of the step. Each particle is one iteration of a ``prange`` loop (one
contiguous range of particles per thread, sharing its scratch arrays), so there are no per-call
numpy dispatch costs.

One algorithm, written once (``_particle``): the importance weight and the proposal in one pass
over the identified landmarks, the pose drawn, the landmark EKFs at it, the new landmarks. It
evaluates the §9/§10 formulas rewritten in the world frame (derivation above ``_rot3_cs``), which
needs about a third fewer operations than the robot-frame form of the reference, on tuples that
LLVM keeps in registers, and the proposal advances the cosines and sines of the pose angles
instead of calling trig functions per observation. What differs between the dimensions and the
models is small algebra that numba resolves while compiling (``numba.extending.overload``): the
dimension by the marker ``D`` (:class:`Dim2`, :class:`Dim3`: ``_particle``'s overload binds the
3D or the 2D functions of "the per-dimension algebra" below), the model by ``rig`` (None:
Cartesian; the pixel model's constants; :class:`RangeBearing`: ``_meas3``, ``_init3`` and their
kin dispatch on its type). numba compiles one specialised step per (dimension, model) in use, with
no run-time branch in the loop (measured: a run-time model branch cost the Cartesian 2D and
FastSLAM 1.0 steps 10–40 %). Adding a measurement model: a ``rig`` type and its branches of
``_meas*``, ``_init*``, ``_noise*`` and ``_depth_logw``; the algorithm does not change.

The kernel gives bit for bit the results of the separate 3D and 2D kernels it replaced (robotd
581c06c; 50 random problems, every model and version, cold and warm numba caches), so recorded
trajectories stay the same. Under fast-math that is fragile: LLVM reassociates sums in an order
that depends on the shape of the code, and variants that computed the same values differently
(the proposal's trig state as a tuple or through a helper; the dimension dispatched by overloads
inlined at every call) moved the 3D results in their last bits. Check an edit of ``_particle`` or
its algebra the same way (old against new, cold against cold and warm against warm: numba's own
compiled and cached code differ in the last bits in 3D).

Compiled by :func:`robotd.core.jit.jit` (first call compiles for ~10–20 s, later processes load the disk
cache; ``NUMBA_CACHE_DIR`` must be writable by the service, else every process compiles anew).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba as nb
import numpy as np
from numba import types
from numba.extending import overload

from robotd.core.errors import InputError
from robotd.core.jit import jit
from robotd.slam._store import LandmarkStore
from robotd.slam.models import (
    CARTESIAN_2D,
    CARTESIAN_3D,
    RANGE_BEARING_2D,
    MeasurementModel,
    stereo_pixel_model,
)
from robotd.slam.models import PIXEL_MIN_DEPTH_M as _PIXEL_MIN_DEPTH

_TWO_PI = 2.0 * math.pi
_LOG_2PI = math.log(2.0 * math.pi)
# Fast-math without the no-NaN/no-inf assumptions: fused multiply-adds and reassociation let LLVM
# vectorise the small fixed-size products (~10-15 % faster); results still agree with the
# reference to ~1e-14.
_FM = {"contract", "reassoc", "arcp", "nsz"}


# The kernel's compile-time choices. The dimension is a marker type (an empty named tuple), the
# measurement model is ``rig``: None (Cartesian), the pixel model's constants (a 10-tuple, see
# ``_pixel_rig``) or the RangeBearing marker. numba types each as its own type, so the overloads
# below resolve them while compiling (``_step`` is specialised per (dimension, model)).


class Dim2(NamedTuple):
    """Marker: the 2D filter (pose (x, y, ψ), landmarks (x, y))."""


class Dim3(NamedTuple):
    """Marker: the 3D filter (pose (x, y, z, roll, pitch, yaw), landmarks (x, y, z))."""


class RangeBearing(NamedTuple):
    """Marker ``rig`` of the 2D range–bearing model (§7.2; its noise is each observation's Q)."""


def _is_3d(D: types.Type) -> bool:
    """Typing-time test of the dimension marker's type."""
    return getattr(D, "instance_class", None) is Dim3


def _is_range_bearing(rig: types.Type) -> bool:
    """Typing-time test of ``rig``'s type."""
    return getattr(rig, "instance_class", None) is RangeBearing


@jit(fastmath=_FM)
def _wrap(a: float) -> float:
    w = a - _TWO_PI * math.floor((a + math.pi) / _TWO_PI)
    if w == -math.pi:
        w = math.pi
    return w


@jit(fastmath=_FM)
def _mm_into(A, B, C, n: int, k: int, m: int) -> None:  # type: ignore[no-untyped-def]
    """C = A @ B for (n, k) @ (k, m); sizes are passed so that they are compile-time constants."""
    for i in range(n):
        for j in range(m):
            acc = 0.0
            for t in range(k):
                acc += A[i, t] * B[t, j]
            C[i, j] = acc


@jit(fastmath=_FM)
def _cholesky_into(A, L, n: int) -> bool:  # type: ignore[no-untyped-def]
    """Lower Cholesky factor into L; False when A is not positive definite."""
    for i in range(n):
        for j in range(n):
            L[i, j] = 0.0
    for j in range(n):
        s = A[j, j]
        for t in range(j):
            s -= L[j, t] * L[j, t]
        if s <= 0.0:
            return False
        L[j, j] = math.sqrt(s)
        for i in range(j + 1, n):
            s = A[i, j]
            for t in range(j):
                s -= L[i, t] * L[j, t]
            L[i, j] = s / L[j, j]
    return True


# ---------------------------------------------------------------------------------------------
# 3D (Cartesian §7.1) in the world frame.
#
# With R = R(x) and d = m - p, the measurement is z = R^T d, H_m = R^T and H_x = R^T Ĥ with
# Ĥ = [-I | A], A[:, a] = d × W_a, where W_a is the world-frame axis of Euler angle a
# (∂R/∂a = [W_a]× R for ZYX angles: W_roll = R e_x, W_pitch = R_z e_y, W_yaw = e_z; docs/math.md
# §1.3). Every robot-frame innovation covariance is then Ψ = R^T Ψ_w R with
# Ψ_w = Ĥ Σ Ĥ^T + C + R Q R^T, and with ν_w = R ν = R z - d the formulas of §9/§10 become
#   ν^T Ψ^{-1} ν = ν_w^T Ψ_w^{-1} ν_w,  det Ψ = det Ψ_w,
#   pose gain:      K_x ν = (Σ Ĥ^T) Ψ_w^{-1} ν_w,   K_x Ψ K_x^T = (Σ Ĥ^T) Ψ_w^{-1} (Σ Ĥ^T)^T,
#   landmark gain:  K H = C Ψ_w^{-1} =: K_w,  K ν = K_w ν_w,  K Q K^T = K_w (R Q R^T) K_w^T,
# so the Joseph update is (I - K_w) C (I - K_w)^T + K_w Q_w K_w^T. These are the quantities of the
# robot-frame formulas (the reference) up to round-off, with about a third fewer operations: H_x is
# never formed and the Euler-angle derivatives are three cross products.
#
# The 3×3 algebra works on tuples, which LLVM keeps in registers (small numpy scratch arrays are
# heap memory that it must assume may alias the landmark pool). Symmetric 3×3 matrices are
# 6-tuples (a00, a01, a02, a11, a12, a22), general ones 9-tuples in row order. Q and the landmark
# covariances are covariances: only their upper triangles are read.


@jit(fastmath=_FM, inline="always")
def _rot3_cs(cr: float, sr: float, cp: float, sp: float, cy: float, sy: float):  # type: ignore[no-untyped-def]
    """R_z(yaw) R_y(pitch) R_x(roll) as a 9-tuple (row order) from the angles' cosines and sines."""
    return (
        cy * cp,
        cy * sp * sr - sy * cr,
        cy * sp * cr + sy * sr,
        sy * cp,
        sy * sp * sr + cy * cr,
        sy * sp * cr - cy * sr,
        -sp,
        cp * sr,
        cp * cr,
    )


@jit(fastmath=_FM, inline="always")
def _rot3t(roll: float, pitch: float, yaw: float):  # type: ignore[no-untyped-def]
    """(R_z(yaw) R_y(pitch) R_x(roll) as a 9-tuple, sin yaw, cos yaw) — the latter give W_pitch."""
    cy, sy = math.cos(yaw), math.sin(yaw)
    return _rot3_cs(math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch), cy, sy), sy, cy


@jit(fastmath=_FM, inline="always")
def _turn(c: float, s: float, delta: float):  # type: ignore[no-untyped-def]
    """(cos(a + δ), sin(a + δ)) from c = cos a, s = sin a by the angle-addition formulas.

    The proposal moves the pose angles by small steps; for |δ| < 0.05 the Taylor series used here
    are exact to double precision (first omitted terms δ^10/10! and δ^11/11! < 1e-19), which is
    several times cheaper than ``sin``/``cos`` of the full angle (the rounding of the recurrence
    grows to ~1e-14 after hundreds of observations, far inside the 1e-9 agreement).
    """
    if abs(delta) < 0.05:
        d2 = delta * delta
        sd = delta * (1.0 - d2 / 6.0 * (1.0 - d2 / 20.0 * (1.0 - d2 / 42.0 * (1.0 - d2 / 72.0))))
        cd = 1.0 - d2 / 2.0 * (1.0 - d2 / 12.0 * (1.0 - d2 / 30.0 * (1.0 - d2 / 56.0)))
    else:
        sd, cd = math.sin(delta), math.cos(delta)
    return c * cd - s * sd, s * cd + c * sd


@jit(fastmath=_FM, inline="always")
def _sym3(C):  # type: ignore[no-untyped-def]
    """Upper triangle of a 3×3 array as a 6-tuple."""
    return (C[0, 0], C[0, 1], C[0, 2], C[1, 1], C[1, 2], C[2, 2])


@jit(fastmath=_FM, inline="always")
def _sandwich3(R, S):  # type: ignore[no-untyped-def]
    """R S R^T for R a 9-tuple and S a symmetric 6-tuple (returns a 6-tuple)."""
    s00, s01, s02, s11, s12, s22 = S
    # rows of R S
    a0 = R[0] * s00 + R[1] * s01 + R[2] * s02
    a1 = R[0] * s01 + R[1] * s11 + R[2] * s12
    a2 = R[0] * s02 + R[1] * s12 + R[2] * s22
    b0 = R[3] * s00 + R[4] * s01 + R[5] * s02
    b1 = R[3] * s01 + R[4] * s11 + R[5] * s12
    b2 = R[3] * s02 + R[4] * s12 + R[5] * s22
    c0 = R[6] * s00 + R[7] * s01 + R[8] * s02
    c1 = R[6] * s01 + R[7] * s11 + R[8] * s12
    c2 = R[6] * s02 + R[7] * s12 + R[8] * s22
    return (
        a0 * R[0] + a1 * R[1] + a2 * R[2],
        a0 * R[3] + a1 * R[4] + a2 * R[5],
        a0 * R[6] + a1 * R[7] + a2 * R[8],
        b0 * R[3] + b1 * R[4] + b2 * R[5],
        b0 * R[6] + b1 * R[7] + b2 * R[8],
        c0 * R[6] + c1 * R[7] + c2 * R[8],
    )


@jit(fastmath=_FM, inline="always")
def _add3(A, B):  # type: ignore[no-untyped-def]
    """Sum of two symmetric 6-tuples."""
    return (A[0] + B[0], A[1] + B[1], A[2] + B[2], A[3] + B[3], A[4] + B[4], A[5] + B[5])


@jit(fastmath=_FM, inline="always")
def _inv_sym3(A):  # type: ignore[no-untyped-def]
    """(inverse as a 6-tuple, determinant) of a symmetric 3×3 6-tuple (adjugate formula)."""
    a00, a01, a02, a11, a12, a22 = A
    c00 = a11 * a22 - a12 * a12
    c01 = a12 * a02 - a01 * a22
    c02 = a01 * a12 - a11 * a02
    c11 = a00 * a22 - a02 * a02
    c12 = a01 * a02 - a00 * a12
    c22 = a00 * a11 - a01 * a01
    det = a00 * c00 + a01 * c01 + a02 * c02
    r = 1.0 / det
    return (c00 * r, c01 * r, c02 * r, c11 * r, c12 * r, c22 * r), det


@jit(fastmath=_FM, inline="always")
def _logpdf3(n0: float, n1: float, n2: float, Si, det: float) -> float:  # type: ignore[no-untyped-def]
    """log N(ν; 0, S) from S^{-1} (6-tuple) and det S."""
    maha = (
        Si[0] * n0 * n0
        + Si[3] * n1 * n1
        + Si[5] * n2 * n2
        + 2.0 * (Si[1] * n0 * n1 + Si[2] * n0 * n2 + Si[4] * n1 * n2)
    )
    return -0.5 * (maha + math.log(det) + 3.0 * _LOG_2PI)


@jit(fastmath=_FM, inline="always")
def _innov3t(x, m, zm, R):  # type: ignore[no-untyped-def]
    """(d = m - p, ν_w = R z_meas - d) as 3-tuples."""
    d0, d1, d2 = m[0] - x[0], m[1] - x[1], m[2] - x[2]
    z0, z1, z2 = zm[0], zm[1], zm[2]
    nu = (
        R[0] * z0 + R[1] * z1 + R[2] * z2 - d0,
        R[3] * z0 + R[4] * z1 + R[5] * z2 - d1,
        R[6] * z0 + R[7] * z1 + R[8] * z2 - d2,
    )
    return (d0, d1, d2), nu


@jit(fastmath=_FM, inline="always")
def _pose_part3t(Sg, d, R, sy: float, cy: float, T):  # type: ignore[no-untyped-def]
    """T = Σ Ĥ^T (into the 6×3 array T) and Ĥ Σ Ĥ^T (returned, 6-tuple) for Σ = Sg (6×6).

    Ĥ = [-I | A] with A's columns d × W_roll, d × W_pitch, d × e_z (W_roll = R e_x,
    W_pitch = (-sin yaw, cos yaw, 0)).
    """
    d0, d1, d2 = d
    a00, a01, a02 = d1 * R[6] - d2 * R[3], -d2 * cy, d1
    a10, a11, a12 = d2 * R[0] - d0 * R[6], -d2 * sy, -d0
    a20, a21 = d0 * R[3] - d1 * R[0], d0 * cy + d1 * sy  # a22 = 0
    for i in range(6):
        s3, s4, s5 = Sg[i, 3], Sg[i, 4], Sg[i, 5]
        T[i, 0] = -Sg[i, 0] + s3 * a00 + s4 * a01 + s5 * a02
        T[i, 1] = -Sg[i, 1] + s3 * a10 + s4 * a11 + s5 * a12
        T[i, 2] = -Sg[i, 2] + s3 * a20 + s4 * a21
    return (
        -T[0, 0] + a00 * T[3, 0] + a01 * T[4, 0] + a02 * T[5, 0],
        -T[0, 1] + a00 * T[3, 1] + a01 * T[4, 1] + a02 * T[5, 1],
        -T[0, 2] + a00 * T[3, 2] + a01 * T[4, 2] + a02 * T[5, 2],
        -T[1, 1] + a10 * T[3, 1] + a11 * T[4, 1] + a12 * T[5, 1],
        -T[1, 2] + a10 * T[3, 2] + a11 * T[4, 2] + a12 * T[5, 2],
        -T[2, 2] + a20 * T[3, 2] + a21 * T[4, 2],
    )


# Pixel model (docs/slam.md "Measurement models") in the same world frame. With q = Rᵀ d (depth
# clamped to PIXEL_MIN_DEPTH_M: X̃) and G = J_π(q̃) Rᵀ the pixel model's H_m (H_x = G Ĥ), its
# formulas equal those of a Cartesian model with
#   ν_w = G⁻¹ ν_px,  Q_w = G⁻¹ Q_px G⁻ᵀ,  det Ψ_px = g · det Ψ_w,  g = det(G)² = (f³ b / X̃⁴)²,
# and G⁻¹ = R J_tri, J_tri = ∂q/∂(x_L, x_R, y) = s [[−X̃, X̃, 0], [−(Y − b/2), Y + b/2, 0], [−Z, Z, b]]
# with s = X̃/(f b), whose columns give R J_tri = s [−D + h | D + h | b r2], D = R q̃, h = (b/2) r1
# (r1, r2 R's second and third columns). For the model's noise Q_px = diag(σx², σx², σy²):
#   ν_w = s (D (ν_R − ν_L) + h (ν_L + ν_R) + b r2 ν_y),  Q_w = s² (2σx² D Dᵀ + A),
#   A = (σx² b²/2) r1 r1ᵀ + σy² b² r2 r2ᵀ (a function of the pose only),
# cheaper than the Cartesian R Q Rᵀ; and since ν = z − π(q̃), s (ν_R − ν_L) = 1 − X̃ (x_L − x_R)/(f b),
# s b/2 (ν_L + ν_R) = X̃ (x_L + x_R − 2 p_x)/(2 f) − Y, s b ν_y = X̃ (y − p_y)/f − Z: no division on the
# update's path. The weights' log det Ψ_px = log det Ψ_w + log g: the log g terms are collected per
# particle (``_depth_acc``, ``_depth_logw``). ``rig`` is (f, p_x, p_y, b, σx², σy², 1/(f b), 1/f,
# log (f³ b)², log (f² b)²) for the pixel model (``_pixel_rig``) and None for the Cartesian one;
# numba compiles the two apart (no branch in the kernels: measured, a run-time branch cost the
# Cartesian 2D and FastSLAM 1.0 steps 10–40 %).


def _noise3(R, rig):  # type: ignore[no-untyped-def]
    """Pixel model: A (6-tuple) of Q_w for the rotation R (9-tuple); Cartesian: 0.0 (unused). numba only."""
    raise NotImplementedError("numba only: an @overload stub, compiled into the jitted kernels")


@overload(_noise3, inline="always", jit_options={"fastmath": _FM})
def _noise3_impl(R, rig):  # type: ignore[no-untyped-def]
    if isinstance(rig, types.NoneType):
        return lambda R, rig: 0.0

    def pixel(R, rig):  # type: ignore[no-untyped-def]
        b2 = rig[3] * rig[3]
        k1, k2 = 0.5 * rig[4] * b2, rig[5] * b2
        u0, u1, u2 = R[1], R[4], R[7]
        v0, v1, v2 = R[2], R[5], R[8]
        return (
            k1 * u0 * u0 + k2 * v0 * v0,
            k1 * u0 * u1 + k2 * v0 * v1,
            k1 * u0 * u2 + k2 * v0 * v2,
            k1 * u1 * u1 + k2 * v1 * v1,
            k1 * u1 * u2 + k2 * v1 * v2,
            k1 * u2 * u2 + k2 * v2 * v2,
        )

    return pixel


@jit(fastmath=_FM, inline="always")
def _pixel_cov3(D0: float, D1: float, D2: float, sc: float, A, vx: float):  # type: ignore[no-untyped-def]
    """Q_w = s² (2σx² D Dᵀ + A) as a 6-tuple."""
    s2 = sc * sc
    k = 2.0 * vx * s2
    return (
        k * D0 * D0 + s2 * A[0],
        k * D0 * D1 + s2 * A[1],
        k * D0 * D2 + s2 * A[2],
        k * D1 * D1 + s2 * A[3],
        k * D1 * D2 + s2 * A[4],
        k * D2 * D2 + s2 * A[5],
    )


def _meas3(x, m, zm, Qm, R, rig, A):  # type: ignore[no-untyped-def]
    """One observation at pose x in the world frame: (d = m − p, ν_w, Q_w (6-tuple), X̃); numba only.

    Cartesian (``rig`` None): ν_w = R z − d, Q_w = R Q Rᵀ, X̃ None. Pixel: see above, X̃ the clamped
    depth for the weight's log g (Qm is not read: the noise is rig[4:6]; A = _noise3(R, rig)).
    """
    raise NotImplementedError("numba only: an @overload stub, compiled into the jitted kernels")


@overload(_meas3, inline="always", jit_options={"fastmath": _FM})
def _meas3_impl(x, m, zm, Qm, R, rig, A):  # type: ignore[no-untyped-def]
    if isinstance(rig, types.NoneType):

        def cartesian(x, m, zm, Qm, R, rig, A):  # type: ignore[no-untyped-def]
            d, nu = _innov3t(x, m, zm, R)
            return d, nu, _sandwich3(R, _sym3(Qm)), None

        return cartesian

    def pixel(x, m, zm, Qm, R, rig, A):  # type: ignore[no-untyped-def]
        px, py, vx, i_fb, i_f = rig[1], rig[2], rig[4], rig[6], rig[7]
        d0, d1, d2 = m[0] - x[0], m[1] - x[1], m[2] - x[2]
        X = R[0] * d0 + R[3] * d1 + R[6] * d2
        Y = R[1] * d0 + R[4] * d1 + R[7] * d2
        Z = R[2] * d0 + R[5] * d1 + R[8] * d2
        Xc = max(X, _PIXEL_MIN_DEPTH)
        e = Xc - X
        D0, D1, D2 = d0 + e * R[0], d1 + e * R[3], d2 + e * R[6]
        sc = Xc * i_fb
        # s (ν_R − ν_L), s b/2 (ν_L + ν_R), s b ν_y with ν = z − π(q̃), written without 1/X̃
        t = 1.0 - sc * (zm[0] - zm[1])
        u = 0.5 * Xc * i_f * (zm[0] + zm[1] - 2.0 * px) - Y
        v = Xc * i_f * (zm[2] - py) - Z
        nu = (t * D0 + u * R[1] + v * R[2], t * D1 + u * R[4] + v * R[5], t * D2 + u * R[7] + v * R[8])
        return (d0, d1, d2), nu, _pixel_cov3(D0, D1, D2, sc, A, vx), Xc

    return pixel


def _init3(x, zm, Qm, R, rig, A):  # type: ignore[no-untyped-def]
    """A new landmark at pose x (§9 step 3): (μ (3-tuple), Σ without the floor (6-tuple)); numba only.

    Cartesian (``rig`` None): μ = p + R z, Σ = R Q Rᵀ. Pixel: q = π⁻¹(z) (triangulation),
    μ = p + R q, Σ = (R J_tri) Q_px (R J_tri)ᵀ = s² (2σx² D Dᵀ + A), D = R q.
    """
    raise NotImplementedError("numba only: an @overload stub, compiled into the jitted kernels")


@overload(_init3, inline="always", jit_options={"fastmath": _FM})
def _init3_impl(x, zm, Qm, R, rig, A):  # type: ignore[no-untyped-def]
    if isinstance(rig, types.NoneType):

        def cartesian(x, zm, Qm, R, rig, A):  # type: ignore[no-untyped-def]
            z0, z1, z2 = zm[0], zm[1], zm[2]
            D0 = R[0] * z0 + R[1] * z1 + R[2] * z2
            D1 = R[3] * z0 + R[4] * z1 + R[5] * z2
            D2 = R[6] * z0 + R[7] * z1 + R[8] * z2
            return (x[0] + D0, x[1] + D1, x[2] + D2), _sandwich3(R, _sym3(Qm))

        return cartesian

    def pixel(x, zm, Qm, R, rig, A):  # type: ignore[no-untyped-def]
        f, px, py, b, vx = rig[0], rig[1], rig[2], rig[3], rig[4]
        r = b / (zm[0] - zm[1])
        z0 = f * r
        z1 = (zm[0] - px) * r - 0.5 * b
        z2 = (zm[2] - py) * r
        D0 = R[0] * z0 + R[1] * z1 + R[2] * z2
        D1 = R[3] * z0 + R[4] * z1 + R[5] * z2
        D2 = R[6] * z0 + R[7] * z1 + R[8] * z2
        return (x[0] + D0, x[1] + D1, x[2] + D2), _pixel_cov3(D0, D1, D2, z0 * rig[6], A, vx)

    return pixel


@jit(fastmath=_FM, inline="always")
def _joseph3(m, Cm, C, Qw, Pinv, nu) -> None:  # type: ignore[no-untyped-def]
    """A landmark's EKF update in the world frame, in place: m += K_w ν_w and
    Cm = (I - K_w) C (I - K_w)^T + K_w Q_w K_w^T with K_w = C Ψ_w^{-1} (C, Q_w, Ψ_w^{-1} 6-tuples)."""
    c00, c01, c02, c11, c12, c22 = C
    p00, p01, p02, p11, p12, p22 = Pinv
    # K_w = C Ψ_w^{-1} (general 3×3)
    k00 = c00 * p00 + c01 * p01 + c02 * p02
    k01 = c00 * p01 + c01 * p11 + c02 * p12
    k02 = c00 * p02 + c01 * p12 + c02 * p22
    k10 = c01 * p00 + c11 * p01 + c12 * p02
    k11 = c01 * p01 + c11 * p11 + c12 * p12
    k12 = c01 * p02 + c11 * p12 + c12 * p22
    k20 = c02 * p00 + c12 * p01 + c22 * p02
    k21 = c02 * p01 + c12 * p11 + c22 * p12
    k22 = c02 * p02 + c12 * p12 + c22 * p22
    m[0] += k00 * nu[0] + k01 * nu[1] + k02 * nu[2]
    m[1] += k10 * nu[0] + k11 * nu[1] + k12 * nu[2]
    m[2] += k20 * nu[0] + k21 * nu[1] + k22 * nu[2]
    # C' = (I - K_w) C (I - K_w)^T + K_w Q_w K_w^T: B = (I - K_w) C row by row, then the triangle
    b00 = (1.0 - k00) * c00 - k01 * c01 - k02 * c02
    b01 = (1.0 - k00) * c01 - k01 * c11 - k02 * c12
    b02 = (1.0 - k00) * c02 - k01 * c12 - k02 * c22
    b10 = -k10 * c00 + (1.0 - k11) * c01 - k12 * c02
    b11 = -k10 * c01 + (1.0 - k11) * c11 - k12 * c12
    b12 = -k10 * c02 + (1.0 - k11) * c12 - k12 * c22
    b20 = -k20 * c00 - k21 * c01 + (1.0 - k22) * c02
    b21 = -k20 * c01 - k21 * c11 + (1.0 - k22) * c12
    b22 = -k20 * c02 - k21 * c12 + (1.0 - k22) * c22
    q00, q01, q02, q11, q12, q22 = Qw
    # rows of K_w Q_w
    e00 = k00 * q00 + k01 * q01 + k02 * q02
    e01 = k00 * q01 + k01 * q11 + k02 * q12
    e02 = k00 * q02 + k01 * q12 + k02 * q22
    e10 = k10 * q00 + k11 * q01 + k12 * q02
    e11 = k10 * q01 + k11 * q11 + k12 * q12
    e12 = k10 * q02 + k11 * q12 + k12 * q22
    e20 = k20 * q00 + k21 * q01 + k22 * q02
    e21 = k20 * q01 + k21 * q11 + k22 * q12
    e22 = k20 * q02 + k21 * q12 + k22 * q22
    n00 = b00 * (1.0 - k00) - b01 * k01 - b02 * k02 + e00 * k00 + e01 * k01 + e02 * k02
    n01 = -b00 * k10 + b01 * (1.0 - k11) - b02 * k12 + e00 * k10 + e01 * k11 + e02 * k12
    n02 = -b00 * k20 - b01 * k21 + b02 * (1.0 - k22) + e00 * k20 + e01 * k21 + e02 * k22
    n11 = -b10 * k10 + b11 * (1.0 - k11) - b12 * k12 + e10 * k10 + e11 * k11 + e12 * k12
    n12 = -b10 * k20 - b11 * k21 + b12 * (1.0 - k22) + e10 * k20 + e11 * k21 + e12 * k22
    n22 = -b20 * k20 - b21 * k21 + b22 * (1.0 - k22) + e20 * k20 + e21 * k21 + e22 * k22
    Cm[0, 0], Cm[1, 1], Cm[2, 2] = n00, n11, n22
    Cm[0, 1] = Cm[1, 0] = n01
    Cm[0, 2] = Cm[2, 0] = n02
    Cm[1, 2] = Cm[2, 1] = n12


# ---------------------------------------------------------------------------------------------
# 2D (Cartesian §7.2) in the world frame: the 3D derivation above with R = R2(ψ), H_x = R^T [-I | a],
# a = J^T d = (d_y, -d_x) (∂R2/∂ψ = J R2, J the 90° rotation). Symmetric 2×2 matrices are
# 3-tuples (a00, a01, a11).


@jit(fastmath=_FM, inline="always")
def _add2(A, B):  # type: ignore[no-untyped-def]
    """Sum of two symmetric 3-tuples."""
    return (A[0] + B[0], A[1] + B[1], A[2] + B[2])


@jit(fastmath=_FM, inline="always")
def _sandwich2(c: float, s: float, S):  # type: ignore[no-untyped-def]
    """R S R^T for R = [[c, -s], [s, c]] and a symmetric 3-tuple S."""
    s00, s01, s11 = S
    a0, a1 = c * s00 - s * s01, c * s01 - s * s11  # row 0 of R S
    b0, b1 = s * s00 + c * s01, s * s01 + c * s11  # row 1 of R S
    return (a0 * c - a1 * s, a0 * s + a1 * c, b0 * s + b1 * c)


@jit(fastmath=_FM, inline="always")
def _inv_sym2(A):  # type: ignore[no-untyped-def]
    """(inverse as a 3-tuple, determinant) of a symmetric 2×2 3-tuple."""
    a00, a01, a11 = A
    det = a00 * a11 - a01 * a01
    r = 1.0 / det
    return (a11 * r, -a01 * r, a00 * r), det


@jit(fastmath=_FM, inline="always")
def _logpdf2(n0: float, n1: float, Si, det: float) -> float:  # type: ignore[no-untyped-def]
    """log N(ν; 0, S) from S^{-1} (3-tuple) and det S."""
    maha = Si[0] * n0 * n0 + 2.0 * Si[1] * n0 * n1 + Si[2] * n1 * n1
    return -0.5 * (maha + math.log(det) + 2.0 * _LOG_2PI)


def _depth_acc(acc, g):  # type: ignore[no-untyped-def]
    """The weights' Jacobian terms: ``acc`` = (Π g since the last fold, Σ log of the folded
    products, count) gains ``g`` (pixel: the depth X̃; range–bearing: the range r); Cartesian
    (``g`` None): unchanged. numba only.

    log det Ψ = log det Ψ_w + log det(G)²; pixel: det(G)² = (f³ b)²/X̃⁸ (2D (f² b)²/X̃⁶),
    range–bearing: det(G)² = 1/r². That part of every weight term is collected here and added once
    per particle (``_depth_logw``), so the weight terms need no division or logarithm of their own.
    The product is folded into the log sum before it can overflow or underflow (X̃ ∈ [0.05 m,
    ~1e4 m]).
    """
    raise NotImplementedError("numba only: an @overload stub, compiled into the jitted kernels")


@overload(_depth_acc, inline="always", jit_options={"fastmath": _FM})
def _depth_acc_impl(acc, g):  # type: ignore[no-untyped-def]
    if isinstance(g, types.NoneType):
        return lambda acc, g: acc

    def pixel(acc, g):  # type: ignore[no-untyped-def]
        p, ls, n = acc[0] * g, acc[1], acc[2] + 1
        if p > 1e200 or p < 1e-200:
            return 1.0, ls + math.log(p), n
        return p, ls, n

    return pixel


def _depth_logw(xacc, rig, dz: int):  # type: ignore[no-untyped-def]
    """Σ over the weight terms of −½ log det(G)² (0 for the Cartesian model); numba only."""
    raise NotImplementedError("numba only: an @overload stub, compiled into the jitted kernels")


@overload(_depth_logw, inline="always", jit_options={"fastmath": _FM})
def _depth_logw_impl(acc, rig, dz):  # type: ignore[no-untyped-def]
    if isinstance(rig, types.NoneType):
        return lambda acc, rig, dz: 0.0
    if _is_range_bearing(rig):
        # −½ log det(G)² = log r per term
        return lambda acc, rig, dz: acc[1] + math.log(acc[0])

    def pixel(acc, rig, dz):  # type: ignore[no-untyped-def]
        # 3D: −½ (log (f³ b)² − 8 log X̃) per term; 2D: −½ (log (f² b)² − 6 log X̃)
        logc = rig[8] if dz == 3 else rig[9]
        return (dz + 1) * (acc[1] + math.log(acc[0])) - 0.5 * acc[2] * logc

    return pixel


@jit(fastmath=_FM, inline="always")
def _innov2t(x, m, zm, c: float, s: float):  # type: ignore[no-untyped-def]
    """(d = m - p, ν_w = R z_meas - d) as 2-tuples."""
    d0, d1 = m[0] - x[0], m[1] - x[1]
    return (d0, d1), (c * zm[0] - s * zm[1] - d0, s * zm[0] + c * zm[1] - d1)


@jit(fastmath=_FM, inline="always")
def _pose_part2t(Sg, d, T):  # type: ignore[no-untyped-def]
    """T = Σ Ĥ^T (into the 3×2 array T) and Ĥ Σ Ĥ^T (returned, 3-tuple) for Ĥ = [-I | (d_y, -d_x)]."""
    a0, a1 = d[1], -d[0]
    for i in range(3):
        T[i, 0] = -Sg[i, 0] + Sg[i, 2] * a0
        T[i, 1] = -Sg[i, 1] + Sg[i, 2] * a1
    return (-T[0, 0] + a0 * T[2, 0], -T[0, 1] + a0 * T[2, 1], -T[1, 1] + a1 * T[2, 1])


# Range–bearing (§7.2) in the same world frame: z = (r, β) = (|d|, bearing of Rᵀ d), whose
# H_m = G = [[d_x/r, d_y/r], [−d_y/r², d_x/r²]] gives H_x = G Ĥ with the Cartesian Ĥ = [−I | (d_y, −d_x)]
# (G (d_y, −d_x) = (0, −1)). So, as for the pixel model, its formulas are a Cartesian model's with
#   ν_w = G⁻¹ ν,  Q_w = G⁻¹ Q G⁻ᵀ,  det Ψ = det(G)² det Ψ_w = det Ψ_w / r²,
# G⁻¹ = [[d_x/r, −d_y], [d_y/r, d_x]]; the new landmark's J_z = ∂m/∂(r, β) is G⁻¹ at it. Q is each
# observation's (a general covariance).


@jit(fastmath=_FM, inline="always")
def _gqg(g00: float, g01: float, g10: float, g11: float, Qm):  # type: ignore[no-untyped-def]
    """G Q Gᵀ (3-tuple) for G = [[g00, g01], [g10, g11]] and Q's upper triangle."""
    q00, q01, q11 = Qm[0, 0], Qm[0, 1], Qm[1, 1]
    a0, a1 = g00 * q00 + g01 * q01, g00 * q01 + g01 * q11  # row 0 of G Q
    b0, b1 = g10 * q00 + g11 * q01, g10 * q01 + g11 * q11  # row 1 of G Q
    return (a0 * g00 + a1 * g01, a0 * g10 + a1 * g11, b0 * g10 + b1 * g11)


def _noise2(c: float, s: float, rig):  # type: ignore[no-untyped-def]
    """Pixel model: A = (σx² b²/2) r1 r1ᵀ (3-tuple), r1 = (−sin ψ, cos ψ); other models: 0.0. numba only."""
    raise NotImplementedError("numba only: an @overload stub, compiled into the jitted kernels")


@overload(_noise2, inline="always", jit_options={"fastmath": _FM})
def _noise2_impl(c, s, rig):  # type: ignore[no-untyped-def]
    if isinstance(rig, types.NoneType) or _is_range_bearing(rig):
        return lambda c, s, rig: 0.0

    def pixel(c, s, rig):  # type: ignore[no-untyped-def]
        k1 = 0.5 * rig[4] * rig[3] * rig[3]
        return (k1 * s * s, -k1 * s * c, k1 * c * c)

    return pixel


@jit(fastmath=_FM, inline="always")
def _pixel_cov2(D0: float, D1: float, sc: float, A, vx: float):  # type: ignore[no-untyped-def]
    """Q_w = s² (2σx² D Dᵀ + A) as a 3-tuple."""
    s2 = sc * sc
    k = 2.0 * vx * s2
    return (k * D0 * D0 + s2 * A[0], k * D0 * D1 + s2 * A[1], k * D1 * D1 + s2 * A[2])


def _meas2(x, m, zm, Qm, c: float, s: float, rig, A):  # type: ignore[no-untyped-def]
    """One 2D observation in the world frame: (d, ν_w, Q_w (3-tuple), g), as ``_meas3`` with
    R = R2(ψ) = [[c, −s], [s, c]]; pixel: z = (x_L, x_R), g = X̃ (det(J_π)² = (f² b / X̃³)²);
    range–bearing: see ``_gqg``, g = r; numba only."""
    raise NotImplementedError("numba only: an @overload stub, compiled into the jitted kernels")


@overload(_meas2, inline="always", jit_options={"fastmath": _FM})
def _meas2_impl(x, m, zm, Qm, c, s, rig, A):  # type: ignore[no-untyped-def]
    if isinstance(rig, types.NoneType):

        def cartesian(x, m, zm, Qm, c, s, rig, A):  # type: ignore[no-untyped-def]
            d, nu = _innov2t(x, m, zm, c, s)
            return d, nu, _sandwich2(c, s, (Qm[0, 0], Qm[0, 1], Qm[1, 1])), None

        return cartesian
    if _is_range_bearing(rig):

        def range_bearing(x, m, zm, Qm, c, s, rig, A):  # type: ignore[no-untyped-def]
            d0, d1 = m[0] - x[0], m[1] - x[1]
            r = math.sqrt(d0 * d0 + d1 * d1)
            # ν = z − (r, β̂) with β̂ the bearing of Rᵀ d, wrapped; ν_w = G⁻¹ ν
            nr = zm[0] - r
            nb = _wrap(zm[1] - math.atan2(-s * d0 + c * d1, c * d0 + s * d1))
            a, b = d0 / r, d1 / r
            return (d0, d1), (a * nr - d1 * nb, b * nr + d0 * nb), _gqg(a, -d1, b, d0, Qm), r

        return range_bearing

    def pixel(x, m, zm, Qm, c, s, rig, A):  # type: ignore[no-untyped-def]
        px, vx, i_fb, i_f = rig[1], rig[4], rig[6], rig[7]
        d0, d1 = m[0] - x[0], m[1] - x[1]
        X = c * d0 + s * d1
        Y = -s * d0 + c * d1
        Xc = max(X, _PIXEL_MIN_DEPTH)
        e = Xc - X
        D0, D1 = d0 + e * c, d1 + e * s
        sc = Xc * i_fb
        t = 1.0 - sc * (zm[0] - zm[1])
        u = 0.5 * Xc * i_f * (zm[0] + zm[1] - 2.0 * px) - Y
        return (d0, d1), (t * D0 - u * s, t * D1 + u * c), _pixel_cov2(D0, D1, sc, A, vx), Xc

    return pixel


def _init2(x, zm, Qm, c: float, s: float, rig, A):  # type: ignore[no-untyped-def]
    """A new 2D landmark at pose x: (μ (2-tuple), Σ without the floor (3-tuple)), as ``_init3``;
    range–bearing: μ = p + r (cos(ψ + β), sin(ψ + β)), Σ = J_z Q J_zᵀ (J_z = G⁻¹ there). numba only."""
    raise NotImplementedError("numba only: an @overload stub, compiled into the jitted kernels")


@overload(_init2, inline="always", jit_options={"fastmath": _FM})
def _init2_impl(x, zm, Qm, c, s, rig, A):  # type: ignore[no-untyped-def]
    if isinstance(rig, types.NoneType):

        def cartesian(x, zm, Qm, c, s, rig, A):  # type: ignore[no-untyped-def]
            z0, z1 = zm[0], zm[1]
            mu = (x[0] + c * z0 - s * z1, x[1] + s * z0 + c * z1)
            return mu, _sandwich2(c, s, (Qm[0, 0], Qm[0, 1], Qm[1, 1]))

        return cartesian
    if _is_range_bearing(rig):

        def range_bearing(x, zm, Qm, c, s, rig, A):  # type: ignore[no-untyped-def]
            r, cb, sb = zm[0], math.cos(zm[1]), math.sin(zm[1])
            ct, st = c * cb - s * sb, s * cb + c * sb  # cos, sin of ψ + β
            D0, D1 = r * ct, r * st
            return (x[0] + D0, x[1] + D1), _gqg(ct, -D1, st, D0, Qm)

        return range_bearing

    def pixel(x, zm, Qm, c, s, rig, A):  # type: ignore[no-untyped-def]
        f, px, b = rig[0], rig[1], rig[3]
        r = b / (zm[0] - zm[1])
        z0, z1 = f * r, (zm[0] - px) * r - 0.5 * b
        D0, D1 = c * z0 - s * z1, s * z0 + c * z1
        return (x[0] + D0, x[1] + D1), _pixel_cov2(D0, D1, z0 * rig[6], A, rig[4])

    return pixel


@jit(fastmath=_FM, inline="always")
def _joseph2(m, Cm, C, Qw, Pinv, nu) -> None:  # type: ignore[no-untyped-def]
    """``_joseph3`` in 2D (C, Q_w, Ψ_w^{-1} 3-tuples)."""
    c00, c01, c11 = C
    q00, q01, q11 = Qw
    p00, p01, p11 = Pinv
    # K_w = C Ψ_w^{-1}
    k00, k01 = c00 * p00 + c01 * p01, c00 * p01 + c01 * p11
    k10, k11 = c01 * p00 + c11 * p01, c01 * p01 + c11 * p11
    m[0] += k00 * nu[0] + k01 * nu[1]
    m[1] += k10 * nu[0] + k11 * nu[1]
    # C' = (I - K_w) C (I - K_w)^T + K_w Q_w K_w^T
    b00, b01 = (1.0 - k00) * c00 - k01 * c01, (1.0 - k00) * c01 - k01 * c11
    b10, b11 = -k10 * c00 + (1.0 - k11) * c01, -k10 * c01 + (1.0 - k11) * c11
    e00, e01 = k00 * q00 + k01 * q01, k00 * q01 + k01 * q11
    e10, e11 = k10 * q00 + k11 * q01, k10 * q01 + k11 * q11
    n00 = b00 * (1.0 - k00) - b01 * k01 + e00 * k00 + e01 * k01
    n01 = -b00 * k10 + b01 * (1.0 - k11) + e00 * k10 + e01 * k11
    n11 = -b10 * k10 + b11 * (1.0 - k11) + e10 * k10 + e11 * k11
    Cm[0, 0], Cm[1, 1] = n00, n11
    Cm[0, 1] = Cm[1, 0] = n01


# ---------------------------------------------------------------------------------------------
# The per-dimension algebra the step is written in. _particle's overload (below) picks the 3D or
# the 2D set while compiling; each is a plain function that numba inlines into the step (no
# dispatch at run time). A pose's angles are its last three entries (3D: roll, pitch, yaw; 2D:
# x, y, ψ, of which only ψ is an angle and read); a frame ``F`` is what the measurement formulas
# take (3D (R, sin yaw, cos yaw), 2D (cos ψ, sin ψ)). Symmetric matrices are their upper
# triangles as tuples (6 entries 3×3, 3 entries 2×2), rows of the dx × dm arrays T and Lc are
# dm-tuples; the measurement's dimension is the landmark's in the world frame (Ψ_w is dm × dm for
# every model).


@jit(fastmath=_FM, inline="always")
def _frame3(cr: float, sr: float, cp: float, sp: float, cy: float, sy: float):  # type: ignore[no-untyped-def]
    """The 3D frame of a trig state (cosines and sines of roll, pitch, yaw): (R, sin yaw, cos yaw)."""
    return _rot3_cs(cr, sr, cp, sp, cy, sy), sy, cy


@jit(fastmath=_FM, inline="always")
def _frame2(cr: float, sr: float, cp: float, sp: float, cy: float, sy: float):  # type: ignore[no-untyped-def]
    """The 2D frame (cos ψ, sin ψ) = (cy, sy) of a trig state (the other pairs are not angles)."""
    return cy, sy


@jit(fastmath=_FM, inline="always")
def _frame_at3(x):  # type: ignore[no-untyped-def]
    """The frame of 3D pose x."""
    return _rot3t(x[3], x[4], x[5])


@jit(fastmath=_FM, inline="always")
def _frame_at2(x):  # type: ignore[no-untyped-def]
    """The frame of 2D pose x."""
    return math.cos(x[2]), math.sin(x[2])


@jit(fastmath=_FM, inline="always")
def _advance3(cr: float, sr: float, cp: float, sp: float, cy: float, sy: float, new, old):  # type: ignore[no-untyped-def]
    """The trig state after roll, pitch, yaw moved from ``old`` to ``new`` (``_turn``)."""
    cr, sr = _turn(cr, sr, new[0] - old[0])
    cp, sp = _turn(cp, sp, new[1] - old[1])
    cy, sy = _turn(cy, sy, new[2] - old[2])
    return cr, sr, cp, sp, cy, sy


@jit(fastmath=_FM, inline="always")
def _advance2(cr: float, sr: float, cp: float, sp: float, cy: float, sy: float, new, old):  # type: ignore[no-untyped-def]
    """The trig state after ψ (the last entry) moved from ``old`` to ``new``."""
    cy, sy = _turn(cy, sy, new[2] - old[2])
    return cr, sr, cp, sp, cy, sy


@jit(fastmath=_FM, inline="always")
def _wrap_angles3(x, new) -> None:  # type: ignore[no-untyped-def]
    """x's roll, pitch, yaw = ``new``'s wrapped."""
    x[3] = _wrap(new[0])
    x[4] = _wrap(new[1])
    x[5] = _wrap(new[2])


@jit(fastmath=_FM, inline="always")
def _wrap_angles2(x, new) -> None:  # type: ignore[no-untyped-def]
    """x's ψ = ``new``'s last entry wrapped."""
    x[2] = _wrap(new[2])


@jit(fastmath=_FM, inline="always")
def _noise3f(F, rig):  # type: ignore[no-untyped-def]
    return _noise3(F[0], rig)


@jit(fastmath=_FM, inline="always")
def _noise2f(F, rig):  # type: ignore[no-untyped-def]
    return _noise2(F[0], F[1], rig)


@jit(fastmath=_FM, inline="always")
def _meas3f(x, m, zm, Qm, F, rig, A):  # type: ignore[no-untyped-def]
    return _meas3(x, m, zm, Qm, F[0], rig, A)


@jit(fastmath=_FM, inline="always")
def _meas2f(x, m, zm, Qm, F, rig, A):  # type: ignore[no-untyped-def]
    return _meas2(x, m, zm, Qm, F[0], F[1], rig, A)


@jit(fastmath=_FM, inline="always")
def _init3f(x, zm, Qm, F, rig, A):  # type: ignore[no-untyped-def]
    return _init3(x, zm, Qm, F[0], rig, A)


@jit(fastmath=_FM, inline="always")
def _init2f(x, zm, Qm, F, rig, A):  # type: ignore[no-untyped-def]
    return _init2(x, zm, Qm, F[0], F[1], rig, A)


@jit(fastmath=_FM, inline="always")
def _pose_part3f(Sg, d, F, T):  # type: ignore[no-untyped-def]
    return _pose_part3t(Sg, d, F[0], F[1], F[2], T)


@jit(fastmath=_FM, inline="always")
def _pose_part2f(Sg, d, F, T):  # type: ignore[no-untyped-def]
    return _pose_part2t(Sg, d, T)


@jit(fastmath=_FM, inline="always")
def _sym2(C):  # type: ignore[no-untyped-def]
    """Upper triangle of a 2×2 array as a 3-tuple."""
    return (C[0, 0], C[0, 1], C[1, 1])


@jit(fastmath=_FM, inline="always")
def _logpdf3t(nu, Si, det: float) -> float:  # type: ignore[no-untyped-def]
    return _logpdf3(nu[0], nu[1], nu[2], Si, det)


@jit(fastmath=_FM, inline="always")
def _logpdf2t(nu, Si, det: float) -> float:  # type: ignore[no-untyped-def]
    return _logpdf2(nu[0], nu[1], Si, det)


@jit(fastmath=_FM, inline="always")
def _row3(A, i: int):  # type: ignore[no-untyped-def]
    """Row i of A's first three columns."""
    return (A[i, 0], A[i, 1], A[i, 2])


@jit(fastmath=_FM, inline="always")
def _row2(A, i: int):  # type: ignore[no-untyped-def]
    """Row i of A's first two columns."""
    return (A[i, 0], A[i, 1])


@jit(fastmath=_FM, inline="always")
def _set_row3(A, i: int, v) -> None:  # type: ignore[no-untyped-def]
    A[i, 0], A[i, 1], A[i, 2] = v


@jit(fastmath=_FM, inline="always")
def _set_row2(A, i: int, v) -> None:  # type: ignore[no-untyped-def]
    A[i, 0], A[i, 1] = v


@jit(fastmath=_FM, inline="always")
def _dot3(a, b) -> float:  # type: ignore[no-untyped-def]
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@jit(fastmath=_FM, inline="always")
def _dot2(a, b) -> float:  # type: ignore[no-untyped-def]
    return a[0] * b[0] + a[1] * b[1]


@jit(fastmath=_FM, inline="always")
def _times_sym3(t, P):  # type: ignore[no-untyped-def]
    """The row t (3-tuple) times the symmetric P (6-tuple)."""
    return (
        t[0] * P[0] + t[1] * P[1] + t[2] * P[2],
        t[0] * P[1] + t[1] * P[3] + t[2] * P[4],
        t[0] * P[2] + t[1] * P[4] + t[2] * P[5],
    )


@jit(fastmath=_FM, inline="always")
def _times_sym2(t, P):  # type: ignore[no-untyped-def]
    """The row t (2-tuple) times the symmetric P (3-tuple)."""
    return (t[0] * P[0] + t[1] * P[1], t[0] * P[1] + t[1] * P[2])


@jit(fastmath=_FM, inline="always")
def _put_new3(m, Cm, mn, Qn, floor: float) -> None:  # type: ignore[no-untyped-def]
    """m = μ, Cm = Σ + floor·I for a new landmark (Σ a 6-tuple)."""
    m[0], m[1], m[2] = mn
    q00, q01, q02, q11, q12, q22 = Qn
    Cm[0, 0], Cm[1, 1], Cm[2, 2] = q00 + floor, q11 + floor, q22 + floor
    Cm[0, 1] = Cm[1, 0] = q01
    Cm[0, 2] = Cm[2, 0] = q02
    Cm[1, 2] = Cm[2, 1] = q12


@jit(fastmath=_FM, inline="always")
def _put_new2(m, Cm, mn, Qn, floor: float) -> None:  # type: ignore[no-untyped-def]
    """m = μ, Cm = Σ + floor·I for a new landmark (Σ a 3-tuple)."""
    m[0], m[1] = mn
    q00, q01, q11 = Qn
    Cm[0, 0], Cm[1, 1] = q00 + floor, q11 + floor
    Cm[0, 1] = Cm[1, 0] = q01


# ---------------------------------------------------------------------------------------------
# The step


def _particle(  # type: ignore[no-untyped-def]
    k,
    version,
    pose,
    S,
    pool_mean,
    pool_cov,
    table,
    bs,
    slots_old,
    z_old,
    Q_old,
    slots_new,
    z_new,
    Q_new,
    eps,
    floor,
    out_pose,
    dlogw,
    seq,
    out_mu,
    out_Sx,
    rig,
    D,
    x,
    mu,
    T,
    Sx,
    Lc,
) -> None:
    """The whole FastSLAM step of particle k (§9, §10) in the world frame (see above).

    x, mu (dx,), T (dx, dm), Sx, Lc (dx, dx) are scratch arrays reused across particles. numba
    only: the overload below compiles the one algorithm with the algebra of D's dimension.
    """
    raise NotImplementedError("numba only: an @overload stub, compiled into the jitted kernels")


@overload(_particle, jit_options={"fastmath": _FM})
def _particle_impl(  # type: ignore[no-untyped-def]
    k,
    version,
    pose,
    S,
    pool_mean,
    pool_cov,
    table,
    bs,
    slots_old,
    z_old,
    Q_old,
    slots_new,
    z_new,
    Q_new,
    eps,
    floor,
    out_pose,
    dlogw,
    seq,
    out_mu,
    out_Sx,
    rig,
    D,
    x,
    mu,
    T,
    Sx,
    Lc,
):
    # the algebra of D's dimension; the names below are constants of the compiled step
    if _is_3d(D):
        dm, dx = 3, 6
        frame, frame_at, advance, wrap_angles = _frame3, _frame_at3, _advance3, _wrap_angles3
        meas, init, noise, pose_part = _meas3f, _init3f, _noise3f, _pose_part3f
        sym, add, inv_sym, logpdf, joseph, put_new = _sym3, _add3, _inv_sym3, _logpdf3t, _joseph3, _put_new3
        row, set_row, dot, times_sym = _row3, _set_row3, _dot3, _times_sym3
    else:
        dm, dx = 2, 3
        frame, frame_at, advance, wrap_angles = _frame2, _frame_at2, _advance2, _wrap_angles2
        meas, init, noise, pose_part = _meas2f, _init2f, _noise2f, _pose_part2f
        sym, add, inv_sym, logpdf, joseph, put_new = _sym2, _add2, _inv_sym2, _logpdf2t, _joseph2, _put_new2
        row, set_row, dot, times_sym = _row2, _set_row2, _dot2, _times_sym2

    def particle(  # type: ignore[no-untyped-def]
        k,
        version,
        pose,
        S,
        pool_mean,
        pool_cov,
        table,
        bs,
        slots_old,
        z_old,
        Q_old,
        slots_new,
        z_new,
        Q_new,
        eps,
        floor,
        out_pose,
        dlogw,
        seq,
        out_mu,
        out_Sx,
        rig,
        D,
        x,
        mu,
        T,
        Sx,
        Lc,
    ):
        n_old = slots_old.shape[0]
        Sk = S[k]
        for i in range(dx):
            x[i] = pose[k, i]
        w = 0.0
        xacc = (1.0, 0.0, 0)  # Jacobian terms of the pixel and range–bearing weights (_depth_acc)
        if version == 2:
            # One pass over the identified landmarks: the importance weight at the prior x̂ with S
            # and the landmarks before the update (§10 "Importance weight"), and the Kalman-form
            # proposal that moves μ_x, Σ_x one observation after another (§10 "Proposal").
            # Cosines and sines of μ_x's angles (its last three entries; 2D: only ψ's, cy and sy,
            # are read), advanced by _turn as μ_x moves (no trig per observation). Six scalars
            # written out here, not a tuple or a helper's result: see the module docstring.
            cr, sr = math.cos(x[dx - 3]), math.sin(x[dx - 3])
            cp, sp = math.cos(x[dx - 2]), math.sin(x[dx - 2])
            cy, sy = math.cos(x[dx - 1]), math.sin(x[dx - 1])
            F0 = frame(cr, sr, cp, sp, cy, sy)
            A0 = noise(F0, rig)
            for i in range(dx):
                mu[i] = x[i]
                for t in range(dx):
                    Sx[i, t] = Sk[i, t]
            for j in range(n_old):
                s = slots_old[j]
                blk = table[k, s // bs]
                m = pool_mean[blk, s % bs]
                C = sym(pool_cov[blk, s % bs])
                if j == 0 or not seq:
                    # weight term: L_w = Ĥ S Ĥ^T + C + Q_w at x̂ (Cartesian Q_w = R̂ Q R̂^T)
                    d, nu, Qw, g = meas(x, m, z_old[j], Q_old[j], F0, rig, A0)
                    HSH = pose_part(Sk, d, F0, T)
                    Pinv, det = inv_sym(add(add(HSH, C), Qw))
                    w += logpdf(nu, Pinv, det)
                    xacc = _depth_acc(xacc, g)
                if j > 0:  # proposal step at the current μ_x, Σ_x (for j = 0 it is the weight term)
                    F = frame(cr, sr, cp, sp, cy, sy)
                    d, nu, Qw, g = meas(mu, m, z_old[j], Q_old[j], F, rig, noise(F, rig))
                    HSH = pose_part(Sx, d, F, T)
                    Pinv, det = inv_sym(add(add(HSH, C), Qw))
                    if seq:  # sequential weight: the chain rule p(z_j | z_<j) with the proposal's Ψ_j
                        w += logpdf(nu, Pinv, det)
                        xacc = _depth_acc(xacc, g)
                old = (mu[dx - 3], mu[dx - 2], mu[dx - 1])
                # world-frame pose gain K = T Ψ_w^{-1} (into Lc's first dm columns); μ_x += K ν_w
                for i in range(dx):
                    kr = times_sym(row(T, i), Pinv)
                    set_row(Lc, i, kr)
                    mu[i] += dot(kr, nu)
                new = (mu[dx - 3], mu[dx - 2], mu[dx - 1])
                cr, sr, cp, sp, cy, sy = advance(cr, sr, cp, sp, cy, sy, new, old)
                wrap_angles(mu, new)
                # Σ_x ← Σ_x - K T^T (symmetric: one triangle, mirrored)
                for i in range(dx):
                    kr = row(Lc, i)
                    for t in range(i, dx):
                        v = Sx[i, t] - dot(kr, row(T, t))
                        Sx[i, t] = v
                        Sx[t, i] = v
            for i in range(dx):
                out_mu[k, i] = mu[i]
                for t in range(dx):
                    out_Sx[k, i, t] = Sx[i, t]
            if not _cholesky_into(Sx, Lc, dx):
                ev, V = np.linalg.eigh(Sx)
                for i in range(dx):
                    for t in range(dx):
                        Lc[i, t] = V[i, t] * math.sqrt(max(ev[t], 0.0))
            for i in range(dx):
                acc = 0.0
                for t in range(dx):
                    acc += Lc[i, t] * eps[k, t]
                x[i] = mu[i] + acc
            for i in range(dm, dx):
                x[i] = _wrap(x[i])
        # landmark EKFs at the sampled pose (§9 step 2), Joseph form in the world frame
        F = frame_at(x)
        A = noise(F, rig)
        for j in range(n_old):
            s = slots_old[j]
            blk = table[k, s // bs]
            m = pool_mean[blk, s % bs]
            Cm = pool_cov[blk, s % bs]
            C = sym(Cm)
            _, nu, Qw, g = meas(x, m, z_old[j], Q_old[j], F, rig, A)
            Pinv, det = inv_sym(add(C, Qw))
            joseph(m, Cm, C, Qw, Pinv, nu)
            if version == 1:
                w += logpdf(nu, Pinv, det)
                xacc = _depth_acc(xacc, g)
        # new landmarks (§9 step 3): μ = p + R z, Σ = R Q R^T + floor·I; pixel: z triangulated
        # first; range–bearing: μ = p + r (cos(ψ + β), sin(ψ + β)) (_init3, _init2)
        for j in range(slots_new.shape[0]):
            s = slots_new[j]
            blk = table[k, s // bs]
            m = pool_mean[blk, s % bs]
            Cm = pool_cov[blk, s % bs]
            mn, Qn = init(x, z_new[j], Q_new[j], F, rig, A)
            put_new(m, Cm, mn, Qn, floor)
        for i in range(dx):
            out_pose[k, i] = x[i]
        dlogw[k] = w + _depth_logw(xacc, rig, dm)

    return particle


@jit(fastmath=_FM)
def _chunk(  # type: ignore[no-untyped-def]
    k0,
    k1,
    version,
    pose,
    S,
    pool_mean,
    pool_cov,
    table,
    bs,
    slots_old,
    z_old,
    Q_old,
    slots_new,
    z_new,
    Q_new,
    eps,
    floor,
    out_pose,
    dlogw,
    seq,
    out_mu,
    out_Sx,
    rig,
    D,
) -> None:
    """Particles k0 … k1-1, one after another, with one set of scratch arrays."""
    dx = pose.shape[1]
    dm = 3 if dx == 6 else 2
    x = np.empty(dx)
    mu = np.empty(dx)
    T = np.empty((dx, dm))
    Sx = np.empty((dx, dx))
    Lc = np.empty((dx, dx))
    for k in range(k0, k1):
        _particle(
            k,
            version,
            pose,
            S,
            pool_mean,
            pool_cov,
            table,
            bs,
            slots_old,
            z_old,
            Q_old,
            slots_new,
            z_new,
            Q_new,
            eps,
            floor,
            out_pose,
            dlogw,
            seq,
            out_mu,
            out_Sx,
            rig,
            D,
            x,
            mu,
            T,
            Sx,
            Lc,
        )


@jit(fastmath=_FM, parallel=True)
def _step(  # type: ignore[no-untyped-def]
    version,
    pose,
    S,
    pool_mean,
    pool_cov,
    table,
    bs,
    slots_old,
    z_old,
    Q_old,
    slots_new,
    z_new,
    Q_new,
    eps,
    floor,
    out_pose,
    dlogw,
    seq,
    out_mu,
    out_Sx,
    rig,
    D,
    n_chunks,
):
    # one contiguous range of particles per thread (_chunk: a function of its own, so that numba
    # compiles _particle's overload once, not once more for the parallel loop's body)
    P = pose.shape[0]
    for c in nb.prange(n_chunks):
        _chunk(
            c * P // n_chunks,
            (c + 1) * P // n_chunks,
            version,
            pose,
            S,
            pool_mean,
            pool_cov,
            table,
            bs,
            slots_old,
            z_old,
            Q_old,
            slots_new,
            z_new,
            Q_new,
            eps,
            floor,
            out_pose,
            dlogw,
            seq,
            out_mu,
            out_Sx,
            rig,
            D,
        )


@jit(fastmath=_FM)
def _predict3(pose, u, M, extra, want_S, cos_pitch_min, out_pose, out_S):  # type: ignore[no-untyped-def]
    """§6.3 motion model for every particle: p' = p + R(η) Δp, R(η') = R(η) exp([ω]×), and
    (``want_S``) S = V M V^T + diag(extra), V = blockdiag(R, E(η') J_r(ω)), symmetric by
    construction (as :func:`robotd.slam.models.motion3d`).

    u is (1, 6) (one control for all particles) or (P, 6). Returns the index of a particle at the
    pitch singularity (|cos pitch| < cos_pitch_min; nothing after it is written) or -1.
    """
    P = pose.shape[0]
    V = np.zeros((6, 6))
    VM = np.empty((6, 6))
    Rw = np.empty((3, 3))
    Jr = np.empty((3, 3))
    Rn = np.empty((3, 3))
    pitch_max = math.acos(cos_pitch_min)
    for k in range(P):
        roll, pitch = pose[k, 3], pose[k, 4]
        cp = math.cos(pitch)
        if abs(cp) < cos_pitch_min:
            return k
        R, _, _ = _rot3t(roll, pitch, pose[k, 5])
        uk = u[k if u.shape[0] > 1 else 0]
        for i in range(3):
            out_pose[k, i] = pose[k, i] + R[3 * i] * uk[0] + R[3 * i + 1] * uk[1] + R[3 * i + 2] * uk[2]
        _so3_exp_jr(uk[3], uk[4], uk[5], Rw, Jr)
        for i in range(3):
            for t in range(3):
                Rn[i, t] = R[3 * i] * Rw[0, t] + R[3 * i + 1] * Rw[1, t] + R[3 * i + 2] * Rw[2, t]
        sp_new = min(1.0, max(-1.0, -Rn[2, 0]))
        pitch_new = math.asin(sp_new)
        roll_new = math.atan2(Rn[2, 1], Rn[2, 2])
        out_pose[k, 3] = _wrap(roll_new)
        out_pose[k, 4] = _wrap(pitch_new)
        out_pose[k, 5] = _wrap(math.atan2(Rn[1, 0], Rn[0, 0]))
        if not want_S:
            continue
        for i in range(3):
            for t in range(3):
                V[i, t] = R[3 * i + t]
        # E at the new attitude (a pitch the increment took to the singularity: clamped, finite)
        pe = min(pitch_max, max(-pitch_max, pitch_new))
        cr, sr, cpn, tp = math.cos(roll_new), math.sin(roll_new), math.cos(pe), math.tan(pe)
        for t in range(3):
            V[3, 3 + t] = Jr[0, t] + sr * tp * Jr[1, t] + cr * tp * Jr[2, t]
            V[4, 3 + t] = cr * Jr[1, t] - sr * Jr[2, t]
            V[5, 3 + t] = (sr * Jr[1, t] + cr * Jr[2, t]) / cpn
        _mm_into(V, M, VM, 6, 6, 6)
        for i in range(6):
            for t in range(i, 6):
                acc = 0.0
                for c in range(6):
                    acc += VM[i, c] * V[t, c]
                out_S[k, i, t] = acc
                out_S[k, t, i] = acc
            out_S[k, i, i] += extra[i]
    return -1


@jit(fastmath=_FM, inline="always")
def _so3_exp_jr(wx: float, wy: float, wz: float, Rw, Jr) -> None:  # type: ignore[no-untyped-def]
    """exp([w]×) and the right Jacobian J_r(w) into Rw, Jr (3, 3), as robotd.core.geometry's."""
    th2 = wx * wx + wy * wy + wz * wz
    th = math.sqrt(th2)
    if th < 1e-4:
        a = 1.0 - th2 / 6.0
        b = 0.5 - th2 / 24.0
        c = 1.0 / 6.0 - th2 / 120.0
    else:
        s, co = math.sin(th), math.cos(th)
        a = s / th
        b = (1.0 - co) / th2
        c = (th - s) / (th2 * th)
    # K = [w]×, K² = w wᵀ − th² I
    K = ((0.0, -wz, wy), (wz, 0.0, -wx), (-wy, wx, 0.0))
    w = (wx, wy, wz)
    for i in range(3):
        for j in range(3):
            k2 = w[i] * w[j] - (th2 if i == j else 0.0)
            d = 1.0 if i == j else 0.0
            Rw[i, j] = d + a * K[i][j] + b * k2
            Jr[i, j] = d - b * K[i][j] + c * k2


def predict3_numba(
    pose: np.ndarray, u: np.ndarray, M: np.ndarray, extra: np.ndarray, want_S: bool, cos_pitch_min: float
) -> tuple[np.ndarray, np.ndarray | None, int]:
    """3D motion update of all particles (docs/math.md §6.3), as :func:`robotd.slam.models.motion3d`.

    Args:
        pose: (P, 6) poses; u: (6,) or (P, 6) controls (Δp_b [m], ω [rad]); M: (6, 6) control
        covariance; extra: (6,) variances added to the diagonal of S.

    Returns:
        (new poses (P, 6) with wrapped angles, S (P, 6, 6) = V M V^T + diag(extra) or None, index of
        a particle at the pitch singularity or -1).
    """
    P = pose.shape[0]
    out_pose = np.empty((P, 6))
    out_S = np.empty((P, 6, 6)) if want_S else np.empty((0, 6, 6))
    bad = _predict3(
        np.ascontiguousarray(pose, dtype=np.float64),
        np.ascontiguousarray(np.atleast_2d(u), dtype=np.float64),
        np.ascontiguousarray(M, dtype=np.float64),
        np.ascontiguousarray(extra, dtype=np.float64),
        bool(want_S),
        float(cos_pitch_min),
        out_pose,
        out_S,
    )
    return out_pose, (out_S if want_S else None), int(bad)


@jit
def copy_blocks(pool_mean, pool_cov, src, dst) -> None:  # type: ignore[no-untyped-def]
    """Copy-on-write block copies pool[src[i]] -> pool[dst[i]] in place (no gather temporary)."""
    n = pool_mean.shape[0]
    pm = pool_mean.reshape((n, -1))
    pc = pool_cov.reshape((n, -1))
    for i in range(src.shape[0]):
        a, b = src[i], dst[i]
        for j in range(pm.shape[1]):
            pm[b, j] = pm[a, j]
        for j in range(pc.shape[1]):
            pc[b, j] = pc[a, j]


def _pixel_rig(
    intrinsics: tuple[float, float, float, float] | None, Q_old: np.ndarray, Q_new: np.ndarray
) -> tuple[float, ...] | None:
    """The kernels' ``rig``: None (Cartesian), or (f, p_x, p_y, b, σx², σy², 1/(f b), 1/f, log (f³ b)²,
    log (f² b)²) with the pixel model's noise Q = diag(σx², σx², σy²) (2D: diag(σx², σx²)), which must be
    every row's."""
    if intrinsics is None:
        return None
    f, px, py, b = (float(v) for v in intrinsics)
    vx = vy = 1.0
    Q0 = Q_old[0] if Q_old.shape[0] else (Q_new[0] if Q_new.shape[0] else None)
    if Q0 is not None:
        dz = Q0.shape[0]
        vx, vy = float(Q0[0, 0]), float(Q0[2, 2]) if dz == 3 else 1.0
        expect = np.diag([vx, vx, vy][:dz])
        if not (np.all(Q_old == expect) and np.all(Q_new == expect)):
            raise InputError("FastSLAM pixel kernel: expected Q = diag(σx², σx², σy²) for every observation")
    return (f, px, py, b, vx, vy, 1.0 / (f * b), 1.0 / f, 2.0 * math.log(f**3 * b), 2.0 * math.log(f * f * b))


_DIMS: dict[int, Dim2 | Dim3] = {2: Dim2(), 3: Dim3()}
_RANGE_BEARING = RangeBearing()


def _kernel_model(
    model: MeasurementModel, Q_old: np.ndarray, Q_new: np.ndarray
) -> tuple[tuple[float, ...] | RangeBearing | None, Dim2 | Dim3]:
    """(``rig``, dimension marker) of ``model`` for the kernels; InputError for a model they lack."""
    D = _DIMS[model.dm]
    if model.intrinsics is not None:
        return _pixel_rig(model.intrinsics, Q_old, Q_new), D
    if model.name == RANGE_BEARING_2D.name:
        return _RANGE_BEARING, D
    if model.name in (CARTESIAN_2D.name, CARTESIAN_3D.name):
        return None, D
    raise InputError(f"FastSLAM kernel: no formulas for the measurement model {model.name!r}")


def _run(
    version: int,
    pose: np.ndarray,
    S: np.ndarray | None,
    pool_mean: np.ndarray,
    pool_cov: np.ndarray,
    table: np.ndarray,
    bs: int,
    slots_old: np.ndarray,
    z_old: np.ndarray,
    Q_old: np.ndarray,
    slots_new: np.ndarray,
    z_new: np.ndarray,
    Q_new: np.ndarray,
    eps: np.ndarray | None,
    model: MeasurementModel,
    floor: float,
    seq_weights: bool = False,
    out_mu: np.ndarray | None = None,
    out_Sx: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    P, dx = pose.shape
    if dx != model.dx:
        raise InputError(f"FastSLAM kernel: expected poses (P, {model.dx}) for {model.name}, got {pose.shape}")
    rig, D = _kernel_model(model, Q_old, Q_new)
    out_pose = np.empty_like(pose)
    dlogw = np.zeros(P)
    # FastSLAM 2.0's proposal means and covariances (the Rao-Blackwellised pose estimate uses them)
    mu_ = out_mu if out_mu is not None else np.empty((P, dx))
    Sx_ = out_Sx if out_Sx is not None else np.empty((P, dx, dx))
    S_ = S if S is not None else np.zeros((P, dx, dx))
    eps_ = eps if eps is not None else np.zeros((P, dx))
    _step(
        int(version),
        np.ascontiguousarray(pose, dtype=np.float64),
        np.ascontiguousarray(S_, dtype=np.float64),
        pool_mean,
        pool_cov,
        np.ascontiguousarray(table, dtype=np.int64),
        int(bs),
        np.ascontiguousarray(slots_old, dtype=np.int64),
        np.ascontiguousarray(z_old, dtype=np.float64),
        np.ascontiguousarray(Q_old, dtype=np.float64),
        np.ascontiguousarray(slots_new, dtype=np.int64),
        np.ascontiguousarray(z_new, dtype=np.float64),
        np.ascontiguousarray(Q_new, dtype=np.float64),
        np.ascontiguousarray(eps_, dtype=np.float64),
        float(floor),
        out_pose,
        dlogw,
        bool(seq_weights),
        mu_,
        Sx_,
        rig,
        D,
        max(1, min(P, nb.get_num_threads())),
    )
    return out_pose, dlogw


def fastslam_step(
    version: int,
    pose: np.ndarray,
    S: np.ndarray | None,
    lm_mean: np.ndarray,
    lm_cov: np.ndarray,
    slots_old: np.ndarray,
    z_old: np.ndarray,
    Q_old: np.ndarray,
    slots_new: np.ndarray,
    z_new: np.ndarray,
    Q_new: np.ndarray,
    eps: np.ndarray | None,
    model: MeasurementModel,
    floor: float,
    seq_weights: bool = False,
    out_mu: np.ndarray | None = None,
    out_Sx: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """One FastSLAM measurement step for all particles; the landmark arrays are updated in place.

    Version 1 (§9): ``pose`` (P, dx) are the sampled poses; the landmark updates give the weights.
    Version 2 (§10): ``pose`` are the priors x̂ with covariances ``S`` (P, dx, dx); the proposal is
    built from the identified landmarks, a pose drawn with ``eps`` (P, dx) standard normals, then
    the landmarks are updated at it. New landmarks are initialised from the final pose (their
    covariance plus ``floor``·I). ``seq_weights`` takes 2.0's importance weight from the proposal's
    sequential innovations (the chain rule; docs/math.md §10) instead of §10's
    product at the prior; ``out_mu`` (P, dx) and ``out_Sx`` (P, dx, dx), when given, receive the
    proposal means and covariances (version 2).

    Landmarks: lm_mean (P, cap, dm), lm_cov (P, cap, dm, dm) dense (block storage with one block of
    ``cap`` slots per particle); slots_old (N,) distinct with z_old (N, dz), Q_old (N, dz, dz);
    slots_new, z_new, Q_new likewise. ``model``: Cartesian 2D/3D, range–bearing 2D, or a stereo
    pixel model (z are pixels, and every Q must be the model's diag(σx², σx², σy²)).

    Returns:
        (pose (P, dx) after the step, log-weight increment (P,)).
    """
    P, cap = lm_mean.shape[:2]
    table = np.arange(P, dtype=np.int64)[:, None]
    return _run(
        version,
        pose,
        S,
        lm_mean,
        lm_cov,
        table,
        cap,
        slots_old,
        z_old,
        Q_old,
        slots_new,
        z_new,
        Q_new,
        eps,
        model,
        floor,
        seq_weights,
        out_mu,
        out_Sx,
    )


def fastslam_step_store(
    version: int,
    pose: np.ndarray,
    S: np.ndarray | None,
    store: LandmarkStore,
    slots_old: np.ndarray,
    z_old: np.ndarray,
    Q_old: np.ndarray,
    slots_new: np.ndarray,
    z_new: np.ndarray,
    Q_new: np.ndarray,
    eps: np.ndarray | None,
    model: MeasurementModel,
    floor: float,
    seq_weights: bool = False,
    out_mu: np.ndarray | None = None,
    out_Sx: np.ndarray | None = None,
    threads: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`fastslam_step` directly in a copy-on-write :class:`LandmarkStore` (no gather/scatter copies).

    The blocks written this step are made private first, then the kernel reads and writes the pool
    through the particles' block tables. ``threads``: the kernel's threads from this call on (capped
    by ``NUMBA_NUM_THREADS``; 0 leaves numba's setting, by default one per core); results do not
    depend on it.
    """
    if threads:
        nb.set_num_threads(min(int(threads), int(getattr(nb.config, "NUMBA_NUM_THREADS", 1))))
    store.make_writable(np.concatenate([slots_old, slots_new]), copy_blocks)
    return _run(
        version,
        pose,
        S,
        store.pool_mean,
        store.pool_cov,
        store.table,
        store.B,
        slots_old,
        z_old,
        Q_old,
        slots_new,
        z_new,
        Q_new,
        eps,
        model,
        floor,
        seq_weights,
        out_mu,
        out_Sx,
    )


def warmup(models: tuple[str, ...] = ("cartesian", "pixel"), dims: tuple[int, ...] = (2, 3)) -> None:
    """Compile (first run) or load from the cache (later runs) every kernel on tiny inputs.
    ``models``, ``dims``: the measurement models and dimensions to prepare the FastSLAM step for.
    Each (model, dimension) is a compilation of its own; one left out compiles on first use (the
    range–bearing model, used by ``update_range_bearing`` only, is not prepared)."""
    st = LandmarkStore(2, 3, 2)
    st.ensure_capacity(2)
    st.select(np.array([0, 0]))
    st.make_writable(np.array([0]), copy_blocks)
    for want_S in (False, True):
        predict3_numba(np.zeros((2, 6)), np.zeros(6), np.eye(6), np.zeros(6), want_S, 1e-3)
    for dm in dims:
        dx = 6 if dm == 3 else 3
        P, n = 2, 2
        pose = np.zeros((P, dx))
        S = np.tile(np.eye(dx) * 1e-4, (P, 1, 1))
        mean = np.ones((P, n, dm))
        cov = np.tile(np.eye(dm), (P, n, 1, 1))
        z = np.ones((1, dm))
        z[0, 0] = 2.0  # a positive disparity for the pixel model
        Q = np.eye(dm)[None]
        for name in models:
            # one compilation each; the step's version is a run-time argument
            cart = CARTESIAN_3D if dm == 3 else CARTESIAN_2D
            model = stereo_pixel_model(dm, 1.0, 0.0, 0.0, 1.0) if name == "pixel" else cart
            for version in (1, 2):
                fastslam_step(
                    version, pose, S, mean, cov, np.array([0]), z, Q, np.array([1]), z, Q, np.zeros((P, dx)), model, 0.0
                )
