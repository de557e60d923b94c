"""The simulated rover's world: textured planar surfaces (a walled yard with boxes and posts) and
the rover's trajectory through it, with its exact velocities for the odometry.

Frames (``robotd.geometry``): the world ``W`` is the robot frame at t = 0 (FRD: x forward,
y right, z down), so the truth starts at the identity and the flat ground lies at z = +h, h the
camera height. The yard is laid out in its own frame ``Y`` (same axes, origin on the ground below
the yard centre shifted up by h) and moved into ``W`` once at construction.

Everything here is deterministic for a seed: the layout and the textures come from
``np.random.default_rng([seed, ...])`` streams, never from global state.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np

from robotd.errors import DriverError
from robotd.geometry import euler_rate_matrix, euler_to_R, se3, se3_inverse

# --------------------------------------------------------------------------------------------
# Surfaces


@dataclass(frozen=True, slots=True, eq=False)
class Surface:
    """One textured planar rectangle.

    A texel (s, t) of the level-0 texture (column s, row t, centres at integers) sits at the world
    point ``origin_W + s * u_W + t * v_W``; ``u_W``/``v_W`` (3,) [m per texel] span the plane and
    ``normal_W`` (3,) is the unit normal of the visible side (surfaces are one-sided: seen from
    behind they are culled). ``corners_W`` (4, 3) [m] are the texture's outer texel edges.
    """

    name: str
    origin_W: np.ndarray  # (3,) [m]
    u_W: np.ndarray  # (3,) [m/texel]
    v_W: np.ndarray  # (3,) [m/texel]
    normal_W: np.ndarray  # (3,) unit, towards the viewer side
    corners_W: np.ndarray  # (4, 3) [m]
    texel_m: float
    mips: tuple[np.ndarray, ...]  # level L: (h / 2^L, w / 2^L) uint8, cv2.pyrDown chain


def make_surface(
    name: str,
    corner_W: np.ndarray,
    edge_a_W: np.ndarray,
    edge_b_W: np.ndarray,
    outward_W: np.ndarray,
    texture: np.ndarray,
) -> Surface:
    """A rectangle ``corner + α edge_a + β edge_b`` (α, β ∈ [0, 1]) wearing ``texture`` (h, w) uint8.

    The texture's columns run along ``edge_a`` and its rows along ``edge_b``, as an image seen
    from the ``outward_W`` side (like a camera: x right, y down, z into the surface), so letters
    read the right way round; if ``edge_a`` runs the other way for that side it is reversed.
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
    mips = [np.ascontiguousarray(texture)]
    while min(mips[-1].shape) >= 16 and len(mips) < 7:
        mips.append(cv2.pyrDown(mips[-1]))
    return Surface(name, origin, u, v, n, corners, float(np.linalg.norm(u)), tuple(mips))


def transformed(s: Surface, T_new_old: np.ndarray) -> Surface:
    """The same surface with its geometry mapped by the rigid transform ``T_new_old`` (4, 4)."""
    R, t = T_new_old[:3, :3], T_new_old[:3, 3]
    return Surface(
        s.name, R @ s.origin_W + t, R @ s.u_W, R @ s.v_W, R @ s.normal_W, s.corners_W @ R.T + t, s.texel_m, s.mips
    )


# --------------------------------------------------------------------------------------------
# Procedural textures. Each is built from a few octaves of value noise plus drawn shapes, so
# corners and blobs are distinctive at every scale and nothing repeats (no tiling).


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


_GLYPHS = "ABCDEFGHJKLMNPQRSTUVWXYZ0123456789#&%@"


def _stencil_text(img: np.ndarray, rng: np.random.Generator, n: int, scale_px: float) -> None:
    """Draw ``n`` random short strings (stencilled letters) of height ≈ ``scale_px`` texels."""
    h, w = img.shape
    fonts = (cv2.FONT_HERSHEY_SIMPLEX, cv2.FONT_HERSHEY_DUPLEX, cv2.FONT_HERSHEY_TRIPLEX, cv2.FONT_HERSHEY_COMPLEX)
    for _ in range(n):
        text = "".join(rng.choice(list(_GLYPHS), size=int(rng.integers(1, 5))))
        scale = scale_px / 22.0 * float(rng.uniform(0.6, 1.6))
        thick = max(1, int(scale * float(rng.uniform(1.5, 4.0))))
        org = (int(rng.integers(0, max(1, w - 20))), int(rng.integers(int(scale_px), max(int(scale_px) + 1, h))))
        grey = int(rng.choice([int(rng.integers(0, 60)), int(rng.integers(190, 256))]))
        cv2.putText(img, text, org, int(rng.choice(fonts)), scale, grey, thick, cv2.LINE_AA)


def _blobs(img: np.ndarray, rng: np.random.Generator, n: int, r_min: float, r_max: float) -> None:
    """Random filled ellipses, rectangles and triangles in random greys ("coloured blobs in grey")."""
    h, w = img.shape
    for _ in range(n):
        cx, cy = int(rng.integers(0, w)), int(rng.integers(0, h))
        r = float(rng.uniform(r_min, r_max))
        grey = int(rng.integers(0, 256))
        kind = int(rng.integers(0, 3))
        if kind == 0:
            axes = (max(1, int(r)), max(1, int(r * rng.uniform(0.3, 1.0))))
            cv2.ellipse(img, (cx, cy), axes, float(rng.uniform(0, 180)), 0, 360, grey, -1, cv2.LINE_AA)
        elif kind == 1:
            ang = rng.uniform(0, np.pi)
            d = np.array([[np.cos(ang), np.sin(ang)], [-np.sin(ang), np.cos(ang)]])
            half = np.array([r, r * rng.uniform(0.3, 1.0)])
            pts = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * half @ d + (cx, cy)
            cv2.fillConvexPoly(img, pts.astype(np.int32), grey, cv2.LINE_AA)
        else:
            pts = (rng.uniform(-r, r, (3, 2)) + np.array([cx, cy])).astype(np.int32)
            cv2.fillConvexPoly(img, pts, grey, cv2.LINE_AA)


def _to_u8(x: np.ndarray) -> np.ndarray:
    return np.clip(x * 255.0, 0, 255).astype(np.uint8)


def texture_ground(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """Gravel and dirt: noise, scattered stones, a few painted marks and letters."""
    base = value_noise(rng, h, w, (512, 128, 32, 8, 3))
    img = _to_u8(0.25 + 0.5 * base)
    area = h * w
    # stones: many small ellipses, light and dark
    n = area // 900
    cx = rng.integers(0, w, n)
    cy = rng.integers(0, h, n)
    rx = rng.uniform(2, 9, n)
    ry = rx * rng.uniform(0.4, 1.0, n)
    ang = rng.uniform(0, 180, n)
    grey = rng.integers(20, 240, n)
    for i in range(n):
        cv2.ellipse(img, (int(cx[i]), int(cy[i])), (int(rx[i]), int(ry[i])), float(ang[i]), 0, 360, int(grey[i]), -1)
    _blobs(img, rng, area // 40000, 10, 60)
    _stencil_text(img, rng, area // 120000, 60.0)
    return img


def texture_bricks(rng: np.random.Generator, h: int, w: int, texel_m: float) -> np.ndarray:
    """A brick wall (0.24 × 0.075 m bricks, running bond) with per-brick grey, stains and posters."""
    bw, bh = max(4, round(0.24 / texel_m)), max(3, round(0.075 / texel_m))
    mortar = max(1, round(0.01 / texel_m))
    noise = value_noise(rng, h, w, (256, 64, 16, 4))
    img = np.empty((h, w), np.float32)
    img[:] = 0.55
    for r, y0 in enumerate(range(0, h, bh)):
        off = (bw // 2) * (r % 2)
        for x0 in range(-off, w, bw):
            g = float(rng.uniform(0.25, 0.75))
            img[y0 : y0 + bh - mortar, max(0, x0) : max(0, x0 + bw - mortar)] = g
    out = _to_u8(0.75 * img + 0.35 * (noise - 0.5) + 0.1)
    _blobs(out, rng, max(4, h * w // 30000), 15, 70)
    _stencil_text(out, rng, max(3, h * w // 25000), 45.0)
    return out


def texture_crate(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """A box face: noise, bold shapes, planks, stencilled letters."""
    noise = value_noise(rng, h, w, (128, 32, 8, 3))
    out = _to_u8(0.2 + 0.6 * noise)
    plank = int(rng.integers(18, 40))
    for y in range(int(rng.integers(0, plank)), h, plank):
        cv2.line(out, (0, y), (w - 1, y), int(rng.integers(0, 80)), 2)
    _blobs(out, rng, max(6, h * w // 6000), 8, 40)
    _stencil_text(out, rng, max(2, h * w // 12000), 40.0)
    return out


# --------------------------------------------------------------------------------------------
# Trajectory: a smooth closed loop on the ground


@dataclass(frozen=True, slots=True)
class TruthState:
    """Ground truth at one time: ``T_world_robot`` (4, 4), ``vel_R_mps`` (3,) and ``rate_R_radps``
    (3,) in the robot frame (FRD), as the wheels and a gyro would ideally measure them."""

    T_world_robot: np.ndarray
    vel_R_mps: np.ndarray
    rate_R_radps: np.ndarray


class LoopTrajectory:
    """The rover drives a peanut-shaped loop (about 28.5 m) at a gently varying speed.

    Path in the yard frame: x(φ) = A r(φ) cos φ, y(φ) = B r(φ) sin φ, r = 1 + e cos 2φ; the rover
    moves along it with arc-length speed v(t) = speed (1 + ε sin(2π t / T_v)), heading along the
    tangent (no slip), so body velocity is (v, 0, 0) and yaw rate is κ v with κ the signed
    curvature (x′y″ − y′x″)/|p′|³ (positive = right turn in FRD). ``tilt_deg`` adds a gentle
    terrain-like rocking: roll and pitch of that amplitude varying along the path; body rates then
    come from the Euler rates through E⁻¹ (algorithms.md §6.3).
    """

    def __init__(
        self, speed_mps: float = 1.0, tilt_deg: float = 0.0, size: tuple[float, float] = (4.5, 3.5), eps: float = 0.15
    ) -> None:
        self.A, self.B = size
        self.e = 0.3  # waist of the peanut: the curvature changes sign twice per lap, min radius 1.8 m
        self.speed = speed_mps
        self.eps = eps
        self.T_v = 11.0  # [s] period of the speed variation
        self.tilt_rad = math.radians(tilt_deg)
        phi = np.linspace(0.0, 2.0 * np.pi, 20001)
        dp = np.hypot(*self._d1(phi))
        # arc length by the trapezoid rule on a fine grid; φ(s) by interpolation
        self._s_tab = np.concatenate([[0.0], np.cumsum(0.5 * (dp[1:] + dp[:-1]) * np.diff(phi))])
        self._phi_tab = phi
        self.length_m = float(self._s_tab[-1])
        x0, y0 = self._p(np.array(0.0))
        psi0 = float(np.arctan2(*self._d1(np.array(0.0))[::-1]))
        # yard → world: the world is the robot frame at t = 0 (position, heading; tilt is 0 at t = 0)
        self.T_yard_world0 = se3(euler_to_R(np.array([0.0, 0.0, psi0])), np.array([float(x0), float(y0), 0.0]))
        self.T_world_yard = se3_inverse(self.T_yard_world0)

    def _p(self, phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r = 1.0 + self.e * np.cos(2 * phi)
        return self.A * r * np.cos(phi), self.B * r * np.sin(phi)

    def _d1(self, phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r = 1.0 + self.e * np.cos(2 * phi)
        dr = -2.0 * self.e * np.sin(2 * phi)
        c, s = np.cos(phi), np.sin(phi)
        return self.A * (dr * c - r * s), self.B * (dr * s + r * c)

    def _d2(self, phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r = 1.0 + self.e * np.cos(2 * phi)
        dr = -2.0 * self.e * np.sin(2 * phi)
        ddr = -4.0 * self.e * np.cos(2 * phi)
        c, s = np.cos(phi), np.sin(phi)
        return self.A * (ddr * c - 2 * dr * s - r * c), self.B * (ddr * s + 2 * dr * c - r * s)

    def path_points_yard(self, n: int = 720) -> np.ndarray:
        """(n, 2) [m] points of the loop in the yard frame (for placing obstacles clear of it)."""
        x, y = self._p(np.linspace(0, 2 * np.pi, n, endpoint=False))
        return np.stack([x, y], 1)

    def arc_length(self, t_s: float) -> float:
        """s(t) = ∫ v dt, in closed form."""
        w = 2.0 * np.pi / self.T_v
        return self.speed * (t_s + self.eps * (1.0 - math.cos(w * t_s)) / w)

    def speed_at(self, t_s: float) -> float:
        return self.speed * (1.0 + self.eps * math.sin(2.0 * np.pi * t_s / self.T_v))

    def _tilt(self, s: float) -> tuple[np.ndarray, np.ndarray]:
        """Roll, pitch as functions of arc length, and their derivatives d/ds."""
        a = self.tilt_rad
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

    def state(self, t_s: float) -> TruthState:
        """Truth at ``t_s`` seconds after the start (t ≥ 0)."""
        s = self.arc_length(t_s)
        v = self.speed_at(t_s)
        phi = np.array(np.interp(s % self.length_m, self._s_tab, self._phi_tab))
        x, y = self._p(phi)
        dx, dy = self._d1(phi)
        ddx, ddy = self._d2(phi)
        yaw = float(np.arctan2(dy, dx))
        kappa = float((dx * ddy - dy * ddx) / (dx * dx + dy * dy) ** 1.5)
        rp, drp = self._tilt(s)
        rpy = np.array([rp[0], rp[1], yaw])
        R_yard = euler_to_R(rpy)
        T_yard_robot = se3(R_yard, np.array([float(x), float(y), 0.0]))
        T_world_robot = self.T_world_yard @ T_yard_robot
        # velocity along the ground tangent in the yard frame, into the (tilted) body frame
        vel_yard = v * np.array([math.cos(yaw), math.sin(yaw), 0.0])
        vel_R = R_yard.T @ vel_yard
        rpy_dot = np.array([drp[0] * v, drp[1] * v, kappa * v])
        rate_R = np.linalg.solve(euler_rate_matrix(rpy), rpy_dot)
        return TruthState(T_world_robot, vel_R, rate_R)


# --------------------------------------------------------------------------------------------
# The yard


@dataclass(frozen=True, slots=True, eq=False)
class World:
    """Surfaces in the world frame, the trajectory, and the layout facts tests and docs use."""

    seed: int
    surfaces: tuple[Surface, ...]
    trajectory: LoopTrajectory
    cam_height_m: float
    yard_size_m: tuple[float, float]


WORLDS = ("yard",)


def _box_surfaces(
    name: str,
    rng: np.random.Generator,
    c: np.ndarray,
    yaw: float,
    size: tuple[float, float, float],
    h: float,
    texel: float,
) -> list[Surface]:
    """Four sides and the top of a box standing on the ground (z = h) in the yard frame."""
    lx, ly, lz = size
    R = euler_to_R(np.array([0.0, 0.0, yaw]))
    ex, ey = R[:, 0] * lx, R[:, 1] * ly
    up = np.array([0.0, 0.0, -lz])  # FRD: up is -z
    base = np.array([c[0], c[1], h]) - 0.5 * ex - 0.5 * ey
    out = []
    faces = [
        (base + up, ex, -up, -R[:, 1], lx, lz),
        (base + up + ey, ex, -up, R[:, 1], lx, lz),
        (base + up, ey, -up, -R[:, 0], ly, lz),
        (base + up + ex, ey, -up, R[:, 0], ly, lz),
        (base + up, ex, ey, np.array([0.0, 0.0, -1.0]), lx, ly),
    ]
    for i, (corner, a, b, outward, la, lb) in enumerate(faces):
        tex = texture_crate(rng, max(8, round(lb / texel)), max(8, round(la / texel)))
        out.append(make_surface(f"{name}.{i}", corner, a, b, outward, tex))
    return out


def build_world(seed: int, world: str = "yard", speed_mps: float = 1.0, tilt_deg: float = 0.0) -> World:
    """The textured yard for ``seed`` with the rover driving at ``speed_mps`` (tilt in degrees).

    The surfaces and textures (about 12 Mpx, 1–2 s to generate) are built once per (seed, world)
    and cached; speed and tilt only change the trajectory, whose start pose (and so the world
    frame) does not depend on them.
    """
    if world not in WORLDS:
        raise DriverError(f"sim world {world!r}: unknown; known: {', '.join(WORLDS)}")
    traj = LoopTrajectory(speed_mps=speed_mps, tilt_deg=tilt_deg)
    surfaces, h, size = _yard_surfaces(seed, world)
    T = traj.T_world_yard
    return World(seed, tuple(transformed(s, T) for s in surfaces), traj, h, size)


@functools.lru_cache(maxsize=3)
def _yard_surfaces(seed: int, world: str) -> tuple[tuple[Surface, ...], float, tuple[float, float]]:
    """Surfaces of the yard in the yard frame, camera height h [m], yard size (x, y) [m].

    Layout in the yard frame: a loop of about 28.5 m (11.7 × 5.2 m) inside a walled yard of
    about 16.7 × 10.2 m (walls 2.5 m high), boxes and posts scattered at least 0.9 m clear of the path;
    camera height 0.4 m. Textures: 5 mm/texel on walls and boxes, 6 mm on the ground.
    """
    h = 0.4
    traj = LoopTrajectory()
    ext = np.abs(traj.path_points_yard()).max(0)
    half_x, half_y = float(ext[0]) + 2.5, float(ext[1]) + 2.5
    wall_h = 2.5
    g_texel, w_texel, b_texel = 0.006, 0.005, 0.005
    surfaces: list[Surface] = []

    rng = np.random.default_rng([seed, 101])
    gx, gy = 2 * half_x, 2 * half_y
    ground_tex = texture_ground(rng, round(gy / g_texel), round(gx / g_texel))
    surfaces.append(
        make_surface(
            "ground",
            np.array([-half_x, -half_y, h]),
            np.array([gx, 0.0, 0.0]),
            np.array([0.0, gy, 0.0]),
            np.array([0.0, 0.0, -1.0]),
            ground_tex,
        )
    )
    up = np.array([0.0, 0.0, -wall_h])
    corners = [(-half_x, -half_y), (half_x, -half_y), (half_x, half_y), (-half_x, half_y)]
    for i in range(4):
        p0 = np.array([*corners[i], h])
        p1 = np.array([*corners[(i + 1) % 4], h])
        along = p1 - p0
        inward = -np.array([p0[0] + p1[0], p0[1] + p1[1], 0.0])
        tex = texture_bricks(rng, round(wall_h / w_texel), round(float(np.linalg.norm(along)) / w_texel), w_texel)
        surfaces.append(make_surface(f"wall{i}", p0 + up, along, -up, inward, tex))

    # obstacles, clear of the path
    path = traj.path_points_yard()
    placed: list[tuple[float, float, float]] = []
    n_boxes, n_posts = 12, 8
    tries = 0
    while len(placed) < n_boxes + n_posts and tries < 5000:
        tries += 1
        is_post = len(placed) >= n_boxes
        if is_post:
            size = (float(rng.uniform(0.1, 0.2)),) * 2 + (float(rng.uniform(1.2, 2.2)),)
        else:
            size = (float(rng.uniform(0.4, 1.2)), float(rng.uniform(0.4, 1.2)), float(rng.uniform(0.3, 1.4)))
        radius = 0.5 * math.hypot(size[0], size[1])
        c = np.array([rng.uniform(-half_x + 0.8, half_x - 0.8), rng.uniform(-half_y + 0.8, half_y - 0.8)])
        if np.min(np.linalg.norm(path - c, axis=1)) < 0.9 + radius:
            continue
        if any(math.hypot(c[0] - q[0], c[1] - q[1]) < radius + q[2] + 0.3 for q in placed):
            continue
        placed.append((float(c[0]), float(c[1]), radius))
        yaw = float(rng.uniform(0, np.pi))
        name = f"post{len(placed) - n_boxes}" if is_post else f"box{len(placed)}"
        surfaces.extend(_box_surfaces(name, rng, c, yaw, size, h, b_texel))

    return tuple(surfaces), h, (gx, gy)
