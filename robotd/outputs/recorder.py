"""The recording output (``robotd record OUT.mcap``): the sensor log, every camera frame and every
vehicle sample as the devices delivered them, whatever SLAM kept up with, and beside them what
SLAM made of the frames it processed (every published pose, the features the filter used and,
once a second, the landmark map), in one MCAP file (robotd.formats.record, docs/recording.md).

The inputs come from the daemon's input threads (:meth:`RecorderOutput.tee_frame` on the camera
thread, :meth:`RecorderOutput.tee_odometry` on the vehicle thread), before the SLAM frame queue
and the latency budget; the poses from its worker thread (robotd.outputs.runner). None of them waits for the disk:
each hands its sample to a bounded queue (:class:`SampleQueue`) and returns, and the output's
own writer thread encodes (PNG) and writes. When the writer falls behind (a slow disk, a host too
busy to encode) and the queue is full, a new sample is refused and counted under its stream
(``frames_lost``, ``odometry_lost``, ``poses_lost``): the health document and the ``record``
command's summary show them, and the file's ``robotd.recording`` metadata keeps them.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections import deque
from collections.abc import Mapping
from typing import Any

from robotd.core.errors import RobotdError
from robotd.core.msgs import LandmarkMap, Observations, Odometry, PoseEstimate, StereoFrame
from robotd.core.stereo import RectifiedStereo
from robotd.formats.record import SessionWriter
from robotd.outputs.base import Output, StepReport

logger = logging.getLogger(__name__)

DEFAULT_BUFFER_MB = 128.0  # ~8 s of 640×400 stereo at 30 Hz waiting for the writer
MAX_QUEUED = 100_000  # samples of any kind (odometry at 1 kHz for 100 s)
STREAMS = ("frames", "odometry", "poses")

_Step = tuple[PoseEstimate, Observations | None, LandmarkMap | None]


class SampleQueue:
    """A bounded FIFO from the threads that produce samples to the one that writes them.

    ``put`` never blocks: a sample that does not fit (``max_bytes`` of image data queued, or
    ``max_items`` samples) is refused and counted in ``lost[stream]``; an empty queue takes any
    one sample. ``close`` refuses everything after it (counted too) and lets ``get`` return None
    once the queue is empty.
    """

    def __init__(self, max_bytes: int, max_items: int = MAX_QUEUED) -> None:
        if max_bytes < 1 or max_items < 1:
            raise ValueError(f"max_bytes {max_bytes}, max_items {max_items}: expected >= 1")
        self.max_bytes, self.max_items = int(max_bytes), int(max_items)
        self._items: deque[tuple[str, Any, int]] = deque()
        self._cond = threading.Condition()
        self._closed = False
        self.bytes = 0
        self.high_water_bytes = 0
        self.put_count = dict.fromkeys(STREAMS, 0)
        self.lost = dict.fromkeys(STREAMS, 0)
        self.last_loss_ns = 0  # monotonic time of the last refused sample (0: none)

    def put(self, stream: str, item: Any, nbytes: int = 0) -> bool:
        """Queue ``item`` of ``stream`` (``nbytes`` of image data); False when it was refused."""
        with self._cond:
            full = len(self._items) >= self.max_items or (self._items and self.bytes + nbytes > self.max_bytes)
            if self._closed or full:
                self.lost[stream] = self.lost.get(stream, 0) + 1
                self.last_loss_ns = time.monotonic_ns()
                return False
            self._items.append((stream, item, nbytes))
            self.bytes += nbytes
            self.high_water_bytes = max(self.high_water_bytes, self.bytes)
            self.put_count[stream] = self.put_count.get(stream, 0) + 1
            self._cond.notify()
            return True

    def get(self, timeout: float | None = None) -> tuple[str, Any] | None:
        """The oldest ``(stream, item)``; None after ``timeout`` seconds, or when closed and empty."""
        with self._cond:
            if not self._items and not self._closed:
                self._cond.wait(timeout)
            if not self._items:
                return None
            stream, item, nbytes = self._items.popleft()
            self.bytes -= nbytes
            return stream, item

    def close(self) -> None:
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    def lose(self, stream: str) -> None:
        """Count one sample of ``stream`` as lost (one the writer had taken and could not write)."""
        with self._cond:
            self.lost[stream] = self.lost.get(stream, 0) + 1
            self.last_loss_ns = time.monotonic_ns()

    def discard(self) -> int:
        """Drop everything queued, counted as lost; returns how many."""
        with self._cond:
            n = len(self._items)
            for stream, _, _ in self._items:
                self.lost[stream] = self.lost.get(stream, 0) + 1
            if n:
                self.last_loss_ns = time.monotonic_ns()
            self._items.clear()
            self.bytes = 0
            return n

    @property
    def closed(self) -> bool:
        return self._closed

    def __len__(self) -> int:
        with self._cond:
            return len(self._items)


class RecorderOutput(Output):
    """Writes the session to ``path`` (atomically renamed from ``PATH.tmp`` on close) on its own
    writer thread; ``buffer_mb`` of images may wait for it (module docstring). ``error`` is the
    failure that stopped the recording (None while it works): the daemon stops on it."""

    name = "recorder"
    health_key = "recording"  # the health state reads the recording's losses and error there
    map_period_s = 1.0  # the landmark map (point cloud and ellipsoids) once a second

    def __init__(
        self,
        path: str,
        rig: RectifiedStereo,
        meta: Mapping[str, Any],
        raw_calibration: Any = None,
        buffer_mb: float = DEFAULT_BUFFER_MB,
        writer: SessionWriter | None = None,
    ) -> None:
        self.path = path
        self.writer = writer or SessionWriter(path, rig, meta, raw_calibration=raw_calibration)
        self.buffer_mb = float(buffer_mb)
        self.queue = SampleQueue(max(1, int(buffer_mb * 1e6)))
        self.error: str | None = None
        self._crashed = False  # a bug, not a write error: the file is still whole up to here
        self._first_t_ns: int | None = None
        self._last_t_ns: int | None = None
        self._thread = threading.Thread(target=self._write_loop, name="robotd-recorder", daemon=True)
        self._thread.start()

    # -- the producers' side: never blocks ----------------------------------------------------
    def tee_frame(self, frame: StereoFrame) -> None:
        self.queue.put("frames", frame, int(frame.left.nbytes + frame.right.nbytes))

    def tee_odometry(self, odometry: Odometry) -> None:
        self.queue.put("odometry", odometry)

    def publish(self, report: StepReport) -> None:
        res, lm = report.result, report.landmarks
        nbytes = 0 if lm is None else int(lm.xyz_W_m.nbytes + lm.cov_W.nbytes)
        self.queue.put("poses", (res.pose, res.observations, lm), nbytes)

    # -- the writer thread ---------------------------------------------------------------------
    def _write_loop(self) -> None:
        w = self.writer
        while True:
            item = self.queue.get(timeout=w.flush_period_s)
            try:
                if item is None:
                    if self.queue.closed:
                        return
                    w.flush_if_due()  # a quiet camera must not keep the last chunk from the disk
                    continue
                stream, obj = item
                if stream == "frames":
                    w.write_frame(obj)
                    self._first_t_ns = obj.t_ns if self._first_t_ns is None else self._first_t_ns
                    self._last_t_ns = obj.t_ns
                elif stream == "odometry":
                    w.write_odometry(obj)
                else:
                    self._write_step(obj)
            except RobotdError as exc:  # disk full, an I/O error: the writer discarded its file
                self._stop(str(exc), item)
                return
            except Exception as exc:  # a bug: the recording ends as loudly
                logger.exception("recorder thread crashed")
                self._crashed = True
                self._stop(f"recorder thread crashed: {type(exc).__name__}: {exc}", item)
                return

    def _stop(self, why: str, item: tuple[str, Any] | None) -> None:
        if item is not None:
            self.queue.lose(item[0])
        self.error = why
        logger.error("recording stopped: %s", why)
        self.queue.close()
        self.queue.discard()

    def _write_step(self, step: _Step) -> None:
        pose, observations, landmarks = step
        self.writer.write_pose(pose)
        if observations is not None:
            self.writer.write_features(observations)
        if landmarks is not None:
            self.writer.write_map(pose.t_ns, landmarks)

    # -- figures and the end ---------------------------------------------------------------------
    def stats(self) -> dict[str, Any]:
        c, q = self.writer.counts, self.queue
        first, last = self._first_t_ns, self._last_t_ns
        span = 0.0 if first is None or last is None else (last - first) / 1e9
        return {
            "out": self.path,
            "frames": c["frames"],
            "odometry": c["odometry"],
            "poses": c["poses"],
            "frames_lost": q.lost["frames"],
            "odometry_lost": q.lost["odometry"],
            "poses_lost": q.lost["poses"],
            "last_loss_ns": q.last_loss_ns,
            "queued": len(q),
            "queued_mb": round(q.bytes / 1e6, 1),
            "queue_high_water_mb": round(q.high_water_bytes / 1e6, 1),
            "buffer_mb": self.buffer_mb,
            "bytes": c["bytes"],
            "span_s": round(span, 3),
            "error": self.error,
        }

    def close(self) -> None:
        """Write what is still queued, then finalise the file (or discard it when it holds no frame)."""
        self.queue.close()
        while self._thread.is_alive():
            left = len(self.queue)
            if left:
                logger.info("recording: writing the %d samples still queued (%.0f MB)", left, self.queue.bytes / 1e6)
            self._thread.join(5.0)
        if self.error is not None:
            # a write error: the writer discarded its temporary file and said why; the daemon
            # stopped on it. A crash of this thread: what was written is finalised.
            if self._crashed and self.writer.counts["frames"]:
                with contextlib.suppress(Exception):
                    self.writer.close()
            return
        if self.writer.counts["frames"] == 0:
            logger.warning("no frame was recorded: %s not written", self.path)
            self.writer.discard()
            return
        s = self.stats()
        self.writer.add_metadata(
            "robotd.recording", {k: str(s[k]) for k in ("frames", "odometry", "poses", "frames_lost", "odometry_lost",
                                                         "poses_lost", "queue_high_water_mb", "buffer_mb")}
        )  # fmt: skip
        self.writer.close()


def summary_line(s: Mapping[str, Any]) -> str:
    """``robotd record``'s last line (from :meth:`robotd.daemon.Daemon.record_summary`): what the
    devices delivered, what the file holds and lost, its size and rate, and what SLAM processed."""
    if s.get("error"):
        return f"recording failed: {s['error']}"
    if not s.get("frames"):
        return f"no frame was recorded: {s.get('out')} not written"
    mb, span = s.get("bytes", 0) / 1e6, s.get("span_s", 0.0)
    rate = f", {mb / span:.1f} MB/s" if span > 0 else ""
    line = (
        f"recorded {s['frames']} of {s['frames_delivered']} frames the camera delivered, "
        f"{s['odometry']} of {s['odometry_delivered']} odometry samples, {s['poses']} poses: "
        f"{mb:.1f} MB over {span:.1f} s{rate}, {s['out']}"
    )
    lost = s.get("frames_lost", 0), s.get("odometry_lost", 0), s.get("poses_lost", 0)
    if any(lost):
        line += (
            f"; LOST {lost[0]} frames, {lost[1]} odometry samples, {lost[2]} poses: the writer fell behind "
            f"(disk or CPU; --buffer-mb {s.get('buffer_mb', DEFAULT_BUFFER_MB):g} was full)"
        )
    line += f"; live SLAM processed {s['slam_steps']} of them (a replay processes every recorded frame)"
    return line
