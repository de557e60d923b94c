"""Replay sources: ``kitti://DIR``, ``euroc://DIR`` and ``mcap://FILE`` (or a bare ``FILE.mcap``).

Each is a :class:`drivers.StereoCamera` yielding rectified :class:`robotd.core.msgs.StereoFrame`s, plus a
:class:`drivers.VehicleLink` companion. Replay drivers keep **dataset time**: ``t_ns`` is the
dataset's own stamp (KITTI ``times.txt`` or 0.1 s × index, EuRoC nanosecond stamps, the recorded
host-monotonic stamps of an MCAP session), strictly increasing, from the first selected frame on.
They never substitute the replaying host's clock, so a replay is bit-for-bit repeatable.

Options (keyword arguments, or the URL query, e.g. ``kitti:///data/seq?stride=2&realtime=1``):

- ``start`` (0), ``stop`` (None = to the end): frame index range ``[start, stop)`` before striding;
- ``stride`` (1): keep every n-th frame;
- ``drop`` (none): ``A-B`` leaves out frames A … B−1 (indices as for start/stop): a camera stall
  or a hole in the recording, for testing what the pipeline does across one;
- ``realtime`` (False): sleep so frames come out at the dataset rate (× ``speed``, default 1.0);
  otherwise as fast as the consumer pulls.

Dataset-specific options: EuRoC ``alpha`` (0.0, OpenCV free scaling of the rectified view) and
``pair_tolerance_ns`` (1 ms, cam0/cam1 stamp pairing), and ``calibration`` (a StereoCalibration,
the config's ``camera.calibration``: the raw images are rectified with it instead of with the
folder's ``sensor.yaml``; it must be for the images' size). KITTI images and recordings are
rectified already and refuse one (their drivers' ``own_rig``, at the end of this module). Ground
truth, where the dataset has it, is attached to each frame as ``truth_T_world_robot`` (robot frame
FRD at the baseline centre of the rectified rig, world = robot frame at the first frame with
truth); it is for evaluation only.

Vehicle links: by default the dataset vehicle is **visual only**: ``odometry()`` yields nothing
and the pipeline runs on its visual (or constant-velocity) prediction. A KITTI raw folder that
keeps its drive's OXTS GPS/INS records (``raw/*/oxts``) offers them as recorded odometry with
``odometry=oxts`` (:mod:`drivers.kitti_oxts`; ``source="oxts"``); a folder without them has none.
``gt_odometry=True`` synthesises odometry from ground truth for experiments only (every sample
has ``source="gt-synthetic"``); see :class:`DatasetVehicle`. An MCAP recording's vehicle replays the
recorded odometry.
"""

from __future__ import annotations

import abc
import itertools
import logging
import re
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import parse_qsl

import cv2
import numpy as np

from drivers import AutopilotLink
from drivers._rectify import Rectifier, StereoCalibration, T_robot_leftraw, check_calibration_size, user_rectifier
from drivers.base import Driver
from drivers.cameras import CameraBase, DatasetOdometry
from robotd.core.errors import DatasetError, DriverError
from robotd.core.geometry import T_optical_to_robot, quat_to_R, se3, se3_inverse, so3_log
from robotd.core.msgs import Odometry, PoseEstimate, StereoFrame
from robotd.core.stereo import RectifiedStereo

logger = logging.getLogger(__name__)

KITTI_DT_NS = 100_000_000  # KITTI odometry runs at 10 Hz; used when times.txt is absent


# --------------------------------------------------------------------------------------------
# URL and option parsing


def _split_url(url: str | Path, scheme: str) -> tuple[Path, dict[str, str]]:
    """``scheme://PATH?k=v`` (or a bare path) -> (Path, query options).

    The part after ``scheme://`` is a filesystem path (absolute with three slashes, relative with
    two), not a network location, so ``urlsplit`` is not used on it.
    """
    s = str(url)
    prefix = f"{scheme}://"
    if s.lower().startswith(prefix):
        s = s[len(prefix) :]
    elif "://" in s:
        raise DriverError(f"{url!r}: expected a {prefix} URL or a path")
    path, _, query = s.partition("?")
    if not path:
        raise DriverError(f"{url!r}: expected a path after {prefix}")
    return Path(path).expanduser(), dict(parse_qsl(query, keep_blank_values=True))


def _as_bool(key: str, v: Any) -> bool:
    if isinstance(v, bool):
        return v
    s = str(v).strip().lower()
    if s in ("1", "true", "yes", "on", ""):
        return True
    if s in ("0", "false", "no", "off"):
        return False
    raise DriverError(f"option {key}: expected a boolean, got {v!r}")


def _as_int(key: str, v: Any, minimum: int | None = None) -> int:
    try:
        i = int(v)
    except (TypeError, ValueError):
        raise DriverError(f"option {key}: expected an integer, got {v!r}") from None
    if minimum is not None and i < minimum:
        raise DriverError(f"option {key}: expected >= {minimum}, got {i}")
    return i


def _as_range(key: str, v: Any) -> tuple[int, int]:
    """``A-B`` (integers, 0 <= A < B) -> (A, B); None or empty -> (0, 0)."""
    if v in (None, ""):
        return (0, 0)
    a, sep, b = str(v).partition("-")
    try:
        lo, hi = int(a), int(b)
    except ValueError:
        lo, hi = -1, -1
    if not sep or not 0 <= lo < hi:
        raise DriverError(f"option {key}: expected A-B with integers 0 <= A < B (frames A … B-1), got {v!r}")
    return (lo, hi)


def _as_float(key: str, v: Any, minimum: float | None = None) -> float:
    try:
        x = float(v)
    except (TypeError, ValueError):
        raise DriverError(f"option {key}: expected a number, got {v!r}") from None
    if not np.isfinite(x) or (minimum is not None and x < minimum):
        raise DriverError(f"option {key}: expected a finite number >= {minimum}, got {v!r}")
    return x


@dataclass(frozen=True, slots=True)
class ReplayOptions:
    """Frame selection and pacing shared by every replay source (see the module docstring)."""

    start: int = 0
    stop: int | None = None
    stride: int = 1
    realtime: bool = False
    speed: float = 1.0
    drop: tuple[int, int] = (0, 0)  # frames [A, B) left out (a stall); (0, 0): none

    @staticmethod
    def pop_from(options: dict[str, Any]) -> ReplayOptions:
        """Take the replay keys out of ``options`` (mutated), validating each."""
        stop = options.pop("stop", None)
        return ReplayOptions(
            start=_as_int("start", options.pop("start", 0), 0),
            stop=None if stop in (None, "", "none") else _as_int("stop", stop, 0),
            stride=_as_int("stride", options.pop("stride", 1), 1),
            realtime=_as_bool("realtime", options.pop("realtime", False)),
            speed=_as_float("speed", options.pop("speed", 1.0), 1e-3),
            drop=_as_range("drop", options.pop("drop", None)),
        )

    def select(self, n: int) -> list[int]:
        stop = n if self.stop is None else min(self.stop, n)
        return [k for k in range(self.start, stop, self.stride) if not self.dropped(k)]

    def dropped(self, k: int) -> bool:
        """Frame index ``k`` is inside the ``drop`` range."""
        return self.drop[0] <= k < self.drop[1]


def _reject_unknown(url: str, options: dict[str, Any], known: Sequence[str] = ()) -> None:
    extra = sorted(set(options) - set(known))
    if extra:
        raise DriverError(
            f"{url!r}: unknown option(s) {extra}; known: {sorted(known)} and start/stop/stride/drop/realtime"
        )


class _Pacer:
    """Sleeps so that dataset stamps come out at their recorded rate (× speed) on the host."""

    def __init__(self, enabled: bool, speed: float) -> None:
        self.enabled = enabled
        self.speed = speed
        self._t0_data: int | None = None
        self._t0_host = 0.0

    def wait(self, t_ns: int) -> None:
        if not self.enabled:
            return
        if self._t0_data is None:
            self._t0_data, self._t0_host = t_ns, time.monotonic()
            return
        due = self._t0_host + (t_ns - self._t0_data) * 1e-9 / self.speed
        delay = due - time.monotonic()
        if delay > 0:
            time.sleep(delay)


def _read_gray(path: Path) -> np.ndarray | None:
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        return None
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if img.dtype != np.uint8:
        return None
    return img


# --------------------------------------------------------------------------------------------
# Indexed image-pair sources (KITTI, EuRoC)


@dataclass(frozen=True, slots=True)
class FrameEntry:
    """One selectable stereo pair of a dataset index."""

    t_ns: int  # dataset time
    seq: int  # dataset frame index
    left: Path
    right: Path
    truth_T_world_robot: np.ndarray | None = None  # (4, 4)


class _ImageDatasetCamera(Driver):
    """Common replay logic of the folder datasets: select, load, rectify, pace, count."""

    url: str
    raw_calibration = None
    fps = None  # frames carry their recorded stamps; there is no nominal rate to budget for
    host_clock = False  # dataset time, not the replaying host's

    def __init__(self, url: str, entries: list[FrameEntry], replay: ReplayOptions) -> None:
        self.url = url
        self._all = entries
        self.entries = [entries[i] for i in replay.select(len(entries))]
        self.replay = replay
        self._closed = False
        self._stats: dict[str, Any] = {"frames": 0, "read_errors": 0, "drops": 0, "gaps": 0, "selected": 0}
        self._stats["selected"] = len(self.entries)

    # StereoCamera protocol ------------------------------------------------------------------
    def close(self) -> None:
        self._closed = True

    def stats(self) -> dict[str, Any]:
        return dict(self._stats)

    @abc.abstractmethod
    def rectified_model(self) -> RectifiedStereo:
        """The rectified rig of the dataset (each layout reads it from its own calibration files)."""

    def _rectify(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return left, right

    def truth(self) -> list[tuple[int, np.ndarray]]:
        """(t_ns, T_world_robot) of every selected frame with ground truth, in frame order."""
        return [(e.t_ns, e.truth_T_world_robot) for e in self.entries if e.truth_T_world_robot is not None]

    def frames(self, timeout_s: float = 1.0) -> Iterator[StereoFrame]:
        """Yield the selected frames in order; unreadable images are logged, counted and skipped."""
        pacer = _Pacer(self.replay.realtime, self.replay.speed)
        for e in self.entries:
            if self._closed:
                return
            left, right = _read_gray(e.left), _read_gray(e.right)
            if left is None or right is None or left.shape != right.shape:
                self._stats["read_errors"] += 1
                logger.warning("%s: cannot read 8-bit grey pair %s / %s; skipped", self.url, e.left, e.right)
                continue
            left, right = self._rectify(left, right)
            pacer.wait(e.t_ns)
            self._stats["frames"] += 1
            yield StereoFrame(e.t_ns, e.seq, left, right, rectified=True, truth_T_world_robot=e.truth_T_world_robot)


# --------------------------------------------------------------------------------------------
# KITTI odometry


def _kitti_calib(path: Path, size: tuple[int, int]) -> RectifiedStereo:
    """P0/P1 of ``calib.txt`` -> the rectified rig (f, p_x, p_y, b = -P1[0,3]/P1[0,0])."""
    P0, b = _kitti_projection(path)
    return RectifiedStereo(float(P0[0, 0]), float(P0[0, 2]), float(P0[1, 2]), b, size[0], size[1])


def kitti_baseline_m(path: str | Path) -> float:
    """The stereo baseline b = -P1[0,3]/P1[0,0] [m] of a KITTI ``calib.txt``."""
    return _kitti_projection(Path(path))[1]


def _kitti_projection(path: Path) -> tuple[np.ndarray, float]:
    """(P0 (3, 4), baseline [m]) of a KITTI ``calib.txt``."""
    rows: dict[str, np.ndarray] = {}
    unlabelled = 0
    for line in path.read_text().splitlines():
        if not line.strip():
            continue
        # "P0: 12 numbers" in the benchmark files; some redistributions drop the labels, in P0, P1… order
        key, sep, rest = line.partition(":")
        if not sep:
            key, rest, unlabelled = f"P{unlabelled}", line, unlabelled + 1
        try:
            rows[key.strip()] = np.array(rest.split(), dtype=float)
        except ValueError:
            raise DatasetError(f"{path}: row {key!r} is not 12 numbers") from None
    missing = [k for k in ("P0", "P1") if k not in rows or rows[k].size != 12]
    if missing:
        raise DatasetError(f"{path}: expected rows P0: and P1: with 12 numbers each, missing/invalid {missing}")
    P0, P1 = rows["P0"].reshape(3, 4), rows["P1"].reshape(3, 4)
    b = -P1[0, 3] / P1[0, 0]
    if not b > 0:
        raise DatasetError(f"{path}: baseline -P1[0,3]/P1[0,0] = {b:.6g} m, expected > 0")
    return P0, float(b)


def kitti_times_ns(path: str | Path, n: int) -> np.ndarray:
    """The first ``n`` stamps of a KITTI ``times.txt`` (seconds, one per image) as integer ns: the
    dataset time a replay stamps its frames (and its TUM trajectory) with."""
    path = Path(path)
    try:
        t = np.loadtxt(path, dtype=float, ndmin=1)
    except ValueError as exc:
        raise DatasetError(f"{path}: expected one time in seconds per line ({exc})") from None
    if t.ndim != 1 or t.shape[0] < n:
        raise DatasetError(f"{path}: expected {n} stamps (one per image), got {t.shape[0] if t.ndim == 1 else t.shape}")
    # seconds with 6 decimals in KITTI: round to whole microseconds before converting to ns
    t_ns = np.round(t[:n] * 1e6).astype(np.int64) * 1000
    if np.any(np.diff(t_ns) <= 0):
        raise DatasetError(f"{path}: stamps are not strictly increasing")
    return t_ns


def kitti_pose_rows(rows: np.ndarray) -> np.ndarray:
    """Rows of 12 numbers (a KITTI pose file: row-major 3×4 [R|t]) -> (N, 4, 4) poses, each R
    projected to the nearest rotation (SVD). KITTI prints 7 significant digits, so its R are
    orthonormal to ~1e-7 only, and the trace-based angle of a frame-to-frame rotation of 0.05°
    read 0.03° more from that alone (rpe_rot_deg 0.0706° instead of evo's 0.0697° on kitti-seq1)."""
    a = np.asarray(rows, dtype=float).reshape(-1, 3, 4)
    U, _, Vt = np.linalg.svd(a[:, :, :3])
    D = np.ones((len(a), 3))
    D[:, 2] = np.sign(np.linalg.det(U @ Vt))
    T = np.tile(np.eye(4), (len(a), 1, 1))
    T[:, :3, :3] = (U * D[:, None, :]) @ Vt
    T[:, :3, 3] = a[:, :, 3]
    return T


def kitti_truth_to_robot(T_C0_C: np.ndarray, baseline_m: float) -> np.ndarray:
    """KITTI left-camera poses (..., 4, 4), optical frame -> robot-frame poses T_R0_R (FRD, baseline centre).

    ``T_optical_to_robot`` re-expresses both sides in FRD axes (docs/interfaces.md §1.3); the robot
    origin is the baseline centre, b/2 to the right of the left camera: with S the shift
    x_R = x_Rleft - (0, b/2, 0), T_R0_R = S T_Rl0_Rl S⁻¹.
    """
    S = se3(np.eye(3), np.array([0.0, -baseline_m / 2.0, 0.0]))
    return S @ T_optical_to_robot(T_C0_C) @ se3_inverse(S)


class KittiCamera(_ImageDatasetCamera):
    """KITTI odometry layout: image_l|image_0/, image_r|image_1/, calib.txt, optional times.txt and poses.txt."""

    def __init__(self, url: str, **options: Any) -> None:
        root, q = _split_url(url, "kitti")
        opts = {**q, **options}
        replay = ReplayOptions.pop_from(opts)
        _reject_unknown(url, opts)
        if not root.is_dir():
            raise DatasetError(f"{url!r}: {root} is not a directory (expected a KITTI odometry sequence folder)")
        pairs = [("image_l", "image_r"), ("image_0", "image_1")]
        for ln, rn in pairs:
            if (root / ln).is_dir() and (root / rn).is_dir():
                break
        else:
            raise DatasetError(f"{root}: expected image_l/ + image_r/ or image_0/ + image_1/ (KITTI odometry layout)")
        lefts = sorted(p for p in (root / ln).iterdir() if p.suffix.lower() == ".png")
        if not lefts:
            raise DatasetError(f"{root / ln}: expected NNNNNN.png images, found none")
        calib = root / "calib.txt"
        if not calib.is_file():
            raise DatasetError(f"{root}: expected calib.txt with P0/P1 (KITTI odometry layout)")
        first = _read_gray(lefts[0])
        if first is None:
            raise DatasetError(f"{lefts[0]}: not a readable 8-bit grey image")
        self.root = root
        self.model = _kitti_calib(calib, (first.shape[1], first.shape[0]))
        n = len(lefts)
        times_ns = self._times(root / "times.txt", n)
        truth = self._poses(root / "poses.txt", n, self.model.baseline_m)
        entries = [
            FrameEntry(int(times_ns[i]), i, lefts[i], root / rn / lefts[i].name, None if truth is None else truth[i])
            for i in range(n)
        ]
        missing = sum(not e.right.is_file() for e in entries)
        super().__init__(url, [e for e in entries if e.right.is_file()], replay)
        self._stats["missing_files"] = missing
        logger.info("%s: %d KITTI pairs (%d selected), %s", url, n, len(self.entries), self.model)

    @staticmethod
    def _times(path: Path, n: int) -> np.ndarray:
        if not path.is_file():
            return np.arange(n, dtype=np.int64) * KITTI_DT_NS
        return kitti_times_ns(path, n)

    @staticmethod
    def _poses(path: Path, n: int, b: float) -> np.ndarray | None:
        if not path.is_file():
            return None
        rows = np.loadtxt(path, dtype=float, ndmin=2)
        if rows.shape[1] != 12 or rows.shape[0] < n:
            raise DatasetError(f"{path}: expected {n} rows of 12 numbers (3x4 [R|t]), got {rows.shape}")
        T = kitti_pose_rows(rows[:n])
        # KITTI's frame 0 is the identity already; re-anchor anyway so world = robot at frame 0
        T = se3_inverse(T[0]) @ T
        return kitti_truth_to_robot(T, b)

    def rectified_model(self) -> RectifiedStereo:
        return self.model


# --------------------------------------------------------------------------------------------
# EuRoC / ASL


def _read_sensor_yaml(path: Path) -> dict[str, Any]:
    import yaml

    if not path.is_file():
        raise DatasetError(f"{path}: expected an ASL camera sensor.yaml (intrinsics, distortion, T_BS)")
    text = path.read_text()
    # OpenCV-style YAML starts with a "%YAML:1.0" directive that PyYAML rejects
    text = re.sub(r"^%YAML:?1\.0\s*$", "", text, flags=re.M)
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise DatasetError(f"{path}: not valid YAML: {exc}") from None
    for key in ("intrinsics", "distortion_coefficients", "T_BS", "resolution"):
        if not isinstance(data, dict) or key not in data:
            raise DatasetError(f"{path}: expected key {key!r} (ASL camera sensor.yaml)")
    model = data.get("distortion_model", "radial-tangential")
    if model not in ("radial-tangential", "radtan"):
        raise DatasetError(f"{path}: distortion_model {model!r} not supported, expected radial-tangential")
    return data


def _euroc_list(cam_dir: Path) -> list[tuple[int, Path]]:
    csv = cam_dir / "data.csv"
    if not csv.is_file():
        raise DatasetError(f"{cam_dir}: expected data.csv (ASL layout: timestamp [ns], filename)")
    out = []
    for k, line in enumerate(csv.read_text().splitlines()):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = [p.strip() for p in line.split(",")]
        if len(parts) < 2 or not parts[0].isdigit():
            raise DatasetError(f"{csv}:{k + 1}: expected 'timestamp_ns,filename', got {line!r}")
        out.append((int(parts[0]), cam_dir / "data" / parts[1]))
    return out


def read_euroc_truth(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """ORB-SLAM3's EuRoC left-camera ground truth -> (t_ns (N,), T_world_cam0 (N, 4, 4)).

    Rows are ``t_ns, x, y, z, qw, qx, qy, qz`` (stamps may carry a ``.000`` fraction: parsed as
    integers, never through float, which would lose the last digits of a 19-digit stamp).
    Quirk, checked against the EuRoC Vicon body ground truth at the same stamp composed with
    ``T_BS`` of cam0 and against the IMU's gravity direction: the stored quaternion is the
    **conjugate** of the camera-to-world rotation (the position is the camera centre in world),
    so R_world_cam = quat_to_R(q)ᵀ.
    """
    ts: list[int] = []
    rows: list[list[float]] = []
    for k, line in enumerate(path.read_text().splitlines()):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        if len(parts) != 8:
            raise DatasetError(f"{path}:{k + 1}: expected 8 values (t_ns, x, y, z, qw, qx, qy, qz), got {len(parts)}")
        ts.append(int(parts[0].split(".")[0]))
        rows.append([float(v) for v in parts[1:]])
    a = np.array(rows, dtype=float).reshape(-1, 7)
    R = np.swapaxes(quat_to_R(a[:, 3:7]), -1, -2)
    return np.array(ts, dtype=np.int64), se3(R, a[:, :3])


class EurocCamera(_ImageDatasetCamera):
    """ASL/EuRoC layout: ``mav0/cam0|cam1/{data.csv, data/*.png, sensor.yaml}``; raw images rectified here."""

    def __init__(self, url: str, calibration: StereoCalibration | None = None, **options: Any) -> None:
        root, q = _split_url(url, "euroc")
        opts = {**q, **options}
        replay = ReplayOptions.pop_from(opts)
        alpha = _as_float("alpha", opts.pop("alpha", 0.0), -1.0)
        tol_ns = _as_int("pair_tolerance_ns", opts.pop("pair_tolerance_ns", 1_000_000), 0)
        _reject_unknown(url, opts, ("alpha", "pair_tolerance_ns"))
        if not root.is_dir():
            raise DatasetError(f"{url!r}: {root} is not a directory (expected an ASL/EuRoC folder with mav0/)")
        mav = root / "mav0" if (root / "mav0").is_dir() else root
        for cam in ("cam0", "cam1"):
            if not (mav / cam).is_dir():
                raise DatasetError(f"{mav}: expected {cam}/ (ASL layout mav0/cam0, mav0/cam1)")
        s0, s1 = _read_sensor_yaml(mav / "cam0" / "sensor.yaml"), _read_sensor_yaml(mav / "cam1" / "sensor.yaml")
        if calibration is None:
            self.calibration = self._calibration(s0, s1, str(mav))
            self.rectifier = Rectifier(self.calibration, alpha=alpha)
        else:  # the user's calibration file (camera.calibration) instead of sensor.yaml's
            size = (int(s0["resolution"][0]), int(s0["resolution"][1]))
            check_calibration_size(url, calibration, size, f"calibrate at the images' size ({mav}/cam0/sensor.yaml)")
            self.calibration = calibration
            self.rectifier = user_rectifier(calibration, alpha)
        self.model = self.rectifier.model
        self._T_R_C0 = T_robot_leftraw(self.rectifier.rectification.R1, self.model.baseline_m)

        left, right = _euroc_list(mav / "cam0"), _euroc_list(mav / "cam1")
        missing = sum(not p.is_file() for _, p in left) + sum(not p.is_file() for _, p in right)
        left = [(t, p) for t, p in left if p.is_file()]
        right = [(t, p) for t, p in right if p.is_file()]
        pairs = self._pair(left, right, tol_ns)
        truth = self._truth(root, [t for t, _, _ in pairs])
        entries = [FrameEntry(t, i, lp, rp, truth.get(t)) for i, (t, lp, rp) in enumerate(pairs)]
        super().__init__(url, entries, replay)
        self._stats["missing_files"] = missing
        self._stats["unpaired"] = len(left) + len(right) - 2 * len(pairs)
        logger.info(
            "%s: %d pairs (%d selected), %d listed files missing, %d unpaired, truth for %d; %s",
            url, len(pairs), len(self.entries), missing, self._stats["unpaired"], len(truth), self.model,
        )  # fmt: skip

    @staticmethod
    def _calibration(s0: dict[str, Any], s1: dict[str, Any], where: str) -> Any:
        def K(s: dict[str, Any]) -> np.ndarray:
            fu, fv, cu, cv = (float(v) for v in s["intrinsics"])
            return np.array([[fu, 0.0, cu], [0.0, fv, cv], [0.0, 0.0, 1.0]])

        def T_BS(s: dict[str, Any]) -> np.ndarray:
            T = np.asarray(s["T_BS"]["data"] if isinstance(s["T_BS"], dict) else s["T_BS"], dtype=float)
            if T.size != 16:
                raise DatasetError(f"{where}: T_BS must have 16 values, got {T.size}")
            return T.reshape(4, 4)

        if tuple(s0["resolution"]) != tuple(s1["resolution"]):
            raise DatasetError(f"{where}: cam0/cam1 resolutions differ: {s0['resolution']} vs {s1['resolution']}")
        # x_cam1 = T_C1_C0 x_cam0 with T_Ci = T_B_Ci (T_BS): T_C1_C0 = T_BS1⁻¹ T_BS0
        T_10 = se3_inverse(T_BS(s1)) @ T_BS(s0)
        return StereoCalibration(
            K_left=K(s0),
            D_left=np.asarray(s0["distortion_coefficients"], dtype=float),
            K_right=K(s1),
            D_right=np.asarray(s1["distortion_coefficients"], dtype=float),
            R=T_10[:3, :3],
            T=T_10[:3, 3],
            image_size=(int(s0["resolution"][0]), int(s0["resolution"][1])),
            distortion_model="radtan",
            source=f"euroc sensor.yaml ({where})",
        )

    @staticmethod
    def _pair(left: list[tuple[int, Path]], right: list[tuple[int, Path]], tol_ns: int) -> list[tuple[int, Path, Path]]:
        """Pair each left stamp with the nearest right stamp within ``tol_ns``; unmatched rows drop."""
        if not left or not right:
            return []
        rt = np.array([t for t, _ in right], dtype=np.int64)
        order = np.argsort(rt)
        rt = rt[order]
        out, used = [], set()
        for t, lp in sorted(left):
            k = int(np.searchsorted(rt, t))
            cands = [j for j in (k - 1, k) if 0 <= j < rt.size]
            j = min(cands, key=lambda j: abs(int(rt[j]) - t))
            if abs(int(rt[j]) - t) <= tol_ns and j not in used:
                used.add(j)
                out.append((t, lp, right[int(order[j])][1]))
        return out

    def _truth(self, root: Path, stamps: list[int]) -> dict[int, np.ndarray]:
        path = root / "groundtruth_orbslam3" / "V101_GT_left_cam.txt"
        if not path.is_file():
            cands = sorted((root / "groundtruth_orbslam3").glob("*_left_cam.txt")) if root.is_dir() else []
            if not cands:
                return {}
            path = cands[0]
        t_gt, T_W_C = read_euroc_truth(path)
        if t_gt.size == 0:
            return {}
        # camera stamps and ground-truth stamps coincide in this file; accept 1 ms of jitter
        idx = np.searchsorted(t_gt, stamps)
        found: dict[int, np.ndarray] = {}
        for t, k in zip(stamps, idx):
            for j in (k - 1, k):
                if 0 <= j < t_gt.size and abs(int(t_gt[j]) - t) <= 1_000_000:
                    found[t] = T_W_C[j]
                    break
        if not found:
            return {}
        # world = robot frame at the first frame with truth: T_R0_R = T_R_C (T_W_C0⁻¹ T_W_C) T_R_C⁻¹
        first = min(found)
        T_C0w = se3_inverse(found[first])
        A, Ainv = self._T_R_C0, se3_inverse(self._T_R_C0)
        return {t: A @ (T_C0w @ T) @ Ainv for t, T in found.items()}

    def _rectify(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.rectifier.rectify(left, right)  # type: ignore[no-any-return]

    def rectified_model(self) -> RectifiedStereo:
        return self.model  # type: ignore[no-any-return]


# --------------------------------------------------------------------------------------------
# Vehicle links for replay


GT_SIGMA_VEL_MPS = 0.05  # default white noise on synthesised velocities (per axis, per sample)
GT_SIGMA_RATE_RADPS = 0.005  # default white noise on synthesised body rates


@dataclass(frozen=True, slots=True)
class GtOdometryNoise:
    """Noise added to ground-truth-synthesised odometry (white, per sample, robot frame FRD)."""

    sigma_vel_mps: float = GT_SIGMA_VEL_MPS
    sigma_rate_radps: float = GT_SIGMA_RATE_RADPS


def odometry_from_truth(
    truth: list[tuple[int, np.ndarray]], rng: np.random.Generator | None, noise: GtOdometryNoise = GtOdometryNoise()
) -> list[Odometry]:
    """Velocities from consecutive ground-truth poses, one sample per interval (experiments only).

    For poses T_k, T_{k+1} (world <- robot) at t_k < t_{k+1}: ΔT = T_k⁻¹ T_{k+1} (robot frame at
    t_k), v = Δp / Δt and ω = log(ΔR) / Δt (constant body rates over the interval). The sample
    is stamped t_k and holds over [t_k, t_{k+1}) (zero-order hold, like a wheel-speed message).
    Gaussian noise of ``noise`` is added when ``rng`` is given. ``source="gt-synthetic"``.
    """
    out: list[Odometry] = []
    for (t0, T0), (t1, T1) in itertools.pairwise(truth):
        dt = (t1 - t0) * 1e-9
        if dt <= 0:
            continue
        dT = se3_inverse(T0) @ T1
        v = dT[:3, 3] / dt
        w = so3_log(dT[:3, :3]) / dt
        if rng is not None:
            v = v + rng.normal(0.0, noise.sigma_vel_mps, 3)
            w = w + rng.normal(0.0, noise.sigma_rate_radps, 3)
        out.append(Odometry(int(t0), np.asarray(v, float), np.asarray(w, float), source="gt-synthetic"))
    return out


class DatasetVehicle(Driver):
    """A :class:`drivers.VehicleLink` for replay: visual only by default, or a list of samples.

    Visual only (``samples=[]``) means **no odometry at all**: ``odometry()`` returns at once and
    the pipeline predicts with its constant-velocity model. It takes no pose (``autopilot`` is
    None); ``stats()["poses_sent"]`` stays 0 for the health output's shape.
    """

    def __init__(self, url: str, samples: list[Odometry] | None = None, realtime: bool = False) -> None:
        self.url = url
        self.samples = samples or []
        self.realtime = realtime
        # what the odometry is: "none" (visual only), else the samples' source ("oxts", "gt-synthetic", ...)
        self.odometry_source = self.samples[0].source if self.samples else "none"
        self._closed = False
        self._stats: dict[str, Any] = {"odometry": 0, "poses_sent": 0, "mode": "replay" if samples else "visual-only"}

    def odometry(self, timeout_s: float = 1.0) -> Iterator[Odometry]:
        pacer = _Pacer(self.realtime, 1.0)
        for s in self.samples:
            if self._closed:
                return
            pacer.wait(s.t_ns)
            self._stats["odometry"] += 1
            yield s

    @property
    def autopilot(self) -> AutopilotLink | None:
        return None

    def close(self) -> None:
        self._closed = True

    def stats(self) -> dict[str, Any]:
        return dict(self._stats)


def _dataset_vehicle(camera: _ImageDatasetCamera, url: str, opts: dict[str, Any]) -> DatasetVehicle:
    gt = _as_bool("gt_odometry", opts.pop("gt_odometry", False))
    seed = _as_int("seed", opts.pop("seed", 0))
    noise = GtOdometryNoise(
        _as_float("sigma_vel_mps", opts.pop("sigma_vel_mps", GT_SIGMA_VEL_MPS), 0.0),
        _as_float("sigma_rate_radps", opts.pop("sigma_rate_radps", GT_SIGMA_RATE_RADPS), 0.0),
    )
    if not gt:
        return DatasetVehicle(url)
    truth = camera.truth()
    if len(truth) < 2:
        raise DatasetError(f"{url!r}: gt_odometry needs ground truth for at least 2 frames, found {len(truth)}")
    logger.warning("%s: odometry SYNTHESISED FROM GROUND TRUTH (experiments only), noise %s seed %d", url, noise, seed)
    return DatasetVehicle(url, odometry_from_truth(truth, np.random.default_rng(seed), noise), camera.replay.realtime)


_VEHICLE_KEYS = ("gt_odometry", "seed", "sigma_vel_mps", "sigma_rate_radps")
_KITTI_VEHICLE_KEYS = (*_VEHICLE_KEYS, "odometry", "oxts_sigma_vel_mps", "oxts_sigma_rate_radps")
KITTI_ODOMETRY = ("none", "oxts")  # the values of the kitti vehicle's ``odometry`` option


def _split_vehicle_options(
    url: str, scheme: str, options: dict[str, Any], keys: Sequence[str] = _VEHICLE_KEYS
) -> tuple[dict[str, Any], dict[str, Any]]:
    _, q = _split_url(url, scheme)
    merged = {**q, **options}
    veh = {k: merged.pop(k) for k in keys if k in merged}
    return merged, veh


def _kitti_recorded_vehicle(camera: KittiCamera, url: str, opts: dict[str, Any]) -> DatasetVehicle | None:
    """``odometry=oxts``: the raw drive's OXTS records (drivers.kitti_oxts) when the folder keeps
    them, cut to the selected frames' span (one record at or before the first, one at or after
    the last, so realtime pacing of frames and records starts together); None when it has none."""
    from drivers.kitti_oxts import OXTS_SIGMA_RATE_RADPS, OXTS_SIGMA_VEL_MPS, kitti_oxts_odometry

    sv = _as_float("oxts_sigma_vel_mps", opts.pop("oxts_sigma_vel_mps", OXTS_SIGMA_VEL_MPS), 1e-6)
    sr = _as_float("oxts_sigma_rate_radps", opts.pop("oxts_sigma_rate_radps", OXTS_SIGMA_RATE_RADPS), 1e-6)
    frames = [(e.seq, e.t_ns) for e in camera._all]
    samples = kitti_oxts_odometry(camera.root, camera.model.baseline_m, sv, sr, frames)
    if samples is None:
        logger.info("%s: no raw OXTS records (raw/*/oxts): no odometry, visual only", url)
        return None
    if camera.entries:
        t = np.array([o.t_ns for o in samples], dtype=np.int64)
        first = max(int(np.searchsorted(t, camera.entries[0].t_ns, side="right")) - 1, 0)
        last = int(np.searchsorted(t, camera.entries[-1].t_ns, side="left"))
        samples = samples[first : last + 1]
    return DatasetVehicle(url, samples, camera.replay.realtime)


# --------------------------------------------------------------------------------------------
# Factories named in drivers.__init__ and the cameras' registrations below


def open_kitti(url: str, **options: Any) -> KittiCamera:
    """``kitti://DIR[?start=&stop=&stride=&realtime=]`` -> a replaying :class:`KittiCamera`."""
    return KittiCamera(url, **options)


def open_euroc(url: str, **options: Any) -> EurocCamera:
    """``euroc://DIR[?start=&stop=&stride=&realtime=&alpha=]`` -> a replaying :class:`EurocCamera`."""
    return EurocCamera(url, **options)


def open_kitti_vehicle(url: str, **options: Any) -> DatasetVehicle:
    """Vehicle for ``kitti://DIR``: visual only (``odometry=none``, the default); ``odometry=oxts``:
    the recorded OXTS odometry of a KITTI raw folder when it keeps it (``oxts_sigma_vel_mps``,
    ``oxts_sigma_rate_radps`` state its noise), else visual only; or ``gt_odometry=True`` (+ ``seed``,
    sigmas) for experiments."""
    cam_opts, veh = _split_vehicle_options(url, "kitti", options, _KITTI_VEHICLE_KEYS)
    camera = KittiCamera(url.split("?")[0], **cam_opts)
    mode = str(veh.pop("odometry", "none")).lower()
    if mode not in KITTI_ODOMETRY:
        raise DriverError(f"{url!r}: option odometry: expected one of {list(KITTI_ODOMETRY)}, got {mode!r}")
    if mode == "oxts":
        if _as_bool("gt_odometry", veh.get("gt_odometry", False)):
            raise DriverError(f"{url!r}: odometry=oxts and gt_odometry both given; choose one")
        recorded = _kitti_recorded_vehicle(camera, url, veh)
        if recorded is not None:
            return recorded
    for k in ("oxts_sigma_vel_mps", "oxts_sigma_rate_radps"):
        veh.pop(k, None)
    return _dataset_vehicle(camera, url, veh)


def open_euroc_vehicle(url: str, **options: Any) -> DatasetVehicle:
    """Vehicle for ``euroc://DIR``: visual only, or ``gt_odometry=True`` for experiments."""
    cam_opts, veh = _split_vehicle_options(url, "euroc", options)
    return _dataset_vehicle(EurocCamera(url.split("?")[0], **cam_opts), url, veh)


# --------------------------------------------------------------------------------------------
# URL checks (drivers.check_camera_url / check_vehicle_url): the options the factories above read,
# checked as they check them, without touching the folder or the file


def _checked_replay_options(url: str, scheme: str, options: dict[str, Any]) -> dict[str, Any]:
    """The URL's and ``options``' keys after the replay keys (validated) are taken out."""
    _, q = _split_url(url, scheme)
    opts = {**q, **options}
    ReplayOptions.pop_from(opts)
    return opts


def check_kitti_url(url: str, **options: Any) -> None:
    _reject_unknown(url, _checked_replay_options(url, "kitti", options))


def check_euroc_url(url: str, calibration: StereoCalibration | None = None, **options: Any) -> None:
    opts = _checked_replay_options(url, "euroc", options)  # any calibration: its size is checked at the open
    _as_float("alpha", opts.pop("alpha", 0.0), -1.0)
    _as_int("pair_tolerance_ns", opts.pop("pair_tolerance_ns", 1_000_000), 0)
    _reject_unknown(url, opts, ("alpha", "pair_tolerance_ns"))


def check_mcap_url(url: str, **options: Any) -> None:
    _reject_unknown(url, _checked_replay_options(url, "mcap", options))


def _check_vehicle_options(opts: dict[str, Any]) -> None:
    """The keys :func:`_dataset_vehicle` reads."""
    _as_bool("gt_odometry", opts.pop("gt_odometry", False))
    _as_int("seed", opts.pop("seed", 0))
    _as_float("sigma_vel_mps", opts.pop("sigma_vel_mps", GT_SIGMA_VEL_MPS), 0.0)
    _as_float("sigma_rate_radps", opts.pop("sigma_rate_radps", GT_SIGMA_RATE_RADPS), 0.0)


def check_kitti_vehicle_url(url: str, **options: Any) -> None:
    cam_opts, veh = _split_vehicle_options(url, "kitti", options, _KITTI_VEHICLE_KEYS)
    check_kitti_url(url.split("?")[0], **cam_opts)
    mode = str(veh.pop("odometry", "none")).lower()
    if mode not in KITTI_ODOMETRY:
        raise DriverError(f"{url!r}: option odometry: expected one of {list(KITTI_ODOMETRY)}, got {mode!r}")
    if mode == "oxts" and _as_bool("gt_odometry", veh.get("gt_odometry", False)):
        raise DriverError(f"{url!r}: odometry=oxts and gt_odometry both given; choose one")
    for k in ("oxts_sigma_vel_mps", "oxts_sigma_rate_radps"):
        if k in veh:
            _as_float(k, veh.pop(k), 1e-6)
    _check_vehicle_options(veh)


def check_euroc_vehicle_url(url: str, **options: Any) -> None:
    cam_opts, veh = _split_vehicle_options(url, "euroc", options)
    check_euroc_url(url.split("?")[0], **cam_opts)
    _check_vehicle_options(veh)


def check_mcap_vehicle_url(url: str, **options: Any) -> None:
    _, q = _split_url(url, "mcap")
    opts = {**q, **options}
    _as_bool("realtime", opts.pop("realtime", False))
    _reject_unknown(str(url), opts)


# --------------------------------------------------------------------------------------------
# MCAP recordings (robotd.formats.record)


class McapCamera(Driver):
    """Replay a ``robotd record`` session: the recorded frames, same order and stamps, every time.

    (``raw_calibration`` stays None: the recording's own calibration is what ``rectified_model`` gives.)
    The stamps are the recording host's monotonic clock of then, not this host's now
    (``host_clock`` False).

    Options: start/stop/stride (over the recorded frames), realtime/speed. ``recorded_odometry()``
    and :func:`open_mcap_vehicle` give the recorded odometry; :meth:`events` gives frames and
    odometry interleaved exactly as recorded (what a deterministic single-thread replay wants).
    """

    host_clock = False

    def __init__(self, url: str | Path, **options: Any) -> None:
        from robotd.core.errors import PersistenceError
        from robotd.formats.record import SessionReader

        path, q = _split_url(url, "mcap")
        opts = {**q, **options}
        self.replay = ReplayOptions.pop_from(opts)
        self.url = str(url)
        _reject_unknown(self.url, opts)
        if not path.is_file():
            tmp = path.with_name(path.name + ".tmp")
            if tmp.is_file():  # the recorder was killed before it could finish this file
                raise DatasetError(
                    f"{url!r}: recording {path} not found, but {tmp.name} is there: an interrupted recording "
                    f"(robotd record did not finish); replay it as it is: robotd replay {tmp}"
                )
            raise DatasetError(f"{url!r}: recording {path} not found (expected a .mcap written by robotd record)")
        try:
            self.reader = SessionReader(path)
        except PersistenceError as exc:
            raise DatasetError(str(exc)) from None
        self.meta = self.reader.meta
        self.raw_calibration: dict[str, Any] | None = None
        self.fps: float | None = None
        self._closed = False
        self._stats: dict[str, Any] = {"frames": 0, "drops": 0, "gaps": 0, "read_errors": 0}

    def close(self) -> None:
        self._closed = True

    def stats(self) -> dict[str, Any]:
        return dict(self._stats)

    def rectified_model(self) -> RectifiedStereo:
        return self.reader.calibration

    def _selected(self, k: int) -> bool:
        r = self.replay
        return k >= r.start and (r.stop is None or k < r.stop) and (k - r.start) % r.stride == 0 and not r.dropped(k)

    def events(self) -> Iterator[StereoFrame | Odometry]:
        """Frames (selected) and all odometry, interleaved in recorded order, paced if realtime."""
        from robotd.formats.record import TOPIC_FRAME, TOPIC_ODOMETRY

        pacer = _Pacer(self.replay.realtime, self.replay.speed)
        k = -1
        for e in self.reader.events((TOPIC_FRAME, TOPIC_ODOMETRY)):
            if self._closed:
                return
            if isinstance(e, StereoFrame):
                k += 1
                if self.replay.stop is not None and k >= self.replay.stop:
                    return
                if not self._selected(k):
                    continue
                pacer.wait(e.t_ns)
                self._stats["frames"] += 1
                yield e
            elif isinstance(e, Odometry):
                yield e
        if self.reader.stopped and self.reader.frames_read:  # a damaged or interrupted recording: say where
            logger.info("%s: the recording ends early, %s", self.url, self.reader.stopped)

    def frames(self, timeout_s: float = 1.0) -> Iterator[StereoFrame]:
        for e in self.events():
            if isinstance(e, StereoFrame):
                yield e

    def recording_status(self) -> dict[str, Any]:
        """After the frames were read: closed cleanly or not, and where reading stopped early
        (robotd.formats.record.SessionReader.status)."""
        return self.reader.status()

    def recorded_odometry(self) -> list[Odometry]:
        return list(self.reader.odometry())

    def recorded_poses(self) -> list[PoseEstimate]:
        return list(self.reader.poses())


def open_mcap(url: str | Path, **options: Any) -> McapCamera:
    """``mcap://PATH`` or a bare ``PATH.mcap`` -> a replaying :class:`McapCamera`."""
    return McapCamera(url, **options)


def open_mcap_vehicle(url: str | Path, **options: Any) -> DatasetVehicle:
    """The recorded odometry of ``mcap://PATH`` as a VehicleLink (``realtime`` paces it)."""
    path, q = _split_url(url, "mcap")
    opts = {**q, **options}
    realtime = _as_bool("realtime", opts.pop("realtime", False))
    _reject_unknown(str(url), opts)
    cam = McapCamera(path)
    samples = cam.recorded_odometry()
    return DatasetVehicle(str(url), samples, realtime)


# --------------------------------------------------------------------------------------------
# The cameras' drivers (registered with their kinds in drivers.cameras)


def is_kitti_folder(p: Path) -> bool:
    """A KITTI sequence: ``calib.txt`` and ``image_0/`` (odometry) or ``image_l/`` (raw, rectified)."""
    return (p / "calib.txt").is_file() and ((p / "image_0").is_dir() or (p / "image_l").is_dir())


def is_euroc_folder(p: Path) -> bool:
    """An EuRoC sequence: ``mav0/`` (or its ``cam0/`` and ``cam1/`` directly)."""
    mav = p / "mav0" if (p / "mav0").is_dir() else p
    return (mav / "cam0").is_dir() and (mav / "cam1").is_dir()


class _ImageDatasetDriver(CameraBase):
    """A folder of images replayed: its selected frames listed when opened."""

    def frame_total(self, camera: Any) -> int | None:
        return len(camera.entries)  # the selected frames, listed when opened


class KittiCameraDriver(_ImageDatasetDriver):
    """``kitti://DIR``; its OXTS odometry when the dataset's is asked for."""

    def open(self, url: str, **options: Any) -> KittiCamera:
        return open_kitti(url, **options)

    def check_url(self, url: str, **options: Any) -> None:
        check_kitti_url(url, **options)

    def claims_folder(self, path: Path) -> bool:
        return is_kitti_folder(path)

    def replay_vehicle(self, source: str, url: str, odometry: DatasetOdometry | None) -> str | None:
        """With the dataset's odometry asked for: the raw drive's OXTS records (when the folder
        keeps them; else the vehicle is visual only) with the configured noise."""
        if odometry is None:
            return None
        sep = "&" if "?" in url else "?"
        return (
            f"{url}{sep}odometry=oxts&oxts_sigma_vel_mps={odometry.sigma_vel_mps!r}"
            f"&oxts_sigma_rate_radps={odometry.sigma_rate_radps!r}"
        )


class EurocCameraDriver(_ImageDatasetDriver):
    """``euroc://DIR``: visual only."""

    def open(self, url: str, **options: Any) -> EurocCamera:
        return open_euroc(url, **options)

    def check_url(self, url: str, **options: Any) -> None:
        check_euroc_url(url, **options)

    def claims_folder(self, path: Path) -> bool:
        return is_euroc_folder(path)


class RecordingCameraDriver(CameraBase):
    """A ``robotd record`` session: its frames, and always its recorded odometry."""

    def open(self, url: str, **options: Any) -> McapCamera:
        return open_mcap(url, **options)

    def check_url(self, url: str, **options: Any) -> None:
        check_mcap_url(url, **options)

    def frame_total(self, camera: Any) -> int | None:
        """Selected frames, from the MCAP summary's message counts (no message is read; None for
        a file without a summary, e.g. an interrupted recording)."""
        n = camera.reader.frame_count()
        if n is None:
            return None
        sel = camera.replay
        stop = n if sel.stop is None else min(sel.stop, n)
        return len(sel.select(stop))

    def replay_vehicle(self, source: str, url: str, odometry: DatasetOdometry | None) -> str | None:
        """The recorded odometry, unpaced (the replay feeds it by the frames' stamps)."""
        return source if "://" in source else f"mcap://{source}"

    def status(self, camera: Any) -> dict[str, Any] | None:
        return camera.recording_status()  # type: ignore[no-any-return]


KITTI_CAMERA = KittiCameraDriver()
EUROC_CAMERA = EurocCameraDriver()
RECORDING_CAMERA = RecordingCameraDriver()
