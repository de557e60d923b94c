"""The daemon's outputs: one protocol, a list built from the config, every hook on its thread.

A spy output registered the way a new output would be (one factory in robotd.outputs.FACTORIES)
runs inside the real daemon on sim:// and must see: the inputs of every step before it, every
step's report in order, landmark and state snapshots at the periods it asked for, the health
document, and the final state at shutdown. Every output runs under one error policy
(robotd/outputs/runner.py, whose own tests are test_runner.py): one that fails in any hook, or
blocks, must not stop SLAM or the others, and health shows it.

The runs end on what the spies saw (so many steps, health documents, a state snapshot), not after
a number of seconds: on a busy host 2.5 s held 5 steps (tests/support/daemon_runs.py).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import pytest

import robotd.outputs as outputs_mod
from robotd.config import load_config
from robotd.core.errors import DriverError
from robotd.core.msgs import Odometry, StereoFrame
from robotd.daemon import Daemon
from robotd.outputs import Output, OutputContext, OutputRunner, StepReport
from robotd.outputs.runner import QUEUE_SIZE
from tests.support.daemon_runs import HANG_GUARD_S, run_until


class Spy(Output):
    name = "spy"
    map_period_s = 0.5
    state_period_s = 1.0
    health_period_s = 0.3

    def __init__(self, fail: bool = False) -> None:
        self.fail = fail
        self.inputs: list[tuple[int, int]] = []  # (frame t_ns, odometry samples)
        self.reports: list[StepReport] = []
        self.health: list[dict[str, Any]] = []
        self.final: tuple[Mapping[str, Any] | None, int] | None = None
        self.closed = False
        self.threads: set[str] = set()

    def record_inputs(self, frame: StereoFrame, odometry: Sequence[Odometry]) -> None:
        self.threads.add("inputs:" + threading.current_thread().name)
        self.inputs.append((frame.t_ns, len(odometry)))

    def publish(self, report: StepReport) -> None:
        self.threads.add("publish:" + threading.current_thread().name)
        self.reports.append(report)
        if self.fail:
            raise DriverError("spy: this output is broken on purpose")

    def publish_health(self, health: Mapping[str, Any]) -> None:
        self.health.append(dict(health))

    def finish(self, state: Mapping[str, Any] | None, t_ns: int) -> None:
        self.final = (state, t_ns)

    def close(self) -> None:
        self.closed = True


def _run(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, spies: list[Output], done: Callable[[], bool]) -> Daemon:
    def factory_for(spy: Output):
        return lambda ctx: spy if isinstance(ctx, OutputContext) else None

    extra = tuple((f"spy{k}", factory_for(s)) for k, s in enumerate(spies))
    monkeypatch.setattr(outputs_mod, "FACTORIES", (*outputs_mod.FACTORIES, *extra))
    cfg = load_config(
        None,
        {
            "camera": {"url": "sim://?fps=20"},
            "vehicle": {"url": "sim://?fps=20"},
            "zenoh": {"enabled": False},
            "persistence": {"state_dir": str(tmp_path), "save_period_s": 0.0},
        },
    )
    d = Daemon(cfg, duration_s=HANG_GUARD_S, environ={})
    status, reached = run_until(d, done)
    assert status == 0 and reached, (d.stop_reason, d.stats.steps)
    return d


def _hand_overs(monkeypatch: pytest.MonkeyPatch) -> list[tuple[int, float]]:
    """(frame t_ns, time.monotonic()) each time the SLAM thread hands a step's inputs to the outputs
    (OutputRunner.record_inputs: the outputs' workers receive them a little later)."""
    seen: list[tuple[int, float]] = []
    real = OutputRunner.record_inputs

    def record_inputs(self: OutputRunner, frame: StereoFrame, odometry: Sequence[Odometry]) -> None:
        seen.append((frame.t_ns, time.monotonic()))
        real(self, frame, odometry)

    monkeypatch.setattr(OutputRunner, "record_inputs", record_inputs)
    return seen


def _check_period(
    spy: Spy, handed: list[tuple[int, float]], taken: Callable[[StepReport], bool], period_s: float
) -> None:
    """Snapshots every ``period_s``: the SLAM thread takes one at the first step that ends at least
    ``period_s`` after the last one did. It decides after the step, on its own thread: between its
    hand-over of the inputs of the step's frame and of the next one (``handed``; that window
    brackets the moment, so the check holds however slow the machine is). A snapshot sooner than
    the period, or a step that ends a period after the last snapshot without one, fails."""
    index = {t: k for k, (t, _) in enumerate(handed)}
    at = [t for _, t in handed]

    def window(r: StepReport) -> tuple[float, float]:
        k = index[r.result.t_ns]
        return at[k], at[k + 1] if k + 1 < len(at) else math.inf

    last: tuple[float, float] | None = None
    for r in spy.reports:
        lo, hi = window(r)
        if taken(r):
            assert last is None or hi - last[0] >= period_s, f"snapshot at step {r.seq} within {period_s} s"
            last = (lo, hi)
        else:
            assert last is None or lo - last[1] < period_s, f"no snapshot at step {r.seq}, {period_s} s after one"


def test_an_output_added_to_the_factories_sees_every_step(tmp_path, monkeypatch):
    spy = Spy()
    handed = _hand_overs(monkeypatch)

    def done() -> bool:  # steps enough to check the order, a later map and a state snapshot (1 s)
        seen = list(spy.reports)
        maps, states = sum(r.landmarks is not None for r in seen), sum(r.state is not None for r in seen)
        return len(seen) >= 20 and len(spy.health) >= 5 and maps >= 2 and states >= 1

    d = _run(tmp_path, monkeypatch, [spy], done)
    assert [o.name for o in d.outputs] == ["map_file", "autopilot", "spy"]
    n = d.stats.steps
    assert n >= 20 and len(spy.reports) == n == d.stats.published
    assert [r.seq for r in spy.reports] == list(range(1, n + 1))
    # every processed frame's inputs were handed over first, in capture order
    t_in = [t for t, _ in spy.inputs]
    assert t_in == sorted(t_in) and {r.result.t_ns for r in spy.reports} <= set(t_in)
    assert sum(k for _, k in spy.inputs) > 0  # odometry samples travelled with the frames
    # snapshots at the periods asked for: the first report carries the map, later ones now and then
    with_map = [r for r in spy.reports if r.landmarks is not None]
    with_state = [r for r in spy.reports if r.state is not None]
    assert spy.reports[0].landmarks is not None and len(with_map) >= 2, len(with_map)
    _check_period(spy, handed, lambda r: r.landmarks is not None, Spy.map_period_s)
    assert with_state and "estimator" in with_state[0].state
    _check_period(spy, handed, lambda r: r.state is not None, Spy.state_period_s)
    assert all(r.health in ("tracking", "degraded", "failed") for r in spy.reports)
    assert all(-1 <= r.quality <= 100 and r.latency_ms > 0 for r in spy.reports)
    assert len(spy.health) >= 5 and spy.health[-1]["frames_processed"] > 0
    # at shutdown: the final state, then closed
    assert spy.final is not None and spy.final[0] is not None and spy.closed
    # the inputs and the reports reach it on its own worker (robotd.outputs.runner), never on SLAM's thread
    assert spy.threads == {"inputs:robotd-output-spy", "publish:robotd-output-spy"}
    assert [t for t, _ in handed] == t_in  # every hand-over delivered, none dropped


def test_a_failing_output_does_not_stop_the_others(tmp_path, monkeypatch, caplog):
    broken, good = Spy(fail=True), Spy()
    d = _run(tmp_path, monkeypatch, [broken, good], lambda: len(good.reports) >= 12)
    assert len(good.reports) == d.stats.steps > 10
    assert len(broken.reports) == d.stats.steps
    said = [r.getMessage() for r in caplog.records if "this output is broken on purpose" in r.getMessage()]
    assert said == ["output spy: publish failed: DriverError: spy: this output is broken on purpose; SLAM and the "
                    "other outputs go on (later failures are counted: health outputs.spy.errors)"]  # fmt: skip
    doc = d.health_doc()["outputs"]  # two outputs of one name: the second is spy#2
    assert doc["spy"]["errors_by_hook"] == {"publish": d.stats.steps} and doc["spy#2"]["errors"] == 0


class FailsEverywhere(Output):
    """Raises in every hook the daemon calls, a bug's exception (not a RobotdError)."""

    name = "broken"
    health_period_s = 0.3

    def __init__(self) -> None:
        self.calls: dict[str, int] = {}

    def _fail(self, hook: str) -> None:
        self.calls[hook] = self.calls.get(hook, 0) + 1
        raise ZeroDivisionError(f"{hook} broken on purpose")

    def tee_frame(self, frame: StereoFrame) -> None:
        self._fail("tee_frame")

    def tee_odometry(self, odometry: Odometry) -> None:
        self._fail("tee_odometry")

    def record_inputs(self, frame: StereoFrame, odometry: Sequence[Odometry]) -> None:
        self._fail("record_inputs")

    def publish(self, report: StepReport) -> None:
        self._fail("publish")

    def publish_health(self, health: Mapping[str, Any]) -> None:
        self._fail("publish_health")

    def finish(self, state: Mapping[str, Any] | None, t_ns: int) -> None:
        self._fail("finish")

    def stats(self) -> dict[str, Any]:
        self._fail("stats")
        return {}

    def close(self) -> None:
        self._fail("close")


class Stuck(Output):
    """Its first publish blocks until ``release`` (a hung socket, a full disk that never returns)."""

    name = "stuck"

    def __init__(self) -> None:
        self.release = threading.Event()
        self.reports: list[int] = []

    def publish(self, report: StepReport) -> None:
        self.reports.append(report.seq)
        assert self.release.wait(HANG_GUARD_S)

    def stats(self) -> dict[str, Any]:
        return {"published": len(self.reports)}


def test_failing_and_blocked_outputs_stop_neither_slam_nor_the_other_outputs(tmp_path, monkeypatch, caplog):
    """One output raises in every hook, one blocks inside its first publish: SLAM keeps stepping
    (far past what the blocked output's queue holds), the good output gets every step, its health
    documents show each output's error counts, drops and stats, and at shutdown the good output's
    finish runs although the broken one's raised. The run ends on what the outputs saw."""
    broken, stuck, good = FailsEverywhere(), Stuck(), Spy()

    def done() -> bool:
        docs = list(good.health)
        behind = bool(docs) and docs[-1].get("outputs", {}).get("stuck", {}).get("dropped", 0) > 0
        if len(good.reports) >= 3 * QUEUE_SIZE and behind:
            stuck.release.set()  # let it go, so the shutdown need not wait for it
            return True
        return False

    d = _run(tmp_path, monkeypatch, [broken, stuck, good], done)
    steps = d.stats.steps
    assert steps >= 3 * QUEUE_SIZE and len(good.reports) == steps  # SLAM and the good output went on
    assert [r.seq for r in good.reports] == list(range(1, steps + 1))
    assert stuck.reports[0] == 1 and len(stuck.reports) < steps  # it dropped what it could not take
    assert good.final is not None and good.final[0] is not None  # finish ran although broken's raised
    assert (tmp_path / "map.robotd").exists()  # and so did the map file's (the final save)
    for hook in ("tee_frame", "tee_odometry", "record_inputs", "publish", "publish_health", "finish", "close"):
        assert broken.calls.get(hook, 0) >= 1, hook
        said = [r for r in caplog.records if r.getMessage().startswith(f"output broken: {hook} failed:")]
        assert len(said) == 1, hook  # once, however often it failed
    # what the health documents said while it ran
    doc = next(h for h in reversed(good.health) if h["outputs"]["stuck"]["dropped"] > 0)
    out = doc["outputs"]
    assert set(out) == {"map_file", "autopilot", "broken", "stuck", "spy"}
    by_hook = out["broken"]["errors_by_hook"]
    assert by_hook["publish"] >= 1 and by_hook["record_inputs"] >= 1 and by_hook["tee_frame"] >= 1
    assert by_hook["stats"] >= 1 and out["broken"]["stats"] == {}
    assert out["stuck"]["stats"] == {"published": 1} and out["stuck"]["queued"] == QUEUE_SIZE
    assert "saves" in out["map_file"]["stats"] and doc["map_file"] == out["map_file"]["stats"]
    assert out["autopilot"]["stats"]["errors"] == 0 and out["spy"]["errors"] == 0
    assert any(p.startswith("output broken failing") for p in doc["problems"])
    assert any(p.startswith("output stuck behind") for p in doc["problems"])
    assert d.exit_code == 0 and not d.failed
