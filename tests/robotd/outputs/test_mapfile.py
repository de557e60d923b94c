"""The map file output never destroys a map silently: a run that did not resume from the saved map
keeps it under a new name before its first save, up to ``persistence.keep_maps`` of them."""

from __future__ import annotations

import logging
import os
import re
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
    from robotd.core.errors import MapMismatchError

    class OtherFilter:  # a run whose config no longer matches the saved map (slam.dim 3 -> 2, say)
        def load_state_dict(self, state: object) -> None:
            raise MapMismatchError("saved map is from 'fastslam2' in 3D, this run uses 'fastslam2' in 2D")

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


# ---------------------------------------------------------------------------------------------
# maps with a valid checksum and invalid content (issue 15): checked whole before the pipeline is
# touched, moved aside with one log line, and the run starts a new map that works


def _resume(tmp_path: Path, blob: bytes, filt: str = "fastslam2", dim: int = 3, keep: int = 5, **frontend):
    from tests.support import saved_maps

    (tmp_path / "map.robotd").write_bytes(blob)
    p = saved_maps.pipeline(filt, dim, **frontend)
    out = _output(tmp_path, keep)
    return out, p, out.resume(p)


def _step_all(p) -> None:
    from tests.support import saved_maps

    frames, _ = saved_maps.sim_frames()
    p.relocaliser.arm(0)  # the filter predicts and updates on this frame
    for f in frames[saved_maps.N_MAP_FRAMES :]:
        p.step(f, None)


def _set(state: dict, path: str, value: object) -> dict:
    *parents, last = path.split(".")
    d = state
    for k in parents:
        d = d[k]
    if value is _DROP:
        del d[last]
    else:
        d[last] = value
    return state


_DROP = object()


@pytest.mark.parametrize(
    ("path", "value", "message"),
    [
        ("estimator.lm_cov", _DROP, "state.estimator.lm_cov: missing|fastslam2 state.lm_cov: missing"),
        ("database.next_id", _DROP, "database.next_id: missing"),
        ("estimator", _DROP, "state.estimator: missing"),
        ("estimator.pose", "ten", "pose: expected an array, got str"),
        ("estimator.best", 2.5, "best: expected an integer, got float"),
        ("estimator.log_w", np.zeros(3), r"log_w: expected shape \(20,\), got \(3,\)"),
        ("estimator.lm_mean", np.zeros((20, 5, 3), np.float32), "lm_mean: expected dtype <f8, got <f4"),
        ("database.next_id", 2**63 - 1, rf"database.next_id: expected an integer in \[0, {2**63 - 1 - 2**40}\]"),
        ("database.binary", "yes", "database.binary: expected a boolean, got str"),
        ("dim", True, r"state.dim: expected one of \[2, 3\], got True"),
    ],
)
def test_a_map_with_valid_checksum_but_invalid_content_is_moved_aside(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, path: str, value: object, message: str
) -> None:
    from tests.support import saved_maps

    blob = saved_maps.seal(_set(saved_maps.saved_state(), path, value))
    out, p, resumed = _resume(tmp_path, blob)
    assert not resumed and not out.resumed
    failed = [r.getMessage() for r in caplog.records if r.getMessage().startswith("resume failed")]
    assert len(failed) == 1 and "\n" not in failed[0], failed
    assert re.search(message, failed[0]), failed[0]
    assert "moved aside to map.robotd.bad-" in failed[0] and "starting a new map" in failed[0]
    aside = list(tmp_path.glob("map.robotd.bad-*"))
    assert len(aside) == 1 and aside[0].read_bytes() == blob  # kept as it was
    assert p.estimator.landmark_ids().size == 0  # nothing of it reached the filter
    _step_all(p)  # a new map that works
    assert p.estimator.landmark_ids().size > 0
    assert out.save(p.state_dict(), 2)
    out.close()
    assert aside[0].read_bytes() == blob


def test_a_resumed_next_id_at_the_int64_limit_is_refused_not_a_crash_at_association(tmp_path: Path) -> None:
    # the fault campaign's map: the SLAM thread died with OverflowError at the first new landmark
    from tests.support import saved_maps

    blob = saved_maps.seal(_set(saved_maps.saved_state(), "database.next_id", 2**63 - 1))
    out, p, resumed = _resume(tmp_path, blob)
    out.close()
    assert not resumed and list(tmp_path.glob("map.robotd.bad-*"))
    _step_all(p)


def test_a_half_valid_map_changes_nothing(tmp_path: Path) -> None:
    # the filter's part is valid, the descriptors disagree with it: not even the filter is loaded
    from tests.support import saved_maps

    state = saved_maps.saved_state()
    state["database"]["ids"] = state["database"]["ids"][:-1].copy()
    state["database"]["desc"] = state["database"]["desc"][:-1].copy()
    out, p, resumed = _resume(tmp_path, saved_maps.seal(state))
    out.close()
    assert not resumed and p.estimator.landmark_ids().size == 0 and p.frontend.descriptors is None


def test_content_that_fails_is_moved_aside_even_with_keep_maps_0(tmp_path: Path) -> None:
    from tests.support import saved_maps

    blob = saved_maps.seal(_set(saved_maps.saved_state(), "estimator.neff", float("nan")))
    out, p, resumed = _resume(tmp_path, blob, keep=0)
    assert not resumed
    _step_all(p)
    assert out.save(p.state_dict(), 2)
    out.close()
    assert [a.read_bytes() for a in tmp_path.glob("map.robotd.bad-*")] == [blob]


def test_a_map_of_another_detector_is_kept_not_called_corrupt(tmp_path: Path, caplog) -> None:
    # an ORB map and a SIFT run: binary 32-byte descriptors cannot match SIFT's 128 floats
    from tests.support import saved_maps

    blob = saved_maps.seal(saved_maps.saved_state())
    out, p, resumed = _resume(tmp_path, blob, detector="sift")
    assert not resumed and not list(tmp_path.glob("map.robotd.bad-*"))
    assert "saved map has binary descriptors of 32, this run's detector 'sift' makes float descriptors of 128" in (
        caplog.text
    )
    _step_all(p)
    assert out.save(p.state_dict(), 2)
    out.close()
    assert [k.read_bytes() for k in tmp_path.glob("map.2*.robotd")] == [blob]


def test_a_bad_map_that_cannot_be_moved_is_never_saved_over_and_stats_say_why(tmp_path: Path, monkeypatch) -> None:
    # the move-aside fails as on a read-only filesystem (tests/robotd/daemon/test_read_only_state.py
    # runs the daemon on a really read-only directory); only the rename of the bad map is refused
    import errno

    from tests.support import saved_maps

    real_replace = os.replace

    def replace(src, dst):
        if ".bad-" in str(dst):
            raise OSError(errno.EROFS, "Read-only file system")
        return real_replace(src, dst)

    monkeypatch.setattr(os, "replace", replace)
    blob = saved_maps.seal(_set(saved_maps.saved_state(), "estimator.log_w", _DROP))
    out, p, resumed = _resume(tmp_path, blob)
    assert not resumed and out.stats()["not_saving"] is not None
    assert "log_w: missing" in out.stats()["not_saving"]
    _step_all(p)
    assert not out.save(p.state_dict(), 2) and not out.save(p.state_dict(), 3)
    out.close()
    assert out.stats()["failures"] == 2 and out.stats()["saves"] == 0
    assert sorted(q.name for q in tmp_path.iterdir()) == ["map.robotd"]
    assert (tmp_path / "map.robotd").read_bytes() == blob


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
