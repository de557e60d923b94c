"""Alignment where positions cannot fix the rotation: a straight drive, a stationary vehicle."""

from __future__ import annotations

import numpy as np

from robotd.core.geometry import euler_to_R, se3
from robotd.research.evaluate import ate


def _traj(xyz: np.ndarray, rpy: np.ndarray) -> np.ndarray:
    return np.stack([se3(euler_to_R(r), p) for p, r in zip(xyz, rpy)])


def test_straight_drive_heading_error_is_the_true_one(rng: np.random.Generator) -> None:
    n = 50
    xyz = np.c_[np.linspace(0, 60, n), np.zeros(n), np.zeros(n)]
    gt = _traj(xyz, np.zeros((n, 3)))
    # estimate: small position noise and a constant 0.5° yaw error in its orientation
    est = _traj(xyz + rng.normal(0, 0.01, (n, 3)), np.tile([0.0, 0.0, np.radians(0.5)], (n, 1)))
    m = ate(est, gt)
    assert m["ate_rmse_m"] < 0.03
    assert abs(m["heading_rmse_deg"] - 0.5) < 0.1, m["heading_rmse_deg"]


def test_stationary_vehicle_heading_error_is_small(rng: np.random.Generator) -> None:
    n = 60
    gt = _traj(rng.normal(0, 0.001, (n, 3)), np.zeros((n, 3)))
    est = _traj(rng.normal(0, 0.002, (n, 3)), rng.normal(0, np.radians(0.05), (n, 3)))
    m = ate(est, gt)
    assert m["heading_rmse_deg"] < 0.5 and m["ate_rmse_m"] < 0.01


def test_straight_drive_roll_about_the_path_comes_from_orientations(rng: np.random.Generator) -> None:
    # positions along x cannot tell a rotation about x; the orientations can (0.2° roll error)
    n = 50
    xyz = np.c_[np.linspace(0, 60, n), np.zeros(n), np.zeros(n)]
    gt = _traj(xyz, np.zeros((n, 3)))
    est = _traj(xyz + rng.normal(0, 0.01, (n, 3)), np.tile([np.radians(0.2), 0.0, 0.0], (n, 1)))
    m = ate(est, gt)
    assert m["ate_rmse_m"] < 0.03 and m["heading_rmse_deg"] < 0.25
