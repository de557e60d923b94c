"""The camera drivers: each registered once, by URL scheme, with what it declares about itself.

A registration (:func:`register_camera`, the table at the end of this module) names a scheme, the
camera's :class:`CameraKind` (what it is: plain data, known without importing the driver) and its
driver (a :class:`CameraDriver`: what it does, imported when first needed, so a missing optional
library breaks only its own scheme and ``robotd --help`` loads none). Everything outside
``drivers/`` that depends on the camera reads these, never the scheme
(``tests/drivers/test_cameras.py`` fails when a module of ``robotd/`` or ``calib/`` names a
registered scheme).

What a kind declares, and who reads it:

- ``usage``: its URL forms (``kitti://DIR``), for help texts and messages (``robotd.tools.cli``);
- ``hardware``: a device that can appear late (plugged in, powered up): the daemon retries opening
  it (``robotd.daemon.devices``) instead of stopping; ``robotd replay-many`` replays the others;
- ``own_rig``: why it refuses ``camera.calibration`` (its rig is its own), or None when it takes
  the keyword ``calibration`` and rectifies with it (``drivers.open_camera`` and
  ``check_camera_url`` refuse it with a CalibrationError; ``robotd.daemon.device_urls`` names the key);
  ``factory_calibration``: the device's own calibration it rectifies with when
  ``camera.calibration`` is unset; ``calibration_size_in_url``: its URL check compares a
  calibration's image size with the URL's, else the size is checked when it opens (both for
  ``robotd doctor``);
- ``reads``: what its URL names: a ``"device"``; a ``"folder"`` (a dataset, described by
  ``folder``; the driver's ``claims_folder`` recognises one); a ``"file"`` (a recording; bare
  paths ending with one of its ``suffixes`` are its too); or ``"nothing"`` (the URL is the whole
  source: a simulator). ``robotd replay-many`` expands globs, names and digests sources by it;
- ``truth``: its frames carry ``truth_T_world_robot``; ``truth_by_row``: the file a
  KITTI-format trajectory of it pairs with by row, when the source has one (``robotd replay``);
- ``libraries``: the hardware libraries (depthai) that only its driver's module, or package,
  may import (``tests/test_layering.py`` holds every other module to it).

What a driver does (:class:`CameraDriver`; :class:`CameraBase` gives every default):

- ``open`` / ``check_url``: the factory and the URL check (``drivers.open_camera``,
  ``drivers.check_camera_url``; the config check at start-up in ``robotd.daemon.device_urls``);
- for ``robotd replay``: ``frame_total`` (the progress bar's total), ``paced`` (the URL that
  paces it at its own rate, ``--realtime``), ``replay_options`` (options that make two replays
  agree), ``replay_vehicle`` (the vehicle URL that replays its odometry, if any), ``status`` (what
  it says about itself after the last frame, e.g. a damaged recording);
- ``claims_folder``: a folder is one of its sources (``robotd replay-many``);
- ``host_checks``: ``robotd doctor``'s checks of this machine for it (a USB device, a udev rule),
  listed for every registered camera, run for the configured one and skipped for the others.

The camera ``open`` returns satisfies :class:`StereoCamera` (also ``drivers.StereoCamera``).
docs/architecture.md, "A camera driver", shows a new one added.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable
from urllib.parse import urlsplit

from robotd.core.errors import DriverError

if TYPE_CHECKING:
    from collections.abc import Iterator

    from robotd.core.msgs import StereoFrame
    from robotd.core.stereo import RectifiedStereo

READS = ("device", "folder", "file", "nothing")


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


@dataclass(frozen=True)
class CameraKind:
    """What a camera declares about itself at its registration (see the module docstring)."""

    usage: tuple[str, ...]  # its URL forms, for help texts: ("kitti://DIR",)
    reads: str  # one of READS
    hardware: bool = False  # a device that can appear late: opening it is retried
    own_rig: str | None = None  # why it refuses camera.calibration; None: it rectifies with one
    factory_calibration: str | None = None  # the device's own calibration, used without camera.calibration
    calibration_size_in_url: bool = False  # its URL check judges a calibration's size
    truth: bool = False  # its frames carry truth_T_world_robot
    truth_by_row: str | None = None  # the file a KITTI-format trajectory of it pairs with by row
    folder: str | None = None  # reads == "folder": the folder it replays, for messages
    suffixes: tuple[str, ...] = ()  # reads == "file": bare paths ending so are its
    libraries: tuple[str, ...] = ()  # the hardware libraries only its driver's module (package) imports

    def __post_init__(self) -> None:
        if self.reads not in READS:
            raise ValueError(f"CameraKind.reads: expected one of {READS}, got {self.reads!r}")


@dataclass(frozen=True)
class HostCheck:
    """One of ``robotd doctor``'s checks of this machine for a camera: ``run(url)`` -> (passed,
    one line naming the device or file and what to do)."""

    name: str
    run: Callable[[str], tuple[bool, str]]


@dataclass(frozen=True)
class DatasetOdometry:
    """``replay.odometry = "dataset"``: replay a dataset's recorded odometry (KITTI's OXTS GPS/INS),
    with the noise the configuration states for it."""

    sigma_vel_mps: float
    sigma_rate_radps: float


@runtime_checkable
class CameraDriver(Protocol):
    """What a camera driver does (the module docstring says who calls what)."""

    def open(self, url: str, **options: Any) -> StereoCamera:
        """The unopened camera (open it with ``with``); ``options`` override the URL's parameters."""
        ...

    def check_url(self, url: str, **options: Any) -> None:
        """DriverError for what :meth:`open` would refuse in the URL itself; opens nothing."""
        ...

    def claims_folder(self, path: Path) -> bool: ...
    def frame_total(self, camera: Any) -> int | None: ...
    def paced(self, url: str) -> str: ...
    def replay_options(self, url: str) -> dict[str, Any]: ...
    def replay_vehicle(self, source: str, url: str, odometry: DatasetOdometry | None) -> str | None: ...
    def status(self, camera: Any) -> dict[str, Any] | None: ...
    def host_checks(self) -> Sequence[HostCheck]: ...


class CameraBase:
    """The defaults of a :class:`CameraDriver`; a driver overrides ``open``, ``check_url`` and what
    else it has to say."""

    def open(self, url: str, **options: Any) -> StereoCamera:
        raise NotImplementedError

    def check_url(self, url: str, **options: Any) -> None:
        raise NotImplementedError

    def claims_folder(self, path: Path) -> bool:
        """``path`` (a folder) is one of this camera's sources."""
        return False

    def frame_total(self, camera: Any) -> int | None:
        """Frames the opened ``camera`` will yield, when it can tell without reading them."""
        return None

    def paced(self, url: str) -> str:
        """``url`` paced at the source's own rate: the replay sources' ``realtime=1``."""
        return f"{url}{'&' if '?' in url else '?'}realtime=1"

    def replay_options(self, url: str) -> dict[str, Any]:
        """Options for opening ``url`` (camera and vehicle) in a replay, so two replays agree."""
        return {}

    def replay_vehicle(self, source: str, url: str, odometry: DatasetOdometry | None) -> str | None:
        """The vehicle URL whose odometry a replay of ``source`` (opened as ``url``) feeds the
        pipeline, or None (vision only). ``odometry``: the dataset's recorded odometry was asked
        for (``replay.odometry = "dataset"``), else None."""
        return None

    def status(self, camera: Any) -> dict[str, Any] | None:
        """What the source says about itself after the last frame (a replay's summary), or None."""
        return None

    def host_checks(self) -> Sequence[HostCheck]:
        return ()


@dataclass(frozen=True)
class Registration:
    scheme: str
    kind: CameraKind
    target: str | CameraDriver  # "module:attribute", imported when first needed, or the driver


# scheme -> registration, in registration order
CAMERAS: dict[str, Registration] = {}
_LOADED: dict[str, CameraDriver] = {}


def register_camera(scheme: str, kind: CameraKind, driver: str | CameraDriver) -> Registration:
    """Make ``scheme://`` a camera URL: ``kind`` is what the camera is, ``driver`` (a
    :class:`CameraDriver`, or its ``"module:attribute"`` to import when first needed) opens it."""
    scheme = scheme.lower()
    if scheme in CAMERAS:
        raise ValueError(f"camera scheme {scheme!r} is registered already")
    CAMERAS[scheme] = reg = Registration(scheme, kind, driver)
    return reg


def unregister_camera(scheme: str) -> None:
    """Remove a registration (tests that register a fake camera)."""
    del CAMERAS[scheme]
    _LOADED.pop(scheme, None)


def camera_schemes() -> list[str]:
    return sorted(CAMERAS)


def path_scheme(path: str) -> str | None:
    """The scheme of the camera whose ``suffixes`` ``path`` (a bare file name) ends with, or None."""
    for reg in CAMERAS.values():
        if reg.kind.suffixes and path.endswith(reg.kind.suffixes):
            return reg.scheme
    return None


def suffixes() -> tuple[str, ...]:
    """Every registered suffix of a bare path (the recordings'), in registration order."""
    return tuple(s for reg in CAMERAS.values() for s in reg.kind.suffixes)


def scheme_of(url: str) -> str:
    """The lower-case scheme of ``url``; a bare path with a registered suffix is that camera's."""
    if "://" not in url:
        scheme = path_scheme(url)
        if scheme is None:
            raise DriverError(f"{url!r}: expected a URL such as {', '.join(usages())}, got no scheme")
        return scheme
    return urlsplit(url).scheme.lower()


def registration(url: str) -> Registration:
    """The registration of ``url``'s scheme; DriverError for an unknown scheme."""
    scheme = scheme_of(url)
    reg = CAMERAS.get(scheme)
    if reg is None:
        known = ", ".join(f"{s}://" for s in sorted(CAMERAS))
        raise DriverError(f"{url!r}: unknown camera scheme {scheme!r}; known: {known}")
    return reg


def camera_kind(url: str) -> CameraKind:
    """What the camera of ``url`` declared (imports nothing); DriverError for an unknown scheme."""
    return registration(url).kind


def _load(reg: Registration, url: str) -> CameraDriver:
    if not isinstance(reg.target, str):
        return reg.target
    hit = _LOADED.get(reg.scheme)
    if hit is not None:
        return hit
    module_name, _, attr = reg.target.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise DriverError(f"{url!r}: the {reg.scheme}:// driver could not be loaded: {exc}") from exc
    driver = getattr(module, attr, None)
    if driver is None:
        raise DriverError(f"{url!r}: the {reg.scheme}:// driver is not available in this build ({module_name}.{attr})")
    _LOADED[reg.scheme] = driver
    return driver  # type: ignore[no-any-return]


def camera_driver(url: str) -> CameraDriver:
    """The driver of ``url``'s camera (imported); DriverError for an unknown scheme or a driver
    that cannot be loaded."""
    return _load(registration(url), url)


def cameras(hardware: bool | None = None) -> list[Registration]:
    """The registrations, in registration order; only those whose ``hardware`` is the one given."""
    return [r for r in CAMERAS.values() if hardware is None or r.kind.hardware == hardware]


def loaded(reg: Registration) -> CameraDriver | None:
    """The driver of ``reg``, imported; None when this build cannot load it."""
    try:
        return _load(reg, f"{reg.scheme}://")
    except DriverError:
        return None


def usages(hardware: bool | None = None) -> list[str]:
    """The URL forms of the registered cameras (:func:`cameras`' selection), for help texts."""
    return [u for r in cameras(hardware) for u in r.kind.usage]


def schemes_text(schemes: Sequence[str], last: str = "or") -> str:
    """``a://``, ``a:// or b://``, ``a://, b:// or c://`` (for messages)."""
    names = [f"{s}://" for s in schemes]
    if len(names) <= 1:
        return "".join(names)
    return f"{', '.join(names[:-1])} {last} {names[-1]}"


# --------------------------------------------------------------------------------------------
# The cameras robotd ships (the module docstring says what each field means)

register_camera(
    "sim",
    CameraKind(
        usage=("sim://…",),
        reads="nothing",
        own_rig="sim:// renders its own rectified rig (set it with ?f=, ?baseline=, ?width=, ?height=)",
        truth=True,
    ),
    "drivers.sim:SIM_CAMERA",
)
register_camera(
    "oak",
    CameraKind(
        usage=("oak://[device-id]",),
        reads="device",
        hardware=True,
        factory_calibration="the OAK's factory calibration",
        calibration_size_in_url=True,
        libraries=("depthai",),
    ),
    "drivers.oak:OAK_CAMERA",
)
register_camera(
    "kitti",
    CameraKind(
        usage=("kitti://DIR",),
        reads="folder",
        folder="a KITTI folder (calib.txt, image_0/ or image_l/)",
        own_rig="kitti:// images are rectified already and its rig is the folder's calib.txt (P0/P1)",
        truth=True,
        truth_by_row="the folder's poses.txt",
    ),
    "drivers.dataset:KITTI_CAMERA",
)
register_camera(
    "euroc",
    CameraKind(usage=("euroc://DIR",), reads="folder", folder="an EuRoC folder (mav0/)", truth=True),
    "drivers.dataset:EUROC_CAMERA",
)
register_camera(
    "mcap",
    CameraKind(
        usage=("mcap://FILE", "FILE.mcap"),
        reads="file",
        own_rig="a recording replays its rectified images with the rig it was recorded with",
        # .tmp: a recording whose recorder was killed before it could finish the file
        suffixes=(".mcap", ".mcap.tmp"),
    ),
    "drivers.dataset:RECORDING_CAMERA",
)
