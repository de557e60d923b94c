"""The live view (``[liveview] enabled = true``): the recording's channels served to the Foxglove
app while robotd runs, over the Foxglove SDK's WebSocket server (docs/recording.md, "Live view"),
behind a front that also accepts viewers offering only the older ``foxglove.websocket.v1``
subprotocol (liveview_front).

The messages are the ones a recording holds (robotd.formats.record.FoxgloveScene): images with the
feature tracks, the pose, trajectory and ground truth, the landmark map with its ellipsoids, the
transforms world → robot → cameras, the odometry. The server listens on loopback by default
(``liveview.host``); nothing is sent, and no image is encoded, for a channel no client has
subscribed to.

Threads: the frame and the odometry a step consumes (:meth:`record_inputs`, which only keeps
them) and every step's report (:meth:`publish`, where everything is built and sent) arrive on
this output's worker thread (robotd.outputs.runner), so the live view costs the SLAM thread
nothing and a slow viewer delays no other output.
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from collections.abc import Sequence
from typing import Any

from robotd.config import LiveViewConfig
from robotd.core.errors import DriverError
from robotd.core.msgs import Odometry, StereoFrame
from robotd.core.stereo import RectifiedStereo
from robotd.formats.record import FoxgloveScene, Item, calibration_to_json, message_encoding, payload, schema_record
from robotd.outputs.base import Output, StepReport
from robotd.outputs.liveview_front import SubprotocolFront

logger = logging.getLogger(__name__)

KEEP_FRAMES = 8  # frames waiting for their step's result (the publisher queue is shorter)
KEEP_ODOMETRY = 2048  # samples waiting for the next publish


class LiveViewOutput(Output):
    name = "liveview"

    def __init__(self, cfg: LiveViewConfig, rig: RectifiedStereo, robot_id: str, raw_calibration: Any = None) -> None:
        try:
            import foxglove
        except ImportError as exc:
            raise DriverError(
                f"liveview.enabled: the Foxglove SDK is not installed ({exc}); pip install 'robotd[live]' "
                "(or foxglove-sdk), or set [liveview] enabled = false"
            ) from None
        self.cfg = cfg
        self.map_period_s = cfg.map_period_s
        self.scene = FoxgloveScene(rig, calibration_to_json(rig, raw_calibration))
        self._lock = threading.Lock()
        self._frames: deque[StereoFrame] = deque(maxlen=KEEP_FRAMES)
        self._odometry: deque[Odometry] = deque(maxlen=KEEP_ODOMETRY)
        self._counts = {"frames": 0, "odometry": 0, "poses": 0, "sent": 0}
        self._ctx = foxglove.Context()  # robotd's channels only, never the SDK's global context
        self._channels = {}
        for key, (topic, schema) in self.scene.channels().items():
            enc, data = schema_record(schema)
            sch = foxglove.Schema(name=schema, encoding=enc, data=data)
            self._channels[key] = foxglove.Channel(
                topic, schema=sch, message_encoding=message_encoding(schema), context=self._ctx
            )
        # the SDK's server on a loopback port of its own, behind a front on the configured address
        # that also lets in clients offering only the older subprotocol name (liveview_front)
        try:
            self._server = foxglove.start_server(name=f"robotd {robot_id}", host="127.0.0.1", port=0, context=self._ctx)
        except RuntimeError as exc:  # the SDK's FoxgloveError
            raise DriverError(f"liveview: the Foxglove SDK's server did not start: {exc}") from None
        try:
            self._front = SubprotocolFront(cfg.host, cfg.port, int(self._server.port))
        except OSError as exc:  # e.g. the port is taken
            self._server.stop()
            raise DriverError(
                f"liveview.port: cannot listen on {cfg.host}:{cfg.port}: {exc.strerror or exc}; set another "
                "[liveview] port or enabled = false"
            ) from None
        logger.info(
            "live view: ws://%s:%d (Foxglove: open a connection, Foxglove WebSocket; subprotocol foxglove.sdk.v1 "
            "or foxglove.websocket.v1)",
            cfg.host,
            self.port,
        )

    @property
    def port(self) -> int:
        """The port the live view listens on (the configured one, or the one the OS chose for 0)."""
        return self._front.port

    def _wanted(self, key: str) -> bool:
        return bool(self._channels[key].has_sinks())

    def record_inputs(self, frame: StereoFrame, odometry: Sequence[Odometry]) -> None:
        with self._lock:  # keep them, nothing else (publish takes them)
            self._frames.append(frame)
            self._odometry.extend(odometry)

    def publish(self, report: StepReport) -> None:
        res = report.result
        with self._lock:
            odometry = list(self._odometry)
            self._odometry.clear()
            frame = None
            while self._frames and self._frames[0].t_ns <= res.t_ns:
                f = self._frames.popleft()
                if f.t_ns == res.t_ns:
                    frame = f
        s = self.scene
        items: list[Item] = []
        for o in odometry:
            items += s.odometry(o, self._counts["odometry"])
            self._counts["odometry"] += 1
        if frame is not None:
            images = self._wanted("left") or self._wanted("right")  # PNG encoding only for a viewer
            items += s.frame(frame, self._counts["frames"], images=images)
            self._counts["frames"] += 1
        items += s.pose(res.pose, self._counts["poses"])
        self._counts["poses"] += 1
        if res.observations is not None:
            items += s.features(res.observations)
        if report.landmarks is not None and (self._wanted("map") or self._wanted("map_covariance")):
            items += s.map(res.t_ns, report.landmarks)
        for key, t_ns, msg, _seq in items:
            ch = self._channels[key]
            if ch.has_sinks():
                ch.log(payload(msg), log_time=s.wall_ns(t_ns))
                self._counts["sent"] += 1

    def stats(self) -> dict[str, Any]:
        return {"port": self.port, **self._counts, "clients": dict(self._front.counts)}

    def close(self) -> None:
        self._front.close()
        self._server.stop()
        for ch in self._channels.values():
            ch.close()
