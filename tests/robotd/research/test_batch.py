"""Batch least-squares bound (robotd.research.batch): Jacobian, noiseless recovery, beats dead reckoning."""

from __future__ import annotations

import numpy as np
import pytest

from robotd.core.errors import InputError
from robotd.core.geometry import numerical_jacobian
from robotd.research.batch import build_problem, solve_batch, solve_sim
from robotd.research.evaluate import ate, poses_to_T
from robotd.research.landmark_sim import SimConfig, dead_reckoning, simulate

# analytic against central-difference Jacobians (h = 1e-6) of whitened residuals, relative to the
# largest entry; and the level below which a central difference counts as zero
JACOBIAN_RTOL = 1e-5
NONZERO_RTOL = 1e-9

QUIET = dict(
    odo_trans_frac=0.0, odo_heading_deg_per_m=0.0, odo_rot_frac=0.0, odo_trans_floor_m=1e-4, odo_rot_floor_deg=1e-3
)


def _problem_inputs(run):
    return [s.motion for s in run.steps[1:]], [s.observations for s in run.steps]


@pytest.mark.parametrize("dim", [2, 3])
def test_analytic_jacobian_matches_numerical(dim):
    run = simulate(SimConfig(dim=dim, path_length_m=3.0, landmark_density_per_m2=0.5), np.random.default_rng(1))
    motions, obs = _problem_inputs(run)
    pb = build_problem(motions, obs, dim)
    rng = np.random.default_rng(2)
    v = pb.v0 + 0.01 * rng.standard_normal(len(pb.v0))
    Jn = numerical_jacobian(pb.residuals, v, eps=1e-6)
    Ja = pb.jacobian(v).toarray()
    scale = np.abs(Jn).max()
    # relative to the largest entry: the residuals are whitened by their σ, so the entries and the
    # central-difference round-off (EPS·|r|/h) scale together (measured 3.3e-8 of the scale)
    assert np.abs(Ja - Jn).max() < JACOBIAN_RTOL * scale
    # the declared sparsity covers every non-zero (above the central-difference noise)
    assert np.all((np.abs(Jn) > NONZERO_RTOL * scale) <= (pb.sparsity.toarray() != 0))


@pytest.mark.parametrize("dim", [2, 3])
def test_noiseless_data_recovers_truth(dim):
    cfg = SimConfig(dim=dim, path_length_m=20.0, sigma_px=1e-4, **QUIET)
    run = simulate(cfg, np.random.default_rng(3))
    # start far from the truth so the solver has to work: perturbed dead reckoning
    init = dead_reckoning(run)
    init[1:, :2] += 0.05 * np.random.default_rng(4).standard_normal((len(init) - 1, 2))
    motions, obs = _problem_inputs(run)
    res = solve_batch(motions, obs, dim, init_poses=init)
    assert res.success
    assert np.abs(res.poses_W[:, :3] - run.poses_W[:, :3]).max() < 1e-3
    assert np.abs(res.landmarks_W - run.landmarks_W[res.landmark_ids]).max() < 1e-3


@pytest.mark.parametrize("dim", [2, 3])
def test_batch_beats_dead_reckoning_and_is_consistent(dim):
    # d_min = 10 px (≤ 3.25 m): at the default 5 px the triangulation bias of docs/math.md §3.3 (depth too far)
    # scales the whole solution by 2–4 %, which on a 60 m run is as large as the odometry drift
    cfg = SimConfig(dim=dim, path_length_m=60.0, trajectory="loop", d_min_px=10.0)
    run = simulate(cfg, np.random.default_rng(5))
    res = solve_sim(run)
    planar = dim == 2
    gt = poses_to_T(run.poses_W)
    e_batch = ate(poses_to_T(res.poses_W), gt, planar=planar)["ate_rmse_m"]
    e_dr = ate(poses_to_T(dead_reckoning(run)), gt, planar=planar)["ate_rmse_m"]
    assert e_batch < 0.5 * e_dr
    # whitened cost ≈ ½ (residuals − unknowns) when the weights are the true covariances
    dof = res.n_residuals - res.n_unknowns
    assert 0.8 < 2 * res.cost / dof < 1.2


def test_wrong_number_of_motions_is_an_error():
    run = simulate(SimConfig(dim=2, path_length_m=2.0), np.random.default_rng(0))
    motions, obs = _problem_inputs(run)
    with pytest.raises(InputError, match="motions"):
        solve_batch(motions[:-1], obs, 2)
