"""Fuzz the MAVLink link's message handlers (issue 15): messages of every type robotd reads, with
arbitrary field values (NaN, ±inf, huge, negative, out-of-range enums), packed and parsed as on
the wire, go through the link's dispatch without an exception; a value the link cannot use is
counted (``bad_values``), what it makes of the motion is finite, and the daemon's plausibility
gate refuses and counts the implausible rest. Bounded: a few seconds."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.mavlink_link import MavlinkVehicle, mavlink_module
from robotd.odometry import OdometryGate

m = mavlink_module()
KINDS = (
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
)
CLASSES = {k: getattr(m, f"MAVLink_{k.lower()}_message") for k in KINDS}
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


def _wire(msg: Any, sysid: int, compid: int) -> Any:
    """Pack ``msg`` as ``sysid``/``compid`` and parse it back: what the receive thread would see."""
    tx = m.MAVLink(None, srcSystem=sysid, srcComponent=compid)
    rx = m.MAVLink(None)
    return rx.decode(bytearray(msg.pack(tx)))


SENDERS = st.sampled_from([(1, 1), (1, 1), (1, 1), (2, 1), (1, 7)])  # mostly the autopilot
ITEMS = st.lists(
    st.tuples(st.sampled_from(KINDS).flatmap(message), SENDERS, st.integers(1, 200_000_000)),
    min_size=1,
    max_size=40,
)


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


@given(ITEMS)
@settings(max_examples=150, deadline=None)
def test_arbitrary_messages_never_raise_and_bad_values_are_counted(items) -> None:
    link = MavlinkVehicle("mavlink+udp://127.0.0.1:14550", track_width_m=0.4)  # never opened: no socket
    link._conn = type("Conn", (), {"mav": m.MAVLink(None)})()  # the heartbeat sets our srcSystem on it
    t_ns = 10**12
    hb = m.MAVLink_heartbeat_message(m.MAV_TYPE_GROUND_ROVER, m.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4, 3)
    link._dispatch(_wire(hb, 1, 1), t_ns, None)  # the autopilot is sysid 1, compid 1
    for msg, (sysid, compid), dt in items:
        t_ns += dt
        rx = _wire(msg, sysid, compid)
        before = link.c["bad_values"]
        link._dispatch(rx, t_ns, None)  # never raises
        if (sysid, compid) == (1, 1) and _used_values_bad(rx) and link.autopilot_sysid == 1:
            if rx.get_type() == "ATTITUDE" or rx.count > 1:  # wheels 0 and 1 exist
                assert link.c["bad_values"] == before + 1, rx
    samples = link.drain()
    assert len(samples) == link.c["odometry"]
    for s in samples:
        assert np.all(np.isfinite(s.vel_R_mps)) and np.all(np.isfinite(s.rate_R_radps))
    gate = OdometryGate()
    accepted = [s for s in samples if gate.accept(s)]
    assert gate.accepted + sum(gate.rejected.values()) == len(samples)
    for s in accepted:
        assert np.linalg.norm(s.vel_R_mps) <= gate.limits.max_speed_mps
        assert np.linalg.norm(s.rate_R_radps) <= gate.limits.max_rate_radps
    ctl = link.latest_controls()
    assert ctl is None or (abs(ctl.throttle) <= 1.4 and abs(ctl.steering) <= 1.4)  # 800–2200 µs
    st_ = link.stats()
    assert st_["autopilot_sysid"] == 1  # nobody else took the autopilot's place
    foreign = sum(1 for msg, sender, _ in items if sender != (1, 1) and msg.get_type() != "HEARTBEAT")
    assert st_["rejected_source"] >= foreign


def test_wheel_distance_plus_10_km_is_refused_by_the_gate() -> None:
    # issue 15 item 1's MAVLink case: one WHEEL_DISTANCE sample 10 km ahead
    link = MavlinkVehicle("mavlink+udp://127.0.0.1:14550", track_width_m=0.4)
    link._conn = type("Conn", (), {"mav": m.MAVLink(None)})()
    hb = m.MAVLink_heartbeat_message(m.MAV_TYPE_GROUND_ROVER, m.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4, 3)
    link._dispatch(_wire(hb, 1, 1), 10**12, None)
    for k, d in enumerate((0.0, 0.01, 10_000.0, 10_000.01)):
        wd = m.MAVLink_wheel_distance_message(1_000_000 + 20_000 * k, 2, [d, d] + [0.0] * 14)
        link._dispatch(_wire(wd, 1, 1), 10**12 + 20_000_000 * (k + 1), None)
    samples = link.drain()
    gate = OdometryGate()
    verdicts = [gate.accept(s) for s in samples]
    assert verdicts == [True, False, True] and gate.rejected["speed"] == 1
