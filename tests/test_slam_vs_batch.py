"""Filters against the batch least-squares bound on the same simulated data (issue 4)."""

from __future__ import annotations

from robotd.experiments import make_scenario, run_filter
from robotd.sim import SimConfig

# FastSLAM 2.0 against the bound is measured in docs/experiments/report.md (robotd experiments);
# it does not yet meet issue 4's "within 1.5× with 50 particles" on every seed (see the issue note).


def test_ekf_matches_batch_on_a_small_map() -> None:
    small = SimConfig(dim=2, trajectory="loop", path_length_m=30.0, landmark_density_per_m2=0.5)
    for seed in (1, 2):
        sc = make_scenario(small, seed)
        r = run_filter(sc.run, "ekf", seed, batch_ate=sc.batch_ate)
        assert r.ate_rmse_m <= 1.5 * sc.batch_ate + 0.01, (r.ate_rmse_m, sc.batch_ate)
