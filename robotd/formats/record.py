"""MCAP record and replay of a robotd session: the inputs (stereo frames, odometry, calibration)
and the outputs (poses, trajectory, landmark map, feature tracks), in a file Foxglove shows whole.

Format version 2 (docs/recording.md has the details). Foxglove's well-known schemas, protobuf
encoded, wherever Foxglove has one; robotd's own JSON channels only for what replay needs bit
for bit and no standard schema holds:

============================== ============================== =============================================
topic                          schema                         content
============================== ============================== =============================================
``/camera/left/image``,        ``foxglove.CompressedImage``   rectified image, PNG bytes (lossless), or a
``/camera/right/image``        (or ``foxglove.RawImage``)     ``mono8`` RawImage
``/camera/left/calibration``,  ``foxglove.CameraCalibration`` rectified pinhole, ``P[3] = -f b`` on the right
``/camera/right/calibration``
``/camera/left/features``      ``foxglove.ImageAnnotations``  the features the filter used and their tracks
``/tf``                        ``foxglove.FrameTransforms``   world → robot (each pose), robot → cameras
``/robotd/pose``               ``foxglove.PoseInFrame``       the published pose in ``world``
``/robotd/trajectory``         ``foxglove.PosesInFrame``      the estimated path so far (once a second)
``/robotd/map``                ``foxglove.PointCloud``        the landmarks in ``world`` (x, y, z, id)
``/robotd/map_covariance``     ``foxglove.SceneUpdate``       their 2σ covariance ellipsoids
``/truth/pose``,               ``foxglove.PoseInFrame``,      the ground truth, when the source has one
``/truth/trajectory``          ``foxglove.PosesInFrame``
``/robotd/odometry``           ``foxglove.Odometry``          the vehicle's samples (t_ns, source in metadata)
``/robotd/frame``              ``robotd.FrameInfo`` (JSON)    t_ns, seq, rectified flag, raw truth pose, exposure
``/robotd/pose_estimate``      ``robotd.PoseEstimate`` (JSON) every field of :class:`robotd.core.msgs.PoseEstimate`
``/robotd/calibration``        ``robotd.Calibration`` (JSON)  the calibration JSON (also in metadata)
============================== ============================== =============================================

Timestamps: ``log_time``, ``publish_time`` and every Foxglove ``timestamp`` are wall-clock
(Unix) nanoseconds of the capture instant, so Foxglove shows the date of the recording; the
capture time on the recording host's monotonic clock stays in robotd's fields (``t_ns``). Replay
(:class:`SessionReader`) returns messages in **file order**, so a replay sees the same frames, in
the same order, with the same stamps, every time.

Crash safety: data go to ``PATH.tmp`` in zstd chunks, and the writer closes the chunk and hands
it to the operating system at least every ``flush_period_s`` (1 s), so a killed recorder leaves a
``PATH.tmp`` that replays up to its last whole chunk. A clean close writes the MCAP summary,
fsyncs and renames ``PATH.tmp`` over ``PATH``. A recorder that finds a ``PATH.tmp`` left by a
killed one keeps it as ``PATH-stem.interrupted-<time>.mcap`` before it starts. A write error
(disk full, I/O error) raises :class:`robotd.core.errors.PersistenceError`, discards the temporary
file and leaves whatever was already finalised at ``PATH`` untouched.

Reading (:class:`SessionReader`, on :mod:`robotd.formats.mcap_scan`) is bounded and tolerant: every size
is checked before anything is allocated or decoded (records, chunks, messages, image headers
against the calibration's size), and a damaged or truncated file is read up to the damage, which
``stopped`` names (byte offset, record, reason). Format version 1 (robotd's first: JSON channels,
base64 PNG images, host-monotonic log times) is read as before.
"""

from __future__ import annotations

import base64
import binascii
import contextlib
import json
import logging
import math
import os
import queue
import struct
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from pathlib import Path
from typing import IO, Any

import cv2
import numpy as np

from robotd.core.errors import InputError, PersistenceError
from robotd.core.msgs import LandmarkMap, Observations, Odometry, PoseEstimate, StereoFrame
from robotd.core.stereo import RectifiedStereo
from robotd.formats import foxglove_pb as fx
from robotd.formats.mcap_scan import ChannelRec, McapScan, MessageRec

logger = logging.getLogger("robotd.record")  # its name before the layer packages: users filter by it

FORMAT_VERSION = 2
READABLE_VERSIONS = (1, 2)
PROFILE = ""  # no ROS profile: Foxglove protobuf and plain JSON channels
TOPIC_IMAGE = {"left": "/camera/left/image", "right": "/camera/right/image"}
TOPIC_CAMERA_CAL = {"left": "/camera/left/calibration", "right": "/camera/right/calibration"}
TOPIC_FEATURES = "/camera/left/features"
TOPIC_TF = "/tf"
TOPIC_FRAME = "/robotd/frame"
TOPIC_ODOMETRY = "/robotd/odometry"
TOPIC_POSE = "/robotd/pose"
TOPIC_TRAJECTORY = "/robotd/trajectory"
TOPIC_MAP = "/robotd/map"
TOPIC_MAP_COVARIANCE = "/robotd/map_covariance"
TOPIC_TRUTH = "/truth/pose"
TOPIC_TRUTH_TRAJECTORY = "/truth/trajectory"
TOPIC_POSE_ESTIMATE = "/robotd/pose_estimate"
TOPIC_CALIBRATION = "/robotd/calibration"
FRAME_ID = fx.CAMERA
WORLD_FRAME_ID = fx.WORLD

# Reading limits (the MCAP framing's own are in robotd.formats.mcap_scan).
MAX_JSON_BYTES = 1 << 20  # a robotd JSON message (frame info, pose, odometry) is < 2 KB
MAX_META_JSON_BYTES = 4 << 20  # the calibration with a raw OAK EEPROM dump is ~50 KB
MAX_IMAGE_SIDE = 8192  # [px]; the images must also be the calibration's size
MAX_ABS_T_NS = 1 << 62  # stamps beyond ±146 years are forged (and would overflow int64 sums)
PENDING_FRAMES = 8  # images waiting for their frame info; more means the file is not robotd's
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"

# --------------------------------------------------------------------------------------------
# JSON Schemas of robotd's own channels

_NUMBERS = {"type": "array", "items": {"type": "number"}}


def _schema(title: str, props: dict[str, Any]) -> dict[str, Any]:
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": title, "type": "object",
            "properties": props}  # fmt: skip


SCHEMAS: dict[str, dict[str, Any]] = {
    "robotd.FrameInfo": _schema(
        "robotd.FrameInfo",
        {
            "t_ns": {"type": "integer"},
            "seq": {"type": "integer"},
            "rectified": {"type": "boolean"},
            "truth_T_world_robot": {"type": ["array", "null"], "items": _NUMBERS},
            "exposure_ns": {"type": "integer"},
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


def rectified_from_json(d: Any) -> RectifiedStereo:
    """The rectified rig of a calibration record, checked: a forged one must not size the images."""
    try:
        r = d["rectified"]
        f, px, py, b = (float(r[k]) for k in ("f_px", "px", "py", "baseline_m"))
        w, h = r["width"], r["height"]
    except (KeyError, TypeError, ValueError) as exc:
        raise PersistenceError(f"calibration record: {exc!r}") from None
    if not all(isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= MAX_IMAGE_SIDE for v in (w, h)):
        raise PersistenceError(f"calibration record: image size {w!r}x{h!r}, expected 1..{MAX_IMAGE_SIDE} px each")
    if not all(math.isfinite(v) for v in (f, px, py, b)) or f <= 0 or b <= 0:
        raise PersistenceError(f"calibration record: f {f} px, baseline {b} m: expected finite and positive")
    return RectifiedStereo(f, px, py, b, w, h)


def camera_calibration_pb(model: RectifiedStereo, side: str, wall_ns: int) -> fx.CameraCalibration:
    """foxglove.CameraCalibration of one rectified camera (ROS CameraInfo conventions for P)."""
    f, px, py = model.f_px, model.px, model.py
    tx = -f * model.baseline_m if side == "right" else 0.0
    return fx.CameraCalibration(
        timestamp=fx.stamp(wall_ns),
        frame_id=FRAME_ID[side],
        width=model.width,
        height=model.height,
        distortion_model="plumb_bob",
        D=[0.0] * 5,  # rectified images carry no distortion
        K=[f, 0.0, px, 0.0, f, py, 0.0, 0.0, 1.0],
        R=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        P=[f, 0.0, px, tx, 0.0, f, py, 0.0, 0.0, 0.0, 1.0, 0.0],
    )


def odometry_to_json(o: Odometry) -> dict[str, Any]:
    """Format 1's robotd.Odometry (kept for reading and for tools that want JSON)."""
    return {"t_ns": int(o.t_ns), "vel_R_mps": _floats(o.vel_R_mps), "rate_R_radps": _floats(o.rate_R_radps),
            "source": o.source, "cov": None if o.cov is None else _floats(o.cov)}  # fmt: skip


def _t_ns(v: Any, what: str) -> int:
    if not isinstance(v, int) or isinstance(v, bool) or abs(v) >= MAX_ABS_T_NS:
        raise PersistenceError(f"{what}: expected integer nanoseconds within ±2^62, got {str(v)[:40]}")
    return v


def _array(v: Any, shape: tuple[int, ...], what: str) -> np.ndarray:
    a = np.array(v, dtype=float)
    if a.size != math.prod(shape):
        raise PersistenceError(f"{what}: expected {math.prod(shape)} numbers, got {a.size}")
    return a.reshape(shape)


def odometry_from_json(d: Mapping[str, Any]) -> Odometry:
    cov = d.get("cov")  # absent in recordings made before samples carried their noise
    return Odometry(_t_ns(d["t_ns"], "odometry t_ns"), _array(d["vel_R_mps"], (3,), "vel_R_mps"),
                    _array(d["rate_R_radps"], (3,), "rate_R_radps"), str(d["source"]),
                    None if cov is None else _array(cov, (6, 6), "odometry cov"))  # fmt: skip


def odometry_from_pb(m: fx.FoxOdometry) -> Odometry:
    meta = {kv.key: kv.value for kv in m.metadata}
    t = meta.get("t_ns", "")
    if not (t.lstrip("-").isdigit() and len(t) <= 20):
        raise PersistenceError(f"odometry: metadata t_ns {t[:40]!r} is not integer nanoseconds")
    cov = None
    if meta.get("cov") == "given":
        cov = _array(list(m.velocity_covariance), (6, 6), "odometry velocity_covariance")
    v, w = m.linear_velocity, m.angular_velocity
    return Odometry(_t_ns(int(t), "odometry t_ns"), np.array([v.x, v.y, v.z]), np.array([w.x, w.y, w.z]),
                    meta.get("source", "unknown"), cov)  # fmt: skip


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
    n = d["n_particles"]
    if not isinstance(n, int) or isinstance(n, bool) or not 0 <= n < 1 << 31:
        raise PersistenceError(f"pose estimate: n_particles {str(n)[:40]}")
    t = _t_ns(d["t_ns"], "pose t_ns")
    xyz, rpy = _array(d["xyz_W_m"], (3,), "xyz_W_m"), _array(d["rpy_rad"], (3,), "rpy_rad")
    return PoseEstimate(t, xyz, rpy, _array(d["cov"], (6, 6), "pose cov"), neff, n)


def encode_png(img: np.ndarray, level: int) -> bytes:
    """A grey uint8 image as PNG. Huffman-only deflate after PNG's per-row filters: sensor noise
    leaves LZ77 nothing to find, so this is both smaller and faster than the default strategy
    (on the simulated rover's 640×400: 8.4 vs 9.5 MB/s of stereo at 30 Hz, ~3.5 vs ~4.5 ms per image)."""
    params = [cv2.IMWRITE_PNG_COMPRESSION, int(level), cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY]
    ok, buf = cv2.imencode(".png", img, params)
    if not ok:
        raise InputError(f"PNG encoding of a {img.shape} image failed")
    return buf.tobytes()  # type: ignore[no-any-return]


def _check_png_chunks(data: bytes) -> None:
    """Every chunk's stated length within the bytes that follow it, up to IEND. OpenCV's PNG reader
    allocates a chunk's stated length before reading it: one flipped bit in an IDAT length (behind
    valid CRCs) cost 2.3 GB and 6.5 s for a 2 kB image (bench/fuzz.py)."""
    pos = len(PNG_SIGNATURE)
    while pos + 12 <= len(data):
        (n,) = struct.unpack_from(">I", data, pos)
        kind = data[pos + 4 : pos + 8]
        if n > len(data) - pos - 12:
            name = kind.decode("ascii", "replace") if kind.isalpha() else kind.hex()
            raise PersistenceError(
                f"image: PNG chunk {name} at byte {pos} says {n} bytes, {max(0, len(data) - pos - 12)} follow"
            )
        if kind == b"IEND":
            return
        pos += 12 + n
    raise PersistenceError(f"image: PNG ends at byte {len(data)} without an IEND chunk")


def decode_png(data: bytes, width: int, height: int) -> np.ndarray:
    """PNG bytes -> (height, width) uint8, after checking the header says exactly that (a forged
    header must not make the decoder allocate what it claims)."""
    if len(data) < 33 or data[:8] != PNG_SIGNATURE or data[12:16] != b"IHDR":
        raise PersistenceError("image: not a PNG (no signature and IHDR header)")
    w, h, depth, colour = struct.unpack(">IIBB", data[16:26])
    if (w, h) != (width, height) or depth != 8 or colour != 0:
        raise PersistenceError(
            f"image: PNG header says {w}x{h}, {depth}-bit, colour type {colour}; "
            f"the recording's camera is {width}x{height} 8-bit grey (colour type 0)"
        )
    _check_png_chunks(data)
    try:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:
        raise PersistenceError(f"image: PNG does not decode: {str(exc).strip()[:120]}") from None
    if img is None or img.shape != (height, width) or img.dtype != np.uint8:
        raise PersistenceError(f"image: PNG does not decode to a {width}x{height} 8-bit grey image")
    return img


def decode_raw(data: bytes, encoding: str, w: int, h: int, step: int, width: int, height: int) -> np.ndarray:
    if encoding != "mono8":
        raise PersistenceError(f"RawImage encoding {encoding[:40]!r} not supported, expected 'mono8'")
    if (w, h) != (width, height) or not w <= step <= 4 * w:
        raise PersistenceError(f"RawImage {w}x{h} step {step}; the recording's camera is {width}x{height}")
    if len(data) != h * step:
        raise PersistenceError(f"RawImage: {len(data)} bytes for {h} rows of {step}")
    return np.frombuffer(data, np.uint8).reshape(h, step)[:, :w].copy()


def _json(data: bytes, what: str, limit: int = MAX_JSON_BYTES) -> dict[str, Any]:
    if len(data) > limit:
        raise PersistenceError(f"{what}: {len(data)} bytes of JSON, limit {limit}")
    try:
        d = json.loads(data)
    except (ValueError, RecursionError) as exc:  # UnicodeDecodeError is a ValueError
        raise PersistenceError(f"{what}: not JSON ({str(exc)[:80]})") from None
    if not isinstance(d, dict):
        raise PersistenceError(f"{what}: expected a JSON object, got {type(d).__name__}")
    return d


class _Path:
    """A trajectory for Foxglove's PosesInFrame: a pose kept when it moved ``min_step_m`` or
    turned ``min_turn_rad`` from the last kept one, at most ``max_poses`` (every other pose is
    dropped, and the spacing doubled, when full), so its message stays small on long runs."""

    def __init__(self, min_step_m: float = 0.02, min_turn_rad: float = math.radians(1.0), max_poses: int = 4000):
        self.min_step_m, self.min_turn_rad, self.max_poses = min_step_m, min_turn_rad, max_poses
        self.poses: list[np.ndarray] = []
        self.changed = False

    def add(self, T: np.ndarray) -> None:
        if self.poses:
            last = self.poses[-1]
            dR = last[:3, :3].T @ T[:3, :3]
            turn = math.acos(max(-1.0, min(1.0, (float(np.trace(dR)) - 1.0) / 2.0)))
            if np.linalg.norm(T[:3, 3] - last[:3, 3]) < self.min_step_m and turn < self.min_turn_rad:
                return
        self.poses.append(np.array(T, float))
        self.changed = True
        if len(self.poses) > self.max_poses:
            self.poses = self.poses[::2]
            self.min_step_m *= 2.0
            self.min_turn_rad *= 2.0

    def message(self, wall_ns: int) -> fx.PosesInFrame:
        self.changed = False
        return fx.PosesInFrame(timestamp=fx.stamp(wall_ns), frame_id=WORLD_FRAME_ID,
                               poses=[fx.pose_pb(T) for T in self.poses])  # fmt: skip


def _interrupted_name(tmp: Path) -> Path:
    """Where a temporary file left by a killed recorder is kept: OUT.interrupted-<mtime>.mcap."""
    stem = tmp.name.removesuffix(".tmp").removesuffix(".mcap")
    when = time.strftime("%Y%m%d-%H%M%S", time.localtime(tmp.stat().st_mtime))
    cand = tmp.with_name(f"{stem}.interrupted-{when}.mcap")
    k = 1
    while cand.exists():
        k += 1
        cand = tmp.with_name(f"{stem}.interrupted-{when}-{k}.mcap")
    return cand


# --------------------------------------------------------------------------------------------
# The session as Foxglove messages

# (topic, schema name) of each channel key; robotd.* schemas are JSON, the others protobuf
CHANNELS: dict[str, tuple[str, str]] = {
    "left": (TOPIC_IMAGE["left"], "foxglove.CompressedImage"),
    "right": (TOPIC_IMAGE["right"], "foxglove.CompressedImage"),
    "cal_left": (TOPIC_CAMERA_CAL["left"], "foxglove.CameraCalibration"),
    "cal_right": (TOPIC_CAMERA_CAL["right"], "foxglove.CameraCalibration"),
    "features": (TOPIC_FEATURES, "foxglove.ImageAnnotations"),
    "tf": (TOPIC_TF, "foxglove.FrameTransforms"),
    "pose": (TOPIC_POSE, "foxglove.PoseInFrame"),
    "trajectory": (TOPIC_TRAJECTORY, "foxglove.PosesInFrame"),
    "map": (TOPIC_MAP, "foxglove.PointCloud"),
    "map_covariance": (TOPIC_MAP_COVARIANCE, "foxglove.SceneUpdate"),
    "truth": (TOPIC_TRUTH, "foxglove.PoseInFrame"),
    "truth_trajectory": (TOPIC_TRUTH_TRAJECTORY, "foxglove.PosesInFrame"),
    "odometry": (TOPIC_ODOMETRY, "foxglove.Odometry"),
    "frame": (TOPIC_FRAME, "robotd.FrameInfo"),
    "pose_estimate": (TOPIC_POSE_ESTIMATE, "robotd.PoseEstimate"),
    "calibration": (TOPIC_CALIBRATION, "robotd.Calibration"),
}


def schema_record(name: str) -> tuple[str, bytes]:
    """(schema encoding, schema data) of a channel schema, as MCAP and Foxglove's WebSocket
    protocol both declare it."""
    if name in SCHEMAS:
        return "jsonschema", json.dumps(SCHEMAS[name]).encode()
    return "protobuf", fx.file_descriptor_set(fx.CLASSES[name])


def message_encoding(schema: str) -> str:
    return "json" if schema.startswith("robotd.") else "protobuf"


def payload(msg: Any) -> bytes:
    """A message's bytes: JSON for robotd's dicts, protobuf for Foxglove's messages."""
    return _dumps(msg) if isinstance(msg, dict) else msg.SerializeToString()  # type: ignore[no-any-return]


Item = tuple[str, int, Any, int]  # (channel key, t_ns, message, sequence)


class FoxgloveScene:
    """What a session looks like in Foxglove, as messages: no I/O, so the recording
    (:class:`SessionWriter`) and the live view (``robotd.outputs.liveview``) send the same
    channels. Each method returns ``(channel key, t_ns, message, sequence)`` items; the keys are
    :data:`CHANNELS`'. Keeps the little state the messages need (the wall-clock offset, when the
    calibration was last repeated, the trajectories, the last pixel of each tracked landmark).
    Options as :class:`SessionWriter`'s."""

    def __init__(
        self,
        calibration: RectifiedStereo,
        calib_json: Mapping[str, Any],
        *,
        image_format: str = "png",
        png_level: int = 1,
        calibration_period_s: float = 1.0,
        trajectory_period_s: float = 1.0,
        max_ellipsoids: int = 2000,
        wall_offset_ns: int | None = None,
    ) -> None:
        if image_format not in ("png", "raw"):
            raise InputError(f"image_format: expected 'png' or 'raw', got {image_format!r}")
        if not 0 <= int(png_level) <= 9:
            raise InputError(f"png_level: expected 0..9, got {png_level}")
        self.calibration = calibration
        self.calib_json = calib_json
        self.image_format = image_format
        self.png_level = int(png_level)
        self.calibration_period_ns = int(calibration_period_s * 1e9)
        self.trajectory_period_ns = int(trajectory_period_s * 1e9)
        self.max_ellipsoids = int(max_ellipsoids)
        self._wall_offset = wall_offset_ns
        self._last_cal_ns: int | None = None
        self._last_traj_ns: int | None = None
        self._truth0_inv: np.ndarray | None = None
        self._path, self._truth_path = _Path(), _Path()
        self._last_uv: dict[int, tuple[float, float]] = {}

    def channels(self) -> dict[str, tuple[str, str]]:
        """Channel key -> (topic, schema name), with the image schema this scene sends."""
        img = "foxglove.CompressedImage" if self.image_format == "png" else "foxglove.RawImage"
        return {k: (topic, img if k in ("left", "right") else schema) for k, (topic, schema) in CHANNELS.items()}

    def wall_ns(self, t_ns: int) -> int:
        """The wall-clock (Unix) time of an instant ``t_ns`` on the session's clock."""
        if self._wall_offset is None:
            mono, wall = time.monotonic_ns(), time.time_ns()
            # host-monotonic stamps (a live camera) map exactly; a dataset's own clock starts now
            self._wall_offset = wall - mono if abs(int(t_ns) - mono) < 86_400 * 10**9 else wall - int(t_ns)
        return max(0, int(t_ns) + self._wall_offset)

    def frame(self, frame: StereoFrame, k: int, images: bool = True) -> list[Item]:
        """Both images (unless ``images`` is False: the live view with no viewer spares the PNG
        encoding), the frame info, the ground truth when the frame carries one and (once per
        ``calibration_period_s``) the camera calibrations and the robot → camera transforms."""
        t = int(frame.t_ns)
        wall = self.wall_ns(t)
        out: list[Item] = []
        if self._last_cal_ns is None:
            out.append(("calibration", t, dict(self.calib_json), 0))
        if self._last_cal_ns is None or t - self._last_cal_ns >= self.calibration_period_ns:
            for side in ("left", "right"):
                out.append((f"cal_{side}", t, camera_calibration_pb(self.calibration, side, wall), 0))
            tfs = fx.FrameTransforms(transforms=fx.camera_transforms(wall, self.calibration.baseline_m))
            out.append(("tf", t, tfs, 0))
            self._last_cal_ns = t
        for side, img in (("left", frame.left), ("right", frame.right)) if images else ():
            out.append((side, t, self._image(img, side, wall), k))
        truth = None if frame.truth_T_world_robot is None else _floats(frame.truth_T_world_robot)
        info = {"t_ns": t, "seq": int(frame.seq), "rectified": bool(frame.rectified), "truth_T_world_robot": truth}
        if frame.exposure_ns:
            info["exposure_ns"] = int(frame.exposure_ns)  # absent: not reported (older files alike)
        out.append(("frame", t, info, k))
        if frame.truth_T_world_robot is not None:
            # shown from the first truth pose on, where the estimate's world frame starts
            if self._truth0_inv is None:
                self._truth0_inv = np.linalg.inv(frame.truth_T_world_robot)
            G = self._truth0_inv @ frame.truth_T_world_robot
            out.append(("truth", t, fx.PoseInFrame(timestamp=fx.stamp(wall), frame_id=WORLD_FRAME_ID,
                                                   pose=fx.pose_pb(G)), 0))  # fmt: skip
            self._truth_path.add(G)
        return out

    def _image(self, img: np.ndarray, side: str, wall: int) -> Any:
        if self.image_format == "png":
            return fx.CompressedImage(timestamp=fx.stamp(wall), frame_id=FRAME_ID[side],
                                      data=encode_png(img, self.png_level), format="png")  # fmt: skip
        h, w = img.shape
        return fx.RawImage(timestamp=fx.stamp(wall), frame_id=FRAME_ID[side], width=w, height=h, encoding="mono8",
                           step=w, data=np.ascontiguousarray(img).tobytes())  # fmt: skip

    def odometry(self, o: Odometry, k: int) -> list[Item]:
        msg = fx.odometry_pb(self.wall_ns(o.t_ns), o.t_ns, o.vel_R_mps, o.rate_R_radps, o.cov, o.source)
        return [("odometry", int(o.t_ns), msg, k)]

    def pose(self, pose: PoseEstimate, k: int) -> list[Item]:
        """The published pose: foxglove.PoseInFrame and the world → robot transform (for the 3D
        panel), the full robotd.PoseEstimate, and the trajectories (once per ``trajectory_period_s``)."""
        t = int(pose.t_ns)
        wall = self.wall_ns(t)
        T = pose.T_world_robot
        out: list[Item] = [
            ("pose", t, fx.PoseInFrame(timestamp=fx.stamp(wall), frame_id=WORLD_FRAME_ID, pose=fx.pose_pb(T)), k),
            ("tf", t, fx.FrameTransforms(transforms=[fx.transform(wall, fx.WORLD, fx.ROBOT, T)]), 0),
            ("pose_estimate", t, pose_estimate_msg(pose), k),
        ]
        self._path.add(T)
        if self._last_traj_ns is None or t - self._last_traj_ns >= self.trajectory_period_ns:
            out += self.trajectories(t)
        return out

    def trajectories(self, t_ns: int | None = None) -> list[Item]:
        """The trajectories that changed since they were last sent (``t_ns`` None: at the last
        time they were sent, for the end of a session)."""
        t = self._last_traj_ns if t_ns is None else t_ns
        if t is None:
            return []
        wall = self.wall_ns(t)
        out: list[Item] = []
        if self._path.changed:
            out.append(("trajectory", t, self._path.message(wall), 0))
        if self._truth_path.changed:
            out.append(("truth_trajectory", t, self._truth_path.message(wall), 0))
        self._last_traj_ns = t
        return out

    def features(self, obs: Observations) -> list[Item]:
        """The observations the filter took this frame, on the left image, with each re-observed
        landmark's track from the previous annotated frame (nothing when they carry no pixels)."""
        if obs.uv_px is None:
            return []
        ids = [int(i) for i in obs.ids]
        tracks = [(*self._last_uv[i], float(u), float(v)) for i, (u, _, v), new in zip(ids, obs.uv_px, obs.is_new)
                  if not new and i in self._last_uv]  # fmt: skip
        msg = fx.feature_annotations(self.wall_ns(obs.t_ns), obs.uv_px, obs.is_new, tracks)
        self._last_uv = {i: (float(u), float(v)) for i, (u, _, v) in zip(ids, obs.uv_px)}
        return [("features", int(obs.t_ns), msg, 0)]

    def map(self, t_ns: int, landmarks: LandmarkMap) -> list[Item]:
        """The point cloud, and the covariance ellipsoids of the ``max_ellipsoids`` newest
        landmarks (the map lists them in creation order; the newest are the ones around the
        robot). Pure: the ellipsoids of 2000 landmarks take ~17 ms, so callers build them outside
        any lock."""
        wall = self.wall_ns(t_ns)
        n = min(landmarks.n, self.max_ellipsoids)
        cov = fx.covariance_ellipsoids(wall, landmarks.xyz_W_m[landmarks.n - n :], landmarks.cov_W[landmarks.n - n :])
        return [("map", t_ns, fx.points_cloud(wall, landmarks.xyz_W_m, landmarks.ids), 0),
                ("map_covariance", t_ns, cov, 0)]  # fmt: skip


# --------------------------------------------------------------------------------------------
# Writer


class SessionWriter:
    """Write one session to ``path`` (MCAP format 2; crash-safe, atomic finish). Not thread-safe:
    one writer thread (as :class:`robotd.outputs.recorder.RecorderOutput` has), or a lock.

    ``calibration``: the rectified rig the frames are in (:class:`RectifiedStereo`); ``meta``:
    JSON-able facts about the session (source URL, config, robotd version, seed...). Options:
    ``raw_calibration`` (StereoCalibration-like or JSON-able, e.g. the OAK EEPROM dump),
    ``image_format`` ``"png"`` (default, lossless) or ``"raw"`` (mono8 RawImage), ``png_level``
    0–9 (1), ``calibration_period_s`` (1.0: how often the camera calibrations and the static
    transforms are repeated so seeking in Foxglove finds them), ``chunk_size`` (bytes),
    ``max_ellipsoids`` (2000: the landmarks whose covariance ellipsoids are drawn),
    ``flush_period_s`` (1.0: the longest a written message waits before its chunk reaches the
    operating system, i.e. what a killed recorder can lose), ``trajectory_period_s`` (1.0: how
    often the trajectories are written), ``wall_offset_ns`` (wall clock minus ``t_ns``; default:
    the host's wall minus monotonic clock when the stamps are host-monotonic, else the first
    message is stamped now).
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
        flush_period_s: float = 1.0,
        trajectory_period_s: float = 1.0,
        max_ellipsoids: int = 2000,
        wall_offset_ns: int | None = None,
        opener: Callable[[Path], IO[bytes]] | None = None,
    ) -> None:
        from mcap.writer import CompressionType, Writer

        self.path = Path(path)
        self.tmp_path = self.path.with_name(self.path.name + ".tmp")
        self.calibration = calibration
        self.flush_period_s = float(flush_period_s)
        self.counts = {"frames": 0, "odometry": 0, "poses": 0, "maps": 0, "bytes": 0, "flushes": 0}
        self.kept_interrupted: Path | None = None
        self._closed = False
        self._failed: PersistenceError | None = None
        calib_json = calibration_to_json(calibration, raw_calibration)
        self.scene = FoxgloveScene(
            calibration, calib_json, image_format=image_format, png_level=png_level,
            calibration_period_s=calibration_period_s, trajectory_period_s=trajectory_period_s,
            max_ellipsoids=max_ellipsoids, wall_offset_ns=wall_offset_ns,
        )  # fmt: skip
        try:
            session_meta = {"format_version": FORMAT_VERSION, "meta": dict(meta or {})}
            meta_json = json.dumps(session_meta, allow_nan=False)
        except (TypeError, ValueError) as exc:
            raise InputError(f"meta: expected JSON-able values, got {exc}") from None
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            if self.tmp_path.exists():
                # a recorder killed before it could finish: its data are kept, never overwritten
                self.kept_interrupted = _interrupted_name(self.tmp_path)
                os.replace(self.tmp_path, self.kept_interrupted)
                logger.warning(
                    "%s was left by an interrupted recording: kept as %s (replay it: robotd replay %s)",
                    self.tmp_path, self.kept_interrupted, self.kept_interrupted,
                )  # fmt: skip
            self._file: IO[bytes] = opener(self.tmp_path) if opener else open(self.tmp_path, "wb")
            self._writer = Writer(self._file, chunk_size=chunk_size, compression=CompressionType.ZSTD)
            self._writer.start(profile=PROFILE, library=f"robotd-record/{FORMAT_VERSION}")
            # every schema is registered (a format-2 file always declares the same set)
            schema_ids = {name: self._writer.register_schema(name, *schema_record(name))
                          for name in (*fx.CLASSES, *SCHEMAS)}  # fmt: skip
            self._ch = {
                key: self._writer.register_channel(topic, message_encoding(schema), schema_ids[schema])
                for key, (topic, schema) in self.scene.channels().items()
            }
            # metadata go straight to the file, ahead of the first chunk: a killed recording
            # still says what it is
            self._writer.add_metadata("robotd.session", {"json": meta_json})
            self._writer.add_metadata("robotd.calibration", {"json": json.dumps(calib_json)})
            self._file.flush()
        except OSError as exc:
            self._fail(exc, "opening")
        self._last_flush = time.monotonic()
        logger.info("recording to %s (via %s), images %s", self.path, self.tmp_path.name, image_format)

    def wall_ns(self, t_ns: int) -> int:
        """The wall-clock (Unix) time of an instant ``t_ns`` on the session's clock."""
        return self.scene.wall_ns(t_ns)

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

    def _write(self, items: Iterable[Item]) -> None:
        for channel, t_ns, msg, seq in items:
            data = payload(msg)
            wall = self.scene.wall_ns(t_ns)
            try:
                self._writer.add_message(self._ch[channel], log_time=wall, data=data, publish_time=wall, sequence=seq)
                now = time.monotonic()
                if now - self._last_flush >= self.flush_period_s:
                    # close the chunk and hand it to the OS: a killed recorder loses at most this period
                    self._writer.flush()
                    self._last_flush = now
                    self.counts["flushes"] += 1
            except (OSError, ValueError) as exc:
                self._fail(exc, f"writing {channel}")
            self.counts["bytes"] += len(data)

    # -- public API --------------------------------------------------------------------------
    def write_frame(self, frame: StereoFrame) -> None:
        """See :meth:`FoxgloveScene.frame`."""
        self._check_open()
        self._write(self.scene.frame(frame, self.counts["frames"]))
        self.counts["frames"] += 1

    def write_odometry(self, odometry: Odometry) -> None:
        self._check_open()
        self._write(self.scene.odometry(odometry, self.counts["odometry"]))
        self.counts["odometry"] += 1

    def write_pose(self, pose: PoseEstimate) -> None:
        """See :meth:`FoxgloveScene.pose`."""
        self._check_open()
        self._write(self.scene.pose(pose, self.counts["poses"]))
        self.counts["poses"] += 1

    def write_features(self, obs: Observations) -> None:
        """See :meth:`FoxgloveScene.features`."""
        self._check_open()
        self._write(self.scene.features(obs))

    def map_messages(self, t_ns: int, landmarks: LandmarkMap) -> list[Item]:
        """:meth:`FoxgloveScene.map`: built without touching the file, so outside any lock."""
        return self.scene.map(t_ns, landmarks)

    def write_map(self, t_ns: int, landmarks: LandmarkMap | list[Item]) -> None:
        """The landmark map (a :class:`LandmarkMap`, or what :meth:`map_messages` built from one)."""
        self._check_open()
        self._write(self.scene.map(t_ns, landmarks) if isinstance(landmarks, LandmarkMap) else landmarks)
        self.counts["maps"] += 1

    def flush_if_due(self) -> None:
        """Hand the open chunk to the operating system when it waited ``flush_period_s`` (a writer
        with nothing new to write calls this, so a quiet source does not hold data back)."""
        if self._closed or time.monotonic() - self._last_flush < self.flush_period_s:
            return
        try:
            self._writer.flush()
        except (OSError, ValueError) as exc:
            self._fail(exc, "flushing")
        self._last_flush = time.monotonic()

    def add_metadata(self, name: str, data: Mapping[str, str]) -> None:
        """A metadata record (string → string), written where the file is now: Foxglove and
        ``mcap`` list them; robotd writes its recording figures this way just before closing."""
        self._check_open()
        try:
            self._writer.add_metadata(name, dict(data))
        except (OSError, ValueError) as exc:
            self._fail(exc, f"writing metadata {name}")

    def close(self) -> None:
        """Write the last trajectories and the MCAP summary, fsync, and rename ``PATH.tmp`` to
        ``PATH``. Idempotent."""
        if self._closed:
            if self._failed is not None:
                raise PersistenceError(f"{self.path}: writer failed earlier: {self._failed}")
            return
        self._write(self.scene.trajectories())
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
    """Read a recording written by :class:`SessionWriter` (format 2) or by robotd before it
    (format 1); events come back in file order.

    Opening reads only the start of the file (header, schemas, metadata): a file that is not an
    MCAP, not a robotd recording, or of a format version this robotd does not read is refused
    with a :class:`PersistenceError` naming the path and the version. Reading is bounded (see
    :mod:`robotd.formats.mcap_scan` and the limits above) and stops at the first damage: after a walk,
    ``stopped`` says where and why (None: the whole data section was read) and ``finished``
    whether the file was closed cleanly. ``strict=True`` raises at the damage instead.
    """

    def __init__(self, path: str | Path, *, strict: bool = False) -> None:
        self.path = Path(path)
        self.strict = strict
        if not self.path.is_file():
            raise PersistenceError(f"{self.path}: no such recording")
        try:
            self._scan = McapScan(self.path)
            self._scan.preamble()
        except OSError as exc:
            raise PersistenceError(f"{self.path}: cannot read: {exc}") from None
        s = self._scan
        if s.header is None:
            raise PersistenceError(f"{self.path}: not a readable MCAP file: {s.stopped or 'no header record'}")
        metadata = s.metadata
        if "robotd.session" not in metadata or "robotd.calibration" not in metadata:
            raise PersistenceError(
                f"{self.path}: an MCAP file, but not a robotd recording (no robotd.session metadata"
                + (f"; {s.stopped}" if s.stopped else "")
                + ")"
            )
        session = _json(metadata["robotd.session"].get("json", "").encode(), "robotd.session", MAX_META_JSON_BYTES)
        version = session.get("format_version")
        if version not in READABLE_VERSIONS or isinstance(version, bool):
            raise PersistenceError(
                f"{self.path}: recording format version {str(version)[:20]}; this robotd reads versions "
                f"{', '.join(map(str, READABLE_VERSIONS))}" + (": a newer robotd wrote it" if _newer(version) else "")
            )
        self.format_version: int = version
        meta = session.get("meta", {})
        self.meta: dict[str, Any] = meta if isinstance(meta, dict) else {}
        cal = metadata["robotd.calibration"].get("json", "").encode()
        self.calibration_json: dict[str, Any] = _json(cal, "robotd.calibration", MAX_META_JSON_BYTES)
        try:
            self.calibration = rectified_from_json(self.calibration_json)
        except PersistenceError as exc:
            raise PersistenceError(f"{self.path}: {exc}") from None
        self.stopped: str | None = None
        self.finished = False
        self.frames_read = 0

    def _decode(self, schema: str, encoding: str, m: MessageRec) -> Any:
        """One message of a wanted topic -> an image array, a frame-info dict, Odometry or
        PoseEstimate. Raises PersistenceError (or InputError from the messages' own checks)."""
        W, H = self.calibration.width, self.calibration.height
        if encoding == "protobuf":
            cls = fx.CLASSES.get(schema)
            if cls is None:
                raise PersistenceError(f"unexpected protobuf schema {schema[:60]!r}")
            try:
                pb = cls.FromString(m.data)
            except fx.DecodeError as exc:
                raise PersistenceError(f"{schema} does not decode: {exc}") from None
            if schema == "foxglove.CompressedImage":
                if pb.format != "png":
                    raise PersistenceError(f"image format {pb.format[:20]!r}, expected 'png' (lossless)")
                return decode_png(pb.data, W, H)
            if schema == "foxglove.RawImage":
                return decode_raw(pb.data, pb.encoding, pb.width, pb.height, pb.step, W, H)
            if schema == "foxglove.Odometry":
                return odometry_from_pb(pb)
            raise PersistenceError(f"unexpected schema {schema} on a replayed topic")
        if encoding != "json":
            raise PersistenceError(f"message encoding {encoding[:20]!r}, expected protobuf or json")
        d = _json(m.data, schema)
        if schema == "foxglove.CompressedImage":  # format 1: base64 PNG in JSON
            if d.get("format") != "png" or not isinstance(d.get("data"), str):
                raise PersistenceError("format-1 image: expected a base64 'data' string with format 'png'")
            return decode_png(_b64(d["data"]), W, H)
        if schema == "foxglove.RawImage":
            if not isinstance(d.get("data"), str):
                raise PersistenceError("format-1 RawImage: expected a base64 'data' string")
            return decode_raw(_b64(d["data"]), str(d.get("encoding")), _int(d, "width"), _int(d, "height"),
                              _int(d, "step"), W, H)  # fmt: skip
        if schema == "robotd.FrameInfo":
            return d
        if schema == "robotd.Odometry":
            return odometry_from_json(d)
        if schema == "robotd.PoseEstimate":
            return pose_estimate_from_msg(d)
        raise PersistenceError(f"unexpected schema {schema[:60]!r} on a replayed topic")

    def events(
        self, topics: Iterable[str] = (TOPIC_FRAME, TOPIC_ODOMETRY, TOPIC_POSE_ESTIMATE)
    ) -> Iterator[StereoFrame | Odometry | PoseEstimate]:
        """StereoFrame / Odometry / PoseEstimate in the order they were recorded, up to the end
        of the data or the first damage (see the class docstring)."""
        wanted = set(topics)
        want_frames = TOPIC_FRAME in wanted
        read = set(wanted) | (set(TOPIC_IMAGE.values()) if want_frames else set())
        pending: dict[int, dict[str, np.ndarray]] = {}
        self.stopped, self.finished, self.frames_read = None, False, 0
        scan = McapScan(self.path)
        ch: ChannelRec | None = None
        m: MessageRec | None = None
        try:
            for ch, m in scan.messages():
                if ch.topic not in read:
                    continue
                sch = scan.schemas.get(ch.schema_id)
                v = self._decode(sch.name if sch else "", ch.message_encoding, m)
                topic = ch.topic
                if topic == TOPIC_IMAGE["left"] or topic == TOPIC_IMAGE["right"]:
                    pending.setdefault(m.sequence, {})["left" if topic == TOPIC_IMAGE["left"] else "right"] = v
                    while len(pending) > PENDING_FRAMES:
                        pending.pop(next(iter(pending)))
                elif topic == TOPIC_FRAME:
                    imgs = pending.pop(m.sequence, {})
                    if "left" not in imgs or "right" not in imgs:
                        raise PersistenceError(f"frame {str(v.get('seq'))[:20]} has no left/right image before it")
                    yield self._frame(v, imgs)
                    self.frames_read += 1
                else:
                    yield v
        except (PersistenceError, InputError, KeyError, TypeError, ValueError, OverflowError) as exc:
            # a message that is not what its schema says: the damage is here, and reading stops
            where = f"byte {m.offset} of {scan.size}: a {ch.topic} message" if (m and ch) else "its start"
            self.stopped = f"stopped at {where}: {exc!s}"[:300]
            if self.strict:
                raise PersistenceError(f"{self.path}: {self.stopped}") from None
        except OSError as exc:
            raise PersistenceError(f"{self.path}: read error: {exc}") from None
        else:
            self.stopped, self.finished = scan.stopped, scan.finished
            if self.strict and self.stopped:
                raise PersistenceError(f"{self.path}: {self.stopped}")

    @staticmethod
    def _frame(d: Mapping[str, Any], imgs: Mapping[str, np.ndarray]) -> StereoFrame:
        try:
            truth = d.get("truth_T_world_robot")
            T = None if truth is None else _array(truth, (4, 4), "truth_T_world_robot")
            rect, seq = d["rectified"], d["seq"]
            if not isinstance(rect, bool) or not isinstance(seq, int) or isinstance(seq, bool) or abs(seq) >= 1 << 62:
                raise PersistenceError(f"frame info: rectified {str(rect)[:20]}, seq {str(seq)[:20]}")
            exposure = d.get("exposure_ns", 0)
            if not isinstance(exposure, int) or isinstance(exposure, bool) or not 0 <= exposure < 1 << 62:
                raise PersistenceError(f"frame info: exposure_ns {str(exposure)[:20]}")
            return StereoFrame(_t_ns(d["t_ns"], "frame t_ns"), seq, imgs["left"], imgs["right"], rect, T, exposure)
        except (KeyError, TypeError, ValueError, InputError) as exc:
            raise PersistenceError(f"frame info: {exc!r}"[:200]) from None

    def status(self) -> dict[str, Any]:
        """After a walk: whether the file was closed cleanly and, when reading stopped early, where."""
        return {"finished": self.finished, "stopped": self.stopped, "frames_read": self.frames_read,
                "format_version": self.format_version}  # fmt: skip

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

    def frame_count(self) -> int | None:
        """Frames in the file according to its summary (None: no readable summary, e.g. an
        interrupted recording). Reads no message."""
        summary = self._scan.summary()
        if summary is None or summary.message_counts is None:
            return None
        ids = [c.id for c in summary.channels.values() if c.topic == TOPIC_FRAME]
        return sum(summary.message_counts.get(i, 0) for i in ids)


def _newer(version: Any) -> bool:
    return isinstance(version, int) and not isinstance(version, bool) and version > FORMAT_VERSION


def _b64(s: str) -> bytes:
    try:
        return base64.b64decode(s, validate=True)
    except (binascii.Error, ValueError) as exc:
        raise PersistenceError(f"format-1 image: bad base64 ({exc})") from None


def _int(d: Mapping[str, Any], key: str) -> int:
    v = d.get(key)
    if not isinstance(v, int) or isinstance(v, bool) or not 0 <= v <= 1 << 31:
        raise PersistenceError(f"format-1 RawImage: {key} {str(v)[:20]}")
    return v


# --------------------------------------------------------------------------------------------
# Recording loop (used by tests and tools; the daemon records through RecorderOutput)


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
