#!/usr/bin/env python3
"""Fault-injection suite (issue 15): the real daemon, one fault per run, and what came of it.

Each fault starts ``python -m robotd run`` (or ``record``) as a subprocess with its own temporary
state directory, configuration, Zenoh port and sd_notify socket, waits for READY=1, injects the
fault, and stops the daemon with SIGTERM (unless the fault is that it stops). The vehicle inputs
are real: a trajectory-following MCU on a pseudo-terminal (``serial://``), a mock ArduPilot on
loopback UDP (``mavlink+udp://``), or ``sim://``; both follow the simulated rover the ``sim://``
camera sees (the daemon logs the camera clock's start, ``t0_ns``), so their odometry agrees with
the images as a real rover's does. Per fault it reports:

- ``survived``: the daemon kept running through the fault, kept stepping and stopped cleanly on
  SIGTERM (exit 0, no traceback), or, where it cannot go on (a refused configuration, a camera that
  is gone), exited with its documented non-zero status and one clear error line; for a SIGKILL,
  the next start comes up on what was left;
- ``data_lost``: the saved map (or recording) is gone, does not load, or is poisoned: after the
  fault the error against the simulated truth exceeds the same run without the fault by more than
  ``ERR_MARGIN_M``, or the saved map holds more than ``LANDMARK_FACTOR`` times its landmarks;
- ``error_shown``: the log line or health problem the operator sees (``shown``: it was there).

A fault passes when it survived, lost nothing and showed what it should. The "without the fault"
figures come from one baseline run per vehicle input (sim, serial, MAVLink), made on demand.

    python bench/faults.py [--json] [--faults a,b] [--set SECTION.KEY=VALUE ...] [--keep DIR]

``--set`` overrides a configuration key in every run (e.g. to check that the suite fails when a
protection is switched off: ``--set vehicle.max_speed_mps=1e30``). Exit status 1 when any fault
fails. docs/reliability.md ("Fault-injection suite") lists the faults and the measured results.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import random
import re
import resource
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from drivers.mavlink_link import mavlink_module, mavutil  # noqa: E402
from drivers.mavlink_mock import MockAutopilot  # noqa: E402
from drivers.mcu_sim import McuSimulator, open_pty  # noqa: E402
from drivers.serial_protocol import WHEEL_VEL_VALID, WheelOdometry  # noqa: E402
from drivers.simworld import build_world  # noqa: E402
from robotd.config import parse_overrides  # noqa: E402
from robotd.core.errors import ConfigError, PersistenceError  # noqa: E402
from robotd.formats.persist import MAP_FILENAME, MapStore  # noqa: E402

FPS = 10  # the simulated camera's rate: the daemon keeps up with it on a loaded 2-core machine
CAMERA = f"sim://?fps={FPS}"
T_PRE_S = 3.0  # normal running after READY=1 before the fault
T_POST_S = 4.0  # running after the fault before SIGTERM
READY_TIMEOUT_S = 120.0  # the first start on a machine compiles the numba kernels (~20-60 s)
ERR_MARGIN_M = 0.5  # the error against truth may exceed the fault-free run's by this much
# a fault that leaves the rover unmeasured (a frozen host: no frame and no odometry) may add a
# third of the distance driven blind: no sensor saw that motion, and no guess knows a 4 s turn
# (docs/reliability.md, "Across a stall"); the same bound as tests/robotd/pipeline/test_stall.py
BLIND_FRACTION = 1.0 / 3.0
SIM_SPEED_MPS = 1.0  # sim://'s default speed (drivers/sim.py SimParams.speed)
LANDMARK_FACTOR = 3.0  # the saved map may hold this many times the fault-free run's landmarks
MAVLINK_TRACK_M = 0.4  # the mock autopilot's track width (its WHEEL_DISTANCE geometry)
ROBOT = "r1"


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int | float):
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)  # a TOML basic string is a JSON string for what we write
    if isinstance(v, list):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    raise TypeError(f"no TOML for {v!r}")


def to_toml(tree: dict[str, dict[str, Any]]) -> str:
    return "".join(
        f"[{sec}]\n" + "".join(f"{k} = {toml_value(v)}\n" for k, v in keys.items()) + "\n" for sec, keys in tree.items()
    )


def parse_sets(pairs: list[str]) -> dict[str, dict[str, Any]]:
    """["slam.n_particles=50", ...] -> {"slam": {"n_particles": 50}} (robotd.config.parse_overrides)."""
    try:
        return parse_overrides(pairs)
    except ConfigError as exc:
        raise SystemExit(f"faults: {exc}") from exc


def merge(a: dict[str, dict[str, Any]], b: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    out = {k: dict(v) for k, v in a.items()}
    for sec, keys in b.items():
        out.setdefault(sec, {}).update(keys)
    return out


def map_info(path: Path) -> dict[str, Any]:
    """Whether a map file loads (through robotd's own reader, on a copy: a bad file is moved
    aside by it), and its landmark count."""
    with tempfile.TemporaryDirectory(prefix="faults-map-") as tmp:
        shutil.copyfile(path, Path(tmp) / MAP_FILENAME)
        try:
            state = MapStore(Path(tmp), ROBOT).load()["state"]
        except PersistenceError as exc:
            return {"loads": False, "error": str(exc), "landmarks": None}
    return {"loads": True, "landmarks": len(state["database"]["ids"]), "bytes": path.stat().st_size}


# ----------------------------------------------------------------------------------------------
# vehicles that follow the simulated rover


class Follower:
    """The simulated rover's body velocity and yaw rate at host time ``t_ns``, once the daemon's
    ``sim://`` camera has started its clock (``t0_ns()``); stationary before."""

    _world: Any = None

    def __init__(self, t0_ns: Callable[[], int | None]) -> None:
        if Follower._world is None:
            Follower._world = build_world(1, "yard", 1.0, 0.0)
        self.trajectory = Follower._world.trajectory
        self.t0_ns = t0_ns

    def motion(self, t_ns: int) -> tuple[float, float]:
        t0 = self.t0_ns()
        if t0 is None or t_ns < t0:
            return 0.0, 0.0
        st = self.trajectory.state((t_ns - t0) / 1e9)
        return float(st.vel_R_mps[0]), float(st.rate_R_radps[2])


class FaultyMcu(McuSimulator):
    """The reference MCU (drivers.mcu_sim) driving the simulated rover's path, with faults."""

    def __init__(self, fd: int, follower: Follower) -> None:
        super().__init__(fd, rate_hz=100.0, speed_mps=0.0, yaw_rate_radps=0.0)
        self.follower = follower
        self.silent = False  # write nothing
        self.corrupt_all = False  # every frame with a CRC error
        self.extra_speed_mps = 0.0  # added to both wheels (ticks and speeds)
        self.tick_jump = False  # the next wheel frame's left ticks read 2**31 - 1
        self.nan_speeds = False  # wheel frames with NaN speeds (speeds only: no ticks)
        self._last_wheel_ns = 0

    def _advance(self, t_ns: int) -> None:
        v, w = self.follower.motion(t_ns)
        self.speed_mps, self.yaw_rate_radps = v + self.extra_speed_mps, w
        super()._advance(t_ns)

    def _write(self, data: bytes) -> None:
        if not self.silent:
            super()._write(data)

    def send(self, msg: Any, t_us: int | None = None) -> None:
        if self.corrupt_all:
            with self._lock:
                self._corrupt_next = 1
        super().send(msg, t_us)

    def send_wheels(self) -> None:
        t_ns = time.monotonic_ns()
        # the jump goes in a frame on schedule: one that a late loop sends right after the last is
        # merged into the next interval by the link (min_tick_interval_s) and never differenced
        on_schedule = t_ns - self._last_wheel_ns > 8_000_000
        self._last_wheel_ns = t_ns
        if self.tick_jump and on_schedule:
            self.tick_jump = False
            self._advance(t_ns)
            v_l, v_r = self.wheel_speeds()
            ticks_r = math.floor(self._s_r / self.geometry.m_per_tick)
            self.send(WheelOdometry(3, 2**31 - 1, ticks_r, v_l, v_r), self.mcu_time_us(t_ns))
            return
        if self.nan_speeds:
            self._advance(t_ns)
            self.send(WheelOdometry(WHEEL_VEL_VALID, 0, 0, math.nan, math.nan), self.mcu_time_us(t_ns))
            return
        super().send_wheels()


class FaultyAutopilot(MockAutopilot):
    """The mock ArduPilot Rover (drivers.mavlink_mock) driving the simulated rover's path, with
    faults. Injections run on its own thread (pymavlink's encoder is not thread-safe)."""

    def __init__(self, follower: Follower) -> None:
        super().__init__(speed_mps=0.0, yaw_rate_radps=0.0, track_width_m=MAVLINK_TRACK_M)
        self.follower = follower
        self.wheel_jump_m = 0.0  # added once to the next WHEEL_DISTANCE
        self.huge_until = 0.0  # until then (monotonic s): WHEEL_DISTANCE and velocities ±3e38
        self.spoof_system_time = 0  # SYSTEM_TIMEs with random boot times still to send
        self.timesync_flood = 0  # TIMESYNC requests still to send
        self.flood_ts1: set[int] = set()
        self.flood_replies = 0
        self._huge_sign = 1.0

    def _advance(self, t_ns: int) -> None:
        self.speed_mps, self.yaw_rate_radps = self.follower.motion(t_ns)
        super()._advance(t_ns)

    def _send_stream(self, t_ns: int) -> None:
        mav = self.conn.mav
        boot_ms = self.boot_time_ns(t_ns) // 1_000_000
        if self.wheel_jump_m:
            jump, self.wheel_jump_m = self.wheel_jump_m, 0.0
            self._advance(t_ns)
            mav.wheel_distance_send(boot_ms * 1000, 2, [self._s_l + jump, self._s_r + jump] + [0.0] * 14)
            return
        if time.monotonic() < self.huge_until:
            self._advance(t_ns)
            self._huge_sign = -self._huge_sign
            big = 3e38 * self._huge_sign
            mav.attitude_send(boot_ms, 0.0, 0.0, self._yaw, 0.0, 0.0, self.yaw_rate_radps)
            mav.wheel_distance_send(boot_ms * 1000, 2, [big, big] + [0.0] * 14)
            mav.local_position_ned_send(boot_ms, 0.0, 0.0, 0.0, big, -big, 0.0)
            return
        for _ in range(min(self.spoof_system_time, 40)):
            self.spoof_system_time -= 1
            mav.system_time_send(0, random.randrange(0, 2**32))
        for _ in range(min(self.timesync_flood, 40)):
            self.timesync_flood -= 1
            ts1 = time.monotonic_ns()
            self.flood_ts1.add(ts1)
            mav.timesync_send(0, ts1)
        super()._send_stream(t_ns)

    def _handle(self, msg: Any, t_ns: int) -> None:
        if msg.get_type() == "TIMESYNC" and msg.tc1 != 0 and msg.ts1 in self.flood_ts1:
            self.flood_replies += 1
            return
        super()._handle(msg, t_ns)


# ----------------------------------------------------------------------------------------------
# one daemon run


class Notify:
    """systemd's notify socket, played by a datagram socket."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.sock.settimeout(0.1)
        self.messages: list[str] = []
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)
        self._t.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                self.messages.append(self.sock.recv(65536).decode(errors="replace"))
            except TimeoutError:
                continue
            except OSError:
                return

    def has(self, field: str) -> bool:
        return any(field in m.split("\n") for m in list(self.messages))

    def close(self) -> None:
        self._stop.set()
        self._t.join(1)
        self.sock.close()


STATUS_ERR = re.compile(r"\| err (?P<err>[0-9.]+|n/a)(?: m)? \|")
T0_LINE = re.compile(r"sim world seed=\d+ \w+: start t0_ns=(?P<t0>\d+)")


@dataclass
class Line:
    t: float  # bench monotonic time it arrived
    text: str


class Run:
    """One ``robotd`` subprocess with its own directory, config, ports and notify socket."""

    def __init__(
        self,
        suite: Suite,
        name: str,
        *,
        vehicle: str = "sim",
        config: dict[str, dict[str, Any]] | None = None,
        raw_config: bytes | None = None,
        state_dir: Path | None = None,
        command: tuple[str, ...] = ("run",),
        prefix: tuple[str, ...] = (),
        preexec: Callable[[], None] | None = None,
        zenoh: bool = True,
    ) -> None:
        self.suite = suite
        self.dir = suite.root / name
        self.dir.mkdir(parents=True, exist_ok=True)
        self.state_dir = state_dir or self.dir / "state"
        self.port = free_port()
        self.vehicle_kind = vehicle
        self.lines: list[Line] = []
        self.health: list[tuple[float, dict[str, Any]]] = []
        self._t0_ns: int | None = None
        self.mcu: FaultyMcu | None = None
        self.autopilot: FaultyAutopilot | None = None
        self._pty_fds: tuple[int, int] | None = None
        self._zenoh: Any = None
        self.proc: subprocess.Popen[str] | None = None
        self.returncode: int | None = None
        vehicle_url = self._vehicle(vehicle)
        tree: dict[str, dict[str, Any]] = {
            "robot": {"id": ROBOT},
            "camera": {"url": CAMERA},
            "vehicle": {"url": vehicle_url},
            "zenoh": {"enabled": zenoh, "listen": [f"tcp/127.0.0.1:{self.port}"], "health_period_s": 0.5},
            "persistence": {"state_dir": str(self.state_dir), "save_period_s": 2.0},
        }
        tree = merge(merge(tree, config or {}), suite.overrides)
        self.config = self.dir / "robotd.toml"
        if raw_config is not None:
            self.config.write_bytes(raw_config)
        else:
            self.config.write_text(to_toml(tree))
        self.zenoh_enabled = bool(tree["zenoh"].get("enabled", True)) and raw_config is None
        self.notify = Notify(self.dir / "notify.sock")
        argv = [sys.executable, "-m", "robotd", *command, "--config", str(self.config)]
        env = dict(os.environ, NOTIFY_SOCKET=str(self.notify.path), PYTHONPATH=str(REPO))
        env.pop("JOURNAL_STREAM", None)
        self.t_start = time.monotonic()
        self.proc = subprocess.Popen(
            [*prefix, *argv],
            cwd=REPO,
            env=env,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            errors="replace",
            preexec_fn=preexec,
        )
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    # -- vehicles ------------------------------------------------------------------------------
    def t0_ns(self) -> int | None:
        return self._t0_ns

    def _vehicle(self, kind: str) -> str:
        if kind == "sim":
            return CAMERA
        if kind == "serial":
            master, slave, path = open_pty()
            self._pty_fds = (master, slave)
            self.mcu = FaultyMcu(master, Follower(self.t0_ns))
            self.mcu.start()
            return f"serial://{path}"
        if kind == "mavlink":
            ap = self.autopilot = FaultyAutopilot(Follower(self.t0_ns))
            ap.start()
            return f"{ap.url}?track_width_m={MAVLINK_TRACK_M}"
        raise ValueError(kind)

    # -- output --------------------------------------------------------------------------------
    def _read(self) -> None:
        assert self.proc is not None and self.proc.stdout is not None
        for text in self.proc.stdout:
            text = text.rstrip("\n")
            self.lines.append(Line(time.monotonic(), text))
            m = T0_LINE.search(text)
            if m and self._t0_ns is None:
                self._t0_ns = int(m.group("t0"))

    def text(self) -> str:
        return "\n".join(ln.text for ln in list(self.lines))

    def find(self, pattern: str, after: float = 0.0) -> str | None:
        rx = re.compile(pattern)
        for ln in list(self.lines):
            if ln.t >= after and rx.search(ln.text):
                return ln.text
        return None

    def count(self, pattern: str, after: float = 0.0) -> int:
        rx = re.compile(pattern)
        return sum(1 for ln in list(self.lines) if ln.t >= after and rx.search(ln.text))

    def errors_vs_truth(self, after: float = 0.0) -> list[float]:
        """The error against the simulated truth [m] of each once-a-second status line."""
        out = []
        for ln in list(self.lines):
            m = STATUS_ERR.search(ln.text)
            if ln.t >= after and m and m.group("err") != "n/a":
                out.append(float(m.group("err")))
        return out

    def problems(self, after: float = 0.0) -> list[str]:
        """The health problems shown (the status lines' DEGRADED/FAILED: ..., and the health
        documents' ``problems``), in the order they first appeared, each kind once."""
        shown: list[tuple[float, str]] = []
        for ln in list(self.lines):
            m = re.search(r"\| (DEGRADED|FAILED): (.*)$", ln.text)
            if ln.t >= after and m:
                shown += [(ln.t, p) for p in m.group(2).split(", ")]
        shown += [(t, p) for t, doc in list(self.health) if t >= after for p in doc.get("problems", [])]
        seen: list[str] = []
        kinds: set[str] = set()
        for _, p in sorted(shown, key=lambda tp: tp[0]):
            kind = re.sub(r"[\d.e+-]+", "N", p)
            if kind not in kinds:
                kinds.add(kind)
                seen.append(p)
        return seen

    def steps_after(self, after: float) -> int:
        """frames_processed gained since ``after`` (from the health documents)."""
        docs = [(t, d) for t, d in list(self.health) if "frames_processed" in d]
        before = [d["frames_processed"] for t, d in docs if t <= after]
        later = [d["frames_processed"] for t, d in docs if t > after]
        if not later:
            return 0
        return int(later[-1] - (before[-1] if before else 0))

    # -- lifecycle -----------------------------------------------------------------------------
    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def wait_ready(self, timeout_s: float = READY_TIMEOUT_S) -> bool:
        t_end = time.monotonic() + timeout_s
        while time.monotonic() < t_end:
            if self.notify.has("READY=1"):
                self.t_ready = time.monotonic()
                if self.zenoh_enabled:
                    self._subscribe()
                return True
            if not self.alive():
                return False
            time.sleep(0.05)
        return False

    def _subscribe(self) -> None:
        import zenoh

        conf = zenoh.Config()
        conf.insert_json5("mode", '"client"')
        conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{self.port}"]))
        conf.insert_json5("scouting/multicast/enabled", "false")
        try:
            self._zenoh = zenoh.open(conf)
        except Exception as exc:  # zenoh raises its own ZError
            self.lines.append(Line(time.monotonic(), f"[bench] zenoh client could not connect: {exc}"))
            return

        def on_health(sample: Any) -> None:
            with contextlib.suppress(ValueError):
                self.health.append((time.monotonic(), json.loads(sample.payload.to_bytes())))

        self._sub = self._zenoh.declare_subscriber(f"robotd/{ROBOT}/health", on_health)

    def wait_exit(self, timeout_s: float) -> int | None:
        assert self.proc is not None
        try:
            self.returncode = self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            return None
        self._reader.join(2.0)
        return self.returncode

    def stop(self, timeout_s: float = 15.0) -> int | None:
        """SIGTERM, and the exit status (None: it did not stop in time and was killed)."""
        if self.alive():
            assert self.proc is not None
            self.proc.send_signal(signal.SIGTERM)
            if self.wait_exit(timeout_s) is None:
                self.proc.kill()
                self.wait_exit(5.0)
                self.returncode = None
                return None
        return self.wait_exit(5.0)

    def close(self) -> None:
        if self.alive():
            assert self.proc is not None
            self.proc.kill()
            self.wait_exit(5.0)
        if self._zenoh is not None:
            with contextlib.suppress(Exception):
                self._zenoh.close()
        if self.mcu is not None:
            self.mcu.stop()
        if self.autopilot is not None:
            self.autopilot.stop()
        if self._pty_fds is not None:
            for fd in self._pty_fds:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self.notify.close()
        (self.dir / "output.log").write_text(self.text() + "\n")
        with (self.dir / "health.jsonl").open("w") as f:
            for t, doc in list(self.health):
                f.write(json.dumps({"bench_t": round(t - self.t_start, 3), **doc}, default=str) + "\n")


def sleep_until(t: float) -> None:
    time.sleep(max(0.0, t - time.monotonic()))


# ----------------------------------------------------------------------------------------------
# results


@dataclass
class Result:
    fault: str
    expected: str
    survived: bool = False
    data_lost: bool = True
    shown: bool = False
    error_shown: str = ""
    figures: dict[str, Any] = field(default_factory=dict)
    failed_checks: list[str] = field(default_factory=list)
    note: str = ""
    seconds: float = 0.0

    @property
    def ok(self) -> bool:
        return self.survived and not self.data_lost and self.shown

    def check(self, what: str, holds: bool, kind: str) -> bool:
        """Record a check of ``kind`` ("survived", "data", "shown"); a failed one is listed."""
        if not holds:
            self.failed_checks.append(f"{kind}: {what}")
        return holds

    def to_json(self) -> dict[str, Any]:
        return {
            "fault": self.fault,
            "expected": self.expected,
            "survived": self.survived,
            "data_lost": self.data_lost,
            "shown": self.shown,
            "error_shown": self.error_shown,
            "ok": self.ok,
            "failed_checks": self.failed_checks,
            "figures": self.figures,
            "note": self.note,
            "seconds": round(self.seconds, 1),
        }


@dataclass
class Baseline:
    err_max_m: float
    landmarks: int
    map_path: Path


class Suite:
    def __init__(self, root: Path, overrides: dict[str, dict[str, Any]]) -> None:
        self.root = root
        self.overrides = overrides
        self._baselines: dict[str, Baseline] = {}

    def baseline(self, vehicle: str) -> Baseline:
        """The fault-free run of a vehicle input (made once): its largest error against truth
        after T_PRE_S and its saved map."""
        if vehicle not in self._baselines:
            run = Run(self, f"baseline-{vehicle}", vehicle=vehicle)
            try:
                if not run.wait_ready():
                    raise SystemExit(f"faults: the fault-free {vehicle} run did not start:\n{run.text()[-3000:]}")
                sleep_until(run.t_ready + T_PRE_S + 2.0 + T_POST_S)
                code = run.stop()
            finally:
                run.close()
            errs = run.errors_vs_truth(after=run.t_ready + T_PRE_S)
            path = run.state_dir / MAP_FILENAME
            if code != 0 or not errs or not path.exists():
                raise SystemExit(f"faults: the fault-free {vehicle} run failed (exit {code}):\n{run.text()[-3000:]}")
            info = map_info(path)
            self._baselines[vehicle] = Baseline(max(errs), int(info["landmarks"] or 0), path)
        return self._baselines[vehicle]

    def seed_map(self) -> Path:
        """A valid saved map (the sim baseline's), to resume from."""
        return self.baseline("sim").map_path


# ----------------------------------------------------------------------------------------------
# the faults


@dataclass(frozen=True)
class Fault:
    name: str
    group: str
    injects: str
    expected: str
    fn: Callable[[Suite, Result], None]


FAULTS: dict[str, Fault] = {}


def fault(name: str, group: str, injects: str, expected: str) -> Callable[[Callable[[Suite, Result], None]], Any]:
    def register(fn: Callable[[Suite, Result], None]) -> Callable[[Suite, Result], None]:
        FAULTS[name] = Fault(name, group, injects, expected, fn)
        return fn

    return register


KEEPS_RUNNING = "keeps running"


def judge_running(
    suite: Suite,
    res: Result,
    run: Run,
    t_fault: float,
    code: int | None,
    *,
    shown: str | None,
    problem: str | None = None,
    blind_m: float = 0.0,
) -> None:
    """The common verdict of a fault the daemon must run through: it was alive until SIGTERM,
    stepped after the fault, stopped with 0 and no traceback; its error against truth after the
    fault and its saved map stay within the fault-free run's bounds; ``shown`` (a log-line regex)
    and ``problem`` (a health-problem regex) are what the operator must see."""
    text = run.text()
    ok = res.check(f"exit status {code} on SIGTERM (expected 0)", code == 0, "survived")
    ok &= res.check("no traceback in the output", "Traceback" not in text, "survived")
    steps = run.steps_after(t_fault + 1.0) if run.zenoh_enabled else -1
    if run.zenoh_enabled:
        ok &= res.check(f"kept stepping after the fault ({steps} steps)", steps > 0, "survived")
    res.survived = ok
    base = suite.baseline(run.vehicle_kind)
    errs = run.errors_vs_truth(after=t_fault)
    err_max = max(errs) if errs else math.nan
    bound = base.err_max_m + max(ERR_MARGIN_M, BLIND_FRACTION * blind_m)
    path = run.state_dir / MAP_FILENAME
    info = map_info(path) if path.exists() else {"loads": False, "landmarks": None}
    lm_bound = LANDMARK_FACTOR * base.landmarks
    res.figures.update(
        {
            "err_max_after_fault_m": err_max,
            "err_final_m": errs[-1] if errs else None,
            "err_bound_m": round(bound, 3),
            "baseline_err_max_m": base.err_max_m,
            "map_landmarks": info["landmarks"],
            "baseline_landmarks": base.landmarks,
            "steps_after_fault": steps,
        }
    )
    lost = not res.check(
        f"error against truth after the fault {err_max:.3f} m <= {bound:.3f} m", err_max <= bound, "data"
    )
    lost |= not res.check("the saved map loads", bool(info["loads"]), "data")
    if info["loads"]:
        n_lm = int(info["landmarks"] or 0)
        lost |= not res.check(f"saved map landmarks {n_lm} <= {lm_bound:.0f}", n_lm <= lm_bound, "data")
    res.data_lost = lost
    shown_lines = []
    if shown is not None:
        line = run.find(shown, after=t_fault - 0.5)
        if line:
            shown_lines.append(_strip_log(line))
    problems = run.problems(after=t_fault)
    if problem is not None:
        hits = [p for p in problems if re.search(problem, p)]
        shown_lines += [f"health: {p}" for p in hits[:2]]
    res.figures["health_problems"] = problems
    need = [x for x in (shown, problem) if x is not None]
    res.shown = res.check(
        f"the operator sees {' and '.join(repr(n) for n in need)}",
        (shown is None or any(not s.startswith("health:") for s in shown_lines))
        and (problem is None or any(s.startswith("health:") for s in shown_lines)),
        "shown",
    )
    res.error_shown = " / ".join(shown_lines) if shown_lines else ("(nothing)" if not need else "")


def _strip_log(line: str) -> str:
    """A log line without its time stamp."""
    return re.sub(r"^\d\d:\d\d:\d\d\.\d+ ", "", line)


def running_fault(
    suite: Suite,
    res: Result,
    name: str,
    vehicle: str,
    inject: Callable[[Run], None],
    *,
    fault_s: float = 0.0,
    end: Callable[[Run], None] | None = None,
    shown: str | None,
    problem: str | None = None,
    config: dict[str, dict[str, Any]] | None = None,
    blind_m: float = 0.0,
) -> Run:
    """Start, run T_PRE_S, ``inject``, wait ``fault_s``, ``end`` it, run T_POST_S, SIGTERM, judge.
    ``blind_m``: the distance the rover drives while nothing measures it (see BLIND_FRACTION)."""
    suite.baseline(vehicle)  # first, so that nothing else runs beside the daemon under test
    run = Run(suite, name, vehicle=vehicle, config=config)
    try:
        if not res.check("READY=1", run.wait_ready(), "survived"):
            res.survived = False
            res.error_shown = _last_error(run)
            return run
        sleep_until(run.t_ready + T_PRE_S)
        t_fault = time.monotonic()
        inject(run)
        sleep_until(t_fault + fault_s)
        if end is not None:
            end(run)
        sleep_until(t_fault + fault_s + T_POST_S)
        alive = res.check("alive until SIGTERM", run.alive(), "survived")
        code = run.stop()
        judge_running(suite, res, run, t_fault, code, shown=shown, problem=problem, blind_m=blind_m)
        res.survived &= alive
    finally:
        run.close()
    return run


def _last_error(run: Run) -> str:
    errs = [ln.text for ln in run.lines if " ERROR " in ln.text or ln.text.startswith("robotd: error")]
    return _strip_log(errs[-1]) if errs else ""


# -- serial -------------------------------------------------------------------------------------


@fault(
    "serial_tick_jump",
    "serial",
    "one wheel frame whose left tick count jumps to 2^31-1 (660 km of travel in 10 ms)",
    KEEPS_RUNNING + "; the sample is refused by the plausibility gate and counted",
)
def _serial_tick_jump(suite: Suite, res: Result) -> None:
    def inject(run: Run) -> None:
        assert run.mcu is not None
        run.mcu.tick_jump = True

    running_fault(suite, res, "serial_tick_jump", "serial", inject, shown=r"odometry sample refused \(speed")


@fault(
    "serial_overspeed",
    "serial",
    "1 s of wheel frames at +150 m/s (ticks and speeds), then the true motion again",
    KEEPS_RUNNING + "; every sample over vehicle.max_speed_mps (30) is refused and counted",
)
def _serial_overspeed(suite: Suite, res: Result) -> None:
    def inject(run: Run) -> None:
        assert run.mcu is not None
        run.mcu.extra_speed_mps = 150.0

    def end(run: Run) -> None:
        assert run.mcu is not None
        run.mcu.extra_speed_mps = 0.0

    running_fault(
        suite, res, "serial_overspeed", "serial", inject, fault_s=1.0, end=end, shown=r"odometry sample refused \(speed"
    )


@fault(
    "serial_nan",
    "serial",
    "1 s of wheel frames whose speeds are NaN (no ticks), valid CRC",
    KEEPS_RUNNING + "; counted as bad values, the link goes degraded, the tick odometry resumes",
)
def _serial_nan(suite: Suite, res: Result) -> None:
    def inject(run: Run) -> None:
        assert run.mcu is not None
        run.mcu.nan_speeds = True

    def end(run: Run) -> None:
        assert run.mcu is not None
        run.mcu.nan_speeds = False

    running_fault(suite, res, "serial_nan", "serial", inject, fault_s=1.0, end=end, shown=None, problem=r"vehicle link")


@fault(
    "serial_bad_crc",
    "serial",
    "4 s in which every frame from the MCU has a CRC error",
    KEEPS_RUNNING + "; health shows the vehicle link degraded, then lost; SLAM goes on visually",
)
def _serial_bad_crc(suite: Suite, res: Result) -> None:
    def inject(run: Run) -> None:
        assert run.mcu is not None
        run.mcu.corrupt_all = True

    def end(run: Run) -> None:
        assert run.mcu is not None
        run.mcu.corrupt_all = False

    running_fault(
        suite, res, "serial_bad_crc", "serial", inject, fault_s=4.0, end=end, shown=None, problem=r"vehicle link lost"
    )


@fault(
    "serial_silent",
    "serial",
    "4 s in which the MCU sends nothing",
    KEEPS_RUNNING + "; health shows the vehicle link lost; SLAM goes on visually",
)
def _serial_silent(suite: Suite, res: Result) -> None:
    def inject(run: Run) -> None:
        assert run.mcu is not None
        run.mcu.silent = True

    def end(run: Run) -> None:
        assert run.mcu is not None
        run.mcu.silent = False

    running_fault(
        suite, res, "serial_silent", "serial", inject, fault_s=4.0, end=end, shown=None, problem=r"vehicle link lost"
    )


@fault(
    "serial_clock_backwards",
    "runtime",
    "the MCU's clock steps back 3 s (no reset: sequence and uptime go on)",
    KEEPS_RUNNING + "; samples stamped in the past are refused (clock) and counted",
)
def _serial_clock_backwards(suite: Suite, res: Result) -> None:
    def inject(run: Run) -> None:
        assert run.mcu is not None
        with run.mcu._lock:
            run.mcu.t0_us -= 3_000_000

    running_fault(
        suite, res, "serial_clock_backwards", "serial", inject, shown=r"odometry sample refused \(clock|MCU reset"
    )


# -- MAVLink ------------------------------------------------------------------------------------


@fault(
    "mavlink_wheel_jump",
    "mavlink",
    "one WHEEL_DISTANCE 10 km beyond the last",
    KEEPS_RUNNING + "; the sample is refused by the plausibility gate and counted",
)
def _mavlink_wheel_jump(suite: Suite, res: Result) -> None:
    def inject(run: Run) -> None:
        assert run.autopilot is not None
        run.autopilot.wheel_jump_m = 10_000.0

    running_fault(suite, res, "mavlink_wheel_jump", "mavlink", inject, shown=r"odometry sample refused \(speed")


@fault(
    "mavlink_huge_values",
    "mavlink",
    "1 s of WHEEL_DISTANCE ±3e38 m and LOCAL_POSITION_NED velocities ±3e38 m/s",
    KEEPS_RUNNING + "; refused (speed) and counted, no offset left",
)
def _mavlink_huge(suite: Suite, res: Result) -> None:
    def inject(run: Run) -> None:
        assert run.autopilot is not None
        run.autopilot.huge_until = time.monotonic() + 1.0

    running_fault(
        suite, res, "mavlink_huge_values", "mavlink", inject, fault_s=1.0, shown=r"odometry sample refused \(speed"
    )


@fault(
    "mavlink_system_time_spoof",
    "mavlink",
    "567 SYSTEM_TIME messages with random boot times, from the autopilot's own id and address",
    KEEPS_RUNNING + "; no reboot is counted (a reboot needs a consistent new boot clock with heartbeats)",
)
def _mavlink_spoof(suite: Suite, res: Result) -> None:
    def inject(run: Run) -> None:
        assert run.autopilot is not None
        run.autopilot.spoof_system_time = 567

    run = running_fault(suite, res, "mavlink_system_time_spoof", "mavlink", inject, fault_s=1.0, shown=None)
    reboots = run.count(r"autopilot rebooted")
    vehicle = [d.get("vehicle") or {} for _, d in run.health]
    res.figures["reboots_counted"] = max((v.get("autopilot_reboots", 0) for v in vehicle), default=None)
    res.figures["reboot_candidates"] = max((v.get("reboot_candidates", 0) for v in vehicle), default=None)
    res.figures["reboot_log_lines"] = reboots
    res.survived &= res.check(f"no autopilot reboot counted ({reboots} log lines)", reboots == 0, "survived")
    res.error_shown = (
        f"health: vehicle.reboot_candidates {res.figures['reboot_candidates']}, "
        f"autopilot_reboots {res.figures['reboots_counted']}"
    )


@fault(
    "mavlink_timesync_flood",
    "mavlink",
    "2000 TIMESYNC requests in about 1 s",
    KEEPS_RUNNING + "; at most timesync_reply_hz (20) replies a second",
)
def _mavlink_timesync(suite: Suite, res: Result) -> None:
    holder: dict[str, float] = {}

    def inject(run: Run) -> None:
        assert run.autopilot is not None
        holder["t"] = time.monotonic()
        run.autopilot.timesync_flood = 2000

    run = running_fault(suite, res, "mavlink_timesync_flood", "mavlink", inject, fault_s=1.0, shown=None)
    ap = run.autopilot
    assert ap is not None
    sent = 2000 - ap.timesync_flood
    window_s = T_POST_S + 1.0
    vehicle = [d.get("vehicle") or {} for _, d in run.health]
    limited = max((v.get("timesync_replies_limited", 0) for v in vehicle), default=None)
    res.figures.update({"timesync_requests": sent, "timesync_replies": ap.flood_replies, "replies_limited": limited})
    limit = 20 * (window_s + 1.0)
    res.survived &= res.check(
        f"{ap.flood_replies} replies to {sent} requests <= {limit:.0f} (20/s)", ap.flood_replies <= limit, "survived"
    )
    res.shown = res.check("some replies still go out (PX4 needs them)", ap.flood_replies > 0, "shown")
    res.error_shown = (
        f"{ap.flood_replies} replies to {sent} requests; health vehicle.timesync_replies_limited {limited}"
    )


@fault(
    "mavlink_foreign_sender",
    "mavlink",
    "2 s of WHEEL_DISTANCE (+10 km steps) and HEARTBEATs from an unrelated socket, spoofing the autopilot's ids",
    KEEPS_RUNNING + "; nothing from it is used (the socket is connected to the autopilot)",
)
def _mavlink_foreign(suite: Suite, res: Result) -> None:
    sent = {"n": 0}

    def inject(run: Run) -> None:
        assert run.autopilot is not None
        target = next(iter(run.autopilot.conn.clients))  # where robotd's datagrams come from
        threading.Thread(target=_foreign_sender, args=(target, sent), daemon=True).start()

    run = running_fault(suite, res, "mavlink_foreign_sender", "mavlink", inject, fault_s=2.0, shown=None)
    res.figures["foreign_messages_sent"] = sent["n"]
    res.survived &= res.check("the foreign sender sent", sent["n"] > 0, "survived")
    # what reached robotd from it: with a connected socket, nothing (not even a rejected_source)
    vehicle = [d.get("vehicle") or {} for _, d in run.health]
    res.figures["rejected_source"] = max((v.get("rejected_source", 0) for v in vehicle), default=None)
    res.error_shown = f"(nothing reaches robotd: health vehicle.rejected_source {res.figures['rejected_source']})"


def _foreign_sender(target: tuple[str, int], sent: dict[str, int]) -> None:
    m = mavlink_module()
    conn = mavutil.mavlink_connection(f"udpout:{target[0]}:{target[1]}", source_system=1, source_component=1)
    t_end = time.monotonic() + 2.0
    s = 0.0
    try:
        while time.monotonic() < t_end:
            s += 10_000.0
            conn.mav.heartbeat_send(m.MAV_TYPE_GROUND_ROVER, m.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, m.MAV_STATE_ACTIVE)
            conn.mav.wheel_distance_send(int(time.monotonic() * 1e6), 2, [s, s] + [0.0] * 14)
            sent["n"] += 2
            time.sleep(0.02)
    finally:
        conn.close()


# -- saved maps ---------------------------------------------------------------------------------


def _persist_run(
    suite: Suite,
    res: Result,
    name: str,
    state_dir: Path,
    *,
    config: dict[str, dict[str, Any]] | None = None,
    prefix: tuple[str, ...] = (),
    seconds: float = 4.0,
) -> tuple[Run, int | None]:
    cfg = merge({"persistence": {"resume": True}}, config or {})
    run = Run(suite, name, config=cfg, state_dir=state_dir, prefix=prefix)
    try:
        ready = res.check("READY=1", run.wait_ready(), "survived")
        if ready:
            sleep_until(run.t_ready + seconds)
        alive = res.check("alive until SIGTERM", run.alive(), "survived")
        code = run.stop()
        text = run.text()
        res.survived = (
            res.check(f"exit status {code} on SIGTERM (expected 0)", code == 0, "survived")
            & res.check("no traceback in the output", "Traceback" not in text, "survived")
            & ready
            & alive
        )
    finally:
        run.close()
    return run, code


def _state_with(suite: Suite, name: str, mutate: Callable[[dict[str, Any]], None]) -> tuple[Path, bytes]:
    """A state directory holding the seed map with ``mutate`` applied, sealed with a valid
    checksum by robotd's own writer."""
    state_dir = suite.root / name / "state"
    state_dir.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(suite.seed_map(), state_dir / MAP_FILENAME)
    store = MapStore(state_dir, ROBOT)
    saved = store.load()
    mutate(saved["state"])
    store.save(saved["state"], int(saved["t_ns"]))
    return state_dir, (state_dir / MAP_FILENAME).read_bytes()


def _judge_set_aside(res: Result, run: Run, state_dir: Path, blob: bytes) -> None:
    aside = sorted(state_dir.glob(f"{MAP_FILENAME}.bad-*"))
    kept = [p for p in aside if p.read_bytes() == blob]
    res.figures["moved_aside"] = [p.name for p in aside]
    lost = not res.check("the refused map is kept byte for byte as map.robotd.bad-<time>", bool(kept), "data")
    new = state_dir / MAP_FILENAME
    info = map_info(new) if new.exists() else {"loads": False}
    lost |= not res.check("a new map was saved and loads", bool(info["loads"]), "data")
    res.data_lost = lost
    line = run.find(r"resume failed:")
    res.shown = res.check("one 'resume failed' line", line is not None and run.count(r"resume failed:") == 1, "shown")
    res.error_shown = _strip_log(line or "")


@fault(
    "map_next_id_max",
    "persistence",
    "a saved map (valid checksum) whose landmark database's next_id is 2^63-1, resumed",
    KEEPS_RUNNING + "; the map is refused whole, moved aside as map.robotd.bad-<time>, a new map is started",
)
def _map_next_id(suite: Suite, res: Result) -> None:
    def mutate(state: dict[str, Any]) -> None:
        state["database"]["next_id"] = 2**63 - 1

    state_dir, blob = _state_with(suite, "map_next_id_max", mutate)
    run, _ = _persist_run(suite, res, "map_next_id_max", state_dir)
    _judge_set_aside(res, run, state_dir, blob)


@fault(
    "map_missing_key",
    "persistence",
    "a saved map (valid checksum) without the estimator's lm_cov, resumed",
    KEEPS_RUNNING + "; refused with the key named, moved aside, a new map is started",
)
def _map_missing_key(suite: Suite, res: Result) -> None:
    def mutate(state: dict[str, Any]) -> None:
        del state["estimator"]["lm_cov"]

    state_dir, blob = _state_with(suite, "map_missing_key", mutate)
    run, _ = _persist_run(suite, res, "map_missing_key", state_dir)
    _judge_set_aside(res, run, state_dir, blob)


def _read_only_prefix(directory: Path) -> tuple[str, ...] | None:
    """The argv prefix that runs a command with ``directory`` read-only: a read-only bind mount in
    a user and mount namespace (root ignores file modes); None when this machine cannot."""
    if os.geteuid() != 0:
        directory.chmod(0o555)
        return ()
    script = 'mount --bind "$1" "$1" && mount -o remount,bind,ro "$1" "$1" && shift && exec "$@"'
    prefix = ("unshare", "-rm", "sh", "-c", script, "sh", str(directory))
    if shutil.which("unshare") is None or subprocess.run([*prefix, "true"], capture_output=True).returncode != 0:
        return None
    return prefix


@fault(
    "map_corrupt_read_only",
    "persistence",
    "a map with a flipped byte (checksum fails) in a read-only state directory, resumed",
    KEEPS_RUNNING + "; the map is left in place and ignored, never written over; saves are refused and shown",
)
def _map_corrupt_ro(suite: Suite, res: Result) -> None:
    state_dir = suite.root / "map_corrupt_read_only" / "state"
    state_dir.mkdir(parents=True, exist_ok=True)
    blob = bytearray(suite.seed_map().read_bytes())
    blob[len(blob) // 2] ^= 0xFF
    (state_dir / MAP_FILENAME).write_bytes(bytes(blob))
    prefix = _read_only_prefix(state_dir)
    if prefix is None:
        res.note = "skipped: cannot make a directory read-only here (root without user namespaces)"
        res.failed_checks.append("survived: not run")
        return
    run, _ = _persist_run(suite, res, "map_corrupt_read_only", state_dir, prefix=prefix)
    same = (state_dir / MAP_FILENAME).read_bytes() == bytes(blob)
    others = sorted(p.name for p in state_dir.iterdir() if p.name != MAP_FILENAME)
    res.figures["other_files"] = others
    res.data_lost = not (
        res.check("the corrupt map is unchanged byte for byte", same, "data")
        & res.check("nothing else written in the state directory", not others, "data")
    )
    line = run.find(r"resume failed:.*left in place and ignored")
    refused = run.find(r"map not saved:.*not written over")
    res.shown = res.check(
        "'left in place and ignored' and the refused saves are logged", bool(line and refused), "shown"
    )
    res.error_shown = " / ".join(_strip_log(x) for x in (line, refused) if x)


@fault(
    "map_dim_change",
    "persistence",
    "slam.dim changed 3 -> 2 with a 3-D map saved, resumed",
    KEEPS_RUNNING + "; the 3-D map is kept as map.<time>.robotd byte for byte, a new 2-D map is saved",
)
def _map_dim_change(suite: Suite, res: Result) -> None:
    state_dir = suite.root / "map_dim_change" / "state"
    state_dir.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(suite.seed_map(), state_dir / MAP_FILENAME)
    blob = (state_dir / MAP_FILENAME).read_bytes()
    run, _ = _persist_run(suite, res, "map_dim_change", state_dir, config={"slam": {"dim": 2}})
    kept = [p for p in state_dir.glob("map.2*.robotd") if p.read_bytes() == blob]
    res.figures["kept_as"] = [p.name for p in kept]
    new = state_dir / MAP_FILENAME
    info = map_info(new) if new.exists() else {"loads": False}
    res.data_lost = not (
        res.check("the 3-D map is kept byte for byte as map.<time>.robotd", bool(kept), "data")
        & res.check("the new map loads", bool(info["loads"]), "data")
    )
    line = run.find(r"resume failed:")
    keptline = run.find(r"kept the previous map as")
    res.shown = res.check("the mismatch and where the old map went are logged", bool(line and keptline), "shown")
    res.error_shown = " / ".join(_strip_log(x) for x in (line, keptline) if x)


def _dead_pid() -> int:
    """A pid no process has (above the kernel's pid_max)."""
    try:
        return int(Path("/proc/sys/kernel/pid_max").read_text()) + 1
    except (OSError, ValueError):
        return 2**22 + 1


@fault(
    "map_orphan_temp_files",
    "persistence",
    "two unfinished-save temp files (.map.robotd.<dead pid>.tmp, 5 MB and 1 kB) beside a valid map",
    KEEPS_RUNNING + "; both removed at start and logged; the map resumes",
)
def _map_orphans(suite: Suite, res: Result) -> None:
    state_dir = suite.root / "map_orphan_temp_files" / "state"
    state_dir.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(suite.seed_map(), state_dir / MAP_FILENAME)
    pid = _dead_pid()
    orphans = [state_dir / f".{MAP_FILENAME}.{pid}.tmp", state_dir / f".{MAP_FILENAME}.{pid + 1}.tmp"]
    orphans[0].write_bytes(os.urandom(5_000_000))
    orphans[1].write_bytes(os.urandom(1000))
    run, _ = _persist_run(suite, res, "map_orphan_temp_files", state_dir)
    left = [p.name for p in orphans if p.exists()]
    res.figures["orphans_left"] = left
    resumed = run.find(r"resumed from saved map")
    info = map_info(state_dir / MAP_FILENAME)
    res.data_lost = not (
        res.check("the map resumed", resumed is not None, "data")
        & res.check("the map saved at stop loads", bool(info["loads"]), "data")
    )
    res.survived &= res.check(f"the orphans are gone (left: {left})", not left, "survived")
    removed = run.count(r"removed .*an unfinished save")
    res.shown = res.check(f"each removal logged ({removed} of 2)", removed == 2, "shown")
    rx = re.compile(r"removed .*an unfinished save")
    res.error_shown = " / ".join(_strip_log(ln.text) for ln in run.lines if rx.search(ln.text))


# -- configuration ------------------------------------------------------------------------------


def _refused_config(
    suite: Suite, res: Result, name: str, *, config: dict[str, Any] | None = None, raw: bytes | None = None, names: str
) -> None:
    # a stand-in for a saved map (the refused start must not touch it; it never gets to read it)
    state_dir = suite.root / name / "state"
    state_dir.mkdir(parents=True, exist_ok=True)
    blob = os.urandom(100_000)
    (state_dir / MAP_FILENAME).write_bytes(blob)
    run = Run(suite, name, config=config, raw_config=raw, state_dir=state_dir)
    try:
        code = run.wait_exit(60.0)
    finally:
        run.close()
    lines = [ln.text for ln in run.lines if ln.text.strip()]
    res.figures.update(
        {
            "exit_status": code,
            "output_lines": len(lines),
            "seconds_to_exit": round(run.lines[-1].t - run.t_start, 2) if run.lines else None,
        }
    )
    res.survived = res.check(f"exit status {code} (expected 2)", code == 2, "survived") & res.check(
        f"one line of output ({len(lines)})", len(lines) == 1, "survived"
    )
    res.data_lost = not res.check("the saved map is untouched", (state_dir / MAP_FILENAME).read_bytes() == blob, "data")
    res.error_shown = lines[0] if lines else ""
    res.shown = res.check(f"the line names {names}", bool(lines) and re.search(names, lines[0]) is not None, "shown")


@fault(
    "config_n_particles_100000",
    "configuration",
    "slam.n_particles = 100000",
    "exits 2 at once with one line naming slam.n_particles and the bound",
)
def _config_particles(suite: Suite, res: Result) -> None:
    _refused_config(
        suite, res, "config_n_particles_100000", config={"slam": {"n_particles": 100000}}, names=r"slam\.n_particles"
    )


@fault(
    "config_not_utf8",
    "configuration",
    "a config file with the byte 0xff in a string",
    "exits 2 with one line: not UTF-8, the byte's offset",
)
def _config_utf8(suite: Suite, res: Result) -> None:
    _refused_config(suite, res, "config_not_utf8", raw=b'[robot]\nid = "r\xff1"\n', names=r"not UTF-8")


@fault(
    "config_deep_nesting",
    "configuration",
    "a config file with an array nested 100,000 deep",
    "exits 2 with one line: nested too deep",
)
def _config_deep(suite: Suite, res: Result) -> None:
    raw = b"[robot]\nid = " + b"[" * 100_000 + b"]" * 100_000 + b"\n"
    _refused_config(suite, res, "config_deep_nesting", raw=raw, names=r"nested too deep")


# -- runtime ------------------------------------------------------------------------------------


@fault(
    "camera_unplug",
    "runtime",
    "the camera fails mid-run (sim://?unplug=6: DriverError 'camera disconnected', as depthai raises)",
    "exits 1 (systemd restarts it) with one error line, after saving the map",
)
def _camera_unplug(suite: Suite, res: Result) -> None:
    run = Run(suite, "camera_unplug", config={"camera": {"url": f"{CAMERA}&unplug=6"}, "vehicle": {"url": CAMERA}})
    try:
        ready = res.check("READY=1", run.wait_ready(), "survived")
        code = run.wait_exit(30.0)
    finally:
        run.close()
    text = run.text()
    res.figures["exit_status"] = code
    res.survived = (
        ready
        & res.check(f"exit status {code} (expected 1)", code == 1, "survived")
        & res.check("no traceback", "Traceback" not in text, "survived")
    )
    info = map_info(run.state_dir / MAP_FILENAME) if (run.state_dir / MAP_FILENAME).exists() else {"loads": False}
    res.figures["map_landmarks"] = info.get("landmarks")
    saved_at_stop = run.find(r"map saved to", after=(run.lines[-1].t - 2.0) if run.lines else 0.0)
    res.data_lost = not (
        res.check("the map saved at the stop loads", bool(info["loads"]), "data")
        & res.check("a save at the stop", saved_at_stop is not None, "data")
    )
    line = run.find(r"ERROR .*stopping: camera stopped:")
    res.shown = res.check("'stopping: camera stopped: ...' logged as an error", line is not None, "shown")
    res.error_shown = _strip_log(line or "")


@fault(
    "frame_stall_4s",
    "runtime",
    "the daemon frozen 4 s (SIGSTOP, SIGCONT): no frames processed, then a 4 s backlog",
    KEEPS_RUNNING
    + "; the stall is shown; the error after it within the fault-free run's plus a third of the 4 m driven blind",
)
def _frame_stall(suite: Suite, res: Result) -> None:
    def inject(run: Run) -> None:
        assert run.proc is not None
        run.proc.send_signal(signal.SIGSTOP)

    def end(run: Run) -> None:
        assert run.proc is not None
        run.proc.send_signal(signal.SIGCONT)

    running_fault(
        suite,
        res,
        "frame_stall_4s",
        "sim",
        inject,
        fault_s=4.0,
        end=end,
        shown=r"stall: ",
        problem=r"stall",
        blind_m=4.0 * SIM_SPEED_MPS,
    )


def _zenoh_session(mode: str, *, listen: list[str] | None = None, connect: list[str] | None = None) -> Any:
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    if listen is not None:
        conf.insert_json5("listen/endpoints", json.dumps(listen))
    conf.insert_json5("connect/endpoints", json.dumps(connect or []))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(conf)


_ZENOH_PEER = """
import json, sys, time, zenoh
mode, endpoint = sys.argv[1], sys.argv[2]
conf = zenoh.Config()
conf.insert_json5("mode", json.dumps(mode))
conf.insert_json5("scouting/multicast/enabled", "false")
if mode == "router":
    conf.insert_json5("listen/endpoints", json.dumps([endpoint]))
else:
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
s = zenoh.open(conf)
n = [0]
if mode != "router":
    s.declare_subscriber("robotd/**", lambda smp: n.__setitem__(0, n[0] + 1))
print("up", flush=True)
while True:
    time.sleep(0.5)
    print(n[0], flush=True)
"""


def _zenoh_peer(mode: str, endpoint: str) -> subprocess.Popen[str]:
    """A Zenoh process (a router, or a client subscribed to robotd/**) that the fault kills."""
    proc = subprocess.Popen(
        [sys.executable, "-c", _ZENOH_PEER, mode, endpoint],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    assert proc.stdout is not None
    proc.stdout.readline()  # "up"
    return proc


@fault(
    "zenoh_subscriber_loss",
    "runtime",
    "a Zenoh subscriber of robotd/** (another process) killed with SIGKILL mid-stream",
    KEEPS_RUNNING + "; publishing goes on to the other subscribers",
)
def _zenoh_sub_loss(suite: Suite, res: Result) -> None:
    holder: dict[str, Any] = {}

    def inject(run: Run) -> None:
        holder["p"].kill()
        holder["p"].wait()

    suite.baseline("sim")
    run = Run(suite, "zenoh_subscriber_loss")
    try:
        if not res.check("READY=1", run.wait_ready(), "survived"):
            return
        holder["p"] = _zenoh_peer("client", f"tcp/127.0.0.1:{run.port}")
        sleep_until(run.t_ready + T_PRE_S)
        holder["got"] = holder["p"].stdout.readline() if holder["p"].stdout else ""
        t_fault = time.monotonic()
        inject(run)
        sleep_until(t_fault + T_POST_S)
        alive = res.check("alive until SIGTERM", run.alive(), "survived")
        docs_after = sum(1 for t, _ in run.health if t > t_fault + 1.0)
        code = run.stop()
        judge_running(suite, res, run, t_fault, code, shown=None)
        res.figures["health_docs_after_kill"] = docs_after
        res.survived &= alive & res.check(
            f"the other subscriber still gets health ({docs_after} docs)", docs_after > 0, "survived"
        )
    finally:
        if "p" in holder and holder["p"].poll() is None:
            holder["p"].kill()
        run.close()


@fault(
    "zenoh_router_loss",
    "runtime",
    "robotd in client mode through a Zenoh router (another process) that is killed with SIGKILL",
    KEEPS_RUNNING + "; SLAM and the map go on without Zenoh; it publishes again when a router is back",
)
def _zenoh_router_loss(suite: Suite, res: Result) -> None:
    suite.baseline("sim")
    rport = free_port()
    endpoint = f"tcp/127.0.0.1:{rport}"
    router = _zenoh_peer("router", endpoint)
    run = Run(suite, "zenoh_router_loss", config={"zenoh": {"mode": "client", "connect": [endpoint]}})
    try:
        run.port = rport  # the bench's health subscriber goes through the router too
        if not res.check("READY=1", run.wait_ready(), "survived"):
            return
        sleep_until(run.t_ready + T_PRE_S)
        t_fault = time.monotonic()
        router.kill()
        router.wait()
        sleep_until(t_fault + 2.0)
        router = _zenoh_peer("router", endpoint)  # a router is back on the same endpoint
        t_back = time.monotonic()
        sleep_until(t_fault + 2.0 + T_POST_S)
        alive = res.check("alive until SIGTERM", run.alive(), "survived")
        code = run.stop()
        judge_running(suite, res, run, t_fault, code, shown=None)
        lines_after = len(run.errors_vs_truth(after=t_fault + 1.0))
        back = sum(1 for t, _ in run.health if t > t_back)
        res.figures.update({"status_lines_after_kill": lines_after, "health_docs_after_router_back": back})
        res.survived &= alive & res.check(f"status lines go on ({lines_after})", lines_after >= T_POST_S, "survived")
        res.survived &= res.check(f"health reaches a subscriber through the new router ({back})", back > 0, "survived")
    finally:
        router.kill()
        router.wait()
        run.close()


@fault(
    "disk_full",
    "runtime",
    "map saves fail with EFBIG: RLIMIT_FSIZE of 64 kB on the daemon (SIGXFSZ ignored), resuming a saved map",
    KEEPS_RUNNING + "; each failed save logged and in health; the saved map on disk is untouched",
)
def _disk_full(suite: Suite, res: Result) -> None:
    state_dir = suite.root / "disk_full" / "state"
    state_dir.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(suite.seed_map(), state_dir / MAP_FILENAME)
    blob = (state_dir / MAP_FILENAME).read_bytes()

    def limit_file_size() -> None:  # in the child, before exec
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (65536, 65536))

    run = Run(
        suite,
        "disk_full",
        config={"persistence": {"resume": True, "save_period_s": 1.0}},
        state_dir=state_dir,
        preexec=limit_file_size,
    )
    try:
        ready = res.check("READY=1", run.wait_ready(), "survived")
        if ready:
            sleep_until(run.t_ready + 5.0)
        alive = res.check("alive until SIGTERM", run.alive(), "survived")
        code = run.stop()
    finally:
        run.close()
    text = run.text()
    res.survived = (
        ready
        & alive
        & res.check(f"exit status {code} on SIGTERM (expected 0)", code == 0, "survived")
        & res.check("no traceback", "Traceback" not in text, "survived")
    )
    tmp_left = [p.name for p in state_dir.glob(f".{MAP_FILENAME}.*.tmp")]
    res.figures.update({"failed_saves_logged": run.count(r"map not saved:"), "temp_files_left": tmp_left})
    res.data_lost = not (
        res.check("the saved map is unchanged byte for byte", (state_dir / MAP_FILENAME).read_bytes() == blob, "data")
        & res.check("no temp file left", not tmp_left, "data")
    )
    line = run.find(r"map not saved:")
    problems = run.problems()
    health = [p for p in problems if p.startswith("map save failed")]
    res.shown = res.check("'map not saved' logged and 'map save failed' in health", bool(line and health), "shown")
    res.error_shown = " / ".join([_strip_log(line or "")] + [f"health: {h}" for h in health[:1]])


KILLS_DURING_SAVE = 3


@fault(
    "sigkill_during_save",
    "runtime",
    f"SIGKILL while a map save's temp file holds the whole map, before its rename ({KILLS_DURING_SAVE} times: "
    "kill, restart resuming the map, kill again; saves every 0.5 s, an 11 MB map)",
    "killed; the map on disk is always the previous whole one; each next start removes the temp file and resumes",
)
def _sigkill_save(suite: Suite, res: Result) -> None:
    state_dir = suite.root / "sigkill_during_save" / "state"
    state_dir.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(suite.seed_map(), state_dir / MAP_FILENAME)
    orphans_mb: list[float] = []
    loads: list[bool] = []
    resumed = removed = 0
    came_up = True
    for i in range(KILLS_DURING_SAVE + 1):
        last = i == KILLS_DURING_SAVE
        cfg = {"persistence": {"resume": True, "save_period_s": 0.5}}
        run = Run(suite, f"sigkill_during_save-{i}", config=cfg, state_dir=state_dir)
        caught: Path | None = None
        try:
            ready = run.wait_ready()
            came_up &= ready
            if not ready:
                break
            if last:  # the start after the last kill: runs, and stops cleanly
                sleep_until(run.t_ready + 2.0)
                run.stop()
            else:
                sleep_until(run.t_ready + 1.5)
                assert run.proc is not None
                tmp = state_dir / f".{MAP_FILENAME}.{run.proc.pid}.tmp"
                t_end = time.monotonic() + 10.0
                while time.monotonic() < t_end and run.alive():
                    with contextlib.suppress(FileNotFoundError):
                        if tmp.stat().st_size > 0:  # written, not yet renamed: the fsync
                            run.proc.send_signal(signal.SIGKILL)
                            caught = tmp
                            break
                    time.sleep(0.0005)
                run.wait_exit(5.0)
        finally:
            run.close()
        if i > 0:
            resumed += run.find(r"resumed from saved map") is not None
            removed += run.count(r"removed .*an unfinished save")
        if last:
            break
        if caught is None or not caught.exists():
            res.failed_checks.append(f"survived: kill {i + 1} did not land during a save")
            came_up = False
            break
        orphans_mb.append(round(caught.stat().st_size / 1e6, 2))
        loads.append(bool(map_info(state_dir / MAP_FILENAME)["loads"]))
    left = [p.name for p in state_dir.glob(f".{MAP_FILENAME}.*.tmp")]
    res.figures.update(
        {
            "kills_mid_save": len(orphans_mb),
            "temp_file_mb_at_kill": orphans_mb,
            "map_loads_after_each_kill": loads,
            "restarts_resumed": resumed,
            "temp_files_removed_at_start": removed,
            "temp_files_left": left,
        }
    )
    n = KILLS_DURING_SAVE
    res.survived = (
        res.check("every start came up", came_up, "survived")
        & res.check(f"{len(orphans_mb)} of {n} kills landed mid-save", len(orphans_mb) == n, "survived")
        & res.check(f"the last start stopped with 0 ({run.returncode})", run.returncode == 0, "survived")
        & res.check(f"no temp file left ({left})", not left, "survived")
    )
    res.data_lost = not (
        res.check(f"the map loads after every kill ({loads})", len(loads) == n and all(loads), "data")
        & res.check(f"every restart resumed it ({resumed} of {n})", resumed == n, "data")
    )
    res.shown = res.check(f"each removal logged ({removed} of {n})", removed == n, "shown")
    res.error_shown = _strip_log(run.find(r"removed .*an unfinished save") or "") or "(nothing)"


@fault(
    "sigkill_during_record",
    "runtime",
    "robotd record OUT.mcap killed with SIGKILL after 4 s of recording",
    "killed; OUT.mcap.tmp replays every frame but the last second's, and says it was interrupted",
)
def _sigkill_record(suite: Suite, res: Result) -> None:
    out = suite.root / "sigkill_during_record" / "s.mcap"
    out.parent.mkdir(parents=True, exist_ok=True)
    run = Run(suite, "sigkill_during_record", command=("record", str(out)))
    try:
        if not res.check("READY=1", run.wait_ready(), "survived"):
            return
        sleep_until(run.t_ready + 4.0)
        t_kill = time.monotonic()
        steps = [d["frames_processed"] for t, d in run.health if t <= t_kill - 1.5 and "frames_processed" in d]
        assert run.proc is not None
        run.proc.send_signal(signal.SIGKILL)
        run.wait_exit(5.0)
    finally:
        run.close()
    tmp = out.with_name(out.name + ".tmp")
    res.figures["tmp_mb"] = round(tmp.stat().st_size / 1e6, 2) if tmp.exists() else None
    need = steps[-1] if steps else 1
    proc = subprocess.run(
        [sys.executable, "-m", "robotd", "replay", str(tmp), "--json", "--quiet"],
        cwd=REPO,
        env=dict(os.environ, PYTHONPATH=str(REPO)),
        capture_output=True,
        text=True,
        timeout=120,
    )
    frames = 0
    with contextlib.suppress(ValueError, IndexError):
        frames = int(json.loads(proc.stdout.strip().splitlines()[-1])["frames"])
    summary = proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else ""
    res.figures.update(
        {"frames_replayed": frames, "frames_processed_1_5_s_before_kill": need, "replay_exit": proc.returncode}
    )
    res.survived = res.check(f"replay of the .tmp exits 0 ({proc.returncode})", proc.returncode == 0, "survived")
    res.data_lost = not res.check(
        f"{frames} frames replayed >= {need} (those processed 1.5 s before the kill)", frames >= need > 0, "data"
    )
    res.shown = res.check("the replay says it was interrupted", "interrupted" in summary, "shown")
    res.error_shown = summary


# ----------------------------------------------------------------------------------------------
# the suite


def run_faults(
    names: list[str], root: Path, overrides: dict[str, dict[str, Any]], log: Callable[[str], None]
) -> list[Result]:
    suite = Suite(root, overrides)
    results = []
    for name in names:
        f = FAULTS[name]
        res = Result(name, f.expected)
        t0 = time.monotonic()
        log(f"faults: {name} ...")
        try:
            f.fn(suite, res)
        except SystemExit:
            raise
        except Exception as exc:  # a bench bug or an unforeseen failure: a failed fault, never a silent pass
            res.survived = False
            res.failed_checks.append(f"bench: {type(exc).__name__}: {exc}")
        res.seconds = time.monotonic() - t0
        log(f"faults: {name}: {'ok' if res.ok else 'FAILED ' + '; '.join(res.failed_checks)} ({res.seconds:.1f} s)")
        results.append(res)
    return results


def table(results: list[Result]) -> str:
    rows = ["| fault | expected | survived | data lost | error shown | result |", "|---|---|---|---|---|---|"]
    for r in results:
        shown = r.error_shown.replace("|", "\\|")
        if len(shown) > 160:
            shown = shown[:157] + "..."
        verdict = "ok" if r.ok else "FAILED: " + "; ".join(r.failed_checks).replace("|", "\\|")
        if r.note:
            verdict += f" ({r.note})"
        survived, lost = "yes" if r.survived else "NO", "YES" if r.data_lost else "no"
        rows.append(f"| `{r.fault}` | {r.expected} | {survived} | {lost} | {shown} | {verdict} |")
    return "\n".join(rows)


def _machine() -> str:
    cpu = "unknown CPU"
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    return f"{os.cpu_count()} cores, {cpu}, load {os.getloadavg()[0]:.2f}"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    p.add_argument("--json", action="store_true", help="print one JSON object instead of the table")
    p.add_argument("--faults", default="", help=f"comma-separated subset of: {', '.join(FAULTS)}")
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help="override a config key in every run (repeatable)",
    )
    p.add_argument("--keep", default="", help="keep each run's directory (config, state, output.log) under DIR")
    p.add_argument("--list", action="store_true", help="list the faults and exit")
    args = p.parse_args(argv)
    if args.list:
        for f in FAULTS.values():
            print(f"{f.name:28} {f.group:14} {f.injects}")
        return 0
    names = [n.strip() for n in args.faults.split(",") if n.strip()] or list(FAULTS)
    unknown = [n for n in names if n not in FAULTS]
    if unknown:
        print(f"faults: unknown fault(s) {', '.join(unknown)}; known: {', '.join(FAULTS)}", file=sys.stderr)
        return 2
    overrides = parse_sets(args.set)
    t0 = time.monotonic()
    machine = _machine()
    with contextlib.ExitStack() as stack:
        if args.keep:
            root = Path(args.keep)
            root.mkdir(parents=True, exist_ok=True)
        else:
            root = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="robotd-faults-")))
        results = run_faults(names, root, overrides, lambda s: print(s, file=sys.stderr, flush=True))
    total = time.monotonic() - t0
    failed = [r.fault for r in results if not r.ok]
    if args.json:
        print(
            json.dumps(
                {
                    "machine": machine,
                    "seconds": round(total, 1),
                    "set": args.set,
                    "failed": failed,
                    "faults": [r.to_json() for r in results],
                },
                sort_keys=True,
                default=str,
            )
        )
    else:
        print(table(results))
        print(f"\n{len(results) - len(failed)} of {len(results)} faults ok in {total:.0f} s ({machine})")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
