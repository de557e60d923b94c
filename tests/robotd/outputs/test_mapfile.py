"""The map file output never destroys a map silently: a run that did not resume from the saved map
keeps it under a new name before its first save, up to ``persistence.keep_maps`` of them."""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path

import numpy as np
import pytest

from robotd.config import PersistenceConfig
from robotd.outputs.mapfile import MapFileOutput

STATE = {"estimator_name": "fastslam2", "dim": 3, "estimator": {"x": np.zeros(3)}, "database": {}}


def _output(tmp_path: Path, keep: int = 5) -> MapFileOutput:
    return MapFileOutput(PersistenceConfig(state_dir=str(tmp_path), save_period_s=0.0, keep_maps=keep), "r1")


def _age(path: Path, seconds_ago: float) -> None:
    t = time.time() - seconds_ago
    os.utime(path, (t, t))


def test_a_new_run_keeps_the_previous_map_once(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO)
    first = _output(tmp_path)
    assert first.save(STATE, 1)
    first.close()
    _age(tmp_path / "map.robotd", 3600)
    second = _output(tmp_path)
    assert second.save(STATE, 2) and second.save(STATE, 3)  # the second save just overwrites its own map
    second.close()
    kept = sorted(tmp_path.glob("map.2*.robotd"))
    assert len(kept) == 1 and (tmp_path / "map.robotd").exists()
    assert f"kept the previous map as {kept[0]}" in caplog.text


def test_only_keep_maps_are_kept_and_the_removal_is_logged(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO)
    for k in range(4):
        out = _output(tmp_path, keep=2)
        assert out.save(STATE, k)
        out.close()
        _age(tmp_path / "map.robotd", 3600 * (10 - k))  # distinct, increasing times
    assert len(sorted(tmp_path.glob("map.2*.robotd"))) == 2
    assert caplog.text.count("removed the oldest kept map") == 1


def test_a_resumed_run_continues_its_map_in_place(tmp_path: Path) -> None:
    out = _output(tmp_path)
    assert out.save(STATE, 1)
    out.close()
    again = _output(tmp_path)
    again.resumed = True  # what resume() sets after loading the map into the pipeline
    assert again.save(STATE, 2)
    again.close()
    assert not list(tmp_path.glob("map.2*.robotd"))


def test_keep_maps_zero_overwrites_and_says_so(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    for k in range(2):
        out = _output(tmp_path, keep=0)
        assert out.save(STATE, k)
        out.close()
    assert not list(tmp_path.glob("map.2*.robotd"))
    assert "will be overwritten (persistence.keep_maps = 0)" in caplog.text


def test_unfinished_saves_of_dead_processes_are_removed_at_start(tmp_path: Path, caplog) -> None:
    import subprocess
    import sys

    caplog.set_level(logging.INFO)
    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    dead_pid = int(gone.stdout)  # a process that has exited
    orphan = tmp_path / f".map.robotd.{dead_pid}.tmp"
    orphan.write_bytes(b"x" * 1000)
    live = tmp_path / f".map.robotd.{os.getppid()}.tmp"  # a running process's save in progress
    live.write_bytes(b"y")
    out = _output(tmp_path)
    out.close()
    assert not orphan.exists() and live.exists()
    assert "an unfinished save" in caplog.text


def test_a_map_that_failed_to_resume_is_kept_not_overwritten(tmp_path: Path) -> None:
    from robotd.errors import PersistenceError

    class OtherFilter:  # a run whose config no longer matches the saved map (slam.dim 3 -> 2, say)
        def load_state_dict(self, state: object) -> None:
            raise PersistenceError("saved map is from 'fastslam2' in 3D, this run uses 'fastslam2' in 2D")

    first = _output(tmp_path)
    assert first.save(STATE, 1)
    first.close()
    saved = (tmp_path / "map.robotd").read_bytes()
    second = _output(tmp_path)
    assert not second.resume(OtherFilter())  # type: ignore[arg-type]
    assert second.save(STATE, 2)
    second.close()
    kept = sorted(tmp_path.glob("map.2*.robotd"))
    assert len(kept) == 1 and kept[0].read_bytes() == saved


def test_failed_saves_are_counted_with_the_error_for_health(tmp_path: Path) -> None:
    out = _output(tmp_path)
    assert out.save(STATE, 1)
    assert out.stats()["failures"] == 0 and not out.stats()["last_failed"]
    # the map's name is taken by a non-empty directory: the rename into place fails (even as root)
    (tmp_path / "map.robotd").unlink()
    (tmp_path / "map.robotd").mkdir()
    (tmp_path / "map.robotd" / "x").write_text("x")
    assert not out.save(STATE, 2)
    st = out.stats()
    assert st["failures"] == 1 and st["last_failed"] and st["since_failure_s"] is not None
    assert "map.robotd" in st["last_error"]
    (tmp_path / "map.robotd" / "x").unlink()
    (tmp_path / "map.robotd").rmdir()
    assert out.save(STATE, 3)
    st = out.stats()
    assert st["failures"] == 1 and not st["last_failed"]  # the count stays; the current state is good
    out.close()
