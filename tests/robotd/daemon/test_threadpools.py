"""The daemon's thread settings: OpenBLAS limited while it runs (slam.blas_threads), restored after.

In a fresh process (the robotd command's situation): an earlier limit-and-restore in the same
process can leave OpenBLAS ignoring the next change (robotd.daemon.threadpools.limit_blas_threads).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from tests.support.paths import REPO

SCRIPT = r"""
import json, sys, threading, time
import numpy  # noqa: F401  (loads OpenBLAS with one thread per core)
from threadpoolctl import threadpool_info
from robotd.config import load_config
from robotd.daemon import Daemon

def blas():
    return [int(i["num_threads"]) for i in threadpool_info() if i["user_api"] == "blas"]

before = blas()
cfg = load_config(None, {
    "camera": {"url": "sim://?fps=10"}, "vehicle": {"url": "sim://?fps=10"}, "zenoh": {"enabled": False},
    "slam": {"blas_threads": int(sys.argv[2])},
    "persistence": {"state_dir": sys.argv[1], "save_period_s": 0.0},
})
# until the first step (then stopped as a signal would), however long a busy host takes to it;
# the duration only guards against a hang
d = Daemon(cfg, duration_s=100.0, environ={})
th = threading.Thread(target=d.run)
th.start()
during = []
while th.is_alive():
    if d.stats.steps > 0:
        during = blas()
        break
    time.sleep(0.05)
d.stop_event.set()
th.join(30)
print(json.dumps({"before": before, "during": during, "after": blas(), "steps": d.stats.steps}))
"""


def test_blas_threads_limited_while_running_and_restored(tmp_path: Path) -> None:
    env_free = {k: v for k, v in os.environ.items() if not k.startswith("OPENBLAS")}
    out = subprocess.run(
        [sys.executable, "-c", SCRIPT, str(tmp_path), "1"],
        capture_output=True,
        text=True,
        timeout=120,
        env={**env_free, "OPENBLAS_NUM_THREADS": "2"},
        cwd=REPO,
    )
    assert out.returncode == 0, out.stderr[-2000:]
    r = json.loads(out.stdout.strip().splitlines()[-1])
    assert r["steps"] > 0
    assert r["before"] and max(r["before"]) == 2, r  # OpenBLAS started with two threads
    assert r["during"] and all(n == 1 for n in r["during"]), r
    assert r["after"] == r["before"], r


ENV_SCRIPT = r"""
import json, os, sys
import robotd.tools.cli  # noqa: F401  (the robotd command's module: sets the defaults at import)
print(json.dumps({
    "omp": os.environ.get("OMP_WAIT_POLICY"),
    "blas": os.environ.get("OPENBLAS_NUM_THREADS"),
}))
"""


def _cli_env(extra: dict[str, str]) -> dict[str, object]:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("OPENBLAS", "OMP_"))}
    out = subprocess.run(
        [sys.executable, "-c", ENV_SCRIPT],
        capture_output=True,
        text=True,
        timeout=60,
        env={**env, **extra},
        cwd=REPO,
    )
    assert out.returncode == 0, out.stderr[-2000:]
    r: dict[str, object] = json.loads(out.stdout.strip().splitlines()[-1])
    return r


def test_cli_sets_thread_environment_defaults() -> None:
    # one BLAS thread and sleeping (not spinning) OpenMP workers unless the user says otherwise
    r = _cli_env({})
    assert r["omp"] == "passive" and r["blas"] == "1", r


def test_cli_keeps_the_users_thread_environment() -> None:
    r = _cli_env({"OMP_WAIT_POLICY": "active", "OPENBLAS_NUM_THREADS": "3"})
    assert r["omp"] == "active" and r["blas"] == "3", r


def test_signal_handlers_are_restored_after_the_daemon_stops(tmp_path: Path) -> None:
    # a program embedding the daemon gets its own handlers back, and the stopped daemon is freed
    import gc
    import signal
    import weakref

    from robotd.config import load_config
    from robotd.daemon import Daemon

    def mine(signum: int, frame: object) -> None:  # pragma: no cover - never called
        pass

    old = signal.signal(signal.SIGTERM, mine)
    try:
        cfg = load_config(
            None,
            {
                "camera": {"url": "sim://?fps=10"},
                "vehicle": {"url": "sim://?fps=10"},
                "zenoh": {"enabled": False},
                "persistence": {"state_dir": str(tmp_path), "save_period_s": 0.0},
            },
        )
        d = Daemon(cfg, duration_s=1.0, environ={})
        assert d.run() == 0
        assert signal.getsignal(signal.SIGTERM) is mine
        ref = weakref.ref(d)
        del d
        gc.collect()
        assert ref() is None, "the stopped daemon is still referenced"
    finally:
        signal.signal(signal.SIGTERM, old)
