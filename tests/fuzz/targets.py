"""The five fuzz targets of issue 15: their seed corpora, their mutations and their oracles, in one
place for the property tests (``tests/fuzz/test_fuzz_*.py``, where hypothesis makes the choices)
and ``bench/fuzz.py`` (long runs, where a seeded ``random.Random`` makes them, 10⁶ inputs).

An oracle takes one input and either returns a short outcome label (``"refused"``, ``"loaded"``,
...) or raises: an exception outside the target's documented clean-error contract, or an
``AssertionError`` for a broken invariant (non-finite odometry handed on, an intact frame lost, a
two-line error message). docs/reliability.md states each contract.

Each target class has ``setup()`` (build the seed corpus: real frames, real pymavlink messages, the
shipped configuration, real saved maps, a real recording), ``generate(rng) -> Case`` (one input,
deterministic from ``rng``) and ``check(case) -> str`` (the oracle).
"""

from __future__ import annotations

import base64
import logging
import math
import random
import struct
import tempfile
import time
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, TypeVar

import numpy as np

from tests.support.paths import REPO

T = TypeVar("T")

# ------------------------------------------------------------------------------------ choices


class Choices(Protocol):
    """Where a mutation's choices come from: hypothesis (``Drawn``) or a seeded ``random.Random``."""

    def choice(self, seq: Sequence[T]) -> T: ...

    def randint(self, a: int, b: int) -> int: ...


class Drawn:
    """``Choices`` drawn by hypothesis (so that it can shrink a failing input): ``Drawn(data.draw)``
    in a test given ``st.data()``, ``Drawn(draw)`` in a composite strategy."""

    def __init__(self, draw: Callable[[Any], Any]) -> None:
        from hypothesis import strategies as st

        self._draw, self._st = draw, st

    def choice(self, seq: Sequence[T]) -> T:
        return self._draw(self._st.sampled_from(seq))

    def randint(self, a: int, b: int) -> int:
        return self._draw(self._st.integers(a, b))


@dataclass(frozen=True)
class Case:
    """One input: its bytes (what a reproducer file holds) and what the oracle needs besides them
    (the serial frames it was made from, the map's filter)."""

    data: bytes
    context: Any = None


# ------------------------------------------------------------------------ generic byte mutations

INTERESTING_INTS: tuple[int, ...] = (0, 1, 0x7F, 0x80, 0xFF, 0x7FFF, 0x8000, 0xFFFF, 2**31 - 1, 2**31, 2**32 - 1)
INTERESTING_INTS += (2**63 - 1, 2**63, 2**64 - 1, 2**40, 100, 1000, 65536)


def mutate_bytes(data: bytes, rng: random.Random, n: int, donors: Sequence[bytes] = ()) -> bytes:
    """``n`` mutations of ``data``: bit flips, random bytes, insertions, deletions, splices from
    ``donors`` (or from ``data`` itself), interesting integers (1, 2, 4 or 8 bytes, either
    endianness) written over it, a truncation, a block duplicated."""
    b = bytearray(data)
    for _ in range(n):
        kind = rng.randrange(9)
        at = rng.randint(0, len(b))
        if kind == 0 and at < len(b):
            b[at] ^= 1 << rng.randrange(8)
        elif kind == 1 and at < len(b):
            b[at] = rng.randrange(256)
        elif kind == 2:
            b[at:at] = rng.randbytes(rng.randint(1, 16))
        elif kind == 3:
            del b[at : at + rng.randint(1, 16)]
        elif kind == 4:
            donor = rng.choice(donors) if donors else bytes(b)
            if donor:
                start = rng.randrange(len(donor))
                piece = donor[start : start + rng.randint(1, 64)]
                end = at + (len(piece) if rng.random() < 0.5 else 0)  # overwrite, or insert
                b[at:end] = piece
        elif kind in (5, 6):
            width = rng.choice((1, 2, 4, 8))
            value = rng.choice(INTERESTING_INTS) % (1 << (8 * width))
            b[at : at + width] = value.to_bytes(width, rng.choice(("little", "big")))
        elif kind == 7:
            del b[rng.randint(0, len(b)) :]
        elif b:
            start = rng.randrange(len(b))
            b[at:at] = b[start : start + rng.randint(1, 64)]
    return bytes(b)


def float32(x: float) -> float:
    """``x`` as the float32 a wire format carries (so a round trip compares bit for bit)."""
    with np.errstate(over="ignore"):
        return float(np.float32(x))


ODD_FLOATS = (math.nan, math.inf, -math.inf, 3.0e38, -3.0e38, 1e-40, 0.0, -0.0, -1.0, 1e10)


# ======================================================================================= serial


def serial_link(wheel_source: str = "ticks") -> Any:
    """A serial link (never opened: no port) whose handler the fuzz tests call directly."""
    from drivers.serial_link import SerialVehicle

    return SerialVehicle("serial:///dev/robotd-fuzz-not-opened?track_width_m=0.3", wheel_source=wheel_source)


def encode_stream(msgs: Sequence[Any]) -> tuple[bytes, list[tuple[int, int]]]:
    """Frames ``msgs`` (seq i, t_mcu 1000·i µs) end to end; the [start, end) span of each frame."""
    from drivers.serial_protocol import encode_frame

    stream = bytearray()
    spans = []
    for i, msg in enumerate(msgs):
        start = len(stream)
        stream += encode_frame(msg, i, 1000 * i)
        spans.append((start, len(stream)))
    return bytes(stream), spans


def mutate_stream(stream: bytes, mutations: Sequence[tuple[str, int, bytes]]) -> tuple[bytes, set[int]]:
    """Apply the mutations (kind ``flip``/``zero``/``insert``/``delete``, position, bytes); return
    the result and the original positions they touched (a byte changed or deleted, or a neighbour
    of an insertion or deletion)."""
    cells: list[tuple[int, int | None]] = [(b, i) for i, b in enumerate(stream)]  # (byte, origin)
    touched: set[int] = set()

    def touch(k: int) -> None:
        if 0 <= k < len(cells) and cells[k][1] is not None:
            touched.add(cells[k][1])  # type: ignore[arg-type]

    for kind, pos, data in mutations:
        pos %= len(cells) + 1
        if kind in ("flip", "zero") and pos < len(cells):
            touch(pos)
            b = cells[pos][0] ^ (data[0] or 1) if kind == "flip" else 0
            cells[pos] = (b, cells[pos][1])
        elif kind == "insert":
            touch(pos - 1)
            touch(pos)
            cells[pos:pos] = [(b, None) for b in data]
        elif kind == "delete":
            n = min(len(data), len(cells) - pos)
            for k in range(pos - 1, pos + n + 1):
                touch(k)
            del cells[pos : pos + n]
    return bytes(b for b, _ in cells), touched


def same_message(a: object, b: object) -> bool:
    """Equal field by field, NaN equal to NaN (float32 fields round-trip bit for bit)."""
    if type(a) is not type(b):
        return False
    for f in type(a).__dataclass_fields__:  # type: ignore[attr-defined]
        x, y = getattr(a, f), getattr(b, f)
        if isinstance(x, float) and math.isnan(x):
            if not (isinstance(y, float) and math.isnan(y)):
                return False
        elif isinstance(x, float):
            if struct.pack("<f", x) != struct.pack("<f", y):
                return False
        elif x != y:
            return False
    return True


def check_decoded_stream(
    msgs: Sequence[Any], spans: Sequence[tuple[int, int]], mutated: bytes, touched: set[int], cuts: Sequence[int]
) -> list[Any]:
    """Feed ``mutated`` to a FrameDecoder in pieces of ``cuts`` bytes (then the rest): it never
    raises, and every frame whose bytes and preceding delimiter are intact is decoded, in order (a
    mutation may, with CRC luck, add frames between). Returns the decoded frames."""
    from drivers.serial_protocol import FrameDecoder

    dec = FrameDecoder()
    got = []
    pos = 0
    for c in [*cuts, len(mutated)]:
        got += dec.feed(mutated[pos : pos + c])
        pos += c
    got += dec.feed(mutated[pos:])
    intact = [(i, m) for i, (m, (a, b)) in enumerate(zip(msgs, spans)) if not touched & set(range(a - 1, b))]
    it = iter((f.seq, f.msg) for f in got)
    for i, m in intact:
        assert any(seq == i and same_message(msg, m) for seq, msg in it), f"frame {i} ({m}) lost"
    return got


def check_serial_handler(link: Any, frames: Sequence[Any], t_host_ns: Sequence[int]) -> int:
    """What the reader thread does with decoded frames: ``_handle`` each at its arrival time, a
    ``RobotdError`` counted as a bad value (nothing else may come out); then every odometry sample
    is finite and the plausibility gate refuses (and counts) the implausible ones, and the controls
    are within ±1. Returns the number of bad values."""
    from robotd.core.errors import RobotdError
    from tests.support.odometry_checks import assert_finite_and_gated

    bad = 0
    for fr, t in zip(frames, t_host_ns, strict=True):
        try:
            link._handle(fr, t)
        except RobotdError:
            bad += 1
    samples = link.drain()
    assert len(samples) == link.stats()["odometry"]
    assert_finite_and_gated(samples)
    ctl = link.latest_controls()
    assert ctl is None or (abs(ctl.throttle) <= 1.0 and abs(ctl.steering) <= 1.0)
    link._link.closed()
    return bad


class SerialTarget:
    """A stream of real frames (wheel odometry that mostly makes sense, with odd values among it:
    tick jumps, NaN and ±3e38 speeds, controls beyond ±1, MCU resets), damaged by
    ``mutate_stream``, fed to the decoder in random pieces (intact frames must come out), and the
    decoded frames through the link's handler, its odometry from ticks or from wheel speeds
    (nothing but counted errors; finite, gated odometry).
    A raw piece also goes through ``decode_frame`` alone (only ``ProtocolError``)."""

    name = "serial"

    def setup(self) -> None:
        pass

    def _message(self, rng: random.Random, state: list[int]) -> Any:
        from drivers.serial_protocol import ControlInputs, Heartbeat, Version, WheelOdometry

        k = rng.randrange(10)
        if k < 6:
            odd = rng.random() < 0.2
            for w in (0, 1):  # cumulative ticks: a few a frame, or a jump (the campaign's 0 -> 2^31 - 1)
                jump = odd and rng.random() < 0.5
                state[w] += rng.choice((2**31 - 1, -(2**31), 10**6, -1)) if jump else rng.randint(0, 40)
            vel = [rng.uniform(-2, 2) if not odd or rng.random() < 0.5 else rng.choice(ODD_FLOATS) for _ in (0, 1)]
            ticks = [((v + 2**31) % 2**32) - 2**31 for v in state]
            flags = rng.choice((1, 2, 3, 3, 3, 0, 255))
            return WheelOdometry(flags, ticks[0], ticks[1], float32(vel[0]), float32(vel[1]))
        if k < 8:
            vals = [rng.uniform(-1, 1) if rng.random() < 0.8 else rng.choice(ODD_FLOATS) for _ in (0, 1)]
            return ControlInputs(float32(vals[0]), float32(vals[1]))
        if k < 9:
            uptime_ms = (rng.choice((0, 1000, 2**32 - 1)) + rng.randint(0, 10**6)) % 2**32  # resets, wraps
            return Heartbeat(rng.choice((0, 0, 1, 2, 255)), uptime_ms, rng.randrange(2**16))
        major, minor, patch = (rng.randrange(256) for _ in range(3))
        return Version(rng.choice((1, 1, 2, 255)), major, minor, patch, rng.randrange(2**16))

    def generate(self, rng: random.Random) -> Case:
        state = [0, 0]
        msgs = [self._message(rng, state) for _ in range(rng.randint(1, 25))]
        stream, spans = encode_stream(msgs)
        mutations = []
        for _ in range(rng.choice((0, 1, 1, 2, 3, 6))):
            kind = rng.choice(("flip", "insert", "delete", "zero"))
            mutations.append((kind, rng.randrange(10**6), rng.randbytes(rng.randint(1, 40))))
        mutated, touched = mutate_stream(stream, mutations)
        cuts = [rng.randint(1, 97) for _ in range(rng.randint(0, 30))]
        return Case(mutated, (msgs, spans, touched, cuts, rng.choice(("ticks", "velocity"))))

    def check(self, case: Case) -> str:
        from drivers.serial_protocol import decode_frame
        from robotd.core.errors import ProtocolError

        msgs, spans, touched, cuts, wheel_source = case.context
        try:
            decode_frame(case.data[: 1 + len(case.data) // 3])
        except ProtocolError:
            pass
        frames = check_decoded_stream(msgs, spans, case.data, touched, cuts)
        # the handler sees the frames with the MCU times they carry, arriving 10 ms apart
        bad = check_serial_handler(serial_link(wheel_source), frames, [10**12 + 10**7 * k for k in range(len(frames))])
        return "bad values" if bad else "clean"


# ====================================================================================== mavlink

MAVLINK_KINDS = (
    "HEARTBEAT",
    "SYSTEM_TIME",
    "TIMESYNC",
    "ATTITUDE",
    "WHEEL_DISTANCE",
    "LOCAL_POSITION_NED",
    "SERVO_OUTPUT_RAW",
    "RC_CHANNELS",
    "EKF_STATUS_REPORT",
    "GPS_GLOBAL_ORIGIN",
    "COMMAND_ACK",  # the answers to the rate requests
)
INT_RANGES = {
    "uint8_t": (0, 255),
    "int8_t": (-128, 127),
    "uint16_t": (0, 0xFFFF),
    "int16_t": (-(1 << 15), (1 << 15) - 1),
    "uint32_t": (0, (1 << 32) - 1),
    "int32_t": (-(1 << 31), (1 << 31) - 1),
    "uint64_t": (0, (1 << 64) - 1),
    "int64_t": (-(1 << 63), (1 << 63) - 1),
}
AUTOPILOT = (1, 1)  # the autopilot's system and component id in the fuzz runs


def mavlink_classes() -> dict[str, Any]:
    from drivers.mavlink_link import mavlink_module

    m = mavlink_module()
    return {k: getattr(m, f"MAVLink_{k.lower()}_message") for k in MAVLINK_KINDS}


def mavlink_wire(msg: Any, sysid: int, compid: int) -> bytes:
    """``msg`` packed as ``sysid``/``compid``: the bytes on the wire."""
    from drivers.mavlink_link import mavlink_module

    return bytes(msg.pack(mavlink_module().MAVLink(None, srcSystem=sysid, srcComponent=compid)))


def mavlink_parse(wire: bytes) -> Any:
    """One message's bytes parsed back: what the receive thread would see."""
    from drivers.mavlink_link import mavlink_module

    return mavlink_module().MAVLink(None).decode(bytearray(wire))


def mavlink_link_with_autopilot(t_ns: int) -> Any:
    """A MAVLink link (never opened: no socket) that has heard the autopilot's heartbeat (1, 1)."""
    from drivers.mavlink_link import MavlinkVehicle, mavlink_module

    m = mavlink_module()
    link = MavlinkVehicle("mavlink+udp://127.0.0.1:14550", track_width_m=0.4)
    link._conn = type("Conn", (), {"mav": m.MAVLink(None)})()  # the heartbeat sets our srcSystem on it
    hb = m.MAVLink_heartbeat_message(m.MAV_TYPE_GROUND_ROVER, m.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4, 3)
    link._dispatch(mavlink_parse(mavlink_wire(hb, *AUTOPILOT)), t_ns, None)
    return link


def _used_values_bad(msg: Any) -> bool:
    """ATTITUDE and WHEEL_DISTANCE (wheels 0 and 1) carrying a non-finite value the link reads."""
    kind = msg.get_type()
    if kind == "ATTITUDE":
        vals = [msg.roll, msg.pitch, msg.yaw, msg.rollspeed, msg.pitchspeed, msg.yawspeed]
    elif kind == "WHEEL_DISTANCE":
        vals = list(msg.distance[:2])
    else:
        return False
    return not all(math.isfinite(v) for v in vals)


def dispatch_checked(link: Any, rx: Any, t_ns: int) -> None:
    """The link's dispatch of one received message never raises, and a non-finite value it reads
    from the autopilot is counted in ``bad_values``."""
    before = link.c["bad_values"]
    link._dispatch(rx, t_ns, None)
    if rx.get_type() == "BAD_DATA":
        return
    if (rx.get_srcSystem(), rx.get_srcComponent()) == AUTOPILOT and _used_values_bad(rx) and link.autopilot_sysid == 1:
        if rx.get_type() == "ATTITUDE" or rx.count > 1:  # wheels 0 and 1 exist
            assert link.c["bad_values"] == before + 1, rx


def check_mavlink_link(link: Any, foreign: int) -> None:
    """After the messages: every odometry sample finite and gated, the controls from PWM within
    800–2200 µs, nobody else took the autopilot's place, and the ``foreign`` messages (not
    heartbeats, from other senders) counted as rejected."""
    from tests.support.odometry_checks import assert_finite_and_gated

    samples = link.drain()
    assert len(samples) == link.c["odometry"]
    assert_finite_and_gated(samples)
    ctl = link.latest_controls()
    assert ctl is None or (abs(ctl.throttle) <= 1.4 and abs(ctl.steering) <= 1.4)  # 800–2200 µs
    st_ = link.stats()
    assert st_["autopilot_sysid"] == 1
    assert st_["rejected_source"] >= foreign


class MavlinkTarget:
    """Messages of every type robotd reads, with field values anywhere in their type's range or
    odd (NaN, ±inf, ±3e38, extremes), packed by pymavlink as senders (mostly the autopilot), the
    byte stream damaged by ``mutate_bytes``, parsed by pymavlink as the receive thread does
    (robust parsing; the loop survives ``OSError``/``ValueError`` only) and dispatched. Oracle:
    ``dispatch_checked`` and ``check_mavlink_link``."""

    name = "mavlink"
    SENDERS = ((1, 1), (1, 1), (1, 1), (1, 1), (2, 1), (1, 7))

    def setup(self) -> None:
        self.classes = mavlink_classes()
        self.kinds = sorted(self.classes)

    def _value(self, rng: random.Random, ftype: str) -> Any:
        if ftype in INT_RANGES:
            lo, hi = INT_RANGES[ftype]
            r = rng.random()  # plausible, an extreme, or anywhere in the range
            if r < 0.5:
                return rng.randint(0, min(hi, 1000))
            return rng.choice((lo, hi, 0)) if r < 0.7 else rng.randint(lo, hi)
        if ftype in ("float", "double"):
            r = rng.random()
            if r < 0.5:
                x = rng.uniform(-10, 10)
            else:
                x = rng.choice(ODD_FLOATS) if r < 0.8 else rng.uniform(-1, 1) * 10.0 ** rng.randint(-40, 38)
            return float32(x) if ftype == "float" else x
        if ftype == "char":
            return rng.choice((b"", b"x", b"\xff"))
        raise AssertionError(ftype)

    def _message(self, rng: random.Random) -> Any:
        cls = self.classes[rng.choice(self.kinds)]
        lengths = dict(zip(cls.ordered_fieldnames, cls.array_lengths, strict=True))
        args = []
        for name, ftype in zip(cls.fieldnames, cls.fieldtypes, strict=True):
            n = lengths.get(name, 0)
            args.append([self._value(rng, ftype) for _ in range(n)] if n else self._value(rng, ftype))
        return cls(*args)

    def generate(self, rng: random.Random) -> Case:
        wire = bytearray()
        for _ in range(rng.randint(1, 30)):
            wire += mavlink_wire(self._message(rng), *rng.choice(self.SENDERS))
        n = rng.choice((0, 0, 1, 1, 2, 4, 8))
        return Case(mutate_bytes(bytes(wire), rng, n) if n else bytes(wire))

    def check(self, case: Case) -> str:
        from drivers.mavlink_link import mavlink_module

        t_ns = 10**12
        link = mavlink_link_with_autopilot(t_ns)
        rx = mavlink_module().MAVLink(None)
        rx.robust_parsing = True  # as mavutil sets it
        try:
            msgs = rx.parse_buffer(bytearray(case.data)) or []
        except (OSError, ValueError):  # what the receive loop catches (it logs and reads on)
            return "parse error"
        foreign = 0
        for msg in msgs:
            t_ns += 20_000_000
            dispatch_checked(link, msg, t_ns)
            if msg.get_type() in MAVLINK_KINDS and msg.get_type() != "HEARTBEAT":  # not BAD_DATA, UNKNOWN_n
                foreign += (msg.get_srcSystem(), msg.get_srcComponent()) != AUTOPILOT
        check_mavlink_link(link, foreign)
        return "bad data" if link.c["bad_data"] else "clean"


# ======================================================================================= config

SHIPPED_CONFIG = (REPO / "config" / "robotd.toml").read_text(encoding="utf-8")
CONFIG_TOKENS = (b"[", b"]", b'"', b"=", b"\n", b"\\u", b"[[", b"{", b"}", b"'''", b"#", b".", b",")


def config_sections() -> dict[str, list[str]]:
    import dataclasses

    from robotd.config import Config

    return {f.name: [g.name for g in dataclasses.fields(getattr(Config(), f.name))] for f in dataclasses.fields(Config)}


def toml_key(k: str) -> str:
    bare = k and all(c.isascii() and (c.isalnum() or c in "_-") for c in k)
    return k if bare else toml_string(k)


def toml_string(s: str) -> str:
    out = []
    for c in s:
        if c in '"\\':
            out.append("\\" + c)
        elif ord(c) < 0x20 or ord(c) == 0x7F:
            out.append(f"\\u{ord(c):04X}")
        else:
            out.append(c)
    return '"' + "".join(out) + '"'


def toml_value(v: Any) -> str:
    import datetime

    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) else repr(v)
    if isinstance(v, str):
        return toml_string(v)
    if isinstance(v, datetime.datetime | datetime.date | datetime.time):
        return v.isoformat()
    if isinstance(v, list):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{toml_key(k)} = {toml_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(type(v))


def toml_document(tree: dict[str, Any]) -> str:
    """A TOML document of ``tree`` (written here, independent of robotd's own writer)."""
    lines: list[str] = []
    tables: list[tuple[str, dict[str, Any]]] = []
    for k, v in tree.items():
        if isinstance(v, dict) and v and not any(isinstance(x, dict) for x in v.values()):
            tables.append((k, v))
        else:
            lines.append(f"{toml_key(k)} = {toml_value(v)}")
    for name, body in tables:
        lines.append(f"[{toml_key(name)}]")
        lines += [f"{toml_key(k)} = {toml_value(x)}" for k, x in body.items()]
    return "\n".join(lines) + "\n"


def damage_text(data: bytes, c: Choices, n: int, chunk: Callable[[], bytes]) -> bytes:
    """``n`` insertions, deletions or replacements of a ``chunk()`` at chosen places."""
    b = bytearray(data)
    for _ in range(n):
        at = c.randint(0, len(b))
        kind = c.choice(("insert", "delete", "replace"))
        piece = chunk()
        if kind == "insert":
            b[at:at] = piece
        elif kind == "delete":
            del b[at : at + len(piece)]
        else:
            b[at : at + len(piece)] = piece
    return bytes(b)


def check_config(blob: bytes, tmp: Path) -> str:
    """The loader returns a Config or raises ConfigError with a one-line message; whatever it
    accepts, ``print-config`` (``to_toml``) writes back as TOML that loads to the same Config."""
    from robotd.config import load_config, to_toml
    from robotd.core.errors import ConfigError

    path = tmp / "c.toml"
    path.write_bytes(blob)
    try:
        cfg = load_config(path)
    except ConfigError as exc:
        msg = str(exc)
        assert msg and "\n" not in msg and "\r" not in msg, repr(msg)
        return "refused"
    out = tmp / "printed.toml"
    out.write_text(to_toml(cfg, with_docs=True), encoding="utf-8")
    assert load_config(out) == cfg
    return "loaded"


class ConfigTarget:
    """The shipped ``config/robotd.toml``, the rover example and documents written from the real
    keys with odd values (every TOML type, huge integers, NaN, control characters, deep arrays),
    damaged by TOML-token insertions/deletions and ``mutate_bytes``. Oracle: ``check_config``."""

    name = "config"
    ODD: tuple[Any, ...] = (
        0, -1, 1, 2**31, 2**63, -(2**63) - 1, 10**20, 10**400, 0.0, -0.0, 1e-320, 1e308, math.nan, math.inf,
        -math.inf, True, False, "", "x", "\x00", "a\nb", "\u202e", "sim://", "orb", "ekf", "fastslam2", "pixel",
        "tcp/127.0.0.1:7447", "none://", [], [1, "a"], [[[[]]]], {}, {"a": {"b": 1}},
    )  # fmt: skip

    def setup(self) -> None:
        self.sections = config_sections()
        self.bases = [SHIPPED_CONFIG.encode(), *(p.read_bytes() for p in sorted((REPO / "config").glob("*.toml")))]
        self.tmp = Path(tempfile.mkdtemp(prefix="robotd-fuzz-config-"))

    def _document(self, rng: random.Random) -> bytes:
        tree: dict[str, Any] = {}
        for _ in range(rng.randint(0, 8)):
            section = rng.choice(sorted(self.sections)) if rng.random() < 0.9 else rng.choice(("", "x", "slam.x"))
            key = rng.choice(self.sections.get(section) or ["x"]) if rng.random() < 0.9 else "unknown"
            value: Any = rng.choice(self.ODD)
            if rng.random() < 0.05:
                value = [value] * rng.randint(2, 5)
            tree.setdefault(section, {})[key] = value
        doc = toml_document(tree)
        if rng.random() < 0.02:  # deep nesting (tomllib recurses once per level)
            depth = rng.choice((100, 1000, 100_000))
            doc += "x = " + "[" * depth + "]" * depth + "\n"
        return doc.encode("utf-8", "surrogatepass")

    def generate(self, rng: random.Random) -> Case:
        blob = rng.choice(self.bases) if rng.random() < 0.6 else self._document(rng)
        kind = rng.random()
        if kind < 0.45:  # TOML's own characters, or random bytes, put in, cut out or written over

            def chunk() -> bytes:
                return rng.choice(CONFIG_TOKENS) if rng.random() < 0.5 else rng.randbytes(rng.randint(1, 6))

            blob = damage_text(blob, rng, rng.randint(1, 4), chunk)
        elif kind < 0.85:
            blob = mutate_bytes(blob, rng, rng.randint(1, 6), self.bases)
        return Case(blob)

    def check(self, case: Case) -> str:
        return check_config(case.data, self.tmp)


# ====================================================================================== mapfile

MAP_VARIANTS = (("fastslam2", 3), ("ekf", 3), ("fastslam1", 2))
ODD_VALUES: tuple[Any, ...] = (
    None,
    "x",
    b"\x00",
    True,
    0,
    -1,
    2**31,
    2**62,
    2**63 - 1,
    2**64,
    -(2**63),
    1.5,
    -0.0,
    float("nan"),
    float("inf"),
    -float("inf"),
    1e300,
    [],
    [1, 2],
    {},
    {"a": 1},
    np.zeros(0),
    np.zeros((2, 2)),
    np.zeros(3, np.int64),
    np.array(["a"]),
)
ODD_ELEMENTS = (float("nan"), float("inf"), -float("inf"), 1e300, -1e300, 1e20, -1.0, 0.0, 2**62, 2**63 - 1, -(2**63))
DTYPES = ("<f8", "<f4", "<i8", "<i4", "|u1", "|b1", "<c16", "<u8")
FORGED_HEADERS: tuple[dict[str, Any], ...] = (
    {"dtype": "f8,(2", "shape": [1], "data": b""},
    {"dtype": "O", "shape": [1], "data": b"\x00" * 8},
    {"dtype": "<f8", "shape": [-1], "data": b"\x00" * 16},
    {"dtype": "<f8", "shape": [2**40, 2**40], "data": b""},
    {"dtype": "(2,3)f8", "shape": [1], "data": b"\x00" * 48},
    {"dtype": "<U2", "shape": [1], "data": b"\x00" * 8},
    {"dtype": "<f8", "shape": [1], "data": "text"},
    {"dtype": "<f8", "shape": None, "data": b""},
    {"dtype": {"names": ["a"], "formats": ["<f8"]}, "shape": [1], "data": b"\x00" * 8},
)
SCALES = (-1.0, 0.0, 1e-300, 1e-3, 2.0, 10.0, 1e3, 1e7)
# the first six keep the structure (so that many mutated maps load and the filter runs on them)
ARRAY_OPS: tuple[str, ...] = ("scale", "scale", "element", "element", "element", "shuffle")
ARRAY_OPS += ("truncate", "dtype", "reshape", "swap", "forge")
VALUE_OPS = ("scale", "element", "element", "shuffle")


def _paths(tree: dict[str, Any], prefix: tuple[str, ...] = ()) -> list[tuple[str, ...]]:
    out: list[tuple[str, ...]] = []
    for k, v in tree.items():
        if isinstance(v, dict):
            out += [(*prefix, k), *_paths(v, (*prefix, k))]
        else:  # values are mutated more often than whole tables are dropped
            out += [(*prefix, k)] * 3
    return out


_PATHS: dict[tuple[str, int], list[tuple[str, ...]]] = {}  # filled on first use (the map is made then)


def map_paths(variant: tuple[str, int]) -> list[tuple[str, ...]]:
    """Every key path of the saved state of ``variant`` (leaves three times)."""
    from tests.support import saved_maps

    if variant not in _PATHS:
        _PATHS[variant] = _paths(saved_maps.saved_state(*variant))
    return _PATHS[variant]


def _get(tree: dict[str, Any], path: tuple[str, ...]) -> Any:
    for key in path:
        tree = tree[key]
    return tree


def mutate_array(a: np.ndarray, op: str, k: int, c: Choices) -> Any:
    """One mutation of an array; ``k`` picks the element or axis. The first kinds keep the map
    structurally valid (so that the filter runs on odd but plausible content), the others break it."""
    if a.dtype.kind not in "biufc":  # an array an earlier mutation put in (strings): replaced whole
        return c.choice(ODD_VALUES)
    if op == "scale" and a.size:  # every value scaled: a map from far away, covariances inflated, ...
        with np.errstate(all="ignore"):
            return a * np.asarray(c.choice(SCALES)).astype(a.dtype)
    if op == "element" and a.size:  # one value changed by a factor, or odd
        b = a.copy()
        flat = b.reshape(-1)
        with np.errstate(all="ignore"):
            value = c.choice((*(flat[k % a.size] * f for f in SCALES), *ODD_ELEMENTS))
            try:
                flat[k % a.size] = value
            except (OverflowError, ValueError, TypeError):
                flat[k % a.size] = np.iinfo(a.dtype).max if a.dtype.kind in "iu" else np.nan
        return b
    if op == "shuffle" and a.ndim:  # rows reordered (particles, landmarks, ids)
        return a[np.random.default_rng(k).permutation(a.shape[0])]
    if op == "truncate" and a.ndim:  # shortened (or emptied) along one axis
        axis = k % a.ndim
        return np.take(a, np.arange(a.shape[axis] // (2 + k % 3)), axis=axis)
    if op == "dtype":
        return a.astype(c.choice(DTYPES))
    if op == "reshape":
        return a.reshape((1, *a.shape)) if k % 2 else a.reshape(-1)
    if op == "swap" and a.ndim >= 2:
        return np.swapaxes(a, 0, 1).copy()
    if op == "forge":
        return {"__nd__": c.choice(FORGED_HEADERS)}
    return a


def mutate_map(state: dict[str, Any], variant: tuple[str, int], c: Choices) -> None:
    """One structural mutation: a key dropped, a value replaced by another type, an array changed
    (``ARRAY_OPS``), an integer or float nudged or made odd."""
    path = c.choice(map_paths(variant))
    parent: Any = state
    for key in path[:-1]:
        parent = parent.get(key) if isinstance(parent, dict) else None
        if not isinstance(parent, dict):
            return  # an earlier mutation removed or replaced the table
    key = path[-1]
    if key not in parent:
        return
    kind = c.choice(("drop", "replace", "tweak", "tweak", "tweak", "tweak"))
    old = parent[key]
    if kind == "drop":
        del parent[key]
    elif kind == "replace" or isinstance(old, dict | str | bool):
        parent[key] = c.choice(ODD_VALUES)
    elif isinstance(old, np.ndarray):
        op = c.choice(ARRAY_OPS)
        parent[key] = mutate_array(old, op, c.randint(0, 2**31), c)
    elif isinstance(old, int):
        parent[key] = c.choice((old + 1, old - 1, -old - 1, 0, 2**62, 2**63 - 1, 2**64, float(old)))
    elif isinstance(old, float):
        as_int = int(old) if math.isfinite(old) else 0
        parent[key] = c.choice((-old, old / 2, old * 1e6, 0.0, 1e-300, float("nan"), float("inf"), 1e308, as_int))


def mutate_map_values(state: dict[str, Any], variant: tuple[str, int], c: Choices) -> None:
    """One value mutation that keeps the structure (``VALUE_OPS`` on one array): about half of
    these maps load, so the filters run on odd but plausible content."""
    arrays = [p for p in map_paths(variant) if isinstance(_get(state, p), np.ndarray)]
    path = c.choice(arrays)
    parent = _get(state, path[:-1])
    parent[path[-1]] = mutate_array(parent[path[-1]], c.choice(VALUE_OPS), c.randint(0, 2**31), c)


class LogLines(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(record.getMessage())


def resume_and_run(blob: bytes, variant: tuple[str, int]) -> str:
    """Put ``blob`` in a state directory as ``map.robotd``, resume from it as the daemon does and
    step the pipeline three frames (relocalising first, then with the filter predicting and
    updating), publish its map and save. The outcome is a clean refusal (one ``resume failed``
    line; moved aside, or left for a mismatch; nothing reached the filter) or a filter that runs.
    Returns ``"resumed"`` or ``"refused"``."""
    from robotd.outputs.mapfile import MapFileOutput
    from tests.support import saved_maps

    frames, _ = saved_maps.sim_frames()
    log = LogLines()
    logger = logging.getLogger("robotd")
    level = logger.level
    logger.addHandler(log)
    logger.setLevel(logging.INFO)
    try:
        with tempfile.TemporaryDirectory() as tmp:
            state_dir = Path(tmp)
            (state_dir / "map.robotd").write_bytes(blob)
            pipeline = saved_maps.pipeline(*variant)
            out = MapFileOutput(saved_maps.config(*variant, state_dir=state_dir).persistence, "r1")
            try:
                resumed = out.resume(pipeline)
                if not resumed:
                    failed = [line for line in log.lines if line.startswith("resume failed")]
                    assert len(failed) == 1 and "\n" not in failed[0], log.lines
                    aside = list(state_dir.glob("map.robotd.bad-*"))
                    if "moved aside to" in failed[0]:
                        assert [a.read_bytes() for a in aside] == [blob] and not (state_dir / "map.robotd").exists()
                    else:  # a valid map of another configuration: left for keep_maps, untouched
                        assert not aside and (state_dir / "map.robotd").read_bytes() == blob, failed[0]
                    assert pipeline.estimator.landmark_ids().size == 0  # nothing reached the filter
                # a working filter: steps as the daemon does (relocalising first), then with the
                # filter predicting and updating, publishes its map and saves it
                pipeline.step(frames[saved_maps.N_MAP_FRAMES], None)
                pipeline.relocaliser.arm(0)
                for f in frames[saved_maps.N_MAP_FRAMES + 1 : saved_maps.N_MAP_FRAMES + 3]:
                    pipeline.step(f, None)
                pipeline.estimator.landmarks()
                assert out.save(pipeline.state_dict(), 2)
            finally:
                out.close()
    finally:
        logger.removeHandler(log)
        logger.setLevel(level)
    return "resumed" if resumed else "refused"


class MapfileTarget:
    """Real saved maps (FastSLAM 2.0 3-D, EKF 3-D, FastSLAM 1.0 2-D, from ``sim://`` frames)
    with a valid checksum and mutated content: 40 % structural (``mutate_map``, 1–3), 40 % values
    only (``mutate_map_values``, 1–3), 20 % the CBOR payload's bytes (``mutate_bytes``) resealed
    with a valid checksum. Oracle: ``resume_and_run``."""

    name = "mapfile"

    def setup(self) -> None:
        import logging as _logging

        from tests.support import saved_maps

        _logging.getLogger("robotd").propagate = False  # the oracle reads the lines; nobody prints them
        self.payloads = {v: saved_maps.payload(saved_maps.saved_state(*v)) for v in MAP_VARIANTS}
        for v in MAP_VARIANTS:
            map_paths(v)

    def generate(self, rng: random.Random) -> Case:
        from tests.support import saved_maps

        variant = rng.choice(MAP_VARIANTS)
        kind = rng.random()
        if kind < 0.8:
            state = saved_maps.saved_state(*variant)
            for _ in range(rng.randint(1, 3)):
                (mutate_map if kind < 0.4 else mutate_map_values)(state, variant, rng)
            return Case(saved_maps.seal(state), variant)
        payload = mutate_bytes(self.payloads[variant], rng, rng.randint(1, 4))
        return Case(saved_maps.seal_payload(payload), variant)

    def check(self, case: Case) -> str:
        return resume_and_run(case.data, case.context)


# ==================================================================================== recording

FORMAT1_RECORDING = REPO / "tests" / "support" / "data" / "format1_sim_160x100.mcap"
MCAP_MAGIC = b"\x89MCAP0\r\n"
PER_INPUT_S = 2.0  # a mutated input is read (twice) in well under this; the campaign saw 1–9.5 s


def recording_model() -> Any:
    from robotd.core.stereo import RectifiedStereo

    return RectifiedStereo(60.0, 32.0, 20.0, 0.075, 64, 40)


def small_recording(tmp: Path) -> bytes:
    """A small real format-2 recording (8 frames of 64×40, several chunks) by SessionWriter."""
    from robotd.core.msgs import Odometry, PoseEstimate, StereoFrame
    from robotd.formats.record import SessionWriter

    rng = np.random.default_rng(7)
    path = tmp / "small.mcap"
    # the wall clock fixed and no time-driven flushes: the same bytes in every process (bench/fuzz.py
    # makes an input again from its seed and index)
    with SessionWriter(
        path, recording_model(), {"source": "fuzz"}, chunk_size=6 * 1024, flush_period_s=3600.0, wall_offset_ns=0
    ) as w:
        for i in range(8):
            t = 1_000_000_000 + i * 33_333_333
            w.write_odometry(Odometry(t - 5, rng.normal(size=3), rng.normal(size=3), "sim", np.eye(6) * 0.01))
            img = (rng.integers(0, 40, (40, 64)) + np.arange(64) * 3).astype(np.uint8)
            w.write_frame(StereoFrame(t, i, img, np.roll(img, -3, axis=1), True, np.eye(4)))
            w.write_pose(PoseEstimate(t, rng.normal(size=3), rng.normal(size=3) * 0.1, np.eye(6), 50.0, 100))
    return path.read_bytes()


def records(data: bytes) -> list[tuple[int, int, int]]:
    """(offset, opcode, length) of the top-level records of an intact file (MCAP framing)."""
    out, pos = [], len(MCAP_MAGIC)
    while pos + 9 <= len(data) - len(MCAP_MAGIC):
        op, n = struct.unpack_from("<BQ", data, pos)
        out.append((pos, op, n))
        pos += 9 + n
    return out


def chunks(data: bytes) -> list[tuple[int, int]]:
    return [(off, n) for off, op, n in records(data) if op == 0x06]


def chunk_fields(data: bytes, off: int) -> tuple[int, int, str, int]:
    """(uncompressed-size field offset, crc field offset, compression, records offset)."""
    p = off + 9 + 16
    size_at, crc_at = p, p + 8
    (clen,) = struct.unpack_from("<I", data, p + 12)
    comp = data[p + 16 : p + 16 + clen].decode()
    return size_at, crc_at, comp, p + 16 + clen + 8


def rewrite_chunk(data: bytes, k: int, change: Callable[[bytes], bytes]) -> bytes:
    """Chunk k's records passed through ``change`` (bytes -> bytes), then recompressed with its
    sizes and CRC fixed: the framing stays valid, so the damage reaches the message decoders."""
    import zstandard

    cs = chunks(data)
    off, n = cs[k % len(cs)]
    size_at, crc_at, comp, rec_at = chunk_fields(data, off)
    (rlen,) = struct.unpack_from("<Q", data, rec_at - 8)
    body = data[rec_at : rec_at + rlen]
    raw = change(zstandard.decompress(body) if comp == "zstd" else body)
    new = zstandard.compress(raw) if comp == "zstd" else raw
    head = bytearray(data[off + 9 : rec_at - 8])
    struct.pack_into("<Q", head, size_at - off - 9, len(raw))
    struct.pack_into("<I", head, crc_at - off - 9, zlib.crc32(raw))
    rec = bytes(head) + struct.pack("<Q", len(new)) + new
    return data[:off] + struct.pack("<BQ", 0x06, len(rec)) + rec + data[off + 9 + n :]


def edit_png(data: bytes, k: int, edit: Callable[[bytes], bytes]) -> bytes:
    """The first PNG in chunk k passed through ``edit`` (PNG bytes -> PNG bytes of the same length),
    the chunk's CRC fixed; in format 1 the PNG is base64 in JSON."""

    def change(raw: bytes) -> bytes:
        b64 = raw.find(b"iVBORw0KGgo")  # format 1: the PNG is base64 in JSON (same length after editing)
        if b64 >= 0 and (raw.find(b"IHDR") < 0 or b64 < raw.find(b"IHDR")):
            end = raw.index(b'"', b64)
            return raw[:b64] + base64.b64encode(edit(base64.b64decode(raw[b64:end]))) + raw[end:]
        at = raw.find(b"\x89PNG\r\n\x1a\n")
        return raw if at < 0 else raw[:at] + edit(raw[at:])

    return rewrite_chunk(data, k, change)


def forge_png(data: bytes, k: int, width: int, height: int, depth: int) -> bytes:
    """The first PNG header in chunk k forged (IHDR width/height/bit depth) with a valid IHDR CRC
    and the chunk's CRC fixed, so only the image is wrong."""

    def forge(png: bytes) -> bytes:
        at = png.find(b"IHDR")
        if at < 0:
            return png
        ihdr = bytearray(png[at : at + 17])
        struct.pack_into(">IIB", ihdr, 4, width, height, depth)
        return png[:at] + bytes(ihdr) + struct.pack(">I", zlib.crc32(bytes(ihdr))) + png[at + 21 :]

    return edit_png(data, k, forge)


def forge_png_chunk_length(data: bytes, k: int, length: int, which: bytes = b"IDAT") -> bytes:
    """The stated length of the first ``which`` chunk of the first PNG in chunk k forged (what
    a PNG decoder may allocate before reading it), the recording's chunk CRC fixed."""

    def forge(png: bytes) -> bytes:
        at = png.find(which)
        if at < 4:
            return png
        return png[: at - 4] + struct.pack(">I", length % 2**32) + png[at:]

    return edit_png(data, k, forge)


def flip(data: bytes, flips: Sequence[tuple[float, int]]) -> bytes:
    """Each (where as a fraction of the length, xor mask) applied."""
    b = bytearray(data)
    for where, xor in flips:
        b[int(where * len(b))] ^= xor
    return bytes(b)


def duplicate_chunk(data: bytes, k: int, to: int) -> bytes:
    """Chunk k copied in front of top-level record ``to``."""
    off, n = chunks(data)[k % len(chunks(data))]
    at = records(data)[to % len(records(data))][0]
    return data[:at] + data[off : off + 9 + n] + data[at:]


def forge_length(data: bytes, k: int, length: int, field: str) -> bytes:
    """A record's length, or a chunk's stated uncompressed size (what a reader allocates)."""
    b = bytearray(data)
    if field == "record":
        off = records(data)[k % len(records(data))][0]
        struct.pack_into("<Q", b, off + 1, length)
    else:
        off, _ = chunks(data)[k % len(chunks(data))]
        struct.pack_into("<Q", b, chunk_fields(data, off)[0], length)
    return bytes(b)


def read_all(path: Path, limit_s: float | None = PER_INPUT_S) -> str:
    """What replay does with a recording: SessionReader's events, then the mcap:// source; only
    robotd's own error may come out (and, with ``limit_s``, within that time). Returns
    ``"read"`` (both to the end), ``"stopped"`` (read up to damage) or ``"refused"``."""
    from drivers.dataset import McapCamera
    from robotd.core.errors import RobotdError
    from robotd.formats.record import SessionReader

    t0 = time.monotonic()
    outcome = "read"
    try:
        reader = SessionReader(path)
        for _ in reader.events():
            pass
        if reader.stopped is not None:
            outcome = "stopped"
    except RobotdError:
        outcome = "refused"
    try:
        with McapCamera(path) as cam:
            for _ in cam.frames():
                pass
            cam.recorded_odometry()
    except RobotdError:
        pass
    took = time.monotonic() - t0
    assert limit_s is None or took < limit_s, f"{took:.1f} s for one input"
    return outcome


RECORD_LENGTHS = (0, 1, 8, 2**31, 2**32 - 1, 2**63, 2**64 - 1)
PNG_SIDES = (0, 1, 40, 64, 65535, 2**31 - 1, 2**32 - 1)


class RecordingTarget:
    """A small real format-2 recording and the real format-1 one in tests/support/data, damaged
    as in test_fuzz_recording.py (bytes flipped raw or behind valid chunk CRCs, truncation,
    duplicated chunks, forged record lengths and chunk sizes, forged PNG headers and PNG chunk
    lengths) or by ``mutate_bytes``. Oracle: ``read_all`` (the time bound is the bench's watchdog)."""

    name = "recording"

    def setup(self) -> None:
        self.tmp = Path(tempfile.mkdtemp(prefix="robotd-fuzz-recording-"))
        self.originals = {"format2": small_recording(self.tmp), "format1": FORMAT1_RECORDING.read_bytes()}

    def generate(self, rng: random.Random) -> Case:
        data = self.originals[rng.choice(("format2", "format2", "format2", "format1"))]
        flips = [(rng.random(), rng.randint(1, 255)) for _ in range(rng.randint(1, 8))]
        kind = rng.randrange(8)
        if kind == 0:
            out = flip(data, flips)
        elif kind == 1:
            out = rewrite_chunk(data, rng.randrange(100), lambda raw: flip(raw, flips))
        elif kind == 2:
            out = data[: int(rng.random() * len(data))]
        elif kind == 3:
            out = duplicate_chunk(data, rng.randrange(100), rng.randrange(100))
        elif kind == 4:
            length = rng.choice(RECORD_LENGTHS) if rng.random() < 0.5 else rng.randrange(2**64)
            out = forge_length(data, rng.randrange(1000), length, rng.choice(("record", "chunk-size")))
        elif kind == 5:
            sides = [rng.choice(PNG_SIDES) if rng.random() < 0.5 else rng.randrange(2**32) for _ in (0, 1)]
            out = forge_png(data, rng.randrange(100), sides[0], sides[1], rng.choice((1, 8, 16)))
        elif kind == 6:
            length = rng.choice(RECORD_LENGTHS) if rng.random() < 0.5 else rng.randrange(2**32)
            out = forge_png_chunk_length(data, rng.randrange(100), length, rng.choice((b"IDAT", b"IHDR", b"IEND")))
        else:
            out = mutate_bytes(data, rng, rng.randint(1, 8), list(self.originals.values()))
        return Case(out)

    def check(self, case: Case) -> str:
        path = self.tmp / "m.mcap"
        path.write_bytes(case.data)
        return read_all(path, limit_s=None)


TARGETS: dict[str, Callable[[], Any]] = {
    "serial": SerialTarget,
    "mavlink": MavlinkTarget,
    "config": ConfigTarget,
    "mapfile": MapfileTarget,
    "recording": RecordingTarget,
}
