"""``sim://``: the simulated rover. Rendered rectified stereo pairs, noisy odometry, ground truth.

The daemon's built-in default source: ``robotd run`` with no configuration drives this rover
through a textured walled yard (drivers/simworld.py) and renders what its OAK-D-like stereo rig
sees (drivers/_render.py). Every StereoFrame carries ``truth_T_world_robot``.

Worlds (``world=``), the walled yard with a trajectory but for the last; all but the first are the
hard cases real data is short of (docs/sim.md has the layouts and timings):

- ``yard``: the default; a 28.5 m peanut-shaped loop, gentle curves, never stopping.
- ``turn_in_place``: straight legs round a 6 × 3 m parallelogram; at each corner the rover
  brakes to a stop and yaws 98° or 82° on the spot at up to 90 °/s (``speed`` scales both),
  then drives on. The first turn is at t = 2.0–3.4 s.
- ``moving_box``: the loop, in a wider yard, with a moving box (a 1.4 × 2.4 × 1.3 m van) that
  drives across the rover's path 3 m ahead of it, from the right of the view to the left,
  covering up to ≈ 54 % of the image (first crossing in view at t ≈ 2.3–5.0 s, then every half
  lap). It is rendered in both images at the frame's instant and is not part of
  ``World.surfaces`` (the static scene).
- ``low_texture``: the loop with the yard's east end bare (plain walls, bare concrete, no
  obstacles); the rover faces it for ≈ 1.5 s: fewer than 100 ORB features from t ≈ 3.9 to 5.4 s.
- ``open_terrain``: not the yard: open country (drivers/simterrain.py), a 763 m road lap through a
  grass field with sparse posts, rocks and bushes, stands of trees and a treeline 30–200 m away
  and hills beyond; a car's rig (1.65 m up, baseline 0.9 m: at 640×400 KITTI's f·b), so the upper
  half of the image is far points of a few pixels' disparity. The first turn, 98° over 53 m,
  starts 10 m in.

URL: ``sim://[WORLD]?key=value&...`` (all keys optional; one URL can serve camera and vehicle):

========== ======== ===================================================================
key        default  meaning
========== ======== ===================================================================
width      640      image width [px] (16..4096)
height     400      image height [px] (16..4096)
fps        30       frame rate [Hz] (0.1..1000)
f          430·w/640  focal length [px] (keeps the OAK-D's ≈ 73° field of view)
baseline   0.0755   stereo baseline [m]; open_terrain: 0.9 (a car's rig; f·b = KITTI's at 640×400)
seed       1        world layout, textures and noise (integer ≥ 0)
world      yard     yard, turn_in_place, moving_box, low_texture or open_terrain (also the URL's
                    host: ``sim://yard``)
speed      1.0      mean rover speed [m/s] (0..5); turn_in_place: on the straights, and turns × speed
tilt       0        terrain rocking amplitude, roll and pitch [deg] (0..10)
shake      0        a hand-held camera shaken: peak rotation about every axis [deg] (0..10), with
                    5 mm a degree of translation, at 1.7-7.3 Hz; 0 = a rover's steady mount
shake_s    0        the shake fades out over its last 0.5 s and ends then [s]; 0 = it never ends
exposure_ms 0       motion blur: each image is the mean of 9 renders spread over this exposure,
                    centred on the frame's time [ms] (0..50); 0 = an instant
exposure_report 1   1: each frame reports its exposure, as the OAK-D does; 0: none, as a dataset
                    folder (robotd then estimates it: robotd.frontend.exposure)
duration   0        stop after this many simulated seconds; 0 = run forever
realtime   1        1: emit at capture times on time.monotonic_ns(); 0: as fast as pulled
noise      0.05     odometry speed noise, σ as a fraction of the speed (per sample)
gyro_noise 0.005    gyro white noise σ [rad/s] (per sample)
gyro_bias  0.002    gyro bias σ [rad/s], drawn once per seed and held constant
gravity    1        1: each odometry sample carries the IMU's direction of gravity (roll and pitch
                    against the vertical); 0: a rover without one
gravity_noise 0.005 its white noise σ [rad] per axis (per sample)
gravity_bias 0.005  its bias σ [rad] per axis, drawn once per seed and held
gravity_sigma 0.02  the σ [rad] the simulated IMU states with each sample
odom_hz    50       odometry rate [Hz] (1..1000)
img_noise  2.0      sensor noise σ [grey levels] added to each image (0..50)
disparity_error 0   a calibration error [px] (−5..5): the right camera's principal point is this far
                    left of where the rig says, so every disparity reads this much too large; the
                    rig handed to the pipeline stays the nominal one (docs/frontend.md, "Far points")
odometry   1        0: the vehicle yields no odometry (vision only; its autopilot still takes poses)
unplug     0        fault injection: the camera raises DriverError at this simulated time [s], as a
                    USB camera that is pulled out does; 0 = never (bench/faults.py)
stop_at    0        when the rover stops [s] (with stop_s > 0): it brakes, stands still, drives on
stop_s     0        how long it stands still [s]; 0 = it never stops
stall_at   0        when the camera stalls [s] (with stall_s > 0): no frame is captured ...
stall_s    0        ... for this long [s]; 0 = no stall (the hard case "stall", docs/sim.md)
stall_odometry 0    0: the vehicle's samples in the stall are lost too (the host stopped);
                    1: only the camera stalled, odometry flows
follow     (none)   HOST:PORT (loopback): the rover is driven from outside, by the truth states
                    an external physics program sends there (drivers/simfollow.py; the SITL
                    loop of bench/sitl.py); the yard stays, the written trajectory is not used
yaw0       0        with follow: the heading [deg from north] of the loop's start pose in the
                    physics's NED frame (the start pose is NED's origin)
prerender  0        1: render every frame of ``duration`` before the clock starts and deliver them
                    from memory, so the camera costs what a real driver costs (bench/daemon.py;
                    2 × 256 kB a frame at 640×400)
========== ======== ===================================================================

Timing. Camera and vehicle opened separately share one simulated clock and world when their URLs
agree on (seed, world, speed, tilt): a process-wide registry holds the world and the start time
``t0_ns`` taken on time.monotonic_ns() at the first open (or given as the ``t0_ns=`` option).
Frame k is captured at ``t0_ns + round(k · 1e9 / fps)``, odometry sample j at
``t0_ns + round(j · 1e9 / odom_hz)``. With ``realtime=1`` a frame is yielded at its capture time,
rendered just before it (the recent 90th-percentile render time plus 1 ms ahead), as a camera
delivers a frame that was imaged on the device;
a consumer that pulls late gets the newest frame and the skipped ones count as ``dropped``
(the simulated camera never slows down). With ``realtime=0`` frames come as fast as they are
pulled, with the same timestamps, so a run is reproducible.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, fields, replace
from typing import Any
from urllib.parse import parse_qsl, urlsplit

import cv2
import numpy as np

from drivers import HEALTH_STATES, AutopilotLink
from drivers._render import ViewRenderer
from drivers.base import Driver
from drivers.cameras import CameraBase, DatasetOdometry
from drivers.simfollow import FollowedTrajectory, parse_follow, truth_push_args
from drivers.simworld import WORLDS, World, build_world, rig_baseline_m
from robotd.core.errors import DriverError
from robotd.core.geometry import R_ROBOT_OPTICAL, se3
from robotd.core.msgs import Odometry, PoseEstimate, StereoFrame
from robotd.core.stereo import RectifiedStereo

logger = logging.getLogger(__name__)

# --------------------------------------------------------------------------------------------
# Parameters


@dataclass(frozen=True, slots=True)
class SimParams:
    """Resolved ``sim://`` parameters (see the module docstring for meanings and units)."""

    width: int = 640
    height: int = 400
    fps: float = 30.0
    f: float = 0.0  # 0 → 430 · width / 640
    baseline: float = 0.0  # 0 → the world's rig: 0.0755 (the OAK-D's), open_terrain 0.9
    seed: int = 1
    world: str = "yard"
    speed: float = 1.0
    tilt: float = 0.0
    shake: float = 0.0
    shake_s: float = 0.0
    exposure_ms: float = 0.0
    exposure_report: int = 1
    duration: float = 0.0
    realtime: int = 1
    noise: float = 0.05
    gyro_noise: float = 0.005
    gyro_bias: float = 0.002
    gravity: int = 1
    gravity_noise: float = 0.005
    gravity_bias: float = 0.005
    gravity_sigma: float = 0.02
    odom_hz: float = 50.0
    img_noise: float = 2.0
    disparity_error: float = 0.0  # [px] right principal point off by −this: disparities read +this
    odometry: int = 1
    unplug: float = 0.0  # fault injection: the camera fails at this simulated time [s]; 0 = never
    stop_at: float = 0.0
    stop_s: float = 0.0
    stall_at: float = 0.0
    stall_s: float = 0.0
    stall_odometry: int = 0
    follow: str = ""  # HOST:PORT of an external physics's truth stream ("" = the written trajectory)
    yaw0: float = 0.0  # with follow: heading of the start pose in the physics's NED frame [deg]
    prerender: int = 0  # 1: every frame of `duration` rendered before the clock starts, served from memory

    def stalled(self, t_s: float) -> bool:
        """Simulated time ``t_s`` falls in the stall (nothing captured)."""
        return self.stall_s > 0.0 and self.stall_at <= t_s < self.stall_at + self.stall_s

    @property
    def f_px(self) -> float:
        return self.f if self.f > 0 else 430.0 * self.width / 640.0

    @property
    def baseline_m(self) -> float:
        return self.baseline if self.baseline > 0 else rig_baseline_m(self.world)

    @property
    def session_key(self) -> tuple[int, str, float, float, float, float, str, float, float, float]:
        """What camera and vehicle must agree on to share a world and a clock."""
        return (
            self.seed,
            self.world,
            self.speed,
            self.tilt,
            self.stop_at,
            self.stop_s,
            self.follow,
            self.yaw0,
            self.shake,
            self.shake_s,
        )


# key -> (parser, lower bound, upper bound); bounds inclusive, None = open
_RANGES: dict[str, tuple[Callable[[str], Any], float | None, float | None]] = {
    "width": (int, 16, 4096),
    "height": (int, 16, 4096),
    "fps": (float, 0.1, 1000.0),
    "f": (float, 1.0, 1e5),
    "baseline": (float, 1e-3, 10.0),
    "seed": (int, 0, 2**63 - 1),
    "world": (str, None, None),
    "speed": (float, 0.0, 5.0),
    "tilt": (float, 0.0, 10.0),
    "shake": (float, 0.0, 10.0),
    "shake_s": (float, 0.0, 1e9),
    "exposure_ms": (float, 0.0, 50.0),
    "exposure_report": (int, 0, 1),
    "duration": (float, 0.0, 1e9),
    "realtime": (int, 0, 1),
    "noise": (float, 0.0, 1.0),
    "gyro_noise": (float, 0.0, 1.0),
    "gyro_bias": (float, 0.0, 1.0),
    "gravity": (int, 0, 1),
    "gravity_noise": (float, 0.0, 0.5),
    "gravity_bias": (float, 0.0, 0.5),
    "gravity_sigma": (float, 1e-4, 1.0),
    "odom_hz": (float, 1.0, 1000.0),
    "img_noise": (float, 0.0, 50.0),
    "disparity_error": (float, -5.0, 5.0),
    "odometry": (int, 0, 1),
    "unplug": (float, 0.0, 1e9),
    "stop_at": (float, 0.0, 1e9),
    "stop_s": (float, 0.0, 1e9),
    "stall_at": (float, 0.0, 1e9),
    "stall_s": (float, 0.0, 1e9),
    "stall_odometry": (int, 0, 1),
    "follow": (str, None, None),
    "yaw0": (float, -360.0, 360.0),
    "prerender": (int, 0, 1),
}


def _convert(url: str, key: str, raw: Any) -> Any:
    parse, lo, hi = _RANGES[key]
    try:
        if parse is int and isinstance(raw, str):
            value: Any = int(raw, 10)
        elif parse is int and isinstance(raw, bool):
            value = int(raw)
        else:
            value = parse(raw)
    except (TypeError, ValueError):
        raise DriverError(f"{url!r}: parameter {key}={raw!r}: expected {parse.__name__}") from None
    if isinstance(value, float) and not math.isfinite(value):
        raise DriverError(f"{url!r}: parameter {key}={raw!r}: expected a finite number")
    if lo is not None and hi is not None and not lo <= value <= hi:
        raise DriverError(f"{url!r}: parameter {key}={value!r}: expected {lo:g} ≤ {key} ≤ {hi:g}")
    if key == "world" and value not in WORLDS:
        raise DriverError(f"{url!r}: parameter world={value!r}: unknown world; known: {', '.join(WORLDS)}")
    if key == "follow" and value:
        parse_follow(url, value)
    return value


def parse_sim_url(url: str, **options: Any) -> SimParams:
    """Parse ``sim://[WORLD]?k=v&...``; ``options`` (same names) override the URL.

    Raises DriverError naming the parameter for unknown keys, bad values and repeated keys.
    """
    parts = urlsplit(url)
    if parts.scheme.lower() != "sim":
        raise DriverError(f"{url!r}: expected a sim:// URL")
    if parts.path not in ("", "/"):
        raise DriverError(f"{url!r}: sim:// takes no path, got {parts.path!r}")
    values: dict[str, Any] = {}
    if parts.netloc:
        values["world"] = _convert(url, "world", parts.netloc)
    try:
        pairs = parse_qsl(parts.query, keep_blank_values=True, strict_parsing=bool(parts.query))
    except ValueError as exc:
        raise DriverError(f"{url!r}: malformed query string: {exc}") from None
    for key, raw in pairs:
        if key not in _RANGES:
            raise DriverError(f"{url!r}: unknown parameter {key!r}; known: {', '.join(sorted(_RANGES))}")
        if key in values and key != "world":
            raise DriverError(f"{url!r}: parameter {key!r} given twice")
        values[key] = _convert(url, key, raw)
    for key, raw in options.items():
        if key not in _RANGES:
            raise DriverError(f"{url!r}: unknown option {key!r}; known: {', '.join(sorted(_RANGES))}, t0_ns")
        values[key] = _convert(url, key, raw)
    params = replace(SimParams(), **values)
    if params.follow and params.stop_s > 0:
        raise DriverError(f"{url!r}: follow and stop_s: a followed rover stops when its physics stops it")
    if params.follow and params.shake > 0:
        raise DriverError(f"{url!r}: follow and shake: a followed rover moves as its physics moves it")
    if params.prerender and (params.duration <= 0 or params.follow):
        raise DriverError(f"{url!r}: prerender needs a duration (the frames to render) and no follow")
    return params


# --------------------------------------------------------------------------------------------
# Shared sessions: one world and one clock per (seed, world, speed, tilt)


class _Session:
    def __init__(self, params: SimParams, t0_ns: int | None) -> None:
        self.world: World = build_world(
            params.seed,
            params.world,
            params.speed,
            params.tilt,
            (params.stop_at, params.stop_s),
            params.shake,
            params.shake_s,
        )
        # prerender: the whole drive rendered now, before the clock starts
        self.prerendered: list[StereoFrame] | None = None
        self.prerender_s = 0.0
        if params.prerender:
            rig = SimRig(self.world, params)
            n = math.ceil(params.duration * params.fps - 1e-9)
            t_start = time.perf_counter()
            self.prerendered = [rig.render(k, 0, depth=False)[0] for k in range(n)]
            self.prerender_s = time.perf_counter() - t_start
            logger.info("sim: %d frames prerendered in %.1f s", n, self.prerender_s)
        # the clock starts once the world is built, so the first frames are not already late
        self.t0_ns = time.monotonic_ns() if t0_ns is None else int(t0_ns)
        self.followed: FollowedTrajectory | None = None
        if params.follow:
            traj = self.world.trajectory
            self.followed = FollowedTrajectory(
                traj.T_world_yard, traj.path_points_yard(), math.radians(params.yaw0), self.t0_ns
            )
            self.followed.listen(*parse_follow(params.follow, params.follow), truth_push_args)
            self.world = replace(self.world, trajectory=self.followed)
        self.refs = 0
        rng = np.random.default_rng([params.seed, 8])
        self._gyro_bias_unit = rng.standard_normal(3)  # scaled by each link's gyro_bias
        self._gravity_bias_unit = rng.standard_normal(3)  # scaled by each link's gravity_bias

    def gyro_bias(self, sigma: float) -> np.ndarray:
        return sigma * self._gyro_bias_unit

    def gravity_bias(self, sigma: float) -> np.ndarray:
        return sigma * self._gravity_bias_unit


_SESSIONS: dict[tuple[int, str, float, float, float, float, str, float, float, float], _Session] = {}
_SESSIONS_LOCK = threading.Lock()


def _acquire(params: SimParams, t0_ns: int | None) -> _Session:
    with _SESSIONS_LOCK:
        key = params.session_key
        session = _SESSIONS.get(key)
        if session is None:
            session = _Session(params, t0_ns)
            _SESSIONS[key] = session
            logger.info("sim world seed=%d %s: start t0_ns=%d", params.seed, params.world, session.t0_ns)
        elif t0_ns is not None and int(t0_ns) != session.t0_ns:
            raise DriverError(
                f"sim session {key}: t0_ns={t0_ns} requested but the shared clock started at {session.t0_ns}"
            )
        session.refs += 1
        return session


def _release(params: SimParams, session: _Session) -> None:
    with _SESSIONS_LOCK:
        session.refs -= 1
        if session.refs <= 0 and _SESSIONS.get(params.session_key) is session:
            del _SESSIONS[params.session_key]
            if session.followed is not None:
                session.followed.close()


def _pop_t0(url: str, options: dict[str, Any]) -> int | None:
    t0 = options.pop("t0_ns", None)
    if t0 is not None and (not isinstance(t0, int | np.integer) or isinstance(t0, bool)):
        raise DriverError(f"{url!r}: option t0_ns={t0!r}: expected integer nanoseconds")
    return None if t0 is None else int(t0)


def _percentiles(samples: deque[float]) -> tuple[float, float]:
    if not samples:
        return float("nan"), float("nan")
    a = np.fromiter(samples, float)
    return float(np.percentile(a, 50)), float(np.percentile(a, 99))


# --------------------------------------------------------------------------------------------
# The rig: pure rendering of frame k (no clock), usable on its own by tests and benchmarks


class SimRig:
    """Renders the stereo pair of frame ``k`` of a world: deterministic for (world, params, k).

    Left camera at y = −b/2, right at +b/2 in the robot frame, both looking along X_r with the
    optical axes (x right, y down, z forward) = R_ROBOT_OPTICAL; a rectified pinhole pair.
    """

    def __init__(self, world: World, params: SimParams) -> None:
        self.world = world
        self.params = params
        w, h = params.width, params.height
        self.model = RectifiedStereo(params.f_px, (w - 1) / 2.0, (h - 1) / 2.0, params.baseline_m, w, h)
        self._renderer = ViewRenderer(world.surfaces, self.model.f_px, self.model.px, self.model.py, w, h)
        # the right view of a rig whose calibration is off: its principal point sits disparity_error
        # px left of the model's, so x_r is that much smaller and every disparity that much larger
        self._renderer_right = self._renderer
        if params.disparity_error:
            self._renderer_right = ViewRenderer(
                world.surfaces, self.model.f_px, self.model.px - params.disparity_error, self.model.py, w, h
            )
        self._movers_only: ViewRenderer | None = None
        b = params.baseline_m
        self.T_robot_left = se3(R_ROBOT_OPTICAL, np.array([0.0, -b / 2.0, 0.0]))
        self.T_robot_right = se3(R_ROBOT_OPTICAL, np.array([0.0, b / 2.0, 0.0]))
        # sensor noise: a bank of noise fields drawn once; each frame picks fields and offsets
        # (drawing 2 × 256k normals per frame would cost more than the rendering)
        self._pad = 32
        self._noise_pos: list[np.ndarray] = []
        self._noise_neg: list[np.ndarray] = []
        if params.img_noise > 0:
            rng = np.random.default_rng([params.seed, 4])
            for _ in range(6):
                n = np.rint(rng.normal(0.0, params.img_noise, (h + self._pad, w + self._pad)))
                n = np.clip(n, -127, 127)
                self._noise_pos.append(np.maximum(n, 0).astype(np.uint8))
                self._noise_neg.append(np.maximum(-n, 0).astype(np.uint8))

    def frame_time_s(self, k: int) -> float:
        return k / self.params.fps

    def _add_noise(self, img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        if not self._noise_pos:
            return img
        i = int(rng.integers(len(self._noise_pos)))
        dy, dx = (int(v) for v in rng.integers(0, self._pad, 2))
        h, w = img.shape
        # saturating uint8 arithmetic: min(img + max(n, 0), 255), then max(· − max(−n, 0), 0);
        # OpenCV's saturating add/subtract do it in place without int16 temporaries (≈ 8× faster)
        cv2.add(img, self._noise_pos[i][dy : dy + h, dx : dx + w], dst=img)
        cv2.subtract(img, self._noise_neg[i][dy : dy + h, dx : dx + w], dst=img)
        return img

    EXPOSURE_SAMPLES = 9

    def _blurred(self, t_s: float, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Motion blur: the pair averaged over ``EXPOSURE_SAMPLES`` instants spread evenly over the
        exposure, centred on ``t_s`` (whose renders ``left``, ``right`` are; the depth buffer and the
        truth stay the centre's). Both cameras expose together, as a synchronised rig does."""
        n = self.EXPOSURE_SAMPLES
        acc_l = left.astype(np.float32)
        acc_r = right.astype(np.float32)
        e = self.params.exposure_ms * 1e-3
        for j in range(n):
            dt = (j / (n - 1) - 0.5) * e
            if j == (n - 1) // 2:
                continue  # the centre: already rendered
            T = self.world.trajectory.state(t_s + dt).T_world_robot
            moving = self.world.moving_surfaces(t_s + dt)
            acc_l += self._renderer.render(T @ self.T_robot_left, moving)[0]
            acc_r += self._renderer_right.render(T @ self.T_robot_right, moving)[0]
        return (
            np.clip(np.rint(acc_l / n), 0, 255).astype(np.uint8),
            np.clip(np.rint(acc_r / n), 0, 255).astype(np.uint8),
        )

    def render(self, k: int, t_ns: int, depth: bool = True) -> tuple[StereoFrame, np.ndarray | None]:
        """Frame ``k`` stamped ``t_ns``, and the left camera's depth buffer (H, W) float32 [m]
        (Z along the optical axis = X_r depth; +inf where nothing was hit; None when ``depth`` is
        False: the camera's frame stream does not need it)."""
        t_s = self.frame_time_s(k)
        T_world_robot = self.world.trajectory.state(t_s).T_world_robot
        moving = self.world.moving_surfaces(t_s)  # one instant for both views: a synchronised pair
        left, iz = self._renderer.render(T_world_robot @ self.T_robot_left, moving)
        right, _ = self._renderer_right.render(T_world_robot @ self.T_robot_right, moving)
        if self.params.exposure_ms > 0.0:
            left, right = self._blurred(t_s, left, right)
        rng = np.random.default_rng([self.params.seed, 1, k])
        left = self._add_noise(left, rng)
        right = self._add_noise(right, rng)
        exposure_ns = round(self.params.exposure_ms * 1e6) if self.params.exposure_report else 0
        frame = StereoFrame(t_ns, k, left, right, True, T_world_robot, exposure_ns)
        if not depth:
            return frame, None
        with np.errstate(divide="ignore"):
            z = np.where(iz > 0, 1.0 / iz, np.inf).astype(np.float32)
        return frame, z

    def moving_mask(self, k: int) -> np.ndarray:
        """(H, W) bool: the pixels of frame ``k``'s left image that show a moving object (not
        hidden behind the static scene); all False in a world without movers. For tests and
        evaluation (which features sat on the moving box); it renders the view twice."""
        t_s = self.frame_time_s(k)
        moving = self.world.moving_surfaces(t_s)
        if not moving:
            return np.zeros((self.params.height, self.params.width), bool)
        T_world_cam = self.world.trajectory.state(t_s).T_world_robot @ self.T_robot_left
        _, iz_all = self._renderer.render(T_world_cam, moving)
        if self._movers_only is None:
            m = self.model
            self._movers_only = ViewRenderer((), m.f_px, m.px, m.py, m.width, m.height)
        _, iz_mov = self._movers_only.render(T_world_cam, moving)
        # the same plane, pixel and float32 arithmetic: where the mover won the depth test, equal
        return (iz_mov > 0) & (iz_mov >= iz_all)


# --------------------------------------------------------------------------------------------
# Camera


class SimCamera(Driver):
    """``sim://`` stereo camera (StereoCamera protocol). Open with ``with`` or :func:`open_sim_camera`."""

    raw_calibration = None  # a rendered rig has no device calibration

    def __init__(self, url: str, params: SimParams, t0_ns: int | None = None) -> None:
        self.url = url
        self.params = params
        self._t0_request = t0_ns
        self._session: _Session | None = None
        self._rig: SimRig | None = None
        self._closed = threading.Event()
        self._lock = threading.Lock()
        self._next_k = 0
        self._rendered = 0
        self._dropped = 0
        self._render_ms: deque[float] = deque(maxlen=1000)
        self._prerender_ms: float | None = None  # kept once seen: the session goes with the camera

    # lifecycle
    def __exit__(self, *exc: object) -> None:
        super().__exit__(*exc)
        self._release()  # leaving the with block also lets the shared world go; close() alone does not

    def open(self) -> None:
        """Build (or join) the shared world and clock; idempotent."""
        with self._lock:
            if self._session is None:
                self._session = _acquire(self.params, self._t0_request)
                self._rig = SimRig(self._session.world, self.params)
                logger.info(
                    "sim camera %s: %dx%d @ %g fps, f=%.1f px, b=%.4f m, realtime=%d",
                    self.url,
                    self.params.width,
                    self.params.height,
                    self.params.fps,
                    self._rig.model.f_px,
                    self.params.baseline_m,
                    self.params.realtime,
                )

    def _release(self) -> None:
        with self._lock:
            if self._session is not None:
                _release(self.params, self._session)
                self._session = None

    def close(self) -> None:
        """Stop iteration (safe from another thread: ``frames()`` returns within one render)."""
        self._closed.set()

    @property
    def t0_ns(self) -> int:
        self.open()
        assert self._session is not None
        return self._session.t0_ns

    @property
    def fps(self) -> float:
        """Nominal frame rate [Hz] (the daemon sizes its latency budget from it)."""
        return self.params.fps

    @property
    def host_clock(self) -> bool:
        """In real time frames come at their stamps on the host's clock; with ``realtime=0`` as fast
        as pulled, so the stamps run ahead of it (a replay's clock)."""
        return bool(self.params.realtime)

    @property
    def n_frames(self) -> int | None:
        """Frames in the stream when ``duration`` is set (non-real-time), else None (endless)."""
        if self.params.duration <= 0:
            return None
        return math.ceil(self.params.duration * self.params.fps - 1e-9)

    def rectified_model(self) -> RectifiedStereo:
        w, h = self.params.width, self.params.height
        return RectifiedStereo(self.params.f_px, (w - 1) / 2.0, (h - 1) / 2.0, self.params.baseline_m, w, h)

    def frame_t_ns(self, k: int) -> int:
        """Capture time of frame ``k`` on the host monotonic clock."""
        return self.t0_ns + round(k * 1e9 / self.params.fps)

    def render(self, k: int) -> tuple[StereoFrame, np.ndarray]:
        """Frame ``k`` and its left depth buffer [m], off the clock (tests, evaluation)."""
        self.open()
        assert self._rig is not None
        frame, depth = self._rig.render(k, self.frame_t_ns(k))
        assert depth is not None
        return frame, depth

    def frames(self, timeout_s: float = 1.0) -> Iterator[StereoFrame]:
        """Yield frames until ``duration`` is reached or :meth:`close` is called.

        ``timeout_s`` is accepted for the protocol; the simulated camera always delivers.
        """
        if self._closed.is_set():
            return
        self.open()
        assert self._rig is not None
        p = self.params
        t0 = self.t0_ns
        k = self._next_k
        followed = self._session.followed if self._session is not None else None
        self._prerender_ms_per_frame()
        if followed is not None:
            # an external physics moves the rover: nothing to image before its first state
            if not followed.wait_first(self._closed):
                return
            if p.realtime:
                k = max(k, math.floor((time.monotonic_ns() - t0) * p.fps / 1e9))
        while not self._closed.is_set():
            if p.realtime:
                # the newest frame already captured; the ones the consumer missed are dropped
                k_now = math.floor((time.monotonic_ns() - t0) * p.fps / 1e9)
                if k_now > k:
                    self._dropped += k_now - k
                    logger.debug("sim camera: consumer late, dropped %d frames", k_now - k)
                    k = k_now
            if p.duration > 0 and k / p.fps >= p.duration:
                return
            if p.unplug > 0 and k / p.fps >= p.unplug:
                # what a USB camera's driver does when the device is pulled out: the stream fails
                raise DriverError(f"{self.url!r}: camera disconnected at t = {k / p.fps:.2f} s (simulated unplug)")
            if p.stalled(k / p.fps):
                # the camera stalls: these frames are never captured (their sequence numbers are
                # skipped, as a device's are); in real time it is silent until the stall ends
                k_end = math.ceil((p.stall_at + p.stall_s) * p.fps - 1e-9)
                if p.realtime and self._closed.wait(max(0.0, (self.frame_t_ns(k_end) - time.monotonic_ns()) / 1e9)):
                    return
                k = max(k + 1, k_end)
                continue
            t_ns = self.frame_t_ns(k)
            if p.realtime and len(self._render_ms) >= 3:
                # Render just in time, like a camera whose imaging happens before the capture is
                # delivered (an OAK-D does it on the device): start when the recent 90th
                # percentile render time plus 1 ms remains, not right after the previous frame,
                # which would put this process's rendering on top of the consumer's busiest stage.
                lead_ns = (float(np.percentile(np.fromiter(self._render_ms, float)[-30:], 90)) + 1.0) * 1e6
                wait_s = (t_ns - lead_ns - time.monotonic_ns()) / 1e9
                if wait_s > 0 and self._closed.wait(wait_s):
                    return
            start = time.perf_counter()
            pre = self._session.prerendered if self._session is not None else None
            if pre is not None and k < len(pre):
                frame = replace(pre[k], t_ns=t_ns)  # rendered before the clock started
            else:
                frame, _ = self._rig.render(k, t_ns, depth=False)
            self._render_ms.append((time.perf_counter() - start) * 1e3)
            if p.realtime:
                wait_s = (t_ns - time.monotonic_ns()) / 1e9
                if wait_s > 0 and self._closed.wait(wait_s):
                    return
            k += 1
            self._next_k = k
            self._rendered += 1  # counted as delivered, as a device driver counts what it hands over
            yield frame

    def _prerender_ms_per_frame(self) -> float | None:
        """Rendering time per frame before the clock started (prerender=1), else None."""
        s = self._session
        if s is not None and s.prerendered:
            self._prerender_ms = 1e3 * s.prerender_s / len(s.prerendered)
        return self._prerender_ms

    def stats(self) -> dict[str, Any]:
        p50, p99 = _percentiles(self._render_ms)
        return {
            "frames": self._rendered,
            "dropped": self._dropped,
            "render_ms_p50": p50,
            "render_ms_p99": p99,
            "next_seq": self._next_k,
            "prerender_ms_per_frame": self._prerender_ms_per_frame(),
            "fps": self.params.fps,
            "errors": 0,
            "reconnects": 0,
        }


# --------------------------------------------------------------------------------------------
# Vehicle


class SimVehicle(Driver):
    """``sim://`` vehicle link (VehicleLink protocol): noisy wheel/gyro odometry of the rover.

    Sample j (at ``t0 + j/odom_hz``) reports the truth velocity (FRD) plus noise: forward
    σ = noise·|v|, lateral and vertical σ = 0.2·noise·|v| (slip), body rates plus a constant bias
    (σ gyro_bias per axis, drawn once per seed) and white noise σ gyro_noise. The noise of sample j
    depends only on (seed, j), so it does not change with how the consumer pulls.
    """

    _BLOCK = 1024

    def __init__(self, url: str, params: SimParams, t0_ns: int | None = None) -> None:
        self.url = url
        self.params = params
        self._t0_request = t0_ns
        self._session: _Session | None = None
        self._closed = threading.Event()
        self._lock = threading.Lock()
        self._next_j = 0
        self._sent = 0
        self._dropped = 0
        self._autopilot = SimAutopilot(url, self.truth_T_world_robot)
        self._block_id = -1
        self._block = np.zeros((self._BLOCK, 6))
        self._grav_block_id = -1
        self._grav_block = np.zeros((self._BLOCK, 3))

    def __exit__(self, *exc: object) -> None:
        super().__exit__(*exc)
        with self._lock:
            if self._session is not None:
                _release(self.params, self._session)
                self._session = None

    def open(self) -> None:
        with self._lock:
            if self._session is None:
                self._session = _acquire(self.params, self._t0_request)
                if self.params.odometry:
                    logger.info(
                        "sim vehicle %s: odometry @ %g Hz, noise=%g", self.url, self.params.odom_hz, self.params.noise
                    )
                else:
                    logger.info("sim vehicle %s: no odometry (odometry=0)", self.url)

    def close(self) -> None:
        self._closed.set()

    @property
    def t0_ns(self) -> int:
        self.open()
        assert self._session is not None
        return self._session.t0_ns

    def sample_t_ns(self, j: int) -> int:
        return self.t0_ns + round(j * 1e9 / self.params.odom_hz)

    def truth_T_world_robot(self, t_ns: int) -> np.ndarray:
        """Ground-truth pose (4, 4) at host time ``t_ns`` (evaluation only)."""
        self.open()
        assert self._session is not None
        return self._session.world.trajectory.state(max(0.0, (t_ns - self.t0_ns) / 1e9)).T_world_robot

    def sample(self, j: int) -> Odometry:
        """Odometry sample ``j``, off the clock (deterministic)."""
        self.open()
        assert self._session is not None
        p = self.params
        truth = self._session.world.trajectory.state(j / p.odom_hz)
        block = j // self._BLOCK
        if block != self._block_id:
            self._block = np.random.default_rng([p.seed, 7, block]).standard_normal((self._BLOCK, 6))
            self._block_id = block
        n = self._block[j % self._BLOCK]
        v = float(np.linalg.norm(truth.vel_R_mps))
        vel = truth.vel_R_mps + p.noise * v * np.array([1.0, 0.2, 0.2]) * n[:3]
        rate = truth.rate_R_radps + self._session.gyro_bias(p.gyro_bias) + p.gyro_noise * n[3:]
        if not p.gravity:
            return Odometry(self.sample_t_ns(j), vel, rate, "sim")
        return Odometry(
            self.sample_t_ns(j), vel, rate, "sim", None, self._gravity(j, truth.T_world_robot), p.gravity_sigma
        )

    def _gravity(self, j: int, T_world_robot: np.ndarray) -> np.ndarray:
        """The IMU's direction of gravity in the robot frame at sample j: the truth (the world's z
        is the vertical: the rover starts level) tilted by a held bias and white noise, each a small
        angle across the direction (σ gravity_bias, gravity_noise per axis)."""
        assert self._session is not None
        p = self.params
        g = T_world_robot[:3, :3].T @ np.array([0.0, 0.0, 1.0])
        block = j // self._BLOCK
        if block != self._grav_block_id:
            self._grav_block = np.random.default_rng([p.seed, 9, block]).standard_normal((self._BLOCK, 3))
            self._grav_block_id = block
        e = self._session.gravity_bias(p.gravity_bias) + p.gravity_noise * self._grav_block[j % self._BLOCK]
        e -= (e @ g) * g  # across the direction: a tilt, not a change of length
        g = g + e
        return g / np.linalg.norm(g)  # type: ignore[no-any-return]

    def odometry(self, timeout_s: float = 1.0) -> Iterator[Odometry]:
        """Yield samples until ``duration`` or :meth:`close`. In real time a late consumer gets the
        backlog (like a serial buffer), capped at one second; older samples count as dropped."""
        if self._closed.is_set():
            return
        self.open()
        p = self.params
        if not p.odometry:
            return  # odometry=0: a rover without wheel odometry (vision only); poses still go to the autopilot
        t0 = self.t0_ns
        j = self._next_j
        while not self._closed.is_set():
            if p.duration > 0 and j / p.odom_hz >= p.duration:
                return
            t_ns = self.sample_t_ns(j)
            if p.realtime:
                now = time.monotonic_ns()
                j_now = math.floor((now - t0) * p.odom_hz / 1e9)
                backlog_cap = max(1, round(p.odom_hz))
                if j_now - j > backlog_cap:
                    self._dropped += j_now - j - backlog_cap
                    j = j_now - backlog_cap
                    continue
                wait_s = (t_ns - now) / 1e9
                if wait_s > 0 and self._closed.wait(wait_s):
                    return
            j += 1
            self._next_j = j
            if not p.stall_odometry and p.stalled((j - 1) / p.odom_hz):
                continue  # the host stalled: the link's samples of that time are lost
            msg = self.sample(j - 1)
            self._sent += 1
            yield msg

    @property
    def autopilot(self) -> SimAutopilot:
        """The simulated autopilot: takes the SLAM pose and scores it against this rover's truth."""
        return self._autopilot

    def stats(self) -> dict[str, Any]:
        return {
            "samples": self._sent,
            "dropped": self._dropped,
            "poses_received": self._autopilot.poses_received,
            "last_pose_error_m": self._autopilot.last_pose_error_m,
            "errors": 0,
            "reconnects": 0,
        }


class SimAutopilot:
    """``sim://``'s pose sink (:class:`drivers.AutopilotLink`): accepts the SLAM pose like an
    autopilot would and keeps its position error against the truth [m] for stats().

    ``truth`` maps a host time [ns] to the rover's true T_world_robot (4, 4).
    """

    def __init__(self, url: str, truth: Callable[[int], np.ndarray]) -> None:
        self.url = url
        self._truth = truth
        self.poses_received = 0
        self.last_pose_error_m = float("nan")
        self.health: str | None = None

    def send_pose(
        self, pose: PoseEstimate, quality: int, reset_counter: int, vel_R_mps: np.ndarray | None = None
    ) -> None:
        self.poses_received += 1
        truth = self._truth(pose.t_ns)
        self.last_pose_error_m = float(np.linalg.norm(pose.xyz_W_m - truth[:3, 3]))

    def set_health(self, state: str | None) -> None:
        if state is not None and state not in HEALTH_STATES:
            raise DriverError(f"{self.url!r}: health {state!r}, expected one of {HEALTH_STATES}")
        self.health = state

    def stats(self) -> dict[str, Any]:
        return {
            "poses_received": self.poses_received,
            "last_pose_error_m": self.last_pose_error_m,
            "health": self.health,
        }


class NullVehicle(Driver):
    """``none://``: no vehicle. ``odometry()`` yields nothing and returns on :meth:`close`; the
    pipeline then predicts without odometry. It takes no pose (``autopilot`` is None)."""

    def __init__(self, url: str) -> None:
        self.url = url
        self._closed = threading.Event()

    @property
    def autopilot(self) -> AutopilotLink | None:
        return None

    def odometry(self, timeout_s: float = 1.0) -> Iterator[Odometry]:
        self._closed.wait()
        return
        yield  # pragma: no cover - makes this a generator

    def close(self) -> None:
        self._closed.set()

    def stats(self) -> dict[str, Any]:
        # "poses_received" stays for the health output's shape: always 0, no pose comes here
        return {"samples": 0, "poses_received": 0, "errors": 0, "reconnects": 0}


# --------------------------------------------------------------------------------------------
# Factories named in drivers/__init__.py and the camera's registration below


def open_sim_camera(url: str, **options: Any) -> SimCamera:
    """``sim://?width=..&fps=..`` → an unopened :class:`SimCamera` (open it with ``with``).

    ``options`` override URL parameters by name; ``t0_ns`` fixes the shared clock's start.
    """
    t0 = _pop_t0(url, options)
    return SimCamera(url, parse_sim_url(url, **options), t0)


def open_sim_vehicle(url: str, **options: Any) -> SimVehicle:
    """``sim://?seed=..&speed=..&noise=..`` → an unopened :class:`SimVehicle`."""
    t0 = _pop_t0(url, options)
    return SimVehicle(url, parse_sim_url(url, **options), t0)


def open_null_vehicle(url: str, **options: Any) -> NullVehicle:
    """``none://`` → a vehicle link that provides no odometry."""
    check_null_url(url, **options)
    return NullVehicle(url)


def check_sim_url(url: str, **options: Any) -> None:
    """What :func:`open_sim_camera` and :func:`open_sim_vehicle` refuse in ``url`` (DriverError)."""
    options = dict(options)
    _pop_t0(url, options)
    parse_sim_url(url, **options)


def check_null_url(url: str, **options: Any) -> None:
    parts = urlsplit(url)
    if parts.netloc or parts.path not in ("", "/") or parts.query or options:
        raise DriverError(f"{url!r}: none:// takes no host, path, parameters or options")


def param_names() -> list[str]:
    """Every ``sim://`` URL parameter, for docs and error messages."""
    return [f.name for f in fields(SimParams)]


def sim_url(world: str = "", **params: Any) -> str:
    """``sim://WORLD?key=value&...`` of the parameters given (in their order), for programs that
    drive the simulated rover (robotd.research.sitl)."""
    query = "&".join(f"{k}={v}" for k, v in params.items())
    return f"sim://{world}{'?' if query else ''}{query}"


# --------------------------------------------------------------------------------------------
# The camera's registration (drivers.cameras)

# the clock start of an unpaced replay (realtime=0): fixed, so two replays of the same URL write
# the same trajectory file, stamps included (a paced one runs on the host's monotonic clock)
SIM_REPLAY_T0_NS = 1_000_000_000


class SimCameraDriver(CameraBase):
    """``sim://`` (its kind is registered in drivers.cameras): endless or ``duration`` long, paced by
    default, its own rover's odometry."""

    def open(self, url: str, **options: Any) -> SimCamera:
        return open_sim_camera(url, **options)

    def check_url(self, url: str, **options: Any) -> None:
        check_sim_url(url, **options)

    def frame_total(self, camera: Any) -> int | None:
        return camera.n_frames  # type: ignore[no-any-return]

    def paced(self, url: str) -> str:
        return url  # realtime=1 is its default

    def replay_options(self, url: str) -> dict[str, Any]:
        """Unpaced (``realtime=0``), the clock starts at :data:`SIM_REPLAY_T0_NS`."""
        realtime = dict(parse_qsl(urlsplit(url).query)).get("realtime", "1")
        return {"t0_ns": SIM_REPLAY_T0_NS} if realtime.strip() in ("0", "false", "False") else {}

    def replay_vehicle(self, source: str, url: str, odometry: DatasetOdometry | None) -> str | None:
        """The simulated rover's own noisy odometry, same world and clock as its camera (none with
        ``odometry=0`` in the URL: vision only)."""
        return url


SIM_CAMERA = SimCameraDriver()
