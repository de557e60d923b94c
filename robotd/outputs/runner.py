"""Every output under one error policy, each on a worker thread of its own.

The daemon never calls an output's hooks itself; it hands them to an :class:`OutputRunner`:

- ``tee_frame`` / ``tee_odometry`` run on the input threads, where the samples arrive: the
  recorder's sensor log must see every sample in the order the devices delivered them. A tee only
  queues the sample for the output's own thread (robotd.outputs.base) and returns;
- ``record_inputs`` (from the SLAM thread), ``publish`` (the publisher thread) and
  ``publish_health`` (the supervisor) go into the output's bounded drop-oldest queue, and the
  output's worker thread (``robotd-output-<name>``) makes the calls, in the order they were made.
  The caller never waits: an output that is slow or blocked delays neither SLAM nor the other
  outputs; when its queue is full its oldest call is dropped, counted (``dropped``) and said once;
- ``finish`` at shutdown, once every worker delivered what it had queued (within
  ``FINISH_WAIT_S``); each output's in turn, whatever the others' did. An output whose worker is
  still inside a call then does not get it (counted as a failed ``finish``);
- ``close`` when the daemon's ExitStack unwinds (:func:`enter_output`), each output's whatever the
  others' did;
- ``stats`` of every output, in the health document under ``outputs.<name>.stats`` (and, for an
  output with a ``health_key``, under that key as before: ``map_file``, ``recording``).

The policy, the same for every hook and every output: an exception (a RobotdError or any other) is
caught, logged once per output and hook with the output's name (with its traceback when it is not
a RobotdError: a bug), counted, and shown in the health document (``outputs.<name>.errors``,
``errors_by_hook``, ``last_error``, ``since_error_s``; a recent one makes the state ``degraded``,
robotd.daemon.health). It never stops SLAM, the daemon or another output. docs/architecture.md,
"Outputs: one error policy".
"""

from __future__ import annotations

import contextlib
import copy
import logging
import threading
import time
from collections.abc import Mapping, Sequence
from typing import Any, TypeVar

from robotd.core.errors import RobotdError
from robotd.core.msgs import Odometry, StereoFrame
from robotd.formats.queues import DropOldestQueue
from robotd.outputs.base import Output, StepReport

logger = logging.getLogger(__name__)

QUEUE_SIZE = 32  # calls waiting for one output's worker (about a second of steps at 30 Hz)
FINISH_WAIT_S = 5.0  # at shutdown, how long the workers may take to deliver what is queued
QUEUED_HOOKS = ("record_inputs", "publish", "publish_health")
O = TypeVar("O", bound=Output)


def overrides(out: Output, hook: str) -> bool:
    """``out``'s class implements ``hook`` (the base class's does nothing)."""
    return getattr(type(out), hook) is not getattr(Output, hook)


def plain(value: Any) -> Any:
    """``value`` as the health document carries it (JSON): numbers, strings, booleans, None, and
    lists and mappings of them; anything else as its string (an output's stats must not break the
    document another output publishes)."""
    if value is None or isinstance(value, bool | int | float | str):
        return value
    if isinstance(value, Mapping):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [plain(v) for v in value]
    item = getattr(value, "item", None)  # a numpy scalar
    if callable(item):
        with contextlib.suppress(Exception):
            return plain(item())
    return str(value)


class _Slot:
    """One output: its counters and, when it takes queued calls, its queue and worker thread."""

    def __init__(self, out: Output, key: str, queue_size: int) -> None:
        self.out = out
        self.key = key  # its name, made unique among the outputs (the health document's key)
        self.hooks = frozenset(h for h in QUEUED_HOOKS if overrides(out, h))
        self.queue: DropOldestQueue[tuple[str, tuple[Any, ...]]] = DropOldestQueue(queue_size)
        self.thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self.errors: dict[str, int] = {}
        self.last_error: str | None = None
        self.last_error_ns = 0
        self.last_drop_ns = 0
        self.pending = 0  # calls queued or being made (a dropped call is replaced by the new one)

    # -- the policy ----------------------------------------------------------------------------
    def call(self, hook: str, *args: Any) -> Any:
        """``out.<hook>(*args)`` under the policy (module docstring); its result, None on failure."""
        try:
            return getattr(self.out, hook)(*args)
        except Exception as exc:
            self.failed(hook, f"{type(exc).__name__}: {exc}", exc)
            return None

    def failed(self, hook: str, why: str, exc: BaseException | None = None) -> None:
        with self._lock:
            n = self.errors[hook] = self.errors.get(hook, 0) + 1
            self.last_error, self.last_error_ns = f"{hook}: {why}", time.monotonic_ns()
        if n == 1:  # once per output and hook: a broken output called every step must not flood the log
            logger.error(
                "output %s: %s failed: %s; SLAM and the other outputs go on (later failures are counted: "
                "health outputs.%s.errors)",
                self.key,
                hook,
                why,
                self.key,
                exc_info=exc if exc is not None and not isinstance(exc, RobotdError) else None,
            )

    # -- the worker ----------------------------------------------------------------------------
    def put(self, hook: str, args: tuple[Any, ...]) -> None:
        if hook not in self.hooks:
            return
        with self._lock:
            kept = self.queue.put((hook, args))
            self.pending += kept
        if not kept:
            first = self.last_drop_ns == 0
            self.last_drop_ns = time.monotonic_ns()
            if first:
                logger.warning(
                    "output %s falls behind: its oldest queued call was dropped (SLAM does not wait for it; "
                    "counted: health outputs.%s.dropped)",
                    self.key,
                    self.key,
                )

    def start(self) -> None:
        if self.hooks and self.thread is None:
            self.thread = threading.Thread(target=self._work, name=f"robotd-output-{self.key}", daemon=True)
            self.thread.start()

    def _work(self) -> None:
        q = self.queue
        while True:
            item = q.get(timeout=0.5)
            if item is None:
                if q.closed:
                    return
                continue
            self._deliver(item)

    def _deliver(self, item: tuple[str, tuple[Any, ...]]) -> None:
        try:
            self.call(item[0], *item[1])
        finally:
            with self._lock:
                self.pending -= 1

    def drain_here(self) -> None:
        """Make the queued calls on this thread (a worker that never started)."""
        while (item := self.queue.get(timeout=0)) is not None:
            self._deliver(item)

    def busy(self) -> bool:
        """A call is queued or being made."""
        with self._lock:
            return self.pending > 0

    # -- figures -------------------------------------------------------------------------------
    def health(self, now_ns: int) -> dict[str, Any]:
        stats = self.call("stats")
        with self._lock:
            errors = dict(self.errors)
            last, last_ns = self.last_error, self.last_error_ns
        return {
            "errors": sum(errors.values()),
            "errors_by_hook": errors,
            "last_error": last,
            "since_error_s": round((now_ns - last_ns) / 1e9, 1) if last_ns else None,
            "dropped": self.queue.dropped,
            "since_drop_s": round((now_ns - self.last_drop_ns) / 1e9, 1) if self.last_drop_ns else None,
            "queued": len(self.queue),
            "stats": plain(stats) if isinstance(stats, Mapping) else {},
        }


class OutputRunner:
    """The daemon's outputs, called under one error policy (module docstring). ``start`` the
    workers once the outputs are open; ``finish`` stops them."""

    def __init__(self, outputs: Sequence[Output], queue_size: int = QUEUE_SIZE) -> None:
        self.outputs = list(outputs)
        self._slots: list[_Slot] = []
        seen: dict[str, int] = {}
        for out in self.outputs:
            n = seen[out.name] = seen.get(out.name, 0) + 1
            self._slots.append(_Slot(out, out.name if n == 1 else f"{out.name}#{n}", queue_size))
        self._frame_tees = [s for s in self._slots if overrides(s.out, "tee_frame")]
        self._odometry_tees = [s for s in self._slots if overrides(s.out, "tee_odometry")]

    @property
    def tees_frames(self) -> bool:
        return bool(self._frame_tees)

    @property
    def tees_odometry(self) -> bool:
        return bool(self._odometry_tees)

    def start(self) -> None:
        for s in self._slots:
            s.start()

    # -- the hooks -----------------------------------------------------------------------------
    def tee_frame(self, frame: StereoFrame) -> None:
        """Camera thread: every frame the camera delivered."""
        for s in self._frame_tees:
            s.call("tee_frame", frame)

    def tee_odometry(self, odometry: Odometry) -> None:
        """Vehicle thread: every odometry sample the vehicle link delivered."""
        for s in self._odometry_tees:
            s.call("tee_odometry", odometry)

    def record_inputs(self, frame: StereoFrame, odometry: Sequence[Odometry]) -> None:
        """SLAM thread: queued, never waits."""
        args = (frame, list(odometry))
        for s in self._slots:
            s.put("record_inputs", args)

    def publish(self, report: StepReport) -> None:
        """Publisher thread: queued, never waits."""
        for s in self._slots:
            s.put("publish", (report,))

    def publish_health(self, health: Mapping[str, Any]) -> None:
        """Supervisor: queued, never waits. Each output gets its own copy of the document (small, once
        a period): the workers read it at the same time, and one that changed it must not break another."""
        for s in self._slots:
            if "publish_health" in s.hooks:
                s.put("publish_health", (copy.deepcopy(health),))

    def finish(self, state: Mapping[str, Any] | None, t_ns: int, wait_s: float = FINISH_WAIT_S) -> None:
        """Shutdown, once SLAM stopped: the workers deliver what is queued (within ``wait_s`` in
        all) and stop, then every output's ``finish``, each whatever the others' did."""
        for s in self._slots:
            s.queue.close()
        deadline = time.monotonic() + wait_s
        for s in self._slots:
            if s.thread is not None:
                s.thread.join(max(0.0, deadline - time.monotonic()))
            else:  # never started (no step ran): what was queued, here
                s.drain_here()
        for s in self._slots:
            if s.busy():
                s.failed("finish", f"not called: its worker was still in a call {wait_s:g} s after the stop")
                continue
            s.call("finish", state, t_ns)

    # -- figures -------------------------------------------------------------------------------
    def health(self) -> dict[str, Any]:
        """The health document's entries: ``outputs`` (every output's counters and ``stats()``,
        by name) and, for an output with a ``health_key``, its stats under that key."""
        now = time.monotonic_ns()
        entries = {s.key: s.health(now) for s in self._slots}
        doc: dict[str, Any] = {"outputs": entries}
        for s in self._slots:
            if s.out.health_key:
                doc[s.out.health_key] = entries[s.key]["stats"]
        return doc


def enter_output(stack: contextlib.ExitStack, out: O) -> O:
    """Enter ``out`` into ``stack``; its exit (``close``) under the outputs' policy: a failure is
    logged with the output's name, and the outputs entered before it still close."""
    out.__enter__()

    def close() -> None:
        try:
            out.__exit__(None, None, None)
        except Exception as exc:
            logger.error(
                "output %s: close failed: %s: %s", out.name, type(exc).__name__, exc,
                exc_info=exc if not isinstance(exc, RobotdError) else None,
            )  # fmt: skip

    stack.callback(close)
    return out
