"""Daemon runs that end on events, not after a wall-clock duration.

A test that runs the daemon for "2.5 s" and then expects more than 10 steps asserts the machine's
speed: on a busy 2-core CI host the same 2.5 s held 5 steps. These helpers run it until what the
test needs has happened (so many steps published, a health document after the stall, ...), however
long that takes, and stop it the way SIGTERM does. The daemon's own ``duration_s`` is then only a
guard against a hang (``HANG_GUARD_S``), and a run that hits it fails the test with a message.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

from robotd.daemon import Daemon

# long enough that a run stopped by it means a hang or a bug, not a slow machine; well inside the
# suite's per-test timeout (pyproject.toml: 300 s)
HANG_GUARD_S = 150.0


def run_until(d: Daemon, done: Callable[[], bool], poll_s: float = 0.02) -> tuple[int, bool]:
    """Run ``d`` on this thread until ``done()`` holds, then stop it (``d.stop_event``, what the
    signal handlers set). ``done`` is checked every ``poll_s`` from a watcher thread; it reads what
    the test's outputs collected. Returns the exit status and whether ``done()`` held when the run
    ended (False: the daemon stopped by itself before: its source ended, a thread failed, or
    ``duration_s``)."""
    finished = threading.Event()
    reached = threading.Event()

    def watch() -> None:
        while not finished.wait(poll_s):
            if done():
                reached.set()
                d.stop_event.set()
                return

    watcher = threading.Thread(target=watch, name="test-run-until", daemon=True)
    watcher.start()
    try:
        status = d.run()
    finally:
        finished.set()
        watcher.join()
    return status, reached.is_set() or done()
