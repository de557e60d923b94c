"""The daemon's thread settings: OpenBLAS limited while it runs (slam.blas_threads), restored after."""

from __future__ import annotations

import threading
import time
from pathlib import Path

from threadpoolctl import threadpool_info

from robotd.config import load_config
from robotd.daemon import Daemon


def _blas_threads() -> list[int]:
    return [int(i["num_threads"]) for i in threadpool_info() if i["user_api"] == "blas"]


def test_blas_threads_limited_while_running_and_restored(tmp_path: Path) -> None:
    before = _blas_threads()
    assert before, "numpy should be linked against a BLAS threadpoolctl can see"
    cfg = load_config(
        None,
        {
            "camera": {"url": "sim://?fps=10"},
            "vehicle": {"url": "sim://?fps=10"},
            "zenoh": {"enabled": False},
            "slam": {"blas_threads": 1},
            "persistence": {"state_dir": str(tmp_path), "save_period_s": 0.0},
        },
    )
    d = Daemon(cfg, duration_s=4.0, environ={})
    th = threading.Thread(target=d.run)
    th.start()
    during: list[int] = []
    t_end = time.monotonic() + 20
    while th.is_alive() and time.monotonic() < t_end:
        if d.stats.steps > 0:
            during = _blas_threads()
            break
        time.sleep(0.05)
    th.join(30)
    assert not th.is_alive()
    assert d.stats.steps > 0
    assert during and all(n == 1 for n in during), during
    assert _blas_threads() == before
