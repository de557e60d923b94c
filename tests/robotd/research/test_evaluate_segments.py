"""KITTI-style segment drift (robotd.research.evaluate.segment_drift, issue 26 item 3): trajectories
whose error per segment is known in closed form."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robotd.core.errors import InputError
from robotd.core.geometry import rot_z, se3
from robotd.research.evaluate import KITTI_SEGMENT_LENGTHS_M, segment_drift
from tests.support.tolerances import ANGLE_FROM_COSINE_FLOOR_DEG, CONDITIONED_RTOL

STEP_M = 0.5  # a power of two: the path lengths 0.5 k add up exactly, so a segment of L m is 2L steps


def _straight(n: int) -> np.ndarray:
    """(n, 4, 4) along x, STEP_M apart, no rotation."""
    return se3(
        np.broadcast_to(np.eye(3), (n, 3, 3)), np.column_stack([np.arange(n) * STEP_M, np.zeros(n), np.zeros(n)])
    )


def _circle(n: int, r_m: float, dtheta: float) -> np.ndarray:
    """(n, 4, 4) on a circle of radius r_m, dtheta rad apart, heading along the tangent."""
    th = np.arange(n) * dtheta
    xyz = np.column_stack([r_m * np.sin(th), r_m * (1.0 - np.cos(th)), np.zeros(n)])
    return se3(rot_z(th), xyz)


def _scaled(T: np.ndarray, s: float) -> np.ndarray:
    out = T.copy()
    out[:, :3, 3] *= s
    return out


def test_a_trajectory_one_percent_long_drifts_one_percent_on_every_straight_segment() -> None:
    gt = _straight(1801)  # 900 m: every KITTI length has segments
    m = segment_drift(_scaled(gt, 1.01), gt)
    assert m["segment_note"] is None
    # starts 0, 10, ... 1800 (5 m apart); a segment of L needs L m of path after its start
    for row, L in zip(m["segments"], KITTI_SEGMENT_LENGTHS_M):
        assert row["length_m"] == L
        assert row["count"] == len(range(0, 1801 - int(2 * L), 10))
        assert row["drift_pct"] == pytest.approx(1.0, rel=CONDITIONED_RTOL)
        # the angle of E ≈ I is an arccos: zero only to its resolution
        assert row["rot_deg_per_m"] == pytest.approx(0.0, abs=ANGLE_FROM_COSINE_FLOOR_DEG / L)
    assert m["segment_drift_pct"] == pytest.approx(1.0, rel=CONDITIONED_RTOL)
    assert m["segment_count"] == sum(r["count"] for r in m["segments"])


def test_on_a_circle_the_error_of_a_scaled_trajectory_is_one_percent_of_the_chord() -> None:
    """Scaling by 1.01 lengthens the start-to-end chord by 1 %: on a curve that is less than 1 % of
    the segment's path length L, by chord / L; and the pooled mean weighs lengths by their counts."""
    r, dth = 40.0, 0.013  # steps of 2 r sin(dth / 2) = 0.519996 m, so no segment ends exactly at L
    n = 500
    gt = _circle(n, r, dth)
    lengths = (10.0, 20.0, 40.0)
    m = segment_drift(_scaled(gt, 1.01), gt, lengths)
    chord_step = 2 * r * math.sin(dth / 2)
    for row, L in zip(m["segments"], lengths):
        k = math.ceil(L / chord_step)  # the first pose whose path from the start reaches L
        assert row["count"] == len(range(0, n - k, 10))
        assert row["drift_pct"] == pytest.approx(1.0 * 2 * r * math.sin(k * dth / 2) / L, rel=CONDITIONED_RTOL)
        # the angle of E ≈ I is an arccos: zero only to its resolution
        assert row["rot_deg_per_m"] == pytest.approx(0.0, abs=ANGLE_FROM_COSINE_FLOOR_DEG / L)
    assert m["segments"][2]["drift_pct"] < 0.99  # the curve shows: not 1 %
    pooled = sum(r["count"] * r["drift_pct"] for r in m["segments"]) / m["segment_count"]
    assert m["segment_drift_pct"] == pytest.approx(pooled, rel=CONDITIONED_RTOL)


def test_a_constant_yaw_error_per_metre_reads_as_that_many_degrees_per_metre() -> None:
    """The estimate turns 0.02°/m more than the truth (straight): each segment's rotation error is
    0.02° × L, so 0.02 deg/m on every length, whatever the translation error it causes."""
    n = 401
    gt = _straight(n)
    rate_deg_per_m = 0.02
    yaw = np.deg2rad(rate_deg_per_m) * np.arange(n) * STEP_M
    steps = np.column_stack([STEP_M * np.cos(yaw[:-1]), STEP_M * np.sin(yaw[:-1]), np.zeros(n - 1)])
    est = se3(rot_z(yaw), np.vstack([np.zeros(3), np.cumsum(steps, axis=0)]))
    m = segment_drift(est, gt, (10.0, 50.0, 100.0))
    for row in m["segments"]:
        assert row["count"] > 0
        assert row["rot_deg_per_m"] == pytest.approx(rate_deg_per_m, rel=CONDITIONED_RTOL)
    assert m["segment_rot_deg_per_m"] == pytest.approx(rate_deg_per_m, rel=CONDITIONED_RTOL)
    # the heading error bends the path sideways: the longer the segment, the larger its drift in %
    d = [r["drift_pct"] for r in m["segments"]]
    assert 0 < d[0] < d[1] < d[2]


def test_a_path_shorter_than_every_segment_has_none_and_says_why() -> None:
    gt = _straight(61)  # 30 m
    m = segment_drift(_scaled(gt, 1.01), gt)
    assert m["segment_count"] == 0
    assert math.isnan(m["segment_drift_pct"]) and math.isnan(m["segment_rot_deg_per_m"])
    assert all(r["count"] == 0 and math.isnan(r["drift_pct"]) for r in m["segments"])
    assert m["segment_note"] == "no segment: the true path (30.0 m) is shorter than the shortest segment (100 m)"


def test_shorter_segments_on_a_short_path_and_lengths_the_path_cannot_hold() -> None:
    gt = _straight(61)  # 30 m; starts at 0, 5, ... 30 m
    m = segment_drift(_scaled(gt, 1.01), gt, (10.0, 20.0, 40.0))
    assert [r["count"] for r in m["segments"]] == [5, 3, 0]  # starts at ≤ 20 m, ≤ 10 m, none
    assert math.isnan(m["segments"][2]["drift_pct"])
    assert m["segment_count"] == 8 and m["segment_note"] is None
    assert m["segment_drift_pct"] == pytest.approx(1.0, rel=CONDITIONED_RTOL)
    # every frame a start
    assert segment_drift(gt, gt, (10.0,), step_frames=1)["segment_count"] == 41


@pytest.mark.parametrize("lengths", [(), (10.0, -1.0), (math.nan,)])
def test_bad_segment_lengths_are_refused(lengths: tuple[float, ...]) -> None:
    gt = _straight(10)
    with pytest.raises(InputError, match="segment lengths"):
        segment_drift(gt, gt, lengths)
