"""MCAP record and replay of a robotd session: the inputs (stereo frames, odometry, calibration) and
the outputs (published poses), in a file Foxglove opens.

Layout (every channel is JSON-encoded with a JSON Schema; docs/recording.md has the details):

=========================== ========================== ===============================================
topic                       schema                     content
=========================== ========================== ===============================================
``/camera/left/image``      ``foxglove.CompressedImage`` left rectified image, PNG (lossless) — or
``/camera/right/image``     (or ``foxglove.RawImage``)  ``mono8`` RawImage with ``image_format="raw"``
``/camera/left/calibration`` ``foxglove.CameraCalibration`` rectified pinhole model, once per second
``/camera/right/calibration``                            (``P[3] = -f b`` for the right camera)
``/robotd/frame``           ``robotd.FrameInfo``        t_ns, seq, rectified flag, optional truth pose
``/robotd/odometry``        ``robotd.Odometry``         every field of :class:`robotd.msgs.Odometry`
``/robotd/pose``            ``foxglove.PoseInFrame``    the published pose, frame ``world`` (LOCAL_FRD)
``/robotd/pose_estimate``   ``robotd.PoseEstimate``     every field of :class:`robotd.msgs.PoseEstimate`
``/robotd/calibration``     ``robotd.Calibration``      the calibration JSON (also in metadata)
=========================== ========================== ===============================================

MCAP metadata records ``robotd.session`` (format version, caller's ``meta``) and
``robotd.calibration`` (the calibration JSON) make a recording self-describing.

Timestamps: ``log_time`` and ``publish_time`` are the message's own capture time ``t_ns`` on the
recording host's monotonic clock; foxglove ``timestamp`` fields carry the same instant as
``{sec, nsec}``. Replay (:class:`SessionReader`) returns messages in **file order**, i.e. the
order the recorder wrote them, so a replay sees the same frames, in the same order, with the same
stamps, every time.

Writing is atomic: data go to ``PATH.tmp`` and are renamed over ``PATH`` only after the MCAP
summary is written and fsynced. A write error (disk full, I/O error) raises
:class:`robotd.errors.PersistenceError`, discards the temporary file and leaves whatever was
already finalised at ``PATH`` untouched.
"""

from __future__ import annotations

import base64
import contextlib
import json
import logging
import os
import queue
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from pathlib import Path
from typing import IO, Any

import cv2
import numpy as np

from robotd.errors import InputError, PersistenceError
from robotd.msgs import Odometry, PoseEstimate, StereoFrame
from robotd.stereo import RectifiedStereo

logger = logging.getLogger(__name__)

FORMAT_VERSION = 1
PROFILE = ""  # no ROS profile: plain JSON channels
TOPIC_IMAGE = {"left": "/camera/left/image", "right": "/camera/right/image"}
TOPIC_CAMERA_CAL = {"left": "/camera/left/calibration", "right": "/camera/right/calibration"}
TOPIC_FRAME = "/robotd/frame"
TOPIC_ODOMETRY = "/robotd/odometry"
TOPIC_POSE = "/robotd/pose"
TOPIC_POSE_ESTIMATE = "/robotd/pose_estimate"
TOPIC_CALIBRATION = "/robotd/calibration"
FRAME_ID = {"left": "camera_left", "right": "camera_right"}
WORLD_FRAME_ID = "world"

# --------------------------------------------------------------------------------------------
# JSON Schemas. The foxglove ones follow the public definitions of the well-known schemas
# (field names and types are the file format Foxglove decodes); bytes fields are base64 strings
# in the JSON encoding.

_TIME = {
    "type": "object",
    "title": "time",
    "properties": {"sec": {"type": "integer", "minimum": 0}, "nsec": {"type": "integer", "minimum": 0}},
}
_VEC3 = {
    "type": "object",
    "properties": {k: {"type": "number"} for k in ("x", "y", "z")},
}
_QUAT = {
    "type": "object",
    "properties": {k: {"type": "number"} for k in ("x", "y", "z", "w")},
}
_NUMBERS = {"type": "array", "items": {"type": "number"}}


def _schema(title: str, props: dict[str, Any]) -> dict[str, Any]:
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": title, "type": "object",
            "properties": props}  # fmt: skip


SCHEMAS: dict[str, dict[str, Any]] = {
    "foxglove.CompressedImage": _schema(
        "foxglove.CompressedImage",
        {
            "timestamp": _TIME,
            "frame_id": {"type": "string"},
            "data": {"type": "string", "contentEncoding": "base64"},
            "format": {"type": "string"},
        },
    ),
    "foxglove.RawImage": _schema(
        "foxglove.RawImage",
        {
            "timestamp": _TIME,
            "frame_id": {"type": "string"},
            "width": {"type": "integer", "minimum": 0},
            "height": {"type": "integer", "minimum": 0},
            "encoding": {"type": "string"},
            "step": {"type": "integer", "minimum": 0},
            "data": {"type": "string", "contentEncoding": "base64"},
        },
    ),
    "foxglove.CameraCalibration": _schema(
        "foxglove.CameraCalibration",
        {
            "timestamp": _TIME,
            "frame_id": {"type": "string"},
            "width": {"type": "integer", "minimum": 0},
            "height": {"type": "integer", "minimum": 0},
            "distortion_model": {"type": "string"},
            "D": _NUMBERS,
            "K": {**_NUMBERS, "minItems": 9, "maxItems": 9},
            "R": {**_NUMBERS, "minItems": 9, "maxItems": 9},
            "P": {**_NUMBERS, "minItems": 12, "maxItems": 12},
        },
    ),
    "foxglove.PoseInFrame": _schema(
        "foxglove.PoseInFrame",
        {
            "timestamp": _TIME,
            "frame_id": {"type": "string"},
            "pose": {"type": "object", "properties": {"position": _VEC3, "orientation": _QUAT}},
        },
    ),
    "robotd.FrameInfo": _schema(
        "robotd.FrameInfo",
        {
            "t_ns": {"type": "integer"},
            "seq": {"type": "integer"},
            "rectified": {"type": "boolean"},
            "truth_T_world_robot": {"type": ["array", "null"], "items": _NUMBERS},
        },
    ),
    "robotd.Odometry": _schema(
        "robotd.Odometry",
        {
            "t_ns": {"type": "integer"},
            "vel_R_mps": {**_NUMBERS, "minItems": 3, "maxItems": 3},
            "rate_R_radps": {**_NUMBERS, "minItems": 3, "maxItems": 3},
            "source": {"type": "string"},
            "cov": {"type": ["array", "null"], "items": _NUMBERS},
        },
    ),
    "robotd.PoseEstimate": _schema(
        "robotd.PoseEstimate",
        {
            "t_ns": {"type": "integer"},
            "xyz_W_m": {**_NUMBERS, "minItems": 3, "maxItems": 3},
            "rpy_rad": {**_NUMBERS, "minItems": 3, "maxItems": 3},
            "cov": {"type": "array", "items": _NUMBERS},
            "neff": {"type": ["number", "null"]},
            "n_particles": {"type": "integer"},
        },
    ),
    "robotd.Calibration": _schema("robotd.Calibration", {"rectified": {"type": "object"}, "raw": {}}),
}


# --------------------------------------------------------------------------------------------
# Encoding helpers (pure)


def _stamp(t_ns: int) -> dict[str, int]:
    # foxglove time is unsigned {sec, nsec}; monotonic stamps are non-negative
    sec, nsec = divmod(int(t_ns), 1_000_000_000)
    return {"sec": sec, "nsec": nsec}


def _dumps(obj: Any) -> bytes:
    # allow_nan=False: Foxglove's JSON parser rejects NaN; callers map NaN to null first
    return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()


def _floats(a: np.ndarray) -> list[Any]:
    return np.asarray(a, dtype=float).tolist()  # type: ignore[no-any-return]


def calibration_to_json(rectified: RectifiedStereo, raw: Any = None) -> dict[str, Any]:
    """The calibration record: the rectified rig and, optionally, the raw calibration it came from.

    ``raw`` may be a ``StereoCalibration``-like object (K_left, D_left, K_right, D_right, R, T in
    metres, image_size), a JSON-able mapping (e.g. the OAK EEPROM JSON), or None.
    """
    r = {k: getattr(rectified, k) for k in ("f_px", "px", "py", "baseline_m", "width", "height")}
    raw_json: Any = None
    if raw is not None and hasattr(raw, "K_left"):
        raw_json = {k: _floats(getattr(raw, k)) for k in ("K_left", "D_left", "K_right", "D_right", "R", "T")}
        raw_json["image_size"] = list(raw.image_size)
        raw_json["distortion_model"] = str(getattr(raw, "distortion_model", ""))
        raw_json["source"] = str(getattr(raw, "source", ""))
        raw_json["units"] = "T in metres"
    elif raw is not None:
        raw_json = json.loads(json.dumps(raw))  # must be JSON-able; fails early, not at close
    return {"rectified": r, "raw": raw_json}


def rectified_from_json(d: Mapping[str, Any]) -> RectifiedStereo:
    r = d["rectified"]
    return RectifiedStereo(
        float(r["f_px"]), float(r["px"]), float(r["py"]), float(r["baseline_m"]), int(r["width"]), int(r["height"])
    )


def camera_calibration_msg(model: RectifiedStereo, side: str, t_ns: int) -> dict[str, Any]:
    """foxglove.CameraCalibration of one rectified camera (ROS CameraInfo conventions for P)."""
    f, px, py = model.f_px, model.px, model.py
    tx = -f * model.baseline_m if side == "right" else 0.0
    return {
        "timestamp": _stamp(t_ns),
        "frame_id": FRAME_ID[side],
        "width": model.width,
        "height": model.height,
        "distortion_model": "plumb_bob",
        "D": [0.0] * 5,  # rectified images carry no distortion
        "K": [f, 0.0, px, 0.0, f, py, 0.0, 0.0, 1.0],
        "R": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        "P": [f, 0.0, px, tx, 0.0, f, py, 0.0, 0.0, 0.0, 1.0, 0.0],
    }


def odometry_to_json(o: Odometry) -> dict[str, Any]:
    return {"t_ns": int(o.t_ns), "vel_R_mps": _floats(o.vel_R_mps), "rate_R_radps": _floats(o.rate_R_radps),
            "source": o.source, "cov": None if o.cov is None else _floats(o.cov)}  # fmt: skip


def odometry_from_json(d: Mapping[str, Any]) -> Odometry:
    cov = d.get("cov")  # absent in recordings made before samples carried their noise
    return Odometry(int(d["t_ns"]), np.array(d["vel_R_mps"], float), np.array(d["rate_R_radps"], float), d["source"],
                    None if cov is None else np.array(cov, float).reshape(6, 6))  # fmt: skip


def pose_estimate_msg(p: PoseEstimate) -> dict[str, Any]:
    neff = float(p.neff)
    return {
        "t_ns": int(p.t_ns),
        "xyz_W_m": _floats(p.xyz_W_m),
        "rpy_rad": _floats(p.rpy_rad),
        "cov": _floats(p.cov),
        "neff": neff if np.isfinite(neff) else None,  # NaN (EKF) is stored as null
        "n_particles": int(p.n_particles),
    }


def pose_estimate_from_msg(d: Mapping[str, Any]) -> PoseEstimate:
    neff = float("nan") if d.get("neff") is None else float(d["neff"])
    return PoseEstimate(int(d["t_ns"]), np.array(d["xyz_W_m"], float), np.array(d["rpy_rad"], float),
                        np.array(d["cov"], float), neff, int(d["n_particles"]))  # fmt: skip


def pose_in_frame_msg(p: PoseEstimate) -> dict[str, Any]:
    from robotd.geometry import euler_to_quat

    w, x, y, z = (float(v) for v in euler_to_quat(p.rpy_rad))
    px, py, pz = (float(v) for v in p.xyz_W_m)
    return {
        "timestamp": _stamp(p.t_ns),
        "frame_id": WORLD_FRAME_ID,
        "pose": {"position": {"x": px, "y": py, "z": pz}, "orientation": {"x": x, "y": y, "z": z, "w": w}},
    }


def encode_image(img: np.ndarray, image_format: str, png_level: int, side: str, t_ns: int) -> dict[str, Any]:
    """A grey uint8 image (H, W) -> foxglove CompressedImage (PNG, lossless) or RawImage (mono8)."""
    if image_format == "png":
        ok, buf = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, int(png_level)])
        if not ok:
            raise InputError(f"PNG encoding of the {side} image ({img.shape}) failed")
        data = base64.b64encode(buf.tobytes()).decode()
        return {"timestamp": _stamp(t_ns), "frame_id": FRAME_ID[side], "data": data, "format": "png"}
    h, w = img.shape
    data = base64.b64encode(np.ascontiguousarray(img).tobytes()).decode()
    return {"timestamp": _stamp(t_ns), "frame_id": FRAME_ID[side], "width": w, "height": h, "encoding": "mono8",
            "step": w, "data": data}  # fmt: skip


def decode_image(d: Mapping[str, Any]) -> np.ndarray:
    raw = base64.b64decode(d["data"])
    if "format" in d:
        img = cv2.imdecode(np.frombuffer(raw, np.uint8), cv2.IMREAD_UNCHANGED)
        if img is None or img.ndim != 2 or img.dtype != np.uint8:
            raise PersistenceError(f"image ({d.get('format')!r}) does not decode to an 8-bit grey image")
        return img
    if d.get("encoding") != "mono8":
        raise PersistenceError(f"RawImage encoding {d.get('encoding')!r} not supported, expected 'mono8'")
    h, w, step = int(d["height"]), int(d["width"]), int(d["step"])
    if len(raw) != h * step:
        raise PersistenceError(f"RawImage: {len(raw)} bytes for {h} rows of {step}")
    return np.frombuffer(raw, np.uint8).reshape(h, step)[:, :w].copy()


# --------------------------------------------------------------------------------------------
# Writer


class SessionWriter:
    """Write one session to ``path`` (MCAP, atomic finish). Not thread-safe: one writer thread.

    ``calibration``: the rectified rig the frames are in (:class:`RectifiedStereo`); ``meta``:
    JSON-able facts about the session (source URL, config, robotd version, seed...). Options:
    ``raw_calibration`` (StereoCalibration-like or JSON-able, e.g. the OAK EEPROM dump),
    ``image_format`` ``"png"`` (default, lossless, ~2 ms per 640×400 image at level 1) or ``"raw"``,
    ``png_level`` 0–9 (1), ``calibration_period_s`` (1.0: how often the foxglove
    CameraCalibration is repeated so seeking in Foxglove finds one), ``chunk_size`` (bytes).
    """

    def __init__(
        self,
        path: str | Path,
        calibration: RectifiedStereo,
        meta: Mapping[str, Any] | None = None,
        *,
        raw_calibration: Any = None,
        image_format: str = "png",
        png_level: int = 1,
        calibration_period_s: float = 1.0,
        chunk_size: int = 4 * 1024 * 1024,
        opener: Callable[[Path], IO[bytes]] | None = None,
    ) -> None:
        from mcap.writer import CompressionType, Writer

        if image_format not in ("png", "raw"):
            raise InputError(f"image_format: expected 'png' or 'raw', got {image_format!r}")
        if not 0 <= int(png_level) <= 9:
            raise InputError(f"png_level: expected 0..9, got {png_level}")
        self.path = Path(path)
        self.tmp_path = self.path.with_name(self.path.name + ".tmp")
        self.calibration = calibration
        self.image_format = image_format
        self.png_level = int(png_level)
        self.calibration_period_ns = int(calibration_period_s * 1e9)
        self.counts = {"frames": 0, "odometry": 0, "poses": 0, "bytes": 0}
        self._last_cal_ns: int | None = None
        self._closed = False
        self._failed: PersistenceError | None = None
        self._frame_index = 0
        self._seq: dict[int, int] = {}
        self._calib_json = calibration_to_json(calibration, raw_calibration)
        try:
            session_meta = {"format_version": FORMAT_VERSION, "meta": dict(meta or {})}
            meta_json = json.dumps(session_meta, allow_nan=False)
        except (TypeError, ValueError) as exc:
            raise InputError(f"meta: expected JSON-able values, got {exc}") from None
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file: IO[bytes] = opener(self.tmp_path) if opener else open(self.tmp_path, "wb")
            self._writer = Writer(self._file, chunk_size=chunk_size, compression=CompressionType.ZSTD)
            self._writer.start(profile=PROFILE, library=f"robotd-record/{FORMAT_VERSION}")
            self._schema_ids = {
                name: self._writer.register_schema(name, "jsonschema", json.dumps(s).encode())
                for name, s in SCHEMAS.items()
            }
            img_schema = "foxglove.CompressedImage" if image_format == "png" else "foxglove.RawImage"
            ch = self._channel
            self._ch = {
                "left": ch(TOPIC_IMAGE["left"], img_schema),
                "right": ch(TOPIC_IMAGE["right"], img_schema),
                "cal_left": ch(TOPIC_CAMERA_CAL["left"], "foxglove.CameraCalibration"),
                "cal_right": ch(TOPIC_CAMERA_CAL["right"], "foxglove.CameraCalibration"),
                "frame": ch(TOPIC_FRAME, "robotd.FrameInfo"),
                "odometry": ch(TOPIC_ODOMETRY, "robotd.Odometry"),
                "pose": ch(TOPIC_POSE, "foxglove.PoseInFrame"),
                "pose_estimate": ch(TOPIC_POSE_ESTIMATE, "robotd.PoseEstimate"),
                "calibration": ch(TOPIC_CALIBRATION, "robotd.Calibration"),
            }
            self._writer.add_metadata("robotd.session", {"json": meta_json})
            self._writer.add_metadata("robotd.calibration", {"json": json.dumps(self._calib_json)})
        except OSError as exc:
            self._fail(exc, "opening")
        logger.info("recording to %s (via %s), images %s", self.path, self.tmp_path.name, image_format)

    def _channel(self, topic: str, schema: str) -> int:
        return self._writer.register_channel(topic, "json", self._schema_ids[schema])  # type: ignore[no-any-return]

    # -- error handling ----------------------------------------------------------------------
    def _fail(self, exc: BaseException, doing: str) -> None:
        err = PersistenceError(
            f"{self.path}: recording failed while {doing} after {self.counts['frames']} frames: {exc}; "
            f"temporary {self.tmp_path.name} discarded, any previous {self.path.name} left untouched"
        )
        self._failed = err
        self._closed = True
        try:
            self._file.close()
        except (OSError, ValueError, AttributeError):
            pass  # the original error is the one to report
        try:
            self.tmp_path.unlink(missing_ok=True)
        except OSError:
            logger.warning("could not remove %s", self.tmp_path)
        raise err from exc

    def _check_open(self) -> None:
        if self._failed is not None:
            raise PersistenceError(f"{self.path}: writer failed earlier: {self._failed}")
        if self._closed:
            raise PersistenceError(f"{self.path}: writer is closed")

    def _add(self, channel: str, t_ns: int, msg: Mapping[str, Any], seq: int = 0) -> None:
        data = _dumps(msg)
        try:
            self._writer.add_message(self._ch[channel], log_time=int(t_ns), data=data, publish_time=int(t_ns),
                                     sequence=seq)  # fmt: skip
        except (OSError, ValueError) as exc:
            self._fail(exc, f"writing {channel}")
        self.counts["bytes"] += len(data)

    # -- public API --------------------------------------------------------------------------
    def write_frame(self, frame: StereoFrame) -> None:
        """Both images, the frame info and (once per ``calibration_period_s``) the camera calibrations."""
        self._check_open()
        t = int(frame.t_ns)
        if self._last_cal_ns is None:
            self._add("calibration", t, self._calib_json)
        if self._last_cal_ns is None or t - self._last_cal_ns >= self.calibration_period_ns:
            for side in ("left", "right"):
                self._add(f"cal_{side}", t, camera_calibration_msg(self.calibration, side, t))
            self._last_cal_ns = t
        k = self._frame_index
        for side, img in (("left", frame.left), ("right", frame.right)):
            self._add(side, t, encode_image(img, self.image_format, self.png_level, side, t), seq=k)
        truth = None if frame.truth_T_world_robot is None else _floats(frame.truth_T_world_robot)
        info = {"t_ns": t, "seq": int(frame.seq), "rectified": bool(frame.rectified), "truth_T_world_robot": truth}
        self._add("frame", t, info, seq=k)
        self._frame_index += 1
        self.counts["frames"] += 1

    def write_odometry(self, odometry: Odometry) -> None:
        self._check_open()
        self._add("odometry", odometry.t_ns, odometry_to_json(odometry), seq=self.counts["odometry"])
        self.counts["odometry"] += 1

    def write_pose(self, pose: PoseEstimate) -> None:
        """The published pose: foxglove.PoseInFrame (for the 3D panel) and the full robotd.PoseEstimate."""
        self._check_open()
        k = self.counts["poses"]
        self._add("pose", pose.t_ns, pose_in_frame_msg(pose), seq=k)
        self._add("pose_estimate", pose.t_ns, pose_estimate_msg(pose), seq=k)
        self.counts["poses"] += 1

    def close(self) -> None:
        """Write the MCAP summary, fsync, and rename ``PATH.tmp`` to ``PATH``. Idempotent."""
        if self._closed:
            if self._failed is not None:
                raise PersistenceError(f"{self.path}: writer failed earlier: {self._failed}")
            return
        try:
            self._writer.finish()
            self._file.flush()
            os.fsync(self._file.fileno())
            self._file.close()
            os.replace(self.tmp_path, self.path)
            self._fsync_dir()
        except (OSError, ValueError) as exc:
            self._fail(exc, "finishing")
        self._closed = True
        self.counts["bytes"] = self.path.stat().st_size
        logger.info("recording %s closed: %s", self.path, self.counts)

    def discard(self) -> None:
        """Close without publishing: the temporary file is removed and ``PATH`` is left as it was
        (a run that recorded nothing leaves no empty recording behind). Idempotent."""
        if self._closed:
            return
        self._closed = True
        with contextlib.suppress(OSError, ValueError):
            self._file.close()
        try:
            self.tmp_path.unlink(missing_ok=True)
        except OSError as exc:
            logger.warning("could not remove %s: %s", self.tmp_path, exc)

    def _fsync_dir(self) -> None:
        # the rename is durable only once the directory entry is on disk (power loss)
        try:
            fd = os.open(self.path.parent, os.O_RDONLY)
        except OSError:
            return
        try:
            os.fsync(fd)
        except OSError:
            pass
        finally:
            os.close(fd)

    def __enter__(self) -> SessionWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        # finalise what was recorded even when the body raised (e.g. Ctrl-C): a recording of
        # the moments before a failure is the most useful one
        if not self._closed:
            self.close()


# --------------------------------------------------------------------------------------------
# Reader


class SessionReader:
    """Read a recording written by :class:`SessionWriter`; events come back in file order."""

    def __init__(self, path: str | Path) -> None:
        from mcap.exceptions import McapError
        from mcap.reader import make_reader

        self.path = Path(path)
        if not self.path.is_file():
            raise PersistenceError(f"{self.path}: no such recording")
        self._McapError = McapError
        self._make_reader = make_reader
        try:
            with open(self.path, "rb") as f:
                reader = make_reader(f)
                metadata = {m.name: m.metadata for m in reader.iter_metadata()}
        except (McapError, OSError, ValueError) as exc:
            raise PersistenceError(f"{self.path}: not a readable MCAP file: {exc}") from None
        if "robotd.session" not in metadata or "robotd.calibration" not in metadata:
            raise PersistenceError(
                f"{self.path}: an MCAP file, but not a robotd recording (no robotd.session metadata)"
            )
        session = json.loads(metadata["robotd.session"]["json"])
        if int(session.get("format_version", -1)) != FORMAT_VERSION:
            raise PersistenceError(
                f"{self.path}: recording format {session.get('format_version')}, this robotd reads {FORMAT_VERSION}"
            )
        self.meta: dict[str, Any] = session.get("meta", {})
        self.calibration_json: dict[str, Any] = json.loads(metadata["robotd.calibration"]["json"])
        self.calibration = rectified_from_json(self.calibration_json)

    def events(
        self, topics: Iterable[str] = (TOPIC_FRAME, TOPIC_ODOMETRY, TOPIC_POSE_ESTIMATE)
    ) -> Iterator[StereoFrame | Odometry | PoseEstimate]:
        """StereoFrame / Odometry / PoseEstimate in the order they were recorded."""
        wanted = set(topics)
        want_frames = TOPIC_FRAME in wanted
        read = set(wanted) | (set(TOPIC_IMAGE.values()) if want_frames else set())
        pending: dict[int, dict[str, np.ndarray]] = {}
        try:
            with open(self.path, "rb") as f:
                reader = self._make_reader(f)
                for _schema, channel, message in reader.iter_messages(topics=sorted(read), log_time_order=False):
                    topic = channel.topic
                    d = json.loads(message.data)
                    if topic == TOPIC_IMAGE["left"] or topic == TOPIC_IMAGE["right"]:
                        side = "left" if topic == TOPIC_IMAGE["left"] else "right"
                        pending.setdefault(message.sequence, {})[side] = decode_image(d)
                    elif topic == TOPIC_FRAME:
                        imgs = pending.pop(message.sequence, {})
                        if "left" not in imgs or "right" not in imgs:
                            raise PersistenceError(f"{self.path}: frame {d.get('seq')} has no left/right image")
                        truth = d.get("truth_T_world_robot")
                        T = None if truth is None else np.array(truth, float)
                        rect = bool(d["rectified"])
                        yield StereoFrame(int(d["t_ns"]), int(d["seq"]), imgs["left"], imgs["right"], rect, T)
                    elif topic == TOPIC_ODOMETRY:
                        yield odometry_from_json(d)
                    elif topic == TOPIC_POSE_ESTIMATE:
                        yield pose_estimate_from_msg(d)
        except (self._McapError, OSError, ValueError, KeyError) as exc:
            raise PersistenceError(f"{self.path}: corrupt recording: {exc!r}") from None

    def frames(self) -> Iterator[StereoFrame]:
        for e in self.events((TOPIC_FRAME,)):
            assert isinstance(e, StereoFrame)
            yield e

    def odometry(self) -> Iterator[Odometry]:
        for e in self.events((TOPIC_ODOMETRY,)):
            assert isinstance(e, Odometry)
            yield e

    def poses(self) -> Iterator[PoseEstimate]:
        for e in self.events((TOPIC_POSE_ESTIMATE,)):
            assert isinstance(e, PoseEstimate)
            yield e


# --------------------------------------------------------------------------------------------
# Recording loop (used by ``robotd record``)


def record_session(
    camera: Any,
    vehicle: Any | None,
    writer: SessionWriter,
    *,
    duration_s: float = 10.0,
    max_frames: int = 0,
    should_stop: Callable[[], bool] = lambda: False,
    frame_timeout_s: float = 1.0,
) -> dict[str, Any]:
    """Record frames from ``camera`` (a StereoCamera) and odometry from ``vehicle`` into ``writer``.

    Odometry is read on a helper thread into a bounded queue (drop-oldest, counted) and written by
    this thread just before each frame, so the writer stays single-threaded. Stops after
    ``duration_s`` (0: no limit), ``max_frames`` (0: no limit), when the source ends or when
    ``should_stop()`` returns True. Does not close the writer. Returns counts.
    """
    odo_q: queue.Queue[Odometry] = queue.Queue(maxsize=1024)
    stop = threading.Event()
    dropped = 0

    def pump() -> None:
        nonlocal dropped
        assert vehicle is not None
        for o in vehicle.odometry(timeout_s=0.2):
            if stop.is_set():
                return
            while True:
                try:
                    odo_q.put_nowait(o)
                    break
                except queue.Full:
                    try:
                        odo_q.get_nowait()
                        dropped += 1
                    except queue.Empty:
                        pass

    th = threading.Thread(target=pump, name="record-odometry", daemon=True) if vehicle is not None else None
    if th is not None:
        th.start()
    t_end = time.monotonic() + duration_s if duration_s > 0 else float("inf")

    def drain() -> None:
        while True:
            try:
                writer.write_odometry(odo_q.get_nowait())
            except queue.Empty:
                return

    try:
        for frame in camera.frames(timeout_s=frame_timeout_s):
            drain()
            writer.write_frame(frame)
            if should_stop() or time.monotonic() >= t_end or (max_frames and writer.counts["frames"] >= max_frames):
                break
    finally:
        stop.set()
        if th is not None:
            th.join(timeout=1.0)
        drain()
    return {**writer.counts, "odometry_dropped": dropped, "path": str(writer.path)}
