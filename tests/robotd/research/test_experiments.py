"""The experiment runner (robotd.research.experiments): the quick campaign writes a complete report."""

from __future__ import annotations

import json
import math
import re
import sys

import numpy as np
import pytest

from robotd.research.experiments import ExperimentPlan, campaign_runs, make_scenario, run_experiments, run_filter
from robotd.research.landmark_sim import SimConfig


@pytest.mark.timeout(120)
def test_quick_run_writes_report_with_all_sections(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)  # capsys's stderr stands in for a terminal
    path = run_experiments(tmp_path, quick=True)
    text = path.read_text()
    # the progress bar counts every filter run of results.json, plus the two MRCLAM runs when present
    rows = json.loads((tmp_path / "results.json").read_text())
    with_mrclam = "Skipped: MRCLAM" not in text
    total = campaign_runs(ExperimentPlan.quick(1), with_mrclam)
    assert total == len(rows) + (2 if with_mrclam else 0)
    assert f"{total}/{total} [" in capsys.readouterr().err
    for section in (
        "## (a) 2D SLAM",
        "## (b) Number of particles",
        "## (c) Landmark identification under mismatches",
        "## (d) 3D SLAM",
        "## (e) Real odometry: MRCLAM",
        "## Findings against the thesis's claims",
    ):
        assert section in text
    for claim in ("EKF SLAM very sensitive", "FastSLAM 1.0 unable to cope", "FastSLAM 2.0 a good compromise"):
        assert re.search(claim + r".*(confirmed|not confirmed)", text)
    # every image the report links exists and is a PNG
    for name in re.findall(r"\]\(([^)]+\.png)\)", text):
        assert (tmp_path / name).read_bytes()[:4] == b"\x89PNG"
    assert "nan ± nan" not in text


def test_filter_run_metrics_are_sane():
    sc = make_scenario(SimConfig(dim=2, path_length_m=10.0, landmark_density_per_m2=0.5), seed=3)
    r = run_filter(sc.run, "ekf", seed=3, batch_ate=sc.batch_ate)
    assert 0 < r.ate_rmse_m < 0.5
    assert r.ate_ratio == pytest.approx(r.ate_rmse_m / sc.batch_ate)
    assert math.isfinite(r.anees) and r.anees > 0
    assert r.poses.shape == (len(sc.run.steps), 6)
    assert not r.diverged
    assert np.all(r.step_ms >= 0)
