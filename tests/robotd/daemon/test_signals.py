"""SIGTERM and SIGINT stop the daemon, and the handler never waits on a lock.

A Python signal handler runs in the main thread between two bytecodes, also while that thread
holds the stop event's own lock inside ``Event.wait``; a handler calling ``Event.set()`` there
deadlocks. The test calls the handler with the event's lock held by the calling thread, in a
process of its own (a deadlock would otherwise hang the suite), and expects the stop to arrive
once the lock is let go.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading

from robotd.daemon.signals import StopSignals
from tests.support.paths import REPO
from tests.support.waiting import wait_for

PROBE = """
import importlib.util, signal, threading
# the module alone (the robotd.daemon package would import the whole pipeline first)
spec = importlib.util.spec_from_file_location("signals", "robotd/daemon/signals.py")
mod = importlib.util.module_from_spec(spec)
spec.loader.exec_module(mod)
StopSignals = mod.StopSignals
stop = threading.Event()
sig = StopSignals(stop)
sig.install()
with stop._cond:  # what the main thread holds inside stop.wait()
    sig._on_signal(signal.SIGTERM, None)  # the handler, run right there
print("handler returned", flush=True)
print("stopped" if stop.wait(30) else "not stopped", sig.reason, flush=True)
sig.restore()
"""


def test_the_handler_takes_no_lock_the_main_thread_may_hold() -> None:
    out = subprocess.run(
        [sys.executable, "-c", PROBE], cwd=REPO, capture_output=True, text=True, timeout=60, env=dict(os.environ)
    )
    assert out.stdout.splitlines() == ["handler returned", "stopped SIGTERM"], out.stdout + out.stderr


def test_a_real_signal_sets_the_stop_event_and_restore_puts_the_handler_back() -> None:
    stop = threading.Event()
    sig = StopSignals(stop)
    before = signal.getsignal(signal.SIGINT)
    sig.install()
    try:
        os.kill(os.getpid(), signal.SIGINT)
        assert wait_for(stop.is_set, 5.0) and sig.reason == "SIGINT"
    finally:
        sig.restore()
    assert signal.getsignal(signal.SIGINT) is before
