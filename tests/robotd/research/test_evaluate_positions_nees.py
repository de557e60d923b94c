"""The position NEES after aligning by positions over the first M metres
(robotd.research.evaluate.positions_aligned_nees, ``robotd eval --align-positions``, issue 26 item 4)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robotd.core.geometry import rot_z, se3, so3_exp
from robotd.research.evaluate import (
    align_by_positions,
    cumulative_path,
    nees_band_3,
    position_nees,
    positions_aligned_nees,
)

M = 10.0
# the estimate's own world: a rotation and an offset the alignment has to find
H = se3(so3_exp(np.array([0.2, -0.4, 1.3])), np.array([3.0, -7.0, 0.5]))


def _curve(n: int = 600, step_m: float = 0.5) -> np.ndarray:
    """(n, 4, 4) a 300 m drive circling to the left at a radius of 15 m (tight enough that its first
    10 m are not taken for a line), with a gentle climb and dip."""
    s = np.arange(n) * step_m
    th = s / 15.0
    xyz = np.column_stack([15.0 * np.sin(th), 15.0 * (1.0 - np.cos(th)), 2.0 * np.sin(s / 30.0)])
    return se3(rot_z(th), xyz)


def _consistent_run(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(estimate, truth, reported covariance): the estimate in its own world H, its position error
    drawn from N(0, Σ_i) with Σ_i the covariance it reports (in its world). Σ is anisotropic and
    turns with the vehicle; 1 mm over the first M metres (so the fit adds nothing measurable), then
    5 cm growing by 2 mm per metre, as a drift does."""
    rng = np.random.default_rng(seed)
    gt = _curve()
    s = cumulative_path(gt[:, :3, 3])
    sigma = np.where(s <= M, 0.001, 0.05 + 0.002 * s)
    S = np.einsum("nij,j,nkj->nik", gt[:, :3, :3], np.array([1.0, 0.5, 0.3]) ** 2, gt[:, :3, :3])
    S = S * (sigma**2)[:, None, None]
    e = np.einsum("nij,nj->ni", np.linalg.cholesky(S), rng.standard_normal((len(gt), 3)))
    noisy = gt.copy()
    noisy[:, :3, 3] += e
    est = H @ noisy
    cov = np.zeros((len(gt), 6, 6))
    cov[:, :3, :3] = H[:3, :3] @ S @ H[:3, :3].T
    cov[:, 3:, 3:] = np.eye(3) * 1e-4
    return est, gt, cov


def test_errors_drawn_from_the_reported_covariance_put_95_percent_in_the_band() -> None:
    est, gt, cov = _consistent_run(seed=7)
    eps, m = positions_aligned_nees(est, gt, cov, M)
    assert m["alignment"] == "positions" and m["align_positions_m"] == M
    fit = cumulative_path(gt[:, :3, 3]) <= M
    assert m["aligned_fit_frames"] == int(fit.sum()) == 20  # steps of 0.501 m with the climb: 10.02 m at the 21st pose
    assert m["aligned_nees_pos_frames"] == len(gt) - 20
    assert np.all(np.isnan(eps[fit])) and np.all(np.isfinite(eps[~fit]))
    # 580 draws of χ²(3): in band 0.95 ± 0.009 (1 σ), mean 3 ± 0.10
    assert 0.92 <= m["aligned_nees_pos_in_band_frac"] <= 0.98, m
    assert 2.7 <= m["aligned_nees_pos_mean"] <= 3.3, m
    lo, hi = nees_band_3()
    assert m["aligned_nees_pos_in_band_frac"] == pytest.approx(np.mean((eps[~fit] >= lo) & (eps[~fit] <= hi)))


def test_a_covariance_100_times_too_small_puts_almost_nothing_in_the_band() -> None:
    est, gt, cov = _consistent_run(seed=7)
    _, m = positions_aligned_nees(est, gt, cov / 100.0, M)
    # ε is 100 × χ²(3): inside only when χ²(3) ≤ 0.0935, 0.7 % of draws
    assert m["aligned_nees_pos_in_band_frac"] < 0.03, m
    assert m["aligned_nees_pos_mean"] > 200.0


def test_an_orientation_error_at_the_start_spoils_the_first_pose_nees_but_not_this_one() -> None:
    """The issue's reason for it: aligned by the first pose, a 0.5° heading error of the start swings
    the whole estimate; aligned by positions it does not matter."""
    est, gt, cov = _consistent_run(seed=8)
    est[0, :3, :3] = est[0, :3, :3] @ rot_z(math.radians(0.5))
    _, m = positions_aligned_nees(est, gt, cov, M)
    assert 0.92 <= m["aligned_nees_pos_in_band_frac"] <= 0.98, m
    first = position_nees(est, gt, cov)
    assert np.nanmean(first) > 10 * m["aligned_nees_pos_mean"]


def _straight_then_curve() -> np.ndarray:
    """(n, 4, 4) 15 m straight along x, then a 90° left curve of radius 20 m: the first 10 m are
    collinear, and the rotation about them decides where the curve goes."""
    straight = np.arange(0.0, 15.0, 0.5)
    th = np.linspace(0.0, math.pi / 2, 40)[1:]
    xy = np.vstack(
        [np.column_stack([straight, 0 * straight]), np.column_stack([15.0 + 20 * np.sin(th), 20 * (1 - np.cos(th))])]
    )
    yaw = np.concatenate([np.zeros(len(straight)), th])
    return se3(rot_z(yaw), np.column_stack([xy, np.zeros(len(xy))]))


def test_a_straight_start_takes_the_rotation_about_it_from_the_first_pose() -> None:
    gt = _straight_then_curve()
    est = H @ gt  # exact, in its own world: the right alignment leaves no error at all
    al = align_by_positions(est, gt, M)
    assert al.kind == "positions+first-pose-roll"
    assert "lie on a line" in al.note and "first pose's orientation" in al.note
    np.testing.assert_allclose(al.T, np.linalg.inv(H), atol=1e-9)
    cov = np.tile(np.eye(6) * 1e-4, (len(gt), 1, 1))
    eps, m = positions_aligned_nees(est, gt, cov, M)
    assert m["alignment"] == "positions+first-pose-roll" and m["aligned_nees_pos_frames"] == len(gt) - 21
    assert np.nanmax(eps) < 1e-9  # a wrong roll puts the curve metres out of its plane
    # the same start with the first 10 m not quite straight (a 1 m bow): a plain fit of positions
    bowed = gt.copy()
    bowed[:21, 1, 3] = np.sin(np.linspace(0, math.pi, 21))
    assert align_by_positions(H @ bowed, bowed, M).kind == "positions"


def test_a_stationary_start_falls_back_to_the_first_pose_and_a_short_path_leaves_nothing_to_judge() -> None:
    rng = np.random.default_rng(3)
    n = 50
    gt = se3(np.broadcast_to(np.eye(3), (n, 3, 3)), rng.normal(0.0, 0.002, (n, 3)))
    est = H @ gt
    cov = np.tile(np.eye(6) * 1e-4, (n, 1, 1))
    eps, m = positions_aligned_nees(est, gt, cov, M)
    assert m["alignment"] == "first-pose"
    note = m["alignment_note"]
    assert "stay within 0.1 m (RMS about their mean): positions fix no rotation; aligned by the first pose" in note
    path_m = float(np.sum(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1)))  # the jitter adds up to 0.25 m
    assert note.endswith(f"the true path ({path_m:.3f} m) does not go past 10 m: no pose to judge")
    assert m["aligned_nees_pos_frames"] == 0 and math.isnan(m["aligned_nees_pos_mean"])
    assert np.all(np.isnan(eps))


def test_no_pose_within_m_but_the_first_aligns_by_the_first_pose() -> None:
    gt = _curve(n=40, step_m=2.0)
    est = H @ gt
    cov = np.tile(np.eye(6) * 1e-4, (len(gt), 1, 1))
    _, m = positions_aligned_nees(est, gt, cov, 1.0)
    assert m["alignment"] == "first-pose" and m["aligned_fit_frames"] == 1
    assert m["alignment_note"].startswith("no pose but the first within the first 1 m")
    assert m["aligned_nees_pos_frames"] == len(gt) - 1
    assert m["aligned_nees_pos_mean"] < 1e-9  # exact after the first-pose alignment
