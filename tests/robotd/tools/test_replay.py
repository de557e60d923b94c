"""``robotd replay``'s human output (robotd/tools/replay.py): the one summary line on stderr, the opening
line, no progress bar when stderr is not a terminal, and truth figures that do not mislead on a
stationary sequence (null drift %, small drift in metres)."""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import pytest

from robotd.tools.cli import main
from robotd.tools.replay import summary_line
from tests.support.paths import REPO

# the EuRoC micro cut stands still (ground truth moves ≤ 3.3 mm, README); a visual-only estimate
# that wandered more than this would be a regression, not noise
STATIONARY_DRIFT_BOUND_M = 0.05


def test_kitti_replay_prints_one_summary_line_with_the_truth_figures(
    shared_data, capsys: pytest.CaptureFixture[str]
) -> None:
    root = shared_data("kitti-seq1")
    assert main(["replay", f"kitti://{root}", "--max-frames", "6", "--json", "--log-level", "WARNING"]) == 0
    cap = capsys.readouterr()
    summary = json.loads(cap.out.strip().splitlines()[-1])  # stdout: the JSON only
    lines = cap.err.strip().splitlines()
    assert lines[0] == f"opening kitti://{root}..."
    assert "\r" not in cap.err, "no progress bar when stderr is not a terminal"
    done = [ln for ln in lines if ln.startswith("replayed ")]
    assert len(done) == 1
    m = re.fullmatch(r"replayed 6 frames in [\d.]+ s \(\d+ fps\): 0 lost; drift ([\d.]+) %, ATE ([\d.]+) m", done[0])
    assert m, done[0]
    assert float(m.group(1)) == pytest.approx(summary["truth_drift_pct"], abs=0.005)
    assert float(m.group(2)) == pytest.approx(summary["truth_ate_rmse_m"], abs=0.0005)
    assert summary["truth_drift_m"] is not None


def test_quiet_keeps_the_summary_line_but_not_the_opening_line(shared_data, capsys: pytest.CaptureFixture[str]) -> None:
    root = shared_data("kitti-seq1")
    assert main(["replay", f"kitti://{root}", "--max-frames", "3", "--quiet", "--log-level", "WARNING"]) == 0
    cap = capsys.readouterr()
    assert cap.out == ""
    lines = cap.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("replayed 3 frames in ")


def test_progress_bar_on_a_terminal_shows_n_of_total_and_landmarks(
    shared_data, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    root = shared_data("kitti-seq1")
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)  # capsys's stderr stands in for a terminal
    assert main(["replay", f"kitti://{root}?stop=4", "--log-level", "WARNING"]) == 0
    err = capsys.readouterr().err
    assert re.search(r"4/4 \[[^]]*frame/s, lm \d+\]", err), err


def test_stationary_euroc_has_no_drift_percentage(shared_data, capsys: pytest.CaptureFixture[str]) -> None:
    root = shared_data("euroc-v101-micro")
    assert main(["replay", f"euroc://{root}", "--json", "--quiet", "--log-level", "WARNING"]) == 0
    cap = capsys.readouterr()
    s = json.loads(cap.out.strip().splitlines()[-1])  # valid JSON: null, not NaN
    assert s["truth_path_length_m"] < 1.0
    assert s["truth_drift_pct"] is None and s["truth_similarity_scale"] is None
    assert 0.0 <= s["truth_drift_m"] < STATIONARY_DRIFT_BOUND_M
    assert s["truth_final_error_m"] < STATIONARY_DRIFT_BOUND_M
    # no segment of KITTI's, and no pose past the first 10 m to judge the positions-aligned NEES on
    assert s["truth_segment_count"] == 0 and s["truth_segment_drift_pct"] is None
    assert s["truth_alignment"] == "first-pose" and s["truth_aligned_nees_pos_frames"] == 0
    assert s["truth_aligned_nees_pos_mean"] is None and s["truth_aligned_nees_pos_in_band_frac"] is None
    assert re.search(r"drift [\d.]+ m \(path [\d.]+ m\), ATE [\d.]+ m$", cap.err.strip().splitlines()[-1])


def test_summary_line_without_truth() -> None:
    s = {"frames": 40, "wall_s": 2.0, "lost_frames": 3, "gt_odometry": False}
    assert summary_line(s) == "replayed 40 frames in 2.0 s (20 fps): 3 lost"


def test_summary_says_which_odometry_was_used(shared_data, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """replay.odometry = "dataset" on a KITTI folder without raw OXTS records: no odometry, said
    so; the oxts run itself is tests/drivers/test_kitti_oxts.py's."""
    root = shared_data("kitti-seq1")
    cfg = tmp_path / "c.toml"
    cfg.write_text('[replay]\nodometry = "dataset"\n')
    for extra in ([], ["--config", str(cfg)]):
        assert main(["replay", f"kitti://{root}?stop=3", "--json", "--quiet", "--log-level", "WARNING", *extra]) == 0
        s = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
        assert s["odometry"] == "none" and s["odometry_priors"] == 0
    line = summary_line({"frames": 40, "wall_s": 2.0, "lost_frames": 0, "gt_odometry": False, "odometry": "oxts"})
    assert line == "replayed 40 frames in 2.0 s (20 fps): 0 lost [odometry: oxts]"


def test_opening_line_names_a_recording_and_its_size(tmp_path: Path) -> None:
    from robotd.tools.replay import _opening_line

    f = tmp_path / "run.mcap"
    f.write_bytes(b"\0" * 3_000_000)
    assert _opening_line(str(f)) == f"opening {f} (3 MB)..."
    assert _opening_line(f"mcap://{f}") == f"opening {f} (3 MB)..."


def test_replay_rectifies_with_the_calibration_file_and_refuses_it_for_a_recording(
    shared_data, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """camera.calibration reaches the replayed source as it reaches the daemon's camera: a EuRoC
    folder (raw images) is rectified with the file's rig, the truth-derived odometry too; a
    recording, whose images are rectified already, refuses it: one error line naming the key."""
    import dataclasses

    import drivers
    from calib.camchain import save_calibration
    from drivers.dataset import EurocCamera
    from robotd.config import load_config
    from robotd.tools.replay import replay

    url = f"euroc://{shared_data('euroc-v101-micro')}"
    with EurocCamera(url) as cam:
        rig, b = cam.calibration, cam.rectified_model().baseline_m
    path = save_calibration(dataclasses.replace(rig, T=rig.T * 1.1), tmp_path / "rig.yaml")
    opened: list[object] = []
    real_open = drivers.open_camera

    def open_camera(u: str, **options: object) -> object:
        opened.append(cam := real_open(u, **options))
        return cam

    monkeypatch.setattr(drivers, "open_camera", open_camera)
    cfg = load_config(None, {"camera": {"calibration": str(path)}})
    for gt in (False, True):
        s = replay(cfg, url, max_frames=2, progress=False, gt_odometry=gt)
        assert s["frames"] == 2 and opened[-1].rectified_model().baseline_m == pytest.approx(1.1 * b, rel=1e-9)
    assert s["odometry"] != "none"
    toml = tmp_path / "c.toml"
    toml.write_text(f'[camera]\ncalibration = "{path}"\n')
    recording = REPO / "tests" / "support" / "data" / "format1_sim_160x100.mcap"
    assert main(["replay", str(recording), "--config", str(toml), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert any(
        f"camera.calibration: {path}: " in line and "a recording replays its rectified images" in line for line in err
    ), err


def test_a_trajectory_that_cannot_be_written_is_one_clear_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import errno

    import robotd.tools.replay as replay_mod

    # a folder given as the file: refused before the replay
    assert main(["replay", "sim://?duration=1", "--out", str(tmp_path)]) == 2
    assert "is a folder" in capsys.readouterr().err
    # the disk full when the run ends: one line naming the file and the cause, exit non-zero

    def full(*_a: object, **_k: object) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(replay_mod, "write_trajectory", full)
    out = tmp_path / "t.txt"
    assert main(["replay", "sim://?duration=0.4&fps=5&width=160&height=100", "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"writing the trajectory {out}: No space left on device" in err and "Traceback" not in err
