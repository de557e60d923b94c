"""One error policy for every output (robotd/outputs/runner.py), without the daemon: an output that
raises in any hook is logged once per hook with its name, counted and shown in health, and the
others get every call; one that blocks delays no caller and no other output (it drops its oldest
calls, counted); one whose finish raises does not skip the others' finish; every output's stats()
reach the health entries. Blocking is made with events: nothing here waits for a duration."""

from __future__ import annotations

import contextlib
import logging
import threading
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
import pytest

from robotd.core.errors import DriverError
from robotd.core.msgs import Odometry, StereoFrame
from robotd.daemon.health import HealthMonitor
from robotd.outputs import Output, OutputRunner, StepReport, enter_output
from robotd.outputs.runner import QUEUE_SIZE

HOOKS = ("tee_frame", "tee_odometry", "record_inputs", "publish", "publish_health", "finish", "stats", "close")
WAIT_S = 60.0  # a guard against a hang only: every wait below ends on an event long before


class Recorder(Output):
    """Remembers every call, in order, with the thread it came on."""

    name = "good"

    def __init__(self, name: str = "good") -> None:
        self.name = name
        self.calls: list[tuple[str, Any]] = []
        self.threads: dict[str, set[str]] = {}
        self.closed = False
        self._seen_cond = threading.Condition()

    def _seen(self, hook: str, arg: Any) -> None:
        with self._seen_cond:
            self.calls.append((hook, arg))
            self.threads.setdefault(hook, set()).add(threading.current_thread().name)
            self._seen_cond.notify_all()

    def wait_for(self, hook: str, arg: Any) -> None:
        """Until ``hook`` was called with ``arg`` (the output's worker got that far)."""
        with self._seen_cond:
            assert self._seen_cond.wait_for(lambda: (hook, arg) in self.calls, WAIT_S), (hook, arg, self.calls)

    def tee_frame(self, frame: StereoFrame) -> None:
        self._seen("tee_frame", frame.seq)

    def tee_odometry(self, odometry: Odometry) -> None:
        self._seen("tee_odometry", odometry.t_ns)

    def record_inputs(self, frame: StereoFrame, odometry: Sequence[Odometry]) -> None:
        self._seen("record_inputs", frame.seq)

    def publish(self, report: StepReport) -> None:
        self._seen("publish", report.seq)

    def publish_health(self, health: Mapping[str, Any]) -> None:
        self._seen("publish_health", health["n"])

    def finish(self, state: Mapping[str, Any] | None, t_ns: int) -> None:
        self._seen("finish", t_ns)

    def stats(self) -> dict[str, Any]:
        return {"calls": len(self.calls), "numpy": np.int64(7), "nested": {"a": np.float32(0.5)}}

    def close(self) -> None:
        self.closed = True

    def hooks(self) -> list[str]:
        return [h for h, _ in self.calls]


class Broken(Recorder):
    """Raises in every hook: a bug (ValueError) or an expected failure (DriverError)."""

    def _seen(self, hook: str, arg: Any) -> None:
        super()._seen(hook, arg)
        raise (DriverError if hook == "publish" else ValueError)(f"{hook} broken on purpose")

    def stats(self) -> dict[str, Any]:
        raise ValueError("stats broken on purpose")

    def close(self) -> None:
        raise ValueError("close broken on purpose")


class Blocking(Recorder):
    """``publish`` waits for ``release``; ``entered`` says it is inside."""

    def __init__(self, name: str = "slow") -> None:
        super().__init__(name)
        self.entered = threading.Event()
        self.release = threading.Event()

    def publish(self, report: StepReport) -> None:
        super().publish(report)
        self.entered.set()
        assert self.release.wait(WAIT_S), "never released"


class FinishBreaks(Recorder):
    def finish(self, state: Mapping[str, Any] | None, t_ns: int) -> None:
        super().finish(state, t_ns)
        raise OSError(28, "No space left on device")


def _frame(seq: int) -> StereoFrame:
    img = np.zeros((4, 6), np.uint8)
    return StereoFrame(1_000 + seq, seq, img, img)


def _report(seq: int) -> StepReport:
    return StepReport(
        result=None, seq=seq, frame_seq=seq, quality=50, reset_counter=0, latency_ms=1.0, health="tracking"
    )  # type: ignore[arg-type]


def _odometry(t_ns: int) -> Odometry:
    return Odometry(t_ns, np.zeros(3), np.zeros(3))


def _drive(runner: OutputRunner, steps: int) -> None:
    """What the daemon's threads hand the runner for ``steps`` steps, then a health document."""
    for k in range(1, steps + 1):
        runner.tee_frame(_frame(k))
        runner.tee_odometry(_odometry(k))
        runner.record_inputs(_frame(k), [_odometry(k)])
        runner.publish(_report(k))
    runner.publish_health({"n": steps})


def test_an_output_that_fails_in_every_hook_is_logged_once_per_hook_counted_and_stops_nothing(
    caplog: pytest.LogCaptureFixture,
) -> None:
    broken, good = Broken("broken"), Recorder()
    runner = OutputRunner([broken, good])
    runner.start()
    with caplog.at_level(logging.ERROR, logger="robotd.outputs.runner"):
        _drive(runner, 5)
        runner.finish({"state": 1}, 99)
        health = runner.health()
        with contextlib.ExitStack() as stack:
            enter_output(stack, good)
            enter_output(stack, broken)  # closed first; its failure does not keep good open
    # the good output got every call, in order, each queued call on its own worker thread
    steps = [h for h in good.hooks() if h in ("record_inputs", "publish")]
    assert steps == ["record_inputs", "publish"] * 5 and good.hooks()[-2:] == ["publish_health", "finish"]
    assert good.hooks().count("tee_frame") == good.hooks().count("tee_odometry") == 5
    assert good.threads["publish"] == good.threads["record_inputs"] == {"robotd-output-good"}
    assert good.closed
    # the broken one was called as often, and every failure counted by hook
    errors = health["outputs"]["broken"]
    assert errors["errors_by_hook"] == {
        "tee_frame": 5, "tee_odometry": 5, "record_inputs": 5, "publish": 5, "publish_health": 1, "finish": 1,
        "stats": 1,
    }  # fmt: skip
    assert errors["errors"] == 23 and errors["since_error_s"] is not None and errors["stats"] == {}
    assert errors["last_error"] == "stats: ValueError: stats broken on purpose"
    # logged once per hook, naming the output; the traceback only for what is not a RobotdError
    lines = [r for r in caplog.records if r.name == "robotd.outputs.runner"]
    for hook in HOOKS:
        said = [r for r in lines if r.getMessage().startswith(f"output broken: {hook} failed")]
        assert len(said) == 1, (hook, [r.getMessage() for r in lines])
        assert (said[0].exc_info is None) == (hook == "publish"), hook
    assert "output broken: publish failed: DriverError: publish broken on purpose; SLAM and the other" in caplog.text


def test_a_blocked_output_delays_no_caller_and_no_other_output_and_drops_its_oldest_calls() -> None:
    slow, good = Blocking(), Recorder()
    runner = OutputRunner([slow, good])
    runner.start()
    runner.publish(_report(1))
    assert slow.entered.wait(WAIT_S)  # its worker is inside publish(1), blocked
    n = QUEUE_SIZE + 10
    for k in range(2, n + 2):  # the caller (the publisher thread in the daemon) never waits
        runner.publish(_report(k))
        good.wait_for("publish", k)  # steps come no faster than a working output takes them
    health = runner.health()["outputs"]
    assert health["slow"]["dropped"] == n - QUEUE_SIZE and health["slow"]["queued"] == QUEUE_SIZE
    assert health["slow"]["since_drop_s"] is not None and health["good"]["dropped"] == 0
    problems = HealthMonitor().assess({"outputs": runner.health()["outputs"], "budget": {}, "tracking": True}, False)
    assert "output slow behind (10 dropped)" in problems["problems"]
    slow.release.set()
    runner.finish(None, 1)
    # the good output got all of them; the slow one the first and the newest QUEUE_SIZE, in order
    assert [a for h, a in good.calls if h == "publish"] == list(range(1, n + 2))
    got = [a for h, a in slow.calls if h == "publish"]
    assert got == [1, *range(n + 2 - QUEUE_SIZE, n + 2)]
    assert ("finish", 1) in slow.calls and ("finish", 1) in good.calls


def test_one_failing_finish_does_not_skip_the_others() -> None:
    first, second = FinishBreaks("first"), Recorder("second")
    runner = OutputRunner([first, second])
    runner.start()
    _drive(runner, 2)
    runner.finish({"x": 1}, 42)
    assert ("finish", 42) in first.calls and ("finish", 42) in second.calls
    h = runner.health()["outputs"]
    assert h["first"]["errors_by_hook"] == {"finish": 1} and "No space left" in h["first"]["last_error"]
    assert h["second"]["errors"] == 0


def test_an_output_still_inside_a_call_at_shutdown_is_not_finished_and_the_others_are() -> None:
    slow, good = Blocking(), Recorder()
    runner = OutputRunner([slow, good])
    runner.start()
    runner.publish(_report(1))
    assert slow.entered.wait(WAIT_S)
    good.wait_for("publish", 1)
    try:
        runner.finish(None, 7, wait_s=0.0)
        assert ("finish", 7) in good.calls and ("finish", 7) not in slow.calls
        entry = runner.health()["outputs"]["slow"]
        assert entry["errors_by_hook"] == {"finish": 1} and "still in a call" in entry["last_error"]
    finally:
        slow.release.set()


def test_every_outputs_stats_reach_health_by_name_and_under_its_health_key() -> None:
    class Saves(Recorder):
        health_key = "map_file"

        def stats(self) -> dict[str, Any]:
            return {"saves": 3, "last_failed": False}

    a, b, c = Recorder("spy"), Recorder("spy"), Saves("map_file")
    runner = OutputRunner([a, b, c])
    doc = runner.health()
    assert set(doc["outputs"]) == {"spy", "spy#2", "map_file"}  # two outputs of one name both show
    assert doc["outputs"]["spy"]["stats"] == {"calls": 0, "numpy": 7, "nested": {"a": 0.5}}
    assert type(doc["outputs"]["spy"]["stats"]["numpy"]) is int  # plain JSON, whatever the output gave
    assert doc["map_file"] == {"saves": 3, "last_failed": False} == doc["outputs"]["map_file"]["stats"]
    assert all(doc["outputs"][k]["errors"] == 0 for k in doc["outputs"])


def test_calls_queued_before_the_workers_start_are_delivered_at_finish() -> None:
    good = Recorder()
    runner = OutputRunner([good])  # never started: a daemon stopped before its first step
    _drive(runner, 1)
    runner.finish(None, 3)
    assert good.hooks() == ["tee_frame", "tee_odometry", "record_inputs", "publish", "publish_health", "finish"]


def test_each_output_reads_its_own_copy_of_the_health_document() -> None:
    class Mutates(Recorder):
        def publish_health(self, health: Mapping[str, Any]) -> None:
            health.clear()  # type: ignore[attr-defined]

    good = Recorder()
    runner = OutputRunner([Mutates("rude"), good])  # not started: finish makes the calls in this order
    doc = {"n": 1, "budget": {"level": 0}}
    runner.publish_health(doc)
    runner.finish(None, 0)
    assert ("publish_health", 1) in good.calls and doc == {"n": 1, "budget": {"level": 0}}
