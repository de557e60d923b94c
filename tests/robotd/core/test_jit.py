"""robotd.core.jit: a kernel numba finds in its disk cache is loaded, not compiled, and CompileWatch
hears only real compiles (issue 27, item 10: "the first run compiles" was said on warm starts too)."""

from __future__ import annotations

import importlib.util
import logging
from pathlib import Path
from types import ModuleType

import pytest

import robotd.core.jit as robotd_jit
import robotd.daemon.lifecycle as lifecycle
from robotd.config import load_config
from robotd.core.jit import CompileWatch
from robotd.daemon import Daemon
from robotd.pipeline.step import Pipeline

KERNEL = """
from robotd.core.jit import jit


@jit
def plus_one(x):
    return x + 1
"""


def _load(path: Path, name: str) -> ModuleType:
    """The module at ``path`` under a new name: a new dispatcher, as in a new process."""
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_a_kernel_in_the_disk_cache_is_loaded_and_no_compile_is_heard(tmp_path: Path) -> None:
    path = tmp_path / "kern.py"
    path.write_text(KERNEL)
    heard: list[str] = []
    with CompileWatch(lambda: heard.append("first")) as cold:
        assert _load(path, "kern_first_process").plus_one(1) == 2  # nothing cached yet: compiled
    assert cold.compiled == 1 and heard == ["first"]
    with CompileWatch(lambda: heard.append("again")) as warm:
        assert _load(path, "kern_next_process").plus_one(1) == 2  # the same source: from the cache
    assert warm.compiled == 0 and heard == ["first"]
    path.write_text(KERNEL.replace("x + 1", "1 + x"))  # an edited kernel compiles again
    with CompileWatch() as edited:
        assert _load(path, "kern_edited").plus_one(1) == 2
    assert edited.compiled == 1
    with CompileWatch() as outside:
        pass
    plus_two = _load(path, "kern_outside")
    assert plus_two.plus_one(1) == 2 and outside.compiled == 0  # heard only while entered


def _start(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> list[str]:
    """A daemon's start-up (it stops at once: the duration is spent before the first step)."""
    cfg = load_config(
        None,
        {
            "camera": {"url": "sim://?fps=10"},
            "vehicle": {"url": "sim://?fps=10"},
            "zenoh": {"enabled": False},
            "persistence": {"state_dir": str(tmp_path), "save_period_s": 0.0},
        },
    )
    caplog.set_level(logging.INFO, logger="robotd.daemon")
    assert Daemon(cfg, duration_s=0.01, environ={}).run() == 0
    return [r.getMessage() for r in caplog.records if r.name == "robotd.daemon"]


def test_a_warm_start_does_not_say_it_compiles(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    Pipeline.warmup()  # compiled or loaded: either way nothing is left to compile
    lines = _start(tmp_path, caplog)
    assert not any("compil" in x and "kernels" in x and "ready" not in x for x in lines), lines
    ready = [x for x in lines if x.startswith("filter and matcher kernels ready in")]
    assert len(ready) == 1 and "loaded from the numba cache" in ready[0], lines


def test_a_cold_start_says_so_before_the_compile(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    # a cold cache, as numba reports it: a kernel the warm-up has to compile (a new one, uncached)
    real = Pipeline.warmup
    path = tmp_path / "kern.py"
    path.write_text(KERNEL)

    def warmup(measurements: tuple[str, ...] = (), dims: tuple[int, ...] = (3,)) -> float:
        seconds = real(measurements, dims)
        _load(path, "kern_cold_start").plus_one(1)
        return seconds

    monkeypatch.setattr(Pipeline, "warmup", staticmethod(warmup))
    # kernels that an earlier test decorated without a writable cache stay listed for the process
    # (robotd.core.jit.UNCACHED) and change the message: this test is about a cache that works
    monkeypatch.setattr(robotd_jit, "UNCACHED", [])
    lines = _start(tmp_path / "state", caplog)
    said = [k for k, x in enumerate(lines) if x == lifecycle.COMPILING]
    ready = [k for k, x in enumerate(lines) if x.startswith("filter and matcher kernels ready in")]
    assert len(said) == 1 and len(ready) == 1 and said[0] < ready[0], lines
    assert "1 compiled, now cached" in lines[ready[0]]


def test_kernels_cached_reads_the_disk_cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import os
    import subprocess
    import sys

    Pipeline.warmup()  # compiled or loaded: the cache holds them now
    monkeypatch.setattr(robotd_jit, "UNCACHED", [])
    assert lifecycle.kernels_cached()
    # a process whose numba cache is an empty directory: nothing there
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "empty"))
    code = "from robotd.daemon.lifecycle import kernels_cached; print(kernels_cached())"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "False", out
    # kernels without a disk cache compile in every process: not cached
    monkeypatch.setattr(robotd_jit, "UNCACHED", ["kern.plus_one"])
    assert not lifecycle.kernels_cached()


def test_the_kernels_load_while_the_block_runs_and_their_error_is_raised(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import threading

    from robotd.core.errors import RobotdError

    cfg = load_config(None, {"zenoh": {"enabled": False}})
    started, block_ran = threading.Event(), threading.Event()
    seen: list[bool] = []

    def load(_: object) -> None:
        started.set()
        seen.append(block_ran.wait(60.0))  # the block runs meanwhile (a sequential load would time out)

    monkeypatch.setattr(lifecycle, "_load_kernels", load)
    with lifecycle._KernelLoader(cfg):
        assert started.wait(60.0)
        block_ran.set()
    assert seen == [True]  # and the block's end waited for the load

    def fails(_: object) -> None:
        raise RobotdError("no kernels today")

    monkeypatch.setattr(lifecycle, "_load_kernels", fails)
    with pytest.raises(RobotdError, match="no kernels today"), lifecycle._KernelLoader(cfg):
        pass
    # the block's own error wins (a device that failed to open says so, not the kernels)
    with pytest.raises(ValueError, match="the camera"), lifecycle._KernelLoader(cfg):
        raise ValueError("the camera")
