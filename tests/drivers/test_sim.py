"""sim:// and none:// as drivers: URL parameters, odometry against truth, the shared clock,
real-time pacing, dropping, duration and close()."""

from __future__ import annotations

import itertools
import threading
import time

import numpy as np
import pytest

from drivers import AutopilotLink, StereoCamera, VehicleLink, open_camera, open_vehicle
from drivers.sim import SimVehicle, open_sim_camera, open_sim_vehicle, parse_sim_url
from robotd.core.errors import DriverError
from robotd.core.geometry import T_to_pose6, se3, se3_inverse, so3_exp
from tests.support.paths import REPO

SMALL = "width=160&height=100"  # fast renders where the image content does not matter


# --------------------------------------------------------------------------------------------
# URL parameters


def test_defaults_are_the_oak_d_rig():
    with open_camera("sim://?realtime=0") as cam:
        m = cam.rectified_model()
        assert (m.f_px, m.px, m.py, m.baseline_m, m.width, m.height) == (430.0, 319.5, 199.5, 0.0755, 640, 400)
        assert isinstance(cam, StereoCamera)
    p = parse_sim_url("sim://")
    assert (p.fps, p.seed, p.speed, p.duration, p.realtime, p.odom_hz) == (30.0, 1, 1.0, 0.0, 1, 50.0)
    assert parse_sim_url("sim://?width=1280&height=800").f_px == 860.0  # same field of view
    assert parse_sim_url("sim://yard?fps=60").fps == 60.0
    assert parse_sim_url("sim://?fps=60", fps=10).fps == 10.0  # options override the URL


@pytest.mark.parametrize(
    "url, named",
    [
        ("sim://?width=abc", "width"),
        ("sim://?width=8", "width"),
        ("sim://?fps=0", "fps"),
        ("sim://?fps=nan", "fps"),
        ("sim://?seed=-1", "seed"),
        ("sim://?seed=1.5", "seed"),
        ("sim://?realtime=2", "realtime"),
        ("sim://?speed=9", "speed"),
        ("sim://?noise=", "noise"),
        ("sim://?bogus=1", "bogus"),
        ("sim://?fps=30&fps=10", "fps"),
        ("sim://?world=moon", "moon"),
        ("sim://moon", "moon"),
        ("sim:///some/path", "path"),
    ],
)
def test_bad_parameters_raise_a_driver_error_naming_them(url: str, named: str):
    with pytest.raises(DriverError, match=named) as info:
        open_camera(url)
    assert url in str(info.value)
    with pytest.raises(DriverError, match=named):
        open_vehicle(url)


def test_bad_options_and_null_vehicle_urls_are_rejected():
    with pytest.raises(DriverError, match="colour"):
        open_sim_camera("sim://", colour=1)
    with pytest.raises(DriverError, match="t0_ns"):
        open_sim_vehicle("sim://", t0_ns=1.5)
    with pytest.raises(DriverError, match="none://"):
        open_vehicle("none://?x=1")


# --------------------------------------------------------------------------------------------
# Odometry


def _integrate(samples: list) -> np.ndarray:
    """Dead-reckon (4, 4) from velocity samples with the midpoint rule on SE(3)."""
    T = np.eye(4)
    for a, b in itertools.pairwise(samples):
        dt = (b.t_ns - a.t_ns) * 1e-9
        w = 0.5 * (a.rate_R_radps + b.rate_R_radps) * dt
        v = 0.5 * (a.vel_R_mps + b.vel_R_mps) * dt
        T = T @ se3(so3_exp(w), so3_exp(0.5 * w) @ v)
    return T


def test_noise_free_odometry_integrates_to_the_truth():
    url = "sim://?realtime=0&noise=0&gyro_noise=0&gyro_bias=0&tilt=3"
    with open_sim_vehicle(url, t0_ns=0) as veh:
        assert isinstance(veh, VehicleLink)
        for j0 in (0, 333, 1200):
            samples = [veh.sample(j) for j in range(j0, j0 + 51)]  # 1 s at 50 Hz
            truth = se3_inverse(veh.truth_T_world_robot(samples[0].t_ns)) @ veh.truth_T_world_robot(samples[-1].t_ns)
            err = T_to_pose6(se3_inverse(truth) @ _integrate(samples))
            assert np.linalg.norm(err[:3]) < 2e-3 and np.linalg.norm(err[3:]) < 1e-3, err


def test_noisy_odometry_over_one_second_matches_the_truth_within_its_noise():
    noise, gyro_noise, hz = 0.05, 0.005, 50
    url = f"sim://?realtime=0&noise={noise}&gyro_noise={gyro_noise}&gyro_bias=0&odom_hz={hz}"
    dist_err, yaw_err = [], []
    with open_sim_vehicle(url, t0_ns=0) as veh:
        for j0 in range(0, 60 * hz, hz):  # sixty 1-s windows around two laps
            samples = [veh.sample(j) for j in range(j0, j0 + hz + 1)]
            truth = se3_inverse(veh.truth_T_world_robot(samples[0].t_ns)) @ veh.truth_T_world_robot(samples[-1].t_ns)
            est = _integrate(samples)
            dist_err.append(np.linalg.norm(est[:3, 3]) - np.linalg.norm(truth[:3, 3]))
            yaw_err.append(T_to_pose6(se3_inverse(truth) @ est)[5])
    # the trapezoid sum of N white samples of σ_v·dt: σ ≈ σ_v dt √N (speed ≈ 1 m/s ± 15 %)
    sigma_dist = noise * 1.0 * (1 / hz) * np.sqrt(hz)
    sigma_yaw = gyro_noise * (1 / hz) * np.sqrt(hz)
    assert 0.5 < np.std(dist_err) / sigma_dist < 1.5
    assert 0.5 < np.std(yaw_err) / sigma_yaw < 1.5
    assert abs(np.mean(dist_err)) < 4 * sigma_dist / np.sqrt(len(dist_err))


def test_odometry_is_deterministic_and_the_gyro_bias_is_constant():
    url = "sim://?realtime=0&gyro_noise=0&noise=0.05&gyro_bias=0.01"
    with open_sim_vehicle(url, t0_ns=0) as a:
        sa = [a.sample(j) for j in (0, 5, 2000)]
        truth = [a._session.world.trajectory.state(j / 50).rate_R_radps for j in (0, 5, 2000)]  # type: ignore[union-attr]
    with open_sim_vehicle(url, t0_ns=0) as b:
        sb = [b.sample(j) for j in (0, 5, 2000)]
    for x, y in zip(sa, sb):
        assert x.t_ns == y.t_ns and np.array_equal(x.vel_R_mps, y.vel_R_mps)
        assert np.array_equal(x.rate_R_radps, y.rate_R_radps)
    bias = [s.rate_R_radps - t for s, t in zip(sa, truth)]
    assert np.allclose(bias[0], bias[1]) and np.allclose(bias[0], bias[2]) and np.linalg.norm(bias[0]) > 1e-4


# --------------------------------------------------------------------------------------------
# Clock, pacing, dropping, duration, close


def test_camera_and_vehicle_opened_separately_share_clock_and_truth():
    with open_camera(f"sim://?{SMALL}&seed=3&realtime=0") as cam, open_vehicle("sim://?seed=3&realtime=0") as veh:
        assert isinstance(veh, SimVehicle)
        assert cam.t0_ns == veh.t0_ns  # type: ignore[attr-defined]
        frames = cam.frames()
        f0, f1 = next(frames), next(frames)
        assert f1.t_ns - f0.t_ns == round(1e9 / 30)
        odo = veh.odometry()
        o = [next(odo) for _ in range(3)]
        assert o[0].t_ns == f0.t_ns and o[1].t_ns - o[0].t_ns == 20_000_000
        assert np.allclose(veh.truth_T_world_robot(f1.t_ns), f1.truth_T_world_robot)


def test_realtime_frames_arrive_at_their_capture_times():
    with open_camera(f"sim://?{SMALL}&fps=20&seed=4") as cam:
        arrivals, stamps = [], []
        for frame in cam.frames():
            arrivals.append(time.monotonic_ns())
            stamps.append(frame.t_ns)
            if len(stamps) == 12:
                break
    periods = np.diff(arrivals[2:]) / 1e6
    assert np.median(periods) == pytest.approx(50.0, abs=5.0)
    lateness_ms = (np.array(arrivals) - np.array(stamps)) / 1e6
    assert np.all(lateness_ms > -1.0)  # never before its capture time
    assert np.median(lateness_ms) < 15.0


def test_a_slow_consumer_gets_the_newest_frame_and_the_rest_count_as_dropped():
    with open_camera(f"sim://?{SMALL}&fps=50&seed=4") as cam:
        seqs = []
        for frame in cam.frames():
            seqs.append(frame.seq)
            time.sleep(0.07)  # 3.5 frame periods of work
            if len(seqs) == 5:
                break
        stats = cam.stats()
    gaps = np.diff(seqs)
    assert np.all(gaps >= 3)
    assert stats["dropped"] == sum(int(g) - 1 for g in gaps) and stats["frames"] == 5
    assert stats["render_ms_p50"] > 0


def test_duration_ends_the_stream_on_schedule():
    with open_camera(f"sim://?{SMALL}&fps=10&duration=0.5&realtime=0&seed=4") as cam:
        frames = list(cam.frames())
    assert [f.seq for f in frames] == [0, 1, 2, 3, 4]
    with open_vehicle("sim://?odom_hz=20&duration=0.5&realtime=0&seed=4") as veh:
        assert len(list(veh.odometry())) == 10


def test_unplug_fails_the_stream_with_a_driver_error_at_its_time():
    with open_camera(f"sim://?{SMALL}&fps=10&unplug=0.5&realtime=0&seed=4") as cam:
        seen = []
        with pytest.raises(DriverError, match=r"camera disconnected at t = 0\.50 s \(simulated unplug\)"):
            for frame in cam.frames():
                seen.append(frame.seq)
    assert seen == [0, 1, 2, 3, 4]


@pytest.mark.parametrize("kind", ["camera", "vehicle", "none"])
def test_close_from_another_thread_stops_iteration_promptly(kind: str):
    if kind == "camera":
        dev = open_camera(f"sim://?{SMALL}&fps=0.2&seed=4")  # 5 s between frames
        dev.__enter__()
        it = dev.frames()
    elif kind == "vehicle":
        dev = open_vehicle("sim://?odom_hz=1&seed=4")
        dev.__enter__()
        it = dev.odometry()
    else:
        dev = open_vehicle("none://")
        dev.__enter__()
        assert dev.autopilot is None  # none:// takes no pose
        it = dev.odometry()
    got: list[object] = []
    done = threading.Event()

    def consume() -> None:
        for item in it:
            got.append(item)
        done.set()

    thread = threading.Thread(target=consume, daemon=True)
    thread.start()
    # the first item (if any) is out, an event rather than a sleep that a busy host may outlast;
    # the thread then waits for the next (5 s or 1 s away)
    expected = 0 if kind == "none" else 1
    t_end = time.monotonic() + 30.0
    while len(got) < expected and time.monotonic() < t_end:
        time.sleep(0.01)
    t = time.monotonic()
    dev.close()
    assert done.wait(0.5), "iteration did not stop within 0.5 s of close()"
    assert time.monotonic() - t < 0.5
    assert len(got) == expected
    dev.__exit__(None, None, None)


def test_send_pose_reports_the_error_against_truth():
    from robotd.core.msgs import PoseEstimate

    with open_sim_vehicle("sim://?realtime=0&seed=4") as veh:
        t_ns = veh.sample_t_ns(100)
        xyz = veh.truth_T_world_robot(t_ns)[:3, 3] + np.array([0.3, 0.4, 0.0])
        assert isinstance(veh.autopilot, AutopilotLink)
        veh.autopilot.send_pose(PoseEstimate(t_ns, xyz, np.zeros(3), np.eye(6)), quality=80, reset_counter=0)
        assert veh.stats()["last_pose_error_m"] == pytest.approx(0.5)
        assert veh.stats()["poses_received"] == 1
        assert veh.autopilot.stats()["poses_received"] == 1
        veh.autopilot.set_health("tracking")
        with pytest.raises(DriverError, match="health 'lost'"):
            veh.autopilot.set_health("lost")


def test_render_benchmark_prints_exactly_one_json_object(capsys: pytest.CaptureFixture[str]):
    import importlib.util
    import json

    path = REPO / "bench" / "sim_render.py"
    spec = importlib.util.spec_from_file_location("bench_sim_render", path)
    assert spec is not None and spec.loader is not None
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    import cv2

    threads = cv2.getNumThreads()
    try:
        assert bench.main(["--pairs", "3", "--width", "160", "--height", "100", "--json"]) == 0
    finally:
        cv2.setNumThreads(threads)  # the benchmark sets OpenCV's process-wide thread count
    out = capsys.readouterr().out.strip()
    res = json.loads(out)
    assert res["pairs"] == 3 and res["ms_per_pair_p50"] > 0 and res["pairs_per_s"] > 0


# --------------------------------------------------------------------------------------------
# The stall hard case: the rover stops, the camera stalls


def test_a_stop_holds_the_rover_still_and_it_drives_on_where_it_stopped():
    url = "sim://?realtime=0&noise=0&gyro_noise=0&gyro_bias=0&stop_at=2&stop_s=3"
    with open_sim_vehicle(url, t0_ns=0) as veh, open_sim_vehicle("sim://?realtime=0", t0_ns=0) as moving:
        T = [veh.truth_T_world_robot(int(t * 1e9)) for t in (2.6, 4.0, 5.4)]
        assert np.allclose(T[0], T[1]) and np.allclose(T[1], T[2])  # still from at + ramp to at + stop + ramp
        still = veh.sample(200)  # t = 4 s
        assert np.linalg.norm(still.vel_R_mps) == 0.0 and np.linalg.norm(still.rate_R_radps) == 0.0
        # the same path: where it stands is where the moving rover passes
        p = T[0][:3, 3]
        d = min(np.linalg.norm(moving.truth_T_world_robot(int(t * 1e9))[:3, 3] - p) for t in np.arange(2.0, 3.0, 0.01))
        assert d < 0.01
        # braking is gentle: no sample's speed changes faster than the default plausibility gate allows
        v = np.array([np.linalg.norm(veh.sample(j).vel_R_mps) for j in range(50, 400)])
        assert np.max(np.abs(np.diff(v))) * 50 < 10.0


@pytest.mark.parametrize("stall_odometry", [0, 1])
def test_a_stall_captures_no_frame_and_loses_the_odometry_unless_told(stall_odometry: int):
    url = f"sim://?{SMALL}&realtime=0&fps=10&duration=3&stall_at=1&stall_s=1.2&stall_odometry={stall_odometry}"
    with open_sim_camera(url, t0_ns=0) as cam, open_sim_vehicle(url, t0_ns=0) as veh:
        seqs = [f.seq for f in cam.frames()]
        odo_t = np.array([o.t_ns for o in veh.odometry()]) * 1e-9
    assert seqs == [*range(0, 10), *range(22, 30)]  # frames at 1.0 … 2.1 s are never captured
    in_stall = np.count_nonzero((odo_t >= 1.0) & (odo_t < 2.2))
    assert in_stall == (60 if stall_odometry else 0)
    assert odo_t.size == (150 if stall_odometry else 90)


def test_a_stall_in_real_time_is_silent_for_its_length():
    url = f"sim://?{SMALL}&fps=20&duration=1.2&stall_at=0.3&stall_s=0.6"
    with open_sim_camera(url) as cam:
        t_arrive = []
        seqs = []
        for f in cam.frames():
            t_arrive.append(time.monotonic())
            seqs.append(f.seq)
    k = seqs.index(18)
    assert seqs[k - 1] == 5 and t_arrive[k] - t_arrive[k - 1] > 0.55


def test_prerendered_frames_are_the_rendered_ones_served_from_memory() -> None:
    url = "sim://?realtime=0&fps=10&duration=1.0"
    with open_sim_camera(url) as live:
        a = list(live.frames())
    with open_sim_camera(url + "&prerender=1") as pre:
        b = list(pre.frames())
    assert len(a) == len(b) == 10
    for fa, fb in zip(a, b, strict=True):
        assert fa.t_ns - a[0].t_ns == fb.t_ns - b[0].t_ns and fa.seq == fb.seq  # each session its own clock
        np.testing.assert_array_equal(fa.left, fb.left)
        np.testing.assert_array_equal(fa.right, fb.right)
        np.testing.assert_array_equal(fa.truth_T_world_robot, fb.truth_T_world_robot)
    with pytest.raises(DriverError, match="prerender needs a duration"):
        parse_sim_url("sim://?prerender=1")


def test_a_calibration_error_moves_only_the_right_image_by_its_disparity_error() -> None:
    """disparity_error: the right view of a rig whose right principal point is off; the left view
    and the rig the pipeline is given are the nominal ones (docs/sim.md)."""
    import cv2

    from drivers.sim import SimParams, SimRig
    from drivers.simworld import build_world

    p0 = parse_sim_url("sim://?img_noise=0")
    p1 = parse_sim_url("sim://?img_noise=0&disparity_error=0.6")
    assert isinstance(p0, SimParams) and p1.disparity_error == 0.6
    world = build_world(p0.seed, p0.world, p0.speed, p0.tilt)
    f0, _ = SimRig(world, p0).render(30, 0, depth=False)
    r1 = SimRig(world, p1)
    f1, _ = r1.render(30, 0, depth=False)
    assert r1.model.px == SimRig(world, p0).model.px
    np.testing.assert_array_equal(f0.left, f1.left)
    (dx, dy), _ = cv2.phaseCorrelate(f0.right.astype(np.float64), f1.right.astype(np.float64))
    assert dx == pytest.approx(-0.6, abs=0.1) and abs(dy) < 0.1  # x_r smaller: disparities 0.6 px larger
