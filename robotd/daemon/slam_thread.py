"""The daemon's SLAM thread: frame queue → :class:`robotd.pipeline.feed.Feed` → publish queue.

Each frame takes the odometry queued since the last one, and goes through the feed the replay uses
too (robotd.pipeline.feed: gate, integrate, step, skip on error), with the daemon's own two additions: the
latency budget admits the frame or skips it (and degrades features and particles, or recovers,
after each step), and a gap between the frames that reached the step beyond the stall threshold
is a stall. It is the only thread that touches the pipeline: the map and state snapshots the outputs
ask for are taken here, between steps.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from drivers.mavlink_odometry import AutopilotPose
from robotd.core.msgs import LandmarkMap, MotionIncrement, Odometry, StepResult, StereoFrame
from robotd.daemon.budget import LatencyBudget
from robotd.daemon.handover import Handover
from robotd.daemon.handover import record as record_handover
from robotd.daemon.health import STALL_MIN_S, STALL_PERIODS, HealthMonitor
from robotd.formats.autopilot import ResetEvent
from robotd.formats.queues import DropOldestQueue
from robotd.outputs import OutputRunner
from robotd.outputs.base import shortest_period
from robotd.outputs.mapfile import HANDOVER_KEY
from robotd.pipeline.feed import Feed

logger = logging.getLogger("robotd.daemon")


@dataclass(frozen=True, slots=True, eq=False)
class Stepped:
    """One SLAM result on its way from the SLAM thread to the publisher thread, with the
    snapshots taken for the outputs that asked for them."""

    frame: StereoFrame
    result: StepResult
    event: str | None  # a pose discontinuity in this step (ResetEvent)
    odometry: MotionIncrement | None  # the vehicle's motion from the previous step's frame to this one
    landmarks: LandmarkMap | None
    state: dict[str, Any] | None
    t_ref_ns: int  # where its latency is measured from (host monotonic): capture, or delivery (Daemon.host_clock)


class Deliveries:
    """When each frame was delivered (host monotonic ns), for a camera whose stamps are not on the
    host's clock (a dataset replayed by ``robotd run``): its latency is measured from delivery.
    The camera thread adds (a tee), the SLAM thread takes, both in sequence order; frames the
    queue dropped are passed over, and at most ``maxlen`` wait."""

    def __init__(self, maxlen: int) -> None:
        self._d: deque[tuple[int, int]] = deque(maxlen=maxlen)

    def tee(self, frame: StereoFrame) -> None:
        self._d.append((frame.seq, time.monotonic_ns()))

    def take(self, seq: int) -> int | None:
        while self._d:
            s, t = self._d[0]
            if s > seq:
                return None
            self._d.popleft()
            if s == seq:
                return t
        return None


class SlamThread:
    """The SLAM thread's loop (:meth:`run`) and its per-frame work (:meth:`on_frame`).

    ``host_clock``: the camera stamps frames on this host's monotonic clock (latency from capture,
    future-stamped odometry refused); otherwise latency is measured from ``deliveries``.
    """

    def __init__(
        self,
        feed: Feed,
        budget: LatencyBudget,
        health: HealthMonitor,
        queues: tuple[DropOldestQueue[StereoFrame], DropOldestQueue[Odometry], DropOldestQueue[Stepped]],
        runner: OutputRunner,
        host_clock: bool,
        deliveries: Deliveries,
        frame_period_s: float,
        handover: Handover | None = None,
        autopilot_pose_at: Callable[[int], AutopilotPose | None] | None = None,
    ) -> None:
        self.feed, self.budget, self.health = feed, budget, health
        self.frame_q, self.odo_q, self.pub_q = queues
        self.runner = runner
        self.host_clock = host_clock
        self.deliveries = deliveries
        self.frame_period_s = frame_period_s
        self.map_period = shortest_period(runner.outputs, "map_period_s")
        self.state_period = shortest_period(runner.outputs, "state_period_s")
        self.next_map, self.next_state = 0.0, time.monotonic() + self.state_period
        self.handover = handover  # the first frames after a resume: the autopilot carries the pose
        self.autopilot_pose_at = autopilot_pose_at  # recorded with each state snapshot
        self.last_t_ns: int | None = None  # the last stepped frame's (the state's pose is at it)
        self.stepped = 0

    def run(self, stop: threading.Event) -> None:
        """Until ``stop`` or the frame queue closes (the camera ended); then closes the publish
        queue, also when a step raised (the publisher then ends with it instead of waiting on a
        queue nobody closes until the shutdown's join gives up on it)."""
        try:
            while not stop.is_set():
                frame = self.frame_q.get(timeout=0.2)
                if frame is None:
                    if self.frame_q.closed:
                        break
                    continue
                self.on_frame(frame, self.odo_q.drain())
        finally:
            self.pub_q.close()

    def on_frame(self, frame: StereoFrame, odometry: list[Odometry]) -> Stepped | None:
        """One frame with the odometry that came since the last: stepped (and queued for the
        publisher), or None when the budget skipped it or the step failed."""
        # what SLAM consumes, queued for the outputs' workers (the recorder got every sample at the pumps)
        self.runner.record_inputs(frame, odometry)
        # delivery stands for capture when the stamps are on another clock (a dataset's), whose
        # vehicle samples are on that clock too: no future-stamp check against the host's then
        t_ref_ns = frame.t_ns if self.host_clock else self.deliveries.take(frame.seq) or time.monotonic_ns()
        now_ns = time.monotonic_ns() if self.host_clock else None
        budget = self.budget
        handed_over = False
        if self.handover is not None and self.handover.pending:
            handed_over = self.handover.on_frame(frame.t_ns)
        fed = self.feed.process(frame, odometry, now_ns, admit=budget.should_process, gap=self._check_gap)
        if fed is None:
            return None
        result, inc, pipeline = fed.result, fed.motion, self.feed.pipeline
        # the budget judges what the deadline is about: capture (or delivery) to result, queue
        # wait included
        latency_ms = (time.monotonic_ns() - t_ref_ns) / 1e6
        self.health.on_step(result.timings_ms)
        state = budget.record(fed.step_ms, latency_ms)
        pipeline.set_max_features(state.max_features)
        if pipeline.kind.particles is not None:
            pipeline.set_particles(state.n_particles)
        now = time.monotonic()
        landmarks = snapshot = None
        if now >= self.next_map:
            self.next_map, landmarks = now + self.map_period, pipeline.estimator.landmarks()
        self.last_t_ns = frame.t_ns
        if now >= self.next_state:
            self.next_state, snapshot = now + self.state_period, pipeline.state_dict()
            handover = record_handover(self.autopilot_pose_at, frame.t_ns)
            if handover is not None:
                snapshot[HANDOVER_KEY] = handover
        event = ResetEvent.RELOCALISATION if result.relocalised else None
        if handed_over and self.stepped > 0:
            event = ResetEvent.RELOCALISATION  # the pose jumps to the carried one mid-run
        self.stepped += 1
        if result.attitude_reset:
            # the pose jumped to level: the autopilot must not take the jump as motion
            self.health.on_attitude_reset()
            event = event or ResetEvent.ATTITUDE_RESET
        if fed.stalled and inc is None:
            # nothing measured the motion across the stall: the pose after it is a guess, and
            # the autopilot must not fuse the jump as motion (docs/interfaces.md §1.5)
            event = event or ResetEvent.STALL
        stepped = Stepped(frame, result, event, inc, landmarks, snapshot, t_ref_ns)
        self.pub_q.put(stepped)
        # the step's work its result does not wait for, now that the pose is on its way
        self.health.on_deferred(self.feed.after_step())
        return stepped

    def _check_gap(self, gap_ns: int, covered: bool) -> bool:
        """Count a stall (a gap between processed frames beyond STALL_PERIODS frame periods, times
        the budget's frame skipping, and STALL_MIN_S); True on a stall."""
        gap_s = gap_ns / 1e9
        limit_s = max(STALL_MIN_S, STALL_PERIODS * self.frame_period_s * self.budget.state.skip_every)
        if gap_s <= limit_s:
            return False
        self.health.on_stall(gap_s, camera=False)
        if not covered:
            self.health.stats.stalls_without_odometry += 1
        logger.warning(
            "stall: %.2f s between processed frames (more than %.2f s)%s",
            gap_s,
            limit_s,
            "" if covered else "; no odometry covers it, the pose after it is a discontinuity",
        )
        return True
