"""drivers.link_state: a link's state comes from its recent good frames, never from the port alone."""

from __future__ import annotations

from drivers.link_state import CLOSED, DEGRADED, LOST, OK, LinkState, LinkStateParams

S = 1_000_000_000  # ns per second
P = LinkStateParams(stale_after_s=0.5, lost_after_s=2.0, window_s=2.0, max_bad_fraction=0.2, min_bad=5)


def test_silent_link_is_never_ok() -> None:
    link = LinkState(P)
    assert link.state(0) == CLOSED
    link.opened(10 * S)
    assert link.state(10 * S) == DEGRADED  # open, nothing received yet
    assert link.state(11 * S) == DEGRADED
    assert link.state(12 * S + 1) == LOST
    assert link.state(100 * S) == LOST
    assert link.stats(100 * S)["since_good_s"] is None


def test_only_bad_frames_is_lost_not_ok() -> None:
    link = LinkState(P)
    link.opened(0)
    for k in range(400):  # 100 bad-CRC frames a second for 4 s
        t = k * S // 100
        link.record(t, bad=1)
        assert link.state(t) in (DEGRADED, LOST)
    assert link.state(4 * S) == LOST
    assert link.window(4 * S) == (0, 200)


def test_good_frames_ok_then_stale_then_lost_and_back_only_with_good_frames() -> None:
    link = LinkState(P)
    link.opened(0)
    for k in range(100):
        link.record(k * S // 100, good=1)
    t_last = 99 * S // 100
    assert link.state(t_last) == OK
    assert link.state(t_last + S // 2 + 1) == DEGRADED
    assert link.state(t_last + 2 * S + 1) == LOST
    # bad frames do not bring it back
    link.record(t_last + 3 * S, bad=3)
    assert link.state(t_last + 3 * S) == LOST
    link.record(t_last + 3 * S + 1, good=1)
    assert link.state(t_last + 3 * S + 1) == OK


def test_bad_fraction_over_the_window_degrades() -> None:
    link = LinkState(P)
    link.opened(0)
    for k in range(200):  # 30 % bad frames
        t = k * S // 100
        link.record(t, good=1, bad=1 if k % 10 < 3 else 0)
    assert link.state(2 * S) == DEGRADED
    # a few glitches in a busy window are not a degraded link
    link2 = LinkState(P)
    link2.opened(0)
    for k in range(200):
        link2.record(k * S // 100, good=1, bad=1 if k in (50, 150) else 0)
    assert link2.state(2 * S) == OK


def test_a_fault_degrades_whatever_arrives_and_close_says_closed() -> None:
    link = LinkState(P)
    link.opened(0)
    link.record(S // 10, good=5)
    link.fault("protocol version mismatch")
    assert link.state(S // 10) == DEGRADED and link.stats(S // 10)["fault"] == "protocol version mismatch"
    link.fault(None)
    assert link.state(S // 10) == OK
    link.closed()
    assert link.state(S // 10) == CLOSED
