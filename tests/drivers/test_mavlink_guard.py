"""drivers.mavlink_guard: the TIMESYNC rate limit and reboot detection that needs a consistent clock."""

from __future__ import annotations

import numpy as np

from drivers.mavlink_guard import NO_ACK, BootClock, RateLimit, RateOutcome, RateRequests

S = 1_000_000_000
MS = 1_000_000


def test_rate_limit_bounds_a_flood() -> None:
    lim = RateLimit(20.0)
    # 7,376 requests over 2 s
    n = 7376
    got = sum(lim.allow(k * 2 * S // n) for k in range(n))
    assert got <= 20 + 20 * 2 + 1 and got >= 40
    assert lim.refused == n - got
    assert not RateLimit(0.0).allow(0)


def test_rate_limit_passes_a_normal_rate() -> None:
    lim = RateLimit(20.0)
    assert all(lim.allow(k * S // 10) for k in range(100))  # PX4's 10 Hz requests all answered


def autopilot_samples(boot_ns: int, t0: int, n: int, hz: float = 1.0) -> list[tuple[int, int]]:
    """(time_boot_ms, arrival) pairs of an autopilot booted at host time ``boot_ns``, 2 ms latency."""
    out = []
    for k in range(n):
        t = t0 + int(k * S / hz)
        out.append(((t - boot_ns) // MS, t + 2 * MS))
    return out


def test_spoofed_system_times_are_not_reboots() -> None:
    rng = np.random.default_rng(1)
    clock = BootClock()
    real = autopilot_samples(boot_ns=-100 * S, t0=0, n=300)
    spoofs = sorted(int(t) for t in rng.uniform(0, 300 * S, 567))
    events = [(t, "real", ms) for ms, t in real] + [(t, "spoof", int(rng.integers(0, 2**32))) for t in spoofs]
    events += [(t + 500 * MS, "hb", 0) for _, t in real]  # autopilot heartbeats at 1 Hz
    reboots = 0
    for t, kind, ms in sorted(events):
        if kind == "hb":
            clock.heartbeat(t)
        else:
            reboots += clock.observe(ms, t)
    assert reboots == 0 and clock.reboots == 0
    assert clock.mismatches >= 560  # those before the first clock was established are not mismatches


def test_a_spoofed_consistent_pair_between_real_samples_is_not_a_reboot() -> None:
    clock = BootClock()
    for ms, t in autopilot_samples(-100 * S, 0, 5):
        clock.observe(ms, t)
    t = 5 * S
    clock.observe(10, t)  # "just booted", twice, with a heartbeat in between
    clock.heartbeat(t + 100 * MS)
    clock.observe(210, t + 200 * MS)
    clock.observe((t + 900 * MS + 100 * S) // MS, t + 900 * MS)  # the real autopilot carries on
    assert not clock.observe(2_010, t + 2 * S)
    assert clock.reboots == 0


def test_a_real_reboot_is_one_reboot() -> None:
    clock = BootClock()
    before = autopilot_samples(-100 * S, 0, 10)
    after = autopilot_samples(11 * S, 11 * S + 300 * MS, 10)
    got = []
    for ms, t in before:
        clock.heartbeat(t - 100 * MS)
        got.append(clock.observe(ms, t))
    for ms, t in after:
        clock.heartbeat(t - 100 * MS)
        got.append(clock.observe(ms, t))
    assert sum(got) == 1 and clock.reboots == 1
    assert got.index(True) in (12, 13)  # confirmed on the 3rd or 4th sample of the new clock


def test_no_reboot_without_a_heartbeat() -> None:
    clock = BootClock()
    for ms, t in autopilot_samples(-100 * S, 0, 10):
        clock.observe(ms, t)
    assert not any(clock.observe(ms, t) for ms, t in autopilot_samples(11 * S, 11 * S, 10))


ACCEPTED, DENIED, UNSUPPORTED, FAILED, IN_PROGRESS = 0, 2, 3, 4, 5


def test_rate_requests_one_at_a_time_each_ack_to_its_request() -> None:
    r = RateRequests(ack_timeout_s=1.0)
    r.start({"ATTITUDE": 50.0, "LOCAL_POSITION_NED": 10.0, "SYSTEM_TIME": 1.0})
    assert r.next_request(0) == (("ATTITUDE", 50.0), None)
    assert r.next_request(10 * MS) == (None, None)  # the ACK is awaited before the next request
    assert r.on_ack(IN_PROGRESS) is None and r.next_request(20 * MS) == (None, None)  # not an answer yet
    # refused: retried once at half the rate, before the next message
    assert r.on_ack(DENIED) == RateOutcome("ATTITUDE", 50.0, DENIED, 25.0, False)
    assert r.next_request(30 * MS) == (("ATTITUDE", 25.0), None)
    assert r.on_ack(ACCEPTED) == RateOutcome("ATTITUDE", 25.0, ACCEPTED, None, True)
    assert r.next_request(40 * MS) == (("LOCAL_POSITION_NED", 10.0), None)
    assert r.on_ack(ACCEPTED) is not None
    assert r.on_ack(ACCEPTED) is None  # an ACK with nothing outstanding answers nothing
    assert r.next_request(50 * MS)[0] == ("SYSTEM_TIME", 1.0)
    assert not r.round_finished()
    assert r.on_ack(ACCEPTED) is not None
    assert r.next_request(60 * MS) == (None, None) and r.round_finished() and not r.round_finished()
    assert r.granted == {"ATTITUDE": 25.0, "LOCAL_POSITION_NED": 10.0, "SYSTEM_TIME": 1.0}
    assert (r.accepted, r.refused, r.unacknowledged) == (3, 1, 0)
    assert r.refusals == [RateOutcome("ATTITUDE", 50.0, DENIED, 25.0, False)]


def test_rate_requests_retry_once_and_never_for_unsupported_or_a_switch_off() -> None:
    r = RateRequests()
    r.start({"WHEEL_DISTANCE": 50.0, "ODOMETRY": 10.0, "VFR_HUD": -1.0})
    assert r.next_request(0)[0] == ("WHEEL_DISTANCE", 50.0)
    assert r.on_ack(DENIED) is not None and r.next_request(1)[0] == ("WHEEL_DISTANCE", 25.0)
    assert r.on_ack(DENIED) == RateOutcome("WHEEL_DISTANCE", 25.0, DENIED, None, True)  # refused twice: given up
    assert r.next_request(2)[0] == ("ODOMETRY", 10.0)
    assert r.on_ack(UNSUPPORTED) == RateOutcome("ODOMETRY", 10.0, UNSUPPORTED, None, False)
    assert r.next_request(3)[0] == ("VFR_HUD", -1.0)
    assert r.on_ack(FAILED) == RateOutcome("VFR_HUD", -1.0, FAILED, None, False)
    assert r.next_request(4) == (None, None) and not r.busy
    assert r.refused == 4 and r.accepted == 0 and r.granted == {}


def test_rate_requests_a_missing_ack_times_out_and_a_new_round_starts_afresh() -> None:
    r = RateRequests(ack_timeout_s=1.0)
    r.start({"ATTITUDE": 25.0, "SYSTEM_TIME": 1.0})
    assert r.next_request(0)[0] == ("ATTITUDE", 25.0)
    assert r.next_request(999 * MS) == (None, None)
    req, timed_out = r.next_request(S)
    assert req == ("SYSTEM_TIME", 1.0) and timed_out == RateOutcome("ATTITUDE", 25.0, NO_ACK, None, False)
    assert r.unacknowledged == 1 and r.refusals == [timed_out]
    r.start({"ATTITUDE": 25.0})  # the autopilot rebooted: the outstanding request is forgotten
    assert r.on_ack(ACCEPTED) is None and r.refusals == [] and r.busy
    assert r.next_request(2 * S)[0] == ("ATTITUDE", 25.0) and r.on_ack(ACCEPTED) is not None
    assert r.granted == {"ATTITUDE": 25.0} and (r.accepted, r.unacknowledged) == (1, 1)
