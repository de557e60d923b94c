"""The MAVLink link's inbound vehicle messages: the autopilot's motion as :class:`~robotd.core.msgs.Odometry`
and its control inputs as :class:`~drivers.base.ControlSample` (drivers/mavlink_link.py's receive
thread hands them over once they are known to be the autopilot's).

``WHEEL_DISTANCE`` (differential drive, track width from the options; ±100 000 m wrap) gives
forward speed; ``ATTITUDE`` gives body rates (preferred for yaw rate) and the attitude used to
rotate ``LOCAL_POSITION_NED`` velocities into the body frame when no wheel data flows (the
ATTITUDE nearest each sample's stamp, its yaw carried to the stamp: :meth:`OdometryDecoder.attitude_at`);
``SERVO_OUTPUT_RAW``/``RC_CHANNELS`` are the control inputs. Autopilot stamps go onto the host
clock through the link's TIMESYNC offset (``to_host``).

A handler raises ValueError on values it cannot use (NaN, too few wheels, an impossible pulse
width); the link counts them in ``bad_values``. No pymavlink here (drivers/mavlink_link.py is its
only importer): the messages are read by their field names.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from drivers.base import ControlSample
from drivers.mavlink_options import MavlinkOptions
from drivers.serial_protocol import diff_drive
from robotd.core.geometry import euler_to_R, pose6_to_T
from robotd.core.msgs import Odometry

WHEEL_WRAP_M = 100_000.0  # WHEEL_DISTANCE wraps at ±100 000 m (mavlink PR 1032)
PWM_MIN_US, PWM_MAX_US = 800, 2200  # servo/RC pulse widths a real channel can carry
# An odometry sample takes the ATTITUDE nearest its stamp, turned on by the body rates over the
# difference: within ATTITUDE_FRESH_NS that is a refinement; up to ATTITUDE_MAX_AGE_NS (ArduPilot
# streams ATTITUDE at 1 Hz when no rate request is granted) it is an extrapolation, counted in
# ``attitude_extrapolated``; beyond it the sample is dropped, counted in ``no_attitude``.
ATTITUDE_FRESH_NS = 200_000_000
ATTITUDE_MAX_AGE_NS = 1_000_000_000
# the autopilot's own pose (:meth:`OdometryDecoder.pose_at`): LOCAL_POSITION_NED comes at 10 Hz, so
# the sample nearest a time is within 50 ms of it; one further than this is no pose for that time
POSE_MAX_AGE_NS = 300_000_000


@dataclass(frozen=True, slots=True)
class AutopilotPose:
    """The autopilot's estimate of the vehicle's pose at one host time: ``T`` (4, 4) maps the
    body (FRD) frame into the autopilot's local NED frame; ``boot_ms`` is the autopilot's boot
    clock at that time (a reboot restarts it, and its local frame with it)."""

    t_ns: int
    T: np.ndarray
    boot_ms: int


class OdometryDecoder:
    """The receive thread's vehicle-message handlers (:meth:`handlers`, by message type).

    ``to_host(t_autopilot_ns, t_arrival_ns)``: an autopilot stamp on the host clock; ``emit``: an
    odometry sample out (the link's queue); ``counters``: the link's counter dict
    (``wheel_wraps``, ``wheel_intervals_rejected``, ``attitude_extrapolated``, ``no_attitude``).
    """

    def __init__(
        self,
        opts: MavlinkOptions,
        counters: dict[str, int],
        to_host: Callable[[int, int], int],
        emit: Callable[[Odometry], None],
    ) -> None:
        self.opts = opts
        self.c = counters
        self.to_host = to_host
        self.emit = emit
        self._lock = threading.Lock()  # guards _wheels (a reboot forgets them)
        # recent ATTITUDEs (t_ns, rpy, body rates), the newest last: at 25 Hz, 2.5 s of them
        self._attitudes: deque[tuple[int, np.ndarray, np.ndarray]] = deque(maxlen=64)
        self._wheels: tuple[int, float, float] | None = None  # (t_ap_us, s_left, s_right)
        # recent LOCAL_POSITION_NEDs (host t_ns, time_boot_ms, position, velocity), the newest last
        self._positions: deque[tuple[int, int, np.ndarray, np.ndarray]] = deque(maxlen=64)
        self._last_wheel_mono = -math.inf
        self.controls: ControlSample | None = None  # the newest throttle/steering

    def handlers(self) -> dict[str, Callable[[Any, int], None]]:
        """Message type -> handler(msg, arrival t_ns)."""
        return {
            "ATTITUDE": self.on_attitude,
            "WHEEL_DISTANCE": self.on_wheel_distance,
            "LOCAL_POSITION_NED": self.on_local_position_ned,
            "SERVO_OUTPUT_RAW": self.on_servo_output_raw,
            "RC_CHANNELS": self.on_rc_channels,
        }

    def forget_wheels(self) -> None:
        """The autopilot rebooted: its wheel distances start again (no interval across the reboot)."""
        with self._lock:
            self._wheels = None

    def on_attitude(self, msg: Any, t_ns: int) -> None:
        t = self.to_host(int(msg.time_boot_ms) * 1_000_000, t_ns)
        rpy = np.array([msg.roll, msg.pitch, msg.yaw], dtype=float)
        rates = np.array([msg.rollspeed, msg.pitchspeed, msg.yawspeed], dtype=float)
        if not (np.all(np.isfinite(rpy)) and np.all(np.isfinite(rates))):
            raise ValueError(f"ATTITUDE not finite: rpy {rpy}, rates {rates}")
        self._attitudes.append((t, rpy, rates))

    def attitude_at(self, t_ns: int, max_age_ns: int = ATTITUDE_FRESH_NS) -> tuple[np.ndarray, np.ndarray, int] | None:
        """The autopilot's attitude at host time ``t_ns``: the ATTITUDE nearest in time, if within
        ``max_age_ns``, its yaw carried over the difference Δt by the yaw rate its body rates give,
        ψ̇ = (q sin φ + r cos φ) / cos θ (roll and pitch held: a ground vehicle's change slowly);
        (roll/pitch/yaw at ``t_ns``, body rates, |Δt| in ns). None when there is none that near.

        An odometry sample is paired with the attitude at its own stamp, not with whichever
        ATTITUDE came last: LOCAL_POSITION_NED arrives at 10 Hz, ATTITUDE at whatever rate the
        autopilot grants (1 Hz on ArduPilot when the request is refused), and only a sample
        within 200 ms of the last ATTITUDE used to be kept, leaving holes in the odometry that
        the integrator cannot bridge (issue 24: half the frames without odometry)."""
        best: tuple[int, int, np.ndarray, np.ndarray] | None = None
        for t_a, rpy, rates in reversed(self._attitudes):
            d = abs(t_ns - t_a)
            if best is None or d < best[0]:
                best = (d, t_a, rpy, rates)
            if t_a <= t_ns:
                break  # the stamps increase: older ones are further away
        if best is None or best[0] > max_age_ns:
            return None
        d, t_a, rpy, rates = best
        if t_ns != t_a:
            roll, pitch = float(rpy[0]), float(rpy[1])
            yaw_rate = (rates[1] * math.sin(roll) + rates[2] * math.cos(roll)) / max(math.cos(pitch), 1e-3)
            yaw = math.remainder(float(rpy[2]) + yaw_rate * (t_ns - t_a) * 1e-9, math.tau)
            rpy = np.array([roll, pitch, yaw])
        return rpy, rates, d

    def on_wheel_distance(self, msg: Any, t_ns: int) -> None:
        o = self.opts
        n = int(msg.count)
        if max(o.wheel_left, o.wheel_right) >= n:
            raise ValueError(f"WHEEL_DISTANCE has {n} wheels, need indices {o.wheel_left} and {o.wheel_right}")
        t_us = int(msg.time_usec)
        s_l, s_r = float(msg.distance[o.wheel_left]), float(msg.distance[o.wheel_right])
        if not (math.isfinite(s_l) and math.isfinite(s_r)):
            raise ValueError(f"WHEEL_DISTANCE not finite: {s_l}, {s_r}")
        with self._lock:
            prev, self._wheels = self._wheels, (t_us, s_l, s_r)
        self._last_wheel_mono = time.monotonic()
        if prev is None:
            return
        dt = (t_us - prev[0]) * 1e-6
        if not 0 < dt <= 1.0:
            self.c["wheel_intervals_rejected"] += 1  # a stamp going backwards, or a gap: restart
            return
        ds_l, ds_r = self._unwrap_m(s_l - prev[1]), self._unwrap_m(s_r - prev[2])
        if o.track_width_m > 0:
            v, w_wheels = diff_drive(ds_l / dt, ds_r / dt, o.track_width_m)
        else:
            v, w_wheels = 0.5 * (ds_l + ds_r) / dt, math.nan
        # mean speed over the interval: stamp it at the midpoint
        t = self.to_host((t_us * 1000) - int(dt * 5e8), t_ns)
        a = self.attitude_at(t)
        att = None if a is None else (a[0], a[1])
        if o.yaw_rate_source == "attitude" and att is not None:
            rates = att[1]
        elif math.isfinite(w_wheels):
            rates = np.array([0.0, 0.0, w_wheels])
        elif att is not None:
            rates = att[1]
        else:
            rates = np.zeros(3)  # forward speed only; the motion model inflates yaw noise
        self.emit(Odometry(t, np.array([v, 0.0, 0.0]), np.asarray(rates, float), "mavlink", *self._gravity(att)))

    def _unwrap_m(self, d: float) -> float:
        if d > WHEEL_WRAP_M:
            self.c["wheel_wraps"] += 1
            return d - 2 * WHEEL_WRAP_M
        if d < -WHEEL_WRAP_M:
            self.c["wheel_wraps"] += 1
            return d + 2 * WHEEL_WRAP_M
        return d

    def pose_at(self, t_ns: int) -> AutopilotPose | None:
        """The autopilot's pose at host time ``t_ns``: the LOCAL_POSITION_NED nearest in time (within
        :data:`POSE_MAX_AGE_NS`) carried to ``t_ns`` by its velocity, with the attitude at ``t_ns``
        (:meth:`attitude_at`, within the same age). None when either is missing. What a restarted
        robotd continues from (robotd.daemon.handover)."""
        best: tuple[int, int, int, np.ndarray, np.ndarray] | None = None
        for t_p, boot_ms, p, v in reversed(self._positions):
            d = abs(t_ns - t_p)
            if best is None or d < best[0]:
                best = (d, t_p, boot_ms, p, v)
            if t_p <= t_ns:
                break
        if best is None or best[0] > POSE_MAX_AGE_NS:
            return None
        att = self.attitude_at(t_ns, POSE_MAX_AGE_NS)
        if att is None:
            return None
        _, t_p, boot_ms, p, v = best
        dt = (t_ns - t_p) * 1e-9
        T = pose6_to_T(np.r_[p + v * dt, att[0]])
        return AutopilotPose(int(t_ns), T, boot_ms + round(dt * 1000))

    def on_local_position_ned(self, msg: Any, t_ns: int) -> None:
        t = self.to_host(int(msg.time_boot_ms) * 1_000_000, t_ns)
        v_ned = np.array([msg.vx, msg.vy, msg.vz], dtype=float)
        if not np.all(np.isfinite(v_ned)):
            raise ValueError(f"LOCAL_POSITION_NED velocity not finite: {v_ned}")
        p_ned = np.array([msg.x, msg.y, msg.z], dtype=float)
        if np.all(np.isfinite(p_ned)):
            self._positions.append((t, int(msg.time_boot_ms), p_ned, v_ned))
        if time.monotonic() - self._last_wheel_mono < 1.0:
            return  # wheel odometry flows: it is the better velocity source
        a = self.attitude_at(t, ATTITUDE_MAX_AGE_NS)
        if a is None:
            self.c["no_attitude"] += 1  # cannot rotate NED into the body frame without an attitude
            return
        if a[2] > ATTITUDE_FRESH_NS:
            self.c["attitude_extrapolated"] += 1
        att = (a[0], a[1])
        # NED and the body FRD frame share the ZYX Euler convention: v_R = R(rpy)^T v_NED
        v_R = euler_to_R(att[0]).T @ v_ned
        self.emit(Odometry(t, v_R, att[1].copy(), "mavlink", *self._gravity(att)))

    def _gravity(self, att: tuple[np.ndarray, np.ndarray] | None) -> tuple[None, np.ndarray | None, float]:
        """(cov, gravity_R, σ) of an Odometry: the direction of gravity in the body frame from the
        autopilot's roll and pitch, R(rpy)^T (0, 0, 1), which does not depend on its yaw."""
        sigma = math.radians(self.opts.gravity_sigma_deg)
        if att is None or sigma <= 0:
            return None, None, 0.0
        roll, pitch = float(att[0][0]), float(att[0][1])
        g = np.array([-math.sin(pitch), math.sin(roll) * math.cos(pitch), math.cos(roll) * math.cos(pitch)])
        return None, g, sigma

    def on_servo_output_raw(self, msg: Any, t_ns: int) -> None:
        o = self.opts
        t = self.to_host(int(msg.time_usec) * 1000, t_ns)
        thr = getattr(msg, f"servo{o.throttle_channel}_raw", 0)
        ste = getattr(msg, f"servo{o.steering_channel}_raw", 0)
        _check_pwm("SERVO_OUTPUT_RAW", thr, ste)
        if thr and ste:
            self.controls = ControlSample(t, (thr - 1500) / 500.0, (ste - 1500) / 500.0, "SERVO_OUTPUT_RAW")

    def on_rc_channels(self, msg: Any, t_ns: int) -> None:
        if self.controls is not None and self.controls.source == "SERVO_OUTPUT_RAW":
            return  # commanded outputs beat pilot sticks
        o = self.opts
        t = self.to_host(int(msg.time_boot_ms) * 1_000_000, t_ns)
        thr = getattr(msg, f"chan{o.throttle_channel}_raw", 0)
        ste = getattr(msg, f"chan{o.steering_channel}_raw", 0)
        if thr and ste and thr != 0xFFFF and ste != 0xFFFF:
            _check_pwm("RC_CHANNELS", thr, ste)
            self.controls = ControlSample(t, (thr - 1500) / 500.0, (ste - 1500) / 500.0, "RC_CHANNELS")


def _check_pwm(kind: str, *pwm_us: int) -> None:
    """A pulse width outside 800–2200 µs (0: channel unused) is no servo or stick position."""
    for v in pwm_us:
        if v and not PWM_MIN_US <= v <= PWM_MAX_US:
            raise ValueError(f"{kind}: pulse width {v} µs outside {PWM_MIN_US}–{PWM_MAX_US}")
