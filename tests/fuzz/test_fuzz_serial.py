"""Fuzz the serial link's decoder and message handler (issue 15): arbitrary and mutated byte
streams never raise anything but the project's error and never cost a frame that arrives intact
after the damage; frames with arbitrary field values never raise anything the reader does not
count, and what they would make of the motion is refused by the daemon's plausibility gate.

tests/drivers/test_serial_protocol.py holds the round trips and garbage-then-a-delimiter cases;
these add mutated streams and the handler. Bounded: each test runs a few seconds."""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.serial_protocol import ControlInputs, Frame, Heartbeat, Version, WheelOdometry, decode_frame
from robotd.core.errors import ProtocolError
from robotd.pipeline.odometry import OdometryGate
from tests.fuzz.targets import check_decoded_stream, check_serial_handler, encode_stream, mutate_stream, serial_link

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


@given(
    st.lists(MESSAGES, min_size=1, max_size=25),
    st.lists(MUTATION, max_size=6),
    st.lists(st.integers(1, 97), max_size=30),
)
@FUZZ
def test_mutated_stream_keeps_every_intact_frame(msgs, mutations, cuts) -> None:
    stream, spans = encode_stream(msgs)
    mutated, touched = mutate_stream(stream, mutations)
    check_decoded_stream(msgs, spans, mutated, touched, cuts)


@given(
    st.lists(st.tuples(MESSAGES, st.integers(0, 50_000), st.integers(0, 3)), min_size=1, max_size=40),
    st.sampled_from(["ticks", "velocity"]),
)
@settings(max_examples=150, deadline=None)
def test_handler_with_arbitrary_values_counts_and_the_gate_refuses(items, source: str) -> None:
    link = serial_link(source)
    t_mcu = 0
    t_host = 10**12
    frames, arrivals = [], []
    for k, (msg, dt_us, seq_step) in enumerate(items):
        t_mcu = (t_mcu + dt_us) % U32
        t_host += dt_us * 1000 + 1000
        frames.append(Frame(1, msg.TYPE, (k * seq_step) & 0xFFFF, t_mcu, msg))
        arrivals.append(t_host)
    check_serial_handler(link, frames, arrivals)


def test_a_tick_jump_is_refused_by_the_gate_not_integrated() -> None:
    # issue 15 item 1's serial case: ticks_l 0 -> 2**31 - 1 in 10 ms
    link = serial_link()
    link._handle(Frame(1, 1, 0, 0, WheelOdometry(1, 0, 0, 0.0, 0.0)), 10**12)
    link._handle(Frame(1, 1, 1, 10_000, WheelOdometry(1, (1 << 31) - 1, 0, 0.0, 0.0)), 10**12 + 10**7)
    (sample,) = link.drain()
    gate = OdometryGate()
    assert not gate.accept(sample) and gate.rejected["speed"] == 1
