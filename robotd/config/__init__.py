"""Configuration: defaults in code as a tree of frozen dataclasses; TOML files only override.

An unknown key, a wrong type or an out-of-range value fails with the key's dotted path, e.g.
``slam.n_particles: expected an integer >= 1, got 0 (in /etc/robotd/robotd.toml)``.
``robotd print-config [--config FILE]`` prints the resolved tree as TOML.

Each field may carry ``metadata``: ``min``/``max`` (inclusive bounds), ``choices`` and ``doc``.
Calibration is data and lives in its own file (docs/calibration.md), not here.

The package: this module (the sections and the loader: ``from robotd.config import load_config``),
bounds.py (the bounds derived from this machine and the frame deadline) and params.py (the
configuration turned into the core's parameter objects).
"""

from __future__ import annotations

import dataclasses
import math
import re
import tomllib
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from robotd.config.bounds import Sizing, check_bounds
from robotd.core.choices import DETECTORS, MEASUREMENTS, OUTLIER_METHODS
from robotd.core.errors import ConfigError, show_value
from robotd.slam.factory import ESTIMATORS


def _f(default: Any, doc: str = "", **meta: Any) -> Any:
    """A dataclass field with a default and validation metadata."""
    if isinstance(default, list | dict):
        return field(default_factory=lambda: type(default)(default), metadata={"doc": doc, **meta})
    return field(default=default, metadata={"doc": doc, **meta})


@dataclass(frozen=True)
class RobotConfig:
    id: str = _f(
        "r1",
        "robot id: a valid ROS 2 name chunk, used in every Zenoh key robotd/<id>/…",
        pattern=r"[A-Za-z][A-Za-z0-9_]*",
    )
    seed: int = _f(1, "seed of every random generator; logged at start so a run can be replayed", min=0)


@dataclass(frozen=True)
class CameraConfig:
    url: str = _f("sim://", "stereo source: sim://, oak://[device-id], kitti://DIR, euroc://DIR, FILE.mcap")
    calibration: str = _f(
        "",
        "calibration file (Kalibr-style camchain YAML, robotd-calib) to rectify with instead of the camera's own:"
        " oak:// (rectify=host) and euroc:// take it, sim://, kitti:// and recordings refuse it;"
        " empty: the source's own",
    )
    queue_size: int = _f(2, "frames buffered between the camera thread and SLAM (drop-oldest)", min=1, max=64)
    exposure_ms: float = _f(
        0.0,
        "the exposure assumed when the source reports none (datasets; oak:// and sim:// report theirs): it"
        " sizes the motion blur the measurements' model allows for (frontend.motion_blur); 0 = none",
        min=0.0,
        max=1000.0,
    )


@dataclass(frozen=True)
class VehicleConfig:
    url: str = _f("sim://", "vehicle link: sim://, none://, serial:///dev/ttyX?baud=…, mavlink+udp://HOST:PORT")
    queue_size: int = _f(256, "odometry samples buffered (drop-oldest)", min=1, max=100000)
    max_gap_s: float = _f(0.5, "odometry older than this at a frame's time counts as missing", min=0.0)
    max_speed_mps: float = _f(30.0, "odometry faster than this is refused (counted, never integrated)", min=0.1)
    max_accel_mps2: float = _f(50.0, "odometry whose speed changes faster than this is refused", min=0.1)
    max_rate_radps: float = _f(10.0, "odometry turning faster than this is refused", min=0.01)
    max_future_s: float = _f(0.5, "odometry stamped this far after the host's clock is refused", min=0.0)
    max_tilt_deg: float = _f(
        60.0,
        "a measured direction of gravity tilted further than this from the robot's vertical is refused (counted,"
        " never fused): no rover drives there, and a glitch held for a second would otherwise be taken",
        min=5.0,
        max=85.0,
    )


@dataclass(frozen=True)
class FrontendConfig:
    detector: str = _f("orb", "feature detector", choices=DETECTORS)
    max_features: int = _f(1000, "per-image feature cap", min=10, max=20000)
    grid_rows: int = _f(4, "grid bucketing rows (spread features evenly)", min=1, max=64)
    grid_cols: int = _f(8, "grid bucketing columns", min=1, max=64)
    bucketing: bool = _f(True, "spread features evenly over the image")
    depth_min_m: float = _f(0.3, "nearest landmark depth (sets d_max = f·b / depth_min)", min=0.01)
    disparity_min_px: float = _f(
        2.0,
        "smallest disparity accepted (far limit; far points hold the rotation, and the PnP's two-view"
        " adjustment keeps them from shrinking the translation: docs/frontend.md)",
        min=0.5,
    )
    row_tolerance_px: float = _f(2.0, "|y_L - y_R| allowed in stereo matching", min=0.1, max=20.0)
    sigma_x_px: float = _f(0.5, "pixel noise of columns (measurement covariance)", min=0.01, max=10.0)
    sigma_y_px: float = _f(0.3535533905932738, "pixel noise of the mean row", min=0.01, max=10.0)
    cov_inflation: float = _f(1.0, "multiplier on the measurement covariance", min=0.1, max=100.0)
    cov_at: str = _f(
        "predicted",
        "re-observations' covariance at the filter's predicted point (unbiased weights) or at the measured pixels"
        " (slam.measurement = cartesian only: the pixel model's noise is constant)",
        choices=("predicted", "measured"),
    )
    debias_depth: bool = _f(
        False,
        "remove the second-order triangulation bias (depth too far by σ_d²/d²) for the pixel model's σ_d"
        " (off: real matches scatter a tenth of it, docs/frontend.md)",
    )
    debias_limits: bool = _f(
        False,
        "correct disparities near the accepted limits for the gate's selection (a point near the far limit is"
        " kept only when its noise made it look nearer); needs the true disparity noise, sigma_x_px·√2 (off: it"
        " helps the landmark simulator, not yet real or rendered images, docs/frontend.md)",
    )
    outliers: str = _f("similarity_mahalanobis", "outlier detector", choices=OUTLIER_METHODS)
    consensus_confidence: float = _f(
        0.99, "χ² level of the Mahalanobis consensus (0.99: 11.345 in 3D)", min=0.5, max=0.99999
    )
    ransac_max_iterations: int = _f(500, "RANSAC iteration cap", min=1, max=100000)
    min_inliers: int = _f(6, "fewer inliers: no correspondence accepted this frame", min=3)
    restrict_to_fov: bool = _f(True, "match only landmarks predicted inside the field of view")
    guided_matching: bool = _f(
        True, "search each map landmark near its projection from the predicted pose (needs restrict_to_fov)"
    )
    guided_radius_px: float = _f(15.0, "guided matching: search radius around the prediction", min=1.0, max=500.0)
    motion: str = _f(
        "pnp",
        "visual-only motion prior: stereo PnP on pixel residuals, or the thesis's similarity RANSAC on 3-D points",
        choices=("pnp", "similarity"),
    )
    pnp_inlier_px: float = _f(2.0, "stereo PnP: reprojection error of an inlier", min=0.1, max=50.0)
    motion_blur: bool = _f(
        True,
        "with a known exposure (the frame's, else camera.exposure_ms): the streak the camera's turn draws"
        " widens the stereo points' covariance and the PnP's inlier gate (docs/frontend.md)",
    )
    exposure_estimate: bool = _f(
        True,
        "when the source reports no exposure and camera.exposure_ms is 0 (datasets): estimate it from how"
        " the frame-to-frame residuals spread with the turn rate, for the blur model (docs/frontend.md)",
    )
    pnp_two_view_iterations: int = _f(
        3,
        "stereo PnP: passes of the two-view adjustment (the motion with every inlier's position free: far"
        " points then do not shrink the translation, docs/frontend.md); 0 turns it off",
        min=0,
        max=20,
    )
    pnp_align_px: float = _f(
        1.5,
        "stereo PnP: each match's current pixels move onto the previous frame's patch (sub-pixel alignment:"
        " detected corners stick to the pixel grid, docs/frontend.md), by at most this much; 0 turns it off",
        min=0.0,
        max=5.0,
    )
    parallel_detect: bool = _f(
        True, "detect the left and right images on two threads (one thread: a steadier tail on a busy 2-core host)"
    )
    disparity_offset: str = _f(
        "online",
        "the rig's constant disparity error: estimated online from the visual motion (near points fix the"
        " translation, far ones then show the offset) and taken off every disparity, or off (docs/frontend.md)",
        choices=("online", "off"),
    )
    disparity_offset_walk_px: float = _f(
        0.01, "online disparity offset: random walk per estimated frame [px]", min=0.0, max=1.0
    )
    disparity_offset_max_sigma_px: float = _f(
        0.12,
        "online disparity offset: only matches whose disparity the sub-pixel refinement places this"
        " precisely take part [px] (docs/frontend.md)",
        min=0.01,
        max=10.0,
    )


@dataclass(frozen=True)
class SlamConfig:
    filter: str = _f("fastslam2", "estimator", choices=ESTIMATORS)  # the registered names, read live
    dim: int = _f(3, "2 (x, y, yaw) or 3 (x, y, z, roll, pitch, yaw)", choices=(2, 3))
    measurement: str = _f(
        "pixel",
        "measurement model: the landmark's pixels (x_left, x_right, y) in the rectified pair with the"
        " constant noise frontend.sigma_x_px / sigma_y_px (× cov_inflation), or the triangulated point"
        " with its first-order covariance (the thesis's)",
        choices=MEASUREMENTS,
    )
    covariance: str = _f(
        "consistent",
        "the pose covariance reported (pose topic, MAVLink ODOMETRY, replay's T.cov.txt): consistent = the"
        " filter's covariance of each fix, scaled by the innovation consistency monitor, plus the map's own"
        " uncertainty from the anchors of the landmarks it was fixed against; filter = the filter's own"
        " (FastSLAM: the particles' spread, over-confident on long runs)",
        choices=("consistent", "filter"),
    )
    covariance_drift: float = _f(
        0.005,
        "consistent covariance: the error no pixel model holds, as a fraction of the path explored since the"
        " map's landmarks last fixed the pose (a standard deviation per metre, in every direction; every filter,"
        " the EKF's included)",
        min=0.0,
        max=1.0,
    )
    covariance_blur_px: float = _f(
        3.0,
        "consistent covariance: a motion the images measured while blurred (a streak of b px: the rotation's"
        " rate × the exposure × the focal length) adds (b / this)² times the motion's own covariance, an error"
        " the filter is not told of (docs/slam.md); only with frontend.motion_blur off; 0 = off",
        min=0.0,
        max=1000.0,
    )
    n_particles: int = _f(100, "FastSLAM particles (bounded by memory and deadline: docs/reliability.md)", min=1)
    resample_neff_ratio: float = _f(0.5, "resample when N_eff < ratio × N", min=0.0, max=1.0)
    fs2_weights: str = _f(
        "sequential",
        "FastSLAM 2.0 weight: chain rule over the proposal's innovations, or the product at the prior of"
        ' docs/math.md §10 "Importance weight"',
        choices=("sequential", "prior"),
    )
    max_updates_per_frame: int = _f(
        80, "identified measurements fused per frame at most (the filter's cost grows with it)", min=3, max=10000
    )
    max_new_per_frame: int = _f(40, "landmarks initialised per frame at most (nearest first)", min=0, max=10000)
    new_landmarks: str = _f(
        "nearest",
        "which new measurements become landmarks when there are more than max_new_per_frame: nearest (the"
        " most precise), or adaptive (nearest while the map is re-observed; spread over depth in a frame"
        " that re-observed fewer than 6 landmarks, so a map whose near points do not last gets far ones)",
        choices=("nearest", "adaptive"),
    )
    motion_noise_scale: float = _f(
        1.0, "multiplier on the motion prior's covariance (odometry or visual motion)", min=0.01, max=100.0
    )
    gravity: bool = _f(
        True,
        "3D: fuse the direction of gravity when the vehicle measures it (an autopilot's attitude, the"
        " simulator's IMU): it holds the absolute roll and pitch, which vision and a gyro leave to drift",
    )
    gravity_bias: bool = _f(
        True,
        "3D: learn the measured gravity's bias in the robot frame (a misaligned or uncalibrated IMU) from"
        ' its residual as the rover turns, and take it off (docs/slam.md "Gravity")',
    )
    numba_threads: int = _f(0, "threads of the FastSLAM kernel; 0: one per core", min=0, max=256)
    blas_threads: int = _f(
        1,
        "OpenBLAS threads in the daemon (1: no spinning worker; EKF SLAM on a large map gains from more)",
        min=1,
        max=256,
    )


@dataclass(frozen=True)
class ReplayConfig:
    odometry: str = _f(
        "none",
        "vehicle odometry of a dataset replay (kitti://, euroc://): none = vision only; dataset = the "
        "dataset's recorded odometry when the folder has it (KITTI raw OXTS under raw/*/oxts), else none. "
        "A robotd recording (.mcap) always replays its recorded odometry",
        choices=("none", "dataset"),
    )
    oxts_sigma_vel_mps: float = _f(
        0.06,
        "noise (1 sigma per axis) stated with each KITTI OXTS velocity sample (the unit's own vel_accuracy)",
        min=1e-6,
        max=10.0,
    )
    oxts_sigma_rate_radps: float = _f(
        0.015,
        "noise (1 sigma per axis) stated with each KITTI OXTS angular-rate sample (10 Hz hold of a vibrating body)",
        min=1e-6,
        max=10.0,
    )


@dataclass(frozen=True)
class BudgetConfig:
    deadline_ms: float = _f(0.0, "per-frame deadline; 0 means one frame period", min=0.0)
    min_features: int = _f(200, "feature cap floor when degrading", min=10)
    min_particles: int = _f(20, "particle floor when degrading", min=1)
    recover_after_frames: int = _f(30, "frames under budget before one degradation step is undone", min=1)


@dataclass(frozen=True)
class ZenohConfig:
    enabled: bool = _f(True, "publish over Zenoh")
    config_file: str = _f("", "zenoh JSON5 config (router/client mode, endpoints, TLS); overrides the below")
    mode: str = _f("peer", "zenoh mode", choices=("peer", "client", "router"))
    listen: list[str] = _f(["tcp/127.0.0.1:7447"], "listen endpoints (loopback only by default)")
    connect: list[str] = _f([], "endpoints to connect to")
    multicast_scouting: bool = _f(False, "multicast scouting (off: never announce on the LAN)")
    map_period_s: float = _f(2.0, "period of map updates", min=0.1)
    health_period_s: float = _f(1.0, "period of health messages", min=0.1)
    ros2: bool = _f(False, "also publish odom, landmarks, diagnostics as ROS 2 CDR for zenoh-bridge-ros2dds")
    ros2_world_frame: str = _f("map", "ROS 2 frame_id of the world (REP-105)", pattern=r"[A-Za-z_][A-Za-z0-9_/]*")
    ros2_body_frame: str = _f("base_link", "ROS 2 child_frame_id of the odometry", pattern=r"[A-Za-z_][A-Za-z0-9_/]*")
    ros2_stamp: str = _f("wall", "ROS 2 header stamps: capture time on the wall clock or the monotonic one",
                         choices=("wall", "monotonic"))  # fmt: skip


@dataclass(frozen=True)
class LiveViewConfig:
    enabled: bool = _f(False, "serve the recording's channels live to the Foxglove app (WebSocket, needs robotd[live])")
    host: str = _f("127.0.0.1", "address the live view listens on (loopback only by default)")
    port: int = _f(8765, "live view WebSocket port (Foxglove's default)", min=1, max=65535)
    map_period_s: float = _f(1.0, "period of the landmark map in the live view", min=0.1)


@dataclass(frozen=True)
class MavlinkConfig:
    enabled: bool = _f(False, "send the pose to an autopilot")
    url: str = _f("mavlink+udp://127.0.0.1:14550", "autopilot link when different from vehicle.url")
    message: str = _f("odometry", "pose message", choices=("odometry", "vision_position_estimate"))
    system_id: int = _f(1, "the vehicle's MAVLink system id", min=1, max=255)
    set_origin: bool = _f(False, "send SET_GPS_GLOBAL_ORIGIN (needed without GPS) from the values below")
    origin_lat_deg: float = _f(0.0, "EKF origin latitude", min=-90.0, max=90.0)
    origin_lon_deg: float = _f(0.0, "EKF origin longitude", min=-180.0, max=180.0)
    origin_alt_m: float = _f(0.0, "EKF origin altitude")
    signing_key_file: str = _f("", "32-byte MAVLink2 signing key (mode 0600); empty: unsigned")
    quality_good_sigma_m: float = _f(
        0.2, "reported position sigma [m] up to which quality is not lowered (it falls as good/sigma above)", min=0.001
    )


@dataclass(frozen=True)
class PersistenceConfig:
    state_dir: str = _f("", "map directory; empty: $STATE_DIRECTORY, else ~/.local/state/robotd")
    save_period_s: float = _f(30.0, "periodic map save; 0 disables periodic saves", min=0.0)
    resume: bool = _f(False, "start from the saved map when one exists")
    keep_maps: int = _f(
        5, "earlier maps kept (map.<time>.robotd) when a run that did not resume saves a new one", min=0, max=1000
    )


@dataclass(frozen=True)
class LogConfig:
    level: str = _f("INFO", "log level", choices=("DEBUG", "INFO", "WARNING", "ERROR"))
    status_period_s: float = _f(1.0, "period of the health line on stderr", min=0.1)


@dataclass(frozen=True)
class Config:
    robot: RobotConfig = field(default_factory=RobotConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    vehicle: VehicleConfig = field(default_factory=VehicleConfig)
    frontend: FrontendConfig = field(default_factory=FrontendConfig)
    slam: SlamConfig = field(default_factory=SlamConfig)
    replay: ReplayConfig = field(default_factory=ReplayConfig)
    budget: BudgetConfig = field(default_factory=BudgetConfig)
    zenoh: ZenohConfig = field(default_factory=ZenohConfig)
    liveview: LiveViewConfig = field(default_factory=LiveViewConfig)
    mavlink: MavlinkConfig = field(default_factory=MavlinkConfig)
    persistence: PersistenceConfig = field(default_factory=PersistenceConfig)
    log: LogConfig = field(default_factory=LogConfig)


# --------------------------------------------------------------------------------------------


def _type_name(tp: Any) -> str:
    return {bool: "a boolean", int: "an integer", float: "a number", str: "a string"}.get(tp, str(tp))


def _convert(path: str, tp: Any, value: Any, meta: typing.Mapping[str, Any]) -> Any:
    origin = typing.get_origin(tp)
    if origin in (list, tuple):
        (item_tp,) = typing.get_args(tp)[:1]
        if not isinstance(value, list):
            raise ConfigError(f"{path}: expected a list, got {type(value).__name__} {show_value(value)}")
        return [_convert(f"{path}[{i}]", item_tp, v, {}) for i, v in enumerate(value)]
    if origin in (typing.Union, types.UnionType):
        raise ConfigError(f"{path}: union types are not supported in config")  # pragma: no cover
    if tp is bool:
        if not isinstance(value, bool):
            got = f"{type(value).__name__} {show_value(value)}"
            raise ConfigError(f"{path}: expected a boolean (true/false), got {got}")
        out: Any = value
    elif tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{path}: expected an integer, got {type(value).__name__} {show_value(value)}")
        out = value
    elif tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise ConfigError(f"{path}: expected a number, got {type(value).__name__} {show_value(value)}")
        try:
            out = float(value)
        except OverflowError:  # an integer beyond 1.8e308
            raise ConfigError(f"{path}: expected a finite number, got {show_value(value)}") from None
        if not math.isfinite(out):
            raise ConfigError(f"{path}: expected a finite number, got {show_value(out)}")
    elif tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{path}: expected a string, got {type(value).__name__} {show_value(value)}")
        out = value
    else:  # pragma: no cover - every field type is one of the above
        raise ConfigError(f"{path}: unsupported field type {tp}")
    if "pattern" in meta and not re.fullmatch(meta["pattern"], out):
        raise ConfigError(f"{path}: expected a name matching {meta['pattern']}, got {show_value(out)}")
    if "choices" in meta and out not in meta["choices"]:
        raise ConfigError(f"{path}: expected one of {list(meta['choices'])}, got {show_value(out)}")
    if "min" in meta and out < meta["min"]:
        raise ConfigError(f"{path}: expected {_type_name(tp)} >= {meta['min']}, got {show_value(out)}")
    if "max" in meta and out > meta["max"]:
        raise ConfigError(f"{path}: expected {_type_name(tp)} <= {meta['max']}, got {show_value(out)}")
    return out


def _build(cls: type, data: dict[str, Any], prefix: str) -> Any:
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        where = prefix[:-1] if prefix else "top level"
        shown = unknown[0] if unknown[0].isprintable() and unknown[0] else repr(unknown[0])  # one line, always
        raise ConfigError(f"{prefix}{shown}: unknown key in {where}; known keys: {', '.join(sorted(fields))}")
    kwargs: dict[str, Any] = {}
    for name, value in data.items():
        f = fields[name]
        tp = hints[name]
        path = f"{prefix}{name}"
        if dataclasses.is_dataclass(tp):
            if not isinstance(value, dict):
                raise ConfigError(f"{path}: expected a table [{path}], got {type(value).__name__} {show_value(value)}")
            kwargs[name] = _build(tp, value, path + ".")  # type: ignore[arg-type]
        else:
            kwargs[name] = _convert(path, tp, value, f.metadata)
    return cls(**kwargs)


def config_from_dict(data: dict[str, Any]) -> Config:
    """Build a Config from nested dicts (what tomllib returns); validates every key, then the
    values that size memory or time against this machine (robotd.config.bounds)."""
    cfg: Config = _build(Config, data, "")
    s = cfg.slam
    check_bounds(
        Sizing(
            filter=s.filter,
            dim=s.dim,
            n_particles=s.n_particles,
            max_updates_per_frame=s.max_updates_per_frame,
            max_new_per_frame=s.max_new_per_frame,
            max_features=cfg.frontend.max_features,
            deadline_ms=cfg.budget.deadline_ms,
        )
    )
    return cfg


def load_config(path: str | Path | None = None, overrides: dict[str, Any] | None = None) -> Config:
    """Defaults, then the TOML file (if any), then ``overrides`` (nested dicts)."""
    data: dict[str, Any] = {}
    if path is not None:
        p = Path(path)
        try:
            text = p.read_text(encoding="utf-8")
        except OSError as exc:
            raise ConfigError(f"{p}: cannot read config file: {exc.strerror or exc}") from exc
        except UnicodeDecodeError as exc:
            raise ConfigError(f"{p}: not UTF-8 text (byte {exc.start}: {exc.reason}); TOML files are UTF-8") from None
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"{p}: not valid TOML: {exc}") from exc
        except ValueError as exc:  # an integer literal of more than 4300 digits
            raise ConfigError(f"{p}: not valid TOML: {exc}") from None
        except RecursionError:  # tomllib recurses once per nesting level
            raise ConfigError(f"{p}: not valid TOML: arrays or tables nested too deep") from None
    if overrides:
        data = _merge(data, overrides)
    try:
        return config_from_dict(data)
    except ConfigError as exc:
        if path is not None:
            raise ConfigError(f"{exc} (in {path})") from None
        raise


def _merge(a: dict[str, Any], b: dict[str, Any]) -> dict[str, Any]:
    out = dict(a)
    for k, v in b.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def to_dict(cfg: Any) -> dict[str, Any]:
    return dataclasses.asdict(cfg)


# TOML basic strings: these characters have short escapes; every other control character is
# written as \uXXXX (a raw control character makes the file invalid TOML)
_TOML_ESCAPES = {"\\": "\\\\", '"': '\\"', "\b": "\\b", "\t": "\\t", "\n": "\\n", "\f": "\\f", "\r": "\\r"}


def _is_control(c: str) -> bool:
    return ord(c) < 0x20 or ord(c) == 0x7F


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, int):
        return str(v)
    if isinstance(v, str):
        return '"' + "".join(_TOML_ESCAPES.get(c) or (f"\\u{ord(c):04X}" if _is_control(c) else c) for c in v) + '"'
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(type(v))  # pragma: no cover


def to_toml(cfg: Config, with_docs: bool = False) -> str:
    """The resolved tree as TOML; ``with_docs`` adds each field's documentation as a comment."""
    lines: list[str] = []
    for section in dataclasses.fields(cfg):
        sub = getattr(cfg, section.name)
        lines.append(f"[{section.name}]")
        for f in dataclasses.fields(sub):
            if with_docs and f.metadata.get("doc"):
                extra = ""
                if "choices" in f.metadata:
                    extra = f" (one of {', '.join(map(str, f.metadata['choices']))})"
                lines.append(f"# {f.metadata['doc']}{extra}")
            lines.append(f"{f.name} = {_toml_value(getattr(sub, f.name))}")
        lines.append("")
    return "\n".join(lines)


def parse_overrides(pairs: list[str]) -> dict[str, dict[str, Any]]:
    """``["slam.n_particles=50", ...]`` -> ``{"slam": {"n_particles": 50}}``: command-line config
    overrides (the benchmarks' ``--set``), each value read as TOML, else taken as a bare string.
    Raises ConfigError naming the pair when it is not SECTION.KEY=VALUE."""
    out: dict[str, dict[str, Any]] = {}
    for kv in pairs:
        key, _, val = kv.partition("=")
        section, _, name = key.strip().partition(".")
        if not (section and name and val):
            raise ConfigError(f"--set: expected SECTION.KEY=VALUE, got {kv!r}")
        try:
            value = tomllib.loads(f"v = {val}")["v"]
        except tomllib.TOMLDecodeError:
            value = val  # a bare string
        out.setdefault(section, {})[name] = value
    return out
