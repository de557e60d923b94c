"""MRCLAM loader (robotd.research.datasets.mrclam) and a short FastSLAM 2.0 run on its real odometry."""

from __future__ import annotations

import numpy as np
import pytest

from robotd.core.errors import DatasetError
from robotd.research.datasets.mrclam import MRCLAM1_SWAP_11_17, load_mrclam
from robotd.research.experiments import run_mrclam


def test_loader_parses_and_maps_barcodes(shared_data):
    d = load_mrclam(shared_data("mrclam-dataset1-robot1"))
    # README: 97 890 odometry rows over ≈ 1 490.5 s; 4 771 landmark rows; the rest see robots
    assert len(d.odo_t_s) == 97890
    assert d.odo_t_s[-1] == pytest.approx(1490.5, abs=0.5)
    assert len(d.meas_t_s) == 4771
    assert d.n_robot_observations == 5723 - 4771
    assert set(np.unique(d.meas_subject)) <= set(range(6, 21))
    assert np.all(np.diff(d.meas_t_s) >= 0)
    assert len(d.landmark_subject) == 15
    assert d.landmark_truth()[6] == pytest.approx([5.70928255, 4.96404466])
    # relabelling swaps exactly the two subjects
    s = load_mrclam(shared_data("mrclam-dataset1-robot1"), relabel=MRCLAM1_SWAP_11_17)
    assert np.sum(s.meas_subject == 11) == np.sum(d.meas_subject == 17)
    assert np.array_equal(s.meas_range_m, d.meas_range_m)


def test_missing_folder_and_bad_file(tmp_path):
    with pytest.raises(DatasetError, match="no such folder"):
        load_mrclam(tmp_path / "nope")
    (tmp_path / "Robot1_Odometry.dat").write_text("# h\n1 2\n")
    with pytest.raises(DatasetError, match="Robot1_Odometry.dat"):
        load_mrclam(tmp_path)


def test_fastslam2_on_first_100_s_has_bounded_map_error(shared_data, tmp_path):
    r = run_mrclam(shared_data("mrclam-dataset1-robot1"), tmp_path, n_particles=30, seed=0, duration_s=100.0)
    assert len(r.per_landmark_m) >= 8
    # surveyed landmarks to ≈ 0.1 m after a similarity alignment (measured 0.09 m with 50 particles)
    assert r.map_rmse_m < 0.3
    assert 0.9 < r.scale < 1.1
    assert r.png is not None and r.png.read_bytes()[:4] == b"\x89PNG"
