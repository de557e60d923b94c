"""The recording output (``robotd record OUT.mcap``): the frames and odometry exactly as SLAM
consumed them, every published pose, the features the filter used and, once a second, the
landmark map, in one MCAP file (robotd.record, docs/recording.md)."""

from __future__ import annotations

import logging
import threading
from collections.abc import Mapping, Sequence
from typing import Any

from robotd.msgs import Odometry, StereoFrame
from robotd.outputs.base import Output, StepReport
from robotd.record import SessionWriter
from robotd.stereo import RectifiedStereo

logger = logging.getLogger(__name__)


class RecorderOutput(Output):
    """Writes the session to ``path`` (atomically renamed from ``PATH.tmp`` on close).

    The inputs are written on the SLAM thread, the poses on the publisher thread: one lock keeps
    the MCAP writer to one thread at a time.
    """

    name = "recorder"
    map_period_s = 1.0  # the landmark map (point cloud and ellipsoids) once a second

    def __init__(self, path: str, rig: RectifiedStereo, meta: Mapping[str, Any], raw_calibration: Any = None) -> None:
        self.path = path
        self._lock = threading.Lock()
        self.writer = SessionWriter(path, rig, meta, raw_calibration=raw_calibration)

    def record_inputs(self, frame: StereoFrame, odometry: Sequence[Odometry]) -> None:
        with self._lock:
            for odo in odometry:
                self.writer.write_odometry(odo)
            self.writer.write_frame(frame)

    def publish(self, report: StepReport) -> None:
        res = report.result
        # the map's messages are built before taking the lock the SLAM thread's inputs wait on
        lm = None if report.landmarks is None else self.writer.map_messages(res.t_ns, report.landmarks)
        with self._lock:
            self.writer.write_pose(res.pose)
            if res.observations is not None:
                self.writer.write_features(res.observations)
            if lm is not None:
                self.writer.write_map(res.t_ns, lm)

    def stats(self) -> dict[str, Any]:
        c = self.writer.counts
        return {"out": self.path, "frames": c["frames"], "odometry": c["odometry"], "poses": c["poses"]}

    def close(self) -> None:
        with self._lock:
            if self.writer.counts["frames"] == 0:
                logger.warning("no frame was recorded: %s not written", self.path)
                self.writer.discard()
            else:
                self.writer.close()
