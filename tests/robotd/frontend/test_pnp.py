"""Stereo PnP (robotd/frontend/pnp.py): Jacobians, recovery of a known motion, robustness."""

from __future__ import annotations

import numpy as np
import pytest

from robotd.core.errors import ConfigError
from robotd.core.geometry import numerical_jacobian, so3_exp, so3_log
from robotd.core.stereo import RectifiedStereo, triangulate
from robotd.frontend.pnp import (
    MotionPrior,
    PnpParams,
    motion_prior,
    offset_sensitivity,
    project_stereo,
    projection_jacobian,
    refine,
    stereo_pnp,
    two_view,
)
from tests.support import reference_pnp
from tests.support.reference_pnp import residuals_jacobian

RIG = RectifiedStereo(f_px=700.0, px=620.0, py=180.0, baseline_m=0.54, width=1240, height=370)


def _scene(rng: np.random.Generator, n: int) -> np.ndarray:
    """Static points in R(t−1) that stay in view: X 4–40 m, spread over the image."""
    X = rng.uniform(4.0, 40.0, n)
    u = rng.uniform(50, RIG.width - 50, n)
    v = rng.uniform(40, RIG.height - 40, n)
    return np.c_[X, (u - RIG.px) * X / RIG.f_px, (v - RIG.py) * X / RIG.f_px]


def _observe(P: np.ndarray, R: np.ndarray, t: np.ndarray, rng: np.random.Generator, sigma: float) -> tuple:
    """Pixels of the points P (R(t−1)) in both frames with noise, and their triangulations."""
    zp = project_stereo(P, RIG) + rng.normal(0, sigma, P.shape)
    z = project_stereo((P - t) @ R, RIG) + rng.normal(0, sigma, P.shape)
    tri = lambda w: triangulate(w[:, 0], w[:, 1], w[:, 2], RIG.f_px, RIG.px, RIG.py, RIG.baseline_m)  # noqa: E731
    return tri(zp), z, tri(z), zp


def test_projection_jacobian_matches_central_differences():
    rng = np.random.default_rng(0)
    q = _scene(rng, 5)
    J = projection_jacobian(q, RIG)
    for k in range(5):
        Jn = numerical_jacobian(lambda x: project_stereo(x[None], RIG)[0], q[k])
        np.testing.assert_allclose(J[k], Jn, rtol=1e-6, atol=1e-6)


def test_residual_jacobian_matches_central_differences_of_the_perturbation():
    rng = np.random.default_rng(1)
    P = _scene(rng, 4)
    R, t = so3_exp(np.array([0.01, -0.05, 0.02])), np.array([1.0, 0.1, -0.05])
    Pp, z, Q, zp = _observe(P, R, t, rng, 0.3)
    _, J = residuals_jacobian(R, t, Pp, z, Q, zp, RIG)

    def res(d: np.ndarray) -> np.ndarray:
        R2, t2 = R @ so3_exp(d[3:]), t + R @ d[:3]
        r, _ = residuals_jacobian(R2, t2, Pp, z, Q, zp, RIG)
        return r.ravel()

    Jn = numerical_jacobian(res, np.zeros(6))
    # r = z − ẑ(δ): the Jacobian of the residual is −∂ẑ/∂δ
    np.testing.assert_allclose(-J.reshape(-1, 6), Jn, rtol=1e-5, atol=1e-4)


@pytest.mark.parametrize("seed", range(5))
def test_recovers_a_known_motion_within_the_noise(seed):
    rng = np.random.default_rng(seed)
    P = _scene(rng, 200)
    R = so3_exp(rng.normal(0, 0.03, 3))
    t = np.array([1.0, 0.0, 0.0]) + rng.normal(0, 0.1, 3)
    Pp, z, Q, zp = _observe(P, R, t, rng, 0.5)
    res = stereo_pnp(Pp, z, Q, zp, RIG, PnpParams(), rng)
    assert res is not None
    assert np.linalg.norm(res.t - t) < 0.02  # 2 cm on a 1 m step
    assert np.degrees(np.linalg.norm(so3_log(R.T @ res.R))) < 0.05
    # noise in both frames: a 2 px gate on the larger direction's error keeps most pairs
    assert res.inliers.mean() > 0.5


def test_covariance_matches_the_real_error():
    """Mean NEES over 20 motions is 6 (dof) for an honest covariance: within a factor of two,
    with the calibration factor PnpParams.cov_scale; the uncalibrated first-order one is ~3×
    optimistic."""
    nees = []
    for seed in range(20):
        rng = np.random.default_rng(100 + seed)
        P = _scene(rng, 200)
        R, t = so3_exp(rng.normal(0, 0.03, 3)), np.array([1.0, 0.0, 0.0]) + rng.normal(0, 0.1, 3)
        res = stereo_pnp(*_observe(P, R, t, rng, 0.5), RIG, PnpParams(), rng)
        assert res is not None
        e = np.r_[res.t - t, so3_log(R.T @ res.R)]
        nees.append(float(e @ np.linalg.solve(res.cov, e)))
    assert 6.0 / 2.0 < np.mean(nees) < 6.0 * 2.0, np.round(nees, 1)


def test_outliers_and_a_moving_vehicle_lose_the_consensus_to_the_static_background():
    """A vehicle filling one part of the image, carrying more features than the background and
    moving with the rover (appears static), must not win: the consensus counts image cells."""
    rng = np.random.default_rng(7)
    R, t = so3_exp(np.array([0.0, 0.0, 0.02])), np.array([1.0, 0.05, 0.0])
    bg = _scene(rng, 120)
    # the vehicle: 200 points in a compact box ahead (8–10 m, centre of the image), moving with us
    veh = np.c_[rng.uniform(8, 10, 200), rng.uniform(-1.0, 1.0, 200), rng.uniform(-0.8, 0.5, 200)]
    Pb, zb, Qb, zpb = _observe(bg, R, t, rng, 0.5)
    # its points keep their pixels (relative motion zero): current = previous observation + noise
    zpv = project_stereo(veh, RIG) + rng.normal(0, 0.5, veh.shape)
    zv = project_stereo(veh, RIG) + rng.normal(0, 0.5, veh.shape)
    tri = lambda w: triangulate(w[:, 0], w[:, 1], w[:, 2], RIG.f_px, RIG.px, RIG.py, RIG.baseline_m)  # noqa: E731
    # and gross outliers: random pixels
    n_out = 40
    Po = _scene(rng, n_out)
    zo = np.c_[rng.uniform(0, RIG.width, n_out), np.zeros(n_out), rng.uniform(0, RIG.height, n_out)]
    zo[:, 1] = zo[:, 0] - rng.uniform(5, 60, n_out)
    P = np.r_[Pb, tri(zpv), Po]
    z = np.r_[zb, zv, zo]
    Q = np.r_[Qb, tri(zv), tri(zo)]
    zp = np.r_[zpb, zpv, project_stereo(Po, RIG)]
    res = stereo_pnp(P, z, Q, zp, RIG, PnpParams(), rng)
    assert res is not None
    assert np.linalg.norm(res.t - t) < 0.05
    assert res.inliers[: len(bg)].mean() > 0.5 and res.inliers[len(bg) :].mean() < 0.05


def test_too_few_pairs_give_no_motion_and_bad_settings_are_refused():
    rng = np.random.default_rng(3)
    P = _scene(rng, 5)
    Pp, z, Q, zp = _observe(P, np.eye(3), np.array([1.0, 0, 0]), rng, 0.5)
    assert stereo_pnp(Pp, z, Q, zp, RIG, PnpParams(), rng) is None
    with pytest.raises(ConfigError, match="inlier_px"):
        PnpParams(inlier_px=0.0)


def _van_scene(rng: np.random.Generator, van_motion: np.ndarray):
    """A rover moving 4 cm forward; 60 background points far and spread over the image, and a
    van of 300 points filling the left two thirds of the view 3 m ahead, moving sideways by
    ``van_motion`` between the frames (in R(t−1))."""
    R, t = so3_exp(np.array([0.0, 0.0, 0.004])), np.array([0.04, 0.0, 0.0])
    bg = _scene(rng, 60)
    van = np.c_[rng.uniform(3.0, 3.3, 300), rng.uniform(-2.6, 0.6, 300), rng.uniform(-0.6, 0.6, 300)]
    Pb, zb, Qb, zpb = _observe(bg, R, t, rng, 0.3)
    Pv, zv, Qv, zpv = _observe(van, R, t - van_motion, rng, 0.3)  # the van moved with it: t − v
    return R, t, np.r_[Pb, Pv], np.r_[zb, zv], np.r_[Qb, Qv], np.r_[zpb, zpv], len(bg)


def test_a_larger_vehicle_consensus_loses_to_the_background_the_prediction_allows():
    """Without a prediction the van (more cells, more points) wins; with the constant-velocity
    prediction within the acceleration bounds, the background does."""
    rng = np.random.default_rng(11)
    R, t, P, z, Q, zp, nb = _van_scene(rng, np.array([0.0, 0.08, 0.0]))
    free = stereo_pnp(P, z, Q, zp, RIG, PnpParams(), np.random.default_rng(1))
    assert free is not None and np.linalg.norm(free.t - t) > 0.05  # the van's motion
    prior = motion_prior(R, t, 1 / 30, 1 / 30, PnpParams())
    res = stereo_pnp(P, z, Q, zp, RIG, PnpParams(), np.random.default_rng(1), prior)
    assert res is not None and np.linalg.norm(res.t - t) < 0.01
    assert res.inliers[:nb].mean() > 0.7 and res.inliers[nb:].mean() < 0.05


def test_the_prediction_never_vetoes_a_strong_consensus_but_binding_odometry_does():
    """A prediction that is wrong (the rover braked harder than it says) with no plausible
    consensus: the images' strong consensus is taken. Odometry is binding: nothing is taken."""
    rng = np.random.default_rng(5)
    R, t = so3_exp(np.array([0.0, 0.0, 0.01])), np.array([0.5, 0.0, 0.0])
    Pp, z, Q, zp = _observe(_scene(rng, 150), R, t, rng, 0.5)
    wrong = motion_prior(np.eye(3), np.array([1.2, 0.0, 0.0]), 0.1, 0.1, PnpParams())
    assert not wrong.plausible(R[None], t[None])[0]
    res = stereo_pnp(Pp, z, Q, zp, RIG, PnpParams(), rng, wrong)
    assert res is not None and np.linalg.norm(res.t - t) < 0.05
    binding = MotionPrior(wrong.R, wrong.t, wrong.tol_t_m, wrong.tol_rot_rad, binding=True)
    assert stereo_pnp(Pp, z, Q, zp, RIG, PnpParams(), rng, binding) is None


def test_a_weak_jump_the_vehicle_cannot_make_is_not_taken():
    """Ten matches whose consensus asks for a 0.3 m jump at 30 fps: no motion (the
    constant-velocity prediction bridges); without a prediction the same pairs give one."""
    rng = np.random.default_rng(2)
    R, t = np.eye(3), np.array([0.34, 0.0, 0.0])
    Pp, z, Q, zp = _observe(_scene(rng, 10), R, t, rng, 0.3)
    assert stereo_pnp(Pp, z, Q, zp, RIG, PnpParams(), rng) is not None
    prior = motion_prior(np.eye(3), np.array([0.04, 0.0, 0.0]), 1 / 30, 1 / 30, PnpParams())
    assert stereo_pnp(Pp, z, Q, zp, RIG, PnpParams(), rng, prior) is None


@pytest.mark.parametrize("seed", range(6))
def test_the_compiled_refinement_is_its_numpy_twin(seed: int) -> None:
    # robotd.frontend._pnp_kernels against tests/support/reference_pnp.py: the same passes, the
    # same inliers, the same pose and information to rounding, with outliers and points behind
    from robotd.frontend import _pnp_kernels as k
    from robotd.frontend.pnp import _sq_errors, refine

    rng = np.random.default_rng(seed)
    P = _scene(rng, 120)
    R, t = so3_exp(rng.normal(0, 0.03, 3)), np.array([1.0, 0.05, -0.02]) * rng.uniform(0.2, 1.5)
    Pp, z, Q, zp = _observe(P, R, t, rng, 0.5)
    bad = rng.choice(120, 25, replace=False)
    z[bad] += rng.normal(0, 30.0, (25, 3))  # mismatches
    Q[:3, 0] = -1.0  # behind the rig: NaN residuals, never inliers
    R0, t0 = R @ so3_exp(rng.normal(0, 0.002, 3)), t + rng.normal(0, 0.01, 3)  # a RANSAC hypothesis
    p = PnpParams()
    e0 = reference_pnp.sq_errors(R0, t0, Pp, z, Q, zp, RIG)
    np.testing.assert_allclose(_sq_errors(R0, t0, Pp, z, Q, zp, RIG), e0, rtol=1e-12, equal_nan=True)
    inl0 = np.isfinite(e0) & (e0 < 100.0)
    assert inl0.sum() > 20
    got = refine(R0, t0, Pp, z, Q, zp, RIG, p, inl0)
    want = reference_pnp.refine(R0, t0, Pp, z, Q, zp, RIG, p, inl0)
    np.testing.assert_allclose(got[0], want[0], atol=1e-9)
    np.testing.assert_allclose(got[1], want[1], atol=1e-9)
    np.testing.assert_array_equal(got[2], want[2])
    np.testing.assert_allclose(got[3], want[3], rtol=1e-6, atol=1e-15)
    assert got[4] == pytest.approx(want[4], rel=1e-9)
    # the normal equations themselves
    idx = np.flatnonzero(got[2])
    r, J = residuals_jacobian(got[0], got[1], Pp[idx], z[idx], Q[idx], zp[idx], RIG)
    H, g, rss, count = k.normal_equations_kernel(
        got[0], got[1], Pp, z, Q, zp, idx, RIG.f_px, RIG.px, RIG.py, RIG.baseline_m / 2.0
    )
    Jf = J.reshape(-1, 6)
    np.testing.assert_allclose(H, Jf.T @ Jf, rtol=1e-10)
    np.testing.assert_allclose(g, Jf.T @ r.ravel(), rtol=1e-8, atol=1e-9)
    assert count == r.size and rss == pytest.approx(float(np.sum(r * r)))


def _far_scene(rng: np.random.Generator, n: int, d_lo: float, d_hi: float) -> np.ndarray:
    """Points spread over the image at disparities uniform in [d_lo, d_hi] px."""
    X = RIG.fb / rng.uniform(d_lo, d_hi, n)
    u = rng.uniform(50, RIG.width - 50, n)
    v = rng.uniform(40, RIG.height - 40, n)
    return np.c_[X, (u - RIG.px) * X / RIG.f_px - RIG.baseline_m / 2, (v - RIG.py) * X / RIG.f_px]


def test_the_two_view_kernel_is_its_numpy_twin():
    rng = np.random.default_rng(3)
    P = _far_scene(rng, 80, 2.5, 60.0)
    R, t = so3_exp(np.array([0.01, -0.02, 0.03])), np.array([1.0, 0.1, -0.05])
    Pn, z, _, zp = _observe(P, R, t, rng, 0.3)
    from robotd.frontend import _pnp_kernels

    hb = RIG.baseline_m / 2
    Rk, tk, Sk = _pnp_kernels.two_view_kernel(R, t, Pn, z, zp, np.arange(80), RIG.f_px, RIG.px, RIG.py, hb, 3)
    Rn, tn, Sn = reference_pnp.two_view(R, t, Pn, z, zp, RIG, 3)
    np.testing.assert_allclose(Rk, Rn, atol=1e-12)
    np.testing.assert_allclose(tk, tn, atol=1e-12)
    np.testing.assert_allclose(Sk, Sn, rtol=1e-9, atol=1e-9 * np.abs(Sn).max())


def test_the_two_view_adjustment_recovers_an_exact_motion_from_a_wrong_start():
    rng = np.random.default_rng(4)
    P = _far_scene(rng, 60, 3.0, 40.0)
    R, t = so3_exp(np.array([0.0, 0.0, 0.05])), np.array([1.2, 0.05, 0.0])
    zp, z = project_stereo(P, RIG), project_stereo((P - t) @ R, RIG)
    R0, t0 = R @ so3_exp(np.array([0.004, -0.003, 0.006])), t + np.array([0.08, -0.05, 0.03])
    R1, t1 = two_view(R0, t0, P, z, zp, RIG, np.ones(60, bool), 6)
    assert np.linalg.norm(so3_log(R1.T @ R)) < 1e-9 and np.linalg.norm(t1 - t) < 1e-9
    # too few points, or none asked for: the motion comes back unchanged
    for inl, it in ((np.arange(60) < 2, 3), (np.ones(60, bool), 0), (np.zeros(0, bool), 3)):
        n = inl.size
        R2, t2 = two_view(R0, t0, P[:n], z[:n], zp[:n], RIG, inl, it)
        assert np.array_equal(R2, R0) and np.array_equal(t2, t0)
    # a non-finite point or pixel among the inliers: no step and no error (the caller's inliers
    # are finite; the function does not rely on it)
    for arr in ("P", "z", "zp"):
        bad = {"P": P.copy(), "z": z.copy(), "zp": zp.copy()}
        bad[arr][7, 1] = np.nan
        R2, t2 = two_view(R0, t0, bad["P"], bad["z"], bad["zp"], RIG, np.ones(60, bool), 3)
        assert np.array_equal(R2, R0) and np.array_equal(t2, t0), arr


def test_far_points_shrink_the_refined_translation_and_the_two_view_adjustment_does_not():
    """Errors in variables: refine takes each triangulated point as exact, and the inverse depth
    of a point at 2.5-5 px is 6-30 % noisy, so least squares shrinks the translation (about
    1.5 % here, 60 draws of 200 points with 0.3 px noise); with the points' positions free the
    shrink is a quarter of that. Near points (5-60 px) bias neither."""
    rng = np.random.default_rng(5)
    R, t = so3_exp(np.array([0.0, 0.0, 0.02])), np.array([1.0, 0.02, 0.0])
    for d_lo, d_hi, shrinks in ((2.5, 5.0, True), (5.0, 60.0, False)):
        ref, tv = [], []
        for _ in range(60):
            P = _far_scene(rng, 200, d_lo, d_hi)
            P = P[((P - t) @ R)[:, 0] > 1.0]
            Pn, z, Qn, zp = _observe(P, R, t, rng, 0.3)
            R1, t1, inl, _, _ = refine(R, t, Pn, z, Qn, zp, RIG, PnpParams(), np.ones(len(P), bool))
            ref.append(t1[0])
            tv.append(two_view(R1, t1, Pn, z, zp, RIG, inl, 3)[1][0])
        if shrinks:
            assert np.mean(ref) < 0.99, np.mean(ref)
            assert abs(np.mean(tv) - 1.0) < 0.3 * abs(np.mean(ref) - 1.0), (np.mean(ref), np.mean(tv))
        else:
            assert abs(np.mean(ref) - 1.0) < 0.002 and abs(np.mean(tv) - 1.0) < 0.002, (np.mean(ref), np.mean(tv))


def test_the_offset_sensitivity_predicts_what_a_disparity_offset_does_to_a_long_jump():
    """A 4 m jump (a gap the images bridge): rendered with every disparity 0.3 px too large, the
    refined and adjusted motion moves by 0.3 px times the sensitivity found from the clean pixels.
    Its size is physical: a point at disparity d gives depth, and so the translation, an error of
    δ/d, so far points (3-8 px) move a 4 m jump by |t|/d ≈ 0.5-1.3 m per pixel, near ones
    (30-60 px) by a tenth of that."""
    rng = np.random.default_rng(8)
    R, t = so3_exp(np.array([0.0, 0.0, 0.03])), np.array([4.0, 0.1, 0.0])
    tri = lambda w: triangulate(w[:, 0], w[:, 1], w[:, 2], RIG.f_px, RIG.px, RIG.py, RIG.baseline_m)  # noqa: E731
    size = {}
    for d_lo, d_hi in ((3.0, 8.0), (30.0, 60.0)):
        P = _far_scene(rng, 150, d_lo, d_hi)
        P = P[((P - t) @ R)[:, 0] > 1.0]
        zp, z = project_stereo(P, RIG), project_stereo((P - t) @ R, RIG)
        inl = np.ones(len(P), bool)
        J = offset_sensitivity(R, t, z, zp, RIG, PnpParams(), inl)
        zpd, zd = zp.copy(), z.copy()
        zpd[:, 1] -= 0.3  # every disparity reads 0.3 px too large
        zd[:, 1] -= 0.3
        R1, t1, inl1, _, _ = refine(R, t, tri(zpd), zd, tri(zd), zpd, RIG, PnpParams(), inl)
        R1, t1 = two_view(R1, t1, tri(zpd), zd, zpd, RIG, inl1, 3)
        moved = np.r_[t1 - t, so3_log(R.T @ R1)]
        np.testing.assert_allclose(moved, 0.3 * J, atol=0.05 * np.abs(0.3 * J).max())
        size[d_lo] = float(np.linalg.norm(J[:3]))
    assert 4.0 / 8.0 < size[3.0] < 4.0 / 3.0, size
    assert size[30.0] < 0.2 * size[3.0], size
    # too few points left to refine: no sensitivity, not a wrong one
    J = offset_sensitivity(R, t, z[:2], zp[:2], RIG, PnpParams(), np.ones(2, bool))
    assert np.all(np.isnan(J))
