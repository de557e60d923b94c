"""The autopilot in the loop, short: ArduPilot's SITL Rover drives 0.5 laps of the yard on
robotd's poses with GPS off (robotd/research/sitl.py; bench/sitl.py runs the full missions).

Skipped, naming the path, where the SITL binary is absent. It asserts what the loop must do
whatever the machine's load: the mission completes in AUTO, EKF3 stays on robotd's ExternalNav
(no DCM fallback, nothing ignored), its position follows the physics's truth, the rover stays on
the planned path and the reset counter never changes. Speed (the budget's rung) is bench/sitl.py's.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from robotd.research.sitl import REPO, SITL_ENV, LoopOptions, cross_track_m, find_sitl, ned_to_latlon, run_loop

pytestmark = pytest.mark.skipif(
    find_sitl() is None,
    reason=f"ArduPilot SITL not found: {REPO.parent / 'shared/tools/ardupilot-sitl/ardurover'} (or ${SITL_ENV})",
)


def test_ardupilot_drives_a_mission_on_robotds_poses(tmp_path) -> None:
    r = run_loop(LoopOptions(laps=0.5, timeout_s=120.0, workdir=str(tmp_path)))
    f = r.figures
    assert r.armed, r.prearm_failures
    assert r.completed, r.reason
    assert r.driven_m > 0.8 * r.mission_length_m > 10.0
    assert f["dcm_fallbacks"] == 0 and f["stopped_aiding"] == 0, f["texts"][-20:]
    assert f["visp_ignored"] == 0 and f["visp_reset_counters"] == [r.robotd["reset_counters"][0]]
    assert len(r.robotd["reset_counters"]) == 1  # no reset during a smooth drive
    assert f["ekf_error_rms_m"] < 0.3, f
    assert f["cross_track_max_m"] < 0.6, f
    assert r.robotd["frames_without_odometry"] == 0


def test_geometry_helpers_agree_with_ardupilot_scaling() -> None:
    # 1 m north is 1e7 / LOCATION_SCALING_FACTOR … of a degree; east shrinks with cos(latitude)
    lat, lon = ned_to_latlon(111.31884502145034, 0.0, (0.0, 0.0, 0.0))
    assert lat == pytest.approx(0.001) and lon == 0.0
    lat, lon = ned_to_latlon(0.0, 1000.0, (60.0, 10.0, 0.0))
    assert lon - 10.0 == pytest.approx(2 * 1000.0 / 111318.84502145034, rel=1e-6) and lat == 60.0
    path = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]])
    pts = np.array([[5.0, 1.0], [11.0, 5.0], [-1.0, 0.0], [10.0, 12.0]])
    assert cross_track_m(pts, path) == pytest.approx([1.0, 1.0, 1.0, 2.0])
    assert math.isfinite(float(cross_track_m(pts, path).max()))


def test_a_dcm_episode_before_external_nav_is_no_fallback() -> None:
    from robotd.research.sitl import dcm_fallbacks

    start = ["EKF3 IMU0 tilt alignment complete", "AHRS: EKF3 active", "AHRS: DCM active", "EKF3 IMU0 yaw aligned"]
    nav = ["EKF3 IMU0 is using external nav data", "AHRS: EKF3 active", "Throttle armed", "Reached waypoint #1"]
    assert dcm_fallbacks(start + nav) == 0  # ArduPilot's start-up (SITL, 2026-12-02)
    assert dcm_fallbacks(start + nav + ["AHRS: DCM active", "Mission Complete"]) == 1  # a real fallback
    assert dcm_fallbacks(["AHRS: EKF3 active", "AHRS: DCM active"]) == 0  # never on external nav: other checks say so
