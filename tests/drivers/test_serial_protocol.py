"""Pure tests of the MCU wire protocol: COBS, CRC, frames, stream decoder, clock mapping, wheels."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.serial_protocol import (
    MAX_ENCODED,
    ClockMapper,
    ControlInputs,
    FrameDecoder,
    Heartbeat,
    HostPose,
    MsgType,
    Version,
    WheelGeometry,
    WheelOdometry,
    cobs_decode,
    cobs_encode,
    crc16,
    decode_frame,
    diff_drive,
    encode_body,
    encode_frame,
    seq_gap,
    tick_delta,
)
from robotd.core.errors import ProtocolError

U32 = 1 << 32


def test_crc_check_value() -> None:
    # CRC-16/CCITT-FALSE catalogue check value
    assert crc16(b"123456789") == 0x29B1


def test_cobs_known_vectors() -> None:
    # vectors from the COBS paper / Wikipedia table
    assert cobs_encode(b"") == b"\x01"
    assert cobs_encode(b"\x00") == b"\x01\x01"
    assert cobs_encode(b"\x00\x00") == b"\x01\x01\x01"
    assert cobs_encode(b"\x11\x22\x00\x33") == b"\x03\x11\x22\x02\x33"
    assert cobs_encode(b"\x11\x00\x00\x00") == b"\x02\x11\x01\x01\x01"
    run = bytes(range(1, 255))  # 254 non-zero bytes: one full 0xFF block
    assert cobs_encode(run) == b"\xff" + run + b"\x01"
    for v in (b"", b"\x00", b"\x11\x22\x00\x33", run, run + b"\x00" + run):
        assert cobs_decode(cobs_encode(v)) == v


@given(st.binary(max_size=1200))
@settings(max_examples=300, deadline=None)
def test_cobs_round_trip_and_no_zero(data: bytes) -> None:
    enc = cobs_encode(data)
    assert 0 not in enc
    # overhead: at most one byte per 254, plus one
    assert len(enc) <= len(data) + len(data) // 254 + 1
    assert cobs_decode(enc) == data


def test_cobs_rejects_bad_codes() -> None:
    with pytest.raises(ProtocolError, match="zero code byte"):
        cobs_decode(b"\x02\x11\x00")
    with pytest.raises(ProtocolError, match="points past the end"):
        cobs_decode(b"\x05\x11\x22")


MESSAGES = st.one_of(
    st.builds(
        WheelOdometry,
        st.integers(0, 3),
        st.integers(-(2**31), 2**31 - 1),
        st.integers(-(2**31), 2**31 - 1),
        st.floats(-10, 10, width=32),
        st.floats(-10, 10, width=32),
    ),
    st.builds(ControlInputs, st.floats(-1, 1, width=32), st.floats(-1, 1, width=32)),
    st.builds(Heartbeat, st.integers(0, 2), st.integers(0, U32 - 1), st.integers(0, 0xFFFF)),
    st.builds(Version, st.just(1), st.integers(0, 255), st.integers(0, 255), st.integers(0, 255)),
    st.builds(
        HostPose,
        st.floats(-1e3, 1e3, width=32),
        st.floats(-1e3, 1e3, width=32),
        st.floats(-1e3, 1e3, width=32),
        st.floats(-4, 4, width=32),
        st.integers(-1, 100),
        st.integers(0, 255),
    ),
)


@given(MESSAGES, st.integers(0, 0xFFFF), st.integers(0, U32 - 1))
@settings(max_examples=300, deadline=None)
def test_frame_round_trip(msg, seq: int, t_us: int) -> None:
    wire = encode_frame(msg, seq, t_us)
    assert wire.endswith(b"\x00") and wire.count(0) == 1
    fr = decode_frame(wire)
    assert (fr.seq, fr.t_mcu_us, fr.kind) == (seq, t_us, msg.TYPE)
    assert fr.msg == msg


def test_embedded_zeros_survive() -> None:
    msg = WheelOdometry(3, 0, 256, 0.0, 0.0)  # payload full of zero bytes
    assert b"\x00" in msg.pack()
    assert decode_frame(encode_frame(msg, 0, 0)).msg == msg


def test_decode_errors_have_numbers() -> None:
    good = bytearray(encode_body(MsgType.HEARTBEAT, 1, 2, Heartbeat(0, 5).pack()))
    good[9] ^= 0x01
    with pytest.raises(ProtocolError, match=r"CRC mismatch: got 0x[0-9A-F]{4}, computed"):
        decode_frame(cobs_encode(bytes(good)))
    with pytest.raises(ProtocolError, match="unknown message type 0x7E"):
        decode_frame(cobs_encode(encode_body(0x7E, 1, 2, b"")))
    with pytest.raises(ProtocolError, match="payload 1 bytes, expected 7"):
        decode_frame(cobs_encode(encode_body(MsgType.HEARTBEAT, 1, 2, b"\x01")))
    with pytest.raises(ProtocolError, match="protocol version 2, expected 1"):
        decode_frame(cobs_encode(encode_body(MsgType.HEARTBEAT, 1, 2, Heartbeat(0, 5).pack(), ver=2)))
    with pytest.raises(ProtocolError, match="too short"):
        decode_frame(cobs_encode(b"\x01\x02"))


@given(st.binary(max_size=3000), st.lists(st.integers(1, 200), max_size=20))
@settings(max_examples=300, deadline=None)
def test_garbage_never_crashes_the_decoder(garbage: bytes, cuts: list[int]) -> None:
    dec = FrameDecoder()
    pos = 0
    for c in [*cuts, len(garbage)]:
        dec.feed(garbage[pos : pos + c])
        pos += c
    dec.feed(garbage[pos:])
    # after any garbage, a delimiter resynchronises and the next good frame decodes
    msg = Heartbeat(0, 1234)
    out = dec.feed(b"\x00" + encode_frame(msg, 9, 99))
    assert [f.msg for f in out] == [msg]


@given(st.lists(st.tuples(MESSAGES, st.booleans()), min_size=1, max_size=30), st.integers(1, 64))
@settings(max_examples=150, deadline=None)
def test_stream_with_corruption_counts_and_skips(items, chunk: int) -> None:
    stream = bytearray()
    want = []
    n_bad = 0
    for i, (msg, corrupt) in enumerate(items):
        body = bytearray(encode_body(msg.TYPE, i, i * 10, msg.pack()))
        if corrupt:
            body[-1] ^= 0x5A  # wrong CRC
            n_bad += 1
        else:
            want.append(msg)
        stream += cobs_encode(bytes(body)) + b"\x00"
    dec = FrameDecoder()
    got = []
    for k in range(0, len(stream), chunk):
        got += [f.msg for f in dec.feed(bytes(stream[k : k + chunk]))]
    assert got == want
    assert dec.stats.crc_errors == n_bad
    assert dec.stats.frames == len(want)


def test_oversize_run_is_dropped_and_counted() -> None:
    dec = FrameDecoder()
    assert dec.feed(b"\x07" * (MAX_ENCODED + 10)) == []
    assert dec.stats.oversize == 1
    # the tail of the over-long run is skipped up to the delimiter, then decoding resumes
    out = dec.feed(b"\x07\x07\x00" + encode_frame(Heartbeat(1, 2), 0, 0))
    assert len(out) == 1 and dec.stats.frames == 1


def test_seq_gap() -> None:
    assert seq_gap(5, 6) == 0
    assert seq_gap(5, 9) == 3
    assert seq_gap(0xFFFF, 0) == 0  # wrap is consecutive
    assert seq_gap(0xFFFE, 1) == 2
    assert seq_gap(10, 10) == -1  # duplicate
    assert seq_gap(10, 3) == -1  # restart / reorder


def test_clock_mapper_unwraps_32bit_time() -> None:
    cm = ClockMapper()
    t_mcu = U32 - 3_000  # 3 ms before the wrap
    host0 = 10_000_000_000
    mapped = []
    for k in range(10):  # 1 ms steps across the wrap
        mapped.append(cm.observe((t_mcu + 1000 * k) % U32, host0 + 1_000_000 * k + 200_000))
    # the host mapping stays continuous: exactly 1 ms apart, no 71-minute jump
    assert np.all(np.diff(mapped) == 1_000_000)
    assert cm.unwrap((t_mcu + 10_000) % U32) == t_mcu + 10_000


@given(st.integers(0, U32 - 1), st.floats(0.0, 1e-3), st.integers(0, 2**31))
@settings(max_examples=100, deadline=None)
def test_clock_mapper_min_latency_bound(t0_us: int, jitter_scale: float, seed: int) -> None:
    import numpy as np

    rng = np.random.default_rng(seed)
    cm = ClockMapper(window_ns=2_000_000_000)
    true_offset_ns = 5_000_000_000 - t0_us * 1000
    base_latency_ns = 150_000
    err = []
    for k in range(300):  # 3 s at 100 Hz
        t_mcu_ns = t0_us * 1000 + k * 10_000_000
        lat = base_latency_ns + int(rng.exponential(jitter_scale) * 1e9)
        mapped = cm.observe((t_mcu_ns // 1000) % U32, t_mcu_ns + true_offset_ns + lat)
        err.append(mapped - (t_mcu_ns + true_offset_ns))
    # after the first samples the mapping is within [base latency, base latency + small]
    e = np.array(err[50:])
    assert np.all(e >= base_latency_ns)
    assert np.all(e <= base_latency_ns + 200_000 + 1000)  # bound: 0.2 ms above the minimum latency


def test_wheel_geometry_validation() -> None:
    with pytest.raises(ProtocolError, match="track_width_m: expected a positive finite number, got 0"):
        WheelGeometry(track_width_m=0)


def test_diff_drive_and_tick_wrap() -> None:
    # left further than right: FRD yaw positive (turning right)
    dx, dpsi = diff_drive(0.11, 0.09, 0.2)
    assert dx == pytest.approx(0.10)
    assert dpsi == pytest.approx(0.1)
    assert tick_delta(2**31 - 5, -(2**31) + 5) == 10  # int32 counter rolls over
    g = WheelGeometry(0.05, 1000, 0.3)
    assert g.m_per_tick == pytest.approx(2 * math.pi * 0.05 / 1000)
