"""The framed binary protocol between robotd and the vehicle MCU: pure encode/decode, no I/O.

Wire format (docs/interfaces.md §5.1; the full spec, with C snippets for the MCU side, is
``docs/serial-protocol.md``)::

    body  = ver:u8 | type:u8 | seq:u16 | t_mcu_us:u32 | payload      (little-endian)
    frame = COBS(body | crc16:u16) | 0x00

``crc16`` is CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no final xor) over
``body``: ``binascii.crc_hqx(body, 0xFFFF)``, check value 0x29B1 for ``b"123456789"``. COBS makes
0x00 the only delimiter, so a reader that loses sync drops bytes up to the next 0x00 and carries
on. Nothing here imports pyserial; ``drivers.serial_link`` owns the port.

Also here, because they are pure and shared with the MCU simulator and the MAVLink link:
the MCU-to-host clock mapping (:class:`ClockMapper`, a minimum-latency filter over a sliding
window with the 32-bit microsecond wrap) and the differential-drive conversion of wheel
ticks/velocities to body velocity and yaw rate (docs/interfaces.md §1.8).
"""

from __future__ import annotations

import binascii
import math
import struct
from collections import deque
from dataclasses import dataclass, field
from typing import ClassVar

from robotd.core.errors import ProtocolError

PROTOCOL_VERSION = 1
HEADER = struct.Struct("<BBHI")  # ver, type, seq, t_mcu_us
CRC = struct.Struct("<H")
# Largest decoded body (header + payload + crc) we accept; anything longer is garbage or a
# lost delimiter. COBS adds 1 byte per 254, so the encoded cap is a little larger.
MAX_BODY = 256
MAX_ENCODED = MAX_BODY + MAX_BODY // 254 + 2

U32 = 1 << 32
U16 = 1 << 16


# ---------------------------------------------------------------------------------------------
# COBS and CRC


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE of ``data`` (check value 0x29B1 for b"123456789")."""
    return binascii.crc_hqx(data, 0xFFFF)


def cobs_encode(data: bytes) -> bytes:
    """Consistent Overhead Byte Stuffing: the result holds no 0x00 (delimiter not included)."""
    out = bytearray(b"\x00")
    code_at, code = 0, 1
    for byte in data:
        if byte:
            out.append(byte)
            code += 1
        # a zero ends a run; so does a full run of 254 non-zero bytes (code 0xFF, no zero implied)
        if not byte or code == 0xFF:
            out[code_at] = code
            code_at, code = len(out), 1
            out.append(0)
    out[code_at] = code
    return bytes(out)


def cobs_decode(data: bytes) -> bytes:
    """Inverse of :func:`cobs_encode` (without the delimiter).

    Raises :class:`ProtocolError` on a code byte of 0 or one that points past the end.
    """
    out = bytearray()
    i, n = 0, len(data)
    while i < n:
        code = data[i]
        if code == 0:
            raise ProtocolError(f"COBS: zero code byte at offset {i} of {n}")
        end = i + code
        if end > n:
            raise ProtocolError(f"COBS: code {code} at offset {i} points past the end ({n} bytes)")
        run = data[i + 1 : end]
        if 0 in run:
            raise ProtocolError(f"COBS: zero byte inside a run at offset {i + 1 + run.index(0)}")
        out += run
        i = end
        # each run implies a zero after it, except after a full 0xFF run and at the very end
        if code != 0xFF and i < n:
            out.append(0)
    return bytes(out)


# ---------------------------------------------------------------------------------------------
# Messages


class MsgType:
    """Message type codes. MCU -> host below 0x80, host -> MCU from 0x80."""

    WHEEL_ODOMETRY = 0x01
    CONTROL_INPUTS = 0x02
    HEARTBEAT = 0x03
    VERSION = 0x04
    VERSION_REQUEST = 0x80
    HOST_POSE = 0x81


class McuStatus:
    OK = 0
    DEGRADED = 1
    FAULT = 2


WHEEL_TICKS_VALID = 0x01
WHEEL_VEL_VALID = 0x02


@dataclass(frozen=True, slots=True)
class WheelOdometry:
    """Cumulative wheel ticks (int32, wrapping) and/or wheel ground speeds [m/s], left and right."""

    STRUCT: ClassVar[struct.Struct] = struct.Struct("<Biiff")
    TYPE: ClassVar[int] = MsgType.WHEEL_ODOMETRY
    flags: int  # WHEEL_TICKS_VALID | WHEEL_VEL_VALID
    ticks_l: int
    ticks_r: int
    vel_l_mps: float
    vel_r_mps: float

    def pack(self) -> bytes:
        return self.STRUCT.pack(self.flags, _i32(self.ticks_l), _i32(self.ticks_r), self.vel_l_mps, self.vel_r_mps)


@dataclass(frozen=True, slots=True)
class ControlInputs:
    """Commanded throttle and steering, each normalised to [-1, 1] (+steering = turn right)."""

    STRUCT: ClassVar[struct.Struct] = struct.Struct("<ff")
    TYPE: ClassVar[int] = MsgType.CONTROL_INPUTS
    throttle: float
    steering: float

    def pack(self) -> bytes:
        return self.STRUCT.pack(self.throttle, self.steering)


@dataclass(frozen=True, slots=True)
class Heartbeat:
    """MCU status (:class:`McuStatus`), uptime [ms] and a bit field of MCU-specific faults."""

    STRUCT: ClassVar[struct.Struct] = struct.Struct("<BIH")
    TYPE: ClassVar[int] = MsgType.HEARTBEAT
    status: int
    uptime_ms: int
    fault_bits: int = 0

    def pack(self) -> bytes:
        return self.STRUCT.pack(self.status, self.uptime_ms & 0xFFFFFFFF, self.fault_bits & 0xFFFF)


@dataclass(frozen=True, slots=True)
class Version:
    """Protocol version the MCU speaks and its firmware version; sent at boot and on request."""

    STRUCT: ClassVar[struct.Struct] = struct.Struct("<BBBBH")
    TYPE: ClassVar[int] = MsgType.VERSION
    protocol: int
    fw_major: int
    fw_minor: int
    fw_patch: int
    board_id: int = 0

    def pack(self) -> bytes:
        return self.STRUCT.pack(self.protocol, self.fw_major, self.fw_minor, self.fw_patch, self.board_id)


@dataclass(frozen=True, slots=True)
class VersionRequest:
    STRUCT: ClassVar[struct.Struct] = struct.Struct("<B")
    TYPE: ClassVar[int] = MsgType.VERSION_REQUEST
    protocol: int = PROTOCOL_VERSION

    def pack(self) -> bytes:
        return self.STRUCT.pack(self.protocol)


@dataclass(frozen=True, slots=True)
class HostPose:
    """The SLAM pose forwarded to the MCU: LOCAL_FRD position [m], yaw [rad], quality, reset."""

    STRUCT: ClassVar[struct.Struct] = struct.Struct("<ffffbB")
    TYPE: ClassVar[int] = MsgType.HOST_POSE
    x_m: float
    y_m: float
    z_m: float
    yaw_rad: float
    quality: int
    reset_counter: int

    def pack(self) -> bytes:
        return self.STRUCT.pack(
            self.x_m, self.y_m, self.z_m, self.yaw_rad, max(-128, min(127, self.quality)), self.reset_counter & 0xFF
        )


Message = WheelOdometry | ControlInputs | Heartbeat | Version | VersionRequest | HostPose
_MESSAGES: dict[int, type] = {
    cls.TYPE: cls for cls in (WheelOdometry, ControlInputs, Heartbeat, Version, VersionRequest, HostPose)
}


def _i32(v: int) -> int:
    """Wrap an integer onto int32 (tick counters roll over on the MCU)."""
    return ((int(v) + (1 << 31)) % U32) - (1 << 31)


@dataclass(frozen=True, slots=True)
class Frame:
    """One decoded frame: header fields and the parsed message."""

    ver: int
    kind: int
    seq: int
    t_mcu_us: int
    msg: Message


def encode_body(kind: int, seq: int, t_mcu_us: int, payload: bytes, ver: int = PROTOCOL_VERSION) -> bytes:
    """Header + payload + CRC, before stuffing."""
    body = HEADER.pack(ver, kind, seq % U16, t_mcu_us % U32) + payload
    return body + CRC.pack(crc16(body))


def encode_frame(msg: Message, seq: int, t_mcu_us: int, ver: int = PROTOCOL_VERSION) -> bytes:
    """A complete wire frame: COBS-stuffed body and CRC, then the 0x00 delimiter."""
    return cobs_encode(encode_body(msg.TYPE, seq, t_mcu_us, msg.pack(), ver)) + b"\x00"


class CrcError(ProtocolError):
    pass


class CobsError(ProtocolError):
    pass


def decode_frame(encoded: bytes) -> Frame:
    """Decode one frame (COBS bytes, with or without the trailing 0x00).

    Raises :class:`CobsError`, :class:`CrcError` or :class:`ProtocolError` (short, unknown type,
    wrong payload length, foreign version) with the numbers in the message.
    """
    if encoded.endswith(b"\x00"):
        encoded = encoded[:-1]
    if len(encoded) > MAX_ENCODED:
        raise ProtocolError(f"frame too long: {len(encoded)} bytes, cap {MAX_ENCODED}")
    try:
        body = cobs_decode(encoded)
    except ProtocolError as exc:
        raise CobsError(str(exc)) from None
    if len(body) < HEADER.size + CRC.size:
        raise ProtocolError(f"frame too short: {len(body)} bytes, need at least {HEADER.size + CRC.size}")
    (got,) = CRC.unpack_from(body, len(body) - CRC.size)
    want = crc16(body[: -CRC.size])
    if got != want:
        raise CrcError(f"CRC mismatch: got 0x{got:04X}, computed 0x{want:04X} over {len(body) - 2} bytes")
    ver, kind, seq, t_us = HEADER.unpack_from(body)
    if ver != PROTOCOL_VERSION:
        raise ProtocolError(f"protocol version {ver}, expected {PROTOCOL_VERSION}")
    cls = _MESSAGES.get(kind)
    if cls is None:
        raise ProtocolError(f"unknown message type 0x{kind:02X} (seq {seq})")
    payload = body[HEADER.size : -CRC.size]
    st: struct.Struct = cls.STRUCT  # type: ignore[attr-defined]
    if len(payload) != st.size:
        raise ProtocolError(f"type 0x{kind:02X}: payload {len(payload)} bytes, expected {st.size}")
    return Frame(ver, kind, seq, t_us, cls(*st.unpack(payload)))


@dataclass
class DecoderStats:
    frames: int = 0
    crc_errors: int = 0
    cobs_errors: int = 0
    other_errors: int = 0  # short, unknown type, wrong length, foreign version
    oversize: int = 0
    resyncs: int = 0  # times bytes were discarded up to the next 0x00
    bytes_in: int = 0


@dataclass
class FrameDecoder:
    """Stream decoder: feed arbitrary chunks, get whole frames back; never raises on garbage.

    Bytes accumulate until a 0x00; a chunk longer than :data:`MAX_ENCODED` without a delimiter is
    discarded (counted as ``oversize`` and ``resyncs``) and the decoder skips to the next 0x00.
    Any bad frame is counted and skipped, which is exactly a resync at the next delimiter.
    """

    stats: DecoderStats = field(default_factory=DecoderStats)
    _buf: bytearray = field(default_factory=bytearray)
    _skipping: bool = False

    def feed(self, data: bytes) -> list[Frame]:
        self.stats.bytes_in += len(data)
        out: list[Frame] = []
        start = 0
        while True:
            idx = data.find(b"\x00", start)
            if idx < 0:
                self._append(data[start:])
                return out
            chunk = data[start:idx]
            start = idx + 1
            if self._skipping:
                self._skipping = False
                self._buf.clear()
                continue
            if self._buf:
                self._buf += chunk
                chunk = bytes(self._buf)
                self._buf.clear()
            if not chunk:
                continue  # back-to-back delimiters are legal idle filler
            if len(chunk) > MAX_ENCODED:
                self.stats.oversize += 1
                self.stats.resyncs += 1
                continue
            try:
                out.append(decode_frame(chunk))
                self.stats.frames += 1
            except CrcError:
                self.stats.crc_errors += 1
                self.stats.resyncs += 1
            except CobsError:
                self.stats.cobs_errors += 1
                self.stats.resyncs += 1
            except ProtocolError:
                self.stats.other_errors += 1
                self.stats.resyncs += 1

    def _append(self, data: bytes) -> None:
        if self._skipping or not data:
            return
        self._buf += data
        if len(self._buf) > MAX_ENCODED:
            # no delimiter where one must have been: drop and wait for the next 0x00
            self._buf.clear()
            self._skipping = True
            self.stats.oversize += 1
            self.stats.resyncs += 1


# ---------------------------------------------------------------------------------------------
# Sequence numbers


def seq_gap(prev: int, seq: int) -> int:
    """Frames missing between ``prev`` and ``seq`` (16-bit, wrapping); 0 for consecutive.

    A negative or implausibly large step (half the space or more) is a duplicate, reordering or
    restart; it returns -1 so the caller can decide (a restart at 0 is an MCU reset).
    """
    d = (seq - prev) % U16
    if d == 0 or d >= U16 // 2:
        return -1
    return d - 1


# ---------------------------------------------------------------------------------------------
# MCU clock -> host clock


@dataclass
class ClockMapper:
    """Map MCU timestamps (u32 µs, wrapping every ~71.6 min) onto the host monotonic clock [ns].

    Minimum-latency filter (docs/interfaces.md §5.2): every frame gives a sample
    ``o = t_host_arrival − t_mcu`` = true offset + transport latency (≥ 0); the smallest ``o`` in a
    sliding window is the best offset estimate, since the fastest frame had the least delay. The
    window (default 5 s) is short enough that a 100 ppm crystal drifts only 0.5 ms within it.
    The wrap is handled by unwrapping ``t_mcu`` into a 64-bit count: a step forward of less than
    2³¹ µs is progress, anything else is a small step backwards (reordering).
    """

    window_ns: int = 5_000_000_000
    _last_raw: int | None = None
    _unwrapped_us: int = 0
    _samples: deque[tuple[int, int]] = field(default_factory=deque)  # (t_host_ns, offset_ns), offsets increasing
    n_samples: int = 0

    def reset(self) -> None:
        """Forget everything (MCU reset: its clock restarted)."""
        self._last_raw = None
        self._unwrapped_us = 0
        self._samples.clear()

    def unwrap(self, t_mcu_us: int) -> int:
        """Unwrapped MCU time [µs]; advances the internal state."""
        t_mcu_us %= U32
        if self._last_raw is None:
            self._unwrapped_us = t_mcu_us
        else:
            d = (t_mcu_us - self._last_raw) % U32
            self._unwrapped_us += d if d < U32 // 2 else d - U32
        self._last_raw = t_mcu_us
        return self._unwrapped_us

    def peek_unwrap(self, t_mcu_us: int) -> int:
        """Unwrapped time of ``t_mcu_us`` relative to the last sample, without changing state."""
        if self._last_raw is None:
            return t_mcu_us % U32
        d = (t_mcu_us % U32 - self._last_raw) % U32
        return self._unwrapped_us + (d if d < U32 // 2 else d - U32)

    def observe(self, t_mcu_us: int, t_host_ns: int) -> int:
        """Add one (MCU stamp, host arrival) pair; return the MCU stamp mapped onto the host clock."""
        mcu_ns = self.unwrap(t_mcu_us) * 1000
        off = t_host_ns - mcu_ns
        # monotonic deque: drop samples that can never be the minimum again
        while self._samples and self._samples[-1][1] >= off:
            self._samples.pop()
        self._samples.append((t_host_ns, off))
        while self._samples[0][0] < t_host_ns - self.window_ns:
            self._samples.popleft()
        self.n_samples += 1
        return mcu_ns + self._samples[0][1]

    @property
    def offset_ns(self) -> int | None:
        """Current estimate of host − MCU [ns] (includes the minimum transport latency)."""
        return self._samples[0][1] if self._samples else None

    def to_host_ns(self, t_mcu_us: int) -> int:
        """Map an MCU stamp near the latest one onto the host clock (needs at least one sample)."""
        if not self._samples:
            raise ProtocolError("clock mapping has no samples yet")
        return self.peek_unwrap(t_mcu_us) * 1000 + self._samples[0][1]


# ---------------------------------------------------------------------------------------------
# Differential drive (docs/interfaces.md §1.8; docs/math.md §1.2: FRD, positive yaw turns right)


@dataclass(frozen=True, slots=True)
class WheelGeometry:
    """Wheel radius [m], encoder ticks per wheel revolution, track width W [m]."""

    wheel_radius_m: float = 0.05
    ticks_per_rev: float = 1024.0
    track_width_m: float = 0.30

    def __post_init__(self) -> None:
        for name in ("wheel_radius_m", "ticks_per_rev", "track_width_m"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                raise ProtocolError(f"WheelGeometry.{name}: expected a positive finite number, got {v!r}")

    @property
    def m_per_tick(self) -> float:
        return 2.0 * math.pi * self.wheel_radius_m / self.ticks_per_rev


def tick_delta(prev: int, now: int) -> int:
    """Signed int32 tick difference across the counter wrap."""
    return _i32(now - prev)


def diff_drive(ds_l_m: float, ds_r_m: float, track_width_m: float) -> tuple[float, float]:
    """Wheel travel -> body increment: Δx = (Δs_l + Δs_r)/2, FRD yaw Δψ = (Δs_l − Δs_r)/W.

    A left wheel that travels further turns the vehicle right, i.e. positive FRD yaw.
    Works equally on speeds (m/s -> m/s, rad/s).
    """
    return 0.5 * (ds_l_m + ds_r_m), (ds_l_m - ds_r_m) / track_width_m
