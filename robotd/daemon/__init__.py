"""The daemon (``robotd run``, ``robotd record``): lifecycle and threads (lifecycle.py), opening the
devices (devices.py), the latency budget (budget.py), health (health.py), thread-pool limits
(threadpools.py) and systemd notification (sdnotify.py). What it publishes goes through
robotd.outputs; what it computes is robotd.pipeline's ``step``.
"""

from __future__ import annotations

from robotd.daemon.lifecycle import Daemon, run_daemon

__all__ = ["Daemon", "run_daemon"]
