"""Across a stall: the motion between the last frame before a gap and the first one after it.

A stall (the process stopped, the camera or its USB hub silent; docs/reliability.md) leaves a gap
of seconds between two frames. When odometry covers it, the odometry is the motion, as for any
frame. When nothing does, the constant-velocity prediction used between normal frames is no
prior at all: its uncertainty grows with the acceleration bound × Δt² (σ = 84 m over 4 s at
1 m/s), and a particle filter spread over tens of metres, with no map landmark in view to weigh
its particles, puts its estimate wherever the noisiest particle is (21.8 m off on the simulated
rover, then the pitch singularity; kitti-seq1 with a 4 s hole: 24 m).

So the first frame after a gap that nothing measured gets its motion from evidence, in order:

1. **The images across the gap**: stereo PnP of this frame against the last one before the gap
   (robotd.frontend.pnp), with the whole physical reach as the prior's bounds. The prior's own
   hypothesis is *standing still*, which PnP scores first: the usual stall (a camera hiccup while
   the rover waits) is a motion of zero that the images confirm with hundreds of inliers. It must
   rest on twice the inliers a normal frame needs.
2. **The map, searched whole**: the frame's features matched by descriptor to every landmark
   of the map (no pose prior: the wide prior), the outlier stage's similarity giving the pose, as
   :mod:`robotd.pipeline.relocalise` does after a resume, when it rests on ``relocalise.MIN_INLIERS``
   inliers and lies within the physical reach of the last pose.
3. **No evidence** (the view after the gap was never mapped and shares nothing with the one
   before): the best guess (:func:`blind_motion`): the last speed held, the turn rate decaying
   with a time constant of ``TURN_TAU_S`` (standing still when no velocity is known). The filter
   is moved by it *rigidly* (a small nominal noise), so its particles stay together and its
   estimate stays at the guess, and how far off the guess can be goes to the reported covariance
   instead (:meth:`ReportedCovariance.add_uncertainty`), through it to the landmarks mapped after
   the gap, and so to the health topic and the autopilot.

What the vehicle could physically have done over a gap of Δt (:func:`reach`), from its last
velocity v₀ and rate ω₀, with the configured limits (``vehicle.max_speed_mps``,
``vehicle.max_rate_radps``, the front end's acceleration bounds ``PnpParams.max_accel_mps2`` and
``max_angular_accel_radps2``):

    distance from the start   ≤ min(v_max Δt, |v₀| Δt + a Δt² / 2)
    distance from the guess   ≤ min(a Δt² / 2, (v_max + |v₀|) Δt)

and likewise for the rotation (at most π). The first bounds which PnP and map fixes are
plausible; the second is taken as 2σ of the guess's error.

A gap is an interval longer than max(``GAP_MIN_S``, ``GAP_FRAMES`` × the recent median frame
interval): the health monitor's definition of a stall (robotd.daemon.health), seen from the frame
times alone so that replay and the daemon agree.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from robotd.core.geometry import so3_exp, so3_log
from robotd.frontend.pnp import MotionPrior, PnpParams

GAP_MIN_S = 0.5  # a gap is at least this long ...
GAP_FRAMES = 5  # ... and this many recent median frame intervals
INTERVALS = 15  # recent intervals the median frame interval is taken over
TURN_TAU_S = 3.0  # correlation time of the turn rate across a blind gap (blind_motion; docs/reliability.md)


@dataclass(frozen=True, slots=True)
class Reach:
    """How far the vehicle can be after a gap (module docstring): from the start (``t_m``,
    ``rot_rad``) and from the constant-velocity guess (``dev_t_m``, ``dev_rot_rad``)."""

    t_m: float
    rot_rad: float
    dev_t_m: float
    dev_rot_rad: float

    def guess_cov(self) -> np.ndarray:
        """(6, 6) over (x, y, z, roll, pitch, yaw): the guess's error, its bound taken as 2σ per axis."""
        sd = np.r_[np.full(3, self.dev_t_m / 2.0), np.full(3, self.dev_rot_rad / 2.0)]
        return np.diag(sd * sd)


def reach(
    dt_s: float, v0_mps: float, w0_radps: float, max_speed_mps: float, max_rate_radps: float, p: PnpParams
) -> Reach:
    """The physical bounds over a gap of ``dt_s`` from speed ``v0_mps`` and turn rate ``w0_radps``."""
    a, alpha = p.max_accel_mps2, p.max_angular_accel_radps2
    v0, w0 = abs(v0_mps), abs(w0_radps)
    half_a, half_al = 0.5 * a * dt_s * dt_s, 0.5 * alpha * dt_s * dt_s
    return Reach(
        t_m=min(max_speed_mps * dt_s, v0 * dt_s + half_a),
        rot_rad=min(max_rate_radps * dt_s, w0 * dt_s + half_al, math.pi),
        dev_t_m=min(half_a, (max_speed_mps + v0) * dt_s),
        dev_rot_rad=min(half_al, (max_rate_radps + w0) * dt_s, math.pi),
    )


def blind_motion(
    R_last: np.ndarray, t_last: np.ndarray, dt_last_s: float, dt_s: float, turn_tau_s: float = TURN_TAU_S
) -> tuple[np.ndarray, np.ndarray]:
    """The best guess (R (3, 3), t (3,)) of the motion over ``dt_s`` that nothing measured, from the
    last interval's motion (R_last, t_last over ``dt_last_s``): the body speed held, the turn rate
    about the vertical decaying as exp(−t / ``turn_tau_s``) (a mean-reverting turn rate, Singer's
    manoeuvre model: a vehicle in a curve does not go round in circles), roll and pitch held (their
    rates are the terrain's rocking), integrated along the path.

    Why not the constant twist: on the simulated rover, a stall entered at 0.27 rad/s in the loop's changing
    curvature turned a constant-rate guess 47° too far (the error then grew to 3.7 m within 4 s);
    and a straight-ahead guess is 3 m off after 4 s in a 1.8 m radius curve."""
    w_last = so3_log(R_last) / dt_last_s
    # the last interval's translation is its chord: the body velocity turned by half its rotation
    v = so3_exp(-w_last * dt_last_s / 2.0) @ np.asarray(t_last, float) / dt_last_s
    wz = float(w_last[2])
    n = max(1, math.ceil(dt_s / 0.01))  # 10 ms steps, the midpoint rotation for each
    h = dt_s / n
    R, t = np.eye(3), np.zeros(3)
    for k in range(n):
        w = wz * math.exp(-(k + 0.5) * h / turn_tau_s)
        t = t + R @ so3_exp(np.array([0.0, 0.0, w * h / 2.0])) @ (v * h)
        R = R @ so3_exp(np.array([0.0, 0.0, w * h]))
    return R, t


def still_prior(r: Reach) -> MotionPrior:
    """Standing still, with everything the vehicle could have done as its bounds (the PnP across
    the gap scores standing still first and takes any plausible motion the images support)."""
    return MotionPrior(np.eye(3), np.zeros(3), r.t_m, r.rot_rad)


def plausible(r: Reach, t: np.ndarray, R: np.ndarray) -> bool:
    """The motion (t (3,), R (3, 3)) over the gap lies within the vehicle's reach."""
    c = (float(np.trace(R)) - 1.0) / 2.0
    return float(np.linalg.norm(t)) <= r.t_m and math.acos(max(-1.0, min(1.0, c))) <= r.rot_rad


class GapDetector:
    """Recent frame intervals; :meth:`gap` says whether the next one is a gap (module docstring)."""

    def __init__(self) -> None:
        self._dt: deque[float] = deque(maxlen=INTERVALS)

    def reset(self) -> None:
        self._dt.clear()

    def gap(self, dt_s: float) -> bool:
        """True when an interval of ``dt_s`` is a gap; a normal interval joins the recent ones."""
        nominal = float(np.median(np.fromiter(self._dt, float))) if self._dt else 0.0
        if dt_s > max(GAP_MIN_S, GAP_FRAMES * nominal):
            return True
        if dt_s > 0:
            self._dt.append(dt_s)
        return False
