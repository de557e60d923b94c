"""bench/accuracy.py runs robotd's replays on replay-many's engine (robotd.batch) and keeps its table:
the same figures as a replay in this process, and with ``--out`` a rerun replays nothing."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path
from types import ModuleType

import pytest

from robotd.config import load_config
from robotd.replay import replay
from tests.support.paths import REPO


def _bench() -> ModuleType:
    spec = importlib.util.spec_from_file_location("bench_accuracy", REPO / "bench" / "accuracy.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


def test_accuracy_runs_on_the_engine_with_the_figures_of_a_replay(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bench = _bench()
    argv = ["--quick", "--data", str(tmp_path / "no-kitti"), "--sim", "yard", "--max-frames", "6"]
    argv += ["--jobs", "1", "--out", str(tmp_path / "out"), "--json"]
    assert bench.main(argv) == 0
    out = json.loads(capsys.readouterr().out)
    rows = {r["method"]: r for r in out["rows"]}
    assert set(rows) == {"pnp", "robotd"} and out["engine"].startswith("local")
    r = rows["robotd"]
    assert r["source"].endswith("duration=0.2") and r["frames"] == 6
    direct = replay(load_config(None), r["source"], progress=False)
    # the figures of the same replay: to rounding (this test process's thread settings, left by
    # earlier tests, may reorder a sum; the batch tests check bit-identical trajectories between
    # replay-many and single `robotd replay` processes)
    assert r["ate_m"] == pytest.approx(direct["truth_ate_rmse_m"], rel=1e-9, abs=1e-12)
    assert r["drift_m"] == pytest.approx(direct["truth_drift_m"], rel=1e-9, abs=1e-12)
    assert r["lost_frames"] == direct["lost_frames"]
    rows_file = tmp_path / "out" / "rows.jsonl"
    n = len(rows_file.read_text().splitlines())
    assert bench.main(argv) == 0  # the rerun reuses the folder's row
    capsys.readouterr()
    assert len(rows_file.read_text().splitlines()) == n


def test_the_table_keeps_its_columns(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bench = _bench()
    argv = ["--quick", "--data", str(tmp_path), "--sim", "yard", "--max-frames", "4", "--jobs", "1"]
    assert bench.main(argv) == 0
    text = capsys.readouterr().out
    assert "| place | method | detector | filter | input | frames | lost | drift % | ATE m |" in text
    assert "| sim:yard | robotd | orb | fastslam2 | vision+odometry | 4 |" in text
