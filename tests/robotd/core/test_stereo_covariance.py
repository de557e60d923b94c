"""The first-order triangulation covariance (docs/math.md §3.1–§3.2) against simulated pixel noise, and
the motion blur's term (§3.4) against simulated streaks."""

from __future__ import annotations

import numpy as np
import pytest

from robotd.core.stereo import (
    RectifiedStereo,
    blur_covariance,
    project,
    streak_px,
    triangulate,
    triangulation_covariance,
)

# The project's OAK-D at 640x400 (docs/math.md §2.2): f ≈ 430 px, b = 0.0755 m, fb ≈ 32.5 px·m.
F, PX, PY, B = 430.0, 320.0, 200.0, 0.0755
SX = 0.5  # σ per column coordinate [px]
SY_ROW = 0.5  # σ of each row; the model's σ_y is that of their mean, 0.5/√2
N = 20000
# mean of N χ²₃ draws has σ = sqrt(6/N) ≈ 0.017; 0.1 is ~6σ, and still catches a 3.5 % scale error in σ
NEES_TOL = 0.1


def _simulate(X: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """N noisy triangulations of random points at depth X across the field of view; (errors, Q)."""
    half_w = (PX - 20) / F * X
    half_h = (PY - 20) / F * X
    pts = np.c_[np.full(N, X), rng.uniform(-half_w, half_w, N), rng.uniform(-half_h, half_h, N)]
    xl, xr, y = project(pts, F, PX, PY, B)
    xl_n = xl + rng.normal(0, SX, N)
    xr_n = xr + rng.normal(0, SX, N)
    y_n = y + 0.5 * (rng.normal(0, SY_ROW, N) + rng.normal(0, SY_ROW, N))
    est = triangulate(xl_n, xr_n, y_n, F, PX, PY, B)
    Q = triangulation_covariance(xl_n, xr_n, y_n, F, PX, PY, B, sigma_x_px=SX, sigma_y_px=SY_ROW / np.sqrt(2))
    return est - pts, Q


@pytest.mark.parametrize("X", [0.5, 1.0, 2.0, 3.0])
def test_nees_is_chi2_3_where_first_order_holds(X: float, rng: np.random.Generator) -> None:
    """Disparities 65..11 px: σ_d/d ≤ 6 %, where the linearisation of X = fb/d holds."""
    e, Q = _simulate(X, rng)
    nees = np.einsum("ni,ni->n", e, np.linalg.solve(Q, e[..., None])[..., 0])
    assert abs(nees.mean() - 3.0) < NEES_TOL, f"X={X} m: mean NEES {nees.mean():.3f}"
    # and the tail: share above the χ²₃ 95 % quantile (7.815) is 5 %
    assert abs(np.mean(nees > 7.815) - 0.05) < 0.01


def test_first_order_breaks_down_at_small_disparity(rng: np.random.Generator) -> None:
    """At d ≈ 4 px (X = 8 m, below the 5 px floor) depth is biased far and the χ² tail is too heavy
    (docs/math.md §3.3); measured: mean depth error +0.29 m, 7.6 % of NEES above the 95 % quantile."""
    e, Q = _simulate(8.0, rng)
    nees = np.einsum("ni,ni->n", e, np.linalg.solve(Q, e[..., None])[..., 0])
    assert np.mean(nees > 7.815) > 0.065
    assert e[:, 0].mean() > 10 * e[:, 0].std() / np.sqrt(N)


def test_depth_sigma_grows_with_range_squared(rng: np.random.Generator) -> None:
    ranges = np.array([0.5, 1.0, 1.5, 2.0, 3.0])
    sig = np.array([_simulate(X, rng)[0][:, 0].std() for X in ranges])
    slope = np.polyfit(np.log(ranges), np.log(sig), 1)[0]
    assert slope == pytest.approx(2.0, abs=0.06)
    # closed form σ_X = √2 X² σ_x / (f b) (docs/math.md §3.2)
    assert np.allclose(sig, np.sqrt(2) * ranges**2 * SX / (F * B), rtol=0.05)


def test_a_streak_is_rate_times_exposure_times_focal_length_and_nothing_without_exposure() -> None:
    assert streak_px(2.0, 0.01, 450.0) == pytest.approx(9.0)
    assert streak_px(2.0, 0.0, 450.0) == 0.0
    assert streak_px(float("nan"), 0.01, 450.0) == 0.0
    assert streak_px(-1.0, 0.01, 450.0) == 0.0


def test_the_blur_term_is_the_covariance_of_streaks_shared_by_both_views(rng: np.random.Generator) -> None:
    # one point at a time: each measured N times, found anywhere along a streak of b pixels at a
    # random angle, the same offset in both images (both cameras expose together)
    rig = RectifiedStereo(F, PX, PY, B, 640, 400)
    b = 8.0
    for X, Y, Z in [(3.0, 0.4, -0.2), (6.0, -1.0, 0.5), (12.0, 2.0, 1.0)]:
        xl, xr, y = project(np.array([[X, Y, Z]]), F, PX, PY, B)
        s = rng.uniform(-b / 2, b / 2, N)
        a = rng.uniform(0.0, 2.0 * np.pi, N)
        est = triangulate(xl + s * np.cos(a), xr + s * np.cos(a), y + s * np.sin(a), F, PX, PY, B)
        emp = np.cov((est - [X, Y, Z]).T)
        Q = blur_covariance(xl, xr, y, rig, b)[0]
        # the disparity is untouched: no depth error at all
        assert Q[0, 0] == pytest.approx(0.0, abs=1e-15) and emp[0, 0] < 1e-20
        # across the ray: the first-order term holds the streaks' spread (to the sampling's 3 %)
        np.testing.assert_allclose(Q[1:, 1:], emp[1:, 1:], rtol=0.05, atol=0.05 * np.trace(Q))
    assert np.all(blur_covariance(xl, xr, y, rig, 0.0) == 0.0)
    assert np.all(blur_covariance(xl, xr, y, rig, float("nan")) == 0.0)
