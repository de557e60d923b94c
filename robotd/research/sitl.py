"""The autopilot in the loop: ArduPilot's SITL Rover navigating on robotd's poses (docs/sitl.md).

::

    ardurover (SITL, --model JSON) ── servo PWM (UDP, lockstep) ──► drivers.rover_physics (here)
        ▲                                                               │ truth datagrams (UDP)
        │ ODOMETRY, HEARTBEAT, SET_GPS_GLOBAL_ORIGIN (MAVLink, UDP)      ▼
    robotd run (its own process) ◄── rendered stereo pairs ── the simulated yard, follow=…  (drivers.sim)

Everything is on loopback. The physics program (this process) integrates a car-like rover from
the autopilot's steering and throttle outputs and answers SITL with the rover's IMU, pose and
velocity; it streams the same truth to robotd's simulated camera, which renders the textured yard
from it; robotd sends ``ODOMETRY`` to the SITL, whose EKF3 fuses it (GPS off) and whose mission
code drives the rover through waypoints laid along the yard's loop. A pymavlink ground station
(here) sets the mission, arms, switches to AUTO and watches; at the end every process is stopped
and the figures come from the SITL's own DataFlash log (EKF position ``XKF1`` against the
physics's truth ``SIM``, ``VISP`` for what AP_VisualOdom did with each message) and from robotd's
health topic (budget rungs, reset counter, frames without odometry).

``run_loop(LoopOptions(...))`` runs one mission and returns :class:`LoopResult`; bench/sitl.py
runs the scenarios and prints the table; tests/robotd/research/test_sitl.py runs a short one.
The SITL binary is looked for in ``$ROBOTD_ARDUPILOT_SITL``, then in
``../shared/tools/ardupilot-sitl/ardurover`` beside the repository (:func:`find_sitl`).
"""

from __future__ import annotations

import json
import logging
import math
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import asdict, dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from drivers.rover_physics import JsonPhysicsServer, RoverModel, RoverParams
from drivers.simworld import LoopTrajectory
from robotd.core.errors import RobotdError

logger = logging.getLogger(__name__)

REPO = Path(__file__).resolve().parents[2]
SITL_ENV = "ROBOTD_ARDUPILOT_SITL"
# ArduPilot's flat-earth scaling (AP_Math/location.h): metres per 1e-7 degree of latitude
LOCATION_SCALING_FACTOR = 0.011131884502145034
HOME = (-35.363261, 149.165230, 584.0)  # ArduPilot's SITL home (CMAC), lat, lon, alt
JSON_PORT = 9002  # SITL instance I sends its JSON physics datagrams to JSON_PORT + 10·I
RC_PORT = 5501  # ... and listens for RC input on RC_PORT + 10·I (on every address: SITL's choice)
ROVER_AUTO, ROVER_HOLD, ROVER_MANUAL = 10, 4, 0  # Rover's custom modes
WHEEL_TRACK_M = 0.3  # the simulated wheel encoders' spacing (WENC_POS_Y = ∓ half of it)


def dcm_fallbacks(texts: list[str]) -> int:
    """How often the AHRS left EKF3 for DCM once EKF3 navigated on external nav (the SITL's
    STATUSTEXTs in order). Before that, ArduPilot's own start-up can switch EKF3 → DCM → EKF3 in
    tens of milliseconds: EKF3 reports active on its tilt alignment, falls back until its yaw
    aligns on the first vision message, and "is using external nav data" comes with it (seen in
    SITL on a slow VM: 60 ms of DCM 18 s before arming). That is no fallback from robotd's poses."""
    start = next((i for i, t in enumerate(texts) if "is using external nav data" in t), len(texts))
    return sum("AHRS: DCM active" in t for t in texts[start:])


class SitlError(RobotdError):
    """The loop could not run (SITL missing, a process died, a step timed out)."""


def find_sitl() -> Path | None:
    """The ``ardurover`` SITL binary: ``$ROBOTD_ARDUPILOT_SITL``, else the shared tools folder
    beside the repository; None when neither exists."""
    env = os.environ.get(SITL_ENV)
    for p in ([Path(env)] if env else []) + [REPO.parent / "shared" / "tools" / "ardupilot-sitl" / "ardurover"]:
        if p.is_file() and os.access(p, os.X_OK):
            return p
    return None


def _udp_free(port: int, host: str = "0.0.0.0") -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.bind((host, port))
        except OSError:
            return False
    return True


def bind_physics(model: RoverModel, truth_to: tuple[str, int], seed: int) -> tuple[JsonPhysicsServer, int]:
    """The physics server on the JSON port of a SITL instance number nobody on this host uses
    (its JSON and RC ports free), tried in an order drawn from ``seed``; (server, instance)."""
    order = np.random.default_rng([seed, os.getpid()]).permutation(np.arange(1, 60))
    for inst in (int(i) for i in order):
        if not _udp_free(RC_PORT + 10 * inst):
            continue
        try:
            srv = JsonPhysicsServer(model, listen=("127.0.0.1", JSON_PORT + 10 * inst), truth_to=truth_to)
            srv.start()
        except (OSError, RobotdError):
            continue
        return srv, inst
    raise SitlError("no free SITL instance number (JSON ports 9012-9592 all taken)")


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def free_tcp_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


# ---------------------------------------------------------------------------------------------
# geometry: NED <-> lat/lon as ArduPilot computes it, and the mission


def ned_to_latlon(n_m: float, e_m: float, home: tuple[float, float, float] = HOME) -> tuple[float, float]:
    """A point ``n_m`` north and ``e_m`` east of ``home`` in degrees, with ArduPilot's scaling."""
    lat0, lon0, _ = home
    lat = lat0 + n_m / LOCATION_SCALING_FACTOR * 1e-7
    scale = max(math.cos(math.radians((lat0 + lat) / 2.0)), 0.01)  # AP's longitude_scale at the midpoint
    return lat, lon0 + e_m / (LOCATION_SCALING_FACTOR * scale) * 1e-7


def latlon_to_ned(lat: np.ndarray, lon: np.ndarray, home: tuple[float, float, float] = HOME) -> np.ndarray:
    """(N, 2) north, east [m] of points (degrees) from ``home`` (inverse of :func:`ned_to_latlon`)."""
    lat = np.asarray(lat, float)
    lon = np.asarray(lon, float)
    n = (lat - home[0]) * 1e7 * LOCATION_SCALING_FACTOR
    scale = np.maximum(np.cos(np.radians((home[0] + lat) / 2.0)), 0.01)
    e = (lon - home[1]) * 1e7 * LOCATION_SCALING_FACTOR * scale
    return np.stack([n, e], 1)


def loop_mission(laps: float, spacing_m: float, yaw0_deg: float = 0.0) -> np.ndarray:
    """(K, 2) north, east [m] of waypoints laid along the simulated yard's loop every ``spacing_m``
    for ``laps`` laps, from its start (NED's origin, heading ``yaw0_deg``): the obstacle-free path
    the yard was built around."""
    traj = LoopTrajectory()
    n = max(4, math.ceil(laps * traj.length_m / spacing_m))
    s = traj.start_m + spacing_m * np.arange(1, n + 1)
    yard = np.array([traj.point_at(float(v)) for v in s])
    world = (traj.T_world_yard @ np.column_stack([yard, np.zeros(len(yard)), np.ones(len(yard))]).T).T[:, :2]
    c, si = math.cos(math.radians(yaw0_deg)), math.sin(math.radians(yaw0_deg))
    return world @ np.array([[c, si], [-si, c]])  # rows: Rz(yaw0) · (x, y)


def cross_track_m(points: np.ndarray, path: np.ndarray) -> np.ndarray:
    """Distance [m] of each point (N, 2) to the polyline ``path`` (K, 2) (its nearest leg)."""
    a, b = path[:-1], path[1:]
    ab = b - a
    L2 = np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-12)
    ap = points[:, None, :] - a[None, :, :]
    t = np.clip(np.einsum("nkj,kj->nk", ap, ab) / L2, 0.0, 1.0)
    proj = a[None] + t[..., None] * ab[None]
    return np.min(np.linalg.norm(points[:, None, :] - proj, axis=2), axis=1)  # type: ignore[no-any-return]


# ---------------------------------------------------------------------------------------------
# options and results


@dataclass(frozen=True)
class LoopOptions:
    """One closed-loop run. ``vehicle``: robotd's odometry from ``"sim"`` (the simulated rover's
    wheels and gyro, as a serial MCU would give them) or ``"mavlink"`` (the autopilot's own link);
    ``yaw_source``: ``"extnav"`` (EK3_SRC1_YAW 6, robotd is the heading) or ``"compass"`` (1);
    ``restart_at``: stop robotd and start it again from its saved map when this fraction of the
    waypoints is reached (None: never)."""

    laps: float = 2.2
    spacing_m: float = 2.5
    speed_mps: float = 1.5
    fps: float = 30.0
    vehicle: str = "sim"
    yaw_source: str = "extnav"
    yaw0_deg: float = 0.0
    viso_type: int | None = None  # None: 1 (MAVLink) with robotd's heading, 2 (T265) with the compass's
    viso_delay_ms: int = 40
    restart_at: float | None = None
    hold_for_restart: bool = False  # the rover holds (stands still) while robotd restarts
    speedup: float = 1.0
    seed: int = 1
    timeout_s: float = 300.0
    workdir: str | None = None  # keep the run's files here (else a temporary directory)
    extra_params: tuple[tuple[str, float], ...] = ()
    robotd_set: tuple[tuple[str, str], ...] = ()  # extra "section.key" = TOML value lines


@dataclass
class LoopResult:
    options: dict[str, Any]
    completed: bool = False
    reason: str = ""
    armed: bool = False
    prearm_failures: list[str] = field(default_factory=list)
    waypoints: int = 0
    mission_length_m: float = 0.0
    driven_m: float = 0.0
    mission_s: float = 0.0
    texts: list[str] = field(default_factory=list)
    figures: dict[str, Any] = field(default_factory=dict)
    robotd: dict[str, Any] = field(default_factory=dict)
    workdir: str = ""

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def sitl_params(opts: LoopOptions) -> dict[str, float]:
    """The parameters of the run on top of ArduPilot's rover.parm (docs/sitl.md explains each)."""
    p: dict[str, float] = {
        "SERIAL1_PROTOCOL": 2,  # MAVLink 2 to robotd
        "LOG_DISARMED": 1,
        "GPS1_TYPE": 0,  # no GPS: the EKF navigates on robotd
        "AHRS_EKF_TYPE": 3,
        "EK3_ENABLE": 1,
        "EK2_ENABLE": 0,
        "VISO_TYPE": opts.viso_type if opts.viso_type is not None else (1 if opts.yaw_source == "extnav" else 2),
        "VISO_DELAY_MS": opts.viso_delay_ms,
        "EK3_SRC1_POSXY": 6,
        "EK3_SRC1_VELXY": 6,
        "EK3_SRC1_POSZ": 1,
        "EK3_SRC1_VELZ": 0,
        "EK3_SRC1_YAW": 6 if opts.yaw_source == "extnav" else 1,
        "CRUISE_SPEED": opts.speed_mps,
        "CRUISE_THROTTLE": round(100.0 * opts.speed_mps / RoverParams().max_speed_mps),
        "WP_SPEED": opts.speed_mps,
        "WP_RADIUS": 0.5,
    }
    if opts.vehicle == "mavlink":
        # wheel encoders on the simulated rover (SITL's quadrature model), streamed to robotd in
        # the EXTRA1 group of its port (MAV2_* is SERIAL1's in this build): the link's odometry
        p.update(
            {
                "WENC_TYPE": 10,
                "WENC2_TYPE": 10,
                "WENC_POS_Y": -WHEEL_TRACK_M / 2,
                "WENC2_POS_Y": WHEEL_TRACK_M / 2,
                "WENC_RADIUS": 0.05,
                "WENC2_RADIUS": 0.05,
                "MAV2_EXTRA1": 25,
            }
        )
    p.update(dict(opts.extra_params))
    return p


# ---------------------------------------------------------------------------------------------
# the ground station


class Gcs:
    """A pymavlink ground station on ``udpin:127.0.0.1:port`` (the SITL's serial0 sends there).

    A reader thread keeps the latest message of each type and every STATUSTEXT; the methods
    below wait on them. Times are the SITL's (``time_boot_ms``), never the host's, where it matters.
    """

    def __init__(self, port: int) -> None:
        from drivers.mavlink_link import mavutil  # the one pymavlink importer (MAVLink 2 set up there)

        self.mavutil = mavutil
        self.conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", dialect="ardupilotmega", source_system=255)
        self.latest: dict[str, Any] = {}
        self.texts: list[tuple[float, str]] = []
        self.reached: list[int] = []
        self.acks: list[Any] = []
        self.track: list[tuple[int, float, float]] = []  # (time_boot_ms, x, y) of LOCAL_POSITION_NED
        self.xtrack: list[float] = []
        self._lock = threading.Condition()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._read, name="gcs", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.conn.close()

    def _read(self) -> None:
        while not self._stop.is_set():
            try:
                msg = self.conn.recv_match(blocking=True, timeout=0.2)
            except (OSError, ValueError):
                continue
            if msg is None:
                continue
            kind = msg.get_type()
            if kind == "BAD_DATA":
                continue
            if msg.get_srcComponent() != 1:
                continue  # ArduPilot routes robotd's own messages (component 197) to this port too
            with self._lock:
                self.latest[kind] = msg
                if kind == "STATUSTEXT":
                    self.texts.append((time.monotonic(), str(msg.text)))
                    logger.info("SITL: %s", msg.text)
                elif kind == "MISSION_ITEM_REACHED":
                    self.reached.append(int(msg.seq))
                elif kind == "COMMAND_ACK":
                    self.acks.append(msg)
                elif kind == "LOCAL_POSITION_NED":
                    self.track.append((int(msg.time_boot_ms), float(msg.x), float(msg.y)))
                elif kind == "NAV_CONTROLLER_OUTPUT":
                    self.xtrack.append(float(msg.xtrack_error))
                self._lock.notify_all()

    def wait(self, cond: Callable[[], bool], timeout_s: float, what: str, alive: Callable[[], None]) -> None:
        """Wait until ``cond()`` (called under the reader's lock) holds; ``alive()`` raises when a
        process of the loop died. Raises SitlError after ``timeout_s``."""
        t_end = time.monotonic() + timeout_s
        with self._lock:
            while not cond():
                alive()
                left = t_end - time.monotonic()
                if left <= 0:
                    raise SitlError(f"timed out after {timeout_s:.0f} s waiting for {what}")
                self._lock.wait(min(left, 0.5))

    def text_seen(self, fragment: str) -> bool:
        return any(fragment in t for _, t in self.texts)

    @property
    def target(self) -> tuple[int, int]:
        hb = self.latest.get("HEARTBEAT")
        return (hb.get_srcSystem(), hb.get_srcComponent()) if hb is not None else (1, 1)

    def command(self, cmd: int, *params: float) -> None:
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        self.conn.mav.command_long_send(*self.target, cmd, 0, *p)

    def set_rates(self, rates_hz: dict[str, float]) -> None:
        m = self.mavutil.mavlink
        for name, hz in rates_hz.items():
            msg_id = getattr(m, f"MAVLINK_MSG_ID_{name}")
            self.command(m.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 1e6 / hz)

    def set_mode(self, mode: int) -> None:
        m = self.mavutil.mavlink
        self.command(m.MAV_CMD_DO_SET_MODE, m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, mode)

    def arm(self) -> None:
        self.command(self.mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)

    def armed(self) -> bool:
        hb = self.latest.get("HEARTBEAT")
        return hb is not None and bool(hb.base_mode & self.mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED)

    def mode(self) -> int | None:
        hb = self.latest.get("HEARTBEAT")
        return None if hb is None else int(hb.custom_mode)

    def upload_mission(self, latlon: list[tuple[float, float]], alive: Callable[[], None]) -> None:
        """The mission protocol: home (item 0, ArduPilot overwrites it) and one NAV_WAYPOINT each."""
        m = self.mavutil.mavlink
        items = [HOME[:2], *latlon]
        sys_id, comp_id = self.target
        with self._lock:
            self.latest.pop("MISSION_ACK", None)
            self.latest.pop("MISSION_REQUEST", None)
            self.latest.pop("MISSION_REQUEST_INT", None)
        self.conn.mav.mission_count_send(sys_id, comp_id, len(items), m.MAV_MISSION_TYPE_MISSION)
        sent: set[int] = set()
        t_end = time.monotonic() + 30.0
        while time.monotonic() < t_end:
            alive()
            with self._lock:
                ack = self.latest.get("MISSION_ACK")
                req = self.latest.pop("MISSION_REQUEST_INT", None) or self.latest.pop("MISSION_REQUEST", None)
                if ack is None and req is None:
                    self._lock.wait(0.5)
                    continue
            if ack is not None:
                if ack.type != m.MAV_MISSION_ACCEPTED:
                    raise SitlError(f"mission refused: MISSION_ACK type {ack.type}")
                if len(sent) < len(items):
                    raise SitlError(f"mission acknowledged after {len(sent)} of {len(items)} items")
                return
            seq = int(req.seq)
            lat, lon = items[seq]
            self.conn.mav.mission_item_int_send(
                sys_id,
                comp_id,
                seq,
                m.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
                m.MAV_CMD_NAV_WAYPOINT,
                0,
                1,
                0.0,
                0.0,
                0.0,
                0.0,
                round(lat * 1e7),
                round(lon * 1e7),
                0.0,
                m.MAV_MISSION_TYPE_MISSION,
            )
            sent.add(seq)
        raise SitlError("mission upload timed out")


# ---------------------------------------------------------------------------------------------
# robotd as a process, and its health over Zenoh


def robotd_config(
    opts: LoopOptions, state_dir: Path, zenoh_ports: tuple[int, int], mav_port: int, truth_port: int
) -> str:
    """robotd's configuration for the loop (TOML)."""
    from drivers.sim import sim_url

    follow = f"127.0.0.1:{truth_port}"
    cam = sim_url("yard", fps=f"{opts.fps:g}", seed=opts.seed, follow=follow, yaw0=f"{opts.yaw0_deg:g}")
    mav = f"mavlink+udp://127.0.0.1:{mav_port}?mode=in&track_width_m={WHEEL_TRACK_M:g}"
    vehicle = mav if opts.vehicle == "mavlink" else cam
    lines = [
        "[robot]",
        'id = "sitl"',
        f"seed = {opts.seed}",
        "[camera]",
        f'url = "{cam}"',
        "[vehicle]",
        f'url = "{vehicle}"',
        "[mavlink]",
        "enabled = true",
        f'url = "{mav}"',
        "set_origin = true",
        f"origin_lat_deg = {HOME[0]}",
        f"origin_lon_deg = {HOME[1]}",
        f"origin_alt_m = {HOME[2]}",
        "[zenoh]",
        f'listen = ["tcp/127.0.0.1:{zenoh_ports[0]}"]',
        f'connect = ["tcp/127.0.0.1:{zenoh_ports[1]}"]',
        "[persistence]",
        f'state_dir = "{state_dir}"',
        "resume = true",
    ]
    by_section: dict[str, list[str]] = {}
    for key, value in opts.robotd_set:
        section, _, name = key.partition(".")
        by_section.setdefault(section, []).append(f"{name} = {value}")
    out: list[str] = []
    section = ""
    for line in lines:
        if line.startswith("["):
            if section in by_section:
                out.extend(by_section.pop(section))
            section = line[1:-1]
        out.append(line)
    if section in by_section:
        out.extend(by_section.pop(section))
    for sec, kv in by_section.items():
        out.extend([f"[{sec}]", *kv])
    return "\n".join(out) + "\n"


class RobotdProcess:
    """``robotd run --config FILE`` in its own process; its log goes to ``log_path``."""

    def __init__(self, config_path: Path, log_path: Path) -> None:
        self.config_path = config_path
        self.log_path = log_path
        self.proc: subprocess.Popen[bytes] | None = None
        self.starts = 0

    def start(self) -> None:
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        log = open(self.log_path, "ab")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "robotd", "run", "--config", str(self.config_path)],
            stdout=log,
            stderr=subprocess.STDOUT,
            cwd=REPO,
            env=env,
        )
        log.close()
        self.starts += 1

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def stop(self, timeout_s: float = 30.0) -> int | None:
        """SIGTERM (robotd saves its map), then SIGKILL after ``timeout_s``; the exit status."""
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5.0)
        return self.proc.returncode

    def log_tail(self, n: int = 40) -> str:
        try:
            return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-n:])
        except OSError:
            return ""


class HealthWatch:
    """robotd's ``health`` and ``pose`` topics over Zenoh: a peer listening on ``port``, which
    robotd connects to (so a restarted robotd finds it again)."""

    def __init__(self, port: int, robot_id: str = "sitl") -> None:
        import zenoh

        conf = zenoh.Config()
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
        conf.insert_json5("scouting/multicast/enabled", "false")
        self.session = zenoh.open(conf)
        self.health: list[dict[str, Any]] = []
        self.poses = 0
        self.counters: list[int] = []
        self._lock = threading.Lock()
        self._subs = [
            self.session.declare_subscriber(f"robotd/{robot_id}/health", self._on_health),
            self.session.declare_subscriber(f"robotd/{robot_id}/pose", self._on_pose),
        ]

    def _on_health(self, sample: Any) -> None:
        with self._lock:
            self.health.append(json.loads(sample.payload.to_bytes()))

    def _on_pose(self, sample: Any) -> None:
        doc = json.loads(sample.payload.to_bytes())
        with self._lock:
            self.poses += 1
            c = int(doc.get("reset_counter", 0))
            if not self.counters or self.counters[-1] != c:
                self.counters.append(c)

    def all(self) -> list[dict[str, Any]]:
        """Every health document received so far."""
        with self._lock:
            return list(self.health)

    def last(self) -> dict[str, Any]:
        with self._lock:
            return dict(self.health[-1]) if self.health else {}

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()
        self.session.close()


# ---------------------------------------------------------------------------------------------
# SITL


@contextmanager
def sitl_process(
    binary: Path, workdir: Path, opts: LoopOptions, instance: int, gcs_port: int, mav_port: int
) -> Iterator[Any]:
    """The SITL on loopback only, in ``workdir`` (its eeprom.bin and logs/), stopped at the end."""
    defaults = binary.parent / "rover.parm"
    extra = workdir / "robotd-loop.parm"
    extra.write_text("".join(f"{k} {v:g}\n" for k, v in sitl_params(opts).items()))
    cmd = [
        str(binary),
        "-w",
        "--model",
        "JSON:127.0.0.1",
        "--speedup",
        f"{opts.speedup:g}",
        "--defaults",
        f"{defaults},{extra}" if defaults.is_file() else str(extra),
        f"-I{instance}",
        "--home",
        f"{HOME[0]},{HOME[1]},{HOME[2]},{opts.yaw0_deg:g}",
        "--sim-address=127.0.0.1",
        "--serial0",
        f"udpclient:127.0.0.1:{gcs_port}",
        "--serial1",
        f"udpclient:127.0.0.1:{mav_port}",
    ]
    for k in (2, 3, 4, 5, 6, 7, 8):
        cmd += [f"--serial{k}", "none"]
    log = open(workdir / "sitl.out", "wb")
    proc = subprocess.Popen(cmd, cwd=workdir, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
    log.close()
    try:
        yield proc
    finally:
        stop_process(proc)


def stop_process(proc: subprocess.Popen[bytes], grace_s: float = 5.0) -> None:
    """SIGTERM, then SIGKILL after ``grace_s`` (a SITL waiting for a physics answer ignores SIGTERM)."""
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(grace_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5.0)


# ---------------------------------------------------------------------------------------------
# the run


def run_loop(opts: LoopOptions, progress: Callable[[str], None] | None = None) -> LoopResult:
    """One mission in the closed loop; raises SitlError when the SITL binary is absent."""
    binary = find_sitl()
    if binary is None:
        raise SitlError(
            f"ArduPilot SITL not found: set {SITL_ENV} or put ardurover in "
            f"{REPO.parent / 'shared' / 'tools' / 'ardupilot-sitl'}"
        )
    say = progress or (lambda s: logger.info("%s", s))
    result = LoopResult(options=asdict(opts))
    with ExitStack() as stack:
        if opts.workdir:
            workdir = Path(opts.workdir)
            workdir.mkdir(parents=True, exist_ok=True)
        else:
            workdir = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="robotd-sitl-")))
        result.workdir = str(workdir)
        gcs_port, mav_port, truth_port = free_udp_port(), free_udp_port(), free_udp_port()
        zenoh_ports = (free_tcp_port(), free_tcp_port())  # robotd's own, the watcher's
        waypoints = loop_mission(opts.laps, opts.spacing_m, opts.yaw0_deg)
        result.waypoints = len(waypoints)
        path = np.vstack([np.zeros((1, 2)), waypoints])
        result.mission_length_m = float(np.sum(np.linalg.norm(np.diff(path, axis=0), axis=1)))

        model = RoverModel(RoverParams(start_yaw_rad=math.radians(opts.yaw0_deg)), np.random.default_rng(opts.seed))
        physics, instance = bind_physics(model, ("127.0.0.1", truth_port), opts.seed)
        stack.callback(physics.close)
        gcs = Gcs(gcs_port)
        stack.callback(gcs.close)
        sitl = stack.enter_context(sitl_process(binary, workdir, opts, instance, gcs_port, mav_port))
        state_dir = workdir / "state"
        state_dir.mkdir(exist_ok=True)
        cfg_path = workdir / "robotd.toml"
        cfg_path.write_text(robotd_config(opts, state_dir, zenoh_ports, mav_port, truth_port))
        robotd = RobotdProcess(cfg_path, workdir / "robotd.log")
        stack.callback(robotd.stop)

        def alive() -> None:
            if sitl.poll() is not None:
                raise SitlError(f"SITL exited with {sitl.returncode}: {(workdir / 'sitl.out').read_text()[-2000:]}")
            if robotd.proc is not None and not robotd.alive() and not restarting.is_set():
                raise SitlError(f"robotd exited with {robotd.proc.returncode}:\n{robotd.log_tail()}")

        restarting = threading.Event()
        say("waiting for the SITL's heartbeat")
        gcs.wait(lambda: "HEARTBEAT" in gcs.latest, 60.0, "the SITL's first heartbeat", alive)
        gcs.set_rates(
            {
                "LOCAL_POSITION_NED": 10,
                "NAV_CONTROLLER_OUTPUT": 5,
                "MISSION_CURRENT": 2,
                "EKF_STATUS_REPORT": 2,
                "SERVO_OUTPUT_RAW": 2,
            }
        )
        watch = HealthWatch(zenoh_ports[1])
        stack.callback(watch.close)
        say("starting robotd")
        robotd.start()
        gcs.wait(lambda: gcs.text_seen("is using external nav data"), 120.0, "EKF3 to use external nav", alive)
        latlon = [ned_to_latlon(float(n), float(e)) for n, e in waypoints]
        gcs.upload_mission(latlon, alive)
        say(f"mission uploaded: {len(latlon)} waypoints, {result.mission_length_m:.1f} m")
        # arm (pre-arm checks may take a few seconds to pass once the EKF has settled)
        t_arm_end = time.monotonic() + 60.0
        while not gcs.armed() and time.monotonic() < t_arm_end:
            alive()
            gcs.set_mode(ROVER_HOLD)
            gcs.arm()
            time.sleep(1.0)
        result.prearm_failures = sorted({t for _, t in gcs.texts if "PreArm" in t or "Arm:" in t})
        result.armed = gcs.armed()
        if not result.armed:
            result.reason = "did not arm: " + "; ".join(result.prearm_failures[-3:])
            result.texts = [t for _, t in gcs.texts]
            return result
        gcs.set_mode(ROVER_AUTO)
        t_start = time.monotonic()
        last_seq = len(latlon)
        restart_seq = None if opts.restart_at is None else max(1, round(opts.restart_at * last_seq))
        say("AUTO")
        while time.monotonic() - t_start < opts.timeout_s:
            alive()
            if last_seq in gcs.reached or (gcs.mode() == ROVER_HOLD and gcs.reached and gcs.reached[-1] >= last_seq):
                result.completed = True
                break
            if restart_seq is not None and gcs.reached and gcs.reached[-1] >= restart_seq and robotd.starts == 1:
                say(f"waypoint {gcs.reached[-1]}: restarting robotd from its saved map")
                if opts.hold_for_restart:
                    gcs.set_mode(ROVER_HOLD)
                    gcs.wait(lambda: gcs.mode() == ROVER_HOLD and _speed(gcs) < 0.05, 20.0, "the rover to hold", alive)
                restarting.set()
                poses_before = watch.poses
                t_stop = time.monotonic()
                robotd.stop()
                robotd.start()
                restarting.clear()
                gcs.wait(partial(_more_poses, watch, poses_before + 5), 60.0, "robotd's poses after the restart", alive)
                result.figures["restart_gap_s"] = time.monotonic() - t_stop
                if opts.hold_for_restart:
                    time.sleep(2.0)  # let the autopilot take the new segment before it drives on
                    gcs.set_mode(ROVER_AUTO)
            time.sleep(0.2)
        result.mission_s = time.monotonic() - t_start
        if not result.completed:
            servo = gcs.latest.get("SERVO_OUTPUT_RAW")
            result.reason = (
                f"mission not completed in {opts.timeout_s:.0f} s (reached {gcs.reached[-1:] or 'none'}, mode "
                f"{gcs.mode()}, armed {gcs.armed()}, servos {servo and (servo.servo1_raw, servo.servo3_raw)}, "
                f"acks {[(a.command, a.result) for a in gcs.acks[-6:]]}, {gcs.latest.get('MISSION_CURRENT')}, "
                f"{gcs.latest.get('NAV_CONTROLLER_OUTPUT')})"
            )
        result.robotd = _robotd_figures(watch)
        result.texts = [t for _, t in gcs.texts]
        result.figures["gcs_xtrack_abs_max_m"] = max((abs(x) for x in gcs.xtrack), default=float("nan"))
        result.figures["physics"] = physics.stats()
        robotd.stop()
        stop_process(sitl)
        figures = analyse_log(workdir, waypoints)
        result.figures.update(figures)
        result.driven_m = float(figures.get("driven_m", 0.0))
    return result


def _more_poses(watch: HealthWatch, n: int) -> bool:
    return watch.poses > n


def _speed(gcs: Gcs) -> float:
    lp = gcs.latest.get("LOCAL_POSITION_NED")
    return math.inf if lp is None else math.hypot(float(lp.vx), float(lp.vy))


def _robotd_figures(watch: HealthWatch) -> dict[str, Any]:
    h = watch.last()
    budget = h.get("budget", {})
    at = budget.get("frames_at_level") or []
    return {
        "poses": watch.poses,
        "reset_counters": watch.counters,
        # every bump robotd's runs reported, with its reason (a run's start is not a bump)
        "reset_bumps": sorted({(int(c), str(why)) for doc in watch.all() for c, why in doc.get("reset_bumps") or []}),
        "frames_at_level": at,
        "l0_fraction": (at[0] / sum(at)) if at and sum(at) else float("nan"),
        "frames_without_odometry": h.get("frames_without_odometry"),
        "state": h.get("state"),
        "problems": h.get("problems"),
    }


# ---------------------------------------------------------------------------------------------
# the DataFlash log


def analyse_log(workdir: Path, waypoints: np.ndarray) -> dict[str, Any]:
    """Figures from the SITL's newest DataFlash log in ``workdir/logs``: EKF3 position (XKF1, core
    0) against the truth (SIM) while armed, cross-track of the truth against the mission's
    polyline, AP_VisualOdom's resets and ignored messages (VISP), and the text messages."""
    logs = sorted((workdir / "logs").glob("*.BIN"), key=lambda p: p.stat().st_mtime)
    if not logs:
        return {"log": None}
    from drivers.mavlink_link import mavutil

    mlog = mavutil.mavlink_connection(str(logs[-1]), dialect="ardupilotmega")
    sim2: list[tuple[int, float, float]] = []
    visp_t: list[int] = []
    sim: list[tuple[int, float, float]] = []
    ekf: list[tuple[int, float, float]] = []
    visp_rst: list[int] = []
    visp_ign = 0
    visp_n = 0
    armed_us: list[tuple[int, bool]] = []
    texts: list[str] = []
    origin: tuple[float, float] | None = None
    while True:
        m = mlog.recv_match(type=["SIM", "SIM2", "XKF1", "VISP", "ARM", "MSG", "ORGN"])
        if m is None:
            break
        kind = m.get_type()
        if kind == "SIM":
            sim.append((int(m.TimeUS), float(m.Lat), float(m.Lng)))
        elif kind == "SIM2":
            sim2.append((int(m.TimeUS), float(m.PN), float(m.PE)))
        elif kind == "XKF1" and int(getattr(m, "C", 0)) == 0:
            ekf.append((int(m.TimeUS), float(m.PN), float(m.PE)))
        elif kind == "VISP":
            visp_n += 1
            visp_t.append(int(m.TimeUS))
            visp_rst.append(int(getattr(m, "Rst", 0)))
            visp_ign += int(getattr(m, "Ign", 0))
        elif kind == "ARM":
            armed_us.append((int(m.TimeUS), bool(m.ArmState)))
        elif kind == "MSG":
            texts.append(str(m.Message))
        elif kind == "ORGN" and origin is None and int(getattr(m, "Type", 0)) == 0:
            origin = (float(m.Lat), float(m.Lng))
    out: dict[str, Any] = {"log": str(logs[-1].name), "visp_messages": visp_n, "visp_ignored": visp_ign}
    out["visp_reset_counters"] = sorted(set(visp_rst))
    out["texts"] = texts
    out["dcm_fallbacks"] = dcm_fallbacks(texts)
    out["stopped_aiding"] = sum("stopped aiding" in t for t in texts)
    if not (sim or sim2) or not ekf:
        return out
    if sim2:  # the truth as NED from home: the EKF origin is home (robotd sends it)
        t_sim = np.array([s[0] for s in sim2])
        truth = np.array([[s[1], s[2]] for s in sim2])
    else:
        o = origin or HOME[:2]
        t_sim = np.array([s[0] for s in sim])
        truth = latlon_to_ned(np.array([s[1] for s in sim]), np.array([s[2] for s in sim]), (o[0], o[1], 0.0))
    t_ekf = np.array([e[0] for e in ekf])
    est = np.array([[e[1], e[2]] for e in ekf])
    armed_from = next((t for t, a in armed_us if a), t_sim[0])
    vt = np.array([t for t in visp_t if t >= armed_from])
    out["visp_max_gap_s"] = float(np.diff(vt).max() * 1e-6) if vt.size > 1 else float("nan")
    keep = t_ekf >= armed_from
    if keep.any():
        tr = np.column_stack([np.interp(t_ekf[keep], t_sim, truth[:, i]) for i in range(2)])
        err = np.linalg.norm(est[keep] - tr, axis=1)
        out["ekf_error_rms_m"] = float(np.sqrt(np.mean(err**2)))
        out["ekf_error_max_m"] = float(err.max())
    moving = t_sim >= armed_from
    tr_m = truth[moving]
    if len(tr_m) > 1:
        out["driven_m"] = float(np.sum(np.linalg.norm(np.diff(tr_m, axis=0), axis=1)))
        path = np.vstack([np.zeros((1, 2)), waypoints])
        xt = cross_track_m(tr_m, path)
        out["cross_track_max_m"] = float(xt.max())
        out["cross_track_rms_m"] = float(np.sqrt(np.mean(xt**2)))
        out["cross_track_p95_m"] = float(np.percentile(xt, 95))
    return out
