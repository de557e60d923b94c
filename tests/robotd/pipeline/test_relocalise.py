"""After a map load the pipeline finds its pose in the map (the saved pose may be stale).

A map built over frames 0–119 of the simulated rover is loaded into a fresh pipeline, which is then
fed frame 60 again: as if the rover had been moved back 2 m while robotd was down. A map of more
than a lap is restarted a second after it was saved, the rover driving on into ground the first lap
mapped (a watchdog restart mid-drive). The pipeline
must relocalise on that frame to where the first run had it, and keep tracking. A map of another
world must not relocalise: the map is left untouched while it tries, and it gives up after a
bounded number of frames.
"""

from __future__ import annotations

import numpy as np
import pytest

import drivers
from robotd.config import load_config
from robotd.core.geometry import se3_inverse
from robotd.pipeline import relocalise
from robotd.pipeline.step import Pipeline


def _frames(seed: int, n: int) -> tuple[list, object]:
    url = f"sim://?realtime=0&fps=30&seed={seed}"
    with drivers.open_camera(url) as cam:
        it = cam.frames()
        frames = [next(it) for _ in range(n)]
        rig = cam.rectified_model()
    return frames, rig


def _pipeline(rig) -> Pipeline:
    cfg = load_config(None, {"camera": {"url": "sim://?realtime=0"}, "vehicle": {"url": "sim://?realtime=0"}})
    return Pipeline(cfg, rig, np.random.default_rng(3))


@pytest.fixture(scope="module")
def mapped():
    frames, rig = _frames(1, 120)
    a = _pipeline(rig)
    poses = [a.step(f, None).pose.T_world_robot for f in frames]
    return frames, rig, poses, a.state_dict()


def test_relocalises_after_a_map_load(mapped):
    frames, rig, poses, state = mapped
    b = _pipeline(rig)
    b.load_state_dict(state)
    stale = b.estimator.estimate().T_world_robot
    assert np.linalg.norm(stale[:3, 3] - poses[60][:3, 3]) > 1.0  # the saved pose is far from frame 60's
    r = b.step(frames[60], None)
    assert b.counters.relocalisations == 1 and r.tracking
    D = se3_inverse(poses[60]) @ r.pose.T_world_robot
    assert np.linalg.norm(D[:3, 3]) < 0.10, D[:3, 3]
    assert np.degrees(np.arccos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1))) < 2.0
    # and it keeps tracking from there
    for k in range(61, 75):
        r = b.step(frames[k], None)
    D = se3_inverse(poses[74]) @ r.pose.T_world_robot
    assert r.tracking and np.linalg.norm(D[:3, 3]) < 0.15, D[:3, 3]
    assert b.counters.relocalisations == 1


def test_foreign_map_does_not_relocalise_and_is_left_untouched(mapped, monkeypatch, caplog):
    _, rig, _, state = mapped
    other, _ = _frames(2, 35)  # another world
    monkeypatch.setattr(relocalise, "MAX_FRAMES", 4)
    b = _pipeline(rig)
    b.load_state_dict(state)
    ids0 = b.estimator.landmark_ids().copy()
    for k in range(4):
        r = b.step(other[k], None)
        assert not r.tracking
        np.testing.assert_array_equal(b.estimator.landmark_ids(), ids0)  # no update while trying
        db = b.frontend.descriptors
        assert db is not None and np.all(np.isin(db.ids, ids0))  # nor descriptors of new landmarks
    assert b.counters.relocalisations == 0 and b.counters.relocalisation_failures == 1
    assert "relocalisation against the loaded map failed" in caplog.text
    b.step(other[4], None)  # then it carries on from the saved pose and maps again
    assert np.setdiff1d(b.estimator.landmark_ids(), ids0).size > 0
    # and goes on searching the loaded map, which no frame of this world agrees with
    assert b.relocaliser.searching
    for f in other[5:]:
        assert not b.step(f, None).relocalised
    assert b.counters.relocalisations == 0


def test_planar_resume_continues_from_the_saved_pose():
    # a 2-D map has no heights to match against: no relocalisation is tried, tracking goes on
    frames, rig = _frames(1, 30)
    cfg = load_config(
        None,
        {"camera": {"url": "sim://?realtime=0"}, "vehicle": {"url": "sim://?realtime=0"}, "slam": {"dim": 2}},
    )
    a = Pipeline(cfg, rig, np.random.default_rng(3))
    for f in frames[:25]:
        a.step(f, None)
    b = Pipeline(cfg, rig, np.random.default_rng(4))
    b.load_state_dict(a.state_dict())
    r = b.step(frames[25], None)
    assert b.counters.relocalisations == 0 and b.counters.relocalisation_failures == 0
    assert r.tracking and r.counts["identified"] > 0


@pytest.fixture(scope="module")
def laps():
    """The yard at 1.5 m/s and 15 frames/s (a lap of 28.5 m is about 285 frames), 400 frames,
    mapped by one pipeline up to frame 359; its saved state after frames 179 and 359."""
    url = "sim://?realtime=0&fps=15&seed=1&speed=1.5&odometry=0"
    with drivers.open_camera(url) as cam:
        it = cam.frames()
        frames = [next(it) for _ in range(400)]
        rig = cam.rectified_model()
    cfg = load_config(None, {"camera": {"url": url}, "vehicle": {"url": url}})
    a = Pipeline(cfg, rig, np.random.default_rng(3))
    states = {}
    for k, f in enumerate(frames[:360]):
        a.step(f, None)
        if k + 1 in (180, 360):
            states[k + 1] = a.state_dict()
    return frames, cfg, rig, states


def _restarted(laps, saved_after: int, frames_run: range) -> tuple[Pipeline, list[float], list[int]]:
    """A pipeline resumed from the map saved after ``saved_after`` frames, fed ``frames_run``:
    itself, its position error against the truth per frame, and the frames (indices into the
    run) it reported relocalised."""
    frames, cfg, rig, states = laps
    truth0 = se3_inverse(frames[0].truth_T_world_robot)
    b = Pipeline(cfg, rig, np.random.default_rng(4))
    b.load_state_dict(states[saved_after])
    errs, jumps = [], []
    for k, f in enumerate(frames[i] for i in frames_run):
        r = b.step(f, None)
        errs.append(float(np.linalg.norm(r.pose.T_world_robot[:3, 3] - (truth0 @ f.truth_T_world_robot)[:3, 3])))
        if r.relocalised:
            jumps.append(k)
    assert r.tracking
    return b, errs, jumps


def test_relocalises_mid_drive_in_ground_the_first_lap_mapped(laps):
    # The map is saved after frame 359, the next frame is 360 + 15 (a second's downtime, 1.5 m on).
    # Before the landmarks remembered where they were seen from (docs/slam.md "Which landmarks the
    # map keeps"), the second lap had deleted the first lap's landmarks there: 0 inliers for 30
    # frames, 3.9 m off after (seeds 1 and 2).
    b, errs, _ = _restarted(laps, 360, range(375, 400))
    assert b.counters.relocalisations == 1
    assert max(errs[5:]) < 0.2, np.round(errs, 3)


def test_finds_the_loaded_map_after_the_relocalising_window(laps):
    # The map holds the first 63 % of a lap; restarted 2.8 m on (frame 180 + 28), the rover faces
    # ground the map does not hold for the whole relocalising window (2 s): it fails. The search
    # goes on, and when the rover drives into the first lap's ground two finds agree and the pose
    # jumps there. Without the search it stays metres off for the rest of the run.
    b, errs, jumps = _restarted(laps, 180, range(208, 358))
    assert b.counters.relocalisation_failures == 1 and b.counters.relocalisations == 1, jumps
    assert jumps and jumps[0] > relocalise.MAX_FRAMES and errs[jumps[0] - 1] > 1.0  # off until found
    assert max(errs[jumps[0] :]) < 0.15, np.round(errs[jumps[0] :], 3)


def test_a_handed_over_pose_is_tracked_from_at_once_and_the_map_found_later(laps):
    # The same restart into ground the map does not hold, 2.8 m on, but the pose handed over (the
    # saved one moved by the autopilot's motion, robotd.daemon.handover), here the truth 0.2 m and
    # 0.5° off with the uncertainty of a 5 s downtime (σ 0.3 m, 3.5°): no window, no frame metres
    # off (without it: > 1 m until the map is found), and when the rover reaches the first lap's
    # ground the search finds the map: it resets the pose at most once (a find within 0.1 m and
    # 1° only confirms it) and the error stays small.
    # Before the filter took the carried uncertainty as the particles' spread, no landmark of the
    # new ground was ever re-identified (0 a frame: the pose was odometry alone), the reported σ
    # grew to 4 m, and the first loaded landmarks matched pulled the pose 1.2 m off (seed 4).
    from robotd.daemon.handover import filter_pose, prior_cov

    frames, cfg, rig, states = laps
    truth0 = se3_inverse(frames[0].truth_T_world_robot)
    b = Pipeline(cfg, rig, np.random.default_rng(4))
    b.load_state_dict(states[180])
    x = filter_pose(truth0 @ frames[208].truth_T_world_robot, 3) + np.r_[0.2, 0, 0, 0, 0, np.radians(0.5)]
    b.hand_over(x, prior_cov(5.0, 3))
    errs, sig, ident, jumps = [], [], [], []
    for k, f in enumerate(frames[i] for i in range(208, 358)):
        r = b.step(f, None)
        errs.append(float(np.linalg.norm(r.pose.T_world_robot[:3, 3] - (truth0 @ f.truth_T_world_robot)[:3, 3])))
        sig.append(float(np.sqrt(np.trace(r.pose.cov[:3, :3]))))
        ident.append(r.counts["identified"])
        if r.relocalised:
            jumps.append(k)
    assert r.tracking and b.counters.relocalisation_failures == 0
    assert len(jumps) == 1 and not b.relocaliser.searching, jumps  # the carried pose is 0.2 m off: reset
    errs_a, sig_a = np.array(errs), np.array(sig)
    assert max(errs) < 0.45, np.round(errs, 3)
    assert max(errs[jumps[0] :][-50:]) < 0.15, np.round(errs, 3)
    # the new ground is mapped and tracked, not odometry alone
    assert np.median(ident[: jumps[0]]) >= 5, ident[: jumps[0]]
    # until the map fixes it the reported covariance covers the carried error, and stays bounded
    before = slice(0, jumps[0])
    assert np.all(sig_a[before] >= errs_a[before]) and np.all(sig_a[before] < 1.5), np.round(sig_a[before], 2)
