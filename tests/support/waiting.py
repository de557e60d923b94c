"""Waiting for an event in a test, on a machine that may be busy.

A test waits for something to happen (a message to arrive, a link to come up); the time it
allows is a ceiling for a stuck test, never a measurement. CI's 2-core machine may be loaded, so
every ceiling is stretched by ``SLACK``: a condition that holds returns at once whatever the
ceiling, and speed is the benchmarks' business.
"""

from __future__ import annotations

import time
from collections.abc import Callable

SLACK = 4.0


def wait_for(cond: Callable[[], bool], timeout_s: float = 5.0) -> bool:
    """Poll ``cond`` until it holds (True) or ``SLACK × timeout_s`` seconds pass (its last value)."""
    t_end = time.monotonic() + SLACK * timeout_s
    while time.monotonic() < t_end:
        if cond():
            return True
        time.sleep(0.01)
    return cond()
