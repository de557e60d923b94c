"""``robotd doctor``: check a machine for a rover install, one line per problem.

Every check is a small function of the config returning a :class:`CheckResult` (name, status,
one-line message naming the config key, device or file and what to do). Checks that the config
makes irrelevant (the OAK's checks for another camera) return ``skip`` with the reason, so the
output always lists the same checks. The camera's checks are its driver's (``host_checks``,
drivers.cameras): every registered driver's are listed, the configured camera's run. Statuses:
``ok``; ``warn`` (works, but not as it should on a rover, e.g. a cold numba cache); ``fail``
(robotd will not work like this); ``skip``.

The checks only look: they open no camera and send the autopilot nothing but a heartbeat (as
robotd does). The exceptions are the state directory, which is created when missing (the daemon
would create it too) and gets a probe file written and removed, and ``--warm``, which compiles
the numba kernels into their cache.
"""

from __future__ import annotations

import errno
import grp
import os
import pwd
import re
import socket
import stat
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import drivers
from drivers.cameras import Registration, cameras, loaded, registration
from robotd.config import Config
from robotd.core.errors import RobotdError

OK, WARN, FAIL, SKIP = "ok", "warn", "fail", "skip"
HEARTBEAT_TIMEOUT_S = 3.0  # ArduPilot sends HEARTBEAT at 1 Hz: three chances
_PACKAGE_DIR = Path(__file__).resolve().parents[1]  # robotd/: every layer's kernels


@dataclass(frozen=True, slots=True)
class CheckResult:
    name: str
    status: str  # OK | WARN | FAIL | SKIP
    message: str


def format_line(r: CheckResult) -> str:
    """``ok   zenoh: …`` / ``FAIL serial: …``: problems in capitals so they stand out in a column."""
    label = r.status.upper() if r.status in (WARN, FAIL) else r.status
    return f"{label:<4} {r.name}: {r.message}"


def summary(results: Sequence[CheckResult]) -> str:
    counts = {s: sum(r.status == s for r in results) for s in (OK, WARN, FAIL, SKIP)}
    verdict = "problems found" if counts[FAIL] else "no failures"
    return (
        f"doctor: {verdict}: {counts[OK]} ok, {counts[WARN]} warning(s), {counts[FAIL]} failed, {counts[SKIP]} skipped"
    )


def to_json(results: Sequence[CheckResult]) -> dict[str, Any]:
    return {
        "ok": not any(r.status == FAIL for r in results),
        "failed": sum(r.status == FAIL for r in results),
        "warnings": sum(r.status == WARN for r in results),
        "checks": [asdict(r) for r in results],
    }


# --------------------------------------------------------------------------------------------
# The camera's host checks (its driver's)


def _camera(cfg: Config) -> Registration | None:
    """The registration of ``camera.url``'s camera; None when none takes it (its own check says why)."""
    try:
        return registration(cfg.camera.url)
    except RobotdError:
        return None


def check_camera_host(cfg: Config) -> list[CheckResult]:
    """Every registered camera driver's checks of this machine (a USB device, a udev rule): run for
    the camera of ``camera.url``, skipped with the reason for the others."""
    configured = _camera(cfg)
    results = []
    for reg in cameras():
        driver = loaded(reg)
        for check in driver.host_checks() if driver is not None else ():
            if reg is not configured:
                why = f"camera.url is {cfg.camera.url!r}, not {reg.scheme}://"
                results.append(CheckResult(check.name, SKIP, why))
                continue
            passed, message = check.run(cfg.camera.url)
            results.append(CheckResult(check.name, OK if passed else FAIL, message))
    return results


# --------------------------------------------------------------------------------------------
# Vehicle link


def _serial_device(url: str) -> str | None:
    """The device path of a ``serial://`` or ``mavlink+serial://`` URL, else None."""
    parts = urlsplit(url)
    if parts.scheme in ("serial", "mavlink+serial"):
        return parts.path
    return None


def _user_name() -> str:
    try:
        return pwd.getpwuid(os.getuid()).pw_name
    except KeyError:
        return str(os.getuid())


def check_serial(cfg: Config) -> CheckResult:
    """The vehicle's serial device exists, is a character device, and we may read and write it."""
    name = "serial"
    device = _serial_device(cfg.vehicle.url)
    if device is None:
        return CheckResult(name, SKIP, f"vehicle.url is {cfg.vehicle.url!r}, not a serial device")
    if not device:
        return CheckResult(name, FAIL, f"vehicle.url {cfg.vehicle.url!r} names no device (serial:///dev/ttyACM0)")
    try:
        st = os.stat(device)
    except FileNotFoundError:
        return CheckResult(name, FAIL, f"{device} not found (vehicle.url): is it plugged in? ls /dev/serial/by-id/")
    except OSError as exc:
        return CheckResult(name, FAIL, f"{device}: cannot stat: {exc.strerror} (vehicle.url)")
    if not stat.S_ISCHR(st.st_mode):
        return CheckResult(name, FAIL, f"{device} is not a character device (vehicle.url): wrong path?")
    if os.access(device, os.R_OK | os.W_OK):
        return CheckResult(name, OK, f"{device} is a character device, readable and writable")
    user = _user_name()
    try:
        group = grp.getgrgid(st.st_gid).gr_name
    except KeyError:
        group = str(st.st_gid)
    member = st.st_gid in os.getgroups() or st.st_gid == os.getgid()
    if member:
        hint = f"{user} is in group {group}, but the device mode is {stat.S_IMODE(st.st_mode):04o}"
    else:
        hint = f"{user} is not in group {group}: sudo usermod -aG {group} {user}, then log in again"
    return CheckResult(name, FAIL, f"{device}: no read/write access (vehicle.url): {hint}")


def _mavlink_url(cfg: Config) -> tuple[str, str] | None:
    """(URL, the config key that set it) of the autopilot link, or None when there is none."""
    if cfg.vehicle.url.startswith("mavlink+"):
        return cfg.vehicle.url, "vehicle.url"
    if cfg.mavlink.enabled:
        return cfg.mavlink.url, "mavlink.url"
    return None


def check_mavlink(cfg: Config, timeout_s: float = HEARTBEAT_TIMEOUT_S) -> CheckResult:
    """The autopilot answers with a HEARTBEAT within ``timeout_s``."""
    name = "mavlink"
    target = _mavlink_url(cfg)
    if target is None:
        return CheckResult(name, SKIP, f"vehicle.url is {cfg.vehicle.url!r} and mavlink.enabled is false")
    url, key = target
    device = _serial_device(url)
    if device and not os.path.exists(device):
        return CheckResult(name, SKIP, f"{device} is missing ({key}; see the serial check)")
    from drivers.mavlink_link import wait_heartbeat

    options: dict[str, Any] = {}
    if cfg.mavlink.signing_key_file:
        options["signing_key"] = cfg.mavlink.signing_key_file
    try:
        hb = wait_heartbeat(url, timeout_s, **options)
    except RobotdError as exc:
        return CheckResult(name, FAIL, f"{exc} ({key})")
    if hb is None:
        return CheckResult(
            name,
            FAIL,
            f"no autopilot HEARTBEAT on {url} within {timeout_s:g} s ({key}): is the autopilot on, and its "
            "MAVLink output (SERIALn_PROTOCOL / a UDP forward) pointed here?",
        )
    sysid, autopilot = hb
    return CheckResult(name, OK, f"{url}: autopilot sysid {sysid} ({autopilot}) sends heartbeats")


# --------------------------------------------------------------------------------------------
# Zenoh


def _tcp_endpoint(endpoint: str) -> tuple[str, int] | None:
    """``tcp/HOST:PORT`` (``tcp/[::1]:PORT``) -> (host, port); other protocols -> None."""
    proto, _, addr = endpoint.partition("/")
    if proto != "tcp" or not addr:
        return None
    addr = addr.split("#", 1)[0]  # zenoh endpoint metadata/config after '#'
    host, _, port = addr.rpartition(":")
    if not host or not port.isdigit():
        raise ValueError(f"expected tcp/HOST:PORT, got {endpoint!r}")
    return host.strip("[]"), int(port)


def _bind_error(host: str, port: int) -> str | None:
    """None when (host, port) can be bound for TCP, else the reason."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except socket.gaierror as exc:
        return f"cannot resolve {host!r}: {exc.strerror}"
    family, _, _, _, sockaddr = infos[0]
    with socket.socket(family, socket.SOCK_STREAM) as s:
        # SO_REUSEADDR stays off: we want to know whether anybody holds the port
        try:
            s.bind(sockaddr)
        except OSError as exc:
            if exc.errno == errno.EADDRINUSE:
                return "in use"
            return exc.strerror or str(exc)
    return None


def check_zenoh(cfg: Config) -> list[CheckResult]:
    """Each TCP listen endpoint is free, so the daemon's Zenoh session can listen there."""
    name = "zenoh"
    if not cfg.zenoh.enabled:
        return [CheckResult(name, SKIP, "zenoh.enabled is false")]
    if cfg.zenoh.config_file:
        return [CheckResult(name, SKIP, f"zenoh.config_file {cfg.zenoh.config_file} sets the endpoints; not checked")]
    if not cfg.zenoh.listen:
        return [CheckResult(name, SKIP, "zenoh.listen is empty (nothing to bind)")]
    results = []
    for endpoint in cfg.zenoh.listen:
        try:
            hp = _tcp_endpoint(endpoint)
        except ValueError as exc:
            results.append(CheckResult(name, FAIL, f"{exc} (zenoh.listen)"))
            continue
        if hp is None:
            results.append(CheckResult(name, SKIP, f"{endpoint}: only tcp/ endpoints are checked (zenoh.listen)"))
            continue
        why = _bind_error(*hp)
        if why is None:
            results.append(CheckResult(name, OK, f"{endpoint} is free"))
        elif why == "in use":
            results.append(
                CheckResult(
                    name,
                    FAIL,
                    f"{endpoint} is in use by another process (another robotd? ss -ltnp 'sport = :{hp[1]}'): "
                    "stop it or change zenoh.listen",
                )
            )
        else:
            results.append(CheckResult(name, FAIL, f"{endpoint}: cannot bind: {why} (zenoh.listen)"))
    return results


# --------------------------------------------------------------------------------------------
# State directory, numba cache, calibration


def check_state_dir(cfg: Config) -> CheckResult:
    """The map directory exists (or is created) and takes a file: the daemon saves its map there."""
    from robotd.formats.persist import default_state_dir

    name = "state-dir"
    d = default_state_dir(cfg.persistence.state_dir)
    key = "persistence.state_dir" if cfg.persistence.state_dir else "persistence.state_dir (empty: the default)"
    existed = d.is_dir()
    probe = d / f".robotd-doctor-{os.getpid()}"
    try:
        d.mkdir(parents=True, exist_ok=True)
        probe.write_bytes(b"robotd doctor\n")
        probe.unlink()
    except OSError as exc:
        return CheckResult(name, FAIL, f"{d} is not writable: {exc.strerror or exc} ({key})")
    return CheckResult(name, OK, f"{d} {'is writable' if existed else 'created, writable'}")


def kernel_modules(package_dir: Path = _PACKAGE_DIR) -> list[Path]:
    """The source files of robotd's numba kernels: those that use robotd.core.jit's decorator."""
    decorated = re.compile(r"^\s*@jit\b", re.MULTILINE)
    return [p for p in sorted(package_dir.rglob("*.py")) if decorated.search(p.read_text(encoding="utf-8"))]


def _cache_dirs(module: Path) -> list[Path]:
    """Where numba may keep a module's cache (numba.core.caching's locators, in its order)."""
    env = os.environ.get("NUMBA_CACHE_DIR")
    if env:
        return [Path(env)]  # numba then uses this tree only (a subdirectory named after the source dir)
    user_wide = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "numba"
    return [module.parent / "__pycache__", user_wide]


def _is_cached(module: Path) -> bool:
    pattern = f"{module.stem}.*.nbi"  # numba's index: <module>.<function>-<line>.pyXY.nbi
    for d in _cache_dirs(module):
        if d == module.parent / "__pycache__":
            if any(d.glob(pattern)):
                return True
        elif d.is_dir() and any(d.rglob(pattern)):
            return True
    return False


def check_numba_cache(cfg: Config, warm: bool = False, modules: Sequence[Path] | None = None) -> CheckResult:
    """Whether the kernels' numba cache is filled; ``warm``: fill it first (Pipeline.warmup)."""
    name = "numba-cache"
    mods = kernel_modules() if modules is None else list(modules)
    if modules is None and cfg.frontend.detector != "surf":
        # robotd's SURF kernels compile only when SURF is the detector (Pipeline.warmup leaves them out)
        mods = [m for m in mods if m.name != "_surf_kernels.py"]
    warmed = ""
    if warm:
        from robotd.pipeline.step import Pipeline

        seconds = Pipeline.warmup((cfg.slam.measurement,), (cfg.slam.dim,))
        warmed = f"warmed in {seconds:.1f} s; "
    cold = [m.name for m in mods if not _is_cached(m)]
    where = f"NUMBA_CACHE_DIR={os.environ['NUMBA_CACHE_DIR']}" if os.environ.get("NUMBA_CACHE_DIR") else "__pycache__"
    if not cold:
        return CheckResult(name, OK, f"{warmed}{len(mods)} kernel modules cached ({where})")
    return CheckResult(
        name,
        WARN,
        f"{warmed}cold for {len(cold)}/{len(mods)} kernel modules ({', '.join(cold)}; {where}): the first start "
        "compiles them (tens of seconds, more on a busy machine); run `robotd doctor --warm` to fill it",
    )


def check_calibration(cfg: Config) -> CheckResult:
    """camera.calibration loads and the camera's driver can use it (as the daemon will: an OAK's
    streamed size must be the file's; a source with its own rig refuses one)."""
    name = "calibration"
    path = cfg.camera.calibration
    camera = _camera(cfg)
    if not path:
        if camera is not None and camera.kind.factory_calibration:
            return CheckResult(name, OK, f"camera.calibration unset: {camera.kind.factory_calibration} will be used")
        return CheckResult(name, SKIP, f"camera.calibration unset: {cfg.camera.url} brings its own")
    from calib.camchain import load_calibration
    from robotd.core.errors import CalibrationError

    try:
        calib = load_calibration(path)
    except RobotdError as exc:
        return CheckResult(name, FAIL, f"{exc} (camera.calibration): recalibrate with robotd-calib or fix the path")
    w, h = calib.image_size
    try:
        drivers.check_camera_url(cfg.camera.url, calibration=calib)
    except CalibrationError as exc:
        return CheckResult(name, FAIL, f"{path}: {exc} (camera.calibration)")
    except RobotdError as exc:
        return CheckResult(name, FAIL, f"{exc} (camera.url)")
    if camera is None or not camera.kind.calibration_size_in_url:
        return CheckResult(
            name, OK, f"{path}: {w}x{h}; {cfg.camera.url} rectifies with it (its size is checked at open)"
        )
    return CheckResult(name, OK, f"{path}: {w}x{h}, matches camera.url")


# --------------------------------------------------------------------------------------------


def run_checks(
    cfg: Config,
    *,
    warm: bool = False,
    heartbeat_timeout_s: float = HEARTBEAT_TIMEOUT_S,
) -> list[CheckResult]:
    """Every check, in the order a rover fails them: devices (the camera's, then the vehicle's), links,
    ports, disk, cache, calibration."""
    checks: list[Callable[[], CheckResult | list[CheckResult]]] = [
        lambda: check_camera_host(cfg),
        lambda: check_serial(cfg),
        lambda: check_mavlink(cfg, heartbeat_timeout_s),
        lambda: check_zenoh(cfg),
        lambda: check_state_dir(cfg),
        lambda: check_numba_cache(cfg, warm=warm),
        lambda: check_calibration(cfg),
    ]
    results: list[CheckResult] = []
    for check in checks:
        r = check()
        results.extend(r if isinstance(r, list) else [r])
    return results
