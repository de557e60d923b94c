"""Reference vehicle-MCU simulator: speaks ``docs/serial-protocol.md`` over a pseudo-terminal.

Usable as a library (tests, benchmarks) and as a program::

    python -m drivers.mcu_sim --rate 100 --speed 0.5 --yaw-rate 0.2 --link /tmp/ttyMCU

prints the ``serial://`` URL to open and streams wheel odometry (ticks and wheel speeds) at
``--rate`` Hz, control inputs at 20 Hz and a heartbeat at 1 Hz, answers version requests and
records the poses the host forwards. The MCU clock is the host monotonic clock scaled by
``drift_ppm`` and shifted by ``t0_us`` (so tests can start just before the 32-bit wrap).
Fault injection (corrupt frames, skipped sequence numbers, garbage, resets) is for tests.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import logging
import math
import os
import select
import signal
import sys
import threading
import time
import tty
from dataclasses import dataclass, field

from drivers.serial_protocol import (
    HEADER,
    PROTOCOL_VERSION,
    WHEEL_TICKS_VALID,
    WHEEL_VEL_VALID,
    ControlInputs,
    FrameDecoder,
    Heartbeat,
    HostPose,
    McuStatus,
    Message,
    Version,
    VersionRequest,
    WheelGeometry,
    WheelOdometry,
    cobs_encode,
    encode_body,
)
from robotd.core.errors import RobotdError

logger = logging.getLogger(__name__)

FW_VERSION = (1, 0, 0)


def open_pty() -> tuple[int, int, str]:
    """A raw pseudo-terminal pair: (master fd for the MCU, slave fd kept open, slave path)."""
    master, slave = os.openpty()
    tty.setraw(slave)
    return master, slave, os.ttyname(slave)


@dataclass
class McuSimStats:
    frames_sent: int = 0
    wheel_frames: int = 0
    corrupted: int = 0
    skipped_seq: int = 0
    host_frames: int = 0
    version_requests: int = 0  # counted once the reply is written
    resets: int = 0
    write_errors: int = 0
    poses: list[HostPose] = field(default_factory=list)


class McuSimulator:
    """A simulated MCU writing frames to ``fd`` (the pty master) from its own thread.

    ``rate_hz`` is the wheel-odometry rate; 0 means as fast as the port takes it (benchmarks).
    ``speed_mps``/``yaw_rate_radps`` give the commanded motion (FRD: positive yaw turns right).
    """

    def __init__(
        self,
        fd: int,
        *,
        rate_hz: float = 100.0,
        control_hz: float = 20.0,
        heartbeat_hz: float = 1.0,
        geometry: WheelGeometry | None = None,
        speed_mps: float = 0.5,
        yaw_rate_radps: float = 0.2,
        t0_us: int = 0,
        drift_ppm: float = 0.0,
        send_ticks: bool = True,
        send_velocities: bool = True,
        protocol: int = PROTOCOL_VERSION,
    ) -> None:
        self.fd = fd
        self.rate_hz = rate_hz
        self.control_hz = control_hz
        self.heartbeat_hz = heartbeat_hz
        self.geometry = geometry or WheelGeometry()
        self.speed_mps = speed_mps
        self.yaw_rate_radps = yaw_rate_radps
        self.t0_us = t0_us
        self.drift_ppm = drift_ppm
        self.send_ticks = send_ticks
        self.send_velocities = send_velocities
        self.protocol = protocol
        self.stats = McuSimStats()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._decoder = FrameDecoder()
        self._boot_ns = time.monotonic_ns()
        self._seq = 0
        self._s_l = 0.0  # wheel travel [m]
        self._s_r = 0.0
        self._last_motion_ns = self._boot_ns
        self._corrupt_next = 0
        self._skip_next = 0
        os.set_blocking(fd, False)

    # -- clock and motion ------------------------------------------------------------------
    def mcu_time_us(self, t_host_ns: int | None = None) -> int:
        """The MCU's u32 microsecond clock at host time ``t_host_ns`` (now by default)."""
        t = time.monotonic_ns() if t_host_ns is None else t_host_ns
        up_us = (t - self._boot_ns) / 1000.0 * (1.0 + self.drift_ppm * 1e-6)
        return (self.t0_us + int(up_us)) & 0xFFFFFFFF

    def wheel_speeds(self) -> tuple[float, float]:
        """(v_l, v_r) [m/s] for the commanded motion: inverse of Δψ = (Δs_l − Δs_r)/W."""
        half = 0.5 * self.yaw_rate_radps * self.geometry.track_width_m
        return self.speed_mps + half, self.speed_mps - half

    def _advance(self, t_ns: int) -> None:
        dt = (t_ns - self._last_motion_ns) * 1e-9
        self._last_motion_ns = t_ns
        v_l, v_r = self.wheel_speeds()
        self._s_l += v_l * dt
        self._s_r += v_r * dt

    # -- fault injection -------------------------------------------------------------------
    def corrupt_next(self, n: int = 1) -> None:
        """Flip a payload bit in the next ``n`` frames (CRC errors on the host)."""
        with self._lock:
            self._corrupt_next += n

    def skip_seq(self, n: int = 1) -> None:
        """Pretend ``n`` frames were lost on the wire (sequence gap on the host)."""
        with self._lock:
            self._skip_next += n

    def inject(self, data: bytes) -> None:
        """Write raw bytes (garbage, partial frames) into the stream."""
        with self._lock:
            self._write(data)

    def reset(self) -> None:
        """Simulate an MCU reboot: uptime, clock and sequence restart; version announced."""
        with self._lock:
            self._boot_ns = time.monotonic_ns()
            self._last_motion_ns = self._boot_ns
            self.t0_us = 0
            self._seq = 0
            self.stats.resets += 1
        self.send(Version(PROTOCOL_VERSION, *FW_VERSION))

    # -- I/O ---------------------------------------------------------------------------------
    def _write(self, data: bytes) -> None:
        view = memoryview(data)
        deadline = time.monotonic() + 1.0
        while view and not self._stop.is_set():
            try:
                n = os.write(self.fd, view)
                view = view[n:]
            except BlockingIOError:
                # the host is not draining the pty: wait a little (flow control), never forever
                if time.monotonic() > deadline:
                    self.stats.write_errors += 1
                    return
                select.select([], [self.fd], [], 0.05)
            except OSError as exc:
                self.stats.write_errors += 1
                if exc.errno in (errno.EIO, errno.EBADF):
                    self._stop.set()
                return

    def send(self, msg: Message, t_us: int | None = None) -> None:
        """Frame and write one message with the next sequence number."""
        with self._lock:
            if self._skip_next:
                self._seq += self._skip_next
                self.stats.skipped_seq += self._skip_next
                self._skip_next = 0
            t = self.mcu_time_us() if t_us is None else t_us
            body = bytearray(encode_body(msg.TYPE, self._seq, t, msg.pack(), self.protocol))
            if self._corrupt_next:
                self._corrupt_next -= 1
                # flip one bit after the CRC was computed (before stuffing): a CRC error, not a framing one
                body[HEADER.size] ^= 0x10
                self.stats.corrupted += 1
            self._seq = (self._seq + 1) & 0xFFFF
            self.stats.frames_sent += 1
            self._write(cobs_encode(bytes(body)) + b"\x00")

    def send_wheels(self) -> None:
        t_ns = time.monotonic_ns()
        self._advance(t_ns)
        g = self.geometry
        v_l, v_r = self.wheel_speeds()
        flags = (WHEEL_TICKS_VALID if self.send_ticks else 0) | (WHEEL_VEL_VALID if self.send_velocities else 0)
        ticks_l = math.floor(self._s_l / g.m_per_tick)
        ticks_r = math.floor(self._s_r / g.m_per_tick)
        self.send(WheelOdometry(flags, ticks_l, ticks_r, v_l, v_r), self.mcu_time_us(t_ns))
        self.stats.wheel_frames += 1

    def poll_host(self, timeout_s: float) -> None:
        """Read and handle what the host wrote, waiting at most ``timeout_s``."""
        try:
            ready, _, _ = select.select([self.fd], [], [], max(0.0, timeout_s))
        except (OSError, ValueError):
            self._stop.set()
            return
        if not ready:
            return
        try:
            data = os.read(self.fd, 4096)
        except BlockingIOError:
            return
        except OSError:
            # EIO on the master: nobody holds the slave open right now; wait for the host
            time.sleep(min(timeout_s, 0.01))
            return
        for fr in self._decoder.feed(data):
            self.stats.host_frames += 1
            if isinstance(fr.msg, VersionRequest):
                self.send(Version(PROTOCOL_VERSION, *FW_VERSION))
                self.stats.version_requests += 1
            elif isinstance(fr.msg, HostPose):
                self.stats.poses.append(fr.msg)
                del self.stats.poses[:-100]  # keep the last 100 only

    def run(self, duration_s: float | None = None) -> None:
        """Stream until :meth:`stop` or ``duration_s`` elapses (blocking)."""
        self.send(Version(PROTOCOL_VERSION, *FW_VERSION))
        t_end = None if duration_s is None else time.monotonic() + duration_s
        period = 1.0 / self.rate_hz if self.rate_hz > 0 else 0.0
        next_wheel = next_ctl = next_hb = time.monotonic()
        while not self._stop.is_set():
            now = time.monotonic()
            if t_end is not None and now >= t_end:
                break
            if now >= next_wheel:
                self.send_wheels()
                next_wheel = max(next_wheel + period, now - period) if period else now
            if self.control_hz > 0 and now >= next_ctl:
                self.send(ControlInputs(min(1.0, self.speed_mps), max(-1.0, min(1.0, self.yaw_rate_radps))))
                next_ctl += 1.0 / self.control_hz
            if self.heartbeat_hz > 0 and now >= next_hb:
                up_ms = (time.monotonic_ns() - self._boot_ns) // 1_000_000
                self.send(Heartbeat(McuStatus.OK, up_ms))
                next_hb += 1.0 / self.heartbeat_hz
            self.poll_host(max(0.0, next_wheel - time.monotonic()) if period else 0.0)

    def start(self) -> McuSimulator:
        self._thread = threading.Thread(target=self.run, name="mcu-sim", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)

    def __enter__(self) -> McuSimulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def main(argv: list[str] | None = None) -> int:
    """``robotd mcu-sim`` / ``python -m drivers.mcu_sim``: run a simulated MCU on a new pty."""
    p = argparse.ArgumentParser(prog="mcu-sim", description=__doc__.split("\n\n")[0] if __doc__ else None)
    p.add_argument("--rate", type=float, default=100.0, help="wheel odometry rate [Hz], 0 = as fast as possible")
    p.add_argument("--speed", type=float, default=0.5, help="forward speed [m/s]")
    p.add_argument("--yaw-rate", type=float, default=0.2, help="yaw rate [rad/s], positive turns right")
    p.add_argument("--wheel-radius", type=float, default=0.05, help="[m]")
    p.add_argument("--ticks-per-rev", type=float, default=1024.0)
    p.add_argument("--track-width", type=float, default=0.30, help="[m]")
    p.add_argument("--t0-us", type=int, default=0, help="MCU clock at start (u32 µs), to exercise the wrap")
    p.add_argument("--duration", type=float, default=None, help="stop after this many seconds")
    p.add_argument("--link", default=None, help="also create this symlink to the pty (a stable name)")
    p.add_argument("--baud", type=int, default=115200, help="baud written into the printed URL")
    args = p.parse_args(argv)
    try:
        geometry = WheelGeometry(args.wheel_radius, args.ticks_per_rev, args.track_width)
    except RobotdError as exc:
        print(f"mcu-sim: {exc}", file=sys.stderr)
        return 2
    master, slave, path = open_pty()
    link = args.link
    if link:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(link)
        os.symlink(path, link)
    sim = McuSimulator(
        master,
        rate_hz=args.rate,
        geometry=geometry,
        speed_mps=args.speed,
        yaw_rate_radps=args.yaw_rate,
        t0_us=args.t0_us,
    )
    print(f"serial://{link or path}?baud={args.baud}", flush=True)

    def _on_signal(signum: int, _frame: object) -> None:
        sim._stop.set()  # handlers only set flags

    old = {s: signal.signal(s, _on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        sim.run(args.duration)
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        os.close(master)
        os.close(slave)
        if link:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(link)
    print(f"mcu-sim: sent {sim.stats.frames_sent} frames, {sim.stats.host_frames} from the host", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
