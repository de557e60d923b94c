"""``sim://…&follow=HOST:PORT``: the simulated rover driven from outside (hardware in the loop).

Normally ``sim://`` drives its rover along a trajectory written beforehand. With ``follow`` set,
the rover is wherever an external physics program says it is: the program (for example
``drivers.rover_physics``, the ground-vehicle model that ArduPilot's SITL drives through its JSON
interface) sends its truth state as UDP datagrams to ``HOST:PORT``, and the simulated camera
renders the yard from that pose, the simulated vehicle link measures that motion, and every frame
carries it as its truth. So the loop autopilot → servo outputs → physics → images → robotd →
ODOMETRY → autopilot closes through the same drivers the daemon uses on ``sim://``.

Frames. The physics works in a local NED frame (x north, y east, z down, metres from the SITL's
home; the vehicle's reference point, here the camera rig's centre, at z = 0). The yard is placed
in it so that the loop's start pose (where a ``sim://`` rover stands at t = 0) is NED's origin,
heading ``yaw0`` degrees from north. robotd's world frame is that start pose, as on every
``sim://`` world, so a rover that starts at home facing ``yaw0`` starts at robotd's origin.

Time. Both processes run on one host: each datagram carries the host's ``time.monotonic_ns()`` at
which the physics computed the state, and :meth:`FollowedTrajectory.state` answers for any host
time by taking the newest state at or before it and moving it on with its own velocity and body
rates (constant twist), at most :data:`MAX_EXTRAPOLATION_S`; when the physics falls silent (SITL
paused or gone) the rover stands where it was last seen, as the real world would.
"""

from __future__ import annotations

import ipaddress
import logging
import math
import socket
import threading
from collections import deque
from collections.abc import Callable

import numpy as np

from drivers.simbase import TruthState
from robotd.core.errors import DriverError
from robotd.core.geometry import euler_to_R, se3, se3_inverse, so3_exp

logger = logging.getLogger(__name__)

MAX_EXTRAPOLATION_S = 0.25  # a state older than this is held, not moved on (the physics stopped)
_HISTORY = 512  # states kept (≥ 1 s at SITL's rates)


def parse_follow(url: str, value: str) -> tuple[str, int]:
    """``HOST:PORT`` of ``follow=`` → (host, port); loopback only (a simulator's private link)."""
    host, sep, port_s = value.rpartition(":")
    try:
        port = int(port_s, 10)
        addr = ipaddress.ip_address(host)
    except ValueError:
        raise DriverError(f"{url!r}: follow={value!r}: expected HOST:PORT, e.g. 127.0.0.1:9010") from None
    if not sep or not 0 < port < 65536:
        raise DriverError(f"{url!r}: follow={value!r}: expected HOST:PORT with a port 1..65535")
    if not addr.is_loopback:
        raise DriverError(f"{url!r}: follow={value!r}: the truth stream is listened for on loopback only")
    return host, port


class FollowedTrajectory:
    """A :class:`drivers.simworld.Trajectory` whose states come from an external physics program.

    ``T_world_yard`` is the loop's (the world frame is the loop's start pose); ``yaw0_rad`` places
    that start pose in the physics's NED frame; ``t0_ns`` is the sim session's clock start (state
    ``t_s`` is host time ``t0_ns + t_s``). Feed it with :meth:`push` or :meth:`listen`.
    """

    def __init__(self, base_T_world_yard: np.ndarray, path_yard: np.ndarray, yaw0_rad: float, t0_ns: int) -> None:
        self.T_world_yard = base_T_world_yard
        self._path_yard = path_yard
        # NED → world: the world frame is the start pose, at NED's origin heading yaw0
        self.T_world_ned = se3_inverse(se3(euler_to_R(np.array([0.0, 0.0, yaw0_rad])), np.zeros(3)))
        self.t0_ns = int(t0_ns)
        self._lock = threading.Lock()
        self._states: deque[tuple[int, np.ndarray, np.ndarray, np.ndarray]] = deque(maxlen=_HISTORY)
        self._first = threading.Event()
        self._closed = threading.Event()
        self._thread: threading.Thread | None = None
        self._sock: socket.socket | None = None
        self.received = 0
        self.rejected = 0
        self.stale_holds = 0

    # -- feeding -------------------------------------------------------------------------------
    def push(
        self, t_host_ns: int, pos_ned: np.ndarray, rpy: np.ndarray, vel_ned: np.ndarray, rates_R: np.ndarray
    ) -> None:
        """One truth state of the physics (NED position [m], roll/pitch/yaw [rad] of body FRD in
        NED, NED velocity [m/s], body rates [rad/s]) computed at host time ``t_host_ns``."""
        values = np.concatenate([pos_ned, rpy, vel_ned, rates_R]).astype(float)
        if values.shape != (12,) or not np.all(np.isfinite(values)):
            self.rejected += 1
            return
        R_ned = euler_to_R(np.asarray(rpy, float))
        T_world_robot = self.T_world_ned @ se3(R_ned, np.asarray(pos_ned, float))
        vel_R = R_ned.T @ np.asarray(vel_ned, float)
        with self._lock:
            if self._states and t_host_ns <= self._states[-1][0]:
                self.rejected += 1  # out of order or repeated: the newest wins
                return
            self._states.append((int(t_host_ns), T_world_robot, vel_R, np.asarray(rates_R, float).copy()))
        self.received += 1
        self._first.set()

    def listen(self, host: str, port: int, decode: Callable[[bytes], tuple]) -> None:
        """Receive datagrams on ``host:port`` in a thread; ``decode`` turns one into the arguments
        of :meth:`push` (raising ValueError on a bad one, which is counted and skipped)."""
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.bind((host, port))
        except OSError as exc:
            sock.close()
            raise DriverError(f"sim follow: cannot listen for the truth stream on {host}:{port}: {exc}") from None
        sock.settimeout(0.2)
        self._sock = sock
        self._thread = threading.Thread(target=self._receive, args=(sock, decode), name="sim-follow", daemon=True)
        self._thread.start()
        logger.info("sim follow: listening for the physics's truth stream on %s:%d", host, port)

    def _receive(self, sock: socket.socket, decode: Callable[[bytes], tuple]) -> None:
        while not self._closed.is_set():
            try:
                data = sock.recv(2048)
            except TimeoutError:
                continue
            except OSError:
                return
            try:
                args = decode(data)
            except ValueError as exc:
                self.rejected += 1
                if self.rejected in (1, 10, 100, 1000):
                    logger.warning("sim follow: bad truth datagram (%d so far): %s", self.rejected, exc)
                continue
            self.push(*args)

    def close(self) -> None:
        self._closed.set()
        if self._sock is not None:
            self._sock.close()
        if self._thread is not None:
            self._thread.join(1.0)

    def wait_first(self, stop: threading.Event, timeout_s: float | None = None) -> bool:
        """Block until the first state arrives (True), ``stop`` is set or the timeout passes (False)."""
        waited = 0.0
        while not self._first.wait(0.1):
            waited += 0.1
            if stop.is_set() or (timeout_s is not None and waited >= timeout_s):
                return False
        return True

    # -- Trajectory ----------------------------------------------------------------------------
    def state(self, t_s: float) -> TruthState:
        """The truth at session time ``t_s`` (host time ``t0_ns + t_s``): the newest state at or
        before it moved on by its twist (≤ MAX_EXTRAPOLATION_S; older states are held still)."""
        t_ns = self.t0_ns + round(t_s * 1e9)
        with self._lock:
            if not self._states:
                return TruthState(np.eye(4), np.zeros(3), np.zeros(3))
            i = len(self._states) - 1
            while i > 0 and self._states[i][0] > t_ns:
                i -= 1
            t_k, T, v_R, w_R = self._states[i]
        dt = (t_ns - t_k) * 1e-9
        if dt <= 0.0:
            return TruthState(T, v_R, w_R)
        if dt > MAX_EXTRAPOLATION_S:
            self.stale_holds += 1
            return TruthState(T, np.zeros(3), np.zeros(3))
        R = T[:3, :3]
        # a constant twist: the chord of the arc, along the heading halfway through the turn
        half = 0.5 * float(np.linalg.norm(w_R)) * dt
        chord = math.sin(half) / half if half > 1e-9 else 1.0
        R_mid = R @ so3_exp(w_R * dt / 2.0)
        T_new = se3(R @ so3_exp(w_R * dt), T[:3, 3] + R_mid @ (v_R * dt * chord))
        return TruthState(T_new, v_R, w_R)

    def path_points_yard(self, n: int = 720) -> np.ndarray:
        """The loop's points (the yard was laid out around it); the followed rover may leave it."""
        idx = np.linspace(0, len(self._path_yard), n, endpoint=False).astype(int)
        return self._path_yard[idx]


def truth_push_args(data: bytes) -> tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One truth datagram of ``drivers.rover_physics`` → the arguments of
    :meth:`FollowedTrajectory.push`; ValueError on a bad one."""
    from drivers.rover_physics import decode_truth  # the format has one home: the physics

    s = decode_truth(data)
    return (
        s.t_host_ns,
        np.array(s.position_ned_m, float),
        np.array(s.attitude_rad, float),
        np.array(s.velocity_ned_mps, float),
        np.array(s.rates_frd_radps, float),
    )
