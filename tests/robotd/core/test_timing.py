"""robotd.core.timing: the step's stage clock, and stage methods timed by their decorator."""

from __future__ import annotations

import pytest

from robotd.core.errors import InputError
from robotd.core.timing import StageClock, stage


class Stages:
    def __init__(self, clock: StageClock) -> None:
        self.clock = clock
        self.calls: list[tuple[int, int]] = []

    @stage("add")
    def add(self, a: int, b: int = 0) -> int:
        """Adds."""
        self.calls.append((a, b))
        return a + b

    @stage("fail")
    def fail(self) -> None:
        raise InputError("refused")


def test_a_stage_method_is_a_plain_call_timed_under_its_name() -> None:
    clock = StageClock()
    s = Stages(clock)
    assert s.add(2, b=3) == 5 and s.calls == [(2, 3)]
    assert Stages.add.__name__ == "add" and Stages.add.__doc__ == "Adds." and Stages.add.stage_name == "add"
    assert list(clock.ms) == ["add"] and clock.ms["add"] >= 0.0
    timings = clock.finish()
    assert list(timings) == ["add", "total"] and timings["total"] >= timings["add"]


def test_a_stage_that_raises_records_nothing() -> None:
    s = Stages(StageClock())
    with pytest.raises(InputError):
        s.fail()
    assert s.clock.ms == {}


def test_start_begins_a_new_step_and_leaves_the_last_steps_timings() -> None:
    clock = StageClock()
    s = Stages(clock)
    s.add(1)
    first = clock.finish()
    clock.start()
    assert clock.ms == {}
    s.add(2)
    second = clock.finish()
    assert list(first) == list(second) == ["add", "total"] and first is not second
