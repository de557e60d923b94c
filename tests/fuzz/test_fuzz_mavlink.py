"""Fuzz the MAVLink link's message handlers (issue 15): messages of every type robotd reads, with
arbitrary field values (NaN, ±inf, huge, negative, out-of-range enums), packed and parsed as on
the wire, go through the link's dispatch without an exception; a value the link cannot use is
counted (``bad_values``), what it makes of the motion is finite, and the daemon's plausibility
gate refuses and counts the implausible rest. Bounded: a few seconds."""

from __future__ import annotations

import math
from typing import Any

from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.mavlink_link import mavlink_module
from robotd.pipeline.odometry import OdometryGate
from tests.fuzz.targets import (
    AUTOPILOT,
    INT_RANGES,
    MAVLINK_KINDS,
    check_mavlink_link,
    dispatch_checked,
    mavlink_classes,
    mavlink_link_with_autopilot,
    mavlink_parse,
    mavlink_wire,
)

m = mavlink_module()
CLASSES = mavlink_classes()
SPECIAL = st.sampled_from([math.nan, math.inf, -math.inf, 3.0e38, -3.0e38, 1e-40, 0.0, -1.0])


def _value(ftype: str) -> st.SearchStrategy[Any]:
    if ftype in INT_RANGES:
        lo, hi = INT_RANGES[ftype]
        return st.one_of(st.integers(lo, hi), st.sampled_from([lo, hi, 0]))
    if ftype == "float":
        return st.one_of(st.floats(width=32), SPECIAL)
    if ftype == "double":
        return st.one_of(st.floats(), SPECIAL, st.sampled_from([1e300, -1e300]))
    raise AssertionError(ftype)


@st.composite
def message(draw: st.DrawFn, kind: str) -> Any:
    cls = CLASSES[kind]
    lengths = dict(zip(cls.ordered_fieldnames, cls.array_lengths, strict=True))
    args = []
    for name, ftype in zip(cls.fieldnames, cls.fieldtypes, strict=True):
        n = lengths.get(name, 0)
        args.append(draw(st.lists(_value(ftype), min_size=n, max_size=n)) if n else draw(_value(ftype)))
    return cls(*args)


SENDERS = st.sampled_from([AUTOPILOT, AUTOPILOT, AUTOPILOT, (2, 1), (1, 7)])  # mostly the autopilot
ITEMS = st.lists(
    st.tuples(st.sampled_from(MAVLINK_KINDS).flatmap(message), SENDERS, st.integers(1, 200_000_000)),
    min_size=1,
    max_size=40,
)


@given(ITEMS)
@settings(max_examples=150, deadline=None)
def test_arbitrary_messages_never_raise_and_bad_values_are_counted(items) -> None:
    t_ns = 10**12
    link = mavlink_link_with_autopilot(t_ns)
    for msg, (sysid, compid), dt in items:
        t_ns += dt
        dispatch_checked(link, mavlink_parse(mavlink_wire(msg, sysid, compid)), t_ns)
    foreign = sum(1 for msg, sender, _ in items if sender != AUTOPILOT and msg.get_type() != "HEARTBEAT")
    check_mavlink_link(link, foreign)


def test_wheel_distance_plus_10_km_is_refused_by_the_gate() -> None:
    # issue 15 item 1's MAVLink case: one WHEEL_DISTANCE sample 10 km ahead
    link = mavlink_link_with_autopilot(10**12)
    for k, d in enumerate((0.0, 0.01, 10_000.0, 10_000.01)):
        wd = m.MAVLink_wheel_distance_message(1_000_000 + 20_000 * k, 2, [d, d] + [0.0] * 14)
        link._dispatch(mavlink_parse(mavlink_wire(wd, *AUTOPILOT)), 10**12 + 20_000_000 * (k + 1), None)
    samples = link.drain()
    gate = OdometryGate()
    verdicts = [gate.accept(s) for s in samples]
    assert verdicts == [True, False, True] and gate.rejected["speed"] == 1
