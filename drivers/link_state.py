"""A vehicle link's state from what it actually received: ``ok``, ``degraded`` or ``lost``.

A link is only as good as its recent *good* frames (CRC-checked, decoded, values usable; for
MAVLink, messages from the autopilot itself). An open port that delivers nothing, or only frames
that fail their CRC, is not ``ok`` however healthy the port looks:

- ``lost``: no good frame for ``lost_after_s`` (since the link opened, when none came yet);
- ``degraded``: no good frame for ``stale_after_s``, or more than ``max_bad_fraction`` of the
  frames over the last ``window_s`` were bad (at least ``min_bad`` of them), or the owner flagged
  a fault (disconnected and reconnecting, protocol version mismatch);
- ``ok`` otherwise; ``closed`` before the link opens and after it closes.

The state is computed when asked (``state(now)``), from the clock, so it cannot be left behind at
``ok`` by a link that simply went quiet: a bad state never becomes ``ok`` without good frames.
Pure (no I/O, the caller passes monotonic nanoseconds); thread-safe for one writer and readers.
"""

from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass
from typing import Any

OK, DEGRADED, LOST, CLOSED = "ok", "degraded", "lost", "closed"


@dataclass(frozen=True, slots=True)
class LinkStateParams:
    stale_after_s: float = 0.5  # MCU wheel odometry comes at 50–200 Hz; 0.5 s is 25+ missed frames
    lost_after_s: float = 2.0
    window_s: float = 2.0
    max_bad_fraction: float = 0.2
    min_bad: int = 5  # a couple of line glitches in a quiet window are not a degraded link


class LinkState:
    """Good/bad frame bookkeeping and the state derived from it (module docstring)."""

    def __init__(self, params: LinkStateParams | None = None) -> None:
        self.params = params or LinkStateParams()
        self._lock = threading.Lock()
        self._opened_ns: int | None = None
        self._last_good_ns: int | None = None
        self._events: deque[tuple[int, int, int]] = deque()  # (t_ns, good, bad) per batch
        self._fault: str | None = None
        self.good_total = 0
        self.bad_total = 0

    def opened(self, now_ns: int) -> None:
        with self._lock:
            self._opened_ns = now_ns
            self._last_good_ns = None
            self._events.clear()

    def closed(self) -> None:
        with self._lock:
            self._opened_ns = None

    def fault(self, why: str | None) -> None:
        """Flag (or with None clear) a condition that makes the link degraded whatever it receives."""
        with self._lock:
            self._fault = why

    def record(self, now_ns: int, good: int = 0, bad: int = 0) -> None:
        """``good`` and ``bad`` frames received at ``now_ns``."""
        if good <= 0 and bad <= 0:
            return
        with self._lock:
            self.good_total += max(good, 0)
            self.bad_total += max(bad, 0)
            if good > 0:
                self._last_good_ns = now_ns
            self._events.append((now_ns, max(good, 0), max(bad, 0)))
            self._prune(now_ns)

    def _prune(self, now_ns: int) -> None:
        cut = now_ns - int(self.params.window_s * 1e9)
        while self._events and self._events[0][0] < cut:
            self._events.popleft()

    def window(self, now_ns: int) -> tuple[int, int]:
        """Good and bad frames over the last ``window_s``."""
        with self._lock:
            self._prune(now_ns)
            return sum(e[1] for e in self._events), sum(e[2] for e in self._events)

    def since_good_s(self, now_ns: int) -> float | None:
        """Seconds since the last good frame (None: none since the link opened)."""
        with self._lock:
            last = self._last_good_ns
        return None if last is None else max(now_ns - last, 0) / 1e9

    def state(self, now_ns: int) -> str:
        p = self.params
        with self._lock:
            opened, last, fault = self._opened_ns, self._last_good_ns, self._fault
        if opened is None:
            return CLOSED
        silent_s = max(now_ns - (last if last is not None else opened), 0) / 1e9
        if silent_s > p.lost_after_s:
            return LOST
        good, bad = self.window(now_ns)
        if last is None or silent_s > p.stale_after_s or fault is not None:
            return DEGRADED
        if bad >= p.min_bad and bad > p.max_bad_fraction * (good + bad):
            return DEGRADED
        return OK

    def stats(self, now_ns: int) -> dict[str, Any]:
        """``state``, ``since_good_s``, the window's ``good_window``/``bad_window``, and ``fault``."""
        good, bad = self.window(now_ns)
        since = self.since_good_s(now_ns)
        return {
            "state": self.state(now_ns),
            "since_good_s": None if since is None else round(since, 3),
            "good_window": good,
            "bad_window": bad,
            "fault": self._fault,
        }
