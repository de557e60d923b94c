"""robotd/pipeline/feed.py: the per-frame loop the daemon's SLAM thread and ``robotd replay`` share.

- the same frames and odometry give the same poses, to the last bit, through ``robotd replay``
  and through the daemon's SLAM thread (robotd.daemon.slam_thread), a failed step included;
- a step that raises RobotdError is skipped: logged, counted, no pose, and the next frame's
  motion increment runs from the last frame that was stepped;
- the gate keeps implausible samples out of the integrator; gaps in the sequence and frames
  without odometry are counted; the caller's admission and gap check see what they should.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
import pytest

import drivers
from drivers.cameras import camera_driver
from robotd.config import load_config
from robotd.config.params import odometry_limits_from_config
from robotd.core.errors import RobotdError
from robotd.core.msgs import MotionIncrement, Odometry, StepResult, StereoFrame
from robotd.daemon.budget import LatencyBudget
from robotd.daemon.health import DaemonStats, HealthMonitor
from robotd.daemon.slam_thread import Deliveries, SlamThread
from robotd.formats.queues import DropOldestQueue
from robotd.outputs import OutputRunner
from robotd.pipeline.feed import Feed, FeedCounters
from robotd.pipeline.odometry import OdometryGate, OdometryIntegrator
from robotd.pipeline.step import Pipeline
from robotd.tools.replay import replay

MS = 1_000_000
# a short drive of the simulated rover, small images: about 45 frames and 75 odometry samples
SIM = "sim://?width=320&height=200&duration=1.5&realtime=0&seed=1"
FAIL_SEQ = 20  # the frame whose step is made to fail in the skip test


def _frame(seq: int, t_ns: int) -> StereoFrame:
    img = np.zeros((4, 4), np.uint8)
    return StereoFrame(t_ns, seq, img, img)


def _odo(t_ns: int, v: float = 1.0) -> Odometry:
    return Odometry(t_ns, np.array([v, 0.0, 0.0]), np.zeros(3), "test")


class _Pipeline:
    """Pipeline.step's stand-in: remembers what it was given, raises RobotdError on ``fail``."""

    def __init__(self, fail: set[int] = frozenset()) -> None:  # type: ignore[assignment]
        self.fail = fail
        self.steps: list[tuple[int, MotionIncrement | None]] = []

    def step(self, frame: StereoFrame, inc: MotionIncrement | None) -> Any:
        self.steps.append((frame.seq, inc))
        if frame.seq in self.fail:
            raise RobotdError(f"frame {frame.seq} made to fail")
        return ("result", frame.seq)


def _feed(fail: set[int] = frozenset(), counters: FeedCounters | None = None) -> tuple[Feed, _Pipeline]:  # type: ignore[assignment]
    p = _Pipeline(fail)
    return Feed(p, OdometryIntegrator(max_gap_s=0.5), OdometryGate(), counters), p  # type: ignore[arg-type]


# --- skip on error ---------------------------------------------------------------------------


def test_a_failed_step_is_skipped_logged_and_counted(caplog: pytest.LogCaptureFixture) -> None:
    feed, p = _feed(fail={2})
    odo = [_odo(t * 10 * MS) for t in range(0, 40)]  # 100 Hz over 0.4 s
    out = []
    with caplog.at_level(logging.ERROR):
        for seq, t in enumerate((0, 100 * MS, 200 * MS, 300 * MS)):
            out.append(feed.process(_frame(seq, t), [o for o in odo if t - 100 * MS < o.t_ns <= t]))
    assert [f is None for f in out] == [False, False, True, False]
    assert feed.counters.step_errors == 1 and feed.counters.last_step_error_ns > 0
    assert "frame 2 skipped: frame 2 made to fail" in caplog.text
    # the step after the failure is given the motion since the last frame that was stepped
    seq3, inc3 = p.steps[-1]
    assert seq3 == 3 and inc3 is not None and (inc3.t0_ns, inc3.t1_ns) == (100 * MS, 300 * MS)
    assert out[3] is not None and out[3].motion is inc3 and out[3].result == ("result", 3)
    assert feed.last_t == 300 * MS


def test_deferred_work_that_fails_is_logged_and_counted_and_the_feed_goes_on(caplog: pytest.LogCaptureFixture) -> None:
    """``Feed.after_step`` (the daemon calls it once the pose is queued) holds the step's error
    policy: before, a RobotdError there ended the SLAM thread and the daemon."""
    feed, p = _feed()
    calls = {"n": 0}

    def after_step() -> float:
        calls["n"] += 1
        if calls["n"] == 2:
            raise RobotdError("offset solve made to fail")
        return 1.5

    p.after_step = after_step  # type: ignore[attr-defined]
    odo = [_odo(t * 10 * MS) for t in range(0, 40)]
    spent = []
    with caplog.at_level(logging.ERROR):
        for seq, t in enumerate((0, 100 * MS, 200 * MS, 300 * MS)):
            assert feed.process(_frame(seq, t), [o for o in odo if t - 100 * MS < o.t_ns <= t]) is not None
            spent.append(feed.after_step())
    assert spent == [1.5, 0.0, 1.5, 1.5]
    assert feed.counters.step_errors == 1 and feed.counters.last_step_error_ns > 0
    assert "frame 1: deferred work failed: offset solve made to fail" in caplog.text


def test_a_failed_step_keeps_the_samples_its_interval_needs() -> None:
    """The integrator forgets samples only past a stepped frame: after a failure the increment
    from the last stepped frame is still whole (a pruned one would not be covered)."""
    feed, p = _feed(fail={1, 2})
    odo = [_odo(t * 10 * MS, v=0.5) for t in range(0, 40)]
    for seq, t in enumerate((0, 100 * MS, 200 * MS, 300 * MS)):
        feed.process(_frame(seq, t), [o for o in odo if t - 100 * MS < o.t_ns <= t])
    inc = p.steps[-1][1]
    assert inc is not None and inc.t0_ns == 0
    np.testing.assert_allclose(inc.dp_R_m, [0.15, 0.0, 0.0], atol=1e-12)  # 0.5 m/s over 0.3 s
    assert feed.counters.frames_without_odometry == 0


def test_the_first_frame_after_a_failed_first_frame_gets_no_increment() -> None:
    feed, _ = _feed(fail={0})
    odo = [_odo(t * 10 * MS) for t in range(0, 20)]
    assert feed.process(_frame(0, 0), odo[:1]) is None
    fed = feed.process(_frame(1, 100 * MS), odo[1:11])
    assert fed is not None and fed.motion is None and feed.counters.frames_before_odometry == 0


# --- gating, counting, the caller's hooks ---------------------------------------------------


def test_an_implausible_sample_is_never_integrated() -> None:
    feed, p = _feed()
    odo = [_odo(t * 10 * MS) for t in range(0, 11)]
    odo[5] = _odo(50 * MS, v=100.0)  # faster than any ground vehicle
    feed.process(_frame(0, 0), odo[:1])
    feed.process(_frame(1, 100 * MS), odo[1:])
    assert feed.gate.rejected["speed"] == 1
    inc = p.steps[-1][1]
    assert inc is not None
    np.testing.assert_allclose(inc.dp_R_m, [0.1, 0.0, 0.0], atol=1e-12)  # 1 m/s throughout


def test_future_stamped_samples_are_refused_on_the_host_clock_only() -> None:
    feed, _ = _feed()
    feed.add_odometry([_odo(10_000 * MS)], now_ns=0)
    assert feed.gate.rejected["clock"] == 1
    feed.add_odometry([_odo(10_000 * MS)], now_ns=None)
    assert feed.gate.accepted == 1


def test_sequence_gaps_and_frames_without_odometry_are_counted() -> None:
    counters = DaemonStats()  # the daemon's health counters are the feed's and more
    feed, p = _feed(counters=counters)
    feed.process(_frame(0, 0))
    feed.process(_frame(1, 100 * MS))  # the vehicle said nothing yet
    feed.process(_frame(3, 200 * MS), [_odo(150 * MS), _odo(200 * MS)])  # a gap: frame 2 missing
    feed.process(_frame(4, 300 * MS))  # samples stopped at 200 ms: covered, 100 ms < max_gap
    feed.process(_frame(5, 1300 * MS))  # a second without samples
    assert counters.seq_gaps == 1
    assert counters.frames_before_odometry == 2
    assert counters.frames_without_odometry == 1 and counters.last_without_odometry_ns > 0
    assert [inc is not None for _, inc in p.steps] == [False, False, False, True, False]


def test_admission_and_gap_check() -> None:
    feed, p = _feed(fail={2})
    gaps: list[tuple[int, bool]] = []

    def gap(gap_ns: int, covered: bool) -> bool:
        gaps.append((gap_ns, covered))
        return gap_ns > 150 * MS

    admitted = iter([True, False, True, True, True])
    fed = [
        feed.process(_frame(seq, seq * 100 * MS), admit=lambda: next(admitted), gap=gap)
        for seq in range(5)  # 0 stepped, 1 not admitted, 2 fails, 3 and 4 stepped
    ]
    assert [s for s, _ in p.steps] == [0, 2, 3, 4]
    # measured between the frames given to the step, a failed one included
    assert gaps == [(200 * MS, False), (100 * MS, False), (100 * MS, False)]
    assert [f is not None and f.stalled for f in fed] == [False, False, False, False, False]
    assert fed[0] is not None and fed[0].step_ms >= 0.0


# --- the daemon's and the replay's feed: the same poses -------------------------------------


def _replayed(cfg: Any, step_errors: int = 0) -> list[StepResult]:
    out: list[StepResult] = []
    summary = replay(cfg, SIM, progress=False, on_step=out.append)
    assert summary["step_errors"] == step_errors and summary["odometry"] == "sim"
    return out


def _through_the_slam_thread(cfg: Any, ahead: bool, step_errors: int = 0) -> list[StepResult]:
    """The daemon's SLAM thread (its per-frame work, without the thread) fed the replay's frames
    and odometry: each frame with the samples up to its time, or (``ahead``) every sample before
    the first frame, as a vehicle thread running ahead of the camera delivers them. The budget
    never degrades here (it would change the features, as it should in the daemon)."""
    opts = camera_driver(SIM).replay_options(SIM)  # the replay's: the clock starts where its does
    assert opts
    with drivers.open_camera(SIM, **opts) as cam, drivers.open_vehicle(SIM, **opts) as veh:
        frames = list(cam.frames(timeout_s=1.0))
        odometry = list(veh.odometry(timeout_s=0.0))
        rig = cam.rectified_model()
    pipeline = Pipeline(cfg, rig, np.random.default_rng(cfg.robot.seed))
    health = HealthMonitor()
    feed = Feed(
        pipeline,
        OdometryIntegrator(max_gap_s=cfg.vehicle.max_gap_s),
        OdometryGate(odometry_limits_from_config(cfg)),
        health.stats,
    )
    budget = LatencyBudget(1e9, cfg.frontend.max_features, cfg.slam.n_particles, 1, 1, frame_period_ms=1e9)
    pub_q: DropOldestQueue[Any] = DropOldestQueue(10_000)
    queues = (DropOldestQueue[StereoFrame](1), DropOldestQueue[Odometry](1), pub_q)
    slam = SlamThread(feed, budget, health, queues, OutputRunner([]), False, Deliveries(4), 1 / 30)
    taken = 0
    for frame in frames:
        n = len(odometry) if ahead else sum(o.t_ns <= frame.t_ns for o in odometry)
        slam.on_frame(frame, odometry[taken:n])
        taken = max(taken, n)
    assert health.stats.step_errors == step_errors and health.stats.steps == len(frames) - step_errors
    return [item.result for item in pub_q.drain()]


def _same(a: list[StepResult], b: list[StepResult]) -> None:
    assert len(a) == len(b) > 30
    for x, y in zip(a, b, strict=True):
        assert x.t_ns == y.t_ns
        assert np.array_equal(x.pose.T_world_robot, y.pose.T_world_robot)
        assert np.array_equal(x.pose.cov, y.pose.cov)


@pytest.fixture(scope="module")
def cfg() -> Any:
    return load_config(None)


@pytest.fixture(scope="module")
def replayed(cfg: Any) -> list[StepResult]:
    return _replayed(cfg)


@pytest.mark.parametrize("ahead", [False, True], ids=["in-step", "vehicle-ahead"])
def test_the_daemon_and_the_replay_give_the_same_poses(cfg: Any, replayed: list[StepResult], ahead: bool) -> None:
    assert sum(r.counts.get("landmarks", 0) > 0 for r in replayed) > 30  # a run that maps, with odometry
    _same(replayed, _through_the_slam_thread(cfg, ahead))


def test_the_daemon_and_the_replay_skip_a_failed_frame_alike(cfg: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    step = Pipeline.step

    def failing(self: Pipeline, frame: StereoFrame, inc: MotionIncrement | None) -> StepResult:
        if frame.seq == FAIL_SEQ:
            raise RobotdError("made to fail")
        return step(self, frame, inc)

    monkeypatch.setattr(Pipeline, "step", failing)
    replayed = _replayed(cfg, step_errors=1)
    _same(replayed, _through_the_slam_thread(cfg, ahead=False, step_errors=1))
