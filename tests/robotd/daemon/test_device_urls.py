"""Device URLs checked with the config, before anything slow (issue 27, item 6): each driver's own
parser judges its scheme and parameters, nothing is opened, and the daemon stops before the kernels."""

from __future__ import annotations

import logging
import re
from typing import Any

import numpy as np
import pytest

import drivers
from robotd.config import load_config
from robotd.core.errors import ConfigError, DatasetError, RobotdError
from robotd.daemon.device_urls import camera_options, check_device_urls, device_urls
from tests.support.paths import REPO

GOOD = [
    ({"camera": {"url": "sim://?fps=10&seed=3"}}),
    ({"camera": {"url": "oak://"}, "vehicle": {"url": "mavlink+serial:///dev/ttyACM0?baud=921600"}}),
    ({"camera": {"url": "oak://14442C10D13EABCE00?fps=15"}, "vehicle": {"url": "serial:///dev/ttyX?baud=115200"}}),
    # paths and devices are the drivers' business when they open: not checked here
    ({"camera": {"url": "kitti:///no/such/dir?stride=2"}, "vehicle": {"url": "kitti:///no/such/dir?odometry=oxts"}}),
    ({"camera": {"url": "euroc:///no/such?alpha=0.5"}, "vehicle": {"url": "none://"}}),
    ({"camera": {"url": "/no/such/s.mcap"}, "vehicle": {"url": "mcap:///no/such/s.mcap?realtime=1"}}),
    (
        {
            "vehicle": {"url": "serial:///dev/ttyACM0"},
            "mavlink": {"enabled": True, "url": "mavlink+udp://127.0.0.1:14551"},
        }
    ),
]

BAD = [
    ("camera.url", {"camera": {"url": "cam://x"}}, "unknown camera scheme 'cam'"),
    ("camera.url", {"camera": {"url": "sim://?fpz=3"}}, "unknown parameter 'fpz'"),
    ("camera.url", {"camera": {"url": "oak://?fps=500"}}, "fps <= 120"),
    ("camera.url", {"camera": {"url": "kitti:///x?stride=two"}}, "option stride: expected an integer"),
    ("camera.url", {"camera": {"url": "euroc:///x?alpha=wide"}}, "option alpha: expected a number"),
    ("camera.url", {"camera": {"url": "mcap:///x/s.mcap?speed=0"}}, "option speed"),
    ("vehicle.url", {"vehicle": {"url": "tcp://x"}}, "unknown vehicle scheme 'tcp'"),
    ("vehicle.url", {"vehicle": {"url": "serial:///dev/ttyACM0?baud=fast"}}, "option baud='fast'"),
    ("vehicle.url", {"vehicle": {"url": "mavlink+udp://127.0.0.1:14550?mode=sideways"}}, "mode='sideways'"),
    ("vehicle.url", {"vehicle": {"url": "mavlink+udp://127.0.0.1"}}, "expected mavlink+udp://HOST:PORT"),
    ("vehicle.url", {"vehicle": {"url": "none://x"}}, "none:// takes no host"),
    ("vehicle.url", {"vehicle": {"url": "kitti:///x?odometry=gps"}}, "option odometry"),
    ("vehicle.url", {"vehicle": {"url": "mcap:///x/s.mcap?stride=2"}}, "unknown option(s) ['stride']"),
    ("mavlink.url", {"mavlink": {"enabled": True, "url": "mavlink+udp://127.0.0.1:1?bogus=1"}}, "option 'bogus'"),
]


def test_every_scheme_has_a_check() -> None:
    # a camera's check is its driver's own (drivers.cameras): every registered one loads and has one
    for scheme in drivers.cameras.camera_schemes():
        assert isinstance(drivers.cameras.camera_driver(f"{scheme}://"), drivers.cameras.CameraDriver), scheme
    assert set(drivers._VEHICLE_CHECKS) == set(drivers._VEHICLES)


@pytest.mark.parametrize("tree", GOOD)
def test_good_urls_pass_without_opening_anything(tree: dict[str, Any]) -> None:
    check_device_urls(load_config(None, tree))


@pytest.mark.parametrize("path", sorted((REPO / "config").glob("*.toml")), ids=lambda p: p.name)
def test_the_shipped_configs_pass(path: Any) -> None:
    check_device_urls(load_config(path))


@pytest.mark.parametrize(("key", "tree", "message"), BAD, ids=[f"{k}:{m}" for k, _, m in BAD])
def test_a_bad_url_is_one_config_error_naming_the_key_and_the_driver_refuses_it_too(
    key: str, tree: dict[str, Any], message: str
) -> None:
    cfg = load_config(None, tree)
    with pytest.raises(ConfigError) as e:
        check_device_urls(cfg, where="rover.toml")
    text = str(e.value)
    assert text.startswith(f"{key}: ") and message in text and text.endswith("(in rover.toml)"), text
    assert "\n" not in text
    # the check is the driver's own judgement: its factory refuses the same URL for the same reason
    # (the kitti vehicle looks for its folder first: then for that)
    _, kind, url, options = next(d for d in device_urls(cfg) if d[0] == key)
    opener = drivers.open_camera if kind == "camera" else drivers.open_vehicle
    with pytest.raises(RobotdError) as refused:
        opener(url, **options)
    assert re.search(re.escape(message), str(refused.value)) or (
        isinstance(refused.value, DatasetError) and "is not a directory" in str(refused.value)
    ), refused.value


def test_a_value_given_on_the_command_line_is_named_as_such() -> None:
    cfg = load_config(None, {"camera": {"url": "sim://?fps=-3"}})
    with pytest.raises(ConfigError, match=r"^camera.url: 'sim://\?fps=-3': parameter fps.* \(from --camera\)$"):
        check_device_urls(cfg, where="rover.toml", given={"camera.url": "--camera"})


def test_the_daemon_checks_before_loading_the_kernels(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture, tmp_path: Any
) -> None:
    """Daemon.startup (robotd run, record, and any caller of run_daemon): the URL first, in one
    log line and exit status 2, never the 10-40 s kernel load before it."""
    from robotd.daemon import Daemon
    from robotd.pipeline.step import Pipeline

    def no_warmup(*_: Any) -> float:
        raise AssertionError("the kernels were loaded before the URL was checked")

    monkeypatch.setattr(Pipeline, "warmup", staticmethod(no_warmup))
    cfg = load_config(
        None,
        {"camera": {"url": "sim://?fps=-3"}, "zenoh": {"enabled": False}, "persistence": {"state_dir": str(tmp_path)}},
    )
    with caplog.at_level(logging.INFO, logger="robotd"):
        assert Daemon(cfg, duration_s=1.0).run() == 2
    failed = [r.getMessage() for r in caplog.records if "startup failed" in r.getMessage()]
    assert len(failed) == 1 and "camera.url: 'sim://?fps=-3': parameter fps" in failed[0], failed
    assert not list(tmp_path.iterdir()), "nothing written before the check"


# -- camera.calibration: read once, judged by the camera's driver ---------------------------------

V1 = REPO / "tests" / "support" / "data" / "calibration_v1"
OAK_FILE = V1 / "v1_oak_640x400.yaml"  # a file robotd-calib import-oak wrote (640x400)
CHESSBOARD_FILE = V1 / "v1_chessboard.yaml"  # a file robotd-calib stereo wrote (640x480)

REFUSED = [
    ("sim://", OAK_FILE, "'sim://' takes no calibration file: sim:// renders its own rectified rig"),
    ("kitti:///data/seq", OAK_FILE, "kitti:// images are rectified already and its rig is the folder's calib.txt"),
    ("/data/run.mcap", OAK_FILE, "a recording replays its rectified images with the rig it was recorded with"),
    ("oak://", CHESSBOARD_FILE, "the calibration is for 640x480 images but the camera gives 640x400"),
    ("oak://?rectify=device", OAK_FILE, "with rectify=device the device rectifies from its EEPROM calibration"),
]


@pytest.mark.parametrize(("url", "path", "message"), REFUSED, ids=[u for u, _, _ in REFUSED])
def test_a_calibration_file_the_camera_cannot_use_is_a_config_error_naming_the_key(
    url: str, path: Any, message: str
) -> None:
    cfg = load_config(None, {"camera": {"url": url, "calibration": str(path)}})
    with pytest.raises(ConfigError) as e:
        check_device_urls(cfg, where="rover.toml")
    text = str(e.value)
    assert text.startswith(f"camera.calibration: {path}: ") and message in text, text
    assert text.endswith("; unset camera.calibration (in rover.toml)") and "\n" not in text, text
    with pytest.raises(ConfigError, match=re.escape(message)):
        camera_options(cfg)  # what the daemon and replay open the camera with


@pytest.mark.parametrize("url", ["oak://", "oak://?width=640&height=400&fps=15", "euroc:///no/such?alpha=0.5"])
def test_a_calibration_file_reaches_the_cameras_that_rectify(url: str) -> None:
    from calib.camchain import load_calibration

    cfg = load_config(None, {"camera": {"url": url, "calibration": str(OAK_FILE)}})
    check_device_urls(cfg)
    given = camera_options(cfg)["calibration"]
    expected = load_calibration(OAK_FILE)
    for k in ("K_left", "D_left", "K_right", "D_right", "R", "T"):
        assert np.array_equal(getattr(given, k), getattr(expected, k)), k
    assert given.image_size == (640, 400)
    assert camera_options(load_config(None, {"camera": {"url": url}})) == {}  # unset: the camera's own


def test_a_calibration_file_that_cannot_be_read_is_a_config_error(tmp_path: Any) -> None:
    missing = load_config(None, {"camera": {"url": "oak://", "calibration": str(tmp_path / "no.yaml")}})
    with pytest.raises(ConfigError, match=r"^camera.calibration: .*no.yaml: cannot read the calibration file"):
        check_device_urls(missing)
    (tmp_path / "bad.yaml").write_text("cam0: {camera_model: pinhole}\n")
    bad = load_config(None, {"camera": {"url": "euroc:///x", "calibration": str(tmp_path / "bad.yaml")}})
    with pytest.raises(ConfigError, match=r"^camera.calibration: .*bad.yaml") as e:
        check_device_urls(bad, where="rover.toml")
    assert str(e.value).endswith("(in rover.toml)")


def test_a_bad_url_is_named_before_its_calibration() -> None:
    cfg = load_config(None, {"camera": {"url": "sim://?fpz=3", "calibration": str(OAK_FILE)}})
    with pytest.raises(ConfigError, match=r"^camera.url: .*unknown parameter 'fpz'"):
        check_device_urls(cfg)
