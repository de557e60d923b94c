"""Drivers: the only code that touches hardware, each chosen by URL.

``open_camera(url)`` and ``open_vehicle(url)`` pick the driver from the URL scheme, like
pyserial's ``serial_for_url``: the cameras from their registry (:mod:`drivers.cameras`, where each
camera driver declares what it is), the vehicle links from ``_VEHICLES`` below. Mocks are drivers
in their own right (``sim://``, dataset replay) and feed the same pipeline as the hardware. Each
module is the only importer of its library (``drivers.oak`` of depthai, ``drivers.serial_link`` of
pyserial, ``drivers.mavlink_link`` of pymavlink); modules are imported lazily so a missing
optional library only breaks its scheme.

Contract shared by every driver:

- A driver is a context manager (:class:`drivers.base.Driver`); ``__enter__`` opens the device
  (or raises :class:`robotd.core.errors.DriverError` with the URL and the reason), ``__exit__``
  releases it. ``close()`` may come from another thread and ends a running iterator.
- ``StereoCamera.frames(timeout_s)`` yields :class:`robotd.core.msgs.StereoFrame` (rectified when the
  driver can rectify) and returns when the source ends (replay) or ``close()`` is called. A
  hardware camera that unplugs keeps retrying inside the driver and reports it in ``stats()``.
- ``VehicleLink.odometry(timeout_s)`` yields :class:`robotd.core.msgs.Odometry` samples the same way.
  Links fed by a receive thread (serial, MAVLink) share :class:`drivers.base.QueuedVehicleLink`:
  a drop-oldest queue, ``drain()`` and ``latest_controls()``.
- Sending the SLAM pose is a role, not a link method: ``VehicleLink.autopilot`` is the link's
  :class:`AutopilotLink` (``send_pose``, ``set_health``) when the link is also the pose sink
  (``mavlink+…://``; ``sim://`` scores the pose against its truth), else None (``serial://``,
  ``none://``, replay). A daemon that sends the pose to an autopilot other than its odometry
  source opens a MAVLink link for it and uses that link's ``autopilot``.
- ``stats()`` returns counters (frames, drops, gaps, errors, reconnects) for the health output.
- A user's calibration (``camera.calibration``, a :class:`robotd.core.stereo.StereoCalibration` read from
  the camchain file) reaches a camera as the keyword ``calibration``. The cameras that rectify raw
  images take it instead of their own (``oak://`` with ``rectify=host``, ``euroc://``); a camera
  whose rig is its own (its kind's ``own_rig``, :mod:`drivers.cameras`) refuses it with a
  :class:`robotd.core.errors.CalibrationError` saying why, from :func:`open_camera` and
  :func:`check_camera_url` alike. ``calibration=None`` is no calibration, for every camera.
"""

from __future__ import annotations

import importlib
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

from drivers.cameras import StereoCamera as StereoCamera  # the camera's protocol, with its registry
from drivers.cameras import camera_driver, camera_kind, scheme_of
from robotd.core.errors import CalibrationError, DriverError

if TYPE_CHECKING:
    import numpy as np

    from drivers.mavlink_odometry import AutopilotPose
    from robotd.core.msgs import Odometry, PoseEstimate

# what AutopilotLink.set_health accepts (besides None)
HEALTH_STATES = ("starting", "tracking", "degraded", "failed")


@runtime_checkable
class AutopilotLink(Protocol):
    """Where the SLAM pose goes (an autopilot's external navigation input). Any thread may call it."""

    def send_pose(
        self, pose: PoseEstimate, quality: int, reset_counter: int, vel_R_mps: np.ndarray | None = None
    ) -> None:
        """Forward one pose; ``quality`` −1 (lost) or 1..100, ``reset_counter`` bumps on a jump,
        ``vel_R_mps`` the body-frame (FRD) velocity [m/s] (3,), None when unknown."""
        ...

    def set_health(self, state: str | None) -> None:
        """The pipeline's state, one of "starting", "tracking", "degraded", "failed"; None derives
        it from the last quality. Anything else raises DriverError."""
        ...

    def stats(self) -> dict[str, Any]: ...


@runtime_checkable
class AutopilotPoseSource(Protocol):
    """A link that knows the autopilot's own estimate of the vehicle's pose (MAVLink's
    LOCAL_POSITION_NED and ATTITUDE): what carries robotd's pose across its restart
    (robotd.daemon.handover)."""

    def autopilot_pose_at(self, t_ns: int) -> AutopilotPose | None: ...


@runtime_checkable
class VehicleLink(Protocol):
    url: str

    def __enter__(self) -> VehicleLink: ...
    def __exit__(self, *exc: object) -> None: ...
    def odometry(self, timeout_s: float = 1.0) -> Iterator[Odometry]: ...
    def close(self) -> None: ...
    def stats(self) -> dict[str, Any]: ...

    @property
    def autopilot(self) -> AutopilotLink | None:
        """The link's pose-sink role, or None when the link takes no pose."""
        ...


# The cameras are registered in drivers.cameras, each driver once with what it declares about
# itself (drivers.cameras.CameraDriver). The vehicle links: scheme -> (module, factory attribute);
# the factory takes (url, **options).
_VEHICLES: dict[str, tuple[str, str]] = {
    "sim": ("drivers.sim", "open_sim_vehicle"),
    "none": ("drivers.sim", "open_null_vehicle"),
    "serial": ("drivers.serial_link", "open_serial_vehicle"),
    "mavlink+udp": ("drivers.mavlink_link", "open_mavlink_vehicle"),
    "mavlink+serial": ("drivers.mavlink_link", "open_mavlink_vehicle"),
    # replay sources: datasets are visual only unless gt_odometry=1 (experiments only)
    "kitti": ("drivers.dataset", "open_kitti_vehicle"),
    "euroc": ("drivers.dataset", "open_euroc_vehicle"),
    "mcap": ("drivers.dataset", "open_mcap_vehicle"),
}

# scheme -> (module, checker attribute). The checker takes (url, **options), as the factory does, and
# raises DriverError for what the factory would refuse in the URL itself (scheme, parameter names and
# values) without opening a device or reading a file: the config is checked with it at start-up,
# before the kernels load (robotd.daemon.device_urls).
_VEHICLE_CHECKS: dict[str, tuple[str, str]] = {
    "sim": ("drivers.sim", "check_sim_url"),
    "none": ("drivers.sim", "check_null_url"),
    "serial": ("drivers.serial_link", "parse_serial_url"),
    "mavlink+udp": ("drivers.mavlink_link", "parse_mavlink_url"),
    "mavlink+serial": ("drivers.mavlink_link", "parse_mavlink_url"),
    "kitti": ("drivers.dataset", "check_kitti_vehicle_url"),
    "euroc": ("drivers.dataset", "check_euroc_vehicle_url"),
    "mcap": ("drivers.dataset", "check_mcap_vehicle_url"),
}

# vehicle links that can appear later (plugged in, powered up): the daemon retries opening them, as
# it does a camera whose kind declares ``hardware``
_HARDWARE_VEHICLES = frozenset({"serial", "mavlink+udp", "mavlink+serial"})


def _entry(table: dict[str, tuple[str, str]], kind: str, url: str) -> Any:
    """The function ``table`` names for ``url``'s scheme (imported); DriverError for an unknown
    scheme or a driver that cannot be loaded."""
    scheme = scheme_of(url)
    if scheme not in table:
        known = ", ".join(f"{s}://" for s in sorted(table))
        raise DriverError(f"{url!r}: unknown {kind} scheme {scheme!r}; known: {known}")
    module_name, attr = table[scheme]
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise DriverError(f"{url!r}: the {scheme}:// driver could not be loaded: {exc}") from exc
    fn = getattr(module, attr, None)
    if fn is None:
        raise DriverError(f"{url!r}: the {scheme}:// driver is not available in this build ({module_name}.{attr})")
    return fn


def _calibration_option(url: str, options: dict[str, Any]) -> dict[str, Any]:
    """``options`` without ``calibration=None``; CalibrationError when a calibration is given to a
    camera whose rig is its own (its kind's ``own_rig``)."""
    if options.get("calibration") is None:
        return {k: v for k, v in options.items() if k != "calibration"}
    why = camera_kind(url).own_rig
    if why is not None:
        raise CalibrationError(f"{url!r} takes no calibration file: {why}")
    return options


def check_camera_url(url: str, **options: Any) -> None:
    """Raise DriverError when :func:`open_camera` would refuse ``url`` for its scheme or its
    parameters; opens nothing, reads no file (a missing device or folder is found when opened)."""
    driver = camera_driver(url)  # an unknown scheme says so as open_camera does
    driver.check_url(url, **_calibration_option(url, options))


def check_vehicle_url(url: str, **options: Any) -> None:
    """Raise DriverError when :func:`open_vehicle` would refuse ``url`` for its scheme or its
    parameters; opens nothing."""
    _entry(_VEHICLES, "vehicle", url)
    _entry(_VEHICLE_CHECKS, "vehicle", url)(url, **options)


def open_camera(url: str, **options: Any) -> StereoCamera:
    """Open a stereo source by URL (the registered cameras: drivers.cameras), e.g. sim://,
    oak://[device-id], kitti://DIR, euroc://DIR, FILE.mcap. ``calibration``: a StereoCalibration
    to rectify with instead of the camera's own (module docstring)."""
    driver = camera_driver(url)  # an unknown scheme before anything about the calibration
    return driver.open(url, **_calibration_option(url, options))


def open_vehicle(url: str, **options: Any) -> VehicleLink:
    """Open a vehicle link by URL: sim://, none://, serial:///dev/ttyX?baud=…, mavlink+udp://…, mavlink+serial://…"""
    return _entry(_VEHICLES, "vehicle", url)(url, **options)  # type: ignore[no-any-return]


def is_hardware(kind: str, url: str) -> bool:
    """``url`` (a ``kind`` "camera", else a vehicle link) names a device that can appear later
    (plugged in, powered up), whose opening the daemon retries (a camera's kind declares it);
    False for a URL no driver takes."""
    try:
        if kind == "camera":
            return camera_kind(url).hardware
        return scheme_of(url) in _HARDWARE_VEHICLES
    except DriverError:
        return False


def vehicle_schemes() -> list[str]:
    return sorted(_VEHICLES)
