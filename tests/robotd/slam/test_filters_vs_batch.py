"""Filters against the batch least-squares bound on the same simulated data (issue 4)."""

from __future__ import annotations

import numpy as np
from scipy.stats import chi2

from robotd.research.evaluate import anees_band
from robotd.research.experiments import make_scenario, run_filter
from robotd.research.landmark_sim import SimConfig

# FastSLAM 2.0 against the bound is measured in docs/experiments/report.md (robotd experiments);
# it does not yet meet issue 4's "within 1.5× with 50 particles" on every seed (see the issue note).


def test_ekf_matches_batch_on_a_small_map() -> None:
    small = SimConfig(dim=2, trajectory="loop", path_length_m=30.0, landmark_density_per_m2=0.5)
    for seed in (1, 2):
        sc = make_scenario(small, seed)
        r = run_filter(sc.run, "ekf", seed, batch_ate=sc.batch_ate)
        assert r.ate_rmse_m <= 1.5 * sc.batch_ate + 0.01, (r.ate_rmse_m, sc.batch_ate)


def test_ekf_nees_in_band_when_the_noise_matches_its_model() -> None:
    """docs/math.md §11: with measurement noise the filter's model describes exactly (isotropic Gaussian in the
    robot frame, correct correspondences), EKF SLAM is consistent: the ANEES of R runs lies in the
    two-sided 95 % band, and ~95 % of single-step NEES values in the single-run interval. (With the
    stereo noise of §12 it is not: the triangulated depth is skewed and its first-order covariance
    is evaluated at the noisy pixels — docs/experiments/consistency.md.)"""
    cfg = SimConfig(dim=2, trajectory="loop", path_length_m=12.0, landmark_density_per_m2=0.5, noise_model="isotropic")
    seeds = range(6)
    eps = []
    for seed in seeds:
        sc = make_scenario(cfg, seed)
        r = run_filter(sc.run, "ekf", seed)
        eps.append(r.nees)
    E = np.array(eps)  # (R, K - 1)
    lo, hi = anees_band(3, len(seeds))
    assert lo <= E.mean() <= hi, (E.mean(), lo, hi)
    inside = np.mean((E > chi2.ppf(0.025, 3)) & (E < chi2.ppf(0.975, 3)))
    assert inside >= 0.88, inside


def test_fastslam2_50_particles_near_the_batch_bound_on_the_standard_loop() -> None:
    """Issue 4: FastSLAM 2.0 with 50 particles against the batch bound on §12's world (stereo noise,
    1 landmark/m², 20–50 visible per frame), a 40 m loop. Measured over 8 seeds (docs/slam.md):
    mean 1.42× with the sequential weights (1.55× with §10's product at the prior), worst 1.74×;
    asserted here on 4 seeds: mean within 1.5×, none beyond 2×."""
    cfg = SimConfig(dim=2, trajectory="loop", path_length_m=40.0, landmark_density_per_m2=1.0)
    ratios = []
    for seed in range(4):
        sc = make_scenario(cfg, seed)
        ratios.append(run_filter(sc.run, "fastslam2", seed, n_particles=50, batch_ate=sc.batch_ate).ate_ratio)
    assert np.mean(ratios) <= 1.5, ratios
    assert max(ratios) <= 2.0, ratios


def test_fastslam2_nees_in_band_on_a_short_loop_with_enough_particles() -> None:
    """FastSLAM 2.0 (sequential weights, Rao-Blackwellised estimate) is consistent on a short loop
    with model-matched noise and 500 particles. With 50 particles, or with §10's product-at-the-prior
    weights, it is not (ANEES 10.8 and 14.9 in docs/experiments/consistency.md): over-confidence
    from the particles' shared ancestry (Bailey et al. 2006)."""
    cfg = SimConfig(dim=2, trajectory="loop", path_length_m=12.0, landmark_density_per_m2=0.5, noise_model="isotropic")
    seeds = range(6)
    E = np.array([run_filter(make_scenario(cfg, s).run, "fastslam2", s, n_particles=500).nees for s in seeds])
    lo, hi = anees_band(3, len(seeds))
    assert lo <= E.mean() <= hi, (E.mean(), lo, hi)
