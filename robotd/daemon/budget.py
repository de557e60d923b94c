"""Latency budget: stage timings, a per-frame deadline and a degradation policy that recovers.

Degradation order (docs/architecture.md "Performance shape"): (1) cap features, halving down to
``min_features``; (2) reduce particles, halving down to ``min_particles``; (3) skip frames
(process one in 2, then 1 in 3, …).

One step down the ladder when the rung does not fit: a smoothed load above 90 % of the time a
frame may take, or overruns too frequent for a p99 within the deadline (``MISSES_TO_DEGRADE`` in
the last ``MISS_WINDOW`` frames), or one gross overrun (over twice that time: the frame cost the
next one). A lone frame a little late (the scheduler of a shared machine) is not a reason to
degrade: on a 2-core machine a full-settings frame whose steady cost fits the deadline still
overruns now and then, and a rung given up for one such frame was never won back.

One step back up after ``recover_after_frames`` consecutive frames whose smoothed load would fit
the rung above with margin (75 % for feature/particle rungs, whose cost on this pipeline falls
far less than the features or particles do; 80 % for skipping rungs, which cost the same per
processed frame). A step up that is undone within a few recovery periods was a failed probe:
the wait before the next try at that rung doubles (up to ``MAX_BACKOFF`` times), so an
unaffordable rung is not retried every second. The daemon's bounded drop-oldest queues keep
latency bounded meanwhile; the budget keeps the queues short.
"""

from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass

import numpy as np

from robotd.config import Config

DEGRADE_LOAD = 0.9
RECOVER_LOAD = 0.75
SKIP_RECOVER_LOAD = 0.8
EWMA_ALPHA = 0.2
MISS_WINDOW = 100  # frames over which overruns are counted
MISSES_TO_DEGRADE = 3  # ≥ 3 % of frames late: the p99 would no longer be within the deadline
GROSS_OVERRUN = 2.0  # a frame over twice its allowed time degrades at once
PROBE_FRAMES = 4  # a step up undone within this many recovery periods was a failed probe
MAX_BACKOFF = 32  # at most this many times recover_after_frames between probes of one rung


@dataclass(frozen=True, slots=True)
class BudgetState:
    """What the pipeline should do for the next frame."""

    level: int  # 0 = nominal
    max_features: int
    n_particles: int
    skip_every: int  # process one frame in skip_every (1 = every frame)


class StageTimer:
    """Rolling per-stage latency percentiles (last ``window`` frames); safe across threads."""

    def __init__(self, window: int = 300) -> None:
        self.window = window
        self._stages: dict[str, deque[float]] = {}
        self._lock = threading.Lock()

    def add(self, stage: str, ms: float) -> None:
        with self._lock:
            self._stages.setdefault(stage, deque(maxlen=self.window)).append(float(ms))

    def percentiles(self) -> dict[str, dict[str, float]]:
        out: dict[str, dict[str, float]] = {}
        with self._lock:
            snapshot = {k: list(v) for k, v in self._stages.items()}
        for k, v in snapshot.items():
            if v:
                a = np.asarray(v, float)
                out[k] = {"p50": float(np.percentile(a, 50)), "p99": float(np.percentile(a, 99)), "n": len(a)}
        return out


class LatencyBudget:
    def __init__(
        self,
        deadline_ms: float,
        max_features: int,
        n_particles: int,
        min_features: int,
        min_particles: int,
        recover_after_frames: int = 30,
        max_skip: int = 4,
        warmup_frames: int = 0,
        frame_period_ms: float | None = None,
    ) -> None:
        if deadline_ms <= 0:
            raise ValueError(f"deadline_ms: expected > 0, got {deadline_ms}")
        self.deadline_ms = float(deadline_ms)
        # the ladder of states, nominal first
        ladder: list[tuple[int, int, int]] = [(max_features, n_particles, 1)]
        f, p = max_features, n_particles
        while f > min_features:
            f = max(min_features, f // 2)
            ladder.append((f, p, 1))
        while p > min_particles:
            p = max(min_particles, p // 2)
            ladder.append((f, p, 1))
        for k in range(2, max_skip + 1):
            ladder.append((f, p, k))
        self._ladder = ladder
        self.level = 0
        self.recover_after = recover_after_frames
        self.warmup_frames = warmup_frames
        # frames arrive every period: with skipping, k periods per processed frame keep the queue short
        self.frame_period_ms = float(frame_period_ms) if frame_period_ms else float(deadline_ms)
        self._under = 0
        self._ewma: float | None = None
        self._misses: deque[bool] = deque(maxlen=MISS_WINDOW)  # overrun flags of recent frames on this rung
        self._backoff = [1] * len(ladder)  # recovery wait multiplier for stepping up *to* each rung
        self._since_step_up: int | None = None  # frames since the last step up while that probe is judged
        self.deadline_misses = 0
        self.frames = 0
        self.skipped = 0
        self.degrade_events = 0
        self.recover_events = 0
        self._frame_counter = 0
        self.frames_at_level = [0] * len(ladder)  # processed frames per rung (the time spent at each)

    @property
    def state(self) -> BudgetState:
        f, p, k = self._ladder[self.level]
        return BudgetState(self.level, f, p, k)

    @property
    def max_level(self) -> int:
        return len(self._ladder) - 1

    def should_process(self) -> bool:
        """Frame skipping (the last rung): call once per arriving frame."""
        self._frame_counter += 1
        k = self.state.skip_every
        if k > 1 and self._frame_counter % k:
            self.skipped += 1
            return False
        return True

    def record(self, frame_ms: float, latency_ms: float | None = None) -> BudgetState:
        """Account one processed frame's work; returns the state for the next frame.

        ``frame_ms``: the step's own time (the load); ``latency_ms``: capture to the end of the
        step, queue wait included (the deadline's quantity; ``frame_ms`` when not given). A
        processed frame may take at most the deadline (latency) and at most ``skip_every`` frame
        periods (throughput); a step back up is taken when the load would fit the rung above with
        margin.
        """
        self.frames += 1
        self.frames_at_level[self.level] += 1
        if self.frames <= self.warmup_frames:
            return self.state  # first frames (caches, map start) say nothing about steady load
        self._ewma = frame_ms if self._ewma is None else (1 - EWMA_ALPHA) * self._ewma + EWMA_ALPHA * frame_ms
        budget_now = self._allowed_ms(self.state.skip_every)
        late_ms = frame_ms if latency_ms is None else max(frame_ms, latency_ms)
        over = late_ms > budget_now
        if over:
            self.deadline_misses += 1
        self._misses.append(over)
        if self._since_step_up is not None:
            self._since_step_up += 1
            if self._since_step_up > PROBE_FRAMES * self.recover_after:
                self._backoff[self.level] = 1  # the probe held: the rung is affordable again
                self._since_step_up = None
        too_late = late_ms > GROSS_OVERRUN * budget_now or sum(self._misses) >= MISSES_TO_DEGRADE
        if (too_late or self._ewma > DEGRADE_LOAD * budget_now) and self.level < self.max_level:
            if self._since_step_up is not None:
                # the rung we stepped up to did not hold: wait longer before probing it again
                self._backoff[self.level] = min(MAX_BACKOFF, 2 * self._backoff[self.level])
            self.level += 1
            self.degrade_events += 1
            self._under = 0
            self._misses.clear()
            self._since_step_up = None
            # after a step down, judge the new level on fresh data
            self._ewma = min(self._ewma, DEGRADE_LOAD * budget_now * 0.99)
        elif self.level > 0 and self._ewma < self._recover_threshold():
            self._under += 1
            if self._under >= self.recover_after * self._backoff[self.level - 1]:
                self.level -= 1
                self.recover_events += 1
                self._under = 0
                self._misses.clear()
                self._since_step_up = 0
        else:
            self._under = 0
        return self.state

    def _recover_threshold(self) -> float:
        """Load below which one step up is taken: a skipping rung costs the same per processed
        frame as the one above it, so only the time per frame changes (80 % margin); a rung with
        more features or particles costs more, so it needs the wider 75 % margin (a failed probe
        is undone by the degrade rules and backs off)."""
        f, p, _ = self._ladder[self.level]
        f_up, p_up, k_up = self._ladder[self.level - 1]
        margin = SKIP_RECOVER_LOAD if (f_up, p_up) == (f, p) else RECOVER_LOAD
        return margin * self._allowed_ms(k_up)

    def _allowed_ms(self, skip_every: int) -> float:
        """Time a processed frame may take on a rung: within the deadline (latency) and within
        ``skip_every`` frame periods (throughput: otherwise frames queue up)."""
        return min(self.deadline_ms, skip_every * self.frame_period_ms)

    def health(self) -> dict[str, object]:
        s = self.state
        return {
            "deadline_ms": self.deadline_ms,
            "level": s.level,
            "max_level": self.max_level,
            "max_features": s.max_features,
            "n_particles": s.n_particles,
            "skip_every": s.skip_every,
            "load_ms": None if self._ewma is None else round(self._ewma, 3),
            "deadline_misses": self.deadline_misses,
            "skipped_frames": self.skipped,
            "degrade_events": self.degrade_events,
            "recover_events": self.recover_events,
            "recent_misses": int(sum(self._misses)),
            "frames_at_level": list(self.frames_at_level),
        }


def budget_for(cfg: Config, fps: float, particles: bool) -> LatencyBudget:
    """The daemon's budget for a camera at ``fps``: the configured deadline (else the frame
    period), the configured floors, and no particle rungs for a filter without particles; the
    first second (caches, the first map) is warm-up."""
    b = cfg.budget
    return LatencyBudget(
        b.deadline_ms or 1000.0 / fps,
        cfg.frontend.max_features,
        cfg.slam.n_particles if particles else 1,
        min(b.min_features, cfg.frontend.max_features),
        min(b.min_particles, cfg.slam.n_particles) if particles else 1,
        b.recover_after_frames,
        warmup_frames=int(fps),
        frame_period_ms=1000.0 / fps,
    )
