"""A camera driver is registered once (drivers/cameras.py) with what it declares, and nothing
outside ``drivers/`` names a camera's scheme.

A fake camera (``MemoryCamera`` below: frames held in memory, the ``StereoCamera`` protocol and
nothing else) is added by one module's worth of code, its driver, and its registration, and only
that, and runs through every path that used to branch on a scheme: the config check at start-up
and the calibration refusal, ``robotd replay`` (its progress total, its truth, its pacing),
``robotd doctor`` (its own host check), the daemon's retry of missing hardware, ``robotd
replay-many``'s sources and the CLI's help.
"""

from __future__ import annotations

import ast
import contextlib
import dataclasses
import re
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from urllib.parse import parse_qsl, urlsplit

import numpy as np
import pytest

import drivers
from calib.camchain import save_calibration
from drivers.base import Driver
from drivers.cameras import (
    CAMERAS,
    CameraBase,
    CameraDriver,
    CameraKind,
    HostCheck,
    camera_kind,
    camera_schemes,
    register_camera,
    unregister_camera,
)
from robotd.config import load_config
from robotd.core.errors import ConfigError, DriverError, InputError
from robotd.core.msgs import StereoFrame
from robotd.core.stereo import RectifiedStereo
from robotd.daemon.device_urls import check_device_urls
from robotd.daemon.devices import open_with_retry
from robotd.daemon.sdnotify import Notifier
from robotd.tools import doctor
from robotd.tools.batch.sources import check_sources, expand_sources, source_digest
from robotd.tools.cli import build_parser
from robotd.tools.replay import _frame_total, replay
from tests.calib.test_camchain import _calib
from tests.support.paths import REPO
from tests.support.saved_maps import sim_frames

# --------------------------------------------------------------------------------------------
# The fake camera: what a new driver module holds (the camera, its driver) ...

FAKE = "fake"


class MemoryCamera(Driver):
    """Replays frames held in memory (with their truth): ``fake://?n=N`` gives the first N."""

    host_clock = False
    fps = None
    raw_calibration = None

    def __init__(self, url: str, frames: tuple[StereoFrame, ...], rig: RectifiedStereo, realtime: bool) -> None:
        self.url, self._frames, self._rig, self.realtime = url, frames, rig, realtime
        self.delivered = 0

    def frames(self, timeout_s: float = 1.0) -> Iterator[StereoFrame]:
        for f in self._frames:
            self.delivered += 1
            yield f

    def rectified_model(self) -> RectifiedStereo:
        return self._rig

    def close(self) -> None:
        pass

    def stats(self) -> dict[str, Any]:
        return {"frames": self.delivered}


def _options(url: str, options: dict[str, Any]) -> tuple[int, bool]:
    parts = urlsplit(url)
    if parts.scheme != FAKE:
        raise DriverError(f"{url!r}: expected fake://")
    opts = {**dict(parse_qsl(parts.query)), **options}
    unknown = set(opts) - {"n", "realtime"}
    if unknown:
        raise DriverError(f"{url!r}: unknown option(s) {sorted(unknown)}")
    try:
        n = int(opts.get("n", 10))
    except ValueError:
        raise DriverError(f"{url!r}: option n: expected an integer, got {opts['n']!r}") from None
    if not 1 <= n <= 20:
        raise DriverError(f"{url!r}: option n: expected 1..20, got {n}")
    return n, str(opts.get("realtime", "0")) == "1"


class MemoryCameraDriver(CameraBase):
    def open(self, url: str, **options: Any) -> MemoryCamera:
        n, realtime = _options(url, options)
        frames, rig = sim_frames()  # the first frames of the simulated yard, with their truth
        return MemoryCamera(url, frames[:n], rig, realtime)

    def check_url(self, url: str, **options: Any) -> None:
        _options(url, options)

    def frame_total(self, camera: Any) -> int | None:
        return len(camera._frames)

    def host_checks(self) -> tuple[HostCheck, ...]:
        return (HostCheck("fake-memory", lambda url: (True, f"{url}: its frames are in memory")),)


FAKE_KIND = CameraKind(
    usage=("fake://?n=N",), reads="nothing", truth=True, own_rig="fake:// replays the rig its frames came with"
)


# ... and its registration: the one line a new camera adds to drivers/cameras.py


@pytest.fixture
def fake() -> Iterator[MemoryCameraDriver]:
    driver = MemoryCameraDriver()
    register_camera(FAKE, FAKE_KIND, driver)
    yield driver
    unregister_camera(FAKE)


def _cfg(**sections: Any) -> Any:
    small = {"slam": {"n_particles": 20}, "zenoh": {"enabled": False}}
    return load_config(None, {**small, **sections})


def test_the_fake_satisfies_the_driver_protocol_as_every_registered_driver_does(fake: MemoryCameraDriver) -> None:
    for scheme in camera_schemes():
        assert isinstance(drivers.cameras.camera_driver(f"{scheme}://"), CameraDriver), scheme
    with drivers.open_camera("fake://?n=3") as cam:
        assert isinstance(cam, drivers.StereoCamera) and len(list(cam.frames())) == 3


def test_the_config_check_takes_a_registered_camera_and_its_driver_judges_its_url(
    fake: MemoryCameraDriver, tmp_path: Path
) -> None:
    check_device_urls(_cfg(camera={"url": "fake://?n=5"}))
    with pytest.raises(ConfigError, match=r"^camera\.url: 'fake://\?n=x': option n: expected an integer"):
        check_device_urls(_cfg(camera={"url": "fake://?n=x"}))
    # its rig is its own (declared): a calibration file is refused naming the key and the reason
    path = save_calibration(_calib(np.random.default_rng(3)), tmp_path / "rig.yaml")
    with pytest.raises(ConfigError, match=r"camera\.calibration: .*fake:// replays the rig its frames came with"):
        check_device_urls(_cfg(camera={"url": "fake://", "calibration": str(path)}))


def test_replay_runs_a_registered_camera_with_its_declarations(fake: MemoryCameraDriver, tmp_path: Path) -> None:
    out, truth = tmp_path / "t.txt", tmp_path / "g.txt"
    summary = replay(_cfg(), "fake://?n=8", out_traj=str(out), truth_out=str(truth), progress=False)
    assert summary["frames"] == 8 and summary["odometry"] == "none"  # no replay_vehicle: vision only
    assert summary["truth_ate_rmse_m"] is not None  # declared truth=True, and its frames carry it
    rows = [[ln for ln in f.read_text().splitlines() if not ln.startswith("#")] for f in (out, truth)]
    assert [len(r) for r in rows] == [8, 8]
    with drivers.open_camera("fake://?n=5") as cam:
        assert _frame_total(cam, 0) == 5 and _frame_total(cam, 2) == 2  # the progress bar's total
    # --realtime paces it the way a replay source is paced (CameraBase.paced): realtime=1
    assert replay(_cfg(), "fake://?n=2", realtime=True, progress=False)["frames"] == 2


def test_doctor_runs_the_cameras_host_checks_for_it_and_skips_them_for_another(fake: MemoryCameraDriver) -> None:
    mine = {r.name: r for r in doctor.check_camera_host(_cfg(camera={"url": "fake://"}))}
    assert mine["fake-memory"].status == doctor.OK and "in memory" in mine["fake-memory"].message
    assert mine["oak-usb"].status == doctor.SKIP and "not oak://" in mine["oak-usb"].message
    other = {r.name: r for r in doctor.run_checks(_cfg(), heartbeat_timeout_s=0.1)}
    assert other["fake-memory"].status == doctor.SKIP and other["fake-memory"].message.endswith("not fake://")
    calibration = doctor.check_calibration(_cfg(camera={"url": "fake://"}))
    assert calibration.status == doctor.SKIP  # no factory calibration declared: it brings its own


def _never(url: str, **options: object) -> contextlib.AbstractContextManager[object]:
    raise DriverError(f"{url!r}: nothing there")


def test_the_daemon_retries_a_camera_declared_hardware_and_no_other(fake: MemoryCameraDriver) -> None:
    with contextlib.ExitStack() as stack, pytest.raises(DriverError, match="nothing there"):
        open_with_retry(stack, "camera", _never, "fake://", threading.Event(), Notifier({}))
    kind = dataclasses.replace(FAKE_KIND, usage=("fakehw://HOST",), hardware=True, reads="device")
    register_camera("fakehw", kind, fake)
    try:
        assert drivers.is_hardware("camera", "fakehw://x") and not drivers.is_hardware("camera", "fake://")
        t0 = time.monotonic()
        with contextlib.ExitStack() as stack, pytest.raises(DriverError, match="gave up after"):
            open_with_retry(stack, "camera", _never, "fakehw://x", threading.Event(), Notifier({}), t0 + 0.6)
        # replay-many replays the cameras that are not hardware
        with pytest.raises(InputError, match="unknown scheme 'fakehw'"):
            expand_sources(["fakehw://x"])
    finally:
        unregister_camera("fakehw")


def test_replay_many_takes_its_urls_by_what_it_reads(fake: MemoryCameraDriver) -> None:
    (src,) = expand_sources(["fake://?n=4"])
    assert src.url == src.name == "fake://?n=4"  # it reads nothing: the URL is the source and its name
    check_sources([src])
    assert source_digest("fake://?n=4") != source_digest("fake://?n=5")


def test_the_help_lists_a_registered_camera(fake: MemoryCameraDriver, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        build_parser().parse_args(["replay", "--help"])
    text = capsys.readouterr().out
    assert "fake://?n=N" in text and "truth the source carries (sim://, kitti://, euroc:// and fake:// do)" in text


# --------------------------------------------------------------------------------------------
# Nothing outside drivers/ names a camera's scheme

SCANNED = ("robotd", "calib")
# robotd/config/__init__.py holds the configuration's defaults and each key's documentation (camera.url =
# "sim://", the URL forms it takes), which config/robotd.toml repeats; it is in the pipeline layer,
# which may not import the drivers, so it cannot ask the registry.
EXEMPT = {"robotd/config/__init__.py"}


def _scheme_mentions(source: str, schemes: list[str]) -> list[tuple[int, str]]:
    """(line, text) of each string (docstrings included) that writes ``SCHEME://``, and each
    comparison or collection of a registered scheme's name with something called a scheme
    (``scheme == "sim"``, ``HARDWARE_SCHEMES = ("oak", ...)``); comments are prose, not scanned."""
    url = re.compile(r"(?<![\w+.-])(?:" + "|".join(map(re.escape, schemes)) + r")://", re.IGNORECASE)
    hits: list[tuple[int, str]] = []

    def names_a_scheme(node: ast.AST) -> bool:
        elts = node.elts if isinstance(node, (ast.Tuple, ast.List, ast.Set)) else [node]
        return any(isinstance(e, ast.Constant) and e.value in schemes for e in elts)

    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and url.search(node.value):
            hits.append((node.lineno, url.search(node.value).group(0)))  # type: ignore[union-attr]
        elif isinstance(node, ast.Compare):
            sides = [node.left, *node.comparators]
            if any("scheme" in ast.unparse(s).lower() for s in sides) and any(names_a_scheme(s) for s in sides):
                hits.append((node.lineno, ast.unparse(node)))
        elif isinstance(node, ast.Assign) and names_a_scheme(node.value):
            if any("scheme" in ast.unparse(t).lower() for t in node.targets):
                hits.append((node.lineno, ast.unparse(node)))
    return hits


def test_the_scan_finds_a_scheme() -> None:
    src = (
        '"""Replays kitti:// folders."""\n'
        'a = url.startswith("SIM://")\n'
        'b = scheme == "mcap"\n'
        'HARDWARE_SCHEMES = ("oak", "serial")\n'
        'c = urlsplit(url).scheme.lower() != "oak"\n'
        'd = fmt == "kitti"  # a trajectory format, not a scheme\n'
        'e = "mavlink+udp://host:1"  # a vehicle link\n'
        'f = "robotd record OUT.mcap"\n'
    )
    assert sorted(line for line, _ in _scheme_mentions(src, ["sim", "kitti", "mcap", "oak"])) == [1, 2, 3, 4, 5]


def test_no_module_outside_drivers_names_a_camera_scheme() -> None:
    schemes = camera_schemes()
    assert {"sim", "oak", "kitti", "euroc", "mcap"} <= set(schemes)
    bad: list[str] = []
    for pkg in SCANNED:
        for f in sorted((REPO / pkg).rglob("*.py")):
            rel = f.relative_to(REPO).as_posix()
            if rel in EXEMPT:
                continue
            bad += [f"{rel}:{line}: {text}" for line, text in _scheme_mentions(f.read_text(encoding="utf-8"), schemes)]
    assert not bad, "ask the camera registry (drivers.cameras), not the scheme:\n" + "\n".join(bad)


def test_every_camera_is_registered_once_and_declares_what_it_reads() -> None:
    assert list(CAMERAS) == [r.scheme for r in CAMERAS.values()] and len(set(CAMERAS)) == len(CAMERAS)
    for scheme in CAMERAS:
        kind = camera_kind(f"{scheme}://")
        assert kind.usage and all(u.startswith(f"{scheme}://") or "://" not in u for u in kind.usage), scheme
        assert kind.hardware == (kind.reads == "device"), scheme
        assert bool(kind.suffixes) == (kind.reads == "file"), scheme
    assert camera_kind("/x/session.mcap") is CAMERAS["mcap"].kind  # a bare path by its suffix
    with pytest.raises(DriverError, match="unknown camera scheme 'cam'"):
        camera_kind("cam://x")
