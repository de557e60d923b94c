"""FastSLAM's frame-level χ² gate: it keeps wrong correspondences out of every particle's map."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

import robotd.research.experiments as X
from robotd.research.landmark_sim import SimConfig, inject_mismatches, simulate

CFG = SimConfig(dim=2, trajectory="loop", path_length_m=30.0, landmark_density_per_m2=0.5)


def _ate(run, gate: bool, seed: int) -> float:
    orig = X.make_estimator
    X.make_estimator = lambda p, rng, *a, **k: orig(replace(p, fastslam_gate=gate), rng, *a, **k)
    try:
        return X.run_filter(run, "fastslam2", seed, n_particles=50).ate_rmse_m
    finally:
        X.make_estimator = orig


def test_gate_keeps_fastslam2_on_track_at_5_percent_mismatches() -> None:
    with_gate, without = [], []
    for seed in (0, 1):
        clean = simulate(CFG, np.random.default_rng(seed))
        bad = inject_mismatches(clean, 0.05, np.random.default_rng(seed + 100))
        with_gate.append(_ate(bad, True, seed))
        without.append(_ate(bad, False, seed))
        # on clean data the gate costs nothing
        assert _ate(clean, True, seed) < 1.5 * _ate(clean, False, seed) + 0.02
    assert np.mean(with_gate) < 0.5 * np.mean(without), (with_gate, without)
