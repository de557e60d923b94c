"""``sim://?world=open_terrain``: a rover or car in open country (issue 26, the open-terrain hard case).

Most of what such a camera sees is far: a field of grass and dirt up to a treeline and stands of
trees 30–200 m away, hills beyond them, the sky. Near it there is only the ground and, now and
then, a post, a rock or a bush. The world reproduces that: the features of the image's upper
half are far points with a disparity of a few pixels, which bias the translation of a stereo
front end whose disparity error is not zero-mean (issue 26, sequence A: similarity scale 0.934).

The layout, in the layout frame ``Y`` (FRD, origin on the ground plane's level at the path's
centre, as the yard's frame of drivers/simworld.py; the building blocks are drivers/simbase.py's):

- **The path**: a closed road lap of about 763 m, straights joined by six turns of +98°, −60°,
  +120°, +90°, −45° and +157° (positive: right) with peak radii of 25–50 m; the curvature
  ramps in and out over 10 m (sin²), so the yaw rate is smooth. The first turn is the long
  curve: 98° over 52.8 m, starting 10 m after the start. Two straights are sized so the lap
  closes exactly. :class:`RoadLoop`.
- **The ground**: square tiles of 40 m, each wearing one of three grass-and-dirt textures
  (2 cm per texel, no octave coarser than 1 m) turned by a multiple of 90°, never the same way
  round as a neighbour, so no pattern repeats at a fixed period; the renderer picks their mip
  level at each band's nearest visible corner (``lod_nearest``).
- **Sparse near objects**: about one per 20 m of path (38 on the lap for seed 1): posts
  (1.0–1.3 m), rocks (0.3–1.5 m), bushes (1–3 m), 3–20 m to the side of the path and at least
  2.5 m from any part of it.
- **The far band**: 45 stands of trees (8–30 m wide, 8–18 m tall, at least 30 m from the path),
  a closed treeline (12–20 m tall) round the whole area 45 m beyond the path's farthest point,
  and hills (40–110 m high) on a ring 650 m out. Tree crowns and ridges have real outlines (a
  coverage mask, :attr:`drivers.simbase.Surface.alpha`), so farther things show between them.

The camera rig of this world is a car's: the robot origin (the baseline's centre) is 1.65 m above
the ground (KITTI's camera height) and the default baseline is 0.9 m. At the default 640×400
(f = 430 px) that makes fb = 387 px·m, KITTI's (718 px × 0.54 m), so a point has the disparity
it has in KITTI's images: 12.9 px at 30 m, 5 px (the front end's default far limit) at 77 m,
1.9 px at 200 m, 0.6 px at the hills. With the OAK-D's 0.0755 m (``baseline=0.0755``) the far
band would be 0.2–1.1 px, all beyond that limit.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence

import cv2
import numpy as np

from drivers.simbase import Surface, TruthState, VaryingSpeed, make_surface, rover_truth, value_noise
from robotd.core.geometry import euler_to_R, se3, se3_inverse

CAM_HEIGHT_M = 1.65  # robot origin above the ground [m] (KITTI's camera height)
BASELINE_M = 0.9  # the default baseline [m]: fb = 387 px·m at 640×400, KITTI's (718 px × 0.54 m)

# The lap: (straight before the turn [m], turn [deg], + = right in FRD, peak radius [m]), then a
# closing straight; the straights ADJUST (indices into the turns' straights; the last one is the
# closing straight) are resized so that the lap closes.
ROAD_LAP: tuple[tuple[float, float, float], ...] = (
    (25.0, 98.0, 25.0),
    (40.0, -60.0, 40.0),
    (30.0, 120.0, 35.0),
    (50.0, 90.0, 30.0),
    (30.0, -45.0, 50.0),
    (30.0, 157.0, 30.0),
)
CLOSING_M = 30.0
ADJUST = (4, 6)  # the straight before the fifth turn and the closing straight
RAMP_M = 10.0  # curvature ramps at each end of a turn (sin²) [m]
START_M = 15.0  # where the rover is at t = 0: 10 m before the first (98°) turn
_NODE_M = 0.5  # spacing of the precomputed path positions [m]
_GL_X, _GL_W = np.polynomial.legendre.leggauss(6)


def _ramps(u: np.ndarray, T: np.ndarray, Tr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Element-wise :func:`drivers.simworld._ramp`: a unit pulse of length T with sin² ramps of
    Tr at both ends, its value r(u) and its integral R(u) = ∫₀ᵘ r (R(T) = T − Tr)."""
    u = np.clip(u, 0.0, T)

    def head(x: np.ndarray) -> np.ndarray:  # ∫₀ˣ sin²(π y / 2Tr) dy
        return 0.5 * x - Tr / (2.0 * np.pi) * np.sin(np.pi * x / Tr)

    w = T - u
    r = np.where(u < Tr, np.sin(0.5 * np.pi * u / Tr) ** 2, np.where(w < Tr, np.sin(0.5 * np.pi * w / Tr) ** 2, 1.0))
    R = np.where(u < Tr, head(u), np.where(w < Tr, (T - Tr) - head(w), 0.5 * Tr + (u - Tr)))
    return r, R


class RoadLoop(VaryingSpeed):
    """A closed road lap of straights and turns (:data:`ROAD_LAP`), driven at ``speed_mps``
    (± 15 % with an 11 s period, as the yard's loop) without slip.

    The path is given by its curvature along the arc length: 0 on the straights, and on a turn of
    angle θ with peak radius ρ, κ(s) = ±r(s)/ρ with r a unit pulse whose sin² ramps last
    ``ramp_m`` (the turn is |θ|ρ + ramp_m long). The heading is its integral, in closed form; the
    position is the integral of the heading's direction, by 6-point Gauss–Legendre from nodes
    every 0.5 m (exact to far below a micrometre). The yaw rate is κ v. ``start_m``: where on the
    lap (arc length from the start of the first straight) the rover is at t = 0.
    """

    def __init__(
        self,
        speed_mps: float = 1.0,
        tilt_deg: float = 0.0,
        start_m: float = START_M,
        lap: tuple[tuple[float, float, float], ...] = ROAD_LAP,
        closing_m: float = CLOSING_M,
        adjust: tuple[int, int] = ADJUST,
        ramp_m: float = RAMP_M,
        eps: float = 0.15,
    ) -> None:
        self.speed = speed_mps
        self.eps = eps
        self.T_v = 11.0
        self.tilt_rad = math.radians(tilt_deg)
        self.start_m = float(start_m)
        if abs(sum(th for _, th, _ in lap) - 360.0) > 1e-9:
            raise ValueError(f"RoadLoop: the turns must add up to 360°, got {sum(th for _, th, _ in lap)}")
        straights = [s for s, _, _ in lap] + [closing_m]
        turns = [(math.radians(th), rho) for _, th, rho in lap]
        self.ramp_m = ramp_m
        self._set_pieces(straights, turns)
        # resize two straights so that the lap closes: their headings are fixed, so the gap is
        # linear in their lengths
        gap = self._end_point()
        i, j = adjust
        u = np.array([[math.cos(self._psi0[2 * k]), math.sin(self._psi0[2 * k])] for k in (i, j)]).T
        dl = np.linalg.solve(u, -gap)
        straights[i] += float(dl[0])
        straights[j] += float(dl[1])
        if min(straights) <= 0.0:
            raise ValueError(f"RoadLoop: the lap does not close with positive straights: {straights}")
        self.straights_m = tuple(straights)
        self._set_pieces(straights, turns)
        self.length_m = float(self._s0[-1] + self._len[-1])
        # the layout frame: origin at the centre of the path's bounding box
        pts = self._xy(np.linspace(0.0, self.length_m, 4000, endpoint=False))
        self._centre = 0.5 * (pts.min(0) + pts.max(0))
        self._nodes_xy -= self._centre
        s0 = self.start_m % self.length_m
        xy0 = self._xy(np.array([s0]))[0]
        psi0 = float(self._psi_kappa(np.array([s0]))[0][0])
        self.T_yard_world0 = se3(euler_to_R(np.array([0.0, 0.0, psi0])), np.array([xy0[0], xy0[1], 0.0]))
        self.T_world_yard = se3_inverse(self.T_yard_world0)

    def _set_pieces(self, straights: list[float], turns: list[tuple[float, float]]) -> None:
        """Pieces (straight, turn, ..., straight) with their start arc length and heading, and the
        position nodes (starting at the origin, heading +x)."""
        length, kappa, ramp = [], [], []
        for k, (theta, rho) in enumerate(turns):
            length += [straights[k], abs(theta) * rho + self.ramp_m]
            kappa += [0.0, math.copysign(1.0 / rho, theta)]
            ramp += [1.0, self.ramp_m]  # a straight's ramp is unused (κ = 0)
        length.append(straights[-1])
        kappa.append(0.0)
        ramp.append(1.0)
        self._len = np.array(length)
        self._kappa = np.array(kappa)
        self._ramp = np.array(ramp)
        self._s0 = np.concatenate([[0.0], np.cumsum(self._len)[:-1]])
        turned = self._kappa * (self._len - self._ramp)
        self._psi0 = np.concatenate([[0.0], np.cumsum(turned)[:-1]])
        total = float(self._s0[-1] + self._len[-1])
        n = math.ceil(total / _NODE_M)
        self._node_s = np.linspace(0.0, total, n + 1)
        a, b = self._node_s[:-1], self._node_s[1:]
        steps = self._integral(a, b)
        self._nodes_xy = np.concatenate([np.zeros((1, 2)), np.cumsum(steps, axis=0)])

    def _psi_kappa(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Heading [rad] and curvature [1/m] at arc lengths ``s`` (within one lap)."""
        i = np.clip(np.searchsorted(self._s0, s, side="right") - 1, 0, len(self._s0) - 1)
        r, R = _ramps(s - self._s0[i], self._len[i], self._ramp[i])
        return self._psi0[i] + self._kappa[i] * R, self._kappa[i] * r

    def _integral(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """∫ₐᵇ (cos ψ, sin ψ) ds for each pair (a, b) (N,), by Gauss–Legendre: (N, 2)."""
        half = 0.5 * (b - a)
        s = 0.5 * (a + b)[:, None] + half[:, None] * _GL_X[None, :]
        psi = self._psi_kappa(s)[0]
        return np.stack([(np.cos(psi) @ _GL_W) * half, (np.sin(psi) @ _GL_W) * half], axis=1)

    def _end_point(self) -> np.ndarray:
        return self._nodes_xy[-1].copy()

    def _xy(self, s: np.ndarray) -> np.ndarray:
        """(N, 2) positions [m] at arc lengths ``s`` (N,) within one lap."""
        i = np.clip(np.floor(s / _NODE_M).astype(int), 0, len(self._node_s) - 2)
        return self._nodes_xy[i] + self._integral(self._node_s[i], s)

    def path_points_yard(self, n: int = 720) -> np.ndarray:
        """(n, 2) [m] points evenly spaced along the lap (layout frame)."""
        return self._xy(np.linspace(0.0, self.length_m, n, endpoint=False))

    def turns(self) -> list[tuple[float, float, float]]:
        """The lap's turns: (start, end) [m] of arc length from the lap's start and angle [rad]."""
        return [
            (float(s0), float(s0 + ln), float(k * (ln - r)))
            for s0, ln, k, r in zip(self._s0, self._len, self._kappa, self._ramp, strict=True)
            if k != 0.0
        ]

    def state(self, t_s: float) -> TruthState:
        """Truth at ``t_s`` seconds after the start (t ≥ 0)."""
        driven = self.arc_length(t_s)
        s = np.array([(self.start_m + driven) % self.length_m])
        psi, kappa = self._psi_kappa(s)
        xy = self._xy(s)[0]
        v = self.speed_at(t_s)
        return rover_truth(
            self.T_world_yard,
            (float(xy[0]), float(xy[1])),
            float(psi[0]),
            v,
            float(kappa[0]) * v,
            self.tilt_rad,
            driven,
        )


# --------------------------------------------------------------------------------------------
# Textures of open country


def texture_field(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """Grass and dirt seen from above: mottled noise, tufts and stones. No octave is coarser than
    1 m (48 texels of 2 cm), so tiles that meet show little step in brightness."""
    base = value_noise(rng, h, w, (48, 16, 6, 3, 2), gamma=0.5)
    img = _u8(0.22 + 0.5 * base)
    area = h * w
    n = area // 1800  # stones
    cx, cy = rng.integers(0, w, n), rng.integers(0, h, n)
    rx = rng.uniform(2, 7, n)
    ry = rx * rng.uniform(0.4, 1.0, n)
    ang = rng.uniform(0, 180, n)
    grey = rng.integers(20, 235, n)
    for i in range(n):
        cv2.ellipse(img, (int(cx[i]), int(cy[i])), (int(rx[i]), int(ry[i])), float(ang[i]), 0, 360, int(grey[i]), -1)
    n = area // 2500  # tufts: short strokes
    x0, y0 = rng.integers(0, w, n), rng.integers(0, h, n)
    dx, dy = rng.integers(-9, 10, n), rng.integers(-9, 10, n)
    grey = rng.integers(10, 200, n)
    for i in range(n):
        cv2.line(img, (int(x0[i]), int(y0[i])), (int(x0[i] + dx[i]), int(y0[i] + dy[i])), int(grey[i]), 1)
    return img


def _u8(x: np.ndarray) -> np.ndarray:
    return np.clip(x * 255.0, 0, 255).astype(np.uint8)


def texture_foliage(
    rng: np.random.Generator,
    h: int,
    w: int,
    texel_m: float,
    crown_m: tuple[float, float] = (2.0, 5.0),
    trunks: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """A screen of trees (h, w) at ``texel_m`` [m]: dark clumpy leaves (over trunks in the lowest
    1–2 m, if ``trunks``), and its coverage: crowns of ``crown_m`` radius [m] whose tops outline
    the upper fifth or so of the panel (below them it is solid)."""
    leaves = value_noise(rng, h, w, (32, 10, 4, 2), gamma=0.6)
    lit = value_noise(rng, h, w, (8, 3), gamma=0.9)
    img = 20.0 + 80.0 * leaves**1.5 + 55.0 * (lit > 0.62) * (leaves > 0.4)
    # trunks in the lowest 1–2 m
    trunk_h = max(1, round(float(rng.uniform(1.0, 2.0)) / texel_m))
    if trunks and trunk_h < h:
        xs = np.arange(w)
        is_trunk = np.zeros(w, bool)
        for cx in rng.uniform(0, w, max(1, round(w * texel_m / 2.5))):
            is_trunk |= np.abs(xs - cx) < max(1.0, 0.15 / texel_m)
        low = img[h - trunk_h :]
        low[:, ~is_trunk] = 0.5 * low[:, ~is_trunk] + 40.0
        low[:, is_trunk] = 30.0
    img_u8 = np.clip(img, 0, 255).astype(np.uint8)
    # crown outline: the union of discs along the top
    cols = np.arange(w, dtype=float)
    top = np.full(w, float(h))
    x = -crown_m[0] / texel_m
    while x < w + crown_m[0] / texel_m:
        r = float(rng.uniform(*crown_m)) / texel_m
        cy = float(rng.uniform(0.0, 0.2 * h)) + r
        inside = np.abs(cols - x) < r
        top[inside] = np.minimum(top[inside], cy - np.sqrt(r * r - (cols[inside] - x) ** 2))
        x += r * float(rng.uniform(0.8, 1.5))
    rows = np.arange(h, dtype=float)[:, None]
    alpha = np.where(rows >= top[None, :], 255, 0).astype(np.uint8)
    return img_u8, alpha


def texture_hills(rng: np.random.Generator, h: int, w: int, ridge: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Far hills (h, w), hazy and low in contrast, with darker woods; covered below ``ridge``
    (w,) [rows from the top]."""
    base = value_noise(rng, h, w, (128, 32, 8, 3), gamma=0.8)
    woods = value_noise(rng, h, w, (64, 16), gamma=1.0) > 0.62
    img = 105.0 + 45.0 * base - 35.0 * woods
    rows = np.arange(h, dtype=float)[:, None]
    alpha = np.where(rows >= ridge[None, :], 255, 0).astype(np.uint8)
    return np.clip(img, 0, 255).astype(np.uint8), alpha


def texture_rock(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """A rock face: grainy noise with cracks."""
    img = _u8(0.25 + 0.5 * value_noise(rng, h, w, (64, 16, 4, 2), gamma=0.7))
    for _ in range(max(2, h * w // 4000)):
        p = rng.integers(0, (w, h), 2)
        q = p + rng.integers(-40, 41, 2)
        cv2.line(img, (int(p[0]), int(p[1])), (int(q[0]), int(q[1])), int(rng.integers(0, 60)), 1, cv2.LINE_AA)
    return img


def texture_post(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """A road-side post: light, with a dark band and a reflector near the top, weathered."""
    img = _u8(0.7 + 0.15 * (value_noise(rng, h, w, (16, 4, 2)) - 0.5))
    band = int(0.12 * h)
    img[band : 2 * band] = 40
    img[int(1.2 * band) : int(1.6 * band), w // 4 : 3 * w // 4] = 230
    return img


# --------------------------------------------------------------------------------------------
# The layout


def _box(
    name: str,
    c: np.ndarray,
    yaw: float,
    size: tuple[float, float, float],
    h: float,
    tex: tuple[np.ndarray, np.ndarray | None] | Sequence[tuple[np.ndarray, np.ndarray | None]],
    top: np.ndarray | None = None,
) -> list[Surface]:
    """The four sides of a box standing on the ground (z = h) in the layout frame, centre ``c``
    (2,) [m], wearing ``tex`` (one (texture, alpha) for all sides, or one per side), and the top
    wearing ``top`` if given."""
    lx, ly, lz = size
    R = euler_to_R(np.array([0.0, 0.0, yaw]))
    ex, ey = R[:, 0] * lx, R[:, 1] * ly
    up = np.array([0.0, 0.0, -lz])
    base = np.array([c[0], c[1], h]) - 0.5 * ex - 0.5 * ey
    faces = [
        (base + up, ex, -R[:, 1]),
        (base + up + ey, ex, R[:, 1]),
        (base + up, ey, -R[:, 0]),
        (base + up + ex, ey, R[:, 0]),
    ]
    out = []
    for i, (corner, a, outward) in enumerate(faces):
        img, alpha = tex if isinstance(tex, tuple) else tex[i]
        out.append(make_surface(f"{name}.{i}", corner, a, -up, outward, img, alpha))
    if top is not None:
        out.append(make_surface(f"{name}.top", base + up, ex, ey, np.array([0.0, 0.0, -1.0]), top))
    return out


def _ring(
    name: str,
    centre: np.ndarray,
    radius: float,
    n: int,
    h: float,
    heights: np.ndarray,
    textures: list[tuple[np.ndarray, np.ndarray]],
) -> list[Surface]:
    """``n`` vertical panels on a circle (a regular polygon), facing its centre, standing on the
    ground, panel i ``heights[i]`` [m] tall."""
    ang = np.linspace(0.0, 2.0 * np.pi, n + 1)
    pts = centre[None, :] + radius * np.stack([np.cos(ang), np.sin(ang)], 1)
    out = []
    for i in range(n):
        p0, p1 = np.array([*pts[i], h]), np.array([*pts[i + 1], h])
        up = np.array([0.0, 0.0, -heights[i]])
        inward = np.array([*(centre - 0.5 * (pts[i] + pts[i + 1])), 0.0])
        img, alpha = textures[i]
        out.append(make_surface(f"{name}{i}", p0 + up, p1 - p0, -up, inward, img, alpha))
    return out


def _dist_to_path(path: np.ndarray, c: np.ndarray) -> float:
    return float(np.min(np.linalg.norm(path - c, axis=1)))


TILE_M = 40.0  # ground tile [m]
GROUND_TEXEL_M = 0.02
TREE_CLEAR_M = 30.0  # stands of trees at least this far from the path [m]
TREELINE_MARGIN_M = 45.0  # the treeline ring beyond the path's farthest point from the centre [m]
HILLS_RADIUS_M = 650.0


@functools.lru_cache(maxsize=2)
def terrain_surfaces(seed: int) -> tuple[tuple[Surface, ...], float, tuple[float, float]]:
    """Surfaces of the open terrain in the layout frame, the camera height [m] and the size of
    the area inside the treeline (x, y) [m]. Deterministic for ``seed``."""
    h = CAM_HEIGHT_M
    loop = RoadLoop()
    path = loop.path_points_yard(3000)  # every 0.25 m
    centre = np.zeros(2)
    r_path = float(np.max(np.linalg.norm(path - centre, axis=1)))
    r_tree = r_path + TREELINE_MARGIN_M
    surfaces: list[Surface] = []
    down = np.array([0.0, 0.0, -1.0])

    # ground: tiles inside the treeline, three textures, each tile turned by k · 90°
    rng = np.random.default_rng([seed, 201])
    n_tex = round(TILE_M / GROUND_TEXEL_M)
    field = [texture_field(rng, n_tex, n_tex) for _ in range(3)]
    n_tiles = math.ceil(r_tree / TILE_M)
    look: dict[tuple[int, int], tuple[int, int]] = {}  # tile -> (texture, quarter turns)
    for ix in range(-n_tiles, n_tiles):
        for iy in range(-n_tiles, n_tiles):
            lo = np.array([ix, iy]) * TILE_M
            nearest = np.clip(centre, lo, lo + TILE_M)
            if np.linalg.norm(nearest - centre) > r_tree + 1.0:
                continue
            # never the same texture the same way round as a neighbour already laid
            taken = {
                look.get((ix - 1, iy)),
                look.get((ix, iy - 1)),
                look.get((ix - 1, iy - 1)),
                look.get((ix + 1, iy - 1)),
            }
            while (choice := (int(rng.integers(0, 3)), int(rng.integers(0, 4)))) in taken:
                pass
            look[ix, iy] = choice
            tex, k = field[choice[0]], choice[1]
            e = [np.array([TILE_M, 0.0, 0.0]), np.array([0.0, TILE_M, 0.0])]
            a, b = (e[0], e[1]) if k % 2 == 0 else (e[1], e[0])
            corner = np.array([lo[0], lo[1], h])
            if k >= 2:  # the other two turns: start from the opposite corner
                corner, a, b = corner + a + b, -a, -b
            surfaces.append(make_surface(f"ground{ix},{iy}", corner, a, b, down, tex, lod_nearest=True))

    # the far band: the treeline ring, hills beyond, stands of trees in between
    rng = np.random.default_rng([seed, 202])
    n_ring = math.ceil(2 * np.pi * r_tree / 40.0)
    ring_h = rng.uniform(12.0, 20.0, n_ring)
    tl_texel = 0.1
    chord = 2 * r_tree * math.sin(np.pi / n_ring)
    ring_tex = [texture_foliage(rng, round(float(z) / tl_texel), round(chord / tl_texel), tl_texel) for z in ring_h]
    surfaces += _ring("treeline", centre, r_tree, n_ring, h, ring_h, ring_tex)
    n_hill = 24
    hill_texel = 0.5
    chord = 2 * HILLS_RADIUS_M * math.sin(np.pi / n_hill)
    cols = round(chord / hill_texel)
    # one ridge line round the whole ring [m above the ground], smooth, 40–110 m
    ridge = value_noise(rng, 1, n_hill * cols, (cols * 2, cols // 2, cols // 8), gamma=1.0)[0]
    ridge = 40.0 + 70.0 * ridge
    hill_tex, hill_h = [], np.zeros(n_hill)
    for i in range(n_hill):
        ri = ridge[i * cols : (i + 1) * cols]
        hill_h[i] = float(ri.max()) + 2.0
        rows = round(hill_h[i] / hill_texel)
        hill_tex.append(texture_hills(rng, rows, cols, (hill_h[i] - ri) / hill_texel))
    surfaces += _ring("hills", centre, HILLS_RADIUS_M, n_hill, h, hill_h, hill_tex)
    placed: list[tuple[float, float, float]] = []
    st_texel = 0.08
    tries = 0
    while len(placed) < 45 and tries < 5000:
        tries += 1
        size = (float(rng.uniform(8.0, 30.0)), float(rng.uniform(8.0, 30.0)), float(rng.uniform(8.0, 18.0)))
        radius = 0.5 * math.hypot(size[0], size[1])
        c = rng.uniform(-r_tree, r_tree, 2)
        if np.linalg.norm(c - centre) + radius > r_tree - 5.0:
            continue
        if _dist_to_path(path, c) < TREE_CLEAR_M + radius:
            continue
        if any(math.hypot(c[0] - q[0], c[1] - q[1]) < radius + q[2] + 5.0 for q in placed):
            continue
        placed.append((float(c[0]), float(c[1]), radius))
        rows = round(size[2] / st_texel)
        sides = [texture_foliage(rng, rows, round(size[i // 2] / st_texel), st_texel) for i in range(4)]
        surfaces += _box(f"trees{len(placed)}", c, float(rng.uniform(0, np.pi)), size, h, sides)

    # sparse near objects along the path: posts, rocks, bushes, one per 10–25 m
    rng = np.random.default_rng([seed, 203])
    s = float(rng.uniform(5.0, 15.0))
    k = 0
    while s < loop.length_m:
        kind = int(rng.choice(3, p=(0.35, 0.35, 0.3)))
        side = float(rng.choice((-1.0, 1.0)))
        i = int(s / loop.length_m * len(path)) % len(path)
        p = path[i]
        t = path[(i + 1) % len(path)] - path[i - 1]
        t /= np.linalg.norm(t)
        nrm = np.array([-t[1], t[0]]) * side
        if kind == 0:
            size = (0.12, 0.12, float(rng.uniform(1.0, 1.3)))
            off = float(rng.uniform(3.0, 5.0))
        elif kind == 1:
            g = float(rng.uniform(0.3, 1.5))
            size = (
                g * float(rng.uniform(0.7, 1.3)),
                g * float(rng.uniform(0.7, 1.3)),
                g * float(rng.uniform(0.5, 0.9)),
            )
            off = float(rng.uniform(3.0, 12.0))
        else:
            g = float(rng.uniform(1.0, 3.0))
            size = (g * float(rng.uniform(0.7, 1.3)), g * float(rng.uniform(0.7, 1.3)), float(rng.uniform(0.8, 2.0)))
            off = float(rng.uniform(4.0, 20.0))
        radius = 0.5 * math.hypot(size[0], size[1])
        c = p + nrm * (off + radius)
        s += float(rng.uniform(10.0, 25.0))
        if _dist_to_path(path, c) < 2.5 + radius:  # across a curve, another part of the path is near
            continue
        k += 1
        yaw = float(rng.uniform(0, np.pi))
        if kind == 0:
            tex = texture_post(rng, round(size[2] / 0.01), round(size[0] / 0.01))
            surfaces += _box(f"post{k}", c, yaw, size, h, (tex, None))
        elif kind == 1:
            faces: list[tuple[np.ndarray, np.ndarray | None]] = [
                (texture_rock(rng, round(size[2] / 0.01), round(size[j // 2] / 0.01)), None) for j in range(4)
            ]
            top = texture_rock(rng, round(size[1] / 0.01), round(size[0] / 0.01))
            surfaces += _box(f"rock{k}", c, yaw, size, h, faces, top)
        else:
            bush = [
                texture_foliage(rng, round(size[2] / 0.02), round(size[j // 2] / 0.02), 0.02, (0.3, 0.8), False)
                for j in range(4)
            ]
            surfaces += _box(f"bush{k}", c, yaw, size, h, bush)
    return tuple(surfaces), h, (2 * r_tree, 2 * r_tree)
