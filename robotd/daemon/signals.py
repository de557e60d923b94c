"""SIGTERM and SIGINT as a stop flag (signal handlers only set flags).

A Python signal handler runs in the main thread between two bytecodes, wherever that thread is:
also inside ``threading.Event.wait`` with the event's own lock held. A handler that called
``Event.set()`` there would wait for that lock, which its own thread holds, for ever: the daemon's
main thread waits on its stop event in a loop, so a SIGTERM could hang it with no "shutting down"
line (seen once in a test run under load). So the handler here only stores the signal's name, and
a small thread relays it to the stop event.
"""

from __future__ import annotations

import signal
import threading
import time
from collections.abc import Callable
from types import FrameType
from typing import Any

SignalHandler = Callable[[int, FrameType | None], Any] | int | None

RELAY_PERIOD_S = 0.02  # how soon a signal reaches the stop event


class StopSignals:
    """While installed, SIGTERM/SIGINT set ``stop`` and record the signal's name in ``reason``.

    Installing replaces the handlers only on the main thread (Python delivers signals there);
    :meth:`restore` puts the previous handlers back, so a program that embeds the daemon keeps its
    own Ctrl-C after the daemon stops, and a stopped daemon is not kept alive by its handlers.
    """

    def __init__(self, stop: threading.Event) -> None:
        self.stop = stop
        self.reason = ""
        self._prev: dict[int, SignalHandler] = {}
        self._pending = False  # set by the handler: a plain store, no lock
        self._relay: threading.Thread | None = None
        self._relaying = False

    def _on_signal(self, signum: int, _frame: FrameType | None) -> None:
        # no lock may be taken here (module docstring): two attribute stores
        self.reason = signal.Signals(signum).name
        self._pending = True

    def _relay_loop(self) -> None:
        while self._relaying:
            if self._pending and not self.stop.is_set():
                self.stop.set()
            time.sleep(RELAY_PERIOD_S)

    def install(self) -> None:
        if threading.current_thread() is threading.main_thread():
            self._prev = {sig: signal.signal(sig, self._on_signal) for sig in (signal.SIGTERM, signal.SIGINT)}
            self._relaying = True
            self._relay = threading.Thread(target=self._relay_loop, name="robotd-signals", daemon=True)
            self._relay.start()

    def restore(self) -> None:
        if threading.current_thread() is threading.main_thread():
            for sig, handler in self._prev.items():
                signal.signal(sig, handler if handler is not None else signal.SIG_DFL)
        self._prev = {}
        self._relaying = False
        if self._relay is not None:
            self._relay.join(1.0)
            self._relay = None
