"""The simulated worlds' building blocks: textured planar surfaces, value noise, and the truth of
a rover driving along a path (drivers/simworld.py builds the yard worlds from them,
drivers/simterrain.py the open terrain).

Frames (``robotd.core.geometry``): FRD, the world ``W`` the robot frame at t = 0; a world's layout
lies in its own frame ``Y`` (the yard frame), moved into ``W`` once at construction.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from robotd.core.geometry import euler_rate_matrix, euler_to_R, se3

# --------------------------------------------------------------------------------------------
# Surfaces


@dataclass(frozen=True, slots=True, eq=False)
class Surface:
    """One textured planar rectangle.

    A texel (s, t) of the level-0 texture (column s, row t, centres at integers) sits at the world
    point ``origin_W + s * u_W + t * v_W``; ``u_W``/``v_W`` (3,) [m per texel] span the plane and
    ``normal_W`` (3,) is the unit normal of the visible side (surfaces are one-sided: seen from
    behind they are culled). ``corners_W`` (4, 3) [m] are the texture's outer texel edges.
    ``alpha``: the coverage's mip chain (same shapes as ``mips``, 255 opaque, 0 transparent), or
    empty for an opaque rectangle; where it is below 128 the surface is not there (a tree crown's
    outline against what lies behind it). ``lod_nearest``: the renderer picks each depth band's mip
    level for the band's nearest point instead of its centre (for large ground tiles, whose bands
    reach far to the side: the centre's grazing view would blur the near part).
    """

    name: str
    origin_W: np.ndarray  # (3,) [m]
    u_W: np.ndarray  # (3,) [m/texel]
    v_W: np.ndarray  # (3,) [m/texel]
    normal_W: np.ndarray  # (3,) unit, towards the viewer side
    corners_W: np.ndarray  # (4, 3) [m]
    texel_m: float
    mips: tuple[np.ndarray, ...]  # level L: (h / 2^L, w / 2^L) uint8, cv2.pyrDown chain
    alpha: tuple[np.ndarray, ...] = ()  # coverage mips as ``mips``, or () for opaque
    lod_nearest: bool = False


def _mip_chain(texture: np.ndarray) -> tuple[np.ndarray, ...]:
    mips = [np.ascontiguousarray(texture)]
    while min(mips[-1].shape) >= 16 and len(mips) < 7:
        mips.append(cv2.pyrDown(mips[-1]))
    return tuple(mips)


def make_surface(
    name: str,
    corner_W: np.ndarray,
    edge_a_W: np.ndarray,
    edge_b_W: np.ndarray,
    outward_W: np.ndarray,
    texture: np.ndarray,
    alpha: np.ndarray | None = None,
    lod_nearest: bool = False,
) -> Surface:
    """A rectangle ``corner + α edge_a + β edge_b`` (α, β ∈ [0, 1]) wearing ``texture`` (h, w) uint8.

    The texture's columns run along ``edge_a`` and its rows along ``edge_b``, as an image seen
    from the ``outward_W`` side (like a camera: x right, y down, z into the surface), so letters
    read the right way round; if ``edge_a`` runs the other way for that side it is reversed.
    ``alpha`` (h, w) uint8: the surface's coverage (255 where it is, 0 where it is not), if not
    the whole rectangle. ``lod_nearest``: see :class:`Surface`.
    """
    corner = np.asarray(corner_W, float)
    a = np.asarray(edge_a_W, float)
    b = np.asarray(edge_b_W, float)
    outward = np.asarray(outward_W, float)
    if float(np.cross(a, b) @ outward) > 0.0:
        corner, a = corner + a, -a
    n = -np.cross(a, b)
    n /= np.linalg.norm(n)
    h, w = texture.shape
    u = a / w
    v = b / h
    # texel centres at integers: the texture's outer edges are at s = -0.5 and s = w - 0.5
    origin = corner + 0.5 * u + 0.5 * v
    corners = np.stack([corner, corner + a, corner + a + b, corner + b])
    if alpha is not None and alpha.shape != texture.shape:
        raise ValueError(f"make_surface {name}: alpha {alpha.shape} and texture {texture.shape} differ")
    cover = _mip_chain(alpha) if alpha is not None else ()
    return Surface(name, origin, u, v, n, corners, float(np.linalg.norm(u)), _mip_chain(texture), cover, lod_nearest)


def transformed(s: Surface, T_new_old: np.ndarray) -> Surface:
    """The same surface with its geometry mapped by the rigid transform ``T_new_old`` (4, 4)."""
    R, t = T_new_old[:3, :3], T_new_old[:3, 3]
    return Surface(
        s.name,
        R @ s.origin_W + t,
        R @ s.u_W,
        R @ s.v_W,
        R @ s.normal_W,
        s.corners_W @ R.T + t,
        s.texel_m,
        s.mips,
        s.alpha,
        s.lod_nearest,
    )


# --------------------------------------------------------------------------------------------
# Value noise, the base of every procedural texture


def value_noise(rng: np.random.Generator, h: int, w: int, cells: tuple[int, ...], gamma: float = 0.8) -> np.ndarray:
    """Multi-octave value noise (h, w) float32 in [0, 1]: random grids of ``cells`` texels, upsampled
    bicubically and summed with amplitude ∝ cell^gamma (a 1/f-like spectrum)."""
    acc = np.zeros((h, w), np.float32)
    total = 0.0
    for c in cells:
        gh, gw = max(2, h // c + 2), max(2, w // c + 2)
        grid = rng.random((gh, gw), dtype=np.float32)
        up = cv2.resize(grid, ((gw - 1) * c, (gh - 1) * c), interpolation=cv2.INTER_CUBIC)
        amp = float(c) ** gamma
        acc += amp * up[:h, :w]
        total += amp
    acc /= total
    lo, hi = np.percentile(acc[:: max(1, h // 64), :: max(1, w // 64)], (1, 99))
    return np.clip((acc - lo) / max(hi - lo, 1e-6), 0.0, 1.0)


# --------------------------------------------------------------------------------------------
# The truth of a rover on a path


@dataclass(frozen=True, slots=True)
class TruthState:
    """Ground truth at one time: ``T_world_robot`` (4, 4), ``vel_R_mps`` (3,) and ``rate_R_radps``
    (3,) in the robot frame (FRD), as the wheels and a gyro would ideally measure them."""

    T_world_robot: np.ndarray
    vel_R_mps: np.ndarray
    rate_R_radps: np.ndarray


def _tilt(tilt_rad: float, s: float) -> tuple[np.ndarray, np.ndarray]:
    """Terrain rocking: roll, pitch [rad] as functions of the distance driven ``s`` [m] (0 at
    s = 0), and their derivatives d/ds [rad/m]."""
    a = tilt_rad
    k1, k2 = 2 * np.pi / 3.7, 2 * np.pi / 5.3  # [rad/m]: bumps every few metres
    rp = np.array([a * math.sin(k1 * s), a * math.sin(k2 * s + 1.0) * math.sin(0.5 * k1 * s)])
    drp = np.array(
        [
            a * k1 * math.cos(k1 * s),
            a
            * (
                k2 * math.cos(k2 * s + 1.0) * math.sin(0.5 * k1 * s)
                + 0.5 * k1 * math.sin(k2 * s + 1.0) * math.cos(0.5 * k1 * s)
            ),
        ]
    )
    return rp, drp


def rover_truth(
    T_world_yard: np.ndarray, xy: tuple[float, float], yaw: float, v: float, yaw_rate: float, tilt_rad: float, s: float
) -> TruthState:
    """The truth of a rover at ``xy`` [m] (yard frame) heading ``yaw`` [rad], driving forward at
    ``v`` [m/s] and turning at ``yaw_rate`` [rad/s] (no slip), rocked by the terrain at distance
    driven ``s`` [m]: the velocity along the ground tangent goes into the (tilted) body frame and
    the body rates are E⁻¹ · (Euler rates) (docs/math.md §6.3)."""
    rp, drp = _tilt(tilt_rad, s)
    rpy = np.array([rp[0], rp[1], yaw])
    R_yard = euler_to_R(rpy)
    T_yard_robot = se3(R_yard, np.array([xy[0], xy[1], 0.0]))
    vel_yard = v * np.array([math.cos(yaw), math.sin(yaw), 0.0])
    rpy_dot = np.array([drp[0] * v, drp[1] * v, yaw_rate])
    rate_R = np.linalg.solve(euler_rate_matrix(rpy), rpy_dot)
    return TruthState(T_world_yard @ T_yard_robot, R_yard.T @ vel_yard, rate_R)


class VaryingSpeed:
    """A rover driving along a path at arc-length speed v(t) = speed (1 + ε sin(2π t / T_v)),
    starting ``start_m`` [m] along it: the distance driven, its inverse and the speed, in closed
    form. The subclass sets ``speed``, ``eps``, ``T_v`` and ``start_m``."""

    speed: float
    eps: float
    T_v: float
    start_m: float

    def arc_length(self, t_s: float) -> float:
        """Distance driven since t = 0: s(t) = ∫ v dt, in closed form."""
        w = 2.0 * np.pi / self.T_v
        return self.speed * (t_s + self.eps * (1.0 - math.cos(w * t_s)) / w)

    def time_at(self, s_m: float) -> float:
        """When the rover is at arc length ``s_m`` (≥ ``start_m``, counted on from lap to lap):
        the inverse of :meth:`arc_length` by Newton's method (it increases monotonically);
        +inf for a parked rover."""
        ds = s_m - self.start_m
        if self.speed <= 0.0:
            return math.inf
        w = 2.0 * np.pi / self.T_v
        t = ds / self.speed
        for _ in range(50):
            step = (self.arc_length(t) - ds) / (self.speed * (1.0 + self.eps * math.sin(w * t)))
            t -= step
            if abs(step) < 1e-12 * max(1.0, abs(t)):
                break
        return t

    def speed_at(self, t_s: float) -> float:
        return self.speed * (1.0 + self.eps * math.sin(2.0 * np.pi * t_s / self.T_v))
