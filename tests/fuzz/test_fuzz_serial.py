"""Fuzz the serial link's decoder and message handler (issue 15): arbitrary and mutated byte
streams never raise anything but the project's error and never cost a frame that arrives intact
after the damage; frames with arbitrary field values never raise anything the reader does not
count, and what they would make of the motion is refused by the daemon's plausibility gate.

tests/drivers/test_serial_protocol.py holds the round trips and garbage-then-a-delimiter cases;
these add mutated streams and the handler. Bounded: each test runs a few seconds."""

from __future__ import annotations

import math
import struct

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.serial_link import SerialVehicle
from drivers.serial_protocol import (
    ControlInputs,
    Frame,
    FrameDecoder,
    Heartbeat,
    Version,
    WheelOdometry,
    decode_frame,
    encode_frame,
)
from robotd.errors import ProtocolError, RobotdError
from robotd.odometry import OdometryGate

U32 = 1 << 32
F32 = st.floats(width=32)  # NaN, ±inf, ±3.4e38 and everything between
I32 = st.integers(-(1 << 31), (1 << 31) - 1)
MESSAGES = st.one_of(
    st.builds(WheelOdometry, st.integers(0, 255), I32, I32, F32, F32),
    st.builds(ControlInputs, F32, F32),
    st.builds(Heartbeat, st.integers(0, 255), st.integers(0, U32 - 1), st.integers(0, 0xFFFF)),
    st.builds(Version, st.integers(0, 255), st.integers(0, 255), st.integers(0, 255), st.integers(0, 255)),
)
FUZZ = settings(max_examples=200, deadline=None)


@given(st.binary(max_size=600))
@FUZZ
def test_decode_frame_raises_only_protocol_errors(data: bytes) -> None:
    try:
        fr = decode_frame(data)
    except ProtocolError:
        return
    assert isinstance(fr, Frame)


MUTATION = st.tuples(
    st.sampled_from(["flip", "insert", "delete", "zero"]), st.integers(0, 10**6), st.binary(min_size=1, max_size=40)
)


def _mutate(stream: bytes, mutations: list[tuple[str, int, bytes]]) -> tuple[bytes, set[int]]:
    """Apply the mutations; return the result and the original positions they touched (a byte
    changed or deleted, or a neighbour of an insertion or deletion)."""
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


@given(
    st.lists(MESSAGES, min_size=1, max_size=25),
    st.lists(MUTATION, max_size=6),
    st.lists(st.integers(1, 97), max_size=30),
)
@FUZZ
def test_mutated_stream_keeps_every_intact_frame(msgs, mutations, cuts) -> None:
    stream = bytearray()
    spans = []  # [start, end) of each frame, its own delimiter included
    for i, msg in enumerate(msgs):
        start = len(stream)
        stream += encode_frame(msg, i, 1000 * i)
        spans.append((start, len(stream)))
    mutated, touched = _mutate(bytes(stream), mutations)
    dec = FrameDecoder()
    got = []
    pos = 0
    for c in [*cuts, len(mutated)]:
        got += dec.feed(mutated[pos : pos + c])  # never raises
        pos += c
    got += dec.feed(mutated[pos:])
    # a frame is intact when none of its bytes, nor the delimiter before it, was touched
    intact = [(i, m) for i, (m, (a, b)) in enumerate(zip(msgs, spans)) if not touched & set(range(a - 1, b))]
    # every intact frame is decoded, in order (a mutation may, with CRC luck, add frames between)
    it = iter((f.seq, f.msg) for f in got)
    for i, m in intact:
        assert any(seq == i and _same(msg, m) for seq, msg in it), f"frame {i} ({m}) lost"


def _same(a: object, b: object) -> bool:
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


@given(
    st.lists(st.tuples(MESSAGES, st.integers(0, 50_000), st.integers(0, 3)), min_size=1, max_size=40),
    st.sampled_from(["ticks", "velocity"]),
)
@settings(max_examples=150, deadline=None)
def test_handler_with_arbitrary_values_counts_and_the_gate_refuses(items, source: str) -> None:
    link = SerialVehicle("serial:///dev/robotd-fuzz-not-opened?track_width_m=0.3", wheel_source=source)
    t_mcu = 0
    t_host = 10**12
    bad = 0
    for k, (msg, dt_us, seq_step) in enumerate(items):
        t_mcu = (t_mcu + dt_us) % U32
        t_host += dt_us * 1000 + 1000
        fr = Frame(1, msg.TYPE, (k * seq_step) & 0xFFFF, t_mcu, msg)
        try:
            link._handle(fr, t_host)  # what the reader thread does with a decoded frame
        except RobotdError:
            bad += 1  # the reader counts these as bad_values and reads on
    samples = link.drain()
    assert len(samples) == link.stats()["odometry"]
    for s in samples:  # Odometry refuses non-finite values at construction
        assert np.all(np.isfinite(s.vel_R_mps)) and np.all(np.isfinite(s.rate_R_radps))
    gate = OdometryGate()
    accepted = [s for s in samples if gate.accept(s)]
    assert gate.accepted + sum(gate.rejected.values()) == len(samples)
    for s in accepted:
        assert np.linalg.norm(s.vel_R_mps) <= gate.limits.max_speed_mps
        assert np.linalg.norm(s.rate_R_radps) <= gate.limits.max_rate_radps
    ctl = link.latest_controls()
    assert ctl is None or (abs(ctl.throttle) <= 1.0 and abs(ctl.steering) <= 1.0)
    link._link.closed()


def test_a_tick_jump_is_refused_by_the_gate_not_integrated() -> None:
    # issue 15 item 1's serial case: ticks_l 0 -> 2**31 - 1 in 10 ms
    link = SerialVehicle("serial:///dev/robotd-fuzz-not-opened?track_width_m=0.3")
    link._handle(Frame(1, 1, 0, 0, WheelOdometry(1, 0, 0, 0.0, 0.0)), 10**12)
    link._handle(Frame(1, 1, 1, 10_000, WheelOdometry(1, (1 << 31) - 1, 0, 0.0, 0.0)), 10**12 + 10**7)
    (sample,) = link.drain()
    gate = OdometryGate()
    assert not gate.accept(sample) and gate.rejected["speed"] == 1
