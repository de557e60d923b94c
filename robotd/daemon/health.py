"""The daemon's health: counters kept by its threads, the health document (``robotd/<id>/health``,
docs/topics.md) and the once-a-second status line (stderr, systemd STATUS=).

The document's ``state`` is ``ok`` only when nothing is wrong now: ``starting`` before the first
step, ``failed`` while tracking is lost or no step completed for ``RECENT_S``, ``degraded`` with
the reasons in ``problems`` when a vehicle link is not ``ok``, a stall happened in the last
``RECENT_S``, steps failed in that time or none completed for ``NO_STEP_S``, the filter's attitude
was reset in that time (tilted beyond any rover's, docs/reliability.md), frames lately had no
odometry while odometry flows, the last map save failed, the recording lost samples in that time
(its writer fell behind) or failed, an output's hook failed or its worker dropped calls in that
time (robotd.outputs.runner), the pose's position σ exceeds ``MAX_POSE_SIGMA_M``, or the latency
budget runs below full settings (docs/reliability.md).
"""

from __future__ import annotations

import math
import os
import resource
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from robotd.core.geometry import se3_inverse
from robotd.daemon.budget import LatencyBudget, StageTimer
from robotd.formats.queues import DropOldestQueue
from robotd.outputs.base import StepReport
from robotd.pipeline.feed import FeedCounters


def rss_mb() -> float:
    """Resident set size now (Linux /proc), MB."""
    try:
        with open("/proc/self/statm") as f:
            pages = int(f.read().split()[1])
        return pages * os.sysconf("SC_PAGE_SIZE") / 1e6
    except (OSError, ValueError):
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3


# a stall (a gap between processed frames) or a frame without odometry counts as a current problem
# for this long; the counters keep them for good
RECENT_S = 5.0
# a pose whose position σ is larger than this is not a pose to call "ok" (a constant-velocity
# prediction held across a 4 s stall once spread FastSLAM's particles to σ ≈ 84 m)
MAX_POSE_SIGMA_M = 1.0
NO_STEP_S = 1.0  # no completed step for this long: the published pose is stale
STALL_MIN_S = 0.5  # a gap between processed frames longer than this and STALL_PERIODS frame periods
STALL_PERIODS = 5  # (times the budget's 1-in-k frame skipping) is a stall


class HasStats(Protocol):
    def stats(self) -> dict[str, Any]: ...


@dataclass
class DaemonStats(FeedCounters):
    """The daemon threads' counters; the SLAM thread's feed counts its own (robotd.pipeline.feed.FeedCounters:
    step_errors, seq_gaps, frames_without_odometry, frames_before_odometry and their stamps) here too."""

    started_ns: int = field(default_factory=time.monotonic_ns)
    frames_in: int = 0
    odometry_in: int = 0
    steps: int = 0
    last_step_ns: int = 0
    published: int = 0
    latencies_ms: list[float] = field(default_factory=list)  # capture → publish, last window
    reset_counter: int = 0
    last_error_m: float = float("nan")
    max_latency_window: int = 2000
    frames_missed: int = 0  # frames the camera never delivered (gaps in its sequence numbers)
    camera_stalls: int = 0  # gaps in the camera's capture times beyond the stall threshold
    stalls: int = 0  # gaps between processed frames beyond the stall threshold (any cause)
    longest_stall_s: float = 0.0
    last_stall_s: float = 0.0
    last_stall_ns: int = 0  # monotonic time the last stall (either kind) was seen
    stalls_without_odometry: int = 0  # of the stalls, those no odometry covered (a pose discontinuity)
    # 3D: steps whose attitude (roll, pitch) no rover can have was reset to level (Pipeline)
    attitude_resets: int = 0
    last_attitude_reset_ns: int = 0

    def add_latency(self, ms: float) -> None:
        self.latencies_ms.append(ms)
        if len(self.latencies_ms) > self.max_latency_window:
            del self.latencies_ms[: len(self.latencies_ms) - self.max_latency_window]


class HealthMonitor:
    """What the threads report (steps, published results) and the documents made from it."""

    def __init__(self) -> None:
        self.stats = DaemonStats()
        self.timer = StageTimer()  # stage latencies over the last frames
        self._lock = threading.Lock()
        self._last: StepReport | None = None
        self._first_truth_inv: np.ndarray | None = None
        # where latency is measured from: "capture" (the frame's stamp, on this host's monotonic
        # clock) or "delivery" (the host's time when the camera handed the frame over, for a camera
        # whose stamps are on another clock: a dataset replayed by `robotd run`)
        self.latency_from = "capture"

    def frames_dropped(self, frame_q: DropOldestQueue[Any]) -> int:
        """Frames the camera delivered while SLAM was busy (the drop-oldest queue's) plus frames it
        never delivered (gaps in its sequence numbers): the status line's and the stop summary's
        ``dropped``, one quantity."""
        return frame_q.dropped + self.stats.frames_missed

    def on_step(self, timings_ms: Mapping[str, float]) -> None:
        """SLAM thread: one step completed."""
        for k, v in timings_ms.items():
            self.timer.add(k, v)
        self.stats.steps += 1
        self.stats.last_step_ns = time.monotonic_ns()

    def on_deferred(self, ms: float) -> None:
        """SLAM thread: the step's deferred work (``Pipeline.after_step``) took ``ms`` once the pose
        was queued: timed as the stage ``offset``, outside the capture-to-publish latency."""
        if ms > 0:
            self.timer.add("offset", ms)

    def on_attitude_reset(self) -> None:
        """SLAM thread: the step reset an implausible attitude to level (StepResult.attitude_reset)."""
        self.stats.attitude_resets += 1
        self.stats.last_attitude_reset_ns = time.monotonic_ns()

    def on_stall(self, gap_s: float, camera: bool) -> None:
        """A gap of ``gap_s`` between frames: at the camera (capture times) or between processed frames."""
        st = self.stats
        if camera:
            st.camera_stalls += 1
        else:
            st.stalls += 1
        st.longest_stall_s = max(st.longest_stall_s, gap_s)
        st.last_stall_s = gap_s
        st.last_stall_ns = time.monotonic_ns()

    def on_published(self, report: StepReport, truth_T_world_robot: np.ndarray | None) -> None:
        """Publisher thread: a step's report went to the outputs; ``truth``: the simulator's pose."""
        self.stats.add_latency(report.latency_ms)
        self.stats.published += 1
        self.stats.reset_counter = report.reset_counter
        if truth_T_world_robot is not None:
            if self._first_truth_inv is None:
                self._first_truth_inv = se3_inverse(truth_T_world_robot)
            T_true = self._first_truth_inv @ truth_T_world_robot
            est = report.result.pose.T_world_robot
            self.stats.last_error_m = float(np.linalg.norm(est[:3, 3] - T_true[:3, 3]))
        with self._lock:
            self._last = report

    @property
    def last(self) -> StepReport | None:
        with self._lock:
            return self._last

    def doc(
        self,
        ready: bool,
        budget: LatencyBudget,
        frame_q: DropOldestQueue[Any],
        odo_q: DropOldestQueue[Any],
        devices: Mapping[str, HasStats | None],
    ) -> dict[str, Any]:
        """The health document (docs/topics.md ``robotd.health/1``)."""
        lat = np.asarray(self.stats.latencies_ms[-300:]) if self.stats.latencies_ms else np.zeros(0)
        last = self.last
        res = last.result if last else None
        st = self.stats
        now = time.monotonic_ns()
        sigma = _position_sigma_m(res.pose.cov) if res else None
        return {
            "t_ns": time.monotonic_ns(),
            "uptime_s": round((time.monotonic_ns() - self.stats.started_ns) / 1e9, 3),
            "ready": ready,
            "tracking": bool(res.tracking) if res else False,
            "quality": last.quality if last else 0,
            "stages_ms": self.timer.percentiles(),
            "latency_ms": {
                "p50": float(np.percentile(lat, 50)) if lat.size else None,
                "p99": float(np.percentile(lat, 99)) if lat.size else None,
                "from": self.latency_from,
            },
            "frames_in": self.stats.frames_in,
            "frames_processed": self.stats.steps,
            "frames_dropped": self.frames_dropped(frame_q),
            "frame_drops": frame_q.dropped,
            "odometry_drops": odo_q.dropped,
            "seq_gaps": self.stats.seq_gaps,
            "frames_missed": st.frames_missed,
            "stalls": st.stalls,
            "camera_stalls": st.camera_stalls,
            "longest_stall_s": round(st.longest_stall_s, 3),
            "last_stall_s": round(st.last_stall_s, 3),
            "since_stall_s": round((now - st.last_stall_ns) / 1e9, 1) if st.last_stall_ns else None,
            "stalls_without_odometry": st.stalls_without_odometry,
            "frames_without_odometry": st.frames_without_odometry,
            "frames_before_odometry": st.frames_before_odometry,
            "pose_sigma_m": None if sigma is None or not np.isfinite(sigma) else round(sigma, 4),
            "step_errors": self.stats.step_errors,
            "attitude_resets": st.attitude_resets,
            "budget": budget.health(),
            "neff": None if not res or not np.isfinite(res.pose.neff) else float(res.pose.neff),
            "particles": res.pose.n_particles if res else 0,
            "features": res.counts.get("features_left", 0) if res else 0,
            "landmarks": res.counts.get("landmarks", 0) if res else 0,
            # the reported covariance's consistency monitor (pose_sigma_m above is its position sigma)
            "consistency": dict(res.consistency) if res else None,
            "error_vs_truth_m": None if not np.isfinite(self.stats.last_error_m) else self.stats.last_error_m,
            "rss_mb": round(rss_mb(), 1),
            **{name: _safe_stats(dev) for name, dev in devices.items()},
        }

    def assess(self, h: dict[str, Any], needs_vehicle: bool) -> dict[str, Any]:
        """Add ``state`` and ``problems`` to the health document ``h`` (module docstring)."""
        st = self.stats
        now = time.monotonic_ns()
        problems: list[str] = []
        vehicle = h.get("vehicle") or {}
        link = vehicle.get("state")
        if needs_vehicle and link not in (None, "ok"):
            problems.append(f"vehicle link {link}")
        if st.last_stall_ns and now - st.last_stall_ns < RECENT_S * 1e9:
            problems.append(f"stall {st.last_stall_s:.1f} s")
        lacking = st.last_without_odometry_ns and now - st.last_without_odometry_ns < RECENT_S * 1e9
        if st.last_step_error_ns and now - st.last_step_error_ns < RECENT_S * 1e9:
            problems.append(f"frames failing ({st.step_errors})")
        if st.last_attitude_reset_ns and now - st.last_attitude_reset_ns < RECENT_S * 1e9:
            problems.append(f"attitude reset ({st.attitude_resets}): tilt beyond vehicle.max_tilt_deg")
        if self.last is not None and now - st.last_step_ns > NO_STEP_S * 1e9:
            problems.append(f"no SLAM step for {(now - st.last_step_ns) / 1e9:.1f} s")
        if needs_vehicle and st.odometry_in > 0 and lacking:
            problems.append(f"frames without odometry ({st.frames_without_odometry})")
        saves = h.get("map_file") or {}
        if saves.get("last_failed"):
            problems.append(f"map save failed ({saves.get('failures')})")
        rec = h.get("recording") or {}
        if rec.get("error"):
            problems.append("recording failed")
        elif rec.get("last_loss_ns") and now - rec["last_loss_ns"] < RECENT_S * 1e9:
            # the recorder's writer (disk, PNG encoding) fell behind and its queue was full
            problems.append(f"recording lost {rec['frames_lost']} frames, {rec['odometry_lost']} odometry")
        for name, out in (h.get("outputs") or {}).items():  # robotd.outputs.runner: one policy for all
            if out.get("since_error_s") is not None and out["since_error_s"] < RECENT_S:
                problems.append(f"output {name} failing ({out['errors']})")
            if out.get("since_drop_s") is not None and out["since_drop_s"] < RECENT_S:
                problems.append(f"output {name} behind ({out['dropped']} dropped)")
        sigma = h.get("pose_sigma_m")
        if sigma is None and self.last is not None:
            sigma = math.inf  # a covariance that is no longer finite
        if sigma is not None and sigma > MAX_POSE_SIGMA_M:
            problems.append(f"pose sigma {sigma:.2g} m")
        if h["budget"].get("level", 0) > 0:
            problems.append(f"budget L{h['budget']['level']}")
        if self.last is None:
            state = "starting"
        elif not h["tracking"]:
            state = "failed"
            problems.insert(0, "tracking lost")
        elif now - st.last_step_ns > RECENT_S * 1e9:
            state = "failed"  # frames come but no step completes: the pose is not being estimated
        else:
            state = "degraded" if problems else "ok"
        h["state"], h["problems"] = state, problems
        return h

    def status_line(self, h: Mapping[str, Any], fps: float) -> str:
        """The once-a-second line: pose, error against truth, latency, rate, map and budget."""
        last = self.last
        if last is None:
            return f"waiting for frames (in {h['frames_in']}, odometry {self.stats.odometry_in})"
        p = last.result.pose
        yaw = np.degrees(p.rpy_rad[2])
        err = h["error_vs_truth_m"]
        lat = h["latency_ms"]
        b = h["budget"]
        since = " from delivery" if lat.get("from") == "delivery" else ""  # a dataset's clock is not the host's
        # frames SLAM did not process: dropped (delivered while SLAM was busy, or never delivered:
        # frames_dropped) or skipped by the latency budget (its last rung processes one frame in k)
        budget = f"budget L{b['level']}"
        if b["level"] > 0:
            budget += f" ({b['max_features']} feat, {b['n_particles']} particles"
            budget += f", 1 frame in {b['skip_every']})" if b["skip_every"] > 1 else ")"
        line = (
            f"pose x {p.xyz_W_m[0]:+7.2f} y {p.xyz_W_m[1]:+7.2f} z {p.xyz_W_m[2]:+6.2f} m yaw {yaw:+6.1f}° | "
            f"err {'n/a' if err is None else f'{err:.3f} m'} | "
            f"latency p50 {lat['p50'] or 0:.1f} p99 {lat['p99'] or 0:.1f} ms{since} | "
            f"{fps:.1f} fps, dropped {h['frames_dropped']} skipped {b['skipped_frames']} | "
            f"lm {h['landmarks']} feat {h['features']} | q {last.quality} {budget}"
        )
        # what is wrong, when something is: the stalls, missing odometry, the links, failed saves
        if h.get("state", "ok") != "ok":
            line += f" | {h['state'].upper()}: {', '.join(h.get('problems', []))}"
        return line


def _position_sigma_m(cov: np.ndarray) -> float:
    """sqrt of the trace of the position block of a (6, 6) pose covariance (x, y, z, roll, pitch, yaw)."""
    tr = float(np.trace(np.asarray(cov, float)[:3, :3]))
    return math.sqrt(tr) if np.isfinite(tr) and tr >= 0 else math.inf


def _safe_stats(dev: HasStats | None) -> dict[str, Any]:
    """A device's scalar figures, and its lists of them (a link's refused message rates)."""
    if dev is None:
        return {}
    try:
        s = dev.stats()
        return {k: (list(v) if isinstance(v, list | tuple) else v) for k, v in s.items() if _plain(v)}
    except Exception as exc:
        return {"error": str(exc)}


def _plain(v: Any) -> bool:
    if isinstance(v, list | tuple):
        return all(isinstance(x, int | float | str | bool) for x in v)
    return isinstance(v, int | float | str | bool) or v is None
