"""A mock ArduPilot Rover on loopback UDP, for tests and benchmarks (pymavlink via drivers.mavlink_link).

It listens on ``127.0.0.1:<ephemeral>`` (``udpin``) as system ``sysid`` / component 1 and, once
robotd has spoken, streams what a Rover with wheel encoders sends: HEARTBEAT and SYSTEM_TIME at
1 Hz, ATTITUDE, WHEEL_DISTANCE (two wheels, cumulative metres, millisecond-resolution stamps,
±100 000 m wrap), LOCAL_POSITION_NED and SERVO_OUTPUT_RAW. It answers TIMESYNC with its boot
time in ns (as ArduPilot does), asks robotd for TIMESYNC itself (as PX4 does), confirms
SET_GPS_GLOBAL_ORIGIN with GPS_GLOBAL_ORIGIN, can "reboot" (SYSTEM_TIME drops) and can fall silent
(link loss). It answers SET_MESSAGE_INTERVAL as ArduPilot Rover 4.7 does (measured on its SITL,
docs/mavlink.md §3): MAV_RESULT_DENIED, with ArduPilot's STATUSTEXT, for an interval under 1.25
periods of ``loop_rate_hz`` (SCHED_LOOP_RATE; 40 Hz is the most a 50 Hz loop grants) and for the
messages it has no interval for (``unrequestable``: WHEEL_DISTANCE); otherwise ACCEPTED, and the
ATTITUDE and LOCAL_POSITION_NED rates change accordingly. Its COMMAND_ACKs name the requester
(``target_system``, ``target_component``) and not the message. Everything received is recorded
with its arrival time for the tests to check what ArduPilot checks.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, field
from typing import Any

from drivers.mavlink_link import DIALECT, mavlink_module, mavutil

WHEEL_WRAP_M = 100_000.0


@dataclass
class Received:
    t_ns: int
    msg: Any


@dataclass
class MockAutopilot:
    """Mock Rover. ``speed_mps``/``yaw_rate_radps`` drive the wheels (FRD: positive turns right)."""

    sysid: int = 1
    speed_mps: float = 0.5
    yaw_rate_radps: float = 0.2
    track_width_m: float = 0.4
    stream_hz: float = 50.0  # WHEEL_DISTANCE
    attitude_hz: float | None = None  # None: stream_hz (until a granted SET_MESSAGE_INTERVAL changes it)
    local_position_hz: float = 10.0
    loop_rate_hz: float = 50.0  # ArduPilot's SCHED_LOOP_RATE: intervals under 1.25 periods are refused
    unrequestable: tuple[str, ...] = ("WHEEL_DISTANCE",)  # no ap_message: every request refused
    wheel_start_m: float = 0.0
    roll_rad: float = 0.0  # the attitude ATTITUDE reports (a rover on a slope)
    pitch_rad: float = 0.0
    signing_key: bytes | None = None
    send_wheels: bool = True
    send_timesync_requests: bool = True
    received: list[Received] = field(default_factory=list)
    timesync_replies: list[tuple[int, int, Any]] = field(default_factory=list)  # (ts1 sent, t_reply_ns, msg)
    intervals: dict[int, int] = field(default_factory=dict)  # granted SET_MESSAGE_INTERVAL: msg id -> µs
    heartbeat_enabled: bool = True
    bad_data: int = 0
    origin: tuple[int, int, int] | None = None  # the EKF origin (lat, lon [1e-7 deg], alt [mm]) once set
    armed: bool = False  # HEARTBEAT.base_mode's safety-armed flag

    def __post_init__(self) -> None:
        self.conn = mavutil.mavlink_connection(
            "udpin:127.0.0.1:0", source_system=self.sysid, source_component=1, dialect=DIALECT
        )
        self.port = self.conn.port.getsockname()[1]
        if self.signing_key is not None:
            self.conn.setup_signing(self.signing_key, sign_outgoing=True, allow_unsigned_callback=lambda *_: False)
        self.boot_ns = time.monotonic_ns()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._s_l = self.wheel_start_m
        self._s_r = self.wheel_start_m
        self._yaw = 0.0
        self._north = self._east = 0.0  # the position LOCAL_POSITION_NED reports [m]
        self._last_motion_ns = self.boot_ns
        self._ts_sent: dict[int, int] = {}
        if self.attitude_hz is None:
            self.attitude_hz = self.stream_hz

    @property
    def url(self) -> str:
        return f"mavlink+udp://127.0.0.1:{self.port}"

    def boot_time_ns(self, t_host_ns: int | None = None) -> int:
        """The autopilot's clock (time since boot) at host time ``t_host_ns``."""
        return (time.monotonic_ns() if t_host_ns is None else t_host_ns) - self.boot_ns

    def reboot(self) -> None:
        """Restart the boot clock: SYSTEM_TIME.time_boot_ms drops (and the EKF origin is gone)."""
        with self._lock:
            self.boot_ns = time.monotonic_ns()
            self.origin = None

    def messages(self, kind: str) -> list[Received]:
        with self._lock:
            return [r for r in self.received if r.msg.get_type() == kind]

    # -- loop ----------------------------------------------------------------------------------
    def _heard(self) -> bool:
        return bool(self.conn.clients)

    def _advance(self, t_ns: int) -> None:
        dt = (t_ns - self._last_motion_ns) * 1e-9
        self._last_motion_ns = t_ns
        half = 0.5 * self.yaw_rate_radps * self.track_width_m
        self._s_l = self._wrap(self._s_l + (self.speed_mps + half) * dt)
        self._s_r = self._wrap(self._s_r + (self.speed_mps - half) * dt)
        # the position along the arc (exact for a constant speed and turn rate over dt)
        w, y0 = self.yaw_rate_radps, self._yaw
        if abs(w * dt) > 1e-9:
            dn = self.speed_mps / w * (math.sin(y0 + w * dt) - math.sin(y0))
            de = self.speed_mps / w * (math.cos(y0) - math.cos(y0 + w * dt))
        else:
            dn, de = self.speed_mps * dt * math.cos(y0), self.speed_mps * dt * math.sin(y0)
        self._north += dn
        self._east += de
        self._yaw = (self._yaw + self.yaw_rate_radps * dt + math.pi) % (2 * math.pi) - math.pi

    @staticmethod
    def _wrap(s: float) -> float:
        if s > WHEEL_WRAP_M:
            return s - 2 * WHEEL_WRAP_M
        if s < -WHEEL_WRAP_M:
            return s + 2 * WHEEL_WRAP_M
        return s

    def _send_attitude(self, t_ns: int) -> None:
        self._advance(t_ns)
        ms = self.boot_time_ns(t_ns) // 1_000_000
        self.conn.mav.attitude_send(ms, self.roll_rad, self.pitch_rad, self._yaw, 0.0, 0.0, self.yaw_rate_radps)

    def _send_stream(self, t_ns: int) -> None:
        """The ``stream_hz`` tick: WHEEL_DISTANCE (ATTITUDE has its own rate, ``attitude_hz``)."""
        self._advance(t_ns)
        if self.send_wheels:
            # Rover stamps WHEEL_DISTANCE with millisecond resolution
            t_us = (self.boot_time_ns(t_ns) // 1_000_000) * 1000
            self.conn.mav.wheel_distance_send(t_us, 2, [self._s_l, self._s_r] + [0.0] * 14)

    def _send_local_position(self, t_ns: int) -> None:
        self._advance(t_ns)
        vn = self.speed_mps * math.cos(self._yaw)
        ve = self.speed_mps * math.sin(self._yaw)
        ms = self.boot_time_ns(t_ns) // 1_000_000
        self.conn.mav.local_position_ned_send(ms, self._north, self._east, 0.0, vn, ve, 0.0)

    def _send_slow(self, t_ns: int) -> None:
        m = mavlink_module()
        mav = self.conn.mav
        boot_ns = self.boot_time_ns(t_ns)
        if self.heartbeat_enabled:
            base_mode = m.MAV_MODE_FLAG_SAFETY_ARMED if self.armed else 0
            mav.heartbeat_send(m.MAV_TYPE_GROUND_ROVER, m.MAV_AUTOPILOT_ARDUPILOTMEGA, base_mode, 0, m.MAV_STATE_ACTIVE)
        mav.system_time_send(0, boot_ns // 1_000_000)
        mav.servo_output_raw_send(boot_ns // 1000 & 0xFFFFFFFF, 0, 1600, 0, 1750, 0, 0, 0, 0, 0)
        if self.send_timesync_requests:
            ts1 = time.monotonic_ns()
            self._ts_sent[ts1] = ts1
            mav.timesync_send(0, ts1)

    def _handle(self, msg: Any, t_ns: int) -> None:
        m = mavlink_module()
        kind = msg.get_type()
        if kind == "BAD_DATA":
            self.bad_data += 1
            return
        with self._lock:
            self.received.append(Received(t_ns, msg))
        if kind == "TIMESYNC":
            if msg.tc1 == 0:
                self.conn.mav.timesync_send(self.boot_time_ns(), msg.ts1)  # ArduPilot: boot time in ns
            elif msg.ts1 in self._ts_sent:
                self.timesync_replies.append((self._ts_sent.pop(msg.ts1), t_ns, msg))
        elif kind == "COMMAND_LONG":
            result = m.MAV_RESULT_ACCEPTED
            if msg.command == m.MAV_CMD_SET_MESSAGE_INTERVAL:
                result = self._set_message_interval(int(msg.param1), int(msg.param2))
            self.conn.mav.command_ack_send(msg.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent())
            if msg.command == m.MAV_CMD_REQUEST_MESSAGE and int(msg.param1) == m.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN:
                self._send_origin()  # as ArduPilot: nothing when it has no origin
        elif kind == "SET_GPS_GLOBAL_ORIGIN":
            with self._lock:
                if self.origin is None:  # ArduPilot sets it once per boot
                    self.origin = (int(msg.latitude), int(msg.longitude), int(msg.altitude))
            self._send_origin()

    def _send_origin(self) -> None:
        with self._lock:
            o = self.origin
        if o is not None:
            self.conn.mav.gps_global_origin_send(*o, self.boot_time_ns() // 1000)

    def statustext(self, text: str, severity: int = 4) -> None:
        """Send one STATUSTEXT (ArduPilot's pre-arm messages are severity 4, WARNING... or 2)."""
        self.conn.mav.statustext_send(severity, text.encode()[:50])

    def forget_origin(self) -> None:
        """What EKF3 does when it initialises after an origin was set: the origin is gone."""
        with self._lock:
            self.origin = None

    def _set_message_interval(self, msg_id: int, interval_us: int) -> int:
        """ArduPilot's answer (GCS_MAVLINK::set_message_interval) and, when granted, the new rate."""
        m = mavlink_module()
        cls = m.mavlink_map.get(msg_id)
        name = cls.msgname if cls is not None else ""
        if name in self.unrequestable:
            self.conn.mav.statustext_send(m.MAV_SEVERITY_INFO, f"No ap_message for mavlink id ({msg_id})".encode())
            return int(m.MAV_RESULT_DENIED)
        if interval_us == 0:
            return int(m.MAV_RESULT_ACCEPTED)  # "the default rate": this mock keeps its current one
        interval_ms = 0 if interval_us == -1 else max(1, interval_us // 1000)
        if interval_ms and interval_ms * 800 < 1e6 / self.loop_rate_hz:
            text = f"Requested rate for message ID {msg_id} too fast. Increase SCHED_LOOP_RATE"
            self.conn.mav.statustext_send(m.MAV_SEVERITY_WARNING, text[:50].encode())
            return int(m.MAV_RESULT_DENIED)
        self.intervals[msg_id] = interval_us
        hz = 0.0 if interval_ms == 0 else 1000.0 / interval_ms
        if name == "ATTITUDE":
            self.attitude_hz = hz
        elif name == "LOCAL_POSITION_NED":
            self.local_position_hz = hz
        return int(m.MAV_RESULT_ACCEPTED)

    def run(self) -> None:
        now = time.monotonic()
        due = {"attitude": now, "stream": now, "local_position": now, "slow": now}
        while not self._stop.is_set():
            msg = self.conn.recv_match(blocking=True, timeout=0.005)
            while msg is not None:
                self._handle(msg, time.monotonic_ns())
                msg = self.conn.recv_match(blocking=False)
            if not self._heard():
                continue  # udpin: cannot talk before robotd has spoken
            now = time.monotonic()
            t_ns = time.monotonic_ns()
            rates = {
                "attitude": self.attitude_hz or 0.0,
                "stream": self.stream_hz,
                "local_position": self.local_position_hz,
                "slow": 1.0,
            }
            for kind, hz in rates.items():
                if hz <= 0 or now < due[kind]:
                    continue
                getattr(self, f"_send_{kind}")(t_ns)
                period = 1.0 / hz
                due[kind] = max(due[kind] + period, now - period)

    def start(self) -> MockAutopilot:
        self._thread = threading.Thread(target=self.run, name="mock-autopilot", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self.conn.close()

    def __enter__(self) -> MockAutopilot:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
