"""The local engine's limits (robotd/tools/batch/local.py, robotd/tools/batch/jobs.py): a replay past its time or
memory limit, or whose worker process dies, is a row saying so, and the other replays go on."""

from __future__ import annotations

import os
import signal
import threading
from typing import Any

from robotd.tools.batch.configs import build_configurations
from robotd.tools.batch.jobs import DIED, MEMORY, OK, TIMEOUT
from robotd.tools.batch.local import LocalEngine
from tests.support.batch_sources import sim_url
from tests.support.waiting import wait_for

# a paced drive of ten minutes: it would run for ten minutes
ENDLESS = "sim://yard?duration=600&realtime=1&width=160&height=100&fps=5&seed=2"


def _job(key: str, source: str, **limits: float) -> dict[str, Any]:
    c = build_configurations()[0]
    return {
        "key": key,
        "source": source,
        "source_digest": key,
        "config_name": c.name,
        "config": c.data,
        "config_digest": c.digest,
        **limits,
    }


def test_time_and_memory_limits_and_a_dead_worker_are_rows_and_the_rest_go_on() -> None:
    engine = LocalEngine(workers=2)
    rows: dict[str, dict[str, Any]] = {}
    killed: list[int] = []

    def kill_the_endless_one() -> None:
        # the job "dies" runs the endless drive without limits: its worker is killed from outside
        def running() -> list[int]:
            return [pid for pid, key in engine.running().items() if key == "dies"]

        if wait_for(lambda: bool(running()), 60.0):
            pid = running()[0]
            os.kill(pid, signal.SIGKILL)
            killed.append(pid)

    jobs = [
        _job("slow", ENDLESS, timeout_s=2.0),
        _job("hungry", sim_url(3), memory_mb=50.0),  # a worker process alone holds more
        _job("dies", ENDLESS),
        _job("fine", sim_url(4)),
    ]
    killer = threading.Thread(target=kill_the_endless_one, daemon=True)
    killer.start()
    engine.run(jobs, lambda row: rows.__setitem__(row["key"], row))
    killer.join()
    assert set(rows) == {"slow", "hungry", "dies", "fine"}
    slow = rows["slow"]
    assert slow["status"] == TIMEOUT and "after 2 s" in slow["error"], (slow.get("error"), slow.get("traceback"))
    assert rows["hungry"]["status"] == MEMORY and "above the limit of 50 MB" in rows["hungry"]["error"], rows["hungry"]
    assert killed and rows["dies"]["status"] == DIED, rows["dies"]
    assert rows["dies"]["error"] == "worker process died: killed by signal 9"
    assert rows["fine"]["status"] == OK and rows["fine"]["summary"]["frames"] == 10
    assert engine.replaced >= 3  # after the dead worker and the ones over their time and memory
