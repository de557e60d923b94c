"""Odometry: plausibility gates on the vehicle's samples, and their integration into the motion
increment between two frame times.

Samples (robotd.core.msgs.Odometry) are body-frame velocities and rates on the host monotonic clock.
:class:`OdometryGate` refuses a sample no vehicle could have produced (a speed, an acceleration or
an angular rate beyond the configured limits, a timestamp going backwards or into the future):
one wheel-tick counter that jumps, or one corrupt MAVLink field, must not throw the pose hundreds
of kilometres away. A refused sample is counted and never integrated.

Between two capture times the body motion is integrated with a zero-order hold of each sample
(the latest sample at or before a time holds until the next one), composing rotations exactly
(SO(3) exponential), so the increment is expressed in the robot frame at the earlier frame.

When every sample used states its noise (``Odometry.cov``, independent from sample to sample), the
increment carries it: the error (δp, φ) of the increment, φ the rotation error in the frame at t0
(R̃ = exp(φ) R), is propagated segment by segment to first order,

    δp ← δp − [a]× φ + R_mid Δt δv − R_mid [v]× (Δt²/2) δω,     φ ← φ + R_new Δt δω,

with a = R_mid v Δt the segment's translation, R_mid the rotation at its middle and R_new at its
end (the right Jacobian of exp(ω Δt) taken as I: |ω Δt| < 0.05 rad for a car at 10 Hz). For the
small rotations of one frame interval φ is the perturbation of ``drot_R_rad`` to first order.
Without stated noise the increment's covariance is zero, which the filters read as "use the motion
model" (``SlamParams.motion_cov_source``).
"""

from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from robotd.core.errors import InputError
from robotd.core.geometry import se3, skew, so3_exp, so3_log
from robotd.core.msgs import MotionIncrement, Odometry

logger = logging.getLogger("robotd.odometry")  # its name before the layer packages: users filter by it

# Acceleration is judged over at least this interval: two samples a millisecond apart differ by
# their noise, not by a physical acceleration (the sim rover's 50 Hz odometry reaches 14 m/s² of
# apparent acceleration from its noise alone over 20 ms).
MIN_ACCEL_DT_S = 0.02
REJECT_REASONS = ("speed", "acceleration", "rate", "clock")
# A gravity direction older than this at a frame's time is not used for it (a vehicle turning at
# 1 rad/s rolls and pitches little in 0.2 s; the samples come at the odometry rate).
GRAVITY_MAX_AGE_S = 0.2


@dataclass(frozen=True, slots=True)
class OdometryLimits:
    """What a vehicle sample may be (config ``vehicle.max_*``; defaults bound any ground vehicle
    robotd is meant for, including a car on public roads)."""

    max_speed_mps: float = 30.0
    max_accel_mps2: float = 50.0
    max_rate_radps: float = 10.0
    max_future_s: float = 0.5  # a sample stamped this far after "now" (the host clock) is refused


def _norm(v: object) -> float:
    """|v| of a 3-vector without overflow: a link may send values near float32's limit (3e38),
    whose squares overflow in float32 (the gate then refuses them, as it should, quietly)."""
    return math.hypot(*(float(x) for x in np.ravel(np.asarray(v))))


class OdometryGate:
    """Refuses implausible samples (module docstring) and counts them per reason."""

    def __init__(self, limits: OdometryLimits | None = None) -> None:
        self.limits = limits or OdometryLimits()
        self.rejected = dict.fromkeys(REJECT_REASONS, 0)
        self.accepted = 0
        self._last: Odometry | None = None

    def check(self, odo: Odometry, now_ns: int | None = None) -> str | None:
        """Why ``odo`` is refused ("speed", "acceleration", "rate", "clock"), or None when it is
        plausible. ``now_ns``: the host's monotonic time (live); None in a replay."""
        lim = self.limits
        last = self._last
        if (last is not None and odo.t_ns <= last.t_ns) or (
            now_ns is not None and odo.t_ns > now_ns + lim.max_future_s * 1e9
        ):
            return "clock"
        if _norm(odo.vel_R_mps) > lim.max_speed_mps:
            return "speed"
        if _norm(odo.rate_R_radps) > lim.max_rate_radps:
            return "rate"
        if last is not None:
            dt = (odo.t_ns - last.t_ns) * 1e-9
            dv = _norm(np.asarray(odo.vel_R_mps, dtype=np.float64) - np.asarray(last.vel_R_mps, dtype=np.float64))
            if dt < 1.0 and dv / max(dt, MIN_ACCEL_DT_S) > lim.max_accel_mps2:
                return "acceleration"
        return None

    def accept(self, odo: Odometry, now_ns: int | None = None) -> bool:
        """True when ``odo`` may be integrated; a refusal is counted (and logged, sparingly)."""
        why = self.check(odo, now_ns)
        if why is None:
            self._last = odo
            self.accepted += 1
            return True
        self.rejected[why] += 1
        n = self.rejected[why]
        if n == 1 or math.log10(n).is_integer():  # the 1st, 10th, 100th ... of each kind
            logger.warning(
                "odometry sample refused (%s; %d so far): v %s m/s, rate %s rad/s at t %d ns (vehicle.max_*)",
                why,
                n,
                np.round(np.asarray(odo.vel_R_mps, dtype=np.float64), 3).tolist(),
                np.round(np.asarray(odo.rate_R_radps, dtype=np.float64), 3).tolist(),
                odo.t_ns,
            )
        return False

    def stats(self) -> dict[str, int]:
        return {"accepted": self.accepted, **{f"rejected_{k}": v for k, v in self.rejected.items()}}


class OdometryIntegrator:
    """Keeps recent samples and integrates them between frame times."""

    def __init__(self, max_samples: int = 4096, max_gap_s: float = 0.5) -> None:
        self._t: deque[int] = deque(maxlen=max_samples)
        self._v: deque[np.ndarray] = deque(maxlen=max_samples)
        self._w: deque[np.ndarray] = deque(maxlen=max_samples)
        self._c: deque[np.ndarray | None] = deque(maxlen=max_samples)
        self.max_gap_ns = int(max_gap_s * 1e9)
        self.out_of_order = 0
        self.gaps = 0
        # measured gravity directions (t_ns, g_R, σ): the newest at or before a frame goes with it
        self._gravity: deque[tuple[int, np.ndarray, float]] = deque(maxlen=256)

    def add(self, odo: Odometry) -> None:
        if self._t and odo.t_ns < self._t[-1]:
            self.out_of_order += 1  # a late sample cannot rewrite the past; drop it
            return
        self._t.append(int(odo.t_ns))
        self._v.append(np.asarray(odo.vel_R_mps, float))
        self._w.append(np.asarray(odo.rate_R_radps, float))
        self._c.append(None if odo.cov is None else np.asarray(odo.cov, float))
        if odo.gravity_R is not None:
            self._gravity.append((int(odo.t_ns), np.asarray(odo.gravity_R, float), float(odo.gravity_sigma_rad)))

    def gravity_at(self, t_ns: int) -> tuple[np.ndarray, float] | None:
        """The newest measured gravity direction at or before ``t_ns`` and within
        ``GRAVITY_MAX_AGE_S`` of it, with its σ; None when there is none."""
        for t, g, sigma in reversed(self._gravity):
            if t <= t_ns:
                return (g, sigma) if t_ns - t <= GRAVITY_MAX_AGE_S * 1e9 else None
        return None

    @property
    def latest_t_ns(self) -> int | None:
        return self._t[-1] if self._t else None

    def integrate(self, t0_ns: int, t1_ns: int) -> MotionIncrement | None:
        """The increment from t0 to t1, or None when the samples do not cover the interval."""
        if t1_ns < t0_ns or not self._t:
            return None
        t = np.fromiter(self._t, np.int64)
        # coverage: a sample at or before t0 (within max_gap) and data reaching close to t1
        i0 = int(np.searchsorted(t, t0_ns, side="right")) - 1
        if i0 < 0 or t0_ns - t[i0] > self.max_gap_ns or t1_ns - t[-1] > self.max_gap_ns:
            self.gaps += 1
            return None
        V = np.asarray(self._v)
        W = np.asarray(self._w)
        # segment boundaries: t0, sample times inside (t0, t1), t1
        inner = np.nonzero((t > t0_ns) & (t < t1_ns))[0]
        bounds = np.concatenate([[t0_ns], t[inner], [t1_ns]])
        seg_idx = np.concatenate([[i0], inner])
        if np.any(np.diff(t[max(i0, 0) :]) > self.max_gap_ns):
            # a hole inside the interval: holding one sample across it would invent motion
            within = t[max(i0, 0) :]
            holes = np.diff(within) > self.max_gap_ns
            if np.any(holes & (within[1:] > t0_ns) & (within[:-1] < t1_ns)):
                self.gaps += 1
                return None
        covs = [self._c[int(j)] for j in seg_idx]
        stated = all(c is not None for c in covs)
        R = np.eye(3)
        p = np.zeros(3)
        P = np.zeros((6, 6))
        for k in range(len(seg_idx)):
            dt = (bounds[k + 1] - bounds[k]) * 1e-9
            if dt <= 0:
                continue
            j = seg_idx[k]
            # translation along the segment with the rotation at its midpoint (second order)
            R_mid = R @ so3_exp(W[j] * dt / 2.0)
            a = R_mid @ (V[j] * dt)
            p = p + a
            R = R @ so3_exp(W[j] * dt)
            if stated:
                P = _propagate(P, a, R_mid, R, V[j], dt, covs[k])  # type: ignore[arg-type]
        grav = self.gravity_at(t1_ns)
        return MotionIncrement(
            int(t0_ns),
            int(t1_ns),
            p,
            so3_log(R),
            0.5 * (P + P.T),
            None if grav is None else grav[0],
            0.0 if grav is None else grav[1],
        )

    def prune_before(self, t_ns: int) -> None:
        """Forget samples no longer needed (keep the last one at or before t_ns)."""
        while len(self._t) >= 2 and self._t[1] <= t_ns:
            self._t.popleft()
            self._v.popleft()
            self._w.popleft()
            self._c.popleft()


def _propagate(
    P: np.ndarray, a: np.ndarray, R_mid: np.ndarray, R_new: np.ndarray, v: np.ndarray, dt: float, S: np.ndarray
) -> np.ndarray:
    """One zero-order-hold segment's first-order covariance step (module docstring): (δp, φ) (6, 6)
    through F = [[I, −[a]×], [0, I]], plus the sample's noise S over (δv, δω) through
    G = [[R_mid Δt, −R_mid [v]× Δt²/2], [0, R_new Δt]]."""
    F = np.eye(6)
    F[:3, 3:] = -skew(a)
    G = np.zeros((6, 6))
    G[:3, :3] = R_mid * dt
    G[:3, 3:] = -R_mid @ skew(v) * (dt * dt / 2.0)
    G[3:, 3:] = R_new * dt
    return F @ P @ F.T + G @ S @ G.T  # type: ignore[no-any-return]


def dead_reckon(samples: Iterable[Odometry], t_ns: Sequence[int], max_gap_s: float = 0.5) -> np.ndarray:
    """Odometry alone: poses T_world_robot (N, 4, 4) at the times ``t_ns`` (increasing), world =
    the robot at ``t_ns[0]``, composing :meth:`OdometryIntegrator.integrate` between consecutive
    times. Raises InputError when the samples do not cover an interval."""
    integ = OdometryIntegrator(max_samples=1 << 20, max_gap_s=max_gap_s)
    for s in samples:
        integ.add(s)
    out = np.tile(np.eye(4), (len(t_ns), 1, 1))
    for k in range(1, len(t_ns)):
        inc = integ.integrate(int(t_ns[k - 1]), int(t_ns[k]))
        if inc is None:
            raise InputError(f"dead_reckon: no odometry covers {t_ns[k - 1]}…{t_ns[k]} ns")
        out[k] = out[k - 1] @ se3(so3_exp(inc.drot_R_rad), inc.dp_R_m)
    return out
