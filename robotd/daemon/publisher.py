"""The daemon's publisher thread: every SLAM step's :class:`~robotd.outputs.base.StepReport` (the
reset counter, the pose quality, the health state, the latency) to the outputs' workers.

The reset counter (robotd.formats.autopilot.ResetCounterPolicy) tells the autopilot where robotd's pose
stream jumped (a map load, a relocalisation, an attitude reset, a stall no odometry covered, a
jump the policy sees itself); each new value is saved to the counter file, so the next run starts
a new segment.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from robotd.config import Config
from robotd.core.msgs import StepResult
from robotd.daemon.budget import LatencyBudget
from robotd.daemon.health import MAX_POSE_SIGMA_M, HealthMonitor
from robotd.daemon.slam_thread import Stepped
from robotd.formats.autopilot import ResetCounterPolicy
from robotd.formats.persist import CounterFile
from robotd.formats.queues import DropOldestQueue
from robotd.outputs import OutputRunner, StepReport, pose_quality

logger = logging.getLogger("robotd.daemon")


class Publisher:
    """The publisher thread's loop (:meth:`run`). ``pending_event``: a discontinuity before the
    first step (a map load), given to the first report."""

    def __init__(
        self,
        cfg: Config,
        pub_q: DropOldestQueue[Stepped],
        health: HealthMonitor,
        budget: LatencyBudget | None,
        runner: OutputRunner,
        reset_policy: ResetCounterPolicy,
        counter_file: CounterFile | None,
        pending_event: str | None = None,
    ) -> None:
        self.cfg = cfg
        self.pub_q = pub_q
        self.health = health
        self.budget = budget
        self.runner = runner
        self.reset_policy = reset_policy
        self.counter_file = counter_file
        self.pending_event = pending_event
        self.seq = 0

    def run(self) -> None:
        """Until the publish queue closes (the SLAM thread ended)."""
        while True:
            item = self.pub_q.get(timeout=0.2)
            if item is None:
                if self.pub_q.closed:
                    break
                continue
            self.publish(item)

    def publish(self, item: Stepped) -> None:
        res = item.result
        self.seq += 1
        event, self.pending_event = self.pending_event or item.event, None
        policy = self.reset_policy
        bumps = policy.bumps
        reset_counter = policy.update(res.pose, event, item.odometry)
        if policy.bumps != bumps:
            logger.info("reset_counter %d: %s at frame %d", reset_counter, policy.last_reason, item.frame.seq)
            if self.counter_file is not None:
                self.counter_file.save(reset_counter)
        report = StepReport(
            result=res,
            seq=self.seq,
            frame_seq=item.frame.seq,
            quality=pose_quality(res, self.cfg.frontend.min_inliers, self.cfg.mavlink.quality_good_sigma_m),
            reset_counter=reset_counter,
            latency_ms=(time.monotonic_ns() - item.t_ref_ns) / 1e6,
            health=self.health_state(res),
            landmarks=item.landmarks,
            state=item.state,
            vel_R_mps=policy.velocity_R,
        )
        self.health.on_published(report, item.frame.truth_T_world_robot)
        self.runner.publish(report)

    def health_state(self, result: StepResult) -> str:
        """The report's health: failed (tracking lost), degraded (the budget below full settings,
        or the position σ beyond MAX_POSE_SIGMA_M) or tracking."""
        if not result.tracking:
            return "failed"
        if self.budget is not None and self.budget.state.level > 0:
            return "degraded"
        if not np.trace(result.pose.cov[:3, :3]) <= MAX_POSE_SIGMA_M**2:  # NaN too
            return "degraded"
        return "tracking"
