"""drivers/rover_physics.py: the kinematic bicycle, the SITL JSON protocol over loopback UDP, the
truth stream, the command line, and the whole loop against ArduPilot's own SITL (skipped where the
binary is absent). Time is simulated time throughout: nothing here asserts on the wall clock."""

from __future__ import annotations

import itertools
import json
import logging
import math
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from drivers.rover_physics import (
    GRAVITY_MPS2,
    TRUTH,
    JsonPhysicsServer,
    RoverModel,
    RoverParams,
    RoverState,
    TruthSample,
    decode_truth,
    encode_servo_packet,
    encode_truth,
    main,
)
from robotd.core.errors import DriverError
from tests.support.paths import REPO
from tests.support.tolerances import CONDITIONED_ATOL, CONDITIONED_RTOL, ROUNDOFF_ATOL

RATE_HZ = 1200  # SITL's JSON frame rate for the rover (SIM_RATE_HZ), measured
DT = 1.0 / RATE_HZ
IO_TIMEOUT_S = 10.0  # bounds a hang on a lost datagram; never a timing assertion

# the central difference of velocity at 1/1200 s against the reported specific force: truncation
# dt²/6·|d³v/dt³| ≲ 1e-5 m/s² for these inputs (τ = 0.4 s, v ≤ 3 m/s, |r| ≤ 6 rad/s); a wrong sign
# or a missing term is O(0.1..10) m/s²
DIFF_ACCEL_ATOL = 1e-4


def run(model: RoverModel, steer: int, throttle: int, seconds: float, dt: float = DT) -> list[RoverState]:
    model.set_controls(steer, throttle)
    out = []
    for _ in range(round(seconds / dt)):
        model.step(dt)
        out.append(model.state())
    return out


def positions(states: list[RoverState]) -> np.ndarray:
    return np.array([s.position_ned_m for s in states])


# -- the model ------------------------------------------------------------------------------------


def test_full_and_part_throttle_reach_their_speeds_along_the_start_heading() -> None:
    yaw0 = math.radians(30.0)
    for throttle, v_expected in ((2000, 3.0), (1750, 1.5), (1250, -1.5), (1000, -3.0)):
        m = RoverModel(RoverParams(start_north_m=2.0, start_east_m=-1.0, start_yaw_rad=yaw0))
        states = run(m, 1500, throttle, 8.0)  # 20 time constants
        s = states[-1]
        assert math.hypot(*s.velocity_ned_mps[:2]) == pytest.approx(abs(v_expected), rel=1e-6)
        assert m.speed_mps == pytest.approx(v_expected, rel=1e-6)
        # a straight line along the start heading, forward or back, as far as ∫v dt says
        d = positions(states)[:, :2] - [2.0, -1.0]
        along = d @ [math.cos(yaw0), math.sin(yaw0)]
        across = d @ [-math.sin(yaw0), math.cos(yaw0)]
        tau = m.params.speed_tau_s
        t = 8.0
        distance = v_expected * (t - tau * (1 - math.exp(-t / tau)))
        assert along[-1] == pytest.approx(distance, rel=CONDITIONED_RTOL)
        assert np.abs(across).max() < CONDITIONED_ATOL
        assert s.attitude_rad == pytest.approx((0.0, 0.0, yaw0), abs=ROUNDOFF_ATOL)
        assert s.position_ned_m[2] == 0.0 and s.velocity_ned_mps[2] == 0.0


def _fit_circle(xy: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares circle (Kåsa): x² + y² = 2a x + 2b y + c; centre (a, b), radius √(c + a² + b²)."""
    A = np.column_stack([2 * xy[:, 0], 2 * xy[:, 1], np.ones(len(xy))])
    (a, b, c), *_ = np.linalg.lstsq(A, (xy**2).sum(axis=1), rcond=None)
    return np.array([a, b]), float(np.sqrt(c + a * a + b * b))


@pytest.mark.parametrize(("steer", "throttle"), [(1750, 1700), (1250, 1700), (1900, 1300)])
def test_a_constant_steering_angle_draws_a_circle_of_radius_wheelbase_over_tan_delta(steer: int, throttle: int) -> None:
    p = RoverParams(start_yaw_rad=math.radians(-50.0))
    m = RoverModel(p)
    states = run(m, steer, throttle, 12.0)
    delta = (steer - 1500) / 500 * math.radians(p.max_steer_deg)
    radius = p.wheelbase_m / math.tan(abs(delta))
    centre, r_fit = _fit_circle(positions(states)[:, :2])
    assert r_fit == pytest.approx(radius, rel=CONDITIONED_RTOL)
    # the centre is on the side the wheels point to (steer > 1500: right of the start heading)
    right = np.array([-math.sin(p.start_yaw_rad), math.cos(p.start_yaw_rad)])
    assert centre @ right == pytest.approx(math.copysign(radius, delta), rel=CONDITIONED_RTOL)
    # yaw turns clockwise (NED) for a right turn forward, and the other way in reverse
    v = m.speed_mps
    assert np.sign(states[-1].rates_frd_radps[2]) == np.sign(delta * v)
    assert states[-1].rates_frd_radps[2] == pytest.approx(v / radius * np.sign(delta), rel=1e-9)


def test_one_long_step_equals_many_short_ones() -> None:
    a, b = RoverModel(), RoverModel()
    for steer, throttle in ((1700, 1800), (1300, 1600), (1500, 1200)):
        a.set_controls(steer, throttle)
        b.set_controls(steer, throttle)
        for _ in range(600):
            a.step(DT)
        b.step(600 * DT)
        sa, sb = a.state(0), b.state(0)
        fields_a = sa.position_ned_m + sa.attitude_rad + sa.velocity_ned_mps
        fields_b = sb.position_ned_m + sb.attitude_rad + sb.velocity_ned_mps
        assert fields_a == pytest.approx(fields_b, abs=CONDITIONED_ATOL)


def test_specific_force_and_gyro_agree_with_the_kinematics() -> None:
    m = RoverModel(RoverParams(start_yaw_rad=1.0))
    controls = [(1500, 1900), (1800, 1900), (1200, 1700), (1650, 1300), (1500, 1500), (1950, 2000)]
    t, vel, yaw, acc, gyro = [], [], [], [], []
    for steer, throttle in controls:
        for s in run(m, steer, throttle, 1.0):
            t.append(s.t_sim_s)
            vel.append(s.velocity_ned_mps)
            yaw.append(s.attitude_rad[2])
            acc.append(s.accel_frd_mps2)
            gyro.append(s.rates_frd_radps)
    t_s, v_ned, psi = np.array(t), np.array(vel), np.unwrap(np.array(yaw))
    f, w = np.array(acc), np.array(gyro)
    # central differences, away from the instants where the inputs change (the derivative jumps there)
    n = len(t_s)
    k = np.arange(1, n - 1)
    per = round(1.0 / DT)
    k = k[(k % per > 1) & (k % per < per - 2)]
    dv = (v_ned[k + 1] - v_ned[k - 1]) / (t_s[k + 1] - t_s[k - 1])[:, None]
    cos, sin = np.cos(psi[k]), np.sin(psi[k])
    a_body = np.column_stack([cos * dv[:, 0] + sin * dv[:, 1], -sin * dv[:, 0] + cos * dv[:, 1], dv[:, 2]])
    gravity_body = np.array([0.0, 0.0, GRAVITY_MPS2])  # level: body z is down
    assert np.abs(f[k] + gravity_body - a_body).max() < DIFF_ACCEL_ATOL
    assert np.abs(f[k, 1]).max() > 1.0  # the lateral term was exercised
    dpsi = (psi[k + 1] - psi[k - 1]) / (t_s[k + 1] - t_s[k - 1])
    assert np.abs(w[k, 2] - dpsi).max() < DIFF_ACCEL_ATOL
    assert np.all(w[:, :2] == 0.0)


@pytest.mark.parametrize(("steer", "throttle"), [(1500, 1500), (0, 0), (1900, 0), (0, 1500)])
def test_neutral_and_no_output_keep_it_still(steer: int, throttle: int) -> None:
    p = RoverParams(start_north_m=5.0, start_east_m=7.0, start_yaw_rad=2.0)
    m = RoverModel(p)
    for s in run(m, steer, throttle, 2.0):
        assert s.position_ned_m == (5.0, 7.0, 0.0)
        assert s.velocity_ned_mps == (0.0, 0.0, 0.0)
        assert s.rates_frd_radps == (0.0, 0.0, 0.0)
        assert s.accel_frd_mps2 == (0.0, 0.0, -GRAVITY_MPS2)
        assert s.attitude_rad == pytest.approx((0.0, 0.0, 2.0), abs=ROUNDOFF_ATOL)


@pytest.mark.parametrize("steer", [0, 500, 2500, 1000, 2000])
@pytest.mark.parametrize("throttle", [0, 500, 2500])
def test_extreme_pwm_values_stay_finite_and_bounded(steer: int, throttle: int) -> None:
    m = RoverModel()
    states = run(m, steer, throttle, 3.0)
    values = np.array([s.position_ned_m + s.velocity_ned_mps + s.rates_frd_radps + s.accel_frd_mps2 for s in states])
    assert np.all(np.isfinite(values))
    assert abs(m.speed_mps) <= m.params.max_speed_mps
    expected = {0: 0.0, 500: -3.0, 2500: 3.0}[throttle]  # clamped to 1000..2000 µs; 0 is neutral
    assert m.speed_mps == pytest.approx(expected, abs=0.01)


def test_reset_returns_to_the_start_pose_at_rest() -> None:
    p = RoverParams(start_north_m=-3.0, start_east_m=4.0, start_yaw_rad=math.radians(200.0))
    m = RoverModel(p)
    s0 = m.state()
    assert s0.position_ned_m == (-3.0, 4.0, 0.0)
    assert s0.attitude_rad[2] == pytest.approx(math.radians(200.0) - 2 * math.pi)  # wrapped to [−π, π)
    run(m, 1800, 1900, 2.0)
    m.reset(0.0)
    s1 = m.state()
    assert (s1.t_sim_s, s1.position_ned_m, s1.velocity_ned_mps, s1.attitude_rad) == (
        0.0,
        s0.position_ned_m,
        (0.0, 0.0, 0.0),
        s0.attitude_rad,
    )
    assert m.state().accel_frd_mps2 == (0.0, 0.0, -GRAVITY_MPS2)  # neutral inputs after a reset


def test_imu_noise_is_off_by_default_and_has_its_sigma_when_on() -> None:
    m = RoverModel()
    s = m.state()
    assert m.imu(s) == (s.rates_frd_radps, s.accel_frd_mps2)
    noisy = RoverModel(RoverParams(gyro_noise_radps=0.01, accel_noise_mps2=0.2), rng=np.random.default_rng(7))
    s = noisy.state()
    draws = [noisy.imu(s) for _ in range(4000)]
    g = np.array([d[0] for d in draws])
    a = np.array([d[1] for d in draws]) - s.accel_frd_mps2
    # 4000 draws: the sample σ is within ±4 % of σ at > 4 standard errors (σ/√(2n) ≈ 1.1 %)
    assert np.std(g, axis=0) == pytest.approx([0.01] * 3, rel=0.05)
    assert np.std(a, axis=0) == pytest.approx([0.2] * 3, rel=0.05)
    assert noisy.state().accel_frd_mps2 == (0.0, 0.0, -GRAVITY_MPS2)  # the truth stays noise-free


def test_params_are_checked() -> None:
    with pytest.raises(ValueError, match="wheelbase_m = 0"):
        RoverParams(wheelbase_m=0)
    with pytest.raises(ValueError, match="max_steer_deg"):
        RoverParams(max_steer_deg=90)
    with pytest.raises(ValueError, match="start_north_m"):
        RoverParams(start_north_m=math.nan)
    with pytest.raises(ValueError, match="dt_s"):
        RoverModel().step(-1e-3)


# -- the JSON protocol over loopback UDP -----------------------------------------------------------


class FakeSitl:
    """What SITL does on the wire: one UDP socket that sends servo datagrams and reads the answers."""

    def __init__(self, server: tuple[str, int]) -> None:
        self.server = server
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(IO_TIMEOUT_S)

    def send(self, frame_count: int, steer: int = 1500, throttle: int = 1500, n: int = 16) -> bytes:
        pwm = [1500] * n
        pwm[0], pwm[2] = steer, throttle
        self.sock.sendto(encode_servo_packet(RATE_HZ, frame_count, pwm), self.server)
        return self.sock.recv(4096)

    def doc(self, frame_count: int, **kw: Any) -> dict[str, Any]:
        raw = self.send(frame_count, **kw)
        return json.loads(raw.strip(b"\n"))

    def close(self) -> None:
        self.sock.close()


@pytest.fixture
def server() -> Iterator[JsonPhysicsServer]:
    with JsonPhysicsServer(
        RoverModel(RoverParams(start_north_m=1.0, start_east_m=2.0)), listen=("127.0.0.1", 0)
    ) as srv:
        yield srv


@pytest.fixture
def sitl(server: JsonPhysicsServer) -> Iterator[FakeSitl]:
    fake = FakeSitl(server.address)
    yield fake
    fake.close()


@pytest.mark.parametrize("n_servos", [16, 32])
def test_the_answer_is_one_line_of_compact_json_between_newlines(sitl: FakeSitl, n_servos: int) -> None:
    raw = sitl.send(0, n=n_servos)
    assert raw.startswith(b"\n") and raw.endswith(b"\n") and raw.count(b"\n") == 2
    assert b" " not in raw  # SITL's parser wants "key":[a,b,c]
    doc = json.loads(raw[1:-1])
    assert set(doc) == {"timestamp", "imu", "position", "attitude", "velocity"}
    assert set(doc["imu"]) == {"gyro", "accel_body"}
    for v in (doc["imu"]["gyro"], doc["imu"]["accel_body"], doc["position"], doc["attitude"], doc["velocity"]):
        assert len(v) == 3 and all(isinstance(x, float) for x in v)
    assert doc["timestamp"] == 0.0
    assert doc["position"] == [1.0, 2.0, 0.0]
    assert doc["imu"]["accel_body"] == [0.0, 0.0, -GRAVITY_MPS2]
    # both magics drive the model: SERVO1 steers, SERVO3 throttles
    for k in range(1, 601):
        doc = sitl.doc(k, steer=1800, throttle=1900, n=n_servos)
    assert doc["timestamp"] == pytest.approx(600 / RATE_HZ, abs=ROUNDOFF_ATOL)
    assert doc["position"][0] > 1.1 and doc["position"][1] > 2.0  # forward (north), turning right (east)
    assert doc["imu"]["gyro"][2] > 0.5


def test_frames_advance_time_by_their_count_and_hold_the_previous_inputs(
    server: JsonPhysicsServer, sitl: FakeSitl
) -> None:
    ref = RoverModel(server.model.params)
    docs = [sitl.doc(k, steer=1700, throttle=1800) for k in range(5)]
    assert [d["timestamp"] for d in docs] == pytest.approx([k / RATE_HZ for k in range(5)], abs=ROUNDOFF_ATOL)
    jump = sitl.doc(12, steer=1500, throttle=1500)  # 8 frames later: one exact step of 8/rate
    ref.set_controls(1700, 1800)
    ref.step(12 / RATE_HZ)  # 0 → 12/rate with the inputs of frames 0..4 (frame 4's held across the gap)
    assert jump["timestamp"] == pytest.approx(12 / RATE_HZ, abs=ROUNDOFF_ATOL)
    assert jump["position"] == pytest.approx([ref.north_m, ref.east_m, 0.0], abs=CONDITIONED_ATOL)
    assert jump["attitude"][2] == pytest.approx(ref.yaw_rad, abs=CONDITIONED_ATOL)
    # frame 12's inputs (neutral) act from frame 12 on: the speed decays from here
    assert jump["imu"]["accel_body"][0] < 0
    st = server.stats()
    assert (st["steps"], st["skipped_frames"], st["resends"], st["restarts"], st["malformed"]) == (5, 7, 0, 0, 0)
    latest = server.latest()
    assert latest is not None and latest.t_sim_s == jump["timestamp"]
    assert list(latest.position_ned_m) == jump["position"]


def test_a_resend_is_answered_identically(server: JsonPhysicsServer, sitl: FakeSitl) -> None:
    for k in range(50):
        first = sitl.send(k, steer=1900, throttle=2000)
    again = [sitl.send(49, steer=1100, throttle=1000) for _ in range(3)]
    assert again == [first] * 3
    assert server.stats()["resends"] == 3 and server.stats()["steps"] == 49
    assert server.model.speed_cmd_mps == 3.0  # frame 49's full throttle still holds, not the resends' 1000 µs


def test_a_resend_repeats_the_imu_noise_too() -> None:
    noisy = RoverModel(RoverParams(gyro_noise_radps=0.1, accel_noise_mps2=0.1), rng=np.random.default_rng(3))
    with JsonPhysicsServer(noisy, listen=("127.0.0.1", 0)) as srv:
        fake = FakeSitl(srv.address)
        try:
            a, b, c = fake.send(0), fake.send(0), fake.send(1)
        finally:
            fake.close()
    assert a == b and a != c


def test_a_smaller_frame_count_restarts_at_the_start_pose_and_time_zero(
    server: JsonPhysicsServer, sitl: FakeSitl
) -> None:
    for k in range(1000, 1600):
        moved = sitl.doc(k, steer=1700, throttle=2000)
    assert moved["position"][0] > 1.3 and moved["timestamp"] == pytest.approx(1599 / RATE_HZ)
    doc = sitl.doc(0, steer=1500, throttle=1500)
    assert doc["timestamp"] == 0.0
    assert doc["position"] == [1.0, 2.0, 0.0] and doc["velocity"] == [0.0, 0.0, 0.0]
    assert doc["attitude"] == [0.0, 0.0, 0.0]
    assert sitl.doc(1)["timestamp"] == pytest.approx(DT, abs=ROUNDOFF_ATOL)
    assert server.stats()["restarts"] == 1


def test_malformed_datagrams_are_counted_logged_sparsely_and_not_answered(
    server: JsonPhysicsServer, sitl: FakeSitl, caplog: pytest.LogCaptureFixture
) -> None:
    good = encode_servo_packet(RATE_HZ, 0, [1500] * 16)
    bad = [
        good[:-1],  # wrong length for its magic
        good + b"\0\0",
        b"\x00\x00" + good[2:],  # unknown magic
        good[:2] + b"\0\0" + good[4:],  # frame rate 0
        b"",
        b"\x1aH",  # shorter than the header
    ]
    with caplog.at_level(logging.WARNING, logger="drivers.rover_physics"):
        for i in range(12):
            sitl.sock.sendto(bad[i % len(bad)], server.address)
        # datagrams from one socket arrive in order: the next answer is this frame's, so none of the
        # malformed ones was answered and the server is still serving
        assert sitl.doc(0)["timestamp"] == 0.0
    assert server.stats()["malformed"] == 12
    lines = [r.getMessage() for r in caplog.records if "malformed" in r.getMessage()]
    assert len(lines) == 2  # the 1st and the 10th
    assert "39 bytes with magic 18458: expected 40" in lines[0] and "(1 so far" in lines[0]
    assert "frame_rate_hz = 0: expected > 0" in lines[1] and "(10 so far" in lines[1]


def test_an_error_in_the_model_is_logged_and_the_server_goes_on(
    server: JsonPhysicsServer, sitl: FakeSitl, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    sitl.doc(0)
    step = server.model.step
    calls = []

    def failing_once(dt_s: float) -> None:
        calls.append(dt_s)
        if len(calls) == 1:
            raise RuntimeError("a bug")
        step(dt_s)

    monkeypatch.setattr(server.model, "step", failing_once)
    with caplog.at_level(logging.ERROR, logger="drivers.rover_physics"):
        sitl.sock.sendto(encode_servo_packet(RATE_HZ, 1, [1500] * 16), server.address)
        assert sitl.doc(2)["timestamp"] == pytest.approx(2 * DT)  # frame 1 was not answered; 2 is
    assert server.stats()["errors"] == 1
    assert any("not answered" in r.getMessage() and r.exc_info for r in caplog.records)


def test_answers_go_back_to_each_datagrams_source(server: JsonPhysicsServer) -> None:
    a, b = FakeSitl(server.address), FakeSitl(server.address)
    try:
        assert a.doc(0)["timestamp"] == 0.0
        assert b.doc(1)["timestamp"] == pytest.approx(DT)
        assert a.doc(2)["timestamp"] == pytest.approx(2 * DT)
    finally:
        a.close()
        b.close()


def test_the_server_refuses_a_remote_listen_address_and_a_busy_port(server: JsonPhysicsServer) -> None:
    with pytest.raises(DriverError, match="loopback only"):
        JsonPhysicsServer(listen=("0.0.0.0", 9002))
    with pytest.raises(DriverError, match=f"cannot listen on 127.0.0.1:{server.address[1]}"):
        JsonPhysicsServer(listen=server.address).start()


# -- the truth stream -------------------------------------------------------------------------------


def test_truth_round_trip() -> None:
    s = TruthSample(
        seq=4_000_000_000,
        t_sim_s=12.345,
        t_host_ns=1_234_567_890_123,
        position_ned_m=(1.5, -2.25, 0.0),
        attitude_rad=(0.0, -0.0, 3.1),
        velocity_ned_mps=(0.1, 0.2, 0.3),
        rates_frd_radps=(1e-9, 0.0, -0.7),
    )
    data = encode_truth(s)
    assert len(data) == TRUTH.size == 124 and data[:4] == b"RTRU"
    assert decode_truth(data) == s


def test_truth_decode_rejects_a_wrong_length_magic_or_version() -> None:
    data = encode_truth(TruthSample(1, 0.0, 0, (0.0,) * 3, (0.0,) * 3, (0.0,) * 3, (0.0,) * 3))
    with pytest.raises(ValueError, match="truth datagram of 123 bytes: expected 124"):
        decode_truth(data[:-1])
    with pytest.raises(ValueError, match="magic b'XTRU': expected b'RTRU'"):
        decode_truth(b"XTRU" + data[4:])
    with pytest.raises(ValueError, match="version 2: expected 1"):
        decode_truth(data[:4] + b"\x02\x00" + data[6:])


def _truth_receiver() -> socket.socket:
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.settimeout(IO_TIMEOUT_S)
    return rx


def test_the_truth_stream_carries_each_steps_state() -> None:
    rx = _truth_receiver()
    try:
        with JsonPhysicsServer(listen=("127.0.0.1", 0), truth_to=rx.getsockname(), truth_rate_hz=RATE_HZ) as srv:
            fake = FakeSitl(srv.address)
            try:
                t0 = time.monotonic_ns()
                docs = [fake.doc(k, steer=1650, throttle=1900) for k in range(100)]
                t1 = time.monotonic_ns()
            finally:
                fake.close()
            truths = [decode_truth(rx.recv(256)) for _ in range(100)]
    finally:
        rx.close()
    assert [t.seq for t in truths] == list(range(100))
    for d, t in zip(docs, truths):
        assert t.t_sim_s == d["timestamp"]
        assert list(t.position_ned_m) == d["position"] and list(t.velocity_ned_mps) == d["velocity"]
        assert list(t.attitude_rad) == d["attitude"] and list(t.rates_frd_radps) == d["imu"]["gyro"]
        assert t0 <= t.t_host_ns <= t1
    assert all(a.t_host_ns <= b.t_host_ns for a, b in itertools.pairwise(truths))


def test_the_truth_stream_is_decimated_to_at_least_its_rate() -> None:
    rx = _truth_receiver()
    try:
        with JsonPhysicsServer(listen=("127.0.0.1", 0), truth_to=rx.getsockname(), truth_rate_hz=200.0) as srv:
            fake = FakeSitl(srv.address)
            try:
                for k in range(61):
                    fake.send(k)
                fake.send(0)  # a restart is sent at once
            finally:
                fake.close()
            truths = [decode_truth(rx.recv(256)) for _ in range(12)]
            assert srv.stats()["truth_sent"] == 12
    finally:
        rx.close()
    # 1200 Hz / 200 Hz: every 6th step, from the first frame on
    assert [round(t.t_sim_s * RATE_HZ) for t in truths] == [*range(0, 61, 6), 0]


# -- the command line ---------------------------------------------------------------------------------


def test_the_program_refuses_a_remote_address_without_allow_remote(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--listen", "192.0.2.1:9002"]) == 2
    assert "loopback only" in capsys.readouterr().err


def test_the_program_serves_until_sigterm_and_prints_its_counters() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    proc = subprocess.Popen(
        [sys.executable, "-m", "drivers.rover_physics", "--listen", f"127.0.0.1:{port}", "--yaw-deg", "90"],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    fake = FakeSitl(("127.0.0.1", port))
    try:
        fake.sock.settimeout(0.5)
        doc = None
        for _ in range(int(30 / 0.5)):  # until the program is up (a loaded machine starts Python slowly)
            try:
                doc = fake.doc(0)
                break
            except TimeoutError:
                assert proc.poll() is None, proc.communicate()
        assert doc is not None and doc["attitude"][2] == pytest.approx(math.pi / 2)
        fake.sock.settimeout(IO_TIMEOUT_S)
        fake.doc(1)
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=IO_TIMEOUT_S)
    finally:
        fake.close()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    assert "rover-physics: steps 1, resends 0, restarts 0, malformed 0" in out


# -- against ArduPilot's SITL ---------------------------------------------------------------------------

SITL_HOME = (-35.363261, 149.165230, 584.0)
LATLON_TO_M = 0.011131884502145034  # ArduPilot's metres per 1e-7 degree of latitude
SITL_SPEEDUP = 4  # lockstep: a busy machine only makes it slower, never wrong
WALL_BUDGET_S = 50.0
# 200 Hz (every 6th step): the receive buffer holds seconds of it, should the test stall
TRUTH_RATE_HZ = 200.0
AGREE_M = 1.0  # ArduPilot's EKF position vs the physics truth at the same simulated time
MAV_SYS_STATUS_PREARM_CHECK = 0x10000000
EKF_POS_HORIZ_ABS = 16
MAV_MODE_FLAG_SAFETY_ARMED = 128
# the MAVLink stream rates on SERIAL0 (this build calls the SRn_ parameters MAVn_): positions at 10 Hz
EXTRA_PARM = """MAV1_POSITION 10
MAV1_EXTRA1 10
MAV1_EXT_STAT 2
MAV1_RC_CHAN 4
"""


def _sitl_binary() -> Path:
    env = os.environ.get("ROBOTD_ARDUPILOT_SITL")
    path = Path(env) if env else REPO / ".." / "shared" / "tools" / "ardupilot-sitl" / "ardurover"
    if path.is_dir():
        path = path / "ardurover"
    if not path.is_file():
        pytest.skip(
            f"ArduPilot SITL not found: {path.resolve()} (set ROBOTD_ARDUPILOT_SITL to the ardurover binary, "
            "or place it in ../shared/tools/ardupilot-sitl beside the repository)"
        )
    return path


class Processes:
    """Programs started in one directory, each with its output in <dir>/<name>.log."""

    def __init__(self, cwd: Path) -> None:
        self.cwd = cwd
        self.started: list[subprocess.Popen[bytes]] = []

    def start(self, cmd: list[str]) -> subprocess.Popen[bytes]:
        with open(self.cwd / f"{Path(cmd[0]).name}.log", "wb") as log:
            proc = subprocess.Popen(cmd, cwd=self.cwd, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT)
        self.started.append(proc)
        return proc

    @staticmethod
    def stop(proc: subprocess.Popen[bytes]) -> None:
        """SIGTERM, then SIGKILL after 5 s (SITL blocked waiting for a physics answer ignores SIGTERM)."""
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


@pytest.fixture
def processes(tmp_path: Path) -> Iterator[Processes]:
    """Starts programs in tmp_path; whatever still runs at the end of the test is stopped."""
    procs = Processes(tmp_path)
    try:
        yield procs
    finally:
        for proc in procs.started:
            procs.stop(proc)


def _ned_from_home(lat_e7: int, lon_e7: int) -> tuple[float, float]:
    lat0, lon0 = round(SITL_HOME[0] * 1e7), round(SITL_HOME[1] * 1e7)
    north = (lat_e7 - lat0) * LATLON_TO_M
    east = (lon_e7 - lon0) * LATLON_TO_M * math.cos(math.radians(SITL_HOME[0]))
    return north, east


def test_ardupilot_sitl_drives_the_model_and_agrees_with_its_truth(
    tmp_path: Path, processes: Processes, monkeypatch: pytest.MonkeyPatch
) -> None:
    binary = _sitl_binary()
    monkeypatch.setenv("MAVLINK20", "1")  # before pymavlink picks its bindings
    from pymavlink import mavutil

    start = RoverParams(start_north_m=2.0, start_east_m=-1.0, start_yaw_rad=math.radians(30.0))
    (tmp_path / "extra.parm").write_text(EXTRA_PARM)
    rx = _truth_receiver()
    rx.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
    rx.setblocking(False)
    conn = mavutil.mavlink_connection("udpin:127.0.0.1:0", dialect="ardupilotmega")
    truth: list[TruthSample] = []
    ap_positions: list[tuple[str, float, float, float]] = []  # (message, t_sim, north, east) from home
    texts: list[str] = []
    marks: dict[str, float] = {}
    try:
        with JsonPhysicsServer(
            RoverModel(start), listen=("127.0.0.1", 0), truth_to=rx.getsockname(), truth_rate_hz=TRUTH_RATE_HZ
        ) as srv:
            cmd = [
                str(binary), "-w", "--model", "JSON:127.0.0.1", "--speedup", str(SITL_SPEEDUP),
                "--defaults", f"{binary.parent / 'rover.parm'},{tmp_path / 'extra.parm'}", "-I0",
                "--home", ",".join(f"{x:.6f}" for x in SITL_HOME) + ",0",
                "--sim-address=127.0.0.1", "--sim-port-out", str(srv.address[1]),
                "--serial0", f"udpclient:127.0.0.1:{conn.port.getsockname()[1]}", "--serial1", "none",
                "--serial2", "none", "--serial5", "none", "--serial6", "none", "--serial7", "none",
                "--serial8", "none",
            ]  # fmt: skip
            proc = processes.start(cmd)
            state = _drive(conn, srv, proc, rx, truth, ap_positions, texts, marks)
            processes.stop(proc)  # while the physics still answers: SITL then exits at once
            stats = srv.stats()
    finally:
        conn.close()
        rx.close()
    log = (tmp_path / "ardurover.log").read_text(errors="replace")[-3000:]
    assert state == "done", f"stopped in phase {state!r}; STATUSTEXT: {texts[-15:]}\nSITL log:\n{log}"
    assert stats["frame_rate_hz"] == RATE_HZ and stats["malformed"] == 0 and stats["restarts"] == 0

    t = np.array([s.t_sim_s for s in truth])
    ne = np.array([s.position_ned_m[:2] for s in truth])
    yaw = np.unwrap([s.attitude_rad[2] for s in truth])

    def at(t_s: float) -> int:
        return int(np.searchsorted(t, t_s))

    # still until armed and driven; forward along the start heading; then a right turn (yaw grows)
    i0, i1, i2, i3 = at(marks["straight"]), at(marks["turn"]), at(marks["stop"]), len(t) - 1
    assert np.allclose(ne[t <= marks["straight"]], [2.0, -1.0], atol=ROUNDOFF_ATOL)
    d = ne[i1] - ne[i0]
    heading = np.array([math.cos(start.start_yaw_rad), math.sin(start.start_yaw_rad)])
    assert d @ heading > 2.0, f"moved {d} in the straight phase"
    assert abs(d @ [-heading[1], heading[0]]) < 0.05 and abs(yaw[i1] - yaw[i0]) < math.radians(1.0)
    turned = math.degrees(yaw[i2] - yaw[i1])
    assert turned > 45.0, f"turned {turned:.1f}° with steering right (RC1 > 1500)"
    assert np.hypot(*(ne[i3] - ne[at(marks["end"] - 0.5)])) < 0.05  # stopped at the end

    # ArduPilot's EKF (fed by SITL's GPS, compass and IMU from these answers) agrees with the truth;
    # SITL's clock is the physics timestamp, so the truth is interpolated at time_boot_ms
    origin = np.array([start.start_north_m, start.start_east_m])  # the EKF origin: set while parked there
    errors: dict[str, list[float]] = {"GLOBAL_POSITION_INT": [], "LOCAL_POSITION_NED": []}
    for kind, t_msg, north, east in ap_positions:
        if t_msg < marks["straight"]:
            continue
        p = np.array([north, east]) + (origin if kind == "LOCAL_POSITION_NED" else 0.0)
        truth_ne = [np.interp(t_msg, t, ne[:, 0]), np.interp(t_msg, t, ne[:, 1])]
        errors[kind].append(float(np.hypot(*(p - truth_ne))))
    for kind, e in errors.items():
        assert len(e) >= 20, f"only {len(e)} {kind} messages while driving"
        assert max(e) < AGREE_M, f"{kind} differs from the truth by up to {max(e):.2f} m"


def _drive(
    conn: Any,
    srv: JsonPhysicsServer,
    proc: subprocess.Popen[bytes],
    rx: socket.socket,
    truth: list[TruthSample],
    ap_positions: list[tuple[str, float, float, float]],
    texts: list[str],
    marks: dict[str, float],
) -> str:
    """Wait for GPS and EKF, arm in MANUAL, drive straight 3 s, turn right 2.5 s, stop 3 s, all in
    simulated time; returns the phase reached ("done" when complete)."""
    deadline = time.monotonic() + WALL_BUDGET_S
    phase, t_phase, t_rc, t_arm = "boot", 0.0, -1.0, -10.0
    gps_fix, ekf_flags, prearm = 0, 0, False
    rc = {"straight": (1500, 1800), "turn": (1700, 1800), "stop": (1500, 1500)}
    while phase != "done":
        if time.monotonic() > deadline or proc.poll() is not None:
            return phase
        msg = conn.recv_match(blocking=True, timeout=0.02)
        while True:
            try:
                truth.append(decode_truth(rx.recv(256)))
            except BlockingIOError:
                break
        latest = srv.latest()
        now = latest.t_sim_s if latest else 0.0
        kind = msg.get_type() if msg is not None else ""
        if kind == "STATUSTEXT":
            texts.append(f"{now:.1f} {msg.text}")
        elif kind == "GPS_RAW_INT":
            gps_fix = msg.fix_type
        elif kind == "EKF_STATUS_REPORT":
            ekf_flags = msg.flags
        elif kind == "SYS_STATUS":
            prearm = bool(msg.onboard_control_sensors_health & MAV_SYS_STATUS_PREARM_CHECK)
        elif kind == "GLOBAL_POSITION_INT" and msg.lat != 0:
            ap_positions.append((kind, msg.time_boot_ms / 1e3, *_ned_from_home(msg.lat, msg.lon)))
        elif kind == "LOCAL_POSITION_NED":
            ap_positions.append((kind, msg.time_boot_ms / 1e3, msg.x, msg.y))
        elif kind == "HEARTBEAT" and msg.get_srcComponent() == 1 and phase == "arming":
            if msg.base_mode & MAV_MODE_FLAG_SAFETY_ARMED and msg.custom_mode == 0:  # armed, in MANUAL
                phase, t_phase = "straight", now
                marks["straight"] = now
        if phase == "boot" and gps_fix >= 3 and ekf_flags & EKF_POS_HORIZ_ABS and prearm:
            phase = "arming"
        if phase == "arming" and now - t_arm > 2.0:  # ask again every 2 s until the heartbeat says armed
            t_arm = now
            conn.mav.command_long_send(1, 1, 176, 0, 1, 0, 0, 0, 0, 0, 0)  # DO_SET_MODE custom MANUAL (0)
            conn.mav.command_long_send(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)  # COMPONENT_ARM_DISARM, not forced
        if phase in rc and now - t_rc >= 0.1:
            t_rc = now
            steer, throttle = rc[phase]
            conn.mav.rc_channels_override_send(1, 1, steer, 0, throttle, 0, 0, 0, 0, 0)
        for this, length, following in (("straight", 3.0, "turn"), ("turn", 2.5, "stop"), ("stop", 3.0, "done")):
            if phase == this and now - t_phase >= length:
                phase, t_phase = following, now
                marks["end" if following == "done" else following] = now
    return phase
