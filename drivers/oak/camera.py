"""``oak://[device-id]``: the OAK-D stereo pair through depthai v3 (docs/interfaces.md §2).

Pipeline: two mono ``Camera`` nodes (CAM_B left, CAM_C right, GRAY8 at ``width``×``height`` and
``fps``; default 640×400 @ 30) -> ``Sync`` (threshold well under half a frame period: default
min(5 ms, 15 % of the period)) -> a small non-blocking host queue (the host never stalls the
device). Optionally the images go through ``StereoDepth`` and its ``rectifiedLeft/Right``
outputs (``rectify="device"``); by default they are rectified on the host from the factory
calibration (``rectify="host"``), or from the user's calibration file when one is given
(``calibration=``, the config's ``camera.calibration``: :func:`session_rig`). The device
rectifies with its EEPROM only, so ``rectify=device`` and ``rectify=none`` refuse a calibration
file, as does one made for another image size (:func:`check_oak_url`).

On the host every ``MessageGroup`` passes a :class:`PairGate`: a group whose interval exceeds the
threshold is dropped and counted (never "fixed"), and gaps in the left sequence numbers are
counted. Stamps are the middle of the exposure, ``getTimestamp(CameraExposureOffset.MIDDLE)``,
on ``dai.Clock`` = the host monotonic clock, converted exactly to integer nanoseconds.

Robustness: ``dai.Device.getAllAvailableDevices()`` is checked before any pipeline is built (a
``dai.Pipeline()`` without a device blocks ~11 s before failing). An X_LINK error (unplug, bad
cable) closes the pipeline, backs off and reopens it inside :meth:`OakCamera.frames`; meanwhile
``stats()["degraded"]`` is True. The daemon never restarts for it.

The frame-pairing code (:func:`make_sync`, :class:`PairGate`, :func:`group_to_frame`) is shared
with host-only pipelines (``dai.Pipeline(False)``), which is how the tests exercise it with the
real depthai library and no device. This is the only module (with ``drivers.oak``) that imports
depthai.
"""

from __future__ import annotations

import contextlib
import logging
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from datetime import timedelta
from typing import Any, Protocol
from urllib.parse import parse_qsl, urlsplit

import numpy as np

from drivers._rectify import Rectifier, StereoCalibration, check_calibration_size, user_rectifier
from drivers.base import Driver
from robotd.core.errors import CalibrationError, DriverError
from robotd.core.msgs import StereoFrame
from robotd.core.stereo import RectifiedStereo

logger = logging.getLogger(__name__)

LEFT, RIGHT = "left", "right"


def timedelta_ns(td: timedelta) -> int:
    """Exact integer nanoseconds of a ``timedelta`` (no float rounding; µs resolution)."""
    return (td.days * 86_400 + td.seconds) * 1_000_000_000 + td.microseconds * 1_000


# --------------------------------------------------------------------------------------------
# Options


@dataclass(frozen=True, slots=True)
class OakOptions:
    """Driver options (keyword arguments of :func:`open_oak_camera` or URL query keys)."""

    width: int = 640
    height: int = 400
    fps: float = 30.0
    sync_threshold_ms: float | None = None  # None: min(5 ms, 0.15 × frame period)
    sync_attempts: int = 0  # 0: Sync emits every filled group, so the host sees and counts mismatches
    queue_size: int = 4
    rectify: str = "host"  # "host" (factory calibration, OpenCV maps), "device" (StereoDepth), "none"
    alpha: float = 0.0  # host rectification free scaling (0: valid pixels only)
    reconnect_backoff_s: float = 0.5
    reconnect_backoff_max_s: float = 8.0
    wait_for_device: bool = False  # True: __enter__ succeeds without a device and frames() keeps trying

    @property
    def threshold_ns(self) -> int:
        if self.sync_threshold_ms is not None:
            return round(self.sync_threshold_ms * 1e6)
        return int(min(5e6, 0.15 * 1e9 / self.fps))

    @staticmethod
    def parse(url: str, options: dict[str, Any]) -> OakOptions:
        q = dict(parse_qsl(urlsplit(url).query))
        merged: dict[str, Any] = {**q, **options}
        known = set(OakOptions.__dataclass_fields__)
        extra = sorted(set(merged) - known)
        if extra:
            raise DriverError(f"{url!r}: unknown option(s) {extra}; known: {sorted(known)}")
        kw: dict[str, Any] = {}
        for name, value in merged.items():
            default: Any = OakOptions.__dataclass_fields__[name].default
            try:
                if name == "wait_for_device":
                    kw[name] = value if isinstance(value, bool) else str(value).lower() in ("1", "true", "yes", "on")
                elif name == "rectify":
                    kw[name] = str(value)
                elif name == "sync_threshold_ms":
                    kw[name] = None if value in (None, "") else float(value)
                else:
                    kw[name] = type(default)(value)
            except (TypeError, ValueError):
                raise DriverError(f"{url!r}: option {name}: expected {type(default).__name__}, got {value!r}") from None
        opts = OakOptions(**kw)
        if opts.rectify not in ("host", "device", "none"):
            raise DriverError(f"{url!r}: option rectify: expected host, device or none, got {opts.rectify!r}")
        if not (opts.width > 0 and opts.height > 0 and 0 < opts.fps <= 120 and opts.queue_size >= 1):
            raise DriverError(f"{url!r}: expected positive size, 0 < fps <= 120, queue_size >= 1, got {opts}")
        if not 0 < opts.threshold_ns < 0.5e9 / opts.fps:
            raise DriverError(
                f"{url!r}: sync threshold {opts.threshold_ns / 1e6:.3f} ms must be in (0, half the frame period "
                f"{500 / opts.fps:.2f} ms)"
            )
        return opts


# --------------------------------------------------------------------------------------------
# Pairing (pure logic + the shared Sync construction)


class PairGate:
    """Accept or drop synchronised groups; count mismatches and sequence gaps.

    ``check`` is called for every group the host receives, in order. Sequence accounting uses the
    left stream: a jump of n > 1 adds n - 1 missing frames (whether the device, the Sync node or
    a full queue lost them); a non-increasing number counts as a reset (device restart).
    """

    def __init__(self, threshold_ns: int) -> None:
        self.threshold_ns = int(threshold_ns)
        self.groups = 0
        self.pairs = 0
        self.mismatched = 0
        self.seq_missing = 0
        self.seq_gap_events = 0
        self.seq_resets = 0
        self.non_monotonic = 0
        self.max_interval_ns = 0
        self._last_seq: int | None = None
        self._last_t_ns: int | None = None

    def check(self, t_left_ns: int, t_right_ns: int, seq_left: int, interval_ns: int = 0) -> bool:
        self.groups += 1
        if self._last_seq is not None:
            d = seq_left - self._last_seq
            if d > 1:
                self.seq_missing += d - 1
                self.seq_gap_events += 1
            elif d <= 0:
                self.seq_resets += 1
        self._last_seq = seq_left
        interval = max(int(interval_ns), abs(t_left_ns - t_right_ns))
        if interval > self.threshold_ns:
            self.mismatched += 1
            logger.debug("pair seq %d dropped: interval %.3f ms > %.3f ms", seq_left, interval / 1e6,
                         self.threshold_ns / 1e6)  # fmt: skip
            return False
        if self._last_t_ns is not None and t_left_ns <= self._last_t_ns:
            self.non_monotonic += 1
            return False
        self._last_t_ns = t_left_ns
        self.max_interval_ns = max(self.max_interval_ns, interval)
        self.pairs += 1
        return True

    def counts(self) -> dict[str, int]:
        return {
            "groups": self.groups,
            "pairs": self.pairs,
            "mismatched": self.mismatched,
            "seq_missing": self.seq_missing,
            "seq_gap_events": self.seq_gap_events,
            "seq_resets": self.seq_resets,
            "non_monotonic": self.non_monotonic,
            "max_interval_us": self.max_interval_ns // 1000,
        }


def make_sync(pipeline: Any, opts: OakOptions, run_on_host: bool) -> tuple[Any, Any]:
    """Create the Sync node (inputs ``"left"``/``"right"``) and its non-blocking host queue."""
    import depthai as dai

    sync = pipeline.create(dai.node.Sync)
    sync.setSyncThreshold(timedelta(microseconds=opts.threshold_ns / 1000))
    sync.setSyncAttempts(int(opts.sync_attempts))
    if run_on_host:
        sync.setRunOnHost(True)
    # non-blocking: a slow host drops the oldest groups (seen as sequence gaps) instead of stalling the device
    q = sync.out.createOutputQueue(maxSize=int(opts.queue_size), blocking=False)
    return sync, q


def group_to_frame(group: Any, gate: PairGate, rectifier: Any | None) -> StereoFrame | None:
    """A ``dai.MessageGroup`` with ``left``/``right`` ImgFrames -> StereoFrame, or None if dropped."""
    import depthai as dai

    left, right = group[LEFT], group[RIGHT]
    mid = dai.CameraExposureOffset.MIDDLE
    t_l = timedelta_ns(left.getTimestamp(mid))
    t_r = timedelta_ns(right.getTimestamp(mid))
    if not gate.check(t_l, t_r, int(left.getSequenceNum()), int(group.getIntervalNs())):
        return None
    img_l, img_r = left.getCvFrame(), right.getCvFrame()
    if img_l.ndim == 3:  # a colour or planar type slipped through: the front end wants grey
        import cv2

        img_l, img_r = cv2.cvtColor(img_l, cv2.COLOR_BGR2GRAY), cv2.cvtColor(img_r, cv2.COLOR_BGR2GRAY)
    rectified = rectifier is not None
    if rectifier is not None:
        img_l, img_r = rectifier.rectify(img_l, img_r)
    return StereoFrame(t_l, int(left.getSequenceNum()), np.ascontiguousarray(img_l), np.ascontiguousarray(img_r),
                       rectified=rectified, exposure_ns=exposure_ns(left))  # fmt: skip


def exposure_ns(img: Any) -> int:
    """The exposure an ImgFrame reports (``getExposureTime()``, a timedelta), in nanoseconds; 0
    when it reports none (or nonsense)."""
    try:
        ns = timedelta_ns(img.getExposureTime())
    except (AttributeError, TypeError, ValueError):
        return 0
    return ns if 0 < ns < 10_000_000_000 else 0


# --------------------------------------------------------------------------------------------
# Factory calibration (to be replaced by drivers/oak/calibration.py when it lands)


def calibration_from_handler(handler: Any, size: tuple[int, int]) -> StereoCalibration:
    """``dai.CalibrationHandler`` -> StereoCalibration of CAM_B (left) / CAM_C (right) at ``size``, metres.

    Intrinsics are requested for the output size (docs/interfaces.md §2.3: otherwise fx is for
    1280×800); extrinsics come in centimetres and are converted here, once.
    """
    import depthai as dai

    L, R = dai.CameraBoardSocket.CAM_B, dai.CameraBoardSocket.CAM_C
    w, h = size
    try:
        K_l = np.array(handler.getCameraIntrinsics(L, w, h), dtype=float)
        K_r = np.array(handler.getCameraIntrinsics(R, w, h), dtype=float)
        D_l = np.array(handler.getDistortionCoefficients(L), dtype=float)
        D_r = np.array(handler.getDistortionCoefficients(R), dtype=float)
        T_rl = np.array(handler.getCameraExtrinsics(L, R), dtype=float)  # x_right = T x_left, translation in cm
    except RuntimeError as exc:
        raise CalibrationError(f"OAK factory calibration lacks CAM_B/CAM_C data: {exc}") from None
    return StereoCalibration(
        K_left=K_l,
        D_left=D_l,
        K_right=K_r,
        D_right=D_r,
        R=T_rl[:3, :3],
        T=T_rl[:3, 3] / 100.0,  # cm -> m
        image_size=(w, h),
        distortion_model="rational",
        source="oak factory calibration",
    )


def session_rig(
    handler: Any, opts: OakOptions, user: Rectifier | None
) -> tuple[Rectifier | None, RectifiedStereo | None, Any]:
    """What a device session rectifies with: (the host rectifier, None unless ``rectify=host``; the
    rectified rig, None for ``rectify=none``; what a recording keeps as the raw calibration).

    ``user`` is the rectifier of the user's calibration file (``camera.calibration``), built once by
    :class:`OakCamera` and allowed only with ``rectify=host`` (:func:`check_oak_url`); without one,
    the factory calibration in the device's EEPROM (``handler``, a ``dai.CalibrationHandler``: the
    device's, or one read from an EEPROM JSON) at the streamed size, and its JSON dump.
    """
    if user is not None:
        return user, user.model, user.calib
    try:
        raw: Any = handler.eepromToJson()
    except RuntimeError:
        raw = None
    calib = _load_calibration(handler, (opts.width, opts.height))
    if opts.rectify == "none":
        return None, None, raw
    rectifier = Rectifier(calib, alpha=opts.alpha)
    # rectify=device: the device's rectified geometry is assumed equal to OpenCV's from the same
    # calibration; verify once with a target at known range (docs/math.md §2.1)
    return (rectifier if opts.rectify == "host" else None), rectifier.model, raw


def _load_calibration(handler: Any, size: tuple[int, int]) -> StereoCalibration:
    """Prefer the calibration module of ``drivers.oak`` when it provides a converter; else ours."""
    try:
        from drivers.oak import calibration as oak_cal  # type: ignore[attr-defined]

        fn = getattr(oak_cal, "stereo_calibration_from_handler", None)
        if fn is not None:
            return fn(handler, size)  # type: ignore[no-any-return]
    except ImportError:
        pass
    return calibration_from_handler(handler, size)


# --------------------------------------------------------------------------------------------
# Sessions: one opened pipeline. The device session is the real one; tests supply host-only ones.


class PipelineSession(Protocol):
    queue: Any  # dai.MessageQueue of MessageGroups
    rectifier: Any | None  # host rectifier (None: images already rectified or not rectified)
    model: RectifiedStereo | None
    rectified: bool
    raw_calibration: Any  # the EEPROM JSON dump, the user's StereoCalibration, or None

    def is_running(self) -> bool: ...
    def close(self) -> None: ...


def find_device(device_id: str) -> Any:
    """The DeviceInfo for ``device_id`` ('' = first), checked without building a pipeline."""
    import depthai as dai

    devices = dai.Device.getAllAvailableDevices()
    if not devices:
        raise DriverError(
            "no OAK device found (check the USB cable or PoE link and the udev rule "
            "systemd/60-robotd-oak.rules, README 'On the rover'; `robotd doctor` checks both)"
        )
    if not device_id:
        return devices[0]
    for d in devices:
        if device_id in (d.getDeviceId(), d.name):
            return d
    ids = [d.getDeviceId() for d in devices]
    raise DriverError(f"OAK device {device_id!r} not found; available: {ids}")


class DeviceSession:
    """A running device pipeline: cameras -> [StereoDepth] -> Sync -> host queue. ``user``: the
    rectifier of the user's calibration file (None: the EEPROM's calibration; :func:`session_rig`)."""

    def __init__(self, opts: OakOptions, device_id: str, user: Rectifier | None = None) -> None:
        import depthai as dai

        info = find_device(device_id)
        self._stack = contextlib.ExitStack()
        try:
            device = dai.Device(info)
            self._stack.callback(device.close)
            pipeline = self._stack.enter_context(dai.Pipeline(device))
            self.pipeline = pipeline
            size = (opts.width, opts.height)
            self.rectifier: Any | None
            self.model: RectifiedStereo | None
            self.rectifier, self.model, self.raw_calibration = session_rig(device.readCalibration(), opts, user)
            sync, self.queue = make_sync(pipeline, opts, run_on_host=False)
            outs = {}
            for name, board in ((LEFT, dai.CameraBoardSocket.CAM_B), (RIGHT, dai.CameraBoardSocket.CAM_C)):
                cam = pipeline.create(dai.node.Camera).build(board, sensorFps=float(opts.fps))
                outs[name] = cam.requestOutput(size, dai.ImgFrame.Type.GRAY8, fps=float(opts.fps))
            self.rectified = opts.rectify != "none"
            if opts.rectify == "device":
                stereo = pipeline.create(dai.node.StereoDepth)
                stereo.setRectification(True)
                outs[LEFT].link(stereo.left)
                outs[RIGHT].link(stereo.right)
                stereo.rectifiedLeft.link(sync.inputs[LEFT])
                stereo.rectifiedRight.link(sync.inputs[RIGHT])
            else:
                outs[LEFT].link(sync.inputs[LEFT])
                outs[RIGHT].link(sync.inputs[RIGHT])
            pipeline.start()
        except BaseException:
            self._stack.close()
            raise
        logger.info("OAK %s streaming %dx%d @ %.1f fps, rectify=%s, model %s", info.getDeviceId(), opts.width,
                    opts.height, opts.fps, opts.rectify, self.model)  # fmt: skip

    def is_running(self) -> bool:
        return bool(self.pipeline.isRunning())

    def close(self) -> None:
        with contextlib.suppress(RuntimeError):
            self.pipeline.stop()
        self._stack.close()


SessionFactory = Callable[[OakOptions], PipelineSession]


# --------------------------------------------------------------------------------------------
# The driver


def _is_link_error(exc: BaseException) -> bool:
    import depthai as dai

    link_types = tuple(
        t for t in (getattr(dai, "XLinkError", None), getattr(dai.MessageQueue, "QueueException", None)) if t
    )
    return isinstance(exc, link_types) or "X_LINK" in str(exc) or "Communication exception" in str(exc)


def check_oak_url(url: str, calibration: StereoCalibration | None = None, **options: Any) -> OakOptions:
    """``oak://[device-id]?options`` -> its options; DriverError for another scheme or a bad option,
    CalibrationError for a ``calibration`` (the user's file) these options cannot use: the device
    rectifies with its own EEPROM (``rectify=device``) or not at all (``rectify=none``), and the
    file must be for the streamed size. Opens no device (the config check at start-up calls it)."""
    if urlsplit(url).scheme.lower() != "oak":
        raise DriverError(f"{url!r}: expected oak://[device-id]")
    opts = OakOptions.parse(url, options)
    if calibration is not None:
        if opts.rectify != "host":
            how = (
                "the device rectifies from its EEPROM calibration" if opts.rectify == "device" else "nothing rectifies"
            )
            raise CalibrationError(
                f"{url!r}: a calibration file is used to rectify on the host (rectify=host, the default); "
                f"with rectify={opts.rectify} {how}"
            )
        w, h = calibration.image_size
        check_calibration_size(
            url,
            calibration,
            (opts.width, opts.height),
            f"set ?width={w}&height={h} or calibrate at {opts.width}x{opts.height}",
        )
    return opts


class OakCamera(Driver):
    """The ``oak://`` StereoCamera. ``session_factory`` replaces the device (tests, benchmarks)."""

    host_clock = True  # dai.Clock stamps: the host's monotonic clock

    def __init__(
        self,
        url: str,
        session_factory: SessionFactory | None = None,
        calibration: StereoCalibration | None = None,
        **options: Any,
    ) -> None:
        self.url = url
        parts = urlsplit(url)
        self.opts = check_oak_url(url, calibration, **options)
        # the user's calibration file (camera.calibration): its rectifier is built here, once, so a
        # rig it cannot rectify fails the open instead of every reconnection (None: the EEPROM's)
        self.calibration_rectifier = None if calibration is None else user_rectifier(calibration, self.opts.alpha)
        self.device_id = (parts.netloc + parts.path).strip("/")
        self._factory: SessionFactory = session_factory or (
            lambda o: DeviceSession(o, self.device_id, self.calibration_rectifier)
        )
        self.gate = PairGate(self.opts.threshold_ns)
        self._session: PipelineSession | None = None
        self._closed = threading.Event()
        self._model: RectifiedStereo | None = None
        self.raw_calibration: Any = None
        self._stats: dict[str, Any] = {"frames": 0, "reconnects": 0, "link_errors": 0, "open_failures": 0,
                                       "timeouts": 0, "degraded": False, "last_error": ""}  # fmt: skip

    @property
    def fps(self) -> float:
        """The configured frame rate [Hz] (``?fps=``)."""
        return float(self.opts.fps)

    # lifecycle --------------------------------------------------------------------------------
    def open(self) -> None:
        try:
            self._start()
        except (DriverError, CalibrationError, RuntimeError) as exc:
            if not self.opts.wait_for_device:
                raise DriverError(f"{self.url!r}: {exc}") from None
            self._mark_degraded(exc)
            logger.warning("%s: not available yet (%s); will keep trying", self.url, exc)

    def _start(self) -> None:
        s = self._factory(self.opts)
        self._session = s
        self.raw_calibration = s.raw_calibration
        if s.model is not None:
            self._model = s.model
        self._stats["degraded"] = False

    def _stop_session(self) -> None:
        s, self._session = self._session, None
        if s is not None:
            try:
                s.close()
            except RuntimeError as exc:  # a dead link may fail to close cleanly; it is gone either way
                logger.debug("%s: closing pipeline: %s", self.url, exc)

    def close(self) -> None:
        self._closed.set()
        self._stop_session()

    def _mark_degraded(self, exc: BaseException) -> None:
        self._stats["degraded"] = True
        self._stats["last_error"] = str(exc)[:200]

    # StereoCamera protocol --------------------------------------------------------------------
    def rectified_model(self) -> RectifiedStereo:
        if self._model is None:
            raise DriverError(f"{self.url!r}: no rectified model (rectify=none, or the device never opened)")
        return self._model

    def stats(self) -> dict[str, Any]:
        return {**self._stats, **self.gate.counts()}

    def frames(self, timeout_s: float = 1.0) -> Iterator[StereoFrame]:
        """Yield synchronised, rectified pairs until :meth:`close`; reconnect on link loss."""
        backoff = self.opts.reconnect_backoff_s
        while not self._closed.is_set():
            if self._session is None:
                if not self._reopen(backoff):
                    backoff = min(2.0 * backoff, self.opts.reconnect_backoff_max_s)
                    continue
                backoff = self.opts.reconnect_backoff_s
            s = self._session
            assert s is not None
            try:
                group = s.queue.get(timedelta(seconds=timeout_s))
                if group is None:
                    self._stats["timeouts"] += 1
                    if not s.is_running():
                        raise RuntimeError("pipeline stopped (X_LINK: device lost)")
                    continue
                frame = group_to_frame(group, self.gate, s.rectifier)
            except Exception as exc:
                if self._closed.is_set():
                    return
                if not _is_link_error(exc):
                    raise
                self._stats["link_errors"] += 1
                self._mark_degraded(exc)
                logger.warning("%s: link lost (%s); reopening in %.1f s", self.url, exc, backoff)
                self._stop_session()
                self._sleep(backoff)
                continue
            if frame is not None:
                self._stats["frames"] += 1
                yield frame

    def _reopen(self, backoff: float) -> bool:
        try:
            self._start()
        except (DriverError, CalibrationError, RuntimeError) as exc:
            self._stats["open_failures"] += 1
            self._mark_degraded(exc)
            logger.info("%s: reopen failed (%s); retry in %.1f s", self.url, exc, backoff)
            self._sleep(backoff)
            return False
        self._stats["reconnects"] += 1
        logger.info("%s: reconnected", self.url)
        return True

    def _sleep(self, seconds: float) -> None:
        self._closed.wait(seconds)  # returns early on close()


def open_oak_camera(url: str, **options: Any) -> OakCamera:
    """``oak://[device-id][?width=640&height=400&fps=30&rectify=host&sync_threshold_ms=…]``."""
    return OakCamera(url, **options)
