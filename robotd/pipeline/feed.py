"""One frame into SLAM: the per-frame loop the daemon's SLAM thread and ``robotd replay`` share.

:meth:`Feed.process` takes a frame and the vehicle samples that arrived with it and does, in
order: the odometry gate (an implausible sample is counted and never integrated) and the
integrator; the frame's sequence gap (counted); the caller's admission (the daemon's latency
budget may skip the frame); the motion increment from the last stepped frame to this one (None:
visual only; counted when odometry flows but does not cover it); the caller's gap check (the
daemon's stall); ``Pipeline.step``; and the skip semantics: a step that raises ``RobotdError`` is
logged, counted in ``step_errors`` and skipped (the next frame's increment then starts from the
last frame that was stepped), and the integrator forgets samples only past a stepped frame.

Nothing here owns a thread, a queue or a device: the daemon feeds it from its queues on its SLAM
thread, the replay from its source in recorded order. The same frames and samples in give the
same steps out, whichever feeds them (tests/robotd/pipeline/test_feed.py).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass

from robotd.core.errors import RobotdError
from robotd.core.msgs import MotionIncrement, Odometry, StepResult, StereoFrame
from robotd.pipeline.odometry import OdometryGate, OdometryIntegrator
from robotd.pipeline.step import Pipeline

logger = logging.getLogger("robotd.feed")  # its name before the layer packages: users filter by it


@dataclass
class FeedCounters:
    """What the feed counts (the daemon's health counters, :class:`robotd.daemon.health.DaemonStats`,
    are these and more). The ``last_*_ns`` stamps are the host's monotonic clock."""

    step_errors: int = 0  # frames whose step raised RobotdError (logged and skipped)
    last_step_error_ns: int = 0
    seq_gaps: int = 0  # frames whose sequence number did not follow the previous frame's
    frames_without_odometry: int = 0  # stepped-for frames whose interval no odometry covered
    frames_before_odometry: int = 0  # ... before the vehicle's first plausible sample (not counted above)
    last_without_odometry_ns: int = 0


@dataclass(frozen=True, slots=True, eq=False)
class Fed:
    """A frame that was stepped: its result, the motion increment it was given, the step's
    milliseconds (``Pipeline.step`` alone) and whether the caller's gap check called it a stall."""

    result: StepResult
    motion: MotionIncrement | None
    step_ms: float
    stalled: bool


class Feed:
    """The per-frame loop around ``pipeline``: gate → integrate → step → skip on error.

    ``counters``: where to count (a :class:`FeedCounters` or a subclass; a fresh one by default).
    ``log``: the logger of a skipped frame's line (the caller's: ``robotd.daemon``, ``robotd.tools.replay``).
    """

    def __init__(
        self,
        pipeline: Pipeline,
        integrator: OdometryIntegrator,
        gate: OdometryGate,
        counters: FeedCounters | None = None,
        log: logging.Logger = logger,
    ) -> None:
        self.pipeline = pipeline
        self.integrator = integrator
        self.gate = gate
        self.counters = FeedCounters() if counters is None else counters
        self.log = log
        self.last_t: int | None = None  # the last frame stepped
        self.last_in: int | None = None  # the last frame given to the step (it may have failed)
        self._last_seq: int | None = None
        self._first_odo_ns: int | None = None  # the first plausible odometry sample's time

    def add_odometry(self, samples: Iterable[Odometry], now_ns: int | None = None) -> None:
        """Gate each sample (``now_ns``: the host's clock, for the future-stamp check; None when
        the stamps are on another clock) and integrate the plausible ones, in order."""
        for odo in samples:
            if self.gate.accept(odo, now_ns):  # an implausible sample is never integrated
                self.integrator.add(odo)
                if self._first_odo_ns is None:
                    self._first_odo_ns = odo.t_ns

    def process(
        self,
        frame: StereoFrame,
        odometry: Iterable[Odometry] = (),
        now_ns: int | None = None,
        admit: Callable[[], bool] | None = None,
        gap: Callable[[int, bool], bool] | None = None,
    ) -> Fed | None:
        """Step ``frame`` with the vehicle samples that came with it; None when ``admit`` (called
        once per frame, after the samples are taken) passes the frame over or the step failed.
        ``gap(gap_ns, covered)``: called before the step with the time since the last frame given
        to the step and whether odometry covers it; its answer is :attr:`Fed.stalled`."""
        self.add_odometry(odometry, now_ns)
        if self._last_seq is not None and frame.seq > self._last_seq + 1:
            self.counters.seq_gaps += 1
        self._last_seq = frame.seq
        if admit is not None and not admit():
            return None
        inc = self.motion(frame.t_ns)
        # a stall: measured between frames that reached the step, whether or not the step worked
        stalled = gap is not None and self.last_in is not None and gap(frame.t_ns - self.last_in, inc is not None)
        self.last_in = frame.t_ns
        t0 = time.perf_counter()
        try:
            result = self.pipeline.step(frame, inc)
        except RobotdError as exc:
            self.counters.step_errors += 1
            self.counters.last_step_error_ns = time.monotonic_ns()
            self.log.error("frame %d skipped: %s", frame.seq, exc)
            return None
        step_ms = (time.perf_counter() - t0) * 1e3
        self.last_t = frame.t_ns
        self.integrator.prune_before(frame.t_ns)
        return Fed(result, inc, step_ms, stalled)

    def after_step(self) -> float:
        """The last step's deferred work (``Pipeline.after_step``), under the step's error policy:
        a RobotdError there is logged and counted in ``step_errors`` like a failed step (the pose
        it followed is already out; the measurement it would have made is lost) and the feed goes
        on. Returns the milliseconds it took (0 when nothing waited or it failed)."""
        try:
            return self.pipeline.after_step()
        except RobotdError as exc:
            self.counters.step_errors += 1
            self.counters.last_step_error_ns = time.monotonic_ns()
            self.log.error("frame %s: deferred work failed: %s", self._last_seq, exc)
            return 0.0

    def motion(self, t_ns: int) -> MotionIncrement | None:
        """The vehicle's motion from the last stepped frame to ``t_ns``; None for the first frame
        and when no odometry covers the interval (counted)."""
        if self.last_t is None:
            return None
        inc = self.integrator.integrate(self.last_t, t_ns)
        if inc is None:
            if self._first_odo_ns is None or self.last_t < self._first_odo_ns:
                # the vehicle has not measured anything yet (an autopilot's EKF sends no
                # velocity for its first seconds): counted apart, not a fault of the link
                self.counters.frames_before_odometry += 1
            else:
                self.counters.frames_without_odometry += 1
                self.counters.last_without_odometry_ns = time.monotonic_ns()
        return inc
