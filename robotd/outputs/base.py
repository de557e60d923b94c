"""What every output of the daemon receives, and the base class the outputs build on.

An output is one destination for what SLAM produces: the Zenoh topics, the autopilot link, the
MCAP recording, the map file. The daemon calls every output's hooks the same way, through
:class:`robotd.outputs.runner.OutputRunner`, under one error policy (an exception is logged once
with the output's name, counted, shown in the health document, and stops nothing else):

- :meth:`Output.tee_frame` (camera thread) and :meth:`Output.tee_odometry` (vehicle thread):
  every frame and every odometry sample the devices delivered, before the SLAM queues and the
  latency budget (the recording's sensor log). They must return at once: an output hands the
  sample to a bounded queue of its own and does its work on its own thread;
- :meth:`Output.record_inputs` (before each step: the frame and the odometry that step consumes,
  exactly; the live view shows these), :meth:`Output.publish` (after each step: the step's
  :class:`StepReport`) and :meth:`Output.publish_health` (every ``health_period_s``: the health
  document), in that order, on the output's own worker thread (``robotd-output-<name>``): the
  SLAM, publisher and supervisor threads only queue the call, so a slow output delays nothing but
  itself (its oldest queued calls are dropped, counted);
- :meth:`Output.finish` (shutdown, after the SLAM thread stopped and the worker delivered what
  was queued): the final pipeline state;
- :meth:`Output.close` (when the daemon's ExitStack unwinds);
- :meth:`Output.stats` (supervisor): in the health document under ``outputs.<name>.stats``.

An output that wants the landmark map or the pipeline's state sets ``map_period_s`` /
``state_period_s``: the SLAM thread then takes that snapshot between steps (it is the only
thread that touches the pipeline) and hands it over in the report.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Self

import numpy as np

from robotd.core.msgs import LandmarkMap, Odometry, StepResult, StereoFrame
from robotd.formats.autopilot import position_sigma_m, quality_from

HEALTH_STATES = ("tracking", "degraded", "failed")


@dataclass(frozen=True, slots=True, eq=False)
class StepReport:
    """One step's result as every output receives it.

    seq: publish sequence number (1, 2, …); frame_seq: the camera's sequence number of the frame.
    quality: MAVLink convention, −1 lost, 1..100 (:func:`pose_quality`). reset_counter: bumps at
    every pose discontinuity (docs/interfaces.md §1.5). latency_ms: capture to hand-over to the
    outputs. health: "tracking" | "degraded" (the latency budget is trading accuracy for time) |
    "failed" (tracking lost). landmarks / state: the snapshots taken for outputs that asked for
    them (``map_period_s`` / ``state_period_s``), else None.
    """

    result: StepResult
    seq: int
    frame_seq: int
    quality: int
    reset_counter: int
    latency_ms: float
    health: str
    landmarks: LandmarkMap | None = None
    state: Mapping[str, Any] | None = None
    vel_R_mps: np.ndarray | None = None  # body-frame (FRD) velocity [m/s] of the published poses (ODOMETRY's)


def pose_quality(result: StepResult, min_inliers: int, good_sigma_m: float = 0.2) -> int:
    """The pose's quality in MAVLink's convention (robotd.formats.autopilot.quality_from): −1 lost, else
    1..100 from the accepted correspondences, N_eff/N, the reported position sigma against
    ``good_sigma_m`` (``mavlink.quality_good_sigma_m``) and the consistency monitor's state."""
    pose = result.pose
    cons = result.consistency or {}
    ratio = cons.get("nis_ratio")
    return quality_from(
        result.tracking,
        result.counts.get("identified", 0),
        pose.neff,
        pose.n_particles,
        min_inliers=min_inliers,
        pos_sigma_m=position_sigma_m(pose.cov),
        good_sigma_m=good_sigma_m,
        consistency_state=str(cons.get("state", "unknown")),
        nis_ratio=float(ratio) if isinstance(ratio, int | float) else math.nan,
    )


class Output:
    """Base of the daemon's outputs: every hook does nothing; an output overrides what it needs."""

    name = "output"
    map_period_s: float | None = None  # a LandmarkMap snapshot in the report this often
    state_period_s: float | None = None  # a pipeline state snapshot (Pipeline.state_dict) this often
    health_period_s: float | None = None  # publish_health this often
    # its stats() also at this top-level key of the health document, which the health state reads
    # (the map file's "map_file", the recorder's "recording"); None: under outputs.<name> only
    health_key: str | None = None

    def tee_frame(self, frame: StereoFrame) -> None:
        """Camera thread: every frame the camera delivered, whatever SLAM later drops or skips.
        Must never block or do work (encoding, I/O): queue it and return."""

    def tee_odometry(self, odometry: Odometry) -> None:
        """Vehicle thread: every odometry sample the vehicle link delivered; as :meth:`tee_frame`."""

    def record_inputs(self, frame: StereoFrame, odometry: Sequence[Odometry]) -> None:
        """Worker thread: the inputs of the next step, in the order it consumes them (before its publish)."""

    def publish(self, report: StepReport) -> None:
        """Worker thread: every step's result, in order."""

    def publish_health(self, health: Mapping[str, Any]) -> None:
        """Worker thread: the daemon's health document."""

    def finish(self, state: Mapping[str, Any] | None, t_ns: int) -> None:
        """Shutdown, once the SLAM thread stopped: the final pipeline state (None when no step ran)."""

    def stats(self) -> dict[str, Any]:
        """Counters for the health document (``outputs.<name>.stats``); plain JSON values."""
        return {}

    def close(self) -> None:
        """Release what the output holds (sessions, files, threads)."""

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def shortest_period(outputs: Sequence[Output], attr: str) -> float:
    """The smallest positive ``attr`` period among ``outputs`` (inf when none asks)."""
    periods = [p for o in outputs if (p := getattr(o, attr)) is not None and p > 0]
    return min(periods) if periods else math.inf
