"""The daemon (``robotd run``, ``robotd record``): lifecycle and threads (lifecycle.py), opening the
devices (devices.py) after checking their URLs (device_urls.py, which ``robotd replay`` and
``robotd doctor`` use too), the latency budget (budget.py), health (health.py), thread-pool limits
(threadpools.py) and systemd notification (sdnotify.py). What it publishes goes through
robotd.outputs; what it computes is ``Pipeline.step`` (robotd.pipeline.step).
"""

from __future__ import annotations

from robotd.daemon.lifecycle import Daemon, run_daemon

__all__ = ["Daemon", "run_daemon"]
