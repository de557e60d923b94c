"""Opening the devices: missing hardware is retried, but ``--duration`` is honoured in every state;
a negative or non-finite duration is refused in one line."""

from __future__ import annotations

import contextlib
import threading
import time

import pytest

from robotd.cli import main
from robotd.config import load_config
from robotd.daemon import Daemon
from robotd.daemon.devices import open_with_retry
from robotd.daemon.sdnotify import Notifier
from robotd.errors import ConfigError, DriverError
from robotd.pipeline import Pipeline


def _never(url: str, **options: object) -> contextlib.AbstractContextManager[object]:
    raise DriverError(f"{url!r}: no OAK device found")


def test_missing_hardware_is_retried_until_the_deadline_then_says_how_long() -> None:
    t0 = time.monotonic()
    with contextlib.ExitStack() as stack, pytest.raises(DriverError, match=r"gave up after 0\.[5-9]\d* s"):
        open_with_retry(stack, "camera", _never, "oak://x", threading.Event(), Notifier({}), t0 + 0.6)
    assert time.monotonic() - t0 < 1.5  # the back-off never sleeps past the deadline


def test_a_simulator_that_fails_to_open_is_not_retried() -> None:
    t0 = time.monotonic()
    with contextlib.ExitStack() as stack, pytest.raises(DriverError, match="no OAK"):
        open_with_retry(stack, "camera", _never, "sim://?fps=-3", threading.Event(), Notifier({}))
    assert time.monotonic() - t0 < 0.2


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
