"""bench/replay_speed.py: robotd's step over OpenCV's ORB floor, both timed on the same frames."""

from __future__ import annotations

import json
from types import ModuleType

import pytest

from tests.support.paths import load_bench


def _bench() -> ModuleType:
    return load_bench("replay_speed")


def test_the_ratio_is_the_step_over_the_floor_bracketing_it(capsys: pytest.CaptureFixture[str]) -> None:
    bench = _bench()
    assert bench.main(["--source", "sim://?fps=10&duration=0.8&seed=2", "--repeat", "1", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    (run,) = doc["runs"]
    assert run["frames"] == 8
    floor = 0.5 * (run["orb_pair_ms_p50_before"] + run["orb_pair_ms_p50_after"])
    assert floor > 0 and run["ratio"] == pytest.approx(run["step_ms_p50"] / floor, rel=1e-12)
    assert {"detect", "stereo", "update"} <= set(run["stages_ms_p50"])
    # the stages and what is outside them add up to the step (medians of sums: within the spread)
    assert run["outside_stages_ms_p50"] >= 0.0


def test_missing_data_is_skipped_with_a_reason(capsys: pytest.CaptureFixture[str], tmp_path) -> None:
    bench = _bench()
    assert bench.main(["--source", f"kitti://{tmp_path / 'none'}", "--json"]) == 0
    assert "no such data: skipped" in json.loads(capsys.readouterr().out)["skipped"]
