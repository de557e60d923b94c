"""The far-limit selection bias of stereo matches and its correction (robotd.core.stereo.gate_selection_shift)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from robotd.core.stereo import gate_selection_shift
from robotd.research.landmark_sim import SimConfig, simulate

D_MIN, D_MAX, SIGMA = 5.0, 100.0, 0.5 * np.sqrt(2.0)


@pytest.mark.parametrize("k", [-1.0, 0.0, 0.5, 1.0, 2.0])
def test_shift_is_the_bias_of_the_kept_measurements(k: float) -> None:
    # a point at true disparity d measured many times: the mean of what the gate keeps, minus d
    d = D_MIN + k * SIGMA
    rng = np.random.default_rng(3)
    m = d + SIGMA * rng.standard_normal(400_000)
    kept = m[(m >= D_MIN) & (m <= D_MAX)]
    bias = kept.mean() - d
    assert bias > 0.05 * SIGMA  # the gate makes far points look nearer
    assert gate_selection_shift(np.array([d]), D_MIN, D_MAX, SIGMA)[0] == pytest.approx(bias, abs=0.01 * SIGMA)


def test_shift_vanishes_inside_and_mirrors_at_the_near_limit() -> None:
    s = gate_selection_shift(np.array([D_MIN + 6 * SIGMA, 50.0, D_MAX - 6 * SIGMA]), D_MIN, D_MAX, SIGMA)
    assert np.all(np.abs(s) < 1e-6)
    near = gate_selection_shift(np.array([D_MAX]), D_MIN, D_MAX, SIGMA)[0]
    far = gate_selection_shift(np.array([D_MIN]), D_MIN, D_MAX, SIGMA)[0]
    assert near == pytest.approx(-far) and far == pytest.approx(SIGMA * np.sqrt(2.0 / np.pi))
    assert gate_selection_shift(np.zeros(0), D_MIN, D_MAX, SIGMA).shape == (0,)


def _first_sighting_depth_error(debias: bool) -> float:
    """Mean relative depth error of landmarks the first time the simulated front end keeps them,
    for those first seen beyond 5 m (the gate's far limit is 6.5 m)."""
    cfg = SimConfig(dim=2, trajectory="loop", path_length_m=40.0, landmark_density_per_m2=0.5)
    cfg = dataclasses.replace(cfg, debias_limits=debias)
    run = simulate(cfg, np.random.default_rng(1))
    rel = []
    for k, step in enumerate(run.steps):
        obs = step.observations
        t = run.poses_W[k]
        c, s = np.cos(t[5]), np.sin(t[5])
        d = run.landmarks_W[obs.ids, :2] - t[:2]
        depth = c * d[:, 0] + s * d[:, 1]
        sel = obs.is_new & (depth > 5.0)
        rel.append((obs.xyz_R_m[sel, 0] - depth[sel]) / depth[sel])
    return float(np.mean(np.concatenate(rel)))


def test_first_sightings_near_the_far_limit_are_unbiased_once_corrected() -> None:
    before, after = _first_sighting_depth_error(False), _first_sighting_depth_error(True)
    assert before < -0.05  # 7 % too near: seen first when the noise made them look nearer
    assert abs(after) < 0.03
