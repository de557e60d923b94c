"""Drivers: the only code that touches hardware, each chosen by URL.

``open_camera(url)`` and ``open_vehicle(url)`` pick the module from the URL scheme, like
pyserial's ``serial_for_url``. Mocks are drivers in their own right (``sim://``, dataset replay)
and feed the same pipeline as the hardware. Each module is the only importer of its library
(``drivers.oak`` of depthai, ``drivers.serial_link`` of pyserial, ``drivers.mavlink_link`` of
pymavlink); modules are imported lazily so a missing optional library only breaks its scheme.

Contract shared by every driver:

- A driver is a context manager (:class:`drivers.base.Driver`); ``__enter__`` opens the device
  (or raises :class:`robotd.errors.DriverError` with the URL and the reason), ``__exit__``
  releases it. ``close()`` may come from another thread and ends a running iterator.
- ``StereoCamera.frames(timeout_s)`` yields :class:`robotd.msgs.StereoFrame` (rectified when the
  driver can rectify) and returns when the source ends (replay) or ``close()`` is called. A
  hardware camera that unplugs keeps retrying inside the driver and reports it in ``stats()``.
- ``VehicleLink.odometry(timeout_s)`` yields :class:`robotd.msgs.Odometry` samples the same way.
  Links fed by a receive thread (serial, MAVLink) share :class:`drivers.base.QueuedVehicleLink`:
  a drop-oldest queue, ``drain()`` and ``latest_controls()``.
- Sending the SLAM pose is a role, not a link method: ``VehicleLink.autopilot`` is the link's
  :class:`AutopilotLink` (``send_pose``, ``set_health``) when the link is also the pose sink
  (``mavlink+…://``; ``sim://`` scores the pose against its truth), else None (``serial://``,
  ``none://``, replay). A daemon that sends the pose to an autopilot other than its odometry
  source opens a MAVLink link for it and uses that link's ``autopilot``.
- ``stats()`` returns counters (frames, drops, gaps, errors, reconnects) for the health output.
- A user's calibration (``camera.calibration``, a :class:`robotd.stereo.StereoCalibration` read from
  the camchain file) reaches a camera as the keyword ``calibration``. The cameras that rectify raw
  images take it instead of their own (``oak://`` with ``rectify=host``, ``euroc://``); a camera
  whose rig is its own (:data:`_OWN_RIG`) refuses it with a :class:`robotd.errors.CalibrationError`
  saying why, from :func:`open_camera` and :func:`check_camera_url` alike. ``calibration=None`` is
  no calibration, for every camera.
"""

from __future__ import annotations

import importlib
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable
from urllib.parse import urlsplit

from robotd.errors import CalibrationError, DriverError

if TYPE_CHECKING:
    import numpy as np

    from robotd.msgs import Odometry, PoseEstimate, StereoFrame
    from robotd.stereo import RectifiedStereo

# what AutopilotLink.set_health accepts (besides None)
HEALTH_STATES = ("starting", "tracking", "degraded", "failed")


@runtime_checkable
class StereoCamera(Protocol):
    url: str
    # for recordings, what the images were rectified from: the device's own calibration dump (OAK
    # EEPROM JSON), or the user's StereoCalibration (camera.calibration); None when the rig is all
    raw_calibration: Any

    @property
    def fps(self) -> float | None:
        """Nominal frame rate [Hz] (the daemon's latency budget follows it); None when unknown (replay)."""
        ...

    @property
    def host_clock(self) -> bool:
        """True when frames are stamped on this host's monotonic clock (a live camera, ``sim://`` in
        real time); False on a dataset's own clock (a replay): the daemon then measures latency
        from each frame's delivery, not from its stamp."""
        ...

    def __enter__(self) -> StereoCamera: ...
    def __exit__(self, *exc: object) -> None: ...
    def frames(self, timeout_s: float = 1.0) -> Iterator[StereoFrame]: ...
    def rectified_model(self) -> RectifiedStereo: ...
    def close(self) -> None: ...
    def stats(self) -> dict[str, Any]: ...


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


# scheme -> (module, factory attribute). The factory takes (url, **options).
_CAMERAS: dict[str, tuple[str, str]] = {
    "sim": ("drivers.sim", "open_sim_camera"),
    "oak": ("drivers.oak", "open_oak_camera"),
    "kitti": ("drivers.dataset", "open_kitti"),
    "euroc": ("drivers.dataset", "open_euroc"),
    "mcap": ("drivers.dataset", "open_mcap"),
}
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


# scheme -> why its camera takes no calibration file: its rig is its own. Every other camera takes the
# keyword ``calibration`` (a StereoCalibration) and rectifies with it.
_OWN_RIG: dict[str, str] = {
    "sim": "sim:// renders its own rectified rig (set it with ?f=, ?baseline=, ?width=, ?height=)",
    "kitti": "kitti:// images are rectified already and its rig is the folder's calib.txt (P0/P1)",
    "mcap": "a recording replays its rectified images with the rig it was recorded with",
}


# scheme -> (module, checker attribute). The checker takes (url, **options), as the factory does, and
# raises DriverError for what the factory would refuse in the URL itself (scheme, parameter names and
# values) without opening a device or reading a file: the config is checked with it at start-up,
# before the kernels load (robotd.device_urls).
_CAMERA_CHECKS: dict[str, tuple[str, str]] = {
    "sim": ("drivers.sim", "check_sim_url"),
    "oak": ("drivers.oak.camera", "check_oak_url"),
    "kitti": ("drivers.dataset", "check_kitti_url"),
    "euroc": ("drivers.dataset", "check_euroc_url"),
    "mcap": ("drivers.dataset", "check_mcap_url"),
}
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


def _scheme(url: str) -> str:
    if "://" not in url:
        # a bare path to a recording is a replay source
        if url.endswith((".mcap", ".mcap.tmp")):  # .tmp: a recording whose recorder was killed
            return "mcap"
        raise DriverError(f"{url!r}: expected a URL such as sim://, oak://, kitti://DIR, got no scheme")
    return urlsplit(url).scheme.lower()


def _entry(table: dict[str, tuple[str, str]], kind: str, url: str) -> Any:
    """The function ``table`` names for ``url``'s scheme (imported); DriverError for an unknown
    scheme or a driver that cannot be loaded."""
    scheme = _scheme(url)
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


def _open(table: dict[str, tuple[str, str]], kind: str, url: str, **options: Any) -> Any:
    return _entry(table, kind, url)(url, **options)


def _calibration_option(url: str, options: dict[str, Any]) -> dict[str, Any]:
    """``options`` without ``calibration=None``; CalibrationError when a calibration is given to a
    camera whose rig is its own (:data:`_OWN_RIG`)."""
    if options.get("calibration") is None:
        return {k: v for k, v in options.items() if k != "calibration"}
    why = _OWN_RIG.get(_scheme(url))
    if why is not None:
        raise CalibrationError(f"{url!r} takes no calibration file: {why}")
    return options


def check_camera_url(url: str, **options: Any) -> None:
    """Raise DriverError when :func:`open_camera` would refuse ``url`` for its scheme or its
    parameters; opens nothing, reads no file (a missing device or folder is found when opened)."""
    _entry(_CAMERAS, "camera", url)  # an unknown scheme says so as open_camera does
    _entry(_CAMERA_CHECKS, "camera", url)(url, **_calibration_option(url, options))


def check_vehicle_url(url: str, **options: Any) -> None:
    """Raise DriverError when :func:`open_vehicle` would refuse ``url`` for its scheme or its
    parameters; opens nothing."""
    _entry(_VEHICLES, "vehicle", url)
    _entry(_VEHICLE_CHECKS, "vehicle", url)(url, **options)


def open_camera(url: str, **options: Any) -> StereoCamera:
    """Open a stereo source by URL: sim://, oak://[device-id], kitti://DIR, euroc://DIR, FILE.mcap.
    ``calibration``: a StereoCalibration to rectify with instead of the camera's own (module docstring)."""
    _entry(_CAMERAS, "camera", url)  # an unknown scheme before anything about the calibration
    return _open(_CAMERAS, "camera", url, **_calibration_option(url, options))  # type: ignore[no-any-return]


def open_vehicle(url: str, **options: Any) -> VehicleLink:
    """Open a vehicle link by URL: sim://, none://, serial:///dev/ttyX?baud=…, mavlink+udp://…, mavlink+serial://…"""
    return _open(_VEHICLES, "vehicle", url, **options)  # type: ignore[no-any-return]


def camera_schemes() -> list[str]:
    return sorted(_CAMERAS)


def vehicle_schemes() -> list[str]:
    return sorted(_VEHICLES)
