"""Ground-vehicle physics for ArduPilot's SITL JSON interface (``--model JSON:127.0.0.1``).

    python -m drivers.rover_physics --listen 127.0.0.1:9002 [--truth-to 127.0.0.1:9010] \\
        [--yaw-deg 0] [--north 0 --east 0]

runs until SIGINT/SIGTERM and prints its counters at the end. It listens on loopback only unless
``--allow-remote`` is given. It is the physics step of the loop autopilot → physics → rendered
stereo camera → robotd → ODOMETRY → EKF3: SITL sends its servo outputs, this program moves a
car-like rover and answers with the rover's IMU, pose and velocity, and it can stream the true
state to a camera renderer in another process (the truth stream, below).

The model (:class:`RoverModel`)
-------------------------------
A kinematic bicycle (Ackermann steering, no slip) whose reference point is the middle of the rear
axle, on the flat level plane z = 0 of SITL's NED frame (origin at SITL's home). Inputs are the
SERVO1 (steering) and SERVO3 (throttle) pulse widths of ArduPilot's ``rover.parm``: 1000–2000 µs,
1500 µs neutral, clamped to that range; 0 µs means "no output yet" and is neutral. With
``u_s, u_t = (pwm − 1500)/500 ∈ [−1, 1]``::

    δ = u_s·δ_max                   steering angle (positive: right, a clockwise turn seen from above)
    v_cmd = u_t·v_max               throttle below 1500 µs commands reverse, as far as it commands
    dv/dt = (v_cmd − v)/τ           first-order speed response
    dψ/dt = r = v·tan δ / L         (L the wheelbase)
    dn/dt = v·cos ψ,  de/dt = v·sin ψ

Inputs are held over a step (a zero-order hold, as SITL holds them), and for held inputs the step
is integrated exactly, not by Euler: v(t) is an exponential, the distance s = ∫v dt has a closed
form, and a path of constant curvature κ = tan δ / L depends on s alone (Δψ = κ·s, and the chord
s·sinc(κs/2) at the heading ψ + κs/2). So one step of n/rate equals n steps of 1/rate, and a
constant steering angle draws a circle of radius L/tan δ to rounding error.

Outputs at the end of a step (:class:`RoverState`): position NED, velocity NED (v cos ψ, v sin ψ,
0), attitude (roll 0, pitch 0, yaw ψ), body rates FRD (0, 0, r) and the specific force in body FRD
an accelerometer measures, (dv/dt, v·r, −9.80665): the acceleration of the reference point in the
rotating body frame minus gravity, so (0, 0, −9.81) at rest. White noise on the IMU (gyro and
accelerometer, σ per axis and sample) is off by default (:class:`RoverParams`).

The JSON protocol (:class:`JsonPhysicsServer`)
----------------------------------------------
SITL sends one UDP datagram per simulation step to the server (127.0.0.1:9002 by default): little
endian ``uint16 magic, uint16 frame_rate_hz, uint32 frame_count``, then 16 ``uint16`` PWM values
when the magic is 18458, 32 when it is 29569 (so 40 or 72 bytes). It waits for the answer, sent
back to the datagram's source address: exactly ``"\\n" + compact JSON + "\\n"``, e.g. ::

    {"timestamp":0.5,"imu":{"gyro":[0.0,0.0,0.1],"accel_body":[0.2,0.3,-9.80665]},
     "position":[1.0,2.0,0.0],"attitude":[0.0,0.0,0.3],"velocity":[1.5,0.5,0.0]}

(one line; SITL's parser is strict: no spaces). Datagrams of another length or magic, or a frame
rate of 0, are malformed: counted, logged at the 1st, 10th, 100th, … and not answered.

Frame counts and time. The answer to frame k is the state at simulated time t_k; ``timestamp`` is
t_k. The first datagram (and the first after a restart) gives t = frame_count/frame_rate_hz (0 for
SITL's first frame) at the start pose. A new frame_count k > k_last advances the model by
(k − k_last)/frame_rate_hz with the PWM values of frame k_last held, then keeps frame k's PWM
values for the next step: the autopilot's output at t_k acts from t_k on. A jump of n > 1 frames is
one exact step of n/rate (identical to n steps, since the inputs are held; the n − 1 frames never
seen are counted in ``skipped_frames``). A repeated frame_count is a resend: the same bytes are sent
again (same state, same time, same IMU noise). A smaller frame_count means SITL restarted: the
model goes back to its start pose, at t = frame_count/frame_rate_hz (time 0 for a fresh SITL; a
frame_count wrapping at 2³² after 41 days at 1200 Hz would look the same). The IMU in the answer to
frame k already reflects frame k's inputs (the specific force just after t_k), as an accelerometer
read then would. SITL's own clock is this timestamp (its ``time_boot_ms`` follows it).

The truth stream
----------------
With ``truth_to`` set, every k-th step (k the largest step count keeping at least ``truth_rate_hz``
datagrams a second of simulated time; every step when that is higher than SITL's rate), and the
first step after a start or restart, the server sends one binary UDP datagram
(:func:`encode_truth` / :func:`decode_truth`), little endian, 124 bytes:

=======  =========================  ====================================================
format   field                      meaning
=======  =========================  ====================================================
``4s``   magic                      ``b"RTRU"``
``H``    version                    1
``H``    flags                      0 (reserved)
``I``    seq                        counts the datagrams sent (a gap is a lost datagram)
``d``    t_sim_s                    simulated time [s], the JSON answer's timestamp
``q``    t_host_ns                  ``time.monotonic_ns()`` on this host when the state was computed
``3d``   position_ned_m             north, east, down [m] from SITL's home
``3d``   attitude_rad               roll, pitch, yaw [rad]
``3d``   velocity_ned_mps           [m/s]
``3d``   rates_frd_radps            body rates p, q, r [rad/s] (noise-free)
=======  =========================  ====================================================

A consumer on the same host (a camera renderer) extrapolates the pose from ``t_host_ns`` to its
own capture time with the velocity and rates.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import signal
import socket
import struct
import sys
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from drivers.base import is_loopback
from robotd.core.errors import DriverError, ProtocolError

logger = logging.getLogger(__name__)

GRAVITY_MPS2 = 9.80665
MAGIC_16 = 18458  # 16 servo outputs
MAGIC_32 = 29569  # 32 servo outputs (SERVO_32_ENABLE 1)
SERVO_COUNT = {MAGIC_16: 16, MAGIC_32: 32}
SERVO_HEADER = struct.Struct("<HHI")  # magic, frame_rate_hz, frame_count
DEFAULT_LISTEN = ("127.0.0.1", 9002)

TRUTH_MAGIC = b"RTRU"
TRUTH_VERSION = 1
TRUTH = struct.Struct("<4sHHIdq3d3d3d3d")  # 124 bytes; the table in the module docstring

Vec3 = tuple[float, float, float]


def _is_power_of_ten(n: int) -> bool:
    while n >= 10 and n % 10 == 0:
        n //= 10
    return n == 1


def _wrap_pi(a: float) -> float:
    """An angle in [−π, π)."""
    return (a + math.pi) % (2.0 * math.pi) - math.pi


@dataclass(frozen=True, slots=True)
class RoverParams:
    """A small car-like rover. Servo channels are 1-based like ArduPilot's SERVOn."""

    wheelbase_m: float = 0.3
    max_steer_deg: float = 30.0  # steering angle at 1000 / 2000 µs
    max_speed_mps: float = 3.0  # |v_cmd| at full throttle, forward and reverse
    speed_tau_s: float = 0.4  # time constant of the first-order speed response
    start_north_m: float = 0.0  # start pose, NED from SITL's home
    start_east_m: float = 0.0
    start_yaw_rad: float = 0.0
    steer_servo: int = 1  # SERVO1
    throttle_servo: int = 3  # SERVO3
    pwm_min_us: int = 1000
    pwm_max_us: int = 2000
    gyro_noise_radps: float = 0.0  # σ of white noise per axis and sample
    accel_noise_mps2: float = 0.0

    def __post_init__(self) -> None:
        def need(ok: bool, name: str, expected: str) -> None:
            if not ok:
                raise ValueError(f"RoverParams.{name} = {getattr(self, name)!r}: expected {expected}")

        finite = {f: getattr(self, f) for f in ("start_north_m", "start_east_m", "start_yaw_rad")}
        for name, v in finite.items():
            need(math.isfinite(v), name, "a finite number")
        need(math.isfinite(self.wheelbase_m) and self.wheelbase_m > 0, "wheelbase_m", "> 0")
        need(0 <= self.max_steer_deg < 90, "max_steer_deg", "in [0, 90)")
        need(math.isfinite(self.max_speed_mps) and self.max_speed_mps >= 0, "max_speed_mps", ">= 0")
        need(math.isfinite(self.speed_tau_s) and self.speed_tau_s > 0, "speed_tau_s", "> 0")
        need(1 <= self.steer_servo <= 32, "steer_servo", "a servo number 1..32")
        need(1 <= self.throttle_servo <= 32, "throttle_servo", "a servo number 1..32")
        need(0 < self.pwm_min_us < self.pwm_max_us, "pwm_max_us", f"> pwm_min_us = {self.pwm_min_us} > 0")
        need(0 <= self.gyro_noise_radps < math.inf, "gyro_noise_radps", ">= 0")
        need(0 <= self.accel_noise_mps2 < math.inf, "accel_noise_mps2", ">= 0")

    def normalised(self, pwm_us: int) -> float:
        """A pulse width as a command in [−1, 1]: clamped to [min, max], 0 (no output) is neutral."""
        if pwm_us == 0:
            return 0.0
        lo, hi = self.pwm_min_us, self.pwm_max_us
        return (min(max(pwm_us, lo), hi) - 0.5 * (lo + hi)) / (0.5 * (hi - lo))


@dataclass(frozen=True, slots=True)
class RoverState:
    """The true state at the end of a step (noise-free)."""

    t_sim_s: float
    t_host_ns: int  # time.monotonic_ns() when it was computed
    position_ned_m: Vec3
    attitude_rad: Vec3  # roll, pitch, yaw
    velocity_ned_mps: Vec3
    rates_frd_radps: Vec3  # body rates p, q, r
    accel_frd_mps2: Vec3  # specific force in body FRD (what an accelerometer reads)


class RoverModel:
    """The kinematic bicycle of the module docstring; ``step`` integrates it exactly."""

    def __init__(self, params: RoverParams | None = None, rng: np.random.Generator | None = None) -> None:
        self.params = params or RoverParams()
        self._rng = rng if rng is not None else np.random.default_rng()
        self.reset()

    def reset(self, t_s: float = 0.0) -> None:
        """Back to the start pose, at rest, neutral inputs, at simulated time ``t_s``."""
        p = self.params
        self.t_s = t_s
        self.north_m = p.start_north_m
        self.east_m = p.start_east_m
        self.yaw_rad = _wrap_pi(p.start_yaw_rad)
        self.speed_mps = 0.0
        self.curvature_pm = 0.0  # tan δ / L [1/m], held until the next set_controls
        self.speed_cmd_mps = 0.0

    def set_controls(self, steer_pwm_us: int, throttle_pwm_us: int) -> None:
        """The inputs held from now on (until the next call)."""
        p = self.params
        delta = p.normalised(steer_pwm_us) * math.radians(p.max_steer_deg)
        self.curvature_pm = math.tan(delta) / p.wheelbase_m
        self.speed_cmd_mps = p.normalised(throttle_pwm_us) * p.max_speed_mps

    def step(self, dt_s: float) -> None:
        """Advance by ``dt_s`` [s] with the held inputs, exactly (module docstring)."""
        if not dt_s >= 0.0:
            raise ValueError(f"dt_s = {dt_s!r}: expected >= 0")
        tau = self.params.speed_tau_s
        v0, vc = self.speed_mps, self.speed_cmd_mps
        decay = math.exp(-dt_s / tau)
        self.speed_mps = vc + (v0 - vc) * decay
        s = vc * dt_s - (v0 - vc) * tau * math.expm1(-dt_s / tau)  # ∫v dt over the step
        half = 0.5 * self.curvature_pm * s  # half the heading change
        chord = s * (math.sin(half) / half if abs(half) > 1e-9 else 1.0 - half * half / 6.0)
        heading = self.yaw_rad + half
        self.north_m += chord * math.cos(heading)
        self.east_m += chord * math.sin(heading)
        self.yaw_rad = _wrap_pi(self.yaw_rad + 2.0 * half)
        self.t_s += dt_s

    def state(self, t_host_ns: int | None = None) -> RoverState:
        v, psi = self.speed_mps, self.yaw_rad
        r = v * self.curvature_pm
        dv = (self.speed_cmd_mps - v) / self.params.speed_tau_s
        return RoverState(
            t_sim_s=self.t_s,
            t_host_ns=time.monotonic_ns() if t_host_ns is None else t_host_ns,
            position_ned_m=(self.north_m, self.east_m, 0.0),
            attitude_rad=(0.0, 0.0, psi),
            velocity_ned_mps=(v * math.cos(psi), v * math.sin(psi), 0.0),
            rates_frd_radps=(0.0, 0.0, r),
            accel_frd_mps2=(dv, v * r, -GRAVITY_MPS2),
        )

    def imu(self, state: RoverState) -> tuple[Vec3, Vec3]:
        """(gyro [rad/s], specific force [m/s²]) in body FRD for ``state``, with the IMU noise."""
        gyro, accel = state.rates_frd_radps, state.accel_frd_mps2
        p = self.params
        if p.gyro_noise_radps > 0:
            n = self._rng.normal(0.0, p.gyro_noise_radps, 3)
            gyro = (gyro[0] + float(n[0]), gyro[1] + float(n[1]), gyro[2] + float(n[2]))
        if p.accel_noise_mps2 > 0:
            n = self._rng.normal(0.0, p.accel_noise_mps2, 3)
            accel = (accel[0] + float(n[0]), accel[1] + float(n[1]), accel[2] + float(n[2]))
        return gyro, accel


# -- wire formats ------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class ServoPacket:
    magic: int
    frame_rate_hz: int
    frame_count: int
    pwm_us: tuple[int, ...]  # 16 or 32 values, SERVO1 first


def parse_servo_packet(data: bytes) -> ServoPacket:
    """One SITL datagram; raises ProtocolError saying what is wrong with it."""
    if len(data) < SERVO_HEADER.size:
        raise ProtocolError(f"{len(data)} bytes: shorter than the {SERVO_HEADER.size}-byte header")
    magic, rate, count = SERVO_HEADER.unpack_from(data)
    n = SERVO_COUNT.get(magic)
    if n is None:
        raise ProtocolError(f"unknown magic {magic}: expected {MAGIC_16} (16 servos) or {MAGIC_32} (32 servos)")
    expected = SERVO_HEADER.size + 2 * n
    if len(data) != expected:
        raise ProtocolError(f"{len(data)} bytes with magic {magic}: expected {expected}")
    if rate == 0:
        raise ProtocolError("frame_rate_hz = 0: expected > 0")
    return ServoPacket(magic, rate, count, struct.unpack_from(f"<{n}H", data, SERVO_HEADER.size))


def encode_servo_packet(frame_rate_hz: int, frame_count: int, pwm_us: list[int] | tuple[int, ...]) -> bytes:
    """What SITL sends (16 or 32 values, padded with 0 to 16 when fewer): for tests and tools."""
    pwm = list(pwm_us) + [0] * max(0, 16 - len(pwm_us))
    if len(pwm) not in (16, 32):
        raise ValueError(f"{len(pwm_us)} PWM values: expected at most 16, or 32")
    magic = MAGIC_16 if len(pwm) == 16 else MAGIC_32
    return SERVO_HEADER.pack(magic, frame_rate_hz, frame_count) + struct.pack(f"<{len(pwm)}H", *pwm)


def encode_answer(state: RoverState, gyro_frd_radps: Vec3, accel_frd_mps2: Vec3) -> bytes:
    """The JSON answer: ``"\\n" + one line of compact JSON + "\\n"``."""
    doc = {
        "timestamp": state.t_sim_s,
        "imu": {"gyro": list(gyro_frd_radps), "accel_body": list(accel_frd_mps2)},
        "position": list(state.position_ned_m),
        "attitude": list(state.attitude_rad),
        "velocity": list(state.velocity_ned_mps),
    }
    return b"\n" + json.dumps(doc, separators=(",", ":"), allow_nan=False).encode() + b"\n"


@dataclass(frozen=True, slots=True)
class TruthSample:
    """One truth-stream datagram (the table in the module docstring)."""

    seq: int
    t_sim_s: float
    t_host_ns: int
    position_ned_m: Vec3
    attitude_rad: Vec3
    velocity_ned_mps: Vec3
    rates_frd_radps: Vec3
    flags: int = 0

    @classmethod
    def from_state(cls, seq: int, state: RoverState) -> TruthSample:
        return cls(
            seq,
            state.t_sim_s,
            state.t_host_ns,
            state.position_ned_m,
            state.attitude_rad,
            state.velocity_ned_mps,
            state.rates_frd_radps,
        )


def encode_truth(sample: TruthSample) -> bytes:
    return TRUTH.pack(
        TRUTH_MAGIC,
        TRUTH_VERSION,
        sample.flags,
        sample.seq & 0xFFFFFFFF,
        sample.t_sim_s,
        sample.t_host_ns,
        *sample.position_ned_m,
        *sample.attitude_rad,
        *sample.velocity_ned_mps,
        *sample.rates_frd_radps,
    )


def decode_truth(data: bytes) -> TruthSample:
    """One truth datagram; raises ValueError on a wrong length, magic or version."""
    if len(data) != TRUTH.size:
        raise ValueError(f"truth datagram of {len(data)} bytes: expected {TRUTH.size}")
    magic, version, flags, seq, t_sim, t_host, *v = TRUTH.unpack(data)
    if magic != TRUTH_MAGIC:
        raise ValueError(f"truth datagram with magic {magic!r}: expected {TRUTH_MAGIC!r}")
    if version != TRUTH_VERSION:
        raise ValueError(f"truth datagram version {version}: expected {TRUTH_VERSION}")
    return TruthSample(
        seq, t_sim, t_host, (v[0], v[1], v[2]), (v[3], v[4], v[5]), (v[6], v[7], v[8]), (v[9], v[10], v[11]), flags
    )


# -- the server --------------------------------------------------------------------------------


def _family(host: str) -> socket.AddressFamily:
    return socket.AF_INET6 if ":" in host else socket.AF_INET


class JsonPhysicsServer:
    """The lockstep UDP server of the module docstring, in its own thread.

    ``with JsonPhysicsServer(model, listen=("127.0.0.1", 0)) as srv:`` binds (port 0: the OS picks
    one, see ``address``) and serves until ``close()``. :meth:`handle` is the protocol without the
    socket. ``latest()`` and ``stats()`` may be called from any thread.
    """

    def __init__(
        self,
        model: RoverModel | None = None,
        *,
        listen: tuple[str, int] = DEFAULT_LISTEN,
        truth_to: tuple[str, int] | None = None,
        truth_rate_hz: float = 200.0,
        allow_remote: bool = False,
    ) -> None:
        if not allow_remote and not is_loopback(listen[0]):
            raise DriverError(f"refusing to listen on {listen[0]}:{listen[1]}: loopback only unless allow_remote")
        if not truth_rate_hz > 0:
            raise DriverError(f"truth_rate_hz = {truth_rate_hz!r}: expected > 0")
        self.model = model or RoverModel()
        self.listen = listen
        self.truth_to = truth_to
        self.truth_rate_hz = truth_rate_hz
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._sock: socket.socket | None = None
        self._truth_sock: socket.socket | None = None
        self._last_count: int | None = None
        self._answer = b""
        self._latest: RoverState | None = None
        self._since_truth = 0
        self._truth_seq = 0
        names = ("steps", "resends", "restarts", "malformed", "skipped_frames", "answers", "send_errors")
        self._counts = dict.fromkeys((*names, "errors", "truth_sent", "truth_errors"), 0)
        self._rate_hz = 0

    # -- protocol (no sockets) -------------------------------------------------------------------
    def handle(self, data: bytes, source: object = "?") -> bytes | None:
        """The answer to one datagram, or None for a malformed one (counted and logged). One thread
        (the server's) calls it; it alone touches the model."""
        try:
            pkt = parse_servo_packet(data)
        except ProtocolError as exc:
            with self._lock:
                self._counts["malformed"] += 1
                n = self._counts["malformed"]
            if _is_power_of_ten(n):
                logger.warning("malformed datagram from %s: %s (%d so far; logged at 1, 10, 100, ...)", source, exc, n)
            return None
        m = self.model
        last = self._last_count
        dt = 1.0 / pkt.frame_rate_hz
        if last is not None and pkt.frame_count == last:
            with self._lock:
                self._counts["resends"] += 1
            return self._answer
        restart = last is not None and pkt.frame_count < last
        if last is None or restart:
            m.reset(pkt.frame_count * dt)
            self._since_truth = -1  # send this state
            if restart:
                logger.info(
                    "frame_count %d after %d: SITL restarted; rover back at its start pose", pkt.frame_count, last
                )
        else:
            m.step((pkt.frame_count - last) * dt)
        self._last_count = pkt.frame_count
        p = m.params
        m.set_controls(pkt.pwm_us[p.steer_servo - 1], pkt.pwm_us[p.throttle_servo - 1])
        state = m.state()
        gyro, accel = m.imu(state)
        self._answer = encode_answer(state, gyro, accel)
        with self._lock:
            c = self._counts
            if restart:
                c["restarts"] += 1
            elif last is not None:
                c["steps"] += 1
                c["skipped_frames"] += pkt.frame_count - last - 1
            self._rate_hz = pkt.frame_rate_hz
            self._latest = state
        self._send_truth(state, pkt.frame_rate_hz)
        return self._answer

    def _send_truth(self, state: RoverState, rate_hz: int) -> None:
        if self.truth_to is None or self._truth_sock is None:
            return
        every = max(1, int(rate_hz // self.truth_rate_hz))
        self._since_truth += 1
        if self._since_truth != 0 and self._since_truth < every:
            return
        self._since_truth = 0
        try:
            self._truth_sock.sendto(encode_truth(TruthSample.from_state(self._truth_seq, state)), self.truth_to)
            sent = 1
        except OSError:
            sent = 0  # nobody listening yet (ECONNREFUSED on loopback) or a full buffer: the next one goes
        self._truth_seq += 1
        with self._lock:
            self._counts["truth_sent"] += sent
            self._counts["truth_errors"] += 1 - sent

    # -- thread-safe views -----------------------------------------------------------------------
    def latest(self) -> RoverState | None:
        """The last computed true state (None before the first datagram)."""
        with self._lock:
            return self._latest

    def stats(self) -> dict[str, Any]:
        with self._lock:
            return {**self._counts, "frame_rate_hz": self._rate_hz, "frame_count": self._last_count}

    @property
    def address(self) -> tuple[str, int]:
        """The bound (host, port); the configured one before ``start``."""
        if self._sock is None:
            return self.listen
        host, port = self._sock.getsockname()[:2]
        return str(host), int(port)

    # -- lifecycle -------------------------------------------------------------------------------
    def start(self) -> JsonPhysicsServer:
        host, port = self.listen
        sock = socket.socket(_family(host), socket.SOCK_DGRAM)
        try:
            sock.bind((host, port))
        except OSError as exc:
            sock.close()
            raise DriverError(f"cannot listen on {host}:{port}: {exc.strerror or exc}") from exc
        sock.settimeout(0.1)  # close() is seen within 0.1 s
        self._sock = sock
        if self.truth_to is not None:
            self._truth_sock = socket.socket(_family(self.truth_to[0]), socket.SOCK_DGRAM)
        self._thread = threading.Thread(target=self._run, name="rover-physics", daemon=True)
        self._thread.start()
        logger.info("rover physics listening on %s:%d%s", *self.address, self._truth_note())
        return self

    def _truth_note(self) -> str:
        if self.truth_to is None:
            return ""
        return f", truth to {self.truth_to[0]}:{self.truth_to[1]} at >= {self.truth_rate_hz:g} Hz"

    def _run(self) -> None:
        sock = self._sock
        assert sock is not None
        while not self._stop.is_set():
            try:
                data, addr = sock.recvfrom(4096)
            except TimeoutError:
                continue
            except OSError as exc:
                if self._stop.is_set():
                    break
                logger.warning("receive failed: %s", exc)
                time.sleep(0.01)
                continue
            try:
                answer = self.handle(data, f"{addr[0]}:{addr[1]}")
            except Exception:  # a bug must not stop the thread: SITL would wait for it forever
                with self._lock:
                    self._counts["errors"] += 1
                logger.exception("datagram from %s:%d not answered", *addr[:2])
                continue
            if answer is None:
                continue
            try:
                sock.sendto(answer, addr)
            except OSError as exc:
                with self._lock:
                    self._counts["send_errors"] += 1
                logger.debug("answer to %s failed: %s", addr, exc)
                continue
            with self._lock:
                self._counts["answers"] += 1

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        for s in (self._sock, self._truth_sock):
            if s is not None:
                s.close()
        self._sock = self._truth_sock = None

    def __enter__(self) -> JsonPhysicsServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()


# -- command line ------------------------------------------------------------------------------


_DEFAULTS = RoverParams()


def _host_port(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise argparse.ArgumentTypeError(f"{text!r}: expected HOST:PORT")
    return host.strip("[]"), int(port)


def main(argv: list[str] | None = None) -> int:
    """``python -m drivers.rover_physics``: serve SITL until SIGINT/SIGTERM, then print the counters."""
    p = argparse.ArgumentParser(prog="rover-physics", description=__doc__.split("\n\n")[0] if __doc__ else None)
    p.add_argument("--listen", type=_host_port, default=DEFAULT_LISTEN, help="HOST:PORT (127.0.0.1:9002)")
    p.add_argument("--allow-remote", action="store_true", help="allow a non-loopback --listen address")
    p.add_argument("--truth-to", type=_host_port, default=None, help="HOST:PORT for the binary truth stream")
    p.add_argument("--truth-rate", type=float, default=200.0, help="truth datagrams per simulated second, at least")
    p.add_argument("--north", type=float, default=0.0, help="start position north of home [m]")
    p.add_argument("--east", type=float, default=0.0, help="start position east of home [m]")
    p.add_argument("--yaw-deg", type=float, default=0.0, help="start heading [deg], 0 north, 90 east")
    p.add_argument("--max-speed", type=float, default=_DEFAULTS.max_speed_mps, help="[m/s] at full throttle")
    p.add_argument("--wheelbase", type=float, default=_DEFAULTS.wheelbase_m, help="[m]")
    p.add_argument("--log-level", default="INFO")
    args = p.parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        params = RoverParams(
            wheelbase_m=args.wheelbase,
            max_speed_mps=args.max_speed,
            start_north_m=args.north,
            start_east_m=args.east,
            start_yaw_rad=math.radians(args.yaw_deg),
        )
        server = JsonPhysicsServer(
            RoverModel(params),
            listen=args.listen,
            truth_to=args.truth_to,
            truth_rate_hz=args.truth_rate,
            allow_remote=args.allow_remote,
        )
        server.start()
    except (ValueError, DriverError) as exc:
        print(f"rover-physics: {exc}", file=sys.stderr)
        return 2
    stop = [False]

    def _on_signal(signum: int, _frame: object) -> None:
        # a plain store: the handler runs in this thread between two bytecodes, so it must not
        # take a lock this thread may hold (an Event's, inside its wait())
        stop[0] = True

    old = {s: signal.signal(s, _on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        while not stop[0]:
            time.sleep(0.1)
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        server.close()
    st = server.stats()
    print("rover-physics: " + ", ".join(f"{k} {v}" for k, v in st.items()), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
