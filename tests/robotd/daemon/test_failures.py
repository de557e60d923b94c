"""A thread that dies unexpectedly stops the daemon with a non-zero exit status (systemd's
Restart=on-failure restarts it), never a quiet "source ended" with status 0; a SLAM thread that
crashed mid-step does not overwrite the saved map with its half-updated state."""

from __future__ import annotations

import threading
from pathlib import Path

import pytest

import robotd.outputs as outputs_mod
from robotd.config import load_config
from robotd.daemon import Daemon
from robotd.outputs import Output, StepReport
from robotd.pipeline.step import Pipeline
from tests.support.daemon_runs import HANG_GUARD_S, run_until


def _daemon(tmp_path: Path, camera: str = "sim://?fps=20", duration_s: float = HANG_GUARD_S) -> Daemon:
    """Each run ends on its event (the failure at the 10th step, ...), however long a busy machine
    takes to reach it; ``duration_s`` only guards against a hang (at 6 s, as it was, a host too busy
    for 10 steps in them would end the run with 0 before the failure it tests)."""
    cfg = load_config(
        None,
        {
            "camera": {"url": camera},
            "vehicle": {"url": "sim://?fps=20"},
            "zenoh": {"enabled": False},
            "persistence": {"state_dir": str(tmp_path), "save_period_s": 0.0},
        },
    )
    return Daemon(cfg, duration_s=duration_s, environ={})


def test_a_crash_in_the_slam_step_exits_1_and_keeps_the_saved_map(tmp_path, monkeypatch, caplog) -> None:
    real_step = Pipeline.step
    calls = {"n": 0}

    def step(self: Pipeline, frame, inc=None):
        calls["n"] += 1
        if calls["n"] == 10:
            raise ZeroDivisionError("a bug in a stage")
        return real_step(self, frame, inc)

    monkeypatch.setattr(Pipeline, "step", step)
    d = _daemon(tmp_path)
    assert d.run() == 1
    assert d.failed == ["slam"] and "slam thread crashed: ZeroDivisionError" in d.stop_reason
    assert "map not saved at shutdown: the SLAM thread crashed" in caplog.text
    assert "did not stop" not in caplog.text  # the publisher ends with the SLAM thread it serves
    assert not (tmp_path / "map.robotd").exists()


def test_an_output_that_raises_something_unexpected_is_counted_and_stops_nothing(tmp_path, monkeypatch, caplog) -> None:
    """An output is not a thread of the daemon: its bug (not a RobotdError) is logged once with its
    name and the traceback, counted in health, and the daemon runs on and stops with status 0
    (robotd.outputs.runner; before, it stopped the publisher thread and the daemon with 1)."""

    class Broken(Output):
        name = "broken"

        def publish(self, report: StepReport) -> None:
            if report.seq >= 5:
                raise ValueError("not a RobotdError")

    monkeypatch.setattr(outputs_mod, "FACTORIES", (*outputs_mod.FACTORIES, ("broken", lambda ctx: Broken())))
    d = _daemon(tmp_path)
    status, reached = run_until(d, lambda: d.stats.published >= 12)
    assert status == 0 and reached and not d.failed, (d.stop_reason, d.failed)
    said = [r for r in caplog.records if "not a RobotdError" in r.getMessage()]
    assert len(said) == 1 and said[0].getMessage().startswith("output broken: publish failed: ValueError")
    assert said[0].exc_info is not None  # a bug's traceback
    assert d.health_doc()["outputs"]["broken"]["errors_by_hook"] == {"publish": d.stats.published - 4}
    assert (tmp_path / "map.robotd").exists()  # saved at the stop, as always


def test_a_source_that_ends_normally_exits_0(tmp_path) -> None:
    d = _daemon(tmp_path, camera="sim://?fps=20&duration=1.5", duration_s=0.0)
    assert d.run() == 0
    assert d.stop_reason == "source ended" and not d.failed


@pytest.mark.parametrize("err", [RuntimeError("usb stack bug"), OSError(5, "Input/output error")])
def test_a_camera_that_fails_mid_stream_exits_1(tmp_path, monkeypatch, err) -> None:
    import drivers.sim

    real_frames = drivers.sim.SimCamera.frames

    def frames(self, timeout_s: float = 1.0):
        for k, frame in enumerate(real_frames(self, timeout_s)):
            if k == 15:
                raise err
            yield frame

    monkeypatch.setattr(drivers.sim.SimCamera, "frames", frames)
    d = _daemon(tmp_path)
    assert d.run() == 1
    assert d.failed == ["camera"]
    assert (tmp_path / "map.robotd").exists()


def test_a_thread_that_fails_just_before_the_supervisor_looks_keeps_its_reason(tmp_path) -> None:
    """The interleaving CI once hit on a busy machine: the supervisor's wait timed out, then the
    SLAM thread crashed (``_fail`` set the reason and the flag) and ended before the supervisor
    asked whether it was alive; the daemon reported "source ended" with exit status 1."""
    d = _daemon(tmp_path)

    class EndsByFailing:
        def is_alive(self) -> bool:
            d._fail("slam", "slam thread crashed: ZeroDivisionError: a bug in a stage")
            return False

    d.threads = [threading.Thread(), threading.Thread(), EndsByFailing()]  # type: ignore[list-item]
    d._supervise()
    assert d.failed == ["slam"] and d.exit_code == 1
    assert d.stop_reason == "slam thread crashed: ZeroDivisionError: a bug in a stage"
