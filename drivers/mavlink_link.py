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
``SET_GPS_GLOBAL_ORIGIN`` (when ``origin`` is configured) and the message-rate requests
(drivers/mavlink_setup.py, with the vision-yaw alignment) go out once the autopilot heartbeat is
seen and again after an autopilot reboot: a new boot clock in SYSTEM_TIME seen consistently, with
the autopilot's heartbeat, while the old one fell silent (:class:`drivers.mavlink_guard.BootClock`).
The rate requests go one at a time, each matched with its COMMAND_ACK; a refused rate is logged,
counted in ``stats()`` and retried once at half the rate (:class:`drivers.mavlink_guard.RateRequests`).
Link loss: no autopilot heartbeat for ``link_timeout_s`` (3 s).

Exposure (issue 15): with ``mode=out`` the socket is connected to the target, so the kernel binds
it to the address that routes there (127.0.0.1 for a loopback target; ``bind=ADDR`` chooses) and
delivers datagrams from the target's address only. Whatever the transport, vehicle messages are
taken only from the autopilot: the system and component id of its first heartbeat and, over UDP,
the address that heartbeat came from (others are counted in ``rejected_source``). TIMESYNC
requests are answered only for the autopilot, at most ``timesync_reply_hz`` a second.

In: ``WHEEL_DISTANCE`` (differential drive, track width from the options; ±100 000 m wrap) gives
forward speed; ``ATTITUDE`` gives body rates (preferred for yaw rate) and the attitude used to
rotate ``LOCAL_POSITION_NED`` velocities into the body frame when no wheel data flows (the
ATTITUDE nearest each sample's stamp, its yaw carried to the stamp); ``SERVO_OUTPUT_RAW``/
``RC_CHANNELS`` are the control inputs (drivers/mavlink_odometry.py decodes them all). Autopilot
stamps are mapped onto the host clock with the TIMESYNC offset (arrival time until the first round
trip). The options and their defaults: drivers/mavlink_options.py.

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
from collections.abc import Callable
from typing import Any
from urllib.parse import parse_qsl, urlsplit

os.environ.setdefault("MAVLINK20", "1")  # before the first pymavlink import: ODOMETRY needs MAVLink 2

from pymavlink import mavutil

from drivers.base import ControlSample, QueuedVehicleLink, is_loopback
from drivers.link_state import LOST, LinkState, LinkStateParams
from drivers.mavlink_guard import BootClock, RateLimit
from drivers.mavlink_odometry import AutopilotPose, OdometryDecoder
from drivers.mavlink_options import MavlinkOptions
from drivers.mavlink_pose import POSE_COUNTERS, MavlinkAutopilot
from drivers.mavlink_setup import Autopilot, SetupLink, VehicleSetup
from robotd.core.errors import DriverError, RobotdError
from robotd.formats.autopilot import CovarianceFloors, TimesyncFilter

logger = logging.getLogger(__name__)

DIALECT = "ardupilotmega"

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
    """TIMESYNC both ways: our requests, the offset filter over their replies and autopilot stamps
    mapped onto the host monotonic clock; the autopilot's requests answered (through ``reply``, the
    link's outbox), at most ``reply_hz`` a second. Counts in the link's counter dict."""

    def __init__(self, counters: dict[str, int], reply_hz: float, reply: Callable[[str, Any], None]) -> None:
        self.filter = TimesyncFilter()
        self._pending: dict[int, int] = {}  # our ts1 -> send time (ns)
        self._c = counters
        self._limit = RateLimit(reply_hz)
        self._reply = reply

    def on_timesync(self, msg: Any, t_ns: int) -> None:
        """A TIMESYNC from the autopilot (receive thread): its request, or a reply to ours."""
        if msg.tc1 == 0:
            # a request (PX4 needs 500 answered round trips before it uses our time_usec); a flood
            # of them gets a bounded number of replies
            if self._limit.allow(t_ns):
                self._reply("timesync_reply", int(msg.ts1))
            else:
                self._c["timesync_replies_limited"] += 1
            return
        self.on_reply(int(msg.ts1), int(msg.tc1), t_ns)

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
    """VehicleLink to an ArduPilot/PX4 autopilot. Use as a context manager.

    The link itself (the connection, the receive and transmit threads, who the autopilot is, the
    heartbeats, TIMESYNC and reboots) is this class; its collaborators share its counter dict:
    the inbound motion and controls (:class:`drivers.mavlink_odometry.OdometryDecoder`), what it
    asks of the autopilot (:class:`drivers.mavlink_setup.VehicleSetup`: the origin, the message
    rates, the yaw alignment) and the pose out (:class:`drivers.mavlink_pose.MavlinkAutopilot`).
    """

    def __init__(self, url: str, **options: Any) -> None:
        self.device, self.opts = parse_mavlink_url(url, **options)
        self._key = read_signing_key(self.opts.signing_key) if self.opts.signing_key else None
        self._conn: Any = None
        self._wake = threading.Event()
        self._lock = threading.Lock()  # guards the outbox
        self._rx: threading.Thread | None = None
        self._tx: threading.Thread | None = None
        self._outbox: deque[tuple[str, Any]] = deque()
        self._peer = Autopilot()  # who the autopilot is, from its heartbeats
        self._src: _DatagramSource | None = None
        self._boot = BootClock()
        self._linkstate = LinkState(
            LinkStateParams(stale_after_s=min(1.5, self.opts.link_timeout_s), lost_after_s=self.opts.link_timeout_s)
        )
        self._last_ap_hb_mono: float | None = None
        self.c: dict[str, int] = dict.fromkeys(COUNTERS, 0)
        self._clock = _AutopilotClock(self.c, self.opts.timesync_reply_hz, self._outbox_put)
        self.rx_types: dict[str, int] = {}
        super().__init__(url, self.opts.queue_size, self.c)
        floors = CovarianceFloors(self.opts.floor_pos_m2, self.opts.floor_ang_rad2)
        # the pose-out role: shares this link's connection, transmit thread and counters
        self._autopilot = MavlinkAutopilot(url, self.opts.message, floors, self.c, self._wake)
        self._decoder = OdometryDecoder(self.opts, self.c, self._clock.to_host, self._emit)
        link = SetupLink(self._peer, self._outbox_put, self._wake, self._autopilot.still_for_s, self._our_sysid)
        self._setup = VehicleSetup(url, self.opts, self.c, _mav(), link)
        # the autopilot's messages by type (HEARTBEAT is the link's own: it says who the autopilot is)
        self._handlers: dict[str, Callable[[Any, int], None]] = {
            **self._decoder.handlers(),
            **self._setup.handlers(),
            "SYSTEM_TIME": self._on_system_time,
            "TIMESYNC": self._clock.on_timesync,
        }

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
        return self._peer.link_up

    @property
    def autopilot_sysid(self) -> int | None:
        return self._peer.sysid

    @property
    def armed(self) -> bool | None:
        """From the autopilot's heartbeat; None before it."""
        return self._peer.armed

    @property
    def origin_confirmed(self) -> bool:
        return self._setup.origin_confirmed

    @property
    def ekf_flags(self) -> int | None:
        return self._setup.ekf_flags

    @property
    def last_visodom_text(self) -> str:
        return self._setup.last_visodom_text

    def latest_controls(self) -> ControlSample | None:
        return self._decoder.controls

    def autopilot_pose_at(self, t_ns: int) -> AutopilotPose | None:
        """The autopilot's own estimate of the vehicle's pose at host time ``t_ns`` (its local NED
        frame; drivers.mavlink_odometry.OdometryDecoder.pose_at), None when it has sent none that near."""
        return self._decoder.pose_at(t_ns)

    def autopilot_to_host_ns(self, t_ap_ns: int) -> int | None:
        """Autopilot boot-clock time [ns] on the host monotonic clock, once TIMESYNC has a sample."""
        return self._clock.filter.autopilot_to_host(t_ap_ns)

    def stats(self) -> dict[str, Any]:
        peer = self._peer
        link = self._linkstate.stats(time.monotonic_ns())  # state from the autopilot's recent messages
        if peer.sysid is not None and not peer.link_up:
            link["state"] = LOST  # its heartbeat timed out
        return {
            **self.c,
            "link_up": peer.link_up,
            **link,
            "autopilot_sysid": peer.sysid,
            "autopilot_compid": peer.compid if peer.sysid is not None else None,
            "autopilot_address": None if peer.addr is None else f"{peer.addr[0]}:{peer.addr[1]}",
            "reboot_candidates": self._boot.mismatches,
            "timesync_offset_ns": self._clock.filter.offset_ns,
            "timesync_rtt_ns": self._clock.filter.rtt_ns,
            "origin_confirmed": self._setup.origin_confirmed,
            "armed": peer.armed,
            "last_visodom_text": self._setup.last_visodom_text,
            "ekf_flags": self._setup.ekf_flags,
            **self._setup.rate_stats(),
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
        handler = self._handlers.get(kind)
        accepted: bool | None
        if kind == "HEARTBEAT":
            accepted = self._on_heartbeat(msg, t_ns, addr)
            if accepted is None:
                return
        elif handler is None:
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
        elif self._peer.sysid is None:
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
        peer = self._peer
        if peer.sysid is None:
            return False
        if msg.get_srcSystem() != peer.sysid or msg.get_srcComponent() != peer.compid:
            return False
        return peer.addr is None or addr == peer.addr

    def _on_heartbeat(self, msg: Any, t_ns: int, addr: tuple[str, int] | None = None) -> bool | None:
        """True when the heartbeat is the autopilot's (the first one defines who that is; another
        sender may take over only once the known autopilot's link is lost), False when it claims a
        vehicle but is not ours, None for ground stations and other companions."""
        m, peer = _mav(), self._peer
        if msg.autopilot == m.MAV_AUTOPILOT_INVALID or msg.type in (m.MAV_TYPE_GCS, m.MAV_TYPE_ONBOARD_CONTROLLER):
            return None  # ground stations and other companions: not the vehicle, nothing wrong either
        src, comp = msg.get_srcSystem(), msg.get_srcComponent()
        if self.opts.sysid and src != self.opts.sysid:
            return False  # a configured vehicle id: other vehicles on the network are not ours
        if peer.sysid is None or (not peer.link_up and not self._from_autopilot(msg, addr)):
            if peer.sysid is not None:
                logger.warning("%s: autopilot link was lost; taking this heartbeat's sender as the autopilot", self.url)
            first = peer.sysid is None
            peer.sysid, peer.compid, peer.addr = src, comp, addr
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
        peer.armed = bool(msg.base_mode & m.MAV_MODE_FLAG_SAFETY_ARMED)
        self._boot.heartbeat(t_ns)
        if not peer.link_up:
            peer.link_up = True
            logger.info("%s: autopilot link up", self.url)
        return True

    def _on_system_time(self, msg: Any, t_ns: int) -> None:
        # a reboot is a new boot clock seen consistently, with heartbeats, while the old one fell
        # silent (drivers.mavlink_guard.BootClock; docs/mavlink.md §7): never one SYSTEM_TIME
        if self._boot.observe(int(msg.time_boot_ms), t_ns):
            self.c["autopilot_reboots"] += 1
            logger.warning("%s: autopilot rebooted (time_boot_ms now %d)", self.url, int(msg.time_boot_ms))
            self._clock.filter.reset()
            self._decoder.forget_wheels()
            self._setup.on_reboot()
            self._outbox_put("vehicle_setup", "reboot")

    def _our_sysid(self) -> int:
        """The system id we speak as (the autopilot's, once its heartbeat named it); 0 unopened."""
        return int(self._conn.mav.srcSystem) if self._conn is not None else 0

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
                mav = self._conn.mav
                if now >= next_hb:
                    self._send_heartbeat()
                    next_hb = max(next_hb + 1.0 / self.opts.heartbeat_hz, now)
                if self.opts.timesync_hz > 0 and now >= next_ts:
                    self._clock.request(mav)
                    next_ts = max(next_ts + 1.0 / self.opts.timesync_hz, now)
                while True:
                    with self._lock:
                        item = self._outbox.popleft() if self._outbox else None
                    if item is None:
                        break
                    self._do(mav, item)
                self._setup.send_rate_request(mav)
                self._autopilot.send_pending(mav)
                self._setup.check_origin(mav, now)
            except (OSError, ValueError) as exc:
                self.c["tx_errors"] += 1
                logger.warning("%s: send failed: %s", self.url, exc)
            self._check_link()
            wait = min(next_hb, next_ts if self.opts.timesync_hz > 0 else next_hb) - time.monotonic()
            self._wake.wait(max(0.0, min(wait, 0.1)))
            self._wake.clear()

    def _check_link(self) -> None:
        hb = self._last_ap_hb_mono
        if self._peer.link_up and (hb is None or time.monotonic() - hb > self.opts.link_timeout_s):
            self._peer.link_up = False
            self.c["link_losses"] += 1
            logger.warning("%s: autopilot link lost (no heartbeat for %.1f s)", self.url, self.opts.link_timeout_s)

    def _send_heartbeat(self) -> None:
        m = _mav()
        self._conn.mav.heartbeat_send(
            m.MAV_TYPE_ONBOARD_CONTROLLER, m.MAV_AUTOPILOT_INVALID, 0, 0, self._autopilot.system_status()
        )
        self.c["heartbeats_sent"] += 1

    def _do(self, mav: Any, item: tuple[str, Any]) -> None:
        kind, arg = item
        if kind == "timesync_reply":
            mav.timesync_send(time.monotonic_ns(), arg)
            self.c["timesync_replies"] += 1
        elif kind == "align_yaw":
            self._setup.align_yaw(mav)
        elif kind == "vehicle_setup":
            self._setup.start(mav)


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
