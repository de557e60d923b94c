"""The simulated rover's world: textured planar surfaces (a walled yard with boxes and posts) and
the rover's trajectory through it, with its exact velocities for the odometry. The building blocks
(surfaces, value noise, a rover's truth) are in drivers/simbase.py; the open-terrain world in
drivers/simterrain.py, which :func:`build_world` builds as it builds the yard's.

Frames (``robotd.core.geometry``): the world ``W`` is the robot frame at t = 0 (FRD: x forward,
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
from typing import Protocol

import cv2
import numpy as np

from drivers.simbase import (
    Surface,
    TruthState,
    VaryingSpeed,
    make_surface,
    rover_truth,
    transformed,
    value_noise,
)
from drivers.simterrain import BASELINE_M, RoadLoop, terrain_surfaces
from robotd.core.errors import DriverError
from robotd.core.geometry import euler_rate_matrix, euler_to_R, se3, se3_inverse

# --------------------------------------------------------------------------------------------
# Procedural textures of the yard (value noise: drivers/simbase.py)


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


def texture_plain(rng: np.random.Generator, h: int, w: int, grey: float, amplitude: float) -> np.ndarray:
    """A blank surface (bare concrete, painted plaster): ``grey`` ± ``amplitude`` grey levels of
    very smooth noise (cells of 256 and 512 texels, over a metre), no edges or corners to find."""
    return np.clip(grey + 2.0 * amplitude * (value_noise(rng, h, w, (512, 256)) - 0.5), 0, 255).astype(np.uint8)


# --------------------------------------------------------------------------------------------
# Trajectories: a smooth closed loop on the ground, or straight legs joined by turns in place


class Trajectory(Protocol):
    """What the drivers and the world builder need of a trajectory."""

    T_world_yard: np.ndarray  # (4, 4): the yard frame in the world frame (the robot at t = 0)

    def state(self, t_s: float) -> TruthState: ...

    def path_points_yard(self, n: int = 720) -> np.ndarray: ...


class LoopTrajectory(VaryingSpeed):
    """The rover drives a peanut-shaped loop (about 28.5 m) at a gently varying speed.

    Path in the yard frame: x(φ) = A r(φ) cos φ, y(φ) = B r(φ) sin φ, r = 1 + e cos 2φ; the rover
    moves along it with arc-length speed v(t) = speed (1 + ε sin(2π t / T_v)), heading along the
    tangent (no slip), so body velocity is (v, 0, 0) and yaw rate is κ v with κ the signed
    curvature (x′y″ − y′x″)/|p′|³ (positive = right turn in FRD). ``tilt_deg`` adds a gentle
    terrain-like rocking: roll and pitch of that amplitude varying along the path; body rates then
    come from the Euler rates through E⁻¹ (docs/math.md §6.3). ``start_m`` is where on the loop
    the rover is at t = 0 (arc length from φ = 0, the tip at +x, heading +y).
    """

    def __init__(
        self,
        speed_mps: float = 1.0,
        tilt_deg: float = 0.0,
        size: tuple[float, float] = (4.5, 3.5),
        eps: float = 0.15,
        start_m: float = 0.0,
    ) -> None:
        self.A, self.B = size
        self.e = 0.3  # waist of the peanut: the curvature changes sign twice per lap, min radius 1.8 m
        self.speed = speed_mps
        self.eps = eps
        self.T_v = 11.0  # [s] period of the speed variation
        self.tilt_rad = math.radians(tilt_deg)
        self.start_m = float(start_m)
        phi = np.linspace(0.0, 2.0 * np.pi, 20001)
        dp = np.hypot(*self._d1(phi))
        # arc length by the trapezoid rule on a fine grid; φ(s) by interpolation
        self._s_tab = np.concatenate([[0.0], np.cumsum(0.5 * (dp[1:] + dp[:-1]) * np.diff(phi))])
        self._phi_tab = phi
        self.length_m = float(self._s_tab[-1])
        phi0 = np.array(np.interp(self.start_m % self.length_m, self._s_tab, self._phi_tab))
        x0, y0 = self._p(phi0)
        psi0 = float(np.arctan2(*self._d1(phi0)[::-1]))
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

    def point_at(self, s_m: float) -> np.ndarray:
        """(2,) [m]: the point of the loop at arc length ``s_m`` (yard frame)."""
        x, y = self._p(np.array(np.interp(s_m % self.length_m, self._s_tab, self._phi_tab)))
        return np.array([float(x), float(y)])

    def state(self, t_s: float) -> TruthState:
        """Truth at ``t_s`` seconds after the start (t ≥ 0)."""
        driven = self.arc_length(t_s)
        v = self.speed_at(t_s)
        phi = np.array(np.interp((self.start_m + driven) % self.length_m, self._s_tab, self._phi_tab))
        x, y = self._p(phi)
        dx, dy = self._d1(phi)
        ddx, ddy = self._d2(phi)
        yaw = float(np.arctan2(dy, dx))
        kappa = float((dx * ddy - dy * ddx) / (dx * dx + dy * dy) ** 1.5)
        return rover_truth(self.T_world_yard, (float(x), float(y)), yaw, v, kappa * v, self.tilt_rad, driven)


def _ramp(u: float, T: float, Tr: float) -> tuple[float, float]:
    """A smooth unit pulse of length ``T`` with sin² ramps of ``Tr`` at both ends (T ≥ 2 Tr): its
    value r(u) ∈ [0, 1] and its integral R(u) = ∫₀ᵘ r, in closed form (R(T) = T − Tr)."""
    u = min(max(u, 0.0), T)

    def head(x: float) -> float:  # ∫₀ˣ sin²(π y / 2Tr) dy
        return 0.5 * x - Tr / (2.0 * np.pi) * math.sin(np.pi * x / Tr)

    if u < Tr:
        return math.sin(0.5 * np.pi * u / Tr) ** 2, head(u)
    if u > T - Tr:
        w = T - u
        return math.sin(0.5 * np.pi * w / Tr) ** 2, (T - Tr) - head(w)
    return 1.0, 0.5 * Tr + (u - Tr)


class StoppingTrajectory:
    """Another trajectory with a stop: the rover brakes (sin² ramp of ``ramp_s``) to stand still
    from ``at_s`` for ``stop_s`` seconds, then drives on where it stopped. Time is warped,
    τ(t) = t − ∫ r, r the stop's smooth unit pulse, so the pose is the base trajectory's at τ and
    every velocity and rate is the base's times dτ/dt = 1 − r: one path, with a pause in it."""

    def __init__(self, base: Trajectory, at_s: float, stop_s: float, ramp_s: float = 0.5) -> None:
        self.base = base
        self.at_s = float(at_s)
        self.stop_s = float(stop_s)
        self.ramp_s = float(ramp_s)
        self.T_world_yard = base.T_world_yard

    def warp(self, t_s: float) -> tuple[float, float]:
        """(τ, dτ/dt) at ``t_s``."""
        T = self.stop_s + 2.0 * self.ramp_s
        r, R = _ramp(t_s - self.at_s, T, self.ramp_s)
        if t_s <= self.at_s:
            return t_s, 1.0
        return t_s - R, 1.0 - r

    def state(self, t_s: float) -> TruthState:
        tau, k = self.warp(t_s)
        st = self.base.state(tau)
        return TruthState(st.T_world_robot, st.vel_R_mps * k, st.rate_R_radps * k)

    def path_points_yard(self, n: int = 720) -> np.ndarray:
        return self.base.path_points_yard(n)


class ShakingTrajectory:
    """Another trajectory carried by a shaking hand: the camera turns about every axis by a sum
    of three sinusoids (1.7, 3.9 and 7.3 Hz, phases drawn from the seed, amplitudes 1/2, 1/3 and
    1/6 of ``amp_deg`` so the peak is about ``amp_deg``) and moves by ``amp_deg`` × 5 mm a degree
    along every axis at the same frequencies. The shake is a pose in the base robot frame,
    ΔT(t) = (R_s, p_s), zero at t = 0 (the world stays the robot at t = 0), so
    T = T_base · ΔT; the body rate is R_sᵀ ω_base + ω_s and the body velocity
    R_sᵀ (v_base + ω_base × p_s + ṗ_s). At 5° the rate peaks at 100–120 °/s: a hand-held
    camera shaken hard (issue 26's held-out sequence D). ``until_s`` > 0: the shake fades out
    (cos², over ``ramp_s``) and ends then, the camera held where the fade left it."""

    FREQ_HZ = (1.7, 3.9, 7.3)
    WEIGHT = (1.0 / 2.0, 1.0 / 3.0, 1.0 / 6.0)
    M_PER_DEG = 0.005

    def __init__(self, base: Trajectory, amp_deg: float, seed: int, until_s: float = 0.0, ramp_s: float = 0.5) -> None:
        self.base = base
        self.until_s = float(until_s)
        self.ramp_s = float(ramp_s)
        self.T_world_yard = base.T_world_yard
        rng = np.random.default_rng([seed, 314])
        self._phase = rng.uniform(0.0, 2.0 * np.pi, size=(6, 3))  # (axis: roll pitch yaw x y z, freq)
        a = math.radians(amp_deg) * np.asarray(self.WEIGHT)
        self._amp = np.vstack([np.tile(a, (3, 1)), np.tile(amp_deg * self.M_PER_DEG * np.asarray(self.WEIGHT), (3, 1))])
        self._w = 2.0 * np.pi * np.asarray(self.FREQ_HZ)

    def shake(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """(6,) the shake (roll, pitch, yaw [rad], x, y, z [m]) at ``t_s`` and its time derivative."""
        arg = self._w[None, :] * t_s + self._phase
        q = np.sum(self._amp * (np.sin(arg) - np.sin(self._phase)), axis=1)
        dq = np.sum(self._amp * self._w[None, :] * np.cos(arg), axis=1)
        if self.until_s > 0.0:  # the hand steadies: a cos² fade over the last ramp_s
            u = (t_s - (self.until_s - self.ramp_s)) / self.ramp_s
            if u >= 1.0:
                return np.zeros(6), np.zeros(6)
            if u > 0.0:
                e = math.cos(0.5 * np.pi * u) ** 2
                de = -0.5 * np.pi * math.sin(np.pi * u) / self.ramp_s
                return e * q, e * dq + de * q
        return q, dq

    def state(self, t_s: float) -> TruthState:
        st = self.base.state(t_s)
        q, dq = self.shake(t_s)
        R_s = euler_to_R(q[:3])
        w_s = np.linalg.solve(euler_rate_matrix(q[:3]), dq[:3])
        T = st.T_world_robot @ se3(R_s, q[3:])
        rate = R_s.T @ st.rate_R_radps + w_s
        vel = R_s.T @ (st.vel_R_mps + np.cross(st.rate_R_radps, q[3:]) + dq[3:])
        return TruthState(T, vel, rate)

    def path_points_yard(self, n: int = 720) -> np.ndarray:
        return self.base.path_points_yard(n)


@dataclass(frozen=True, slots=True)
class _Leg:
    """One leg of a :class:`TurnInPlaceTrajectory`, in the unit time of speed 1."""

    turn: bool
    tau0: float  # [s] start
    T: float  # [s] duration
    Tr: float  # [s] ramp
    peak: float  # [m/s] or [rad/s]
    xy: tuple[float, float]  # [m] start position (yard)
    yaw0: float  # [rad] start heading
    dist0: float  # [m] distance driven in the lap before this leg


class TurnInPlaceTrajectory:
    """Straight legs joined by sharp turns in place, round a parallelogram (6 × 3 m).

    The rover drives a leg at up to ``v_max`` (sin² ramps of 1 s to and from a stop), stops, yaws
    right on the spot (about the robot origin) by 98° or 82° alternately, at up to 90 °/s (sin²
    ramps of 0.3 s: a 98° turn takes 1.39 s at 70 °/s on average), and drives on. ``speed_mps``
    scales time: the straights peak at that speed and the turns at 90 °/s × speed, and 0 parks the
    rover. Tilt rocks the rover with the distance driven (not while it turns on the spot). At
    t = 0 the rover is ``start_s`` (unit time) into the first long leg, 1 s before it brakes for
    the first turn.
    """

    def __init__(
        self,
        speed_mps: float = 1.0,
        tilt_deg: float = 0.0,
        sides_m: tuple[float, float] = (6.0, 3.0),
        turns_deg: tuple[float, float] = (98.0, 82.0),
        rate_max_degps: float = 90.0,
        start_s: float = 5.0,
    ) -> None:
        self.speed = speed_mps
        self.tilt_rad = math.radians(tilt_deg)
        self.rate_max_radps = math.radians(rate_max_degps)
        v_max, ramp_v, ramp_w = 1.0, 1.0, 0.3
        legs: list[_Leg] = []
        xy = np.zeros(2)
        yaw = tau = dist = 0.0
        for i in range(4):
            length, turn = sides_m[i % 2], math.radians(turns_deg[i % 2])
            T = length / v_max + ramp_v
            legs.append(_Leg(False, tau, T, ramp_v, v_max, (float(xy[0]), float(xy[1])), yaw, dist))
            tau, dist = tau + T, dist + length
            xy = xy + length * np.array([math.cos(yaw), math.sin(yaw)])
            T = turn / self.rate_max_radps + ramp_w
            legs.append(_Leg(True, tau, T, ramp_w, self.rate_max_radps, (float(xy[0]), float(xy[1])), yaw, dist))
            tau, yaw = tau + T, yaw + turn
        # centre the parallelogram on the yard origin
        corners = np.array([leg.xy for leg in legs if not leg.turn])
        c = 0.5 * (corners.min(0) + corners.max(0))
        self._legs = [
            _Leg(g.turn, g.tau0, g.T, g.Tr, g.peak, (g.xy[0] - c[0], g.xy[1] - c[1]), g.yaw0, g.dist0) for g in legs
        ]
        self._corners = corners - c
        self._tau0s = np.array([g.tau0 for g in self._legs])
        self.period_s = tau  # unit time of one lap
        self.length_m = dist
        self.start_s = start_s
        xy0, yaw0, _, _, self._dist_start = self._unit(start_s)
        self.T_yard_world0 = se3(euler_to_R(np.array([0.0, 0.0, yaw0])), np.array([xy0[0], xy0[1], 0.0]))
        self.T_world_yard = se3_inverse(self.T_yard_world0)

    def _unit(self, tau: float) -> tuple[tuple[float, float], float, float, float, float]:
        """At unit time ``tau``: position, heading, forward speed and yaw rate at speed 1, and the
        distance driven since tau = 0."""
        lap, tc = divmod(tau, self.period_s)
        g = self._legs[int(np.searchsorted(self._tau0s, tc, side="right")) - 1]
        r, R = _ramp(tc - g.tau0, g.T, g.Tr)
        if g.turn:
            return g.xy, g.yaw0 + g.peak * R, 0.0, g.peak * r, lap * self.length_m + g.dist0
        d = g.peak * R
        xy = (g.xy[0] + d * math.cos(g.yaw0), g.xy[1] + d * math.sin(g.yaw0))
        return xy, g.yaw0, g.peak * r, 0.0, lap * self.length_m + g.dist0 + d

    def path_points_yard(self, n: int = 720) -> np.ndarray:
        """(n, 2) [m] points on the parallelogram's sides (yard frame)."""
        a = np.linspace(0.0, 4.0, n, endpoint=False)
        i = a.astype(int)
        f = (a - i)[:, None]
        return self._corners[i] * (1 - f) + self._corners[(i + 1) % 4] * f

    def turn_windows(self, t_end_s: float) -> list[tuple[float, float, float]]:
        """The turns that start before ``t_end_s``: (start [s], end [s], angle [rad]) on the clock."""
        if self.speed <= 0.0:
            return []
        out: list[tuple[float, float, float]] = []
        lap = 0
        while True:
            for g in self._legs:
                if not g.turn:
                    continue
                t0 = (lap * self.period_s + g.tau0 - self.start_s) / self.speed
                if t0 >= t_end_s:
                    return out
                if t0 + g.T / self.speed > 0:
                    out.append((t0, t0 + g.T / self.speed, g.peak * (g.T - g.Tr)))
            lap += 1

    def state(self, t_s: float) -> TruthState:
        """Truth at ``t_s`` seconds after the start (t ≥ 0)."""
        xy, yaw, v, w, dist = self._unit(self.start_s + self.speed * t_s)
        return rover_truth(
            self.T_world_yard, xy, yaw, self.speed * v, self.speed * w, self.tilt_rad, dist - self._dist_start
        )


# --------------------------------------------------------------------------------------------
# Moving objects


class LaneCrossing:
    """Where the moving box of ``moving_box`` is: it drives across the loop on a lane at yard
    x = ``lane_x`` (along y), from a parking spot outside one lobe to the one outside the other,
    timed on the rover's own schedule. The rover meets the lane twice a lap, once on each lobe;
    each time the box comes from the spot beyond the other lobe, across the loop's middle, and
    crosses the rover's path while the rover is ``lead_m`` of path short of the lane: the rover
    sees it enter from the right, pass ahead and leave to the left. Then it waits, parked, for the
    rover's next half lap and drives back. Its speed peaks at ``v_box_mps`` × the rover's speed
    (sin² ramps of ``ramp_s`` / speed); a parked rover (speed 0) keeps it parked.
    """

    def __init__(
        self,
        rover: LoopTrajectory,
        lane_x: float,
        spot_y: float,
        v_box_mps: float = 2.5,
        lead_m: float = 3.0,
        ramp_s: float = 0.8,
    ) -> None:
        self.rover = rover
        self.lane_x = lane_x
        self.spot_y = spot_y
        self.v_box = v_box_mps
        self.lead_m = lead_m
        self.ramp_s = ramp_s
        L = rover.length_m
        # the rover meets the lane at arc length L/4 + j L/2: on the +y lobe for even j
        self._s_lane0, self._half = 0.25 * L, 0.5 * L
        self.path_y = abs(float(rover.point_at(self._s_lane0)[1]))
        self.move_s = 2.0 * spot_y / v_box_mps + ramp_s  # unit time (speed 1) of one move
        # unit time into a move when the box's centre is over the path the rover approaches,
        # R(u) v = spot + path (it crossed the middle first), by bisection: R increases
        lo, hi = 0.0, self.move_s
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if _ramp(mid, self.move_s, ramp_s)[1] * v_box_mps < spot_y + self.path_y else (lo, mid)
        self.u_cross = 0.5 * (lo + hi)
        # the first half lap whose crossing the rover has not passed at t = 0
        self._j0 = math.ceil((rover.start_m + lead_m - self._s_lane0) / self._half)

    def move_start(self, i: int) -> float:
        """Clock time [s] when move ``i`` (0, 1, ...) starts."""
        s = self._s_lane0 + (self._j0 + i) * self._half
        return self.rover.time_at(s - self.lead_m) - self.u_cross / self.rover.speed

    def move_window(self, i: int) -> tuple[float, float]:
        """(start, end) [s] of move ``i`` on the clock."""
        t0 = self.move_start(i)
        return t0, t0 + self.move_s / self.rover.speed

    def _from_y(self, i: int) -> float:
        # even half laps: the rover approaches the +y lobe, so the box comes from the -y spot
        return -self.spot_y if (self._j0 + i) % 2 == 0 else self.spot_y

    def y(self, t_s: float) -> float:
        """The box's centre, yard y [m], at ``t_s``."""
        if self.rover.speed <= 0.0:
            return self._from_y(0)
        # the smallest i with move_start(i) > t, from a guess by the rover's position
        driven = self.rover.start_m + self.rover.arc_length(t_s)
        i = max(0, math.floor((driven + self.lead_m - self._s_lane0) / self._half) - self._j0)
        while i > 0 and self.move_start(i - 1) > t_s:
            i -= 1
        while self.move_start(i) <= t_s:
            i += 1
        if i == 0:
            return self._from_y(0)
        y0 = self._from_y(i - 1)
        _, R = _ramp((t_s - self.move_start(i - 1)) * self.rover.speed, self.move_s, self.ramp_s)
        return y0 - math.copysign(self.v_box * R, y0)

    def pose(self, t_s: float) -> np.ndarray:
        """T_world_box (4, 4) at ``t_s``: the box frame is the yard frame moved to the box."""
        return self.rover.T_world_yard @ se3(np.eye(3), np.array([self.lane_x, self.y(t_s), 0.0]))


class Motion(Protocol):
    """A moving object's schedule: its pose T_world_object (4, 4) at a time on the clock [s]."""

    def pose(self, t_s: float) -> np.ndarray: ...


@dataclass(frozen=True, slots=True, eq=False)
class Mover:
    """A rigid object that moves through the world (another vehicle): its ``surfaces`` in its own
    frame and its ``motion`` (e.g. :class:`LaneCrossing`). Movers are not part of
    ``World.surfaces``, the static scene: whatever takes the world as map truth leaves them out."""

    name: str
    surfaces: tuple[Surface, ...]
    motion: Motion

    def pose(self, t_s: float) -> np.ndarray:
        """T_world_object (4, 4) at ``t_s``."""
        return self.motion.pose(t_s)

    def surfaces_at(self, t_s: float) -> tuple[Surface, ...]:
        T = self.motion.pose(t_s)
        return tuple(transformed(s, T) for s in self.surfaces)


# --------------------------------------------------------------------------------------------
# The yard


@dataclass(frozen=True, slots=True, eq=False)
class World:
    """Surfaces in the world frame, the trajectory, and the layout facts tests and docs use.

    ``surfaces`` is the static scene; ``movers`` (``moving_box``) move on the same clock as the
    trajectory and are rendered with it (:meth:`moving_surfaces`).
    """

    name: str
    seed: int
    surfaces: tuple[Surface, ...]
    trajectory: Trajectory
    cam_height_m: float
    yard_size_m: tuple[float, float]
    movers: tuple[Mover, ...] = ()
    plain_from_x_m: float | None = None  # low_texture: yard x beyond which every surface is blank

    def moving_surfaces(self, t_s: float) -> tuple[Surface, ...]:
        """The movers' surfaces in the world frame at ``t_s`` (empty for a static world)."""
        return tuple(s for m in self.movers for s in m.surfaces_at(t_s))


WORLDS = ("yard", "turn_in_place", "moving_box", "low_texture", "open_terrain")
OAK_D_BASELINE_M = 0.0755


def rig_baseline_m(world: str) -> float:
    """The stereo baseline [m] a world's camera has unless the URL sets one: the OAK-D's, except
    in ``open_terrain``, whose car-mounted rig has 0.9 m, so that at 640×400 a point has the
    disparity it has in KITTI's images (drivers/simterrain.py)."""
    return BASELINE_M if world == "open_terrain" else OAK_D_BASELINE_M


@dataclass(frozen=True, slots=True)
class _Layout:
    """What a world changes in the yard: the walls' margin beyond the path's extent (x, y) [m],
    where the rover is at t = 0 on the loop (arc length [m]), a yard x beyond which every surface
    is blank, and whether the moving box's lane is kept clear of obstacles."""

    margin_m: tuple[float, float] = (2.5, 2.5)
    start_m: float = 0.0
    plain_from_x: float | None = None
    lane: bool = False


_LAYOUTS = {
    "yard": _Layout(),
    "turn_in_place": _Layout(),
    # the box crosses 3 m ahead of the rover at t ≈ 3.4 s (in view 2.3–5.0 s), then every half lap
    "moving_box": _Layout(margin_m=(2.5, 4.0), start_m=0.5, lane=True),
    # the rover starts on the -y lobe heading +x, towards the blank east end
    "low_texture": _Layout(start_m=21.5, plain_from_x=5.5),
}
_LANE_X = 0.0
_BOX_SIZE = (1.4, 2.4, 1.3)  # [m] across the lane (x), along it (y), height: a small van
_BOX_CLEAR_M = 1.25  # parked box's edge to the path's waist [m]
_PLAIN_GREY = {"ground": (95.0, 4.0), "wall": (165.0, 4.0)}  # grey ± amplitude of blank surfaces


def _trajectory(world: str, speed_mps: float, tilt_deg: float) -> Trajectory:
    if world == "open_terrain":
        return RoadLoop(speed_mps=speed_mps, tilt_deg=tilt_deg)
    if world == "turn_in_place":
        return TurnInPlaceTrajectory(speed_mps=speed_mps, tilt_deg=tilt_deg)
    return LoopTrajectory(speed_mps=speed_mps, tilt_deg=tilt_deg, start_m=_LAYOUTS[world].start_m)


def _box_spot_y(path: np.ndarray) -> float:
    """Yard |y| of the moving box's parking spots: clear of the loop's waist at the lane."""
    near = np.abs(path[:, 0] - _LANE_X) <= 0.5 * _BOX_SIZE[0]
    return float(np.abs(path[near, 1]).max()) + _BOX_CLEAR_M + 0.5 * _BOX_SIZE[1]


def build_world(
    seed: int,
    world: str = "yard",
    speed_mps: float = 1.0,
    tilt_deg: float = 0.0,
    stop: tuple[float, float] = (0.0, 0.0),
    shake_deg: float = 0.0,
    shake_s: float = 0.0,
) -> World:
    """The textured yard ``world`` for ``seed`` with the rover driving at ``speed_mps`` (tilt in degrees).
    ``stop``: (at [s], for [s]): the rover stands still for a while (:class:`StoppingTrajectory`;
    (0, 0) or a duration of 0: no stop). ``shake_deg`` > 0: the camera is shaken as by a hand
    (:class:`ShakingTrajectory`), stopped or not, for ``shake_s`` seconds (0: throughout).

    The surfaces and textures (about 12 Mpx, 1–2 s to generate; ``open_terrain``: see
    drivers/simterrain.py) are built once per (seed, world) and cached; speed and tilt only change
    the trajectory (and the moving box's schedule), whose start pose (and so the world frame) does
    not depend on them.
    """
    if world not in WORLDS:
        raise DriverError(f"sim world {world!r}: unknown; known: {', '.join(WORLDS)}")
    traj: Trajectory = _trajectory(world, speed_mps, tilt_deg)
    if world == "open_terrain":
        surfaces, h, size = terrain_surfaces(seed)
    else:
        surfaces, h, size = _yard_surfaces(seed, world)
    T = traj.T_world_yard
    movers: tuple[Mover, ...] = ()
    if world == "moving_box":
        assert isinstance(traj, LoopTrajectory)
        crossing = LaneCrossing(traj, _LANE_X, _box_spot_y(traj.path_points_yard()))
        movers = (Mover("van", _van_surfaces(seed, h), crossing),)
    if stop[1] > 0.0:
        traj = StoppingTrajectory(traj, stop[0], stop[1])
    if shake_deg > 0.0:
        traj = ShakingTrajectory(traj, shake_deg, seed, shake_s)
    return World(
        world,
        seed,
        tuple(transformed(s, T) for s in surfaces),
        traj,
        h,
        size,
        movers,
        _LAYOUTS[world].plain_from_x if world in _LAYOUTS else None,
    )


@functools.lru_cache(maxsize=3)
def _van_surfaces(seed: int, h: float) -> tuple[Surface, ...]:
    """The moving box's faces in its own frame (centred on the origin, standing on the ground)."""
    rng = np.random.default_rng([seed, 102])
    return tuple(_box_surfaces("van", rng, np.zeros(2), 0.0, _BOX_SIZE, h, 0.005))


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


def _split_x(p0: np.ndarray, p1: np.ndarray, x: float | None) -> list[tuple[np.ndarray, np.ndarray, bool]]:
    """The segment p0 → p1 cut where it crosses yard x = ``x``: (start, end, beyond x) pieces."""
    if x is None:
        return [(p0, p1, False)]
    if (p0[0] - x) * (p1[0] - x) >= 0.0:
        return [(p0, p1, bool(0.5 * (p0[0] + p1[0]) > x))]
    m = p0 + (p1 - p0) * ((x - p0[0]) / (p1[0] - p0[0]))
    return [(p0, m, bool(p0[0] > x)), (m, p1, bool(p1[0] > x))]


@functools.lru_cache(maxsize=3)
def _yard_surfaces(seed: int, world: str) -> tuple[tuple[Surface, ...], float, tuple[float, float]]:
    """Surfaces of the yard in the yard frame, camera height h [m], yard size (x, y) [m].

    Layout in the yard frame (``yard``): a loop of about 28.5 m (11.7 × 5.2 m) inside a walled yard
    of about 16.7 × 10.2 m (walls 2.5 m high), boxes and posts scattered at least 0.9 m clear of
    the path; camera height 0.4 m. Textures: 5 mm/texel on walls and boxes, 6 mm on the ground.
    The other worlds change the path the walls enclose (``turn_in_place``), widen the yard and
    keep the moving box's lane clear (``moving_box``), or leave everything east of a line blank
    (``low_texture``): see ``_LAYOUTS``.
    """
    layout = _LAYOUTS[world]
    h = 0.4
    path = _trajectory(world, 1.0, 0.0).path_points_yard()
    ext = np.abs(path).max(0)
    half_x, half_y = float(ext[0]) + layout.margin_m[0], float(ext[1]) + layout.margin_m[1]
    wall_h = 2.5
    g_texel, w_texel, b_texel = 0.006, 0.005, 0.005
    x_plain = layout.plain_from_x
    down = np.array([0.0, 0.0, -1.0])
    surfaces: list[Surface] = []

    rng = np.random.default_rng([seed, 101])
    gx, gy = 2 * half_x, 2 * half_y
    for x0, x1, plain in _split_x(np.array([-half_x, 0.0]), np.array([half_x, 0.0]), x_plain):
        lx = float(x1[0] - x0[0])
        shape = (round(gy / g_texel), round(lx / g_texel))
        tex = texture_plain(rng, *shape, *_PLAIN_GREY["ground"]) if plain else texture_ground(rng, *shape)
        corner = np.array([x0[0], -half_y, h])
        name = "ground.plain" if plain else "ground"
        surfaces.append(make_surface(name, corner, np.array([lx, 0.0, 0.0]), np.array([0.0, gy, 0.0]), down, tex))
    up = np.array([0.0, 0.0, -wall_h])
    corners = [(-half_x, -half_y), (half_x, -half_y), (half_x, half_y), (-half_x, half_y)]
    for i in range(4):
        for p0, p1, plain in _split_x(np.array([*corners[i], h]), np.array([*corners[(i + 1) % 4], h]), x_plain):
            along = p1 - p0
            inward = -np.array([corners[i][0] + corners[(i + 1) % 4][0], corners[i][1] + corners[(i + 1) % 4][1], 0.0])
            shape = (round(wall_h / w_texel), round(float(np.linalg.norm(along)) / w_texel))
            if plain:
                tex = texture_plain(rng, *shape, *_PLAIN_GREY["wall"])
            else:
                tex = texture_bricks(rng, *shape, w_texel)
            surfaces.append(make_surface(f"wall{i}.plain" if plain else f"wall{i}", p0 + up, along, -up, inward, tex))

    # obstacles, clear of the path (and of the moving box's lane, and out of the blank part)
    if layout.lane:
        lane_y = np.linspace(-1.0, 1.0, 200) * (_box_spot_y(path) + 0.5 * _BOX_SIZE[1])
        lane = np.stack([np.full_like(lane_y, _LANE_X), lane_y], 1)
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
        if layout.lane and np.min(np.linalg.norm(lane - c, axis=1)) < 0.5 * _BOX_SIZE[0] + 0.6 + radius:
            continue
        if x_plain is not None and c[0] + radius + 0.5 > x_plain:
            continue
        if any(math.hypot(c[0] - q[0], c[1] - q[1]) < radius + q[2] + 0.3 for q in placed):
            continue
        placed.append((float(c[0]), float(c[1]), radius))
        yaw = float(rng.uniform(0, np.pi))
        name = f"post{len(placed) - n_boxes}" if is_post else f"box{len(placed)}"
        surfaces.extend(_box_surfaces(name, rng, c, yaw, size, h, b_texel))

    return tuple(surfaces), h, (gx, gy)
