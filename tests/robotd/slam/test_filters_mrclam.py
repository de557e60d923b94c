"""The 2D filters on real data: MRCLAM dataset 1, robot 1 (wheel-odometry v, ω; landmark range/bearing).

The first 300 s are run through ``predict_velocity`` and ``update_range_bearing``; the map is aligned
to the surveyed landmarks with one rigid SE(2) transform (docs/math.md §11) and scored. The data run
in their own (forward-left-up) planar frame, which the 2D formulas allow (docs/math.md §1.2).

Data quirk found here: the surveyed positions of landmarks 11 and 17 are swapped with respect to the
barcode table (each estimate lies ~0.1 m from the other's surveyed position, ~6 m from its own), so
the map is scored with those two entries exchanged.
"""

from __future__ import annotations

import numpy as np
import pytest

from robotd.core.geometry import umeyama
from robotd.slam.factory import make_estimator
from robotd.slam.params import SlamParams

DURATION_S = 300.0
MAP_RMSE_BOUND_M = 0.4  # measured 0.16 m (EKF), 0.28 m (FastSLAM 2.0, 30 particles); σ_r 0.15 m, σ_β 0.05 rad


def _load(root):
    odo = np.loadtxt(root / "Robot1_Odometry.dat", comments="#")
    meas = np.loadtxt(root / "Robot1_Measurement.dat", comments="#")
    barcodes = np.loadtxt(root / "Barcodes.dat", comments="#").astype(int)
    gt = np.loadtxt(root / "Landmark_Groundtruth.dat", comments="#")
    subject = {int(b): int(s) for s, b in barcodes}
    subj = np.array([subject.get(int(b), 0) for b in meas[:, 1]])
    meas = meas[subj >= 6]  # subjects 1–5 are the other robots
    meas[:, 1] = subj[subj >= 6]
    t_end = odo[0, 0] + DURATION_S
    return odo[odo[:, 0] < t_end], meas[meas[:, 0] < t_end], gt


@pytest.mark.parametrize("filt", ["ekf", "fastslam2"])
def test_mrclam_map_matches_survey(shared_data, filt: str) -> None:
    odo, meas, gt = _load(shared_data("mrclam-dataset1-robot1"))
    params = SlamParams(
        filter=filt,
        dim=2,
        n_particles=30,
        prune_enabled=False,  # a monocular barcode camera: the stereo field-of-view test does not apply
        vel2d_alpha=(0.04, 0.001, 0.01, 0.04, 0.001, 0.001),  # commanded, not measured, velocities
    )
    est = make_estimator(params, np.random.default_rng(0))
    R_rb = np.diag([0.15**2, 0.05**2])
    j = 0
    for k in range(len(odo) - 1):
        t, v, w = odo[k]
        dt = odo[k + 1, 0] - t
        est.predict_velocity(v, w, dt)
        j0 = j
        while j < len(meas) and meas[j, 0] < t + dt:
            j += 1
        if j > j0:
            ids, first = np.unique(meas[j0:j, 1].astype(int), return_index=True)
            m = meas[j0:j][first]
            est.update_range_bearing(ids, m[:, 2], m[:, 3], R_rb)
    lm = est.landmarks()
    survey = {int(r[0]): r[1:3] for r in gt}
    survey[11], survey[17] = survey[17], survey[11]  # the data set's swap (module docstring)
    est_xy = lm.xyz_W_m[:, :2]
    ref_xy = np.array([survey[int(i)] for i in lm.ids])
    _, R, t = umeyama(est_xy, ref_xy, with_scale=False)
    err = np.linalg.norm(est_xy @ R.T + t - ref_xy, axis=1)
    assert lm.n >= 12
    assert float(np.sqrt(np.mean(err**2))) < MAP_RMSE_BOUND_M, err
