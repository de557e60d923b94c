"""Opening the devices: missing hardware is retried, but ``--duration`` is honoured in every state;
a negative or non-finite duration is refused in one line; ``camera.calibration`` reaches the
camera, or stops the start-up naming the key."""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from robotd.config import load_config
from robotd.core.errors import ConfigError, DriverError
from robotd.daemon import Daemon
from robotd.daemon.devices import open_devices, open_with_retry
from robotd.daemon.sdnotify import Notifier
from robotd.pipeline.step import Pipeline
from robotd.tools.cli import main
from tests.support.daemon_runs import HANG_GUARD_S, run_until
from tests.support.paths import REPO


def _never(url: str, **options: object) -> contextlib.AbstractContextManager[object]:
    raise DriverError(f"{url!r}: no OAK device found")


def test_missing_hardware_is_retried_until_the_deadline_then_says_how_long() -> None:
    t0 = time.monotonic()
    with contextlib.ExitStack() as stack, pytest.raises(DriverError, match=r"gave up after 0\.[5-9]\d* s"):
        open_with_retry(stack, "camera", _never, "oak://x", threading.Event(), Notifier({}), t0 + 0.6)
    assert time.monotonic() - t0 < 1.5  # the back-off never sleeps past the deadline


def test_a_simulator_that_fails_to_open_is_not_retried() -> None:
    calls: list[str] = []

    def opener(url: str, **options: object) -> contextlib.AbstractContextManager[object]:
        calls.append(url)
        return _never(url, **options)

    with contextlib.ExitStack() as stack, pytest.raises(DriverError, match="no OAK"):
        open_with_retry(stack, "camera", opener, "sim://?fps=-3", threading.Event(), Notifier({}))
    assert calls == ["sim://?fps=-3"]  # once: counted, not timed


def test_run_without_its_camera_stops_at_duration(caplog: pytest.LogCaptureFixture) -> None:
    Pipeline.warmup()  # a cold numba cache compiles for ~15 s first; that is not what is timed here
    t0 = time.monotonic()
    cfg = load_config(None, {"camera": {"url": "oak://no-such-device"}, "zenoh": {"enabled": False}})
    assert Daemon(cfg, duration_s=1.0, environ={}).run() == 2
    assert time.monotonic() - t0 < 15.0  # device discovery may take a few seconds of its own
    assert any("gave up after" in r.message and "--duration" in r.message for r in caplog.records)


@pytest.mark.parametrize("bad", [-1.0, float("nan"), float("inf")])
def test_a_duration_that_is_not_a_time_is_refused(bad: float) -> None:
    with pytest.raises(ConfigError, match="--duration: expected seconds >= 0"):
        Daemon(load_config(None), duration_s=bad, environ={})


@pytest.mark.parametrize("argv", [["run", "--duration", "-1"], ["record", "x.mcap", "--duration", "nan"]])
def test_the_cli_refuses_a_negative_duration_in_one_line(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as e:
        main(argv)
    err = capsys.readouterr().err
    assert e.value.code == 2 and "--duration: expected seconds >= 0" in err and "Traceback" not in err


# -- camera.calibration reaches the camera the daemon opens -------------------------------------


def _moved_euroc_rig(shared_data: Any, tmp_path: Path) -> tuple[str, Path, float]:
    """The EuRoC folder's URL, a calibration file of its rig with a 10 % longer baseline (written
    as robotd-calib writes one) and the folder's own baseline."""
    from calib.camchain import save_calibration
    from drivers.dataset import EurocCamera

    url = f"euroc://{shared_data('euroc-v101-micro')}"
    with EurocCamera(url) as cam:
        rig, b = cam.calibration, cam.rectified_model().baseline_m
    return url, save_calibration(dataclasses.replace(rig, T=rig.T * 1.1), tmp_path / "rig.yaml"), b


def test_open_devices_hands_the_calibration_file_to_the_camera(shared_data: Any, tmp_path: Path) -> None:
    url, path, b = _moved_euroc_rig(shared_data, tmp_path)
    cfg = load_config(
        None, {"camera": {"url": f"{url}?stop=2", "calibration": str(path)}, "vehicle": {"url": "none://"}}
    )
    with contextlib.ExitStack() as stack:
        dev = open_devices(cfg, stack, threading.Event(), Notifier({}))
        assert dev.camera.rectified_model().baseline_m == pytest.approx(1.1 * b, rel=1e-9)


def test_run_steps_on_the_rig_of_the_calibration_file(shared_data: Any, tmp_path: Path) -> None:
    """robotd run: the pipeline is built on the calibration file's rig and steps on its frames."""
    url, path, b = _moved_euroc_rig(shared_data, tmp_path)
    cfg = load_config(
        None,
        {
            "camera": {"url": url, "calibration": str(path)},
            "vehicle": {"url": "none://"},
            "zenoh": {"enabled": False},
            "persistence": {"state_dir": str(tmp_path / "state")},
        },
    )
    d = Daemon(cfg, duration_s=HANG_GUARD_S, environ={})
    status, reached = run_until(d, lambda: d.stats.steps >= 3)
    assert status == 0 and reached, (d.stop_reason, d.stats.steps)
    assert d.pipeline is not None and d.pipeline.rig.baseline_m == pytest.approx(1.1 * b, rel=1e-9)


def test_run_refuses_a_calibration_file_its_camera_cannot_use_before_the_kernels(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture, tmp_path: Path
) -> None:
    def no_warmup(*_: Any) -> float:
        raise AssertionError("the kernels were loaded before the calibration was checked")

    monkeypatch.setattr(Pipeline, "warmup", staticmethod(no_warmup))
    path = REPO / "tests" / "support" / "data" / "calibration_v1" / "v1_oak_640x400.yaml"
    cfg = load_config(
        None,
        {
            "camera": {"url": "sim://", "calibration": str(path)},
            "zenoh": {"enabled": False},
            "persistence": {"state_dir": str(tmp_path)},
        },
    )
    with caplog.at_level(logging.INFO, logger="robotd"):
        assert Daemon(cfg, duration_s=1.0, environ={}).run() == 2
    failed = [r.getMessage() for r in caplog.records if "startup failed" in r.getMessage()]
    assert len(failed) == 1 and failed[0].startswith(f"startup failed: camera.calibration: {path}: 'sim://' takes no")
