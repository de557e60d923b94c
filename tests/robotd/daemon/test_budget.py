"""The daemon's latency budget: the degradation ladder, its recovery, frame skipping, stage timing."""

from __future__ import annotations

import pytest

from robotd.daemon.budget import LatencyBudget, StageTimer


def test_budget_degrades_in_the_stated_order_and_recovers() -> None:
    b = LatencyBudget(
        33.0, max_features=1000, n_particles=100, min_features=250, min_particles=20, recover_after_frames=5, max_skip=3
    )
    states = [b.state]
    for _ in range(b.max_level + 3):  # persistent overload walks down the whole ladder
        states.append(b.record(80.0))
    feats = [s.max_features for s in states]
    parts = [s.n_particles for s in states]
    skips = [s.skip_every for s in states]
    # features first (down to the floor), then particles (down to the floor), then frame skipping
    first_particle_drop = next(i for i, p in enumerate(parts) if p < 100)
    first_skip = next(i for i, k in enumerate(skips) if k > 1)
    assert feats[first_particle_drop - 1] == 250 and first_particle_drop < first_skip
    assert parts[first_skip - 1] == 20 and states[-1].skip_every == 3
    assert b.deadline_misses == b.max_level + 3  # 80 ms is over the 33 ms deadline on every rung
    # load falls: one step back up per `recover_after_frames` quiet frames, all the way to nominal
    for _ in range(5 * b.max_level + 10):  # a few frames first for the smoothed load to fall
        b.record(5.0)
    assert b.state.level == 0 and b.state.max_features == 1000 and b.state.n_particles == 100
    assert b.recover_events == b.max_level
    # every processed frame is counted on the rung it ran at (health's frames_at_level)
    at = b.health()["frames_at_level"]
    assert isinstance(at, list) and sum(at) == b.frames and len(at) == b.max_level + 1
    assert at[b.max_level] >= 3 and at[0] >= 2  # the walk down ended at the last rung; back at L0


def test_frame_skipping_keeps_one_in_k() -> None:
    b = LatencyBudget(10.0, 100, 10, 100, 10, max_skip=3)
    for _ in range(10):
        b.record(100.0)
    assert b.state.skip_every == 3
    kept = sum(b.should_process() for _ in range(30))
    assert kept == 10 and b.skipped == 20


def test_stage_timer_percentiles() -> None:
    t = StageTimer(window=100)
    for v in range(1, 201):
        t.add("detect", float(v))
    p = t.percentiles()["detect"]
    assert p["n"] == 100 and p["p50"] == pytest.approx(150.5) and p["p99"] > 199


def test_skip_rungs_recover_when_the_load_fits_the_rung_above() -> None:
    # 25 ms frames against a 33 ms deadline: too slow to step back to full rate at 60 % margin,
    # but the skipping rungs must not stay engaged (25 ms fits one frame period)
    b = LatencyBudget(33.0, 200, 20, 200, 20, recover_after_frames=5, max_skip=4)
    for _ in range(10):
        b.record(200.0)
    assert b.state.skip_every == 4
    for _ in range(200):
        b.record(25.0)
    assert b.state.skip_every == 1
    # a camera twice as fast as the deadline (16.7 ms frames): 25 ms frames must keep skipping
    fast = LatencyBudget(33.0, 200, 20, 200, 20, recover_after_frames=5, max_skip=4, frame_period_ms=16.7)
    for _ in range(10):
        fast.record(200.0)
    for _ in range(200):
        fast.record(25.0)
    assert fast.state.skip_every == 2


def test_warmup_frames_do_not_degrade() -> None:
    b = LatencyBudget(33.0, 1000, 100, 200, 20, warmup_frames=5)
    for _ in range(5):
        b.record(900.0)
    assert b.state.level == 0 and b.deadline_misses == 0
    b.record(900.0)
    assert b.state.level == 1


def test_isolated_overruns_do_not_degrade_but_frequent_ones_do() -> None:
    # a steady 22 ms frame on a 33 ms deadline with one 40 ms frame in every 100: p99 fits, stay
    b = LatencyBudget(33.0, 1000, 100, 200, 20, recover_after_frames=30)
    for k in range(1000):
        b.record(40.0 if k % 100 == 50 else 22.0)
    assert b.state.level == 0 and b.deadline_misses == 10 and b.degrade_events == 0
    # three late frames within 100 (3 %): the p99 would be over the deadline, step down once
    for k in range(30):
        b.record(40.0 if k % 10 == 0 else 22.0)
    assert b.state.level == 1 and b.degrade_events == 1
    # one frame over twice the deadline degrades at once
    b.record(70.0)
    assert b.state.level == 2


def test_recovers_to_full_settings_when_the_degraded_rungs_barely_save_time() -> None:
    # the per-frame cost is mostly fixed (22 ms at every rung): a load that fits the deadline
    # with 25 % margin must bring the budget back to nominal after a burst of overload
    b = LatencyBudget(33.3, 1000, 100, 200, 20, recover_after_frames=30)
    for _ in range(4):
        b.record(80.0)
    assert b.state.level == 4
    for _ in range(30 * 4 + 20):
        b.record(22.0)
    assert b.state.level == 0 and b.state.max_features == 1000 and b.state.n_particles == 100


def test_failed_probes_back_off() -> None:
    # nominal costs 40 ms (over the 33 ms deadline), one rung down 20 ms: probing nominal every
    # 30 frames would overrun again and again; doubling waits keep the probes rare
    b = LatencyBudget(33.0, 1000, 100, 500, 100, recover_after_frames=30, max_skip=1)
    assert b.max_level == 1
    probes = 0
    for _ in range(5000):
        before = b.state.level
        b.record(40.0 if b.state.level == 0 else 20.0)
        probes += before == 1 and b.state.level == 0
    assert b.recover_events == probes
    # waits of 30, 60, ..., 960 frames (capped at 32×): about 5 + 5000 / 960 probes, not 5000 / 30
    assert 5 <= probes <= 12
    assert b.deadline_misses <= 3 * probes + 1


def test_queue_wait_counts_against_the_deadline() -> None:
    """The deadline is capture-to-result: a 22 ms step that waited 15 ms in the queue is late
    (37 ms), and frequent such frames degrade; the load (EWMA) is still the step's own time."""
    b = LatencyBudget(33.0, 1000, 100, 200, 20, recover_after_frames=30)
    for _ in range(50):
        b.record(22.0, latency_ms=24.0)
    assert b.state.level == 0 and b.deadline_misses == 0
    for k in range(30):
        b.record(22.0, latency_ms=37.0 if k % 10 == 0 else 24.0)
    assert b.deadline_misses == 3 and b.state.level == 1
    assert b.health()["load_ms"] == pytest.approx(22.0)
