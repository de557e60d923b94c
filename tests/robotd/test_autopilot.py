"""Pose -> ODOMETRY field values, covariance layout, quality, reset_counter policy, TIMESYNC filter."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robotd.autopilot import (
    DIAG_INDEX,
    CovarianceFloors,
    ResetCounterPolicy,
    ResetEvent,
    TimesyncFilter,
    VelocityFromPoses,
    cov6_to_upper21,
    odometry_fields,
    position_sigma_m,
    quality_from,
    upper21_to_cov6,
    vision_position_fields,
)
from robotd.geometry import euler_to_R, quat_to_R
from robotd.msgs import PoseEstimate, StepResult, UpdateReport
from robotd.outputs import pose_quality
from tests.support.tolerances import ROUNDOFF_ATOL


def pose(xyz=(0.0, 0.0, 0.0), rpy=(0.0, 0.0, 0.0), t_ns=1_000_000_000, cov=None) -> PoseEstimate:
    return PoseEstimate(
        t_ns, np.array(xyz, float), np.array(rpy, float), np.eye(6) * 0.01 if cov is None else np.asarray(cov)
    )


def test_hand_test() -> None:
    # interfaces.md §1.3 and §6.1: forward +x, right +y, lifting decreases z, identity q = [1,0,0,0]
    f = odometry_fields(pose(), 50, 0)
    assert f.q == (1.0, 0.0, 0.0, 0.0)
    assert (f.frame_id, f.child_frame_id) == (20, 12)
    assert odometry_fields(pose((1.0, 0, 0)), 50, 0).x == 1.0
    assert odometry_fields(pose((0, 1.0, 0)), 50, 0).y == 1.0
    assert odometry_fields(pose((0, 0, -0.3)), 50, 0).z == -0.3  # lifted 0.3 m: z goes down
    # a right turn (positive FRD yaw) maps body forward onto local +y
    q = odometry_fields(pose(rpy=(0, 0, math.pi / 2)), 50, 0).q
    assert quat_to_R(np.array(q)) @ np.array([1.0, 0, 0]) == pytest.approx([0, 1, 0], abs=ROUNDOFF_ATOL)


def test_quaternion_is_ZYX_rpy_and_normalised(rng: np.random.Generator) -> None:
    for _ in range(200):
        rpy = rng.uniform([-1.5, -1.4, -math.pi], [1.5, 1.4, math.pi])
        f = odometry_fields(pose(rpy=rpy), 50, 0)
        q = np.array(f.q)
        assert np.linalg.norm(q) == pytest.approx(1.0, abs=ROUNDOFF_ATOL)
        assert q[0] >= 0
        assert quat_to_R(q) == pytest.approx(euler_to_R(rpy), abs=ROUNDOFF_ATOL)
        assert f.time_usec == 1_000_000
        v = vision_position_fields(pose(rpy=rpy), 3)
        assert (v.roll, v.pitch, v.yaw) == pytest.approx(tuple(rpy))


def test_covariance_upper_triangle_layout() -> None:
    c = np.arange(36, dtype=float).reshape(6, 6)
    c = c + c.T + np.diag([100.0] * 6)  # symmetric, distinct entries
    v = cov6_to_upper21(c)
    assert len(v) == 21
    assert [v[i] for i in DIAG_INDEX] == pytest.approx(np.diag(c))
    assert v[1] == c[0, 1] and v[5] == c[0, 5] and v[7] == c[1, 2] and v[19] == c[4, 5]
    assert upper21_to_cov6(v) == pytest.approx(c)


def test_covariance_floor_never_zero_and_nan_unknown() -> None:
    f = odometry_fields(pose(cov=np.zeros((6, 6))), 50, 0, floors=CovarianceFloors(1e-4, 4e-4))
    diag = [f.pose_covariance[i] for i in DIAG_INDEX]
    assert diag == pytest.approx([1e-4] * 3 + [4e-4] * 3)
    assert all(d > 0 for d in diag)
    # ArduPilot's posErr / angErr stay positive
    c = f.pose_covariance
    assert np.cbrt(c[0] ** 2 + c[6] ** 2 + c[11] ** 2) > 0 and np.cbrt(c[15] ** 2 + c[18] ** 2 + c[20] ** 2) > 0
    # velocity covariance unknown: NaN first
    assert math.isnan(f.velocity_covariance[0]) and len(f.velocity_covariance) == 21
    assert math.isnan(f.rollspeed) and math.isnan(f.yawspeed)
    big = odometry_fields(pose(cov=np.eye(6) * 2.0), 50, 0)
    assert [big.pose_covariance[i] for i in DIAG_INDEX] == pytest.approx([2.0] * 6)
    bad = np.eye(6)
    bad[0, 0] = np.inf
    assert math.isnan(cov6_to_upper21(bad)[0])


def test_quality() -> None:
    assert quality_from(False, 500) == -1
    assert quality_from(True, 0) == 1  # tracked but poor: worst, not "unknown"
    assert quality_from(True, 60) == 100
    assert quality_from(True, 60, neff=50.0, n_particles=100) == round(1 + 99 * 0.5)
    q = [quality_from(True, n) for n in range(0, 80, 5)]
    assert q == sorted(q) and min(q) >= 1 and max(q) <= 100
    assert odometry_fields(pose(), 250, 0).quality == 100
    assert odometry_fields(pose(), -1, 0).quality == -1


def test_quality_reflects_the_reported_covariance_and_the_monitor() -> None:
    # docs/mavlink.md §5: q_σ = min(1, good / σ) with σ = √trace of the position block
    full = dict(neff=50.0, n_particles=50)
    assert quality_from(True, 60, **full, pos_sigma_m=0.1, good_sigma_m=0.2) == 100  # better than good: no loss
    assert quality_from(True, 60, **full, pos_sigma_m=0.2, good_sigma_m=0.2) == 100
    assert quality_from(True, 60, **full, pos_sigma_m=0.8, good_sigma_m=0.2) == round(1 + 99 * 0.25)
    assert quality_from(True, 60, **full, pos_sigma_m=math.inf) == 1  # a covariance that says nothing
    sig = [quality_from(True, 60, **full, pos_sigma_m=s) for s in (0.05, 0.3, 1.0, 3.0, 30.0)]
    assert sig == sorted(sig, reverse=True) and sig[0] == 100 and sig[-1] == 2  # 1 + 99 · 0.2/30
    # the monitor: "ok" changes nothing, "overconfident" multiplies by 1 / NIS ratio
    assert quality_from(True, 60, consistency_state="ok", nis_ratio=1.9) == 100
    assert quality_from(True, 60, consistency_state="overconfident", nis_ratio=4.0) == round(1 + 99 / 4)
    assert quality_from(True, 60, consistency_state="overconfident") == round(1 + 99 / 2)  # ratio unknown
    # lost stays lost, whatever the covariance
    assert quality_from(False, 60, pos_sigma_m=0.01) == -1


def test_pose_quality_takes_the_step_results_covariance_and_monitor() -> None:
    cov = np.diag([0.09, 0.04, 0.03, 1e-4, 1e-4, 4e-4])  # σ = √0.16 = 0.4 m
    p = PoseEstimate(1_000, np.zeros(3), np.zeros(3), cov, neff=40.0, n_particles=50)
    assert position_sigma_m(cov) == pytest.approx(0.4)
    res = StepResult(1_000, p, UpdateReport(), counts={"identified": 60}, consistency={"state": "ok", "nis_ratio": 0.6})
    assert pose_quality(res, 6, good_sigma_m=0.2) == round(1 + 99 * 0.8 * 0.5)
    assert pose_quality(res, 6, good_sigma_m=0.4) == round(1 + 99 * 0.8)
    over = StepResult(
        1_000, p, UpdateReport(), counts={"identified": 60}, consistency={"state": "overconfident", "nis_ratio": 5.0}
    )
    assert pose_quality(over, 6, good_sigma_m=0.4) == round(1 + 99 * 0.8 / 5.0)
    lost = StepResult(1_000, p, UpdateReport(), counts={"identified": 60}, tracking=False)
    assert pose_quality(lost, 6) == -1


def test_reset_counter_policy() -> None:
    pol = ResetCounterPolicy()
    dt = 100_000_000
    # smooth motion at 1 m/s and 0.5 rad/s: never bumps
    for k in range(30):
        assert pol.update(pose((0.1 * k, 0, 0), (0, 0, 0.05 * k), t_ns=k * dt)) == 0
    # 0.05 m beyond the constant-velocity prediction: explained, no bump
    k = 30
    assert pol.update(pose((0.1 * k + 0.05, 0, 0), (0, 0, 0.05 * k), t_ns=k * dt)) == 0
    # 0.3 m jump: bump
    k = 31
    assert pol.update(pose((0.1 * k + 0.35, 0, 0), (0, 0, 0.05 * k), t_ns=k * dt)) == 1
    # events bump regardless of motion
    assert pol.update(pose((3.5, 0, 0), (0, 0, 1.6), t_ns=32 * dt), ResetEvent.RELOCALISATION) == 2
    assert pol.update(pose((3.5, 0, 0), (0, 0, 1.6), t_ns=33 * dt), ResetEvent.MAP_LOAD) == 3
    # an external prediction (odometry) overrides the constant-velocity one
    assert pol.update(pose((3.9, 0, 0), (0, 0, 1.6), t_ns=34 * dt), predicted_xyz=np.array([3.85, 0, 0])) == 3
    # yaw jump
    assert pol.update(pose((3.9, 0, 0), (0, 0, 2.2), t_ns=35 * dt)) == 4
    pol.counter = 255
    assert pol.update(pose(t_ns=36 * dt), ResetEvent.FILTER_RESTART) == 0  # uint8 wraps


def test_velocity_from_poses() -> None:
    vp = VelocityFromPoses()
    yaw = math.pi / 2  # facing local +y
    assert vp.update(pose((0, 0, 0), (0, 0, yaw), t_ns=0), 0) == pytest.approx([0, 0, 0])
    v = vp.update(pose((0, 0.2, 0), (0, 0, yaw), t_ns=100_000_000), 0)
    assert v == pytest.approx([2.0, 0, 0], abs=ROUNDOFF_ATOL)  # moving forward in the body frame
    # across a reset the last good value is held
    assert vp.update(pose((5, 5, 0), (0, 0, yaw), t_ns=200_000_000), 1) == pytest.approx([2.0, 0, 0])


def test_timesync_filter_picks_shortest_round_trip(rng: np.random.Generator) -> None:
    tf = TimesyncFilter(window=64)
    true_offset = -7_000_000_000  # autopilot booted 7 s after the host clock's zero... any value
    t = 10_000_000_000
    for _ in range(64):
        up = int(rng.uniform(0.2e6, 5e6))  # asymmetric random delays
        down = int(rng.uniform(0.2e6, 5e6))
        t0 = t
        tc1 = t0 + up + true_offset
        t1 = t0 + up + down
        assert tf.add(t0, t1, tc1)
        t += 50_000_000
    assert tf.rtt_ns is not None
    assert tf.offset_ns is not None
    # the error of the best sample is at most half its round trip
    assert abs(tf.offset_ns - true_offset) <= tf.rtt_ns / 2
    assert tf.autopilot_to_host(5_000_000_000) == 5_000_000_000 - tf.offset_ns
    assert not tf.add(100, 50, 10)  # negative round trip
    assert not tf.add(0, 10**9, 10)  # 1 s round trip
    assert tf.rejected == 2
    tf.reset()
    assert tf.offset_ns is None
