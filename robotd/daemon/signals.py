"""SIGTERM and SIGINT as a stop flag (design.md §5.10: signal handlers only set flags)."""

from __future__ import annotations

import signal
import threading
from collections.abc import Callable
from types import FrameType
from typing import Any

SignalHandler = Callable[[int, FrameType | None], Any] | int | None


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

    def _on_signal(self, signum: int, _frame: FrameType | None) -> None:
        self.reason = signal.Signals(signum).name
        self.stop.set()

    def install(self) -> None:
        if threading.current_thread() is threading.main_thread():
            self._prev = {sig: signal.signal(sig, self._on_signal) for sig in (signal.SIGTERM, signal.SIGINT)}

    def restore(self) -> None:
        if threading.current_thread() is threading.main_thread():
            for sig, handler in self._prev.items():
                signal.signal(sig, handler if handler is not None else signal.SIG_DFL)
        self._prev = {}
