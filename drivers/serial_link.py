"""``serial://`` vehicle link: the framed MCU protocol over a serial port (the only pyserial importer).

URL: ``serial:///dev/ttyACM0?baud=115200&wheel_radius_m=0.05&ticks_per_rev=1024&track_width_m=0.3``
(keyword options override the query). Use a stable name (``/dev/serial/by-id/...`` or a udev
symlink): after an unplug the link reopens the same name.

Threads: one reader owns ``read_until`` and the decoder and puts :class:`robotd.core.msgs.Odometry`
samples into a bounded drop-oldest queue (drops counted); writes (version requests, forwarded
poses) go through one lock. On ``SerialException``/``OSError`` the reader closes the port, backs
off (doubling up to ``backoff_max_s``), reopens, and reports ``state = "degraded"`` meanwhile
(docs/interfaces.md §5.2). ``stats()["state"]`` comes from the recent good frames
(:mod:`drivers.link_state`): a silent port, or one that delivers only bad-CRC frames, is
``degraded`` and then ``lost``, never ``ok``. Wheel ticks are converted at this border with the configured geometry:
Δx = (Δs_l + Δs_r)/2, FRD yaw Δψ = (Δs_l − Δs_r)/W, divided by the MCU-clock interval, stamped
at the interval's midpoint on the host clock (:class:`drivers.serial_protocol.ClockMapper`).
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from dataclasses import dataclass
from typing import Any
from urllib.parse import parse_qsl, urlsplit

import numpy as np
import serial

from drivers import AutopilotLink
from drivers.base import ControlSample, QueuedVehicleLink
from drivers.link_state import LinkState, LinkStateParams
from drivers.serial_protocol import (
    MAX_ENCODED,
    PROTOCOL_VERSION,
    WHEEL_TICKS_VALID,
    WHEEL_VEL_VALID,
    ClockMapper,
    ControlInputs,
    Frame,
    FrameDecoder,
    Heartbeat,
    HostPose,
    McuStatus,
    Version,
    VersionRequest,
    WheelGeometry,
    WheelOdometry,
    diff_drive,
    encode_frame,
    seq_gap,
    tick_delta,
)
from robotd.core.errors import DriverError, ProtocolError, RobotdError
from robotd.core.msgs import Odometry, PoseEstimate

logger = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class SerialOptions:
    """Every ``serial://`` option with its default (query keys have the same names)."""

    baud: int = 115200
    wheel_radius_m: float = 0.05
    ticks_per_rev: float = 1024.0
    track_width_m: float = 0.30
    wheel_source: str = "ticks"  # "ticks" (exact distance per interval) or "velocity" (MCU wheel speeds)
    read_timeout_s: float = 0.05
    queue_size: int = 512
    backoff_min_s: float = 0.05
    backoff_max_s: float = 2.0
    clock_window_s: float = 5.0
    max_tick_interval_s: float = 1.0  # a longer gap between wheel frames restarts the tick differencing
    # a shorter one is merged into the next interval: one tick over 0.1 ms reads as 3 m/s (10 rad/s
    # between the wheels), so a late MCU's catch-up frame made spikes the plausibility gate refused
    min_tick_interval_s: float = 0.005
    stale_after_s: float = 0.5  # no good frame this long: state "degraded"
    lost_after_s: float = 2.0  # no good frame this long: state "lost"


_OPTION_TYPES: dict[str, type] = {
    "baud": int,
    "wheel_radius_m": float,
    "ticks_per_rev": float,
    "track_width_m": float,
    "wheel_source": str,
    "read_timeout_s": float,
    "queue_size": int,
    "backoff_min_s": float,
    "backoff_max_s": float,
    "clock_window_s": float,
    "max_tick_interval_s": float,
    "min_tick_interval_s": float,
    "stale_after_s": float,
    "lost_after_s": float,
}


def parse_serial_url(url: str, **options: Any) -> tuple[str, SerialOptions]:
    """``serial:///dev/ttyX?baud=...`` -> (device path, options); unknown/bad keys raise DriverError."""
    parts = urlsplit(url)
    if parts.scheme != "serial":
        raise DriverError(f"{url!r}: expected a serial:// URL")
    path = parts.path
    if not path:
        raise DriverError(f"{url!r}: no device path (expected serial:///dev/ttyACM0?baud=115200)")
    values: dict[str, Any] = dict(parse_qsl(parts.query))
    values.update(options)
    kwargs: dict[str, Any] = {}
    for key, raw in values.items():
        if key not in _OPTION_TYPES:
            raise DriverError(f"{url!r}: unknown option {key!r}; known: {', '.join(sorted(_OPTION_TYPES))}")
        try:
            kwargs[key] = _OPTION_TYPES[key](raw)
        except (TypeError, ValueError) as exc:
            raise DriverError(f"{url!r}: option {key}={raw!r}: expected {_OPTION_TYPES[key].__name__}") from exc
    opts = SerialOptions(**kwargs)
    if opts.wheel_source not in ("ticks", "velocity"):
        raise DriverError(f"{url!r}: wheel_source={opts.wheel_source!r}, expected 'ticks' or 'velocity'")
    if opts.baud <= 0 or opts.queue_size <= 0 or opts.read_timeout_s <= 0:
        raise DriverError(f"{url!r}: baud, queue_size and read_timeout_s must be positive, got {opts}")
    if not 0 < opts.stale_after_s <= opts.lost_after_s:
        raise DriverError(
            f"{url!r}: expected 0 < stale_after_s <= lost_after_s, got {opts.stale_after_s} and {opts.lost_after_s}"
        )
    return path, opts


class SerialVehicle(QueuedVehicleLink):
    """VehicleLink over the MCU protocol. Use as a context manager."""

    def __init__(self, url: str, **options: Any) -> None:
        self.path, self.opts = parse_serial_url(url, **options)
        try:
            self.geometry = WheelGeometry(self.opts.wheel_radius_m, self.opts.ticks_per_rev, self.opts.track_width_m)
        except Exception as exc:
            raise DriverError(f"{url!r}: {exc}") from exc
        self._counters: dict[str, int] = dict.fromkeys(
            (
                "seq_gaps",
                "frames_lost",
                "mcu_resets",
                "reconnects",
                "disconnects",
                "drops",
                "odometry",
                "poses_sent",
                "poses_dropped",
                "tx_errors",
                "version_mismatch",
                "tick_intervals_rejected",
                "tick_intervals_merged",
                "bad_values",
            ),
            0,
        )
        super().__init__(url, self.opts.queue_size, self._counters)
        self._port: serial.Serial | None = None
        self._port_lock = threading.Lock()  # owns every write and every port swap
        self._thread: threading.Thread | None = None
        self._decoder = FrameDecoder()
        self._clock = ClockMapper(window_ns=int(self.opts.clock_window_s * 1e9))
        self._tx_seq = 0
        self._last_seq: int | None = None
        self._last_uptime_ms: int | None = None
        self._prev_ticks: tuple[int, int, int] | None = None  # (unwrapped t_mcu_us, ticks_l, ticks_r)
        self._link = LinkState(LinkStateParams(self.opts.stale_after_s, self.opts.lost_after_s))
        self._version_ok = True
        self.mcu_status: int | None = None
        self.fw_version: tuple[int, int, int] | None = None

    # -- lifecycle -----------------------------------------------------------------------------
    def open(self) -> None:
        """Open the port (DriverError with the URL on failure) and start the reader thread."""
        try:
            self._open_port()
        except (serial.SerialException, OSError) as exc:
            raise DriverError(f"{self.url!r}: cannot open {self.path}: {exc}") from exc
        self._link.opened(time.monotonic_ns())
        self._stop.clear()
        self._thread = threading.Thread(target=self._reader, name="serial-reader", daemon=True)
        self._thread.start()

    def _release(self) -> None:
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        self._close_port()
        self._link.closed()

    @property
    def state(self) -> str:
        """``ok``, ``degraded``, ``lost`` (from the recent good frames) or ``closed``."""
        return self._link.state(time.monotonic_ns())

    def _set_fault(self) -> None:
        why = None if self._port is not None else "disconnected"
        if not self._version_ok:
            why = "protocol version mismatch"
        elif why is None and self.mcu_status not in (None, McuStatus.OK):
            kind = "fault" if self.mcu_status == McuStatus.FAULT else "degraded"
            why = f"MCU reports status {self.mcu_status} ({kind})"
        self._link.fault(why)

    def _open_port(self) -> None:
        port = serial.Serial(
            self.path,
            baudrate=self.opts.baud,
            timeout=self.opts.read_timeout_s,
            write_timeout=0.5,
            exclusive=True,  # advisory lock: a second reader fails fast instead of stealing bytes
        )
        with self._port_lock:
            self._port = port
        # a new connection may be a different (or rebooted) MCU: restart all stream state
        self._decoder = FrameDecoder(stats=self._decoder.stats)
        self._last_seq = None
        self._last_uptime_ms = None
        self._prev_ticks = None
        self._clock.reset()
        self._write(VersionRequest(PROTOCOL_VERSION))

    def _close_port(self) -> None:
        with self._port_lock:
            port, self._port = self._port, None
        if port is not None:
            with contextlib.suppress(serial.SerialException, OSError):
                port.close()

    # -- reader --------------------------------------------------------------------------------
    def _reader(self) -> None:
        backoff = self.opts.backoff_min_s
        while not self._stop.is_set():
            port = self._port
            if port is None:
                try:
                    self._open_port()
                except (serial.SerialException, OSError) as exc:
                    logger.debug("%s: reopen failed (%s); retry in %.2f s", self.url, exc, backoff)
                    self._stop.wait(backoff)
                    backoff = min(2 * backoff, self.opts.backoff_max_s)
                    continue
                backoff = self.opts.backoff_min_s
                self._set_fault()
                self._counters["reconnects"] += 1
                logger.info("%s: reconnected to %s", self.url, self.path)
                continue
            try:
                data = port.read_until(b"\x00", MAX_ENCODED + 1)
            except (serial.SerialException, OSError, TypeError) as exc:
                # TypeError: pyserial's read on a port closed under it by close()
                if self._stop.is_set():
                    break
                logger.warning("%s: link lost (%s); reconnecting", self.url, exc)
                self._close_port()
                self._set_fault()
                # counted last: whoever sees the count also sees the degraded state
                self._counters["disconnects"] += 1
                continue
            if not data:
                continue
            t_arrival = time.monotonic_ns()
            errors_before = self._decoder_errors()
            good = 0
            frames = self._decoder.feed(data)
            bad = self._decoder_errors() - errors_before
            for fr in frames:
                try:
                    self._handle(fr, t_arrival)
                    good += 1
                except RobotdError as exc:
                    # a well-framed message with bad values (NaN speeds...): count it, keep reading
                    self._counters["bad_values"] += 1
                    bad += 1
                    logger.debug("%s: frame seq %d rejected: %s", self.url, fr.seq, exc)
            self._link.record(t_arrival, good, bad)

    def _decoder_errors(self) -> int:
        d = self._decoder.stats
        return d.crc_errors + d.cobs_errors + d.other_errors + d.oversize

    def _handle(self, fr: Frame, t_arrival_ns: int) -> None:
        if self._last_seq is not None:
            gap = seq_gap(self._last_seq, fr.seq)
            if gap > 0:
                self._counters["seq_gaps"] += 1
                self._counters["frames_lost"] += gap
            elif gap < 0 and fr.seq == 0:
                self._on_mcu_reset(f"sequence restarted at 0 after {self._last_seq}")
        self._last_seq = fr.seq
        t_ns = self._clock.observe(fr.t_mcu_us, t_arrival_ns)
        msg = fr.msg
        if isinstance(msg, WheelOdometry):
            self._on_wheels(msg, fr.t_mcu_us, t_ns)
        elif isinstance(msg, ControlInputs):
            thr, ste = float(msg.throttle), float(msg.steering)
            if not (abs(thr) <= 1.0 and abs(ste) <= 1.0):  # NaN fails too
                raise ProtocolError(f"CONTROL_INPUTS throttle {thr}, steering {ste}: expected -1…1")
            self._controls = ControlSample(t_ns, thr, ste, "CONTROL_INPUTS")
        elif isinstance(msg, Heartbeat):
            if self._last_uptime_ms is not None and msg.uptime_ms + 1000 < self._last_uptime_ms:
                self._on_mcu_reset(f"uptime fell from {self._last_uptime_ms} ms to {msg.uptime_ms} ms")
            self._last_uptime_ms = msg.uptime_ms
            self.mcu_status = msg.status
            self._set_fault()
        elif isinstance(msg, Version):
            self.fw_version = (msg.fw_major, msg.fw_minor, msg.fw_patch)
            self._version_ok = msg.protocol == PROTOCOL_VERSION  # a reconnect may bring another MCU
            self._set_fault()
            if not self._version_ok:
                self._counters["version_mismatch"] += 1
                logger.error(
                    "%s: MCU speaks protocol %d, robotd %d: update one side", self.url, msg.protocol, PROTOCOL_VERSION
                )

    def _on_mcu_reset(self, why: str) -> None:
        self._counters["mcu_resets"] += 1
        logger.warning("%s: MCU reset detected (%s)", self.url, why)
        self._prev_ticks = None
        self._last_uptime_ms = None
        # the MCU clock restarted; keep only the sample that arrives next
        self._clock.reset()

    def _on_wheels(self, msg: WheelOdometry, t_mcu_us: int, t_ns: int) -> None:
        W = self.geometry.track_width_m
        use_ticks = bool(msg.flags & WHEEL_TICKS_VALID) and (
            self.opts.wheel_source == "ticks" or not msg.flags & WHEEL_VEL_VALID
        )
        if use_ticks:
            now_us = self._clock.peek_unwrap(t_mcu_us)
            prev = self._prev_ticks
            if prev is not None and 0 < now_us - prev[0] < self.opts.min_tick_interval_s * 1e6:
                # too short to difference: the ticks are cumulative, the next interval covers it
                self._counters["tick_intervals_merged"] += 1
                return
            self._prev_ticks = (now_us, msg.ticks_l, msg.ticks_r)
            if prev is None:
                return
            dt_us = now_us - prev[0]
            if dt_us <= 0 or dt_us > self.opts.max_tick_interval_s * 1e6:
                self._counters["tick_intervals_rejected"] += 1
                return
            k = self.geometry.m_per_tick / (dt_us * 1e-6)
            v, w = diff_drive(tick_delta(prev[1], msg.ticks_l) * k, tick_delta(prev[2], msg.ticks_r) * k, W)
            # mean velocity over the interval: valid at its midpoint
            t_ns -= dt_us * 500
        elif msg.flags & WHEEL_VEL_VALID:
            v, w = diff_drive(float(msg.vel_l_mps), float(msg.vel_r_mps), W)
        else:
            return
        self._emit(Odometry(int(t_ns), np.array([v, 0.0, 0.0]), np.array([0.0, 0.0, w]), source="serial"))

    # -- writer --------------------------------------------------------------------------------
    def _write(self, msg: HostPose | VersionRequest) -> bool:
        with self._port_lock:
            port = self._port
            if port is None:
                return False
            frame = encode_frame(msg, self._tx_seq, time.monotonic_ns() // 1000)
            self._tx_seq = (self._tx_seq + 1) & 0xFFFF
            try:
                port.write(frame)
            except (serial.SerialException, OSError) as exc:
                # the reader notices the dead port on its next read and reconnects
                self._counters["tx_errors"] += 1
                logger.debug("%s: write failed: %s", self.url, exc)
                return False
        return True

    # -- VehicleLink (odometry, drain, latest_controls: QueuedVehicleLink) ----------------------
    @property
    def autopilot(self) -> AutopilotLink | None:
        """None: the daemon does not send the SLAM pose to the MCU. :meth:`send_pose` (HOST_POSE)
        is the MCU protocol's pose message for callers that want it; an autopilot gets the pose
        over its own MAVLink link (``mavlink.enabled``)."""
        return None

    def send_pose(self, pose: PoseEstimate, quality: int, reset_counter: int) -> None:
        """Forward the SLAM pose to the MCU (HOST_POSE); dropped and counted while disconnected."""
        msg = HostPose(
            float(pose.xyz_W_m[0]),
            float(pose.xyz_W_m[1]),
            float(pose.xyz_W_m[2]),
            float(pose.rpy_rad[2]),
            int(quality),
            int(reset_counter),
        )
        self._counters["poses_sent" if self._write(msg) else "poses_dropped"] += 1

    def stats(self) -> dict[str, Any]:
        d = self._decoder.stats
        out: dict[str, Any] = {
            "frames": d.frames,
            "crc_errors": d.crc_errors,
            "cobs_errors": d.cobs_errors,
            "other_errors": d.other_errors,
            "oversize": d.oversize,
            "resyncs": d.resyncs,
            "bytes_in": d.bytes_in,
            **self._counters,
            **self._link.stats(time.monotonic_ns()),  # state, since_good_s, good_window, bad_window, fault
            "connected": self._port is not None,
            "mcu_status": self.mcu_status,
            "fw_version": self.fw_version,
            "clock_offset_ns": self._clock.offset_ns,
            "queued": len(self._queue),
        }
        return out


def open_serial_vehicle(url: str, **options: Any) -> SerialVehicle:
    """Factory for ``serial:///dev/ttyX?baud=…`` (drivers.open_vehicle); opens on ``__enter__``."""
    return SerialVehicle(url, **options)
