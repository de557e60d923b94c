"""The outlier stage (docs/math.md §5): similarity solver, consensus statistics, RANSAC, F baseline."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robotd.core.errors import ConfigError, InputError
from robotd.core.geometry import euler_to_R, numerical_jacobian, rot2, skew, umeyama
from robotd.core.outliers import (
    OutlierParams,
    detect_outliers,
    fit_similarity_mahalanobis,
    fundamental_8point,
    iteration_budget,
    mahalanobis_sq,
    ransac_fundamental,
    ransac_similarity,
    sample_indices,
    sampson_sq,
    similarity_d2,
)
from robotd.research.synthetic_pairs import simulate_pairs
from tests.support.reference_outliers import fit_similarity_mahalanobis_numpy, similarity_d2_numpy
from tests.support.tolerances import (
    CENTRAL_DIFF_ATOL,
    CONDITIONED_ATOL,
    CONDITIONED_RTOL,
    KERNEL_TWIN_RTOL,
    ROUNDOFF_ATOL,
)

CHI2_3_099 = 11.345
# Gauss-Newton stops once a step is below robotd.core.outliers.GN_STEP_TOL (1e-7) and converges
# quadratically, so s and R are within ~(1e-7)² · C of the optimum; t = b̄ − s R ā carries the R error
# times |a| ≤ 10 (measured ~1e-16 on noiseless data)
GN_FIT_ATOL = 1e-8
GN_FIT_T_ATOL = 1e-7


def _random_similarity(rng: np.random.Generator) -> tuple[float, np.ndarray, np.ndarray]:
    s = float(rng.uniform(0.95, 1.05))
    R = euler_to_R(rng.uniform(-np.pi, np.pi, 3) * np.array([0.3, 0.3, 1.0]))
    t = rng.normal(0.0, 5.0, 3)
    return s, R, t


def _spd(rng: np.random.Generator, n: int, d: int, scale: float) -> np.ndarray:
    M = rng.normal(size=(n, d, d))
    return scale * (M @ np.swapaxes(M, 1, 2) + 0.5 * np.eye(d))


def test_umeyama_recovers_random_similarity_exactly(rng):
    for _ in range(20):
        s, R, t = _random_similarity(rng)
        a = rng.uniform(-10, 10, (3 + int(rng.integers(0, 10)), 3))
        b = s * a @ R.T + t
        s1, R1, t1 = umeyama(a, b)
        # an SVD on 3 to 12 points: CONDITIONED_ATOL as in test_geometry's Umeyama test (1e-10 before
        # for s and R; measured 4.4e-16 and 1.9e-15)
        assert abs(s1 - s) < CONDITIONED_ATOL
        np.testing.assert_allclose(R1, R, atol=CONDITIONED_ATOL)
        np.testing.assert_allclose(t1, t, atol=CONDITIONED_ATOL)


def test_ransac_recovers_noiseless_transform_and_keeps_all(rng):
    s, R, t = _random_similarity(rng)
    a = rng.uniform(-10, 10, (30, 3))
    b = s * a @ R.T + t
    cov = np.tile(np.eye(3) * 1e-4, (30, 1, 1))
    res = ransac_similarity(a, b, cov, cov, OutlierParams(), rng)
    assert res.accepted and res.inliers.all()
    assert res.s is not None and res.R is not None and res.t is not None
    assert abs(res.s - s) < GN_FIT_ATOL
    np.testing.assert_allclose(res.R, R, atol=GN_FIT_ATOL)
    np.testing.assert_allclose(res.t, t, atol=GN_FIT_T_ATOL)


def test_mahalanobis_closed_form_matches_solve(rng):
    for d in (2, 3):
        C = _spd(rng, 200, d, 0.3)
        e = rng.normal(size=(200, d))
        ref = np.einsum("ni,ni->n", e, np.linalg.solve(C, e[..., None])[..., 0])
        np.testing.assert_allclose(mahalanobis_sq(e, C), ref, rtol=CONDITIONED_RTOL)
    # not positive definite: never an inlier
    assert np.isinf(mahalanobis_sq(np.ones((1, 3)), -np.eye(3)[None]))[0]


def test_batched_d2_matches_one_at_a_time(rng):
    n, k = 25, 4
    a, b = rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
    A, B = _spd(rng, n, 3, 0.01), _spd(rng, n, 3, 0.02)
    hyps = [_random_similarity(rng) for _ in range(k)]
    s = np.array([h[0] for h in hyps])
    R = np.stack([h[1] for h in hyps])
    t = np.stack([h[2] for h in hyps])
    d2 = similarity_d2(s, R, t, a, b, A, B)
    for q in range(k):
        for i in range(n):
            e = b[i] - (s[q] * R[q] @ a[i] + t[q])
            C = B[i] + s[q] ** 2 * R[q] @ A[i] @ R[q].T
            assert d2[q, i] == pytest.approx(e @ np.linalg.solve(C, e), rel=CONDITIONED_RTOL)


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("which", ["AB", "A", "B"])
def test_d2_kernel_matches_numpy_reference(rng, d, which):
    n, k = 300, 24
    a, b = rng.normal(size=(n, d)) * 5, rng.normal(size=(n, d)) * 5
    A = _spd(rng, n, d, 0.01) if "A" in which else None
    B = _spd(rng, n, d, 0.02) if "B" in which else None
    s = rng.uniform(0.9, 1.1, k)
    if d == 3:
        R = np.stack([_random_similarity(rng)[1] for _ in range(k)])
    else:
        th = rng.uniform(-np.pi, np.pi, k)
        R = np.stack([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]]).transpose(2, 0, 1)
    t = rng.normal(size=(k, d))
    got = similarity_d2(s, R, t, a, b, A, B)
    ref = similarity_d2_numpy(s, R, t, a, b, A, B)
    np.testing.assert_allclose(got, ref, rtol=KERNEL_TWIN_RTOL)
    # an indefinite covariance (det < 0) never gives an inlier
    if B is not None:
        B[0] = np.diag([1.0, -1.0, 1.0][:d])
        if A is not None:
            A[0] = 0.0
        assert np.all(np.isinf(similarity_d2(s, R, t, a, b, A, B)[:, 0]))


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("with_scale", [True, False])
def test_weighted_fit_kernel_matches_numpy_reference(rng, d, with_scale):
    n = 200
    if d == 3:
        s, R, t = _random_similarity(rng)
    else:
        th = rng.uniform(-np.pi, np.pi)
        s, R, t = (
            rng.uniform(0.95, 1.05),
            np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]]),
            rng.normal(size=2),
        )
    a = rng.uniform(-10, 10, (n, d))
    A, B = _spd(rng, n, d, 0.01), _spd(rng, n, d, 0.02)
    b = s * a @ R.T + t + rng.normal(scale=0.1, size=(n, d))
    # start away from the optimum, so that Gauss-Newton takes several steps
    R0 = R @ (_random_similarity(rng)[1] if d == 3 else np.eye(2))
    got = fit_similarity_mahalanobis(a, b, A, B, 1.0, R0, t + 0.2, with_scale=with_scale)
    ref = fit_similarity_mahalanobis_numpy(a, b, A, B, 1.0, R0, t + 0.2, with_scale=with_scale)
    for x, y in zip(got, ref, strict=True):
        # Gauss-Newton iterations feed each step's round-off differences into the next: 10 KERNEL_TWIN_RTOL
        np.testing.assert_allclose(x, y, rtol=10 * KERNEL_TWIN_RTOL, atol=ROUNDOFF_ATOL)


def test_consensus_rate_matches_chi2_level_gaussian(rng):
    # exact Gaussian noise with the stated covariances: d² ~ χ²₃ exactly
    n = 20000
    s, R, t = _random_similarity(rng)
    a_true = rng.uniform(-10, 10, (n, 3))
    A, B = _spd(rng, n, 3, 0.01), _spd(rng, n, 3, 0.02)
    a = a_true + np.einsum("nij,nj->ni", np.linalg.cholesky(A), rng.normal(size=(n, 3)))
    b = s * a_true @ R.T + t + np.einsum("nij,nj->ni", np.linalg.cholesky(B), rng.normal(size=(n, 3)))
    d2 = similarity_d2(np.array([s]), R[None], t[None], a, b, A, B)[0]
    rate = float(np.mean(d2 <= CHI2_3_099))
    tol = 4.0 * math.sqrt(0.99 * 0.01 / n)  # 4σ binomial
    assert abs(rate - 0.99) < tol, rate


def test_consensus_rate_on_stereo_simulated_data(rng):
    # stereo noise is only first-order Gaussian (§3.3): the rate stays close to 99 %
    inl, tot = 0, 0
    for seed in range(30):
        d = simulate_pairs(np.random.default_rng(seed), n=60, mismatch_rate=0.0)
        T = np.linalg.inv(d.T_world_robot)
        d2 = similarity_d2(np.ones(1), T[None, :3, :3], T[None, :3, 3], d.a, d.b, d.A, d.B)[0]
        inl += int(np.sum(d2 <= CHI2_3_099))
        tot += d2.size
    rate = inl / tot
    tol = 4.0 * math.sqrt(0.99 * 0.01 / tot)
    assert 0.99 - 2 * tol < rate <= 1.0, rate


@pytest.mark.parametrize("rate", [0.2, 0.3])
def test_ransac_flags_mismatches(rate):
    flagged = bad = false_rej = good = 0
    for seed in range(20):
        d = simulate_pairs(np.random.default_rng(seed), n=40, mismatch_rate=rate)
        res = ransac_similarity(d.a, d.b, d.A, d.B, OutlierParams(), np.random.default_rng(100 + seed))
        flagged += int(np.sum(~res.inliers & d.is_mismatch))
        bad += int(d.is_mismatch.sum())
        false_rej += int(np.sum(~res.inliers & ~d.is_mismatch))
        good += int(np.sum(~d.is_mismatch))
    assert flagged / bad >= 0.95
    assert false_rej / good <= 0.05


def test_mahalanobis_beats_fundamental_and_euclidean_at_20_percent():
    scores = {"similarity_mahalanobis": 0.0, "similarity_euclidean": 0.0, "fundamental": 0.0}
    for seed in range(10):
        d = simulate_pairs(np.random.default_rng(seed), n=40, mismatch_rate=0.2)
        for m in scores:
            res = detect_outliers(OutlierParams(method=m), np.random.default_rng(seed), d.a, d.b, d.A, d.B, d.x1, d.x2)
            # Youden-style score: recall − false rejection
            scores[m] += np.mean(~res.inliers[d.is_mismatch]) - np.mean(~res.inliers[~d.is_mismatch])
    assert scores["similarity_mahalanobis"] > scores["fundamental"]
    assert scores["similarity_mahalanobis"] > scores["similarity_euclidean"]


def test_ransac_2d_variant(rng):
    n = 40
    th, t = 0.7, np.array([3.0, -2.0])
    a = rng.uniform(-10, 10, (n, 2))
    cov = np.tile(np.eye(2) * 0.01**2, (n, 1, 1))
    b = a @ rot2(th).T + t + rng.normal(0, 0.01, (n, 2))
    bad = rng.random(n) < 0.3
    b[bad] = rng.uniform(-10, 10, (int(bad.sum()), 2))
    res = ransac_similarity(a, b, cov, cov, OutlierParams(), rng)
    assert res.threshold == pytest.approx(9.210, abs=1e-3)
    assert res.accepted and not np.any(res.inliers & bad)
    assert np.mean(res.inliers[~bad]) >= 0.9
    assert res.R is not None
    np.testing.assert_allclose(res.R, rot2(th), atol=1e-2)


def test_euclidean_variant_uses_tau(rng):
    n = 40
    a = rng.uniform(-5, 5, (n, 3))
    b = a + np.array([1.0, 0.0, 0.0])
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    b[:8] += 0.6 * u[:8]  # 0.6 m off: beyond τ = 0.2 m
    b[8:] += 0.05 * u[8:]  # 5 cm: within τ
    res = ransac_similarity(a, b, None, None, OutlierParams(method="similarity_euclidean"), rng)
    assert not res.inliers[:8].any() and res.inliers[8:].all()
    assert res.s is not None and res.R is not None and res.t is not None
    e = b - (res.s * a @ res.R.T + res.t)
    np.testing.assert_allclose(res.d2, np.sum(e * e, axis=1), rtol=CONDITIONED_RTOL)
    assert np.array_equal(res.inliers, res.d2 <= 0.2**2)


def test_mahalanobis_fit_converges_and_its_jacobian_is_right(rng):
    s, R, t = _random_similarity(rng)
    a = rng.uniform(-10, 10, (20, 3))
    b = s * a @ R.T + t
    A, B = _spd(rng, 20, 3, 1e-3), _spd(rng, 20, 3, 1e-3)
    R0 = euler_to_R(np.array([0.02, -0.03, 0.05])) @ R
    s1, R1, t1, cov = fit_similarity_mahalanobis(a, b, A, B, 1.0, R0, t + 0.3, iterations=10)
    assert abs(s1 - s) < GN_FIT_ATOL
    np.testing.assert_allclose(R1, R, atol=GN_FIT_ATOL)
    np.testing.assert_allclose(t1, t, atol=GN_FIT_T_ATOL)
    assert cov.shape == (7, 7) and np.all(np.linalg.eigvalsh(cov) > 0)

    # the Jacobian the solver uses: e(δt, δθ, δσ) = b − (s e^{δσ} exp(δθ) R a + t + δt)
    def e_of(x: np.ndarray) -> np.ndarray:
        th = np.linalg.norm(x[3:6])
        K = skew(x[3:6] / th) if th > 0 else np.zeros((3, 3))
        Rx = np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K
        return (b[0] - (s * np.exp(x[6]) * Rx @ R @ a[0] + t + x[:3])).ravel()

    Jn = numerical_jacobian(e_of, np.zeros(7))
    sRa = s * R @ a[0]
    Ja = np.concatenate([-np.eye(3), skew(sRa), -sRa[:, None]], axis=1)
    np.testing.assert_allclose(Ja, Jn, atol=CENTRAL_DIFF_ATOL)


def test_fewer_than_min_inliers_accepts_none(rng):
    a = rng.uniform(-5, 5, (5, 3))
    cov = np.tile(np.eye(3) * 1e-4, (5, 1, 1))
    res = ransac_similarity(a, a.copy(), cov, cov, OutlierParams(), rng)
    assert not res.accepted and not res.inliers.any() and res.n_rejected == 5
    # 12 pairs, all mutually inconsistent: the best consensus is the 3-point sample itself
    a = rng.uniform(-5, 5, (12, 3))
    b = rng.uniform(-5, 5, (12, 3))
    cov = np.tile(np.eye(3) * 1e-6, (12, 1, 1))
    res = ransac_similarity(a, b, cov, cov, OutlierParams(), rng)
    assert not res.accepted and not res.inliers.any()


def test_degenerate_samples_are_skipped(rng):
    # collinear points: every sample has zero triangle area
    a = np.c_[np.linspace(0, 10, 20), np.zeros(20), np.zeros(20)]
    cov = np.tile(np.eye(3) * 1e-4, (20, 1, 1))
    res = ransac_similarity(a, a + 1.0, cov, cov, OutlierParams(max_iterations=64), rng)
    assert res.degenerate == res.iterations == 64
    assert not res.accepted


def test_iteration_budget_values():
    assert iteration_budget(0.5, 3, 0.99, 500) == 35
    assert iteration_budget(0.3, 3, 0.99, 500) == 169
    assert iteration_budget(0.7, 3, 0.99, 500) == 11
    assert iteration_budget(0.5, 8, 0.99, 2000) == 1177
    assert iteration_budget(0.1, 3, 0.99, 500) == 500
    assert iteration_budget(1.0, 3, 0.99, 500) == 1


def test_sample_indices_are_distinct_and_uniform(rng):
    idx = sample_indices(rng, 10, 3, 30000)
    assert np.all((idx >= 0) & (idx < 10))
    srt = np.sort(idx, axis=1)
    assert np.all(np.diff(srt, axis=1) > 0)
    counts = np.bincount(idx.ravel(), minlength=10) / idx.size
    np.testing.assert_allclose(counts, 0.1, atol=0.005)


def _two_views(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    K = np.array([[700.0, 0.0, 600.0], [0.0, 700.0, 180.0], [0.0, 0.0, 1.0]])
    X = rng.uniform([-10, -3, 5], [10, 3, 40], (n, 3))
    R = euler_to_R(np.array([0.01, 0.05, -0.02]))
    t = np.array([0.2, 0.05, -1.2])

    def proj(P: np.ndarray) -> np.ndarray:
        p = P @ K.T
        return p[:, :2] / p[:, 2:]

    Kinv = np.linalg.inv(K)
    F_true = Kinv.T @ skew(t) @ R @ Kinv
    return proj(X), proj(X @ R.T + t), F_true / np.linalg.norm(F_true)


def test_fundamental_8point_recovers_F_noiseless(rng):
    x1, x2, F_true = _two_views(rng, 40)
    F = fundamental_8point(x1[None, :8], x2[None, :8])[0]
    F = F * np.sign(np.sum(F * F_true))
    np.testing.assert_allclose(F, F_true, atol=CONDITIONED_ATOL)  # an SVD; 1e-6 before, measured 5.2e-14
    assert np.linalg.matrix_rank(F, tol=CONDITIONED_ATOL) == 2
    assert sampson_sq(F[None], x1, x2).max() < ROUNDOFF_ATOL


def test_fundamental_ransac_rejects_gross_outliers(rng):
    x1, x2, _ = _two_views(rng, 100)
    x2 = x2 + rng.normal(0, 0.3, x2.shape)
    bad = rng.random(100) < 0.25
    x2[bad] += rng.normal(0, 40, (int(bad.sum()), 2))
    res = ransac_fundamental(x1, x2, OutlierParams(method="fundamental"), rng)
    assert res.accepted and res.F is not None
    assert np.mean(~res.inliers[bad]) >= 0.85  # a few land near their epipolar line by chance
    assert np.mean(res.inliers[~bad]) >= 0.95


def test_seeded_runs_are_reproducible():
    d = simulate_pairs(np.random.default_rng(3), n=40, mismatch_rate=0.3)
    r1 = ransac_similarity(d.a, d.b, d.A, d.B, OutlierParams(), np.random.default_rng(7))
    r2 = ransac_similarity(d.a, d.b, d.A, d.B, OutlierParams(), np.random.default_rng(7))
    assert np.array_equal(r1.inliers, r2.inliers) and r1.iterations == r2.iterations


def test_bad_inputs_give_clear_errors(rng):
    with pytest.raises(InputError, match=r"\(3, 3\).*\(4, 3\)"):
        ransac_similarity(np.zeros((3, 3)), np.zeros((4, 3)), None, None, OutlierParams(), rng)
    with pytest.raises(InputError, match="covariances"):
        ransac_similarity(np.zeros((8, 3)), np.zeros((8, 3)), None, None, OutlierParams(), rng)
    with pytest.raises(InputError, match="Generator"):
        ransac_similarity(np.zeros((8, 3)), np.zeros((8, 3)), None, None, OutlierParams(), None)
    with pytest.raises(InputError, match="x1 and x2"):
        detect_outliers(OutlierParams(method="fundamental"), rng, a=np.zeros((8, 3)))
    with pytest.raises(ConfigError, match="frontend.outliers.method"):
        OutlierParams(method="magic")
    with pytest.raises(ConfigError, match="confidence"):
        OutlierParams(confidence=1.5)
    res = detect_outliers(OutlierParams(method="none"), rng, a=np.zeros((4, 3)))
    assert res.inliers.all() and res.n_inliers == 4
