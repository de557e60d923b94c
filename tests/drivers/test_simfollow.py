"""``sim://…&follow=``: the simulated rover driven by an external physics program's truth stream."""

from __future__ import annotations

import math
import socket
import threading
import time

import numpy as np
import pytest

from drivers.rover_physics import TruthSample, encode_truth
from drivers.sim import open_sim_camera, open_sim_vehicle, parse_sim_url
from drivers.simfollow import MAX_EXTRAPOLATION_S, FollowedTrajectory
from drivers.simworld import LoopTrajectory
from robotd.core.errors import DriverError
from robotd.core.geometry import R_to_euler
from tests.support.tolerances import ROUNDOFF_ATOL


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def followed(yaw0_deg: float = 0.0, t0_ns: int = 0) -> FollowedTrajectory:
    loop = LoopTrajectory()
    return FollowedTrajectory(loop.T_world_yard, loop.path_points_yard(), math.radians(yaw0_deg), t0_ns)


def test_ned_states_land_in_the_start_pose_frame() -> None:
    # the start pose is NED's origin heading yaw0 = 90° (east): north is then to the robot's left
    tr = followed(90.0)
    tr.push(1_000, np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, math.pi / 2]), np.zeros(3), np.zeros(3))
    s = tr.state(1e-6)
    assert s.T_world_robot[:3, 3] == pytest.approx([0.0, -1.0, 0.0], abs=ROUNDOFF_ATOL)
    assert R_to_euler(s.T_world_robot[:3, :3]) == pytest.approx([0.0, 0.0, 0.0], abs=ROUNDOFF_ATOL)
    # driving east at 2 m/s is driving forward in the body frame
    tr.push(2_000, np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, math.pi / 2]), np.array([0.0, 2.0, 0.0]), np.zeros(3))
    assert tr.state(2e-6).vel_R_mps == pytest.approx([2.0, 0.0, 0.0], abs=ROUNDOFF_ATOL)


def test_a_state_is_moved_on_by_its_twist_then_held_when_the_physics_falls_silent() -> None:
    tr = followed()
    v, r = 1.5, 0.6  # forward speed [m/s], yaw rate [rad/s]: a circle of radius 2.5 m
    tr.push(0, np.zeros(3), np.zeros(3), np.array([v, 0.0, 0.0]), np.array([0.0, 0.0, r]))
    dt = 0.1
    s = tr.state(dt)
    radius = v / r
    expect = [radius * math.sin(r * dt), radius * (1.0 - math.cos(r * dt)), 0.0]  # FRD: a right turn
    assert s.T_world_robot[:3, 3] == pytest.approx(expect, abs=1e-9)
    assert R_to_euler(s.T_world_robot[:3, :3])[2] == pytest.approx(r * dt)
    # an older state is used for a time before the newest one
    tr.push(int(0.2e9), np.array([0.3, 0.0, 0.0]), np.zeros(3), np.zeros(3), np.zeros(3))
    assert tr.state(0.05).T_world_robot[:3, 3][0] == pytest.approx(radius * math.sin(r * 0.05))
    # silence: held still, not extrapolated into the walls
    late = tr.state(0.2 + MAX_EXTRAPOLATION_S + 1.0)
    assert late.T_world_robot[:3, 3] == pytest.approx([0.3, 0.0, 0.0]) and not late.vel_R_mps.any()
    # out of order and non-finite states are refused, not used
    tr.push(int(0.1e9), np.ones(3), np.zeros(3), np.zeros(3), np.zeros(3))
    tr.push(int(0.3e9), np.array([np.nan, 0, 0]), np.zeros(3), np.zeros(3), np.zeros(3))
    assert tr.rejected == 2 and tr.received == 2


def test_the_truth_stream_over_udp_and_a_bad_datagram() -> None:
    from drivers.simfollow import truth_push_args

    port = free_udp_port()
    tr = followed(t0_ns=0)
    tr.listen("127.0.0.1", port, truth_push_args)
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
            tx.sendto(b"not a truth datagram", ("127.0.0.1", port))
            t = time.monotonic_ns()
            sample = TruthSample(1, 0.5, t, (2.0, 1.0, 0.0), (0.0, 0.0, 0.25), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
            tx.sendto(encode_truth(sample), ("127.0.0.1", port))
            assert tr.wait_first(threading.Event(), timeout_s=5.0)
        s = tr.state(t * 1e-9)
        assert s.T_world_robot[:3, 3] == pytest.approx([2.0, 1.0, 0.0])
        deadline = time.monotonic() + 5.0
        while tr.rejected < 1 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert tr.rejected == 1
    finally:
        tr.close()


def test_follow_urls_are_checked() -> None:
    p = parse_sim_url("sim://yard?follow=127.0.0.1:9010&yaw0=30")
    assert (p.follow, p.yaw0) == ("127.0.0.1:9010", 30.0)
    with pytest.raises(DriverError, match="loopback only"):
        parse_sim_url("sim://?follow=10.0.0.1:9010")
    with pytest.raises(DriverError, match="HOST:PORT"):
        parse_sim_url("sim://?follow=localhost")
    with pytest.raises(DriverError, match="stop_s"):
        parse_sim_url("sim://?follow=127.0.0.1:9010&stop_s=2")


def test_camera_and_vehicle_follow_the_physics() -> None:
    # the rover stands 3 m north and 1 m east of the start, turned 20° right; the camera images it
    # there, every frame carries that truth, and the wheels measure its motion
    port = free_udp_port()
    url = f"sim://yard?fps=20&follow=127.0.0.1:{port}&img_noise=0"
    pos, yaw = (3.0, 1.0, 0.0), math.radians(20.0)
    stop = threading.Event()

    def physics() -> None:
        seq = 0
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
            while not stop.wait(0.005):
                seq += 1
                vel = (0.5 * math.cos(yaw), 0.5 * math.sin(yaw), 0.0)
                s = TruthSample(seq, seq * 0.005, time.monotonic_ns(), pos, (0.0, 0.0, yaw), vel, (0.0, 0.0, 0.0))
                tx.sendto(encode_truth(s), ("127.0.0.1", port))

    feeder = threading.Thread(target=physics, daemon=True)
    with open_sim_camera(url) as cam, open_sim_vehicle(url + "&noise=0&gyro_noise=0&gyro_bias=0") as veh:
        feeder.start()
        try:
            frames = []
            for f in cam.frames():
                frames.append(f)
                if len(frames) == 3:
                    break
            odo = next(iter(veh.odometry()))
        finally:
            stop.set()
            feeder.join(2.0)
    for f in frames:
        T = f.truth_T_world_robot
        assert T is not None
        # moving at 0.5 m/s: within the extrapolation of one truth datagram's age
        assert np.linalg.norm(T[:3, 3] - np.array(pos)) < 0.05
        assert R_to_euler(T[:3, :3])[2] == pytest.approx(yaw, abs=1e-9)
        assert f.left.std() > 10  # the yard was rendered
    assert odo.vel_R_mps[0] == pytest.approx(0.5, abs=1e-6)
