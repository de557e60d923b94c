"""The exposure estimated from the frame-to-frame residuals' spread (robotd.frontend.exposure)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robotd.core.msgs import MotionIncrement
from robotd.frontend.exposure import ExposureEstimate, residual_spread


def _drive(
    est: ExposureEstimate, seed: int, exposure_s: float, rate_hi: float, dt: float, f: float, n: int = 200
) -> list[float]:
    """Feed ``n`` consecutive motions turning at up to ``rate_hi`` rad/s whose residuals spread as
    the model says (0.75 px² of detector noise plus the two frames' streaks at ``exposure_s``),
    with 15 % of multiplicative noise. Returns the estimate after each."""
    rng = np.random.default_rng(seed)
    out, t, w2_prev = [], 0, None
    for _ in range(n):
        w = rng.normal(size=3)
        w *= rng.uniform(0.0, rate_hi) / np.linalg.norm(w)
        w2 = float(w @ w)
        x = f**2 * (w2 + (w2 if w2_prev is None else w2_prev)) / 12.0
        y = (0.75 + exposure_s**2 * x) * (1.0 + 0.15 * rng.normal())
        w2_prev = w2
        est.add(MotionIncrement(t, t + round(dt * 1e9), np.zeros(3), w * dt, np.eye(6) * 1e-4), f, y)
        t += round(dt * 1e9)
        out.append(est.exposure_s())
    return out


@pytest.mark.parametrize("exposure_ms", [2.0, 6.0, 12.0])
def test_a_shaken_camera_gives_its_exposure(exposure_ms: float) -> None:
    """A hand-held camera turning at up to 3 rad/s (EuRoC's rig at 20 Hz): the estimate is within
    5 % of the exposure the residuals were drawn with, and it is stated within 20 frames."""
    for seed in range(5):
        hist = _drive(ExposureEstimate(), seed, exposure_ms * 1e-3, 3.0, 0.05, 458.0)
        assert hist[-1] == pytest.approx(exposure_ms * 1e-3, rel=0.05)
        assert next(k for k, e in enumerate(hist) if e > 0.0) < 20


def test_no_blur_no_estimate() -> None:
    """No blur in the residuals: a car on the road (KITTI's rig at 10 Hz, turning at up to
    0.06 rad/s, where a slope is poorly fixed) and a shaken camera. A false exposure would widen
    every gate: on most seeds there is none on any frame, and where chance gives one, the streak
    it draws at the fastest turn stays under 1.5 px (b²/12 = 0.19 px², below the 0.5 px detector
    noise's 0.25 px²)."""
    zero = 0
    for seed in range(20):
        car = max(_drive(ExposureEstimate(), seed, 0.0, 0.06, 0.1, 718.0))
        shaken = max(_drive(ExposureEstimate(), seed, 0.0, 3.0, 0.05, 458.0))
        assert car * 0.06 * 718.0 < 1.5 and shaken * 3.0 * 458.0 < 1.5
        zero += car == 0.0 and shaken == 0.0
    assert zero >= 15


def test_a_still_camera_states_nothing_however_the_residuals_spread() -> None:
    """Turning too slowly to streak (0.005 rad/s): no frame counts as fast, so however the residuals
    spread there is no estimate (the stationary EuRoC piece gave a fitted slope of 150 ms)."""
    assert max(_drive(ExposureEstimate(), 1, 0.2, 0.005, 0.05, 458.0)) == 0.0


def test_pairs_follow_each_other_and_bad_input_is_skipped() -> None:
    """A pair needs the previous motion to end where this one starts; a NaN spread and a zero
    interval are skipped and break the chain (a MotionIncrement itself refuses a NaN rotation)."""
    est = ExposureEstimate()
    inc = lambda t0, t1: MotionIncrement(t0, t1, np.zeros(3), np.array([0.1, 0.0, 0.0]), np.eye(6))  # noqa: E731
    est.add(inc(0, 50), 458.0, 1.0)
    est.add(inc(100, 150), 458.0, 1.0)  # a gap: starts a new pair
    assert est.frames == 0
    est.add(inc(150, 200), 458.0, 1.0)
    assert est.frames == 1
    est.add(inc(200, 250), 458.0, math.nan)
    est.add(inc(250, 300), 458.0, 1.0)  # its predecessor was skipped
    est.add(inc(300, 300), 458.0, 1.0)
    est.add(inc(300, 350), 458.0, 1.0)  # after the zero interval
    assert est.frames == 1 and est.exposure_s() == 0.0


def test_residual_spread_is_the_total_variance_and_robust() -> None:
    """Isotropic Gaussian residuals σ = 1.5 px per axis: the spread is 2σ² = 4.5 px² within 5 %;
    20 % of wild matches move it by less than half (the median then sits at the inliers' 62.5th
    percentile: ×1.42); x_R (the depth's) does not count; fewer than 8 finite residuals give None."""
    rng = np.random.default_rng(3)
    res = rng.normal(0.0, 1.5, (4000, 3))
    res[:, 1] = 1e3
    assert residual_spread(res) == pytest.approx(4.5, rel=0.05)
    wild = res.copy()
    wild[:800, [0, 2]] = rng.uniform(-100, 100, (800, 2))
    s = residual_spread(wild)
    assert s is not None and 4.5 < s < 4.5 * 1.5
    few = np.full((20, 3), np.nan)
    few[:7] = 1.0
    assert residual_spread(few) is None
