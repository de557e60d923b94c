"""Pipeline.step: the stages in data-flow order, and one owner of landmark existence.

The filter's existence counter decides which landmarks exist; the front end's descriptor store
follows it through ``UpdateReport.pruned_ids`` and only ever holds ids the filter was given. On
the simulated rover, with caps that drop new measurements and pruning that deletes landmarks,
the two id sets must be equal after every step, for every filter.
"""

from __future__ import annotations

import numpy as np
import pytest

import drivers
from robotd.config import load_config
from robotd.core.errors import InputError
from robotd.core.geometry import se3_inverse
from robotd.core.stereo import triangulate
from robotd.pipeline.stages import fuse
from robotd.pipeline.step import Pipeline
from tests.support.tolerances import ROUNDOFF_ATOL


@pytest.fixture(scope="module")
def sim_frames():
    with drivers.open_camera("sim://?realtime=0&fps=30&seed=2") as cam:
        it = cam.frames()
        frames = [next(it) for _ in range(45)]
        rig = cam.rectified_model()
    return frames, rig


def _pipeline(rig, **slam) -> Pipeline:
    cfg = load_config(None, {"slam": {"max_new_per_frame": 15, "max_updates_per_frame": 20, **slam}})
    return Pipeline(cfg, rig, np.random.default_rng(5))


@pytest.mark.parametrize("filt", ["fastslam2", "fastslam1", "ekf"])
def test_descriptor_store_follows_the_filter_exactly(sim_frames, filt):
    frames, rig = sim_frames
    p = _pipeline(rig, filter=filt, n_particles=20)
    dropped_new = pruned = 0
    for f in frames:
        r = p.step(f, None)
        assert p.frontend.descriptors is not None
        np.testing.assert_array_equal(np.sort(p.frontend.descriptors.ids), np.sort(p.estimator.landmark_ids()))
        dropped_new += r.counts["new"] > r.report.n_new
        pruned += r.report.n_pruned
    # the scenario exercised both ways the id sets could have drifted apart
    assert dropped_new > 0 and pruned > 0, (dropped_new, pruned)


@pytest.mark.parametrize("filt", ["fastslam2", "fastslam1"])
def test_the_reported_covariance_anchors_follow_the_filter(sim_frames, filt):
    """The anchors of the landmarks the filter pruned go with them (bench/soak.py found them piling
    up to 200 000: 66 MB and a 40 ms copy per frame)."""
    frames, rig = sim_frames
    p = _pipeline(rig, filter=filt, n_particles=20)
    pruned = 0
    for f in frames:
        r = p.step(f, None)
        pruned += r.report.n_pruned
        anchors = p.covariance.anchors
        assert anchors is not None and anchors.n_anchored == p.estimator.landmark_ids().size
    assert pruned > 0


def test_step_times_every_stage_in_data_flow_order(sim_frames):
    frames, rig = sim_frames
    p = _pipeline(rig)
    p.step(frames[0], None)
    r = p.step(frames[1], None)
    assert list(r.timings_ms) == [
        "offset",
        "detect",
        "stereo",
        "motion",
        "identify",
        "outliers",
        "select",
        "predict",
        "consistency",
        "update",
        "total",
    ]
    assert all(v >= 0.0 for v in r.timings_ms.values())
    assert r.timings_ms["total"] >= sum(v for k, v in r.timings_ms.items() if k != "total")


@pytest.mark.parametrize("stage", ["update", "predict"])
def test_a_failed_filter_step_leaves_no_orphan_descriptors(sim_frames, monkeypatch, stage):
    """predict is the soak's case: once the pose reached the pitch singularity every predict raised,
    after the frame's new landmarks had their descriptors; they piled up (233 835 descriptors for
    2675 landmarks after 12 minutes) and the saved map no longer passed its own check."""
    frames, rig = sim_frames
    p = _pipeline(rig)
    p.step(frames[0], None)
    before = p.frontend.descriptors.ids.copy()

    def refuse(*_):
        raise InputError(f"{stage} refused for the test")

    monkeypatch.setattr(p.estimator, stage, refuse)
    with pytest.raises(InputError, match="refused for the test"):
        p.step(frames[1], None)
    np.testing.assert_array_equal(p.frontend.descriptors.ids, before)
    p.check_state_dict(p.state_dict())  # the map it would save still passes its own check


def test_motion_noise_scale_multiplies_the_prior_covariance_the_filter_gets(sim_frames):
    frames, rig = sim_frames
    got = {}
    for k in (1.0, 4.0):
        p = _pipeline(rig, motion_noise_scale=k)
        seen = []
        real = p.estimator.predict
        p.estimator.predict = lambda inc, real=real, seen=seen: (seen.append(inc.cov.copy()), real(inc))[1]
        for f in frames[:4]:
            p.step(f, None)
        got[k] = seen
    assert len(got[1.0]) == len(got[4.0]) >= 2
    for a, b in zip(got[1.0], got[4.0], strict=True):
        np.testing.assert_allclose(b, 4.0 * a)


def test_tracking_holds_while_the_visual_motion_constrains_the_pose(sim_frames):
    """The map is wiped each frame (nothing can be identified), but the stereo matches and the
    visual motion remain: tracking must not be declared lost."""
    frames, rig = sim_frames
    p = _pipeline(rig)
    for f in frames[:12]:
        r = p.step(f, None)
        # forget every landmark's descriptor so that identification finds nothing
        assert p.frontend.descriptors is not None
        p.frontend.descriptors.forget(p.frontend.descriptors.ids.copy())
        assert r.tracking
    assert p.counters.lost_events == 0 and p.counters.visual_priors >= 10


def test_the_pixel_model_gets_the_front_ends_pixels_and_tracks(sim_frames, monkeypatch):
    """slam.measurement = "pixel": the filter is given the pixels the front end triangulated
    (frontend.cov_at has nothing to do: the pixel noise is constant), and follows the rover."""
    frames, rig = sim_frames
    p = _pipeline(rig, measurement="pixel")
    given = []
    update = p.estimator.update
    monkeypatch.setattr(p.estimator, "update", lambda obs: given.append(obs) or update(obs))
    monkeypatch.setattr(fuse, "covariance_at_prediction", lambda *a, **k: pytest.fail("cov_at applied"))
    T0_inv = se3_inverse(frames[0].truth_T_world_robot)
    for f in frames:
        r = p.step(f, None)
    obs = given[-1]
    assert obs.uv_px is not None and obs.n > 10
    # the points were triangulated from these pixels (then debiased along their rays: same direction)
    uv = obs.uv_px
    ray = triangulate(uv[:, 0], uv[:, 1], uv[:, 2], rig.f_px, rig.px, rig.py, rig.baseline_m)
    cos = np.einsum("ni,ni->n", ray, obs.xyz_R_m) / np.linalg.norm(ray, axis=1) / np.linalg.norm(obs.xyz_R_m, axis=1)
    np.testing.assert_allclose(cos, 1.0, atol=ROUNDOFF_ATOL)
    # 1.5 m of the simulated rover: within 2 cm at the end (measured 0.9 cm, as the Cartesian model)
    truth = (T0_inv @ frames[-1].truth_T_world_robot)[:3, 3]
    assert r.tracking and np.linalg.norm(r.pose.xyz_W_m - truth) < 0.02


def test_non_finite_odometry_never_reaches_the_motion_stage_and_a_zero_interval_is_harmless(sim_frames):
    """Odometry with NaN cannot be built (the message refuses it by name), so the motion stage's
    odometry bounds never see it; an increment over a zero interval is used for the prediction
    but not as a velocity, and the next frames go on tracking."""
    from robotd.core.errors import InputError
    from robotd.core.msgs import MotionIncrement

    frames, rig = sim_frames
    with pytest.raises(InputError, match="MotionIncrement.dp_R_m: expected finite"):
        MotionIncrement(frames[4].t_ns, frames[5].t_ns, np.array([np.nan, 0, 0]), np.zeros(3), np.eye(6) * 1e-4)
    p = _pipeline(rig)
    for f in frames[:5]:
        p.step(f, None)
    velocity = p.motion.velocity
    zero = MotionIncrement(frames[4].t_ns, frames[4].t_ns, np.zeros(3), np.zeros(3), np.eye(6) * 1e-4)
    r = p.step(frames[5], zero)
    assert r.tracking and p.motion.velocity is velocity  # not a velocity: no division by a zero interval
    for f in frames[6:10]:
        assert p.step(f, None).tracking


@pytest.mark.parametrize("max_tilt_deg, fused", [(60.0, False), (85.0, True)])
def test_gravity_tilted_beyond_any_rover_is_never_fused(sim_frames, max_tilt_deg, fused):
    """A glitching AHRS that says pitch 80° for 3 s: refused by vehicle.max_tilt_deg (never fused,
    never counted toward reopening). With the limit above it, the gate refuses it for 1 s and the
    reopening then takes it: the filter is pulled far off, toward the pitch singularity."""
    from robotd.core.geometry import euler_to_R
    from robotd.core.msgs import MotionIncrement

    frames, rig = sim_frames
    cfg = load_config(None, {"slam": {"max_new_per_frame": 15}, "vehicle": {"max_tilt_deg": max_tilt_deg}})
    p = Pipeline(cfg, rig, np.random.default_rng(5))
    p.step(frames[0], None)
    g_level = np.array([0.0, 0.0, 1.0])
    g_glitch = euler_to_R(np.array([0.0, np.radians(80.0), 0.0])).T @ g_level
    t = frames[0].t_ns
    for g in [g_level] + [g_glitch] * 30:
        inc = MotionIncrement(t, t + 100_000_000, np.zeros(3), np.zeros(3), np.eye(6) * 1e-6, g, 0.02)
        p.fuse.predict(inc)
        t += 100_000_000
    pitch = abs(float(p.estimator.estimate().rpy_rad[1]))
    c = p.counters
    if fused:
        assert c.gravity_reopened >= 1 and pitch > np.radians(20.0)
    else:
        assert (c.gravity_implausible, c.gravity_reopened, c.gravity_fused) == (30, 0, 1)
        assert pitch < np.radians(1.0)


@pytest.mark.parametrize("filt", ["fastslam2", "ekf"])
@pytest.mark.parametrize("pitch_deg", [89.99, 75.0])
def test_an_attitude_no_rover_can_have_is_reset_and_the_run_goes_on(sim_frames, filt, pitch_deg):
    """A pose at the ZYX singularity (pitch 89.99°: the motion model cannot propagate it) or
    tilted beyond vehicle.max_tilt_deg (75° > 60°): before, the first failed every later step
    ("motion3d: pitch ... at the ZYX singularity", for ever) and the second drifted on toward it.
    Now the attitude is reset to level (position and heading kept), the frame is reported lost and
    counted, and the next frames track again."""
    frames, rig = sim_frames
    p = _pipeline(rig, filter=filt, n_particles=20)
    for f in frames[:8]:
        p.step(f, None)
    before = p.estimator.estimate()
    x = np.r_[before.xyz_W_m, 0.0, np.radians(pitch_deg), before.rpy_rad[2]]
    p.estimator.reset_pose(x, None)
    r = p.step(frames[8], None)
    assert r.attitude_reset and not r.tracking
    assert p.counters.attitude_resets == 1 and p.counters.lost_events == 1
    assert np.degrees(np.abs(r.pose.rpy_rad[:2])).max() < 10.0
    assert np.linalg.norm(r.pose.xyz_W_m - before.xyz_W_m) < 0.3  # the position was kept
    for f in frames[9:20]:
        r = p.step(f, None)
        assert not r.attitude_reset
    assert r.tracking and p.counters.attitude_resets == 1
    truth = se3_inverse(frames[0].truth_T_world_robot) @ frames[19].truth_T_world_robot
    assert np.linalg.norm(r.pose.xyz_W_m - truth[:3, 3]) < 0.1
