"""The daemon's outputs: one protocol, a list built from the config, every hook on its thread.

A spy output registered the way a new output would be (one factory in robotd.outputs.FACTORIES)
runs inside the real daemon on sim:// and must see: the inputs of every step before it, every
step's report in order, landmark and state snapshots at the periods it asked for, the health
document, and the final state at shutdown. An output that fails must not stop the others.

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
from robotd.daemon import Daemon
from robotd.errors import DriverError
from robotd.msgs import Odometry, StereoFrame
from robotd.outputs import Output, OutputContext, StepReport
from tests.support.daemon_runs import HANG_GUARD_S, run_until


class Spy(Output):
    name = "spy"
    map_period_s = 0.5
    state_period_s = 1.0
    health_period_s = 0.3

    def __init__(self, fail: bool = False) -> None:
        self.fail = fail
        self.inputs: list[tuple[int, int]] = []  # (frame t_ns, odometry samples)
        self.inputs_at: list[float] = []  # time.monotonic() at each record_inputs
        self.reports: list[StepReport] = []
        self.health: list[dict[str, Any]] = []
        self.final: tuple[Mapping[str, Any] | None, int] | None = None
        self.closed = False
        self.threads: set[str] = set()

    def record_inputs(self, frame: StereoFrame, odometry: Sequence[Odometry]) -> None:
        self.threads.add("inputs:" + threading.current_thread().name)
        self.inputs.append((frame.t_ns, len(odometry)))
        self.inputs_at.append(time.monotonic())

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


def _run(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, spies: list[Spy], done: Callable[[], bool]) -> Daemon:
    def factory_for(spy: Spy):
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


def _check_period(spy: Spy, taken: Callable[[StepReport], bool], period_s: float) -> None:
    """Snapshots every ``period_s``: the SLAM thread takes one at the first step that ends at least
    ``period_s`` after the last one did. It decides after the step, on its own thread: between the
    spy's ``record_inputs`` for the step's frame and the next one (that window brackets the moment,
    so the check holds however slow the machine is). A snapshot sooner than the period, or a step
    that ends a period after the last snapshot without one, fails."""
    index = {t: k for k, (t, _) in enumerate(spy.inputs)}

    def window(r: StepReport) -> tuple[float, float]:
        k = index[r.result.t_ns]
        return spy.inputs_at[k], spy.inputs_at[k + 1] if k + 1 < len(spy.inputs_at) else math.inf

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
    _check_period(spy, lambda r: r.landmarks is not None, Spy.map_period_s)
    assert with_state and "estimator" in with_state[0].state
    _check_period(spy, lambda r: r.state is not None, Spy.state_period_s)
    assert all(r.health in ("tracking", "degraded", "failed") for r in spy.reports)
    assert all(-1 <= r.quality <= 100 and r.latency_ms > 0 for r in spy.reports)
    assert len(spy.health) >= 5 and spy.health[-1]["frames_processed"] > 0
    # at shutdown: the final state, then closed
    assert spy.final is not None and spy.final[0] is not None and spy.closed
    assert spy.threads == {"inputs:robotd-slam", "publish:robotd-publisher"}


def test_a_failing_output_does_not_stop_the_others(tmp_path, monkeypatch, caplog):
    broken, good = Spy(fail=True), Spy()
    d = _run(tmp_path, monkeypatch, [broken, good], lambda: len(good.reports) >= 12)
    assert len(good.reports) == d.stats.steps > 10
    assert len(broken.reports) == d.stats.steps
    assert "output spy: spy: this output is broken on purpose" in caplog.text
