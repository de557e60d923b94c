"""bench/accuracy.py runs robotd's replays on replay-many's engine (robotd.tools.batch) and keeps its table:
the same figures as a replay in this process, and with ``--out`` a rerun replays nothing."""

from __future__ import annotations

import json
from pathlib import Path
from types import ModuleType

import pytest

from robotd.config import load_config
from robotd.tools.replay import replay
from tests.support.paths import load_bench


def _bench() -> ModuleType:
    return load_bench("accuracy")


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
    # issue 26's figures ride along: none on this 0.2 s run (no 100 m segment, nothing past 10 m)
    assert r["segment_count"] == direct["truth_segment_count"] == 0 and r["segment_drift_pct"] is None
    assert r["alignment"] == direct["truth_alignment"] and r["nees_aligned_frames"] == 0
    assert r["nees_aligned_in_band_frac"] is None and out["align_positions_m"] == 10.0
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
    assert "| RPE m | seg. drift % | seg. deg/m | NEES in band, aligned 10 m | ms/frame p50 |" in text
    assert "| sim:yard | robotd | orb | fastslam2 | vision+odometry | 4 |" in text


def test_a_summarys_segment_drift_and_positions_aligned_nees_become_the_rows_columns(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """The one mapping from a replay summary (in process or the engine's) to a row, and the cells."""
    bench = _bench()
    s = {
        "frames": 51,
        "lost_frames": 0,
        "step_ms_p50": 30.0,
        "step_ms_p95": 40.0,
        "wall_s": 2.0,
        "truth_drift_pct": 0.5,
        "truth_ate_rmse_m": 0.06,
        "truth_rpe_trans_m": 0.01,
        "truth_segment_drift_pct": 0.75,
        "truth_segment_rot_deg_per_m": 0.0123,
        "truth_segment_count": 12,
        "truth_aligned_nees_pos_in_band_frac": 0.214,
        "truth_aligned_nees_pos_mean": 25.5,
        "truth_aligned_nees_pos_frames": 42,
        "truth_alignment": "positions+first-pose-roll",
    }
    f = bench._figures(s)
    assert (f["segment_drift_pct"], f["segment_rot_deg_per_m"], f["segment_count"]) == (0.75, 0.0123, 12)
    assert (f["nees_aligned_in_band_frac"], f["nees_aligned_mean"], f["nees_aligned_frames"]) == (0.214, 25.5, 42)
    assert f["alignment"] == "positions+first-pose-roll"
    row = {"place": "p", "method": "robotd", "detector": "orb", "filter": "fastslam2"}
    row.update(f)
    out = {"config": "c", "commit": "x", "host": "h", "rows": [row], "skipped": [], "jobs": 1, "wall_s": 1.0}
    bench.print_table(out)
    text = capsys.readouterr().out
    assert "| 0.060 | 0.0100 | 0.75 | 0.0123 | 0.21 of 42, roll from pose 0 | 30.0 |" in text
    # a summary without them (a path too short, or no covariance: the PnP baseline): dashes
    f = bench._figures({k: v for k, v in s.items() if not k.startswith("truth_")})
    assert f["segment_drift_pct"] is None and f["nees_aligned_in_band_frac"] is None
    assert bench._nees_cell(f) == "–"


def test_every_real_folder_is_a_place_kitti_judged_euroc_reported(tmp_path: Path) -> None:
    """Issue 26 asks for the table on every shared real folder: EuRoC's too (reported, not judged)."""
    bench = _bench()
    (tmp_path / "k" / "image_0").mkdir(parents=True)
    (tmp_path / "k" / "calib.txt").write_text("P0: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    (tmp_path / "e" / "mav0" / "cam0").mkdir(parents=True)
    (tmp_path / "e" / "mav0" / "cam1").mkdir(parents=True)
    (tmp_path / "other").mkdir()
    places = bench.real_places(tmp_path, None)
    assert [(p.name, p.kind) for p in places] == [("k", "kitti"), ("e", "euroc")]
    assert places[1].source == f"euroc://{(tmp_path / 'e').resolve()}"
    assert bench.limit_frames(places[1], 10).source.endswith("?stop=10")
    rows = [{"place": "e", "method": "robotd", "detector": "orb", "filter": "fastslam2", "ate_m": 0.001}]
    bench.judge(rows, places, "fastslam2")
    assert rows[0]["verdict"] is None and rows[0]["target"] is False
    with pytest.raises(SystemExit, match="not a KITTI folder .* or a EuRoC one"):
        bench.real_places(tmp_path, ["other"])
