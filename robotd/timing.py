"""Stage timings of one step, recorded the same way for every stage (``StepResult.timings_ms``).

``time.perf_counter`` only measures; nothing here reads a wall clock or sleeps, so a step stays
pure with respect to I/O.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import ParamSpec, TypeVar

P = ParamSpec("P")
T = TypeVar("T")


class StageClock:
    """Milliseconds per named stage of one step, and the step's total."""

    def __init__(self) -> None:
        self.ms: dict[str, float] = {}
        self._t0 = time.perf_counter()

    def run(self, stage: str, fn: Callable[P, T], *args: P.args, **kwargs: P.kwargs) -> T:
        """Call ``fn(*args, **kwargs)`` as the stage ``stage`` and record how long it took."""
        t0 = time.perf_counter()
        out = fn(*args, **kwargs)
        self.ms[stage] = (time.perf_counter() - t0) * 1e3
        return out

    def finish(self) -> dict[str, float]:
        """The stage timings with ``total`` (since the clock was made) added."""
        self.ms["total"] = (time.perf_counter() - self._t0) * 1e3
        return self.ms
