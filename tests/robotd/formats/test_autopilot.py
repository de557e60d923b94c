"""Pose -> ODOMETRY field values, covariance layout, quality, reset_counter policy, TIMESYNC filter."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robotd.core.geometry import euler_to_R, quat_to_R
from robotd.core.msgs import MotionIncrement, PoseEstimate, StepResult, UpdateReport
from robotd.formats.autopilot import (
    DIAG_INDEX,
    CovarianceFloors,
    ResetCounterPolicy,
    ResetEvent,
    TimesyncFilter,
    cov6_to_upper21,
    odometry_fields,
    position_sigma_m,
    quality_from,
    upper21_to_cov6,
    vision_position_fields,
)
from robotd.outputs import pose_quality
from tests.support.tolerances import ROUNDOFF_ATOL


def pose(xyz=(0.0, 0.0, 0.0), rpy=(0.0, 0.0, 0.0), t_ns=1_000_000_000, cov=None) -> PoseEstimate:
    return PoseEstimate(
        t_ns, np.array(xyz, float), np.array(rpy, float), np.eye(6) * 0.01 if cov is None else np.asarray(cov)
    )


def test_hand_test() -> None:
    # docs/interfaces.md §1.3 and §6 item 1: forward +x, right +y, lifting decreases z, identity q = [1,0,0,0]
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


def drive(speed_mps: float, hz: float, seconds: float, rng: np.random.Generator, noise: bool = True):
    """Poses of a car published at ``hz``: it accelerates from rest at 2 m/s² to ``speed_mps``,
    then weaves (yaw rate up to what 2.5 m/s² of lateral acceleration allows, at most 0.8 rad/s)
    while its speed swings ±15 %; pose noise σ 1 cm and 0.1° like a tracked SLAM pose.
    Returns (poses, true body velocities)."""
    dt_sim = 1e-3
    n_sim = int(seconds / dt_sim)
    x = y = yaw = v = 0.0
    t_pub = 0.0
    poses, vels = [], []
    for k in range(n_sim + 1):
        t = k * dt_sim
        target = speed_mps * (1.0 + 0.15 * math.sin(0.7 * t))
        v = min(target, v + 2.0 * dt_sim) if v < target else max(target, v - 2.0 * dt_sim)
        w = min(0.8, 2.5 / max(speed_mps, 0.5)) * math.sin(0.9 * t) * min(1.0, v / speed_mps)
        if t >= t_pub - 1e-9:
            e = rng.normal(0.0, 0.01, 3) if noise else np.zeros(3)
            eyaw = float(rng.normal(0.0, math.radians(0.1))) if noise else 0.0
            # reported with the σ of the noise added (1 cm, 0.1°): a tracked pose's
            cov = np.diag([1e-4] * 3 + [math.radians(0.1) ** 2] * 3)
            poses.append(pose((x + e[0], y + e[1], e[2]), (0.0, 0.0, yaw + eyaw), t_ns=round(t * 1e9) + 10**9, cov=cov))
            vels.append(np.array([v, 0.0, 0.0]))
            t_pub += 1.0 / hz
        x += v * math.cos(yaw) * dt_sim
        y += v * math.sin(yaw) * dt_sim
        yaw += w * dt_sim
    return poses, vels


def shifted(p: PoseEstimate, dxyz: np.ndarray, dyaw: float = 0.0) -> PoseEstimate:
    return pose(p.xyz_W_m + dxyz, p.rpy_rad + np.array([0.0, 0.0, dyaw]), t_ns=p.t_ns, cov=p.cov)


@pytest.mark.parametrize("sigma_m", [0.05, 0.3])
def test_a_correction_within_the_last_poses_reported_sigma_is_no_jump(sigma_m: float, rng) -> None:
    # a pose sent with a wide covariance (one handed over after a restart: σ 0.29 m for a 4.8 s
    # gap) then converging 0.26 m in one step: the autopilot fused the wide pose with that σ and
    # takes the correction inside its innovation gate, so it is no discontinuity; the same 0.26 m
    # after a pose that claimed 5 cm is one
    poses, _ = drive(2.0, 30.0, 4.0, rng)
    k = 60
    wide = np.diag([sigma_m**2 / 3] * 3 + [math.radians(0.1) ** 2] * 3)  # trace: σ²
    stream = [*poses[: k - 1], pose(poses[k - 1].xyz_W_m, poses[k - 1].rpy_rad, poses[k - 1].t_ns, wide)]
    stream += [shifted(p, np.array([0.0, 0.26, 0.0])) for p in poses[k:]]
    pol = ResetCounterPolicy()
    counters = [pol.update(p) for p in stream]
    assert pol.bumps == (1 if sigma_m < 0.1 else 0), pol.last_reason
    assert counters[-1] == pol.bumps


SPEEDS = (0.5, 2.0, 5.0, 10.0)
RATES = (5.0, 10.0, 15.0, 30.0)


@pytest.mark.parametrize("hz", RATES)
@pytest.mark.parametrize("speed", SPEEDS)
def test_reset_counter_never_bumps_on_smooth_motion(speed: float, hz: float, rng: np.random.Generator) -> None:
    poses, vels = drive(speed, hz, 20.0, rng)
    pol = ResetCounterPolicy()
    counters = [pol.update(p) for p in poses]
    assert pol.bumps == 0, pol.last_reason
    assert set(counters) == {0}
    # ODOMETRY's velocity is the vehicle's, within the lag of the fit
    assert pol.velocity_R[0] == pytest.approx(vels[-1][0], rel=0.1, abs=0.1)


@pytest.mark.parametrize("hz", RATES)
@pytest.mark.parametrize("speed", SPEEDS)
def test_one_jump_bumps_once_and_the_velocity_goes_on(speed: float, hz: float, rng: np.random.Generator) -> None:
    # a correction of the whole pose stream by 1 m sideways at 10 s (a relocalisation the pipeline
    # did not flag): the counter bumps once, the motion after it is smooth again, and ODOMETRY's
    # velocity is the vehicle's before, across and after it (the old policy predicted no motion
    # after a bump, so at 10 cm per pose or more it bumped at every pose from then on)
    poses, vels = drive(speed, hz, 16.0, rng)
    k_jump = int(10.0 * hz)
    jump = np.array([0.3, 1.0, 0.0])
    stream = poses[:k_jump] + [shifted(p, jump) for p in poses[k_jump:]]
    pol = ResetCounterPolicy()
    counters = []
    for k, p in enumerate(stream):
        counters.append(pol.update(p))
        if k / hz > speed / 2.0 + 1.0:  # once up to speed (the fit lags an acceleration by ~0.1 s;
            # 0.35 m/s is 5 σ of the fit with 1 cm pose noise at 10 Hz)
            assert pol.velocity_R[0] == pytest.approx(vels[k][0], rel=0.1, abs=0.35), f"pose {k}"
    assert counters[:k_jump] == [0] * k_jump
    assert counters[k_jump:] == [1] * (len(stream) - k_jump), pol.last_reason
    assert pol.bumps == 1 and pol.last_reason.startswith("jump")


def test_reset_counter_events_yaw_jumps_and_wrap(rng: np.random.Generator) -> None:
    poses, _ = drive(2.0, 10.0, 4.0, rng, noise=False)
    pol = ResetCounterPolicy()
    for p in poses:
        assert pol.update(p) == 0
    t = poses[-1].t_ns
    step = 100_000_000
    # events bump whatever the motion
    last = poses[-1]
    assert pol.update(pose(last.xyz_W_m, last.rpy_rad, t_ns=t + step), ResetEvent.RELOCALISATION) == 1
    assert pol.last_reason == ResetEvent.RELOCALISATION
    assert pol.update(pose(last.xyz_W_m, last.rpy_rad, t_ns=t + 2 * step), ResetEvent.MAP_LOAD) == 2
    # a yaw jump of 0.5 rad with the position on its prediction
    pred = pol.predict(t + 3 * step)
    assert pred is not None
    yaw = float(np.arctan2(pred[1][1, 0], pred[1][0, 0]))
    assert pol.update(pose(pred[0], (0.0, 0.0, yaw + 0.5), t_ns=t + 3 * step)) == 3
    assert "deg" in pol.last_reason
    pol.counter = 255
    assert pol.update(pose(t_ns=t + 4 * step), ResetEvent.FILTER_RESTART) == 0  # uint8 wraps
    # every bump with its reason, for the health topic's reset_bumps
    hist = list(pol.history)
    assert [c for c, _ in hist] == [1, 2, 3, 0]
    assert [why for _, why in hist][:2] == [ResetEvent.RELOCALISATION, ResetEvent.MAP_LOAD]
    assert "deg" in hist[2][1] and hist[3][1] == ResetEvent.FILTER_RESTART


def test_a_gap_in_the_poses_starts_a_new_segment(rng: np.random.Generator) -> None:
    poses, _ = drive(2.0, 10.0, 6.0, rng)
    pol = ResetCounterPolicy()
    for p in poses[:30]:
        assert pol.update(p) == 0
    # 1.5 s without a pose (a stall, a lost link): the next one is a new segment, however plausible
    assert pol.update(poses[45]) == 1 and pol.last_reason.startswith("gap 1.")
    assert [pol.update(p) for p in poses[46:]] == [1] * len(poses[46:])


def test_no_jump_test_before_the_motion_is_known() -> None:
    # a daemon resumed on a moving rover: its first poses come at speed, with no twist yet
    pol = ResetCounterPolicy()
    assert pol.update(pose((0, 0, 0), t_ns=10**9), ResetEvent.MAP_LOAD) == 1
    assert pol.predict(10**9 + 10**8) is None
    # 10 m/s at 10 Hz: 1 m per pose, from the second pose on
    for k in range(1, 20):
        assert pol.update(pose((1.0 * k, 0, 0), t_ns=10**9 + k * 10**8)) == 1
    assert pol.velocity_R == pytest.approx([10.0, 0.0, 0.0])


def test_odometry_is_the_prediction_when_it_covers_the_interval() -> None:
    pol = ResetCounterPolicy()
    step = 100_000_000
    for k in range(5):  # standing still: the twist is zero
        pol.update(pose((0, 0, 0), t_ns=10**9 + k * step))
    t0, t1 = 10**9 + 4 * step, 10**9 + 5 * step

    def inc(dx: float) -> MotionIncrement:
        return MotionIncrement(t0, t1, np.array([dx, 0.0, 0.0]), np.zeros(3), np.eye(6) * 1e-4)

    # the wheels say it moved 0.5 m in 0.1 s (a sudden start the still twist cannot know): no bump
    pred = pol.predict(t1, inc(0.5))
    assert pred is not None and pred[0] == pytest.approx([0.5, 0.0, 0.0])
    assert pol.update(pose((0.5, 0, 0), t_ns=t1), odometry=inc(0.5)) == 0
    # without the odometry the same pose is a jump against the still twist
    pol2 = ResetCounterPolicy()
    for k in range(5):
        pol2.update(pose((0, 0, 0), t_ns=10**9 + k * step))
    assert pol2.update(pose((0.5, 0, 0), t_ns=t1)) == 1
    # an increment of another interval is not used
    pol3 = ResetCounterPolicy()
    for k in range(5):
        pol3.update(pose((0, 0, 0), t_ns=10**9 + k * step))
    other = MotionIncrement(t0 - step, t1, np.array([0.5, 0.0, 0.0]), np.zeros(3), np.eye(6))
    assert pol3.update(pose((0.5, 0, 0), t_ns=t1), odometry=other) == 1


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
