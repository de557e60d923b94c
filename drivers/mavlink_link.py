"""``mavlink+udp://`` / ``mavlink+serial://`` vehicle link (the only pymavlink importer).

URLs::

    mavlink+udp://127.0.0.1:14550            robotd sends first (pymavlink "udpout"); the default
    mavlink+udp://127.0.0.1:14551?mode=in    robotd listens (loopback only unless allow_remote=1)
    mavlink+serial:///dev/ttyACM0?baud=921600

Out: the SLAM pose, through the link's ``autopilot`` role (drivers/mavlink_pose.py), as
``ODOMETRY`` (frames LOCAL_FRD 20 / BODY_FRD 12, quaternion, floored pose covariance, NaN
velocity covariance, reset_counter, estimator VIO, quality), or ``VISION_POSITION_ESTIMATE``
with ``message=vision_position_estimate`` (MAVLink-1 links, old firmware). Data-driven: one
message per ``autopilot.send_pose``, a newer pose supersedes an unsent one and nothing is ever
re-sent. ``HEARTBEAT`` at 1 Hz as MAV_TYPE_ONBOARD_CONTROLLER / MAV_AUTOPILOT_INVALID from
component 197 with ``system_status`` from the health. TIMESYNC requests are answered; our own
requests estimate the autopilot clock offset.
``SET_GPS_GLOBAL_ORIGIN`` (when ``origin`` is configured) and the message-rate requests go out
once the autopilot heartbeat is seen and again after an autopilot reboot: a new boot clock in
SYSTEM_TIME seen consistently, with the autopilot's heartbeat, while the old one fell silent
(:class:`drivers.mavlink_guard.BootClock`). The rate requests go one at a time, each matched with
its COMMAND_ACK; a refused rate is logged, counted in ``stats()`` and retried once at half the rate
(:class:`drivers.mavlink_guard.RateRequests`). Link loss: no autopilot heartbeat for
``link_timeout_s`` (3 s).

Exposure (issue 15): with ``mode=out`` the socket is connected to the target, so the kernel binds
it to the address that routes there (127.0.0.1 for a loopback target; ``bind=ADDR`` chooses) and
delivers datagrams from the target's address only. Whatever the transport, vehicle messages are
taken only from the autopilot: the system and component id of its first heartbeat and, over UDP,
the address that heartbeat came from (others are counted in ``rejected_source``). TIMESYNC
requests are answered only for the autopilot, at most ``timesync_reply_hz`` a second.

In: ``WHEEL_DISTANCE`` (differential drive, track width from the options; ±100 000 m wrap) gives
forward speed; ``ATTITUDE`` gives body rates (preferred for yaw rate) and the attitude used to
rotate ``LOCAL_POSITION_NED`` velocities into the body frame when no wheel data flows (the
ATTITUDE nearest each sample's stamp, its yaw carried to the stamp: ``_attitude_at``);
``SERVO_OUTPUT_RAW``/``RC_CHANNELS`` are the control inputs. Autopilot stamps are mapped onto
the host clock with the TIMESYNC offset (arrival time until the first round trip).

Threads (docs/interfaces.md §1.9): one receive thread (``recv_match`` with a 0.1 s timeout), one
transmit thread that owns every ``*_send`` (the pose role's included: it only parks the pose).
"""

from __future__ import annotations

import errno
import ipaddress
import logging
import math
import os
import socket
import stat
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import parse_qsl, urlsplit

os.environ.setdefault("MAVLINK20", "1")  # before the first pymavlink import: ODOMETRY needs MAVLink 2

import numpy as np
from pymavlink import mavutil

from drivers.base import ControlSample, QueuedVehicleLink, is_loopback
from drivers.link_state import LOST, LinkState, LinkStateParams
from drivers.mavlink_guard import NO_ACK, BootClock, RateLimit, RateOutcome, RateRequests
from drivers.mavlink_pose import POSE_COUNTERS, MavlinkAutopilot
from drivers.serial_protocol import diff_drive
from robotd.autopilot import CovarianceFloors, TimesyncFilter
from robotd.errors import DriverError, RobotdError
from robotd.geometry import euler_to_R
from robotd.msgs import Odometry

logger = logging.getLogger(__name__)

DIALECT = "ardupilotmega"
MAV_COMP_ID_VIO = 197
WHEEL_WRAP_M = 100_000.0  # WHEEL_DISTANCE wraps at ±100 000 m (mavlink PR 1032)
PWM_MIN_US, PWM_MAX_US = 800, 2200  # servo/RC pulse widths a real channel can carry
ORIGIN_CHECK_S = 2.0  # how often the autopilot's EKF origin is checked (and sent again if it is gone)
ALIGN_STILL_S = 2.0  # the vehicle stood still this long before robotd asks for a vision-yaw alignment
ALIGN_INTERVAL_S = 5.0  # ... and at most this often
AUX_FUNCTION_VISO_ALIGN = 80  # ArduPilot's RC aux function "VisOdom align"
# An odometry sample takes the ATTITUDE nearest its stamp, turned on by the body rates over the
# difference: within ATTITUDE_FRESH_NS that is a refinement; up to ATTITUDE_MAX_AGE_NS (ArduPilot
# streams ATTITUDE at 1 Hz when no rate request is granted) it is an extrapolation, counted in
# ``attitude_extrapolated``; beyond it the sample is dropped, counted in ``no_attitude``.
ATTITUDE_FRESH_NS = 200_000_000
ATTITUDE_MAX_AGE_NS = 1_000_000_000
# what to tell the user when the autopilot refuses a rate request for these messages
RATE_HINTS = {
    "WHEEL_DISTANCE": "ArduPilot streams it only with wheel encoders (WENC_TYPE) in its EXTRA1 group "
    "(MAVn_EXTRA1, SRn_EXTRA1 before 4.7): docs/mavlink.md §3",
}

# the messages requested with MAV_CMD_SET_MESSAGE_INTERVAL, and the default rates [Hz], each one
# that ArduPilot Rover grants with its default SCHED_LOOP_RATE of 50 Hz (measured on the SITL build,
# docs/mavlink.md §3: it refuses an interval under 1.25 loop periods, so ATTITUDE at 41 Hz and more).
# Not WHEEL_DISTANCE: ArduPilot has no interval for it (it refuses every request); it streams in
# the EXTRA1 group when wheel encoders are configured, and the link uses it when it comes.
DEFAULT_RATES_HZ: dict[str, float] = {
    "ATTITUDE": 25.0,
    "LOCAL_POSITION_NED": 10.0,
    "SERVO_OUTPUT_RAW": 10.0,
    "RC_CHANNELS": 5.0,
    "SYSTEM_TIME": 1.0,
    "EKF_STATUS_REPORT": 2.0,
}

# every counter of stats(), in its order; the pose role counts its own in this dict too
COUNTERS = (
    "rx_messages",
    "bad_data",
    "heartbeats_sent",
    *POSE_COUNTERS,
    "timesync_requests",
    "timesync_replies",
    "timesync_samples",
    "origins_sent",
    "origin_requests",
    "yaw_align_requests",
    "rate_requests",
    "rates_accepted",
    "rates_refused",
    "rates_unacknowledged",
    "autopilot_reboots",
    "link_losses",
    "odometry",
    "drops",
    "stamped_by_arrival",
    "wheel_wraps",
    "wheel_intervals_rejected",
    "attitude_extrapolated",
    "no_attitude",
    "tx_errors",
    "bad_values",
    "rejected_source",
    "before_heartbeat",
    "timesync_replies_limited",
)


def _mav() -> Any:
    return mavutil.mavlink


def mavlink_module() -> Any:
    """The generated ardupilotmega MAVLink 2 module (for the mock autopilot and tests)."""
    return _mav()


def read_signing_key(path: str) -> bytes:
    """32-byte MAVLink2 signing key from a file that only its owner may read (mode 0600)."""
    try:
        st = os.stat(path)
        with open(path, "rb") as fh:
            key = fh.read()
    except OSError as exc:
        raise DriverError(f"signing key {path!r}: cannot read: {exc}") from exc
    if st.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise DriverError(f"signing key {path!r}: mode {stat.S_IMODE(st.st_mode):04o}, expected 0600")
    if len(key) != 32:
        raise DriverError(f"signing key {path!r}: expected 32 bytes, got {len(key)}")
    return key


@dataclass(frozen=True, slots=True)
class MavlinkOptions:
    """Every option of the MAVLink link with its default (URL query keys have the same names)."""

    mode: str = "out"  # udp only: "out" (robotd sends first) or "in" (robotd listens)
    allow_remote: bool = False  # allow mode=in on a non-loopback address
    baud: int = 921600  # serial only
    sysid: int = 0  # 0: use the autopilot's system id (learned from its heartbeat; 1 until then)
    compid: int = MAV_COMP_ID_VIO
    message: str = "odometry"  # or "vision_position_estimate"
    track_width_m: float = 0.0  # WHEEL_DISTANCE needs it (> 0) to give a yaw rate; 0 = forward speed only
    wheel_left: int = 0  # WHEEL_DISTANCE indices (WENC_POS_Y < 0 is the left wheel)
    wheel_right: int = 1
    yaw_rate_source: str = "attitude"  # "attitude" (gyro) or "wheels"
    steering_channel: int = 1  # RCMAP defaults for Rover
    throttle_channel: int = 3
    link_timeout_s: float = 3.0
    heartbeat_hz: float = 1.0
    timesync_hz: float = 1.0
    timesync_reply_hz: float = 20.0  # at most this many TIMESYNC replies a second (PX4 asks at up to 10 Hz)
    # ATTITUDE's roll and pitch (the autopilot's gravity-referenced AHRS) go with each odometry
    # sample as the direction of gravity, with this σ; 0: not used
    gravity_sigma_deg: float = 2.0
    bind: str = ""  # udp mode=out: local address ("" = the one that routes to the target)
    request_rates: bool = True
    rates_hz: dict[str, float] = field(default_factory=lambda: dict(DEFAULT_RATES_HZ))
    origin: tuple[float, float, float] | None = None  # (lat_deg, lon_deg, alt_m)
    signing_key: str | None = None  # path of a 32-byte key file, mode 0600
    allow_unsigned: bool = False
    # smallest variances in pose_covariance: only keep zeros out (ArduPilot PR 8730); 1 mm and
    # 0.06°, far below the autopilots' own floors (VISO_*_M_NSE, EKF2_EV*_NOISE: docs/mavlink.md §8)
    floor_pos_m2: float = 1e-6
    floor_ang_rad2: float = 1e-6
    queue_size: int = 512
    # when the autopilot reports its vision yaw off its own heading before arming ("VisOdom: yaw
    # diff") and the vehicle stands still: ask it to align them (aux function 80), at most every
    # ALIGN_INTERVAL_S (docs/mavlink.md §6)
    align_yaw: bool = True


_SCALARS: dict[str, type] = {
    "mode": str,
    "allow_remote": bool,
    "baud": int,
    "sysid": int,
    "compid": int,
    "message": str,
    "track_width_m": float,
    "wheel_left": int,
    "wheel_right": int,
    "yaw_rate_source": str,
    "steering_channel": int,
    "throttle_channel": int,
    "link_timeout_s": float,
    "heartbeat_hz": float,
    "timesync_hz": float,
    "timesync_reply_hz": float,
    "gravity_sigma_deg": float,
    "bind": str,
    "request_rates": bool,
    "signing_key": str,
    "allow_unsigned": bool,
    "floor_pos_m2": float,
    "floor_ang_rad2": float,
    "queue_size": int,
    "align_yaw": bool,
}


def _to_bool(v: Any) -> bool:
    if isinstance(v, bool):
        return v
    s = str(v).strip().lower()
    if s in ("1", "true", "yes", "on"):
        return True
    if s in ("0", "false", "no", "off"):
        return False
    raise ValueError(v)


def parse_mavlink_url(url: str, **options: Any) -> tuple[str, MavlinkOptions]:
    """URL + options -> (pymavlink connection string, options). Errors name the URL and the key."""
    parts = urlsplit(url)
    values: dict[str, Any] = dict(parse_qsl(parts.query))
    values.update(options)
    kw: dict[str, Any] = {}
    for key, raw in values.items():
        if key == "origin":
            try:
                o = raw.split(",") if isinstance(raw, str) else list(raw)
                lat, lon, alt = (float(x) for x in o)
            except (TypeError, ValueError) as exc:
                raise DriverError(f"{url!r}: origin={raw!r}: expected lat_deg,lon_deg,alt_m") from exc
            if not (-90 <= lat <= 90 and -180 <= lon <= 180):
                raise DriverError(f"{url!r}: origin={raw!r}: latitude/longitude out of range")
            kw["origin"] = (lat, lon, alt)
        elif key == "rates_hz":
            if not isinstance(raw, dict):
                raise DriverError(f"{url!r}: rates_hz: expected a dict of message name -> Hz, got {raw!r}")
            kw["rates_hz"] = {str(k).upper(): float(v) for k, v in raw.items()}
        elif key in _SCALARS:
            try:
                kw[key] = _to_bool(raw) if _SCALARS[key] is bool else _SCALARS[key](raw)
            except (TypeError, ValueError) as exc:
                raise DriverError(f"{url!r}: option {key}={raw!r}: expected {_SCALARS[key].__name__}") from exc
        else:
            known = ", ".join(sorted([*_SCALARS, "origin", "rates_hz"]))
            raise DriverError(f"{url!r}: unknown option {key!r}; known: {known}")
    opts = MavlinkOptions(**kw)
    if opts.message not in ("odometry", "vision_position_estimate"):
        raise DriverError(f"{url!r}: message={opts.message!r}, expected 'odometry' or 'vision_position_estimate'")
    if opts.yaw_rate_source not in ("attitude", "wheels"):
        raise DriverError(f"{url!r}: yaw_rate_source={opts.yaw_rate_source!r}, expected 'attitude' or 'wheels'")
    if not 0 <= opts.sysid <= 255 or not 1 <= opts.compid <= 255:
        raise DriverError(f"{url!r}: sysid {opts.sysid} / compid {opts.compid} out of range")
    for name in ("floor_pos_m2", "floor_ang_rad2"):
        v = getattr(opts, name)
        if not (math.isfinite(v) and v > 0):
            raise DriverError(f"{url!r}: {name}={v:g}: expected a finite variance > 0")
    if not (math.isfinite(opts.gravity_sigma_deg) and 0 <= opts.gravity_sigma_deg <= 45):
        raise DriverError(f"{url!r}: gravity_sigma_deg={opts.gravity_sigma_deg}: expected 0 (off) to 45")
    if not (math.isfinite(opts.timesync_reply_hz) and opts.timesync_reply_hz >= 0):
        raise DriverError(f"{url!r}: timesync_reply_hz={opts.timesync_reply_hz}: expected a number >= 0")
    if opts.bind:
        try:
            ipaddress.IPv4Address(opts.bind)
        except ValueError as exc:
            raise DriverError(f"{url!r}: bind={opts.bind!r}: expected an IPv4 address") from exc
    for name in opts.rates_hz:
        if not hasattr(_mav(), f"MAVLINK_MSG_ID_{name}"):
            raise DriverError(f"{url!r}: rates_hz: unknown message {name!r}")
    if parts.scheme == "mavlink+udp":
        host, port = parts.hostname, parts.port
        if not host or port is None:
            raise DriverError(f"{url!r}: expected mavlink+udp://HOST:PORT")
        if opts.mode not in ("in", "out"):
            raise DriverError(f"{url!r}: mode={opts.mode!r}, expected 'in' or 'out'")
        if opts.mode == "in" and not opts.allow_remote and not is_loopback(host):
            raise DriverError(f"{url!r}: refusing to listen on {host}: loopback only unless allow_remote=1")
        return f"udp{opts.mode}:{host}:{port}", opts
    if parts.scheme == "mavlink+serial":
        if not parts.path:
            raise DriverError(f"{url!r}: expected mavlink+serial:///dev/ttyX?baud=921600")
        return parts.path, opts
    raise DriverError(f"{url!r}: expected mavlink+udp:// or mavlink+serial://")


class _DatagramSource:
    """Replaces a pymavlink UDP connection's ``recv`` so that every message it parses is known to
    come from one datagram's sender (``addr``): the rest of a datagram is parsed before the next one
    is read, and a partial message left at a datagram's end is dropped, never glued to the next
    sender's bytes. On a listening socket (mode=in) only the ``allowed`` sender (anyone until the
    autopilot is known) becomes a client that robotd sends to."""

    def __init__(self, conn: Any) -> None:
        self.conn = conn
        self.addr: tuple[str, int] | None = None
        self.allowed: tuple[str, int] | None = None
        self._mark: tuple[int, int, int] | None = None

    def recv(self, n: int | None = None) -> bytes:
        mav = self.conn.mav
        mark = (id(mav.buf), mav.buf_index, len(mav.buf))
        if mav.buf_len() > 0 and mark != self._mark:
            self._mark = mark  # the last parse consumed bytes: parse the rest of this datagram first
            return b""
        try:
            data, addr = self.conn.port.recvfrom(65535)
        except OSError as exc:
            if exc.errno in (errno.EAGAIN, errno.EWOULDBLOCK, errno.ECONNREFUSED, errno.EINTR):
                return b""
            raise
        mav.buf, mav.buf_index = bytearray(), 0
        mav.expected_length = _mav().HEADER_LEN_V1 + 2
        self._mark = None
        self.addr = addr
        if self.conn.udp_server and (self.allowed is None or addr == self.allowed):
            self.conn.clients.add(addr)
            self.conn.clients_last_alive[addr] = time.time()
        return bytes(data)

    def lock_to(self, addr: tuple[str, int] | None) -> None:
        """From now on only ``addr`` is a client (mode=in); None: anyone again."""
        self.allowed = addr
        if self.conn.udp_server and addr is not None:
            self.conn.clients.intersection_update({addr})
            for a in [a for a in self.conn.clients_last_alive if a != addr]:
                del self.conn.clients_last_alive[a]


def _connect(url: str, device: str, opts: MavlinkOptions, **kw: Any) -> tuple[Any, _DatagramSource | None]:
    """pymavlink's connection for ``device``; UDP ``out`` sockets are bound and connected to the
    target (module docstring), UDP sockets get a :class:`_DatagramSource`."""
    try:
        conn = mavutil.mavlink_connection(device, **kw)
    except Exception as exc:  # pymavlink raises OSError, SerialException, ValueError...
        raise DriverError(f"{url!r}: cannot open {device}: {exc}") from exc
    if not device.startswith("udp"):
        return conn, None
    if device.startswith("udpout:"):
        host, port = device[len("udpout:") :].rsplit(":", 1)
        try:
            if opts.bind:
                conn.port.bind((opts.bind, 0))
            # a connected UDP socket takes the source address that routes to the target and is
            # delivered datagrams from the target's address only
            conn.port.connect((socket.gethostbyname(host), int(port)))
        except OSError as exc:
            conn.close()
            raise DriverError(f"{url!r}: cannot bind/connect the UDP socket to {host}:{port}: {exc}") from exc
    src = _DatagramSource(conn)
    conn.recv = src.recv
    return conn, src


class _AutopilotClock:
    """Our TIMESYNC requests, the offset filter over their replies, and autopilot stamps mapped
    onto the host monotonic clock. Counts in the link's counter dict."""

    def __init__(self, counters: dict[str, int]) -> None:
        self.filter = TimesyncFilter()
        self._pending: dict[int, int] = {}  # our ts1 -> send time (ns)
        self._c = counters

    def request(self, mav: Any) -> None:
        """Send one request on ``mav`` (pymavlink's MAVLink object; transmit thread)."""
        ts1 = time.monotonic_ns()
        # keep a few outstanding requests only; a lost reply must not grow the table
        if len(self._pending) > 16:
            self._pending.pop(next(iter(self._pending)))
        self._pending[ts1] = ts1
        mav.timesync_send(0, ts1)
        self._c["timesync_requests"] += 1

    def on_reply(self, ts1: int, tc1: int, t_arrival_ns: int) -> None:
        """A reply to one of our requests (receive thread); unknown ``ts1`` values are ignored."""
        t0 = self._pending.pop(ts1, None)
        if t0 is not None and self.filter.add(t0, t_arrival_ns, tc1):
            self._c["timesync_samples"] += 1

    def to_host(self, t_ap_ns: int, t_arrival_ns: int) -> int:
        """Autopilot boot-clock stamp [ns] -> host monotonic [ns], never after its arrival."""
        t = self.filter.autopilot_to_host(t_ap_ns)
        # no offset yet, or an absurd mapping (stale offset): fall back to the arrival time
        if t is None or not (t_arrival_ns - 2_000_000_000 < t <= t_arrival_ns + 50_000_000):
            self._c["stamped_by_arrival"] += 1
            return t_arrival_ns
        # within the offset's error (half a round trip) a stamp may land after its arrival: clamp
        return min(t, t_arrival_ns)


class MavlinkVehicle(QueuedVehicleLink):
    """VehicleLink to an ArduPilot/PX4 autopilot. Use as a context manager."""

    def __init__(self, url: str, **options: Any) -> None:
        self.device, self.opts = parse_mavlink_url(url, **options)
        self._key = read_signing_key(self.opts.signing_key) if self.opts.signing_key else None
        self._conn: Any = None
        self._wake = threading.Event()
        self._lock = threading.Lock()  # guards the shared state below
        self._rx: threading.Thread | None = None
        self._tx: threading.Thread | None = None
        self._outbox: deque[tuple[str, Any]] = deque()
        self._ap_sysid: int | None = None
        self._ap_compid = 1
        self._ap_addr: tuple[str, int] | None = None  # where the autopilot's heartbeat came from (UDP)
        self._src: _DatagramSource | None = None
        self._boot = BootClock()
        self._ts_limit = RateLimit(self.opts.timesync_reply_hz)
        self._linkstate = LinkState(
            LinkStateParams(stale_after_s=min(1.5, self.opts.link_timeout_s), lost_after_s=self.opts.link_timeout_s)
        )
        self._last_ap_hb_mono: float | None = None
        self._link_up = False
        # recent ATTITUDEs (t_ns, rpy, body rates), the newest last: at 25 Hz, 2.5 s of them
        self._attitudes: deque[tuple[int, np.ndarray, np.ndarray]] = deque(maxlen=64)
        self._rates = RateRequests()  # guarded by _lock (ACKs arrive on the receive thread)
        self._wheels: tuple[int, float, float] | None = None  # (t_ap_us, s_left, s_right)
        self._last_wheel_mono = -math.inf
        self.ekf_flags: int | None = None
        self.origin_confirmed = False
        self._origin_heard = False  # a GPS_GLOBAL_ORIGIN with our origin since the last check
        self.armed: bool | None = None  # from the autopilot's heartbeat
        self._last_align_mono = -math.inf
        self.last_visodom_text = ""
        self._next_origin_check = math.inf
        self.c: dict[str, int] = dict.fromkeys(COUNTERS, 0)
        self._clock = _AutopilotClock(self.c)
        self.rx_types: dict[str, int] = {}
        super().__init__(url, self.opts.queue_size, self.c)
        floors = CovarianceFloors(self.opts.floor_pos_m2, self.opts.floor_ang_rad2)
        # the pose-out role: shares this link's connection, transmit thread and counters
        self._autopilot = MavlinkAutopilot(url, self.opts.message, floors, self.c, self._wake)

    # -- lifecycle -----------------------------------------------------------------------------
    def open(self) -> None:
        sysid = self.opts.sysid or 1
        kw: dict[str, Any] = {"source_system": sysid, "source_component": self.opts.compid, "dialect": DIALECT}
        if not self.device.startswith("udp"):
            kw.update(baud=self.opts.baud, autoreconnect=True)
        self._conn, self._src = _connect(self.url, self.device, self.opts, **kw)
        self._linkstate.opened(time.monotonic_ns())
        if not hasattr(self._conn.mav, "odometry_send"):
            raise DriverError(f"{self.url!r}: pymavlink loaded MAVLink 1 bindings (MAVLINK20 set too late)")
        if self._key is not None:
            allow = (lambda _mav, _msgid: True) if self.opts.allow_unsigned else (lambda _mav, _msgid: False)
            self._conn.setup_signing(self._key, sign_outgoing=True, allow_unsigned_callback=allow)
        self._stop.clear()
        self._rx = threading.Thread(target=self._rx_loop, name="mavlink-rx", daemon=True)
        self._tx = threading.Thread(target=self._tx_loop, name="mavlink-tx", daemon=True)
        self._rx.start()
        self._tx.start()

    def _release(self) -> None:
        self._wake.set()
        for t in (self._tx, self._rx):
            if t is not None:
                t.join(timeout=2.0)
        self._rx = self._tx = None
        if self._conn is not None:
            try:
                self._conn.close()
            except OSError:
                pass
            self._conn = None
        self._linkstate.closed()

    # -- public API ----------------------------------------------------------------------------
    @property
    def autopilot(self) -> MavlinkAutopilot:
        """The pose sink (``send_pose``, ``set_health``) on this link's connection."""
        return self._autopilot

    @property
    def link_up(self) -> bool:
        return self._link_up

    @property
    def autopilot_sysid(self) -> int | None:
        return self._ap_sysid

    def autopilot_to_host_ns(self, t_ap_ns: int) -> int | None:
        """Autopilot boot-clock time [ns] on the host monotonic clock, once TIMESYNC has a sample."""
        return self._clock.filter.autopilot_to_host(t_ap_ns)

    def stats(self) -> dict[str, Any]:
        link = self._linkstate.stats(time.monotonic_ns())  # state from the autopilot's recent messages
        if self._ap_sysid is not None and not self._link_up:
            link["state"] = LOST  # its heartbeat timed out
        return {
            **self.c,
            "link_up": self._link_up,
            **link,
            "autopilot_sysid": self._ap_sysid,
            "autopilot_compid": self._ap_compid if self._ap_sysid is not None else None,
            "autopilot_address": None if self._ap_addr is None else f"{self._ap_addr[0]}:{self._ap_addr[1]}",
            "reboot_candidates": self._boot.mismatches,
            "timesync_offset_ns": self._clock.filter.offset_ns,
            "timesync_rtt_ns": self._clock.filter.rtt_ns,
            "origin_confirmed": self.origin_confirmed,
            "armed": self.armed,
            "last_visodom_text": self.last_visodom_text,
            "ekf_flags": self.ekf_flags,
            **self._rate_stats(),
            "queued": len(self._queue),
            "rx_types": dict(self.rx_types),
        }

    # -- receive -------------------------------------------------------------------------------
    def _rx_loop(self) -> None:
        conn = self._conn
        while not self._stop.is_set():
            try:
                msg = conn.recv_match(blocking=True, timeout=0.1)
            except (OSError, ValueError) as exc:
                if self._stop.is_set():
                    break
                logger.warning("%s: receive failed: %s", self.url, exc)
                self._stop.wait(0.2)
                continue
            if msg is None:
                continue
            self._dispatch(msg, time.monotonic_ns(), self._src.addr if self._src is not None else None)

    def _dispatch(self, msg: Any, t_ns: int, addr: tuple[str, int] | None) -> None:
        """One received message (arrival ``t_ns``, UDP sender ``addr``) to its handler, if it is
        the autopilot's; never raises on what a sender can put in a message (counted instead)."""
        kind = msg.get_type()
        if kind == "BAD_DATA":
            # includes signature failures and unsigned packets on a signed link
            self.c["bad_data"] += 1
            self._linkstate.record(t_ns, bad=1)
            return
        self.c["rx_messages"] += 1
        self.rx_types[kind] = self.rx_types.get(kind, 0) + 1
        handler = getattr(self, f"_on_{kind.lower()}", None)
        if handler is None:
            return
        accepted: bool | None
        if kind == "HEARTBEAT":
            accepted = self._on_heartbeat(msg, t_ns, addr)
            if accepted is None:
                return
        elif not self._from_autopilot(msg, addr):
            accepted = False  # vehicle data from anyone but the autopilot is not vehicle data
        else:
            try:
                handler(msg, t_ns)
                accepted = True
            except (RobotdError, ValueError, TypeError, IndexError, ArithmeticError, OverflowError) as exc:
                # a message with values we cannot use (NaN, too few wheels): count, keep reading
                self.c["bad_values"] += 1
                self._linkstate.record(t_ns, bad=1)
                logger.debug("%s: bad %s ignored: %s", self.url, kind, exc)
                return
        if accepted:
            self._linkstate.record(t_ns, good=1)
        elif self._ap_sysid is None:
            self.c["before_heartbeat"] += 1  # nothing is vehicle data before the autopilot is known
        else:
            self.c["rejected_source"] += 1
            n = self.c["rejected_source"]
            if n == 1 or math.log10(n).is_integer():
                logger.warning(
                    "%s: %s from system %d component %d%s is not the autopilot's: ignored (%d so far)",
                    self.url,
                    kind,
                    msg.get_srcSystem(),
                    msg.get_srcComponent(),
                    "" if addr is None else f" at {addr[0]}:{addr[1]}",
                    n,
                )

    def _from_autopilot(self, msg: Any, addr: tuple[str, int] | None) -> bool:
        """The autopilot's system and component id (from its heartbeat) and, over UDP, its address."""
        if self._ap_sysid is None:
            return False
        if msg.get_srcSystem() != self._ap_sysid or msg.get_srcComponent() != self._ap_compid:
            return False
        return self._ap_addr is None or addr == self._ap_addr

    def _on_heartbeat(self, msg: Any, t_ns: int, addr: tuple[str, int] | None = None) -> bool | None:
        """True when the heartbeat is the autopilot's (the first one defines who that is; another
        sender may take over only once the known autopilot's link is lost), False when it claims a
        vehicle but is not ours, None for ground stations and other companions."""
        m = _mav()
        if msg.autopilot == m.MAV_AUTOPILOT_INVALID or msg.type in (m.MAV_TYPE_GCS, m.MAV_TYPE_ONBOARD_CONTROLLER):
            return None  # ground stations and other companions: not the vehicle, nothing wrong either
        src, comp = msg.get_srcSystem(), msg.get_srcComponent()
        if self.opts.sysid and src != self.opts.sysid:
            return False  # a configured vehicle id: other vehicles on the network are not ours
        if self._ap_sysid is None or (not self._link_up and not self._from_autopilot(msg, addr)):
            if self._ap_sysid is not None:
                logger.warning("%s: autopilot link was lost; taking this heartbeat's sender as the autopilot", self.url)
            first = self._ap_sysid is None
            self._ap_sysid, self._ap_compid, self._ap_addr = src, comp, addr
            if self._src is not None:
                self._src.lock_to(addr)
            if not self.opts.sysid:
                self._conn.mav.srcSystem = src  # speak as part of the vehicle
            where = "" if addr is None else f" at {addr[0]}:{addr[1]}"
            logger.info("%s: autopilot sysid %d compid %d%s", self.url, src, comp, where)
            self._boot = BootClock()
            if first:
                self._outbox_put("vehicle_setup", "first heartbeat")
        elif not self._from_autopilot(msg, addr):
            return False
        self._last_ap_hb_mono = time.monotonic()
        self.armed = bool(msg.base_mode & m.MAV_MODE_FLAG_SAFETY_ARMED)
        self._boot.heartbeat(t_ns)
        if not self._link_up:
            self._link_up = True
            logger.info("%s: autopilot link up", self.url)
        return True

    def _on_system_time(self, msg: Any, t_ns: int) -> None:
        # a reboot is a new boot clock seen consistently, with heartbeats, while the old one fell
        # silent (drivers.mavlink_guard.BootClock; docs/mavlink.md §7): never one SYSTEM_TIME
        if self._boot.observe(int(msg.time_boot_ms), t_ns):
            self.c["autopilot_reboots"] += 1
            logger.warning("%s: autopilot rebooted (time_boot_ms now %d)", self.url, int(msg.time_boot_ms))
            self._clock.filter.reset()
            with self._lock:
                self._wheels = None
            self.origin_confirmed = False
            self._outbox_put("vehicle_setup", "reboot")

    def _on_timesync(self, msg: Any, t_ns: int) -> None:
        if msg.tc1 == 0:
            # a request (PX4 needs 500 answered round trips before it uses our time_usec); a flood
            # of them gets a bounded number of replies
            if self._ts_limit.allow(t_ns):
                self._outbox_put("timesync_reply", int(msg.ts1))
            else:
                self.c["timesync_replies_limited"] += 1
            return
        self._clock.on_reply(int(msg.ts1), int(msg.tc1), t_ns)

    def _on_attitude(self, msg: Any, t_ns: int) -> None:
        t = self._clock.to_host(int(msg.time_boot_ms) * 1_000_000, t_ns)
        rpy = np.array([msg.roll, msg.pitch, msg.yaw], dtype=float)
        rates = np.array([msg.rollspeed, msg.pitchspeed, msg.yawspeed], dtype=float)
        if not (np.all(np.isfinite(rpy)) and np.all(np.isfinite(rates))):
            raise ValueError(f"ATTITUDE not finite: rpy {rpy}, rates {rates}")
        self._attitudes.append((t, rpy, rates))

    def _attitude_at(self, t_ns: int, max_age_ns: int = ATTITUDE_FRESH_NS) -> tuple[np.ndarray, np.ndarray, int] | None:
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

    def _on_wheel_distance(self, msg: Any, t_ns: int) -> None:
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
        t = self._clock.to_host((t_us * 1000) - int(dt * 5e8), t_ns)
        a = self._attitude_at(t)
        att = None if a is None else (a[0], a[1])
        if o.yaw_rate_source == "attitude" and att is not None:
            rates = att[1]
        elif math.isfinite(w_wheels):
            rates = np.array([0.0, 0.0, w_wheels])
        elif att is not None:
            rates = att[1]
        else:
            rates = np.zeros(3)  # forward speed only; the motion model inflates yaw noise
        self._emit(Odometry(t, np.array([v, 0.0, 0.0]), np.asarray(rates, float), "mavlink", *self._gravity(att)))

    def _unwrap_m(self, d: float) -> float:
        if d > WHEEL_WRAP_M:
            self.c["wheel_wraps"] += 1
            return d - 2 * WHEEL_WRAP_M
        if d < -WHEEL_WRAP_M:
            self.c["wheel_wraps"] += 1
            return d + 2 * WHEEL_WRAP_M
        return d

    def _on_local_position_ned(self, msg: Any, t_ns: int) -> None:
        if time.monotonic() - self._last_wheel_mono < 1.0:
            return  # wheel odometry flows: it is the better velocity source
        t = self._clock.to_host(int(msg.time_boot_ms) * 1_000_000, t_ns)
        v_ned = np.array([msg.vx, msg.vy, msg.vz], dtype=float)
        if not np.all(np.isfinite(v_ned)):
            raise ValueError(f"LOCAL_POSITION_NED velocity not finite: {v_ned}")
        a = self._attitude_at(t, ATTITUDE_MAX_AGE_NS)
        if a is None:
            self.c["no_attitude"] += 1  # cannot rotate NED into the body frame without an attitude
            return
        if a[2] > ATTITUDE_FRESH_NS:
            self.c["attitude_extrapolated"] += 1
        att = (a[0], a[1])
        # NED and the body FRD frame share the ZYX Euler convention: v_R = R(rpy)^T v_NED
        v_R = euler_to_R(att[0]).T @ v_ned
        self._emit(Odometry(t, v_R, att[1].copy(), "mavlink", *self._gravity(att)))

    def _gravity(self, att: tuple[np.ndarray, np.ndarray] | None) -> tuple[None, np.ndarray | None, float]:
        """(cov, gravity_R, σ) of an Odometry: the direction of gravity in the body frame from the
        autopilot's roll and pitch, R(rpy)^T (0, 0, 1), which does not depend on its yaw."""
        sigma = math.radians(self.opts.gravity_sigma_deg)
        if att is None or sigma <= 0:
            return None, None, 0.0
        roll, pitch = float(att[0][0]), float(att[0][1])
        g = np.array([-math.sin(pitch), math.sin(roll) * math.cos(pitch), math.cos(roll) * math.cos(pitch)])
        return None, g, sigma

    def _on_servo_output_raw(self, msg: Any, t_ns: int) -> None:
        o = self.opts
        t = self._clock.to_host(int(msg.time_usec) * 1000, t_ns)
        thr = getattr(msg, f"servo{o.throttle_channel}_raw", 0)
        ste = getattr(msg, f"servo{o.steering_channel}_raw", 0)
        _check_pwm("SERVO_OUTPUT_RAW", thr, ste)
        if thr and ste:
            self._controls = ControlSample(t, (thr - 1500) / 500.0, (ste - 1500) / 500.0, "SERVO_OUTPUT_RAW")

    def _on_rc_channels(self, msg: Any, t_ns: int) -> None:
        if self._controls is not None and self._controls.source == "SERVO_OUTPUT_RAW":
            return  # commanded outputs beat pilot sticks
        o = self.opts
        t = self._clock.to_host(int(msg.time_boot_ms) * 1_000_000, t_ns)
        thr = getattr(msg, f"chan{o.throttle_channel}_raw", 0)
        ste = getattr(msg, f"chan{o.steering_channel}_raw", 0)
        if thr and ste and thr != 0xFFFF and ste != 0xFFFF:
            _check_pwm("RC_CHANNELS", thr, ste)
            self._controls = ControlSample(t, (thr - 1500) / 500.0, (ste - 1500) / 500.0, "RC_CHANNELS")

    def _on_ekf_status_report(self, msg: Any, t_ns: int) -> None:
        self.ekf_flags = int(msg.flags)

    def _on_gps_global_origin(self, msg: Any, t_ns: int) -> None:
        o = self.opts.origin
        if o is None:
            self.origin_confirmed = True
            return
        # ours, to the message's resolution (1e-7 deg); another origin is not a confirmation
        ours = (round(o[0] * 1e7), round(o[1] * 1e7))
        match = (int(msg.latitude), int(msg.longitude)) == ours
        self.origin_confirmed = match
        self._origin_heard = self._origin_heard or match
        if not match:
            logger.warning(
                "%s: the autopilot's EKF origin is (%.7f, %.7f), not the configured one",
                self.url,
                msg.latitude * 1e-7,
                msg.longitude * 1e-7,
            )

    def _on_statustext(self, msg: Any, t_ns: int) -> None:
        """ArduPilot's pre-arm "VisOdom: yaw diff …" (its vision yaw, rotated onto its own heading
        when it aligned them, no longer agrees with that heading): once the vehicle has stood
        still for ALIGN_STILL_S, robotd asks it to align again (MAV_CMD_DO_AUX_FUNCTION, function
        80), at most every ALIGN_INTERVAL_S and never while armed; an alignment taken while the
        rover turned, or before the compass settled, is what left it off (docs/mavlink.md §6)."""
        text = str(msg.text)
        if "VisOdom:" not in text:
            return
        self.last_visodom_text = text
        if "yaw diff" not in text or not self.opts.align_yaw or self.armed is not False:
            return
        now = time.monotonic()
        if now - self._last_align_mono < ALIGN_INTERVAL_S:
            return
        if self._autopilot.still_for_s() < ALIGN_STILL_S:
            return
        self._last_align_mono = now
        logger.info(
            "%s: the autopilot says %r and the vehicle is still: asking it to align its vision yaw "
            "to its own heading (aux function %d)",
            self.url,
            text,
            AUX_FUNCTION_VISO_ALIGN,
        )
        self._outbox_put("align_yaw", text)

    def _on_command_ack(self, msg: Any, t_ns: int) -> None:
        """An answer to one of our SET_MESSAGE_INTERVAL requests (the outstanding one: the ACK
        does not say which message it concerns, drivers.mavlink_guard.RateRequests)."""
        m = _mav()
        if msg.command != m.MAV_CMD_SET_MESSAGE_INTERVAL:
            return
        # MAVLink 2 ACKs name whom they answer (0 when not filled in): another requester's is not ours
        mav = self._conn.mav if self._conn is not None else None
        ours = (0, mav.srcSystem if mav is not None else 0), (0, self.opts.compid)
        if getattr(msg, "target_system", 0) not in ours[0] or getattr(msg, "target_component", 0) not in ours[1]:
            return
        with self._lock:
            outcome = self._rates.on_ack(int(msg.result))
            self._count_rates()
        if outcome is not None:
            self._log_rate(outcome)
            self._wake.set()  # the next request may leave now

    def _outbox_put(self, kind: str, arg: Any) -> None:
        with self._lock:
            self._outbox.append((kind, arg))
        self._wake.set()

    # -- transmit ------------------------------------------------------------------------------
    def _tx_loop(self) -> None:
        now = time.monotonic()
        next_hb = now
        next_ts = now + 0.05
        while not self._stop.is_set():
            now = time.monotonic()
            try:
                if now >= next_hb:
                    self._send_heartbeat()
                    next_hb = max(next_hb + 1.0 / self.opts.heartbeat_hz, now)
                if self.opts.timesync_hz > 0 and now >= next_ts:
                    self._clock.request(self._conn.mav)
                    next_ts = max(next_ts + 1.0 / self.opts.timesync_hz, now)
                while True:
                    with self._lock:
                        item = self._outbox.popleft() if self._outbox else None
                    if item is None:
                        break
                    self._do(item)
                self._send_rate_request()
                self._autopilot.send_pending(self._conn.mav)
                if now >= self._next_origin_check:
                    self._check_origin(now)
            except (OSError, ValueError) as exc:
                self.c["tx_errors"] += 1
                logger.warning("%s: send failed: %s", self.url, exc)
            self._check_link()
            wait = min(next_hb, next_ts if self.opts.timesync_hz > 0 else next_hb) - time.monotonic()
            self._wake.wait(max(0.0, min(wait, 0.1)))
            self._wake.clear()

    def _check_link(self) -> None:
        hb = self._last_ap_hb_mono
        if self._link_up and (hb is None or time.monotonic() - hb > self.opts.link_timeout_s):
            self._link_up = False
            self.c["link_losses"] += 1
            logger.warning("%s: autopilot link lost (no heartbeat for %.1f s)", self.url, self.opts.link_timeout_s)

    def _send_heartbeat(self) -> None:
        m = _mav()
        self._conn.mav.heartbeat_send(
            m.MAV_TYPE_ONBOARD_CONTROLLER, m.MAV_AUTOPILOT_INVALID, 0, 0, self._autopilot.system_status()
        )
        self.c["heartbeats_sent"] += 1

    def _do(self, item: tuple[str, Any]) -> None:
        kind, arg = item
        if kind == "timesync_reply":
            self._conn.mav.timesync_send(time.monotonic_ns(), arg)
            self.c["timesync_replies"] += 1
        elif kind == "align_yaw":
            m = _mav()
            self._conn.mav.command_long_send(
                self._ap_sysid or 1,
                self._ap_compid,
                m.MAV_CMD_DO_AUX_FUNCTION,
                0,
                AUX_FUNCTION_VISO_ALIGN,
                2,  # switch high
                0,
                0,
                0,
                0,
                0,
            )
            self.c["yaw_align_requests"] += 1
        elif kind == "vehicle_setup":
            self._send_origin()
            if self.opts.request_rates:
                with self._lock:
                    self._rates.start(self.opts.rates_hz)

    def _check_origin(self, now: float) -> None:
        """Keep the EKF origin set: ArduPilot's EKF3 forgets an origin set before it initialised
        (measured in SITL: "origin set", then the EKF started, then no origin, and a mission in
        AUTO waits for one for ever). Every ORIGIN_CHECK_S robotd asks for GPS_GLOBAL_ORIGIN
        (MAV_CMD_REQUEST_MESSAGE); when no matching one came since the last check, the origin is
        sent again (``origins_sent`` counts every send)."""
        self._next_origin_check = now + ORIGIN_CHECK_S
        if not self._link_up or self._ap_sysid is None:
            return
        if not self._origin_heard:
            self.origin_confirmed = False
            self._send_origin()
        self._origin_heard = False
        m = _mav()
        self._conn.mav.command_long_send(
            self._ap_sysid,
            self._ap_compid,
            m.MAV_CMD_REQUEST_MESSAGE,
            0,
            m.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN,
            0,
            0,
            0,
            0,
            0,
            0,
        )
        self.c["origin_requests"] += 1

    def _send_origin(self) -> None:
        if self.opts.origin is None or self._ap_sysid is None:
            return
        if self._next_origin_check == math.inf:
            self._next_origin_check = time.monotonic() + ORIGIN_CHECK_S
        lat, lon, alt = self.opts.origin
        self._conn.mav.set_gps_global_origin_send(
            self._ap_sysid, round(lat * 1e7), round(lon * 1e7), round(alt * 1000), time.monotonic_ns() // 1000
        )
        self.c["origins_sent"] += 1
        logger.info("%s: EKF origin sent (%.7f, %.7f, %.2f m)", self.url, lat, lon, alt)

    def _send_rate_request(self) -> None:
        """The next SET_MESSAGE_INTERVAL request, once the previous one was answered (or timed out)."""
        with self._lock:
            req, timed_out = self._rates.next_request(time.monotonic_ns())
            done = self._rates.round_finished()
            self._count_rates()
        if timed_out is not None:
            self._log_rate(timed_out)
        if done:
            self._log_rates_done()
        if req is None:
            return
        name, hz = req
        m = _mav()
        interval_us = -1 if hz <= 0 else round(1e6 / hz)  # -1 disables the message
        self._conn.mav.command_long_send(
            self._ap_sysid or 1,
            self._ap_compid,
            m.MAV_CMD_SET_MESSAGE_INTERVAL,
            0,
            getattr(m, f"MAVLINK_MSG_ID_{name}"),
            interval_us,
            0,
            0,
            0,
            0,
            0,
        )
        self.c["rate_requests"] += 1

    def _count_rates(self) -> None:
        r = self._rates
        self.c["rates_accepted"], self.c["rates_refused"] = r.accepted, r.refused
        self.c["rates_unacknowledged"] = r.unacknowledged

    def _rate_stats(self) -> dict[str, Any]:
        """This round's requests for stats(): the refused ones (and those never answered) as
        ``NAME RATE Hz: MAV_RESULT``, and the granted rates."""
        with self._lock:
            refusals, granted = list(self._rates.refusals), dict(self._rates.granted)
        return {
            "rates_refused_messages": [f"{o.name} {o.hz:g} Hz: {_result_name(o.result)}" for o in refusals],
            "rates_granted": [f"{name} {hz:g} Hz" for name, hz in granted.items()],
        }

    def _log_rate(self, o: RateOutcome) -> None:
        """One line per request that was not granted; nothing for one that was."""
        what = f"{self.url}: SET_MESSAGE_INTERVAL {o.name} at {o.hz:g} Hz"
        if o.result == NO_ACK:
            logger.warning(
                "%s: no COMMAND_ACK within %.1f s (counted in rates_unacknowledged)", what, self._rates.ack_timeout_s
            )
        elif o.result == _mav().MAV_RESULT_ACCEPTED:
            if o.was_retry:
                logger.info("%s accepted", what)
        elif o.retry_hz is not None:
            logger.warning(
                "%s refused by the autopilot (%s); asking for %g Hz instead", what, _result_name(o.result), o.retry_hz
            )
        else:
            hint = RATE_HINTS.get(o.name)
            logger.warning(
                "%s refused by the autopilot (%s)%s; not asked again: it comes at the autopilot's rate, if at all%s",
                what,
                _result_name(o.result),
                " too" if o.was_retry else "",
                f" ({hint})" if hint else "",
            )

    def _log_rates_done(self) -> None:
        st = self._rate_stats()
        logger.info(
            "%s: message rates granted: %s%s",
            self.url,
            ", ".join(st["rates_granted"]) or "none",
            f"; refused: {', '.join(st['rates_refused_messages'])}" if st["rates_refused_messages"] else "",
        )


def _result_name(result: int) -> str:
    """MAV_RESULT_DENIED for 2, ...; "no ACK" for a request never answered."""
    if result == NO_ACK:
        return "no ACK"
    entry = _mav().enums["MAV_RESULT"].get(result)
    return entry.name if entry is not None else f"MAV_RESULT {result}"


def _check_pwm(kind: str, *pwm_us: int) -> None:
    """A pulse width outside 800–2200 µs (0: channel unused) is no servo or stick position."""
    for v in pwm_us:
        if v and not PWM_MIN_US <= v <= PWM_MAX_US:
            raise ValueError(f"{kind}: pulse width {v} µs outside {PWM_MIN_US}–{PWM_MAX_US}")


def open_mavlink_vehicle(url: str, **options: Any) -> MavlinkVehicle:
    """Factory for ``mavlink+udp://HOST:PORT`` and ``mavlink+serial:///dev/ttyX?baud=…``."""
    return MavlinkVehicle(url, **options)


def wait_heartbeat(url: str, timeout_s: float = 3.0, **options: Any) -> tuple[int, str] | None:
    """The first autopilot HEARTBEAT on ``url`` within ``timeout_s``: (system id, MAV_AUTOPILOT name), else None.

    For ``robotd doctor``: opens the link alone (no threads, no rate requests, no pose), sends our
    own heartbeat once a second as robotd does (with ``mode=out`` the autopilot learns our address
    only from what we send, and ArduPilot streams nothing to a silent peer), and ignores heartbeats
    of ground stations and other companions, like the link does. Options as for the URL
    (``signing_key`` when the autopilot rejects unsigned messages). Raises DriverError when the
    URL is bad or the device cannot be opened.
    """
    device, opts = parse_mavlink_url(url, **options)
    m = _mav()
    kw: dict[str, Any] = {"source_system": opts.sysid or 1, "source_component": opts.compid, "dialect": DIALECT}
    if not device.startswith("udp"):
        kw["baud"] = opts.baud
    conn, _src = _connect(url, device, opts, **kw)
    try:
        if opts.signing_key:
            conn.setup_signing(read_signing_key(opts.signing_key), sign_outgoing=True)
        t_end = time.monotonic() + timeout_s
        next_hb = 0.0
        while (now := time.monotonic()) < t_end:
            if now >= next_hb:
                try:
                    conn.mav.heartbeat_send(m.MAV_TYPE_ONBOARD_CONTROLLER, m.MAV_AUTOPILOT_INVALID, 0, 0, 0)
                except OSError:
                    pass  # nobody listening yet (ICMP unreachable): keep waiting until the timeout
                next_hb = now + 1.0
            try:
                msg = conn.recv_match(type="HEARTBEAT", blocking=True, timeout=min(0.2, max(t_end - now, 0.01)))
            except OSError:
                msg = None
            if msg is None:
                continue
            if msg.autopilot == m.MAV_AUTOPILOT_INVALID or msg.type in (m.MAV_TYPE_GCS, m.MAV_TYPE_ONBOARD_CONTROLLER):
                continue
            if opts.sysid and msg.get_srcSystem() != opts.sysid:
                continue
            entry = m.enums["MAV_AUTOPILOT"].get(msg.autopilot)
            return int(msg.get_srcSystem()), (entry.name if entry is not None else str(msg.autopilot))
        return None
    finally:
        try:
            conn.close()
        except OSError:
            pass
