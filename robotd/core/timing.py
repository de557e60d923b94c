"""Stage timings of one step, recorded the same way for every stage (``StepResult.timings_ms``).

A stage of ``Pipeline.step`` is a method decorated with :func:`stage` on an object that holds the
step's :class:`StageClock` (robotd/pipeline/stages/): the step calls it as a plain method, and the
decorator records how long it took under the stage's name. The front end's own stages are timed
the same way, into the front end's clock (``Frontend.process``, robotd/frontend/frontend.py): a
stage is always a decorated method, never a call wrapped by its caller. ``time.perf_counter`` only
measures; nothing here reads a wall clock or sleeps, so a step stays pure with respect to I/O.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable
from typing import Concatenate, ParamSpec, Protocol, TypeVar

P = ParamSpec("P")
T = TypeVar("T")


class StageClock:
    """Milliseconds per named stage of one step, and the step's total."""

    def __init__(self) -> None:
        self.ms: dict[str, float] = {}
        self._t0 = time.perf_counter()

    def start(self) -> None:
        """A new step: no stage timed yet, the total counted from now. The last step's timings
        (what :meth:`finish` returned) are left as they were."""
        self.ms = {}
        self._t0 = time.perf_counter()

    def finish(self) -> dict[str, float]:
        """The stage timings with ``total`` (since the clock was made or started) added: a copy,
        so a stage timed after the step (``Pipeline.after_step``, on the SLAM thread while the
        publisher reads the result) never changes a result already handed on."""
        self.ms["total"] = (time.perf_counter() - self._t0) * 1e3
        return dict(self.ms)


class Timed(Protocol):
    """An object whose methods are stages: it holds the step's clock."""

    clock: StageClock


S = TypeVar("S", bound=Timed)


def stage(name: str) -> Callable[[Callable[Concatenate[S, P], T]], Callable[Concatenate[S, P], T]]:
    """Decorate a method as the step's stage ``name``: each call is timed into its object's
    ``clock`` (``clock.ms[name]``, in milliseconds; nothing is recorded when it raises). The
    decorated method keeps its name, signature and docstring, and carries ``stage_name``."""

    def decorate(fn: Callable[Concatenate[S, P], T]) -> Callable[Concatenate[S, P], T]:
        @functools.wraps(fn)
        def timed(self: S, *args: P.args, **kwargs: P.kwargs) -> T:
            t0 = time.perf_counter()
            out = fn(self, *args, **kwargs)
            self.clock.ms[name] = (time.perf_counter() - t0) * 1e3
            return out

        timed.stage_name = name  # type: ignore[attr-defined]
        return timed

    return decorate
