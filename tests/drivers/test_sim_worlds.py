"""The hard-case worlds of sim:// (turn_in_place, moving_box, low_texture): each renders a usable
stereo pair, its trajectory does what the docs say (a fast turn on the spot, a box crossing the
view, a stretch with few features), the moving box is in both images at the frame's instant and
never in the static scene, and everything is the same for the same seed."""

from __future__ import annotations

import itertools
import math

import cv2
import numpy as np
import pytest

from drivers import open_camera, open_vehicle
from drivers.sim import SimParams, SimRig
from drivers.simworld import WORLDS, LaneCrossing, build_world
from robotd.core.errors import DriverError
from robotd.core.geometry import T_to_pose6, se3_inverse
from robotd.core.stereo import triangulate
from robotd.frontend.detectors import DetectorParams, make_detector

NEW_WORLDS = ("turn_in_place", "moving_box", "low_texture", "open_terrain")
FPS = 30.0


def _rig(world: str, width: int = 160, height: int = 100, seed: int = 1) -> SimRig:
    return SimRig(build_world(seed, world), SimParams(realtime=0, world=world, width=width, height=height, seed=seed))


def test_the_hard_cases_are_worlds_of_the_url():
    assert set(NEW_WORLDS) < set(WORLDS)
    with open_camera("sim://moving_box?realtime=0&width=64&height=40") as cam:
        assert cam.params.world == "moving_box"  # type: ignore[attr-defined]


@pytest.mark.parametrize("world", NEW_WORLDS)
def test_each_world_renders_a_stereo_pair_and_starts_at_the_identity(world: str):
    rig = _rig(world, 320, 200)
    frame, depth = rig.render(15, 0)
    assert frame.truth_T_world_robot is not None
    assert np.allclose(rig.world.trajectory.state(0.0).T_world_robot, np.eye(4), atol=1e-12)
    assert frame.left.shape == frame.right.shape == (200, 320) and not np.array_equal(frame.left, frame.right)
    assert np.isfinite(depth).mean() > 0.5  # surfaces, not sky
    # ORB matches are row-aligned, as on the rectified rig
    orb = cv2.ORB_create(500)
    kl, dl = orb.detectAndCompute(frame.left, None)
    kr, dr = orb.detectAndCompute(frame.right, None)
    m = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(dl, dr)
    dy = np.array([kl[x.queryIdx].pt[1] - kr[x.trainIdx].pt[1] for x in m])
    assert np.median(np.abs(dy[np.abs(dy) < 3])) < 0.5


@pytest.mark.parametrize("world", NEW_WORLDS)
def test_same_seed_same_frames_other_seed_other_world(world: str):
    a, _ = _rig(world).render(100, 7)
    b, _ = _rig(world).render(100, 7)
    assert np.array_equal(a.left, b.left) and np.array_equal(a.right, b.right)
    assert np.array_equal(a.truth_T_world_robot, b.truth_T_world_robot)
    c, _ = _rig(world, seed=2).render(100, 7)
    assert np.mean(np.abs(a.left.astype(int) - c.left.astype(int))) > 10


@pytest.mark.parametrize("world", NEW_WORLDS)
def test_camera_and_vehicle_share_the_world_and_its_clock(world: str):
    url = f"sim://{world}?realtime=0&width=64&height=40"
    with open_camera(url) as cam, open_vehicle(url) as veh:
        frames = cam.frames()
        for _ in range(4):
            f = next(frames)
        assert np.array_equal(veh.truth_T_world_robot(f.t_ns), f.truth_T_world_robot)  # type: ignore[attr-defined]


# --------------------------------------------------------------------------------------------
# turn_in_place


def _turns(yaw: np.ndarray, dt: float, threshold_degps: float = 5.0) -> list[tuple[int, int]]:
    """(first, last) sample indices of each run where |dyaw/dt| exceeds the threshold."""
    fast = np.abs(np.degrees(np.diff(yaw)) / dt) > threshold_degps
    edges = np.flatnonzero(np.diff(np.concatenate([[0], fast.astype(int), [0]])))
    return list(zip(edges[::2], edges[1::2], strict=True))


def test_turn_in_place_stops_yaws_fast_on_the_spot_and_drives_on():
    traj = build_world(1, "turn_in_place").trajectory
    dt = 1.0 / 100.0
    ts = np.arange(0.0, 10.0, dt)
    T = [traj.state(float(t)).T_world_robot for t in ts]
    yaw = np.unwrap([T_to_pose6(x)[5] for x in T])
    xyz = np.array([x[:3, 3] for x in T])
    speed = np.linalg.norm(np.diff(xyz, axis=0), axis=1) / dt
    turns = _turns(yaw, dt)
    assert len(turns) == 2, turns  # 98° at 2.0–3.4 s, 82° at 7.4–8.6 s
    assert ts[turns[0][0]] < 2.5  # early enough for short test runs
    for a, b in turns:
        angle = math.degrees(yaw[b] - yaw[a])
        peak = np.max(np.abs(np.degrees(np.diff(yaw[a : b + 1])))) / dt
        assert 80.0 <= angle <= 100.0, angle  # right turns (FRD: positive yaw)
        assert 60.0 <= peak <= 95.0, peak
        assert np.linalg.norm(xyz[b] - xyz[a]) < 1e-3  # on the spot
        assert speed[max(0, a - 5) : b].max() < 0.05  # stopped before and during the turn
        assert speed[b : b + 200].max() > 0.9  # and driving on within 2 s
    assert abs(math.degrees(yaw[turns[0][1]] - yaw[turns[0][0]]) - 98.0) < 0.5
    # the trajectory's own account of its turns (for evaluations) agrees with the poses
    windows = traj.turn_windows(10.0)  # type: ignore[attr-defined]
    assert len(windows) == len(turns)
    for (t0, t1, angle), (a, b) in zip(windows, turns, strict=True):
        # the 5 °/s threshold cuts the sin² ramps' first and last 0.05 s (0.1° of the turn)
        assert abs(t0 - ts[a]) <= 0.06 and abs(t1 - ts[b]) <= 0.06
        assert angle == pytest.approx(yaw[b] - yaw[a], abs=math.radians(0.3))


def test_turn_in_place_speed_scales_time():
    slow = build_world(1, "turn_in_place", speed_mps=0.5).trajectory
    fast = build_world(1, "turn_in_place", speed_mps=1.0).trajectory
    for t in (0.7, 4.4, 13.0):
        assert np.allclose(slow.state(2 * t).T_world_robot, fast.state(t).T_world_robot, atol=1e-12)
        assert np.allclose(2 * slow.state(2 * t).rate_R_radps, fast.state(t).rate_R_radps, atol=1e-12)
    parked = build_world(1, "turn_in_place", speed_mps=0.0).trajectory
    assert np.allclose(parked.state(5.0).T_world_robot, np.eye(4)) and not parked.state(5.0).vel_R_mps.any()


def test_odometry_0_gives_a_vehicle_without_odometry_that_still_takes_poses():
    with open_vehicle("sim://?odometry=0&realtime=1&seed=5") as veh:
        assert list(veh.odometry()) == []  # ends at once, even in real time
        assert veh.stats()["samples"] == 0
        assert veh.autopilot is not None
    with open_camera("sim://?odometry=0&realtime=0&width=64&height=40&duration=0.1") as cam:
        assert len(list(cam.frames())) == 3  # the camera is unaffected


# --------------------------------------------------------------------------------------------
# moving_box


@pytest.fixture(scope="module")
def box_rig() -> SimRig:
    return _rig("moving_box", 160, 100)


def test_the_box_crosses_the_view_covering_a_large_part_of_the_image(box_rig: SimRig):
    ks = np.arange(0, int(6.0 * FPS), 3)
    cover = np.array([box_rig.moving_mask(int(k)).mean() for k in ks])
    t = ks / FPS
    assert cover.max() > 0.35, cover.max()  # ≈ 0.46 at 3.6 s
    assert np.sum(cover > 0.2) * 3 / FPS >= 1.0  # more than a fifth of the image for over a second
    assert np.all(cover[t > 5.3] == 0.0)  # and then it is gone
    # it crosses the path ahead: in the robot frame its centre goes from one side to the other
    # while ahead of the rover
    world = box_rig.world
    van = world.movers[0]
    side = []
    for tt in np.arange(1.0, 5.5, 0.1):
        p = se3_inverse(world.trajectory.state(float(tt)).T_world_robot) @ van.pose(float(tt))[:, 3]
        if 1.0 < p[0] < 6.0:
            side.append(p[1])
    assert min(side) < -1.0 and max(side) > 1.0


def test_the_box_never_hits_the_rover_and_crosses_every_half_lap():
    world = build_world(1, "moving_box")
    van = world.movers[0]
    assert isinstance(van.motion, LaneCrossing)
    windows = [van.motion.move_window(i) for i in range(5)]
    T_yard_world = se3_inverse(world.trajectory.T_world_yard)
    half_x, half_y = 0.5 * 1.4 + 0.35, 0.5 * 2.4 + 0.35  # the van's footprint and the rover's half width
    lane_y = []
    for t in np.arange(0.0, 60.0, 0.05):
        T_world_van = van.pose(float(t))
        p = se3_inverse(T_world_van) @ world.trajectory.state(float(t)).T_world_robot[:, 3]
        assert abs(p[0]) > half_x or abs(p[1]) > half_y, t
        lane_y.append((T_yard_world @ T_world_van)[1, 3])
    # each move takes it across the loop's middle (yard y = 0): one per half lap, two laps
    assert np.count_nonzero(np.diff(np.sign(lane_y))) >= 4
    # it moves in its move windows (the schedule evaluations use), and only then
    ts = np.arange(0.0, 60.0, 0.05)
    moved = np.abs(np.diff(lane_y)) > 1e-9
    overlaps = np.array([any(a < t1 and b > t0 for a, b in windows) for t0, t1 in itertools.pairwise(ts)])
    assert np.array_equal(moved, overlaps)


def test_the_box_is_in_both_images_at_the_same_instant_and_not_in_the_static_scene():
    rig = _rig("moving_box", 320, 200)
    k = int(3.2 * FPS)
    frame, depth = rig.render(k, 0)
    mask = rig.moving_mask(k)
    assert mask.mean() > 0.25
    # SIFT matches on the box triangulate to the depth buffer: the right image shows the box
    # where the left image's geometry says (an out-of-sync pair would be off by the box's motion)
    sift = cv2.SIFT_create(1500)
    kl, dl = sift.detectAndCompute(frame.left, mask.astype(np.uint8))
    kr, dr = sift.detectAndCompute(frame.right, None)
    m = cv2.BFMatcher(cv2.NORM_L2, crossCheck=True).match(dl, dr)
    pl = np.array([kl[x.queryIdx].pt for x in m])
    pr = np.array([kr[x.trainIdx].pt for x in m])
    dy, d = pl[:, 1] - pr[:, 1], pl[:, 0] - pr[:, 0]
    ok = (np.abs(dy) < 3) & (d > 2)
    assert ok.sum() >= 40
    assert np.median(np.abs(dy[ok])) < 0.5
    mm = rig.model
    xyz = triangulate(pl[ok, 0], pr[ok, 0], 0.5 * (pl[ok, 1] + pr[ok, 1]), mm.f_px, mm.px, mm.py, mm.baseline_m)
    z = depth[np.rint(pl[ok, 1]).astype(int), np.rint(pl[ok, 0]).astype(int)]
    assert np.median(np.abs(xyz[:, 0] - z) / z) < 0.03
    # the static scene (what a map truth would be built from) does not hold it
    names = {s.name.split(".")[0] for s in rig.world.surfaces}
    assert "van" not in names and {s.name.split(".")[0] for s in rig.world.moving_surfaces(3.2)} == {"van"}
    assert not _rig("yard").moving_mask(k).any()


# --------------------------------------------------------------------------------------------
# low_texture


def test_low_texture_stretch_has_few_features_for_over_a_second():
    """The front end's own ORB (its default parameters) finds plenty before and after, and fewer
    than 30 features for more than a second while the rover faces the blank end of the yard."""
    rig = _rig("low_texture", 320, 200)
    det = make_detector(DetectorParams())
    ks = np.arange(0, int(7.0 * FPS), 3)
    counts = np.array([len(det.detect(rig.render(int(k), 0, depth=False)[0].left).xy) for k in ks])
    t = ks / FPS
    assert np.all(counts[t < 1.5] >= 300), counts
    few = counts < 30
    edges = np.flatnonzero(np.diff(np.concatenate([[0], few.astype(int), [0]])))
    longest_s = max((b - a for a, b in zip(edges[::2], edges[1::2], strict=True)), default=0) * 3 / FPS
    assert longest_s >= 1.0, (longest_s, counts)
    assert np.all(counts[t > 6.5] >= 300), counts  # and the texture comes back


# --------------------------------------------------------------------------------------------
# open_terrain

TERRAIN_URL = "sim://open_terrain?realtime=0&speed=5&fps=5"  # car pace: 1 m per frame


@pytest.fixture(scope="module")
def terrain():
    from drivers.simterrain import RoadLoop

    world = build_world(1, "open_terrain", speed_mps=5.0)
    assert isinstance(world.trajectory, RoadLoop)
    return world


def test_open_terrain_has_a_car_rig_unless_the_url_says_otherwise():
    with open_camera(TERRAIN_URL) as cam:
        m = cam.rectified_model()
        assert (m.f_px, m.baseline_m, m.width, m.height) == (430.0, 0.9, 640, 400)
        assert m.fb == pytest.approx(387.0)  # KITTI's 718 px × 0.54 m: the same disparity at a depth
    with open_camera(TERRAIN_URL + "&baseline=0.54") as cam:
        assert cam.rectified_model().baseline_m == 0.54
    with open_camera("sim://yard?realtime=0") as cam:
        assert cam.rectified_model().baseline_m == 0.0755
    assert build_world(1, "open_terrain").cam_height_m == 1.65


def test_open_terrain_drives_a_long_curve_on_a_long_closed_lap(terrain):
    traj = terrain.trajectory
    turns = traj.turns()
    assert traj.length_m >= 500.0 and len(turns) == 6
    assert {math.copysign(1.0, a) for _, _, a in turns} == {-1.0, 1.0}  # it turns both ways
    # the first turn, from the poses: 98° over about 50 m, entered 10 m after the start
    s0, s1, angle = turns[0]
    t0, t1 = traj.time_at(s0), traj.time_at(s1)
    assert math.degrees(angle) == pytest.approx(98.0) and 50.0 <= s1 - s0 <= 55.0 and s0 - traj.start_m == 10.0
    assert t0 < 2.0 and t1 < 13.0  # at 5 m/s
    ts = np.arange(0.0, t1 + 1.0, 0.01)
    T = [traj.state(float(t)).T_world_robot for t in ts]
    yaw = np.unwrap([T_to_pose6(x)[5] for x in T])
    xyz = np.array([x[:3, 3] for x in T])
    i0, i1 = np.searchsorted(ts, t0), np.searchsorted(ts, t1)
    assert math.degrees(yaw[i1] - yaw[i0]) == pytest.approx(98.0, abs=0.2)
    assert np.sum(np.linalg.norm(np.diff(xyz[i0 : i1 + 1], axis=0), axis=1)) == pytest.approx(s1 - s0, abs=0.1)
    assert abs(math.degrees(yaw[i0] - yaw[0])) < 1e-6  # straight before it
    # a smooth yaw rate: no radius below 25 m, no steps (the curvature ramps in over 10 m: at most
    # 0.2 rad/s² here, where a turn entered without a ramp would step by 0.2 rad/s)
    rate = np.array([traj.state(float(t)).rate_R_radps[2] for t in ts])
    speed = np.array([np.linalg.norm(traj.state(float(t)).vel_R_mps) for t in ts])
    assert np.all(np.abs(rate) <= speed / 25.0 + 1e-9) and np.max(np.abs(np.diff(rate))) < 3e-3
    # the lap closes: after one lap the rover is back at its start pose, heading the same way
    lap_t = traj.time_at(traj.start_m + traj.length_m)
    assert np.allclose(traj.state(lap_t).T_world_robot, np.eye(4), atol=1e-9)


def test_open_terrain_odometry_integrates_to_the_truth_through_the_curve():
    from tests.drivers.test_sim import _integrate

    url = TERRAIN_URL + "&noise=0&gyro_noise=0&gyro_bias=0&tilt=3"
    with open_vehicle(url, t0_ns=0) as veh:
        for j0 in (0, 150, 400):  # on the straight, in the curve, after it
            samples = [veh.sample(j) for j in range(j0, j0 + 51)]  # type: ignore[attr-defined]
            truth = se3_inverse(veh.truth_T_world_robot(samples[0].t_ns)) @ veh.truth_T_world_robot(  # type: ignore[attr-defined]
                samples[-1].t_ns
            )
            assert np.linalg.norm(truth[:3, 3]) > 4.0  # 5 m/s
            err = T_to_pose6(se3_inverse(truth) @ _integrate(samples))
            assert np.linalg.norm(err[:3]) < 2e-3 and np.linalg.norm(err[3:]) < 1e-3, err


def test_open_terrain_near_objects_are_sparse_and_off_the_path_and_the_trees_far(terrain):
    from drivers.simterrain import TREE_CLEAR_M

    T_yard_world = se3_inverse(terrain.trajectory.T_world_yard)
    path = terrain.trajectory.path_points_yard(4000)

    def clearance(names: set[str]) -> tuple[int, float]:
        objs: dict[str, list[np.ndarray]] = {}
        for s in terrain.surfaces:
            if s.name.split(".")[0].rstrip("0123456789") in names:
                objs.setdefault(s.name.split(".")[0], []).append(
                    s.corners_W @ T_yard_world[:3, :3].T + T_yard_world[:3, 3]
                )
        d = [np.min(np.linalg.norm(path[:, None, :] - np.concatenate(c)[None, :, :2], axis=2)) for c in objs.values()]
        return len(objs), float(min(d))

    n_near, near_clear = clearance({"post", "rock", "bush"})
    assert 3 <= n_near / terrain.trajectory.length_m * 100.0 <= 10  # a few per 100 m
    assert near_clear >= 2.5  # never on the path
    n_stands, tree_clear = clearance({"trees"})
    assert n_stands >= 30 and tree_clear >= TREE_CLEAR_M
    # no walls: nothing but the ground, the near objects and the far band
    kinds = {s.name.split(".")[0].rstrip("0123456789,-") for s in terrain.surfaces}
    assert kinds == {"ground", "post", "rock", "bush", "trees", "treeline", "hills"}


@pytest.fixture(scope="module")
def terrain_frames():
    """Frames around the lap at 640×400 (car pace: frame k is k metres on), their depth, the
    front end's ORB features and stereo matches with the far limit at 0.5 px."""
    from robotd.config import load_config
    from robotd.config.params import frontend_params_from_config
    from robotd.frontend.frontend import Frontend

    out = []
    with open_camera(TERRAIN_URL) as cam:
        rig = cam.rectified_model()
        fe = Frontend(rig, frontend_params_from_config(load_config(None, {"frontend": {"disparity_min_px": 0.5}})))
        for k in (0, 40, 120, 200, 320, 440, 600):
            frame, depth = cam.render(k)  # type: ignore[attr-defined]
            feats = fe.detect(frame.left, frame.right)
            out.append((frame, depth, feats, fe.match_stereo(feats, frame.left, frame.right)))
    return rig, out


def test_open_terrain_far_structure_fills_the_upper_half_at_a_few_pixels_of_disparity(terrain_frames):
    """Above the horizon the images show the treeline, the stands and the hills, 30 m and more
    away: at fb = 387 px·m a few pixels of disparity (7.7 px at 50 m, 1.9 px at 200 m). Below it,
    the field gives near features down to 3.5 m (110 px)."""
    rig, frames = terrain_frames
    far_feats, near_disp = [], []
    for _frame, depth, feats, _ in frames:
        top = depth[: int(rig.py)]
        shown = np.isfinite(top)
        assert 0.15 < shown.mean() < 0.6  # a band of far structure and the sky above it
        assert np.mean(top[shown] >= 25.0) > 0.97  # only a near post or bush in front of it now and then
        xy = feats.left.xy
        up = xy[:, 1] < rig.py
        assert up.sum() > 350  # most features are there
        z = depth[np.rint(xy[up, 1]).astype(int), np.rint(xy[up, 0]).astype(int)]
        far_feats.append(rig.fb / z)
        near_disp.append(rig.fb / depth[-1, int(rig.px)])
    d = np.concatenate(far_feats)
    assert 2.0 < np.median(d) < 6.0  # measured 4.3 px
    assert np.mean(d < 10.0) > 0.9  # measured 0.95 (and all below 20 px)
    assert np.mean(d < 5.0) > 0.45  # beyond the default far limit (5 px): measured 0.56
    assert np.median(near_disp) == pytest.approx(rig.fb / (1.65 * rig.f_px / (rig.height - 1 - rig.py)), rel=0.02)


def test_open_terrain_ground_tiles_make_no_false_stereo_matches(terrain_frames):
    """The ground's tiles turn and alternate their textures, and the renderer filters them by
    distance: the front end's stereo matches on it are not fooled by repetition or aliasing."""
    rig, frames = terrain_frames
    gross, n = 0, 0
    for _, depth, _, m in frames:
        low = m.y > rig.py + 10  # the field, below the horizon
        z = depth[np.rint(m.y[low]).astype(int), np.rint(m.xl[low]).astype(int)]
        err = (m.xl - m.xr)[low] - rig.fb / z
        gross += int(np.sum(np.abs(err) > 2.0))
        n += int(low.sum())
    assert n > 500
    assert gross / n < 0.05  # measured 17 of 879 (1.9 %)


# --------------------------------------------------------------------------------------------
# a hand-held camera shaken (shake=, shake_s=, exposure_ms=)


def _rotvec(R: np.ndarray) -> np.ndarray:
    angle = math.acos(max(-1.0, min(1.0, (np.trace(R) - 1.0) / 2.0)))
    if angle < 1e-12:
        return np.zeros(3)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return w * angle / (2.0 * math.sin(angle))


@pytest.mark.parametrize("world", ["yard", "turn_in_place"])
def test_a_shaken_cameras_rates_and_velocity_are_its_poses_derivatives(world: str):
    """The gyro and wheel truth of a shaken camera (T_base · ΔT) match central differences of its
    poses, while it shakes and while the shake fades out."""
    traj = build_world(1, world, 1.0, 0.0, (0.0, 0.0), 5.0, 3.0).trajectory
    h = 1e-5
    for t in (0.37, 1.21, 2.6, 2.83, 2.97):
        a, b = traj.state(t - h).T_world_robot, traj.state(t + h).T_world_robot
        st = traj.state(t)
        w_num = _rotvec(a[:3, :3].T @ b[:3, :3]) / (2 * h)
        v_num = st.T_world_robot[:3, :3].T @ (b[:3, 3] - a[:3, 3]) / (2 * h)
        np.testing.assert_allclose(st.rate_R_radps, w_num, atol=1e-4)
        np.testing.assert_allclose(st.vel_R_mps, v_num, atol=1e-4)


def test_the_shake_starts_at_rest_peaks_near_its_amplitude_and_ends_at_shake_s():
    base = build_world(1, "yard").trajectory
    shaken = build_world(1, "yard", 1.0, 0.0, (0.0, 0.0), 5.0, 6.0).trajectory
    np.testing.assert_allclose(shaken.state(0.0).T_world_robot, np.eye(4), atol=1e-12)  # the world frame stays
    ts = np.arange(0.0, 5.5, 0.01)
    ang = [
        math.degrees(
            np.linalg.norm(_rotvec(base.state(t).T_world_robot[:3, :3].T @ shaken.state(t).T_world_robot[:3, :3]))
        )
        for t in ts
    ]
    rate = [math.degrees(np.abs(shaken.state(t).rate_R_radps - base.state(t).rate_R_radps).max()) for t in ts]
    assert 4.0 < max(ang) < 15.0  # three axes of about 5° each
    assert 60.0 < max(rate) < 200.0  # a hand shaken hard: tens of degrees a frame-time at 20 Hz
    for t in (6.0, 7.5):  # faded out: the base trajectory again
        np.testing.assert_allclose(shaken.state(t).T_world_robot, base.state(t).T_world_robot, atol=1e-12)
        np.testing.assert_allclose(shaken.state(t).rate_R_radps, base.state(t).rate_R_radps, atol=1e-12)


def test_an_exposure_blurs_the_pair_and_keeps_the_frames_truth():
    sharp = SimRig(
        build_world(1, "yard", 1.0, 0.0, (0.0, 0.0), 5.0), SimParams(realtime=0, shake=5.0, width=320, height=200)
    )
    blurred = SimRig(
        build_world(1, "yard", 1.0, 0.0, (0.0, 0.0), 5.0),
        SimParams(realtime=0, shake=5.0, exposure_ms=10.0, width=320, height=200),
    )
    fa, da = sharp.render(20, 0)
    fb, db = blurred.render(20, 0)
    np.testing.assert_array_equal(fa.truth_T_world_robot, fb.truth_T_world_robot)
    np.testing.assert_array_equal(da, db)  # the depth buffer is the centre instant's

    def sharpness(img: np.ndarray) -> float:
        return float(cv2.Laplacian(img, cv2.CV_32F).var())

    for a, b in ((fa.left, fb.left), (fa.right, fb.right)):
        assert sharpness(b) < 0.7 * sharpness(a)
        assert abs(float(a.mean()) - float(b.mean())) < 3.0  # blurred, not darkened


def test_shake_and_exposure_are_url_keys_with_ranges():
    with open_camera("sim://?realtime=0&shake=3&shake_s=2&exposure_ms=4") as cam:
        assert (cam.params.shake, cam.params.shake_s, cam.params.exposure_ms) == (3.0, 2.0, 4.0)
        assert next(iter(cam.frames())).exposure_ns == 4_000_000
    with open_camera("sim://?realtime=0&exposure_ms=4&exposure_report=0") as cam:
        assert next(iter(cam.frames())).exposure_ns == 0  # blurred, but reported as a dataset would
    bad_keys = (("shake=11", "shake"), ("exposure_ms=60", "exposure_ms"), ("shake=-1", "shake"))
    for bad, named in (*bad_keys, ("exposure_report=2", "exposure_report")):
        with pytest.raises(DriverError, match=named):
            open_camera(f"sim://?realtime=0&{bad}")
    with pytest.raises(DriverError, match="follow and shake"):
        open_camera("sim://?realtime=0&shake=2&follow=127.0.0.1:9999")
