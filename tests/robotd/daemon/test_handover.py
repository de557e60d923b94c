"""The handover across a restart (robotd.daemon.handover): robotd's saved pose carried over its own
downtime by the autopilot's motion, whatever the autopilot's frame; refused when the autopilot
rebooted or the gap is too long; recorded with the map and read back."""

from __future__ import annotations

import math
import re
import time
from pathlib import Path

import numpy as np
import pytest

from drivers.mavlink_odometry import AutopilotPose
from robotd.config import load_config
from robotd.core.errors import InputError, PersistenceError
from robotd.core.geometry import T_to_pose6, pose6_to_T, se3_inverse
from robotd.core.stereo import RectifiedStereo
from robotd.daemon import handover as ho
from robotd.formats.persist import MapStore
from robotd.pipeline.step import Pipeline

S = 1_000_000_000


def _random_T(rng: np.random.Generator, planar: bool = False) -> np.ndarray:
    x = np.r_[rng.uniform(-20, 20, 3), rng.uniform(-0.3, 0.3, 2), rng.uniform(-math.pi, math.pi)]
    if planar:
        x[2:5] = 0.0
    return pose6_to_T(x)


@pytest.mark.parametrize("seed", range(5))
def test_the_carried_pose_is_the_saved_pose_moved_by_the_autopilots_motion_in_any_frame(seed: int) -> None:
    """The autopilot's frame is robotd's map turned and shifted by anything (a compass yaw trim, a
    vision yaw shift): only its motion over the gap counts, so the carried pose is the truth."""
    rng = np.random.default_rng(seed)
    T_map_robot_saved = _random_T(rng)
    motion = _random_T(rng) @ pose6_to_T(np.zeros(6))  # the vehicle's motion over the gap, any size
    motion[:3, 3] *= 0.1
    T_ap_map = _random_T(rng)  # the autopilot's frame against robotd's map
    A_saved = T_ap_map @ T_map_robot_saved
    A_now = T_ap_map @ T_map_robot_saved @ motion
    saved = ho.SavedHandover(A_saved, boot_ms=100_000, unix_s=1000.0)
    out = ho.carried_pose(saved, T_map_robot_saved, AutopilotPose(0, A_now, 102_000), unix_now=1002.0)
    assert not isinstance(out, str)
    T, gap = out
    assert gap == pytest.approx(2.0)
    np.testing.assert_allclose(T, T_map_robot_saved @ motion, atol=1e-9)


@pytest.mark.parametrize(
    ("boot_now_ms", "unix_now", "why"),
    [
        (40_000, 1002.0, "went back"),  # the autopilot rebooted: its clock restarted
        (103_500, 1001.0, "advanced 3.5 s over the host's 1.0 s"),  # its clock and the host's disagree
        (130_000, 1030.0, "down 30.0 s"),  # longer than its dead reckoning can vouch for
    ],
)
def test_the_carry_is_refused_after_a_reboot_or_a_long_gap(boot_now_ms: int, unix_now: float, why: str) -> None:
    saved = ho.SavedHandover(np.eye(4), boot_ms=100_000, unix_s=1000.0)
    out = ho.carried_pose(saved, np.eye(4), AutopilotPose(0, np.eye(4), boot_now_ms), unix_now)
    assert isinstance(out, str) and why in out


def test_the_prior_widens_with_the_gap_and_fits_the_filter() -> None:
    c2, c3 = ho.prior_cov(2.0, 2), ho.prior_cov(2.0, 3)
    assert c2.shape == (3, 3) and c3.shape == (6, 6)
    assert np.all(np.diag(ho.prior_cov(5.0, 3)) > np.diag(c3))
    assert math.sqrt(c3[0, 0]) == pytest.approx(ho.SIGMA_POS_M + 2.0 * ho.SIGMA_POS_MPS)
    x = np.array([1.0, 2.0, 0.0, 0.0, 0.0, 0.7])
    np.testing.assert_allclose(ho.filter_pose(pose6_to_T(x), 2), [1.0, 2.0, 0.7], atol=1e-12)
    np.testing.assert_allclose(ho.filter_pose(pose6_to_T(x), 3), x, atol=1e-12)


def test_handover_waits_for_an_autopilot_pose_then_resets_the_filter_once() -> None:
    """No autopilot pose in the first frames (the link still coming up): it waits; the first frame
    with one resets the filter to the carried pose, with the gap's covariance, and never again."""
    t_saved = time.monotonic_ns() - 2 * S
    T_saved = pose6_to_T(np.array([5.0, 1.0, 0.0, 0.0, 0.0, 0.3]))
    A_saved = pose6_to_T(np.array([-3.0, 7.0, 0.0, 0.0, 0.0, 1.2]))
    step = pose6_to_T(np.array([1.5, 0.0, 0.0, 0.0, 0.0, 0.1]))  # 1.5 m ahead, 0.1 rad left
    saved = ho.SavedHandover(A_saved, 50_000, ho.unix_of(t_saved))
    calls: list[tuple[np.ndarray, np.ndarray]] = []
    answers: list[AutopilotPose | None] = [None, None]

    def pose_at(t_ns: int) -> AutopilotPose | None:
        if answers:
            return answers.pop(0)
        boot_ms = 50_000 + (t_ns - t_saved) // 1_000_000
        return AutopilotPose(t_ns, A_saved @ step, int(boot_ms))

    h = ho.Handover(saved, T_saved, 3, pose_at, lambda x, c: calls.append((x, c)))
    now = time.monotonic_ns()
    assert [h.on_frame(now + k * S // 30) for k in range(5)] == [False, False, True, False, False]
    assert len(calls) == 1 and not h.pending
    x, cov = calls[0]
    np.testing.assert_allclose(x, T_to_pose6(T_saved @ step), atol=1e-9)
    assert math.sqrt(cov[0, 0]) == pytest.approx(ho.SIGMA_POS_M + 2.0 * ho.SIGMA_POS_MPS, rel=0.05)
    assert h.outcome is not None and "carried 1.50 m" in h.outcome


def test_handover_gives_up_without_an_autopilot_pose(caplog: pytest.LogCaptureFixture) -> None:
    saved = ho.SavedHandover(np.eye(4), 0, 0.0)
    h = ho.Handover(saved, np.eye(4), 2, lambda t: None, lambda x, c: pytest.fail("reset without a pose"))
    frames = [10 * S + k * S // 30 for k in range(int(30 * ho.WAIT_S) + 5)]  # 30 Hz from t = 10 s
    assert not any(h.on_frame(t) for t in frames[: int(30 * ho.WAIT_S)])
    assert h.pending  # still within WAIT_S of the first frame
    assert not any(h.on_frame(t) for t in frames[int(30 * ho.WAIT_S) :])
    assert not h.pending and h.outcome == f"no autopilot pose within {ho.WAIT_S:g} s of the first frame"
    assert "relocalising against the map alone" in caplog.text


def test_saved_handover_round_trips_through_the_map_file_and_a_bad_one_costs_only_itself(tmp_path: Path) -> None:
    A = pose6_to_T(np.array([1.0, -2.0, 0.1, 0.02, -0.01, 2.5]))
    doc = ho.SavedHandover(A, 123_456, 1.7e9).to_doc()
    store = MapStore(tmp_path, "r1")
    store.save({"x": np.arange(3)}, 5, doc)
    back = ho.SavedHandover.from_doc(store.load()["handover"])
    np.testing.assert_array_equal(back.T, A)
    assert (back.boot_ms, back.unix_s) == (123_456, 1.7e9)
    store.save({"x": np.arange(3)}, 6)  # a save without an autopilot pose (no MAVLink link)
    assert store.load()["handover"] is None
    for bad, why in [
        ({"T": np.eye(3), "boot_ms": 1, "unix_s": 0.0}, "shape"),
        ({"T": np.eye(4), "unix_s": 0.0}, "KeyError"),
        ({"T": 2 * np.eye(4), "boot_ms": 1, "unix_s": 0.0}, "not a rigid transform"),
        ([1, 2], "expected a table"),
    ]:
        with pytest.raises(PersistenceError, match=why):
            ho.SavedHandover.from_doc(bad)


def test_record_is_the_autopilot_pose_at_the_states_frame() -> None:
    A = pose6_to_T(np.array([1.0, 2.0, 0.0, 0.0, 0.0, 0.5]))
    asked: list[int] = []

    def pose_at(t_ns: int) -> AutopilotPose:
        asked.append(t_ns)
        return AutopilotPose(t_ns, A, 9_000)

    t = time.monotonic_ns() - S
    doc = ho.record(pose_at, t)
    assert asked == [t] and doc is not None and doc["boot_ms"] == 9_000
    np.testing.assert_array_equal(doc["T"], A)
    assert doc["unix_s"] == pytest.approx(time.time() - 1.0, abs=0.1)
    assert ho.record(None, t) is None and ho.record(pose_at, None) is None
    assert ho.record(lambda t: None, t) is None
    np.testing.assert_allclose(se3_inverse(doc["T"]) @ A, np.eye(4), atol=1e-12)


def test_a_restarted_daemon_continues_from_the_pose_the_autopilots_motion_carries(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Two real daemon runs on sim:// with the pose going to a mock ArduPilot over loopback UDP:
    the first run's map file records the autopilot's pose; the second, restarted in ground its
    map does not hold (the relocalising window finds nothing), resets the filter to the saved
    pose carried by the autopilot's motion across the restart: the mock drives straight at
    0.5 m/s, so the carried distance is 0.5 m/s times the gap."""
    from drivers.mavlink_mock import MockAutopilot
    from robotd.config import load_config
    from robotd.daemon import Daemon
    from robotd.pipeline.relocalise import Relocaliser
    from tests.support.daemon_runs import HANG_GUARD_S, run_until

    with MockAutopilot(sysid=7, speed_mps=0.5, yaw_rate_radps=0.0) as ap:
        cfg = load_config(
            None,
            {
                "camera": {"url": "sim://?fps=10"},
                "vehicle": {"url": "sim://?fps=10"},
                "zenoh": {"enabled": False},
                "mavlink": {"enabled": True, "url": ap.url, "system_id": 7},
                "persistence": {"state_dir": str(tmp_path), "save_period_s": 0.0, "resume": True},
            },
        )
        d1 = Daemon(cfg, duration_s=HANG_GUARD_S, environ={})
        status, reached = run_until(d1, lambda: d1.stats.steps >= 15)
        assert status == 0 and reached, d1.stop_reason
        saved = MapStore(tmp_path, cfg.robot.id).load()["handover"]
        assert saved is not None, "the map file holds no autopilot pose"
        ho.SavedHandover.from_doc(saved)
        # the second run restarts where the map holds nothing it can see
        monkeypatch.setattr(Relocaliser, "attempt", lambda self, *a: self._count_down())
        d2 = Daemon(cfg, duration_s=HANG_GUARD_S, environ={})
        status, reached = run_until(d2, lambda: d2.handover is not None and d2.handover.outcome is not None)
        assert status == 0 and reached, (d2.stop_reason, d2.handover)
        assert d2.health_doc()["handover"] == d2.handover.outcome  # type: ignore[union-attr]
    assert d2.handover is not None and d2.handover.outcome is not None
    words = d2.handover.outcome.split()  # "carried 1.23 m over a 2.5 s gap"
    assert words[0] == "carried", d2.handover.outcome
    moved_m, gap_s = float(words[1]), float(words[5])
    assert moved_m == pytest.approx(0.5 * gap_s, abs=0.06), d2.handover.outcome


@pytest.mark.parametrize(
    ("x", "cov", "why"),
    [
        (np.zeros(6), np.full((6, 6), np.nan), "finite (6, 6) covariance"),
        (np.zeros(6), np.eye(3), "finite (6, 6) covariance"),
        (np.r_[np.zeros(5), np.inf], np.eye(6), "finite pose of 6 values"),
        (np.zeros(6), np.diag([1.0, 1, 1, 1, 1, -1]), "not symmetric positive semi-definite"),
    ],
)
def test_a_bad_carried_pose_is_refused_and_the_filter_kept(x: np.ndarray, cov: np.ndarray, why: str) -> None:
    """``Pipeline.hand_over`` checks what it is handed before touching the filter, and the handover
    reports the refusal in its outcome instead of ending the SLAM thread."""
    cfg = load_config(None)
    p = Pipeline(cfg, RectifiedStereo(700.0, 320.0, 200.0, 0.12, 640, 400), np.random.default_rng(0))
    before = p.estimator.estimate()
    with pytest.raises(InputError, match=re.escape(why)):
        p.hand_over(x, cov)
    after = p.estimator.estimate()
    np.testing.assert_array_equal(after.T_world_robot, before.T_world_robot)
    np.testing.assert_array_equal(after.cov, before.cov)

    saved = ho.SavedHandover(np.eye(4), 50_000, ho.unix_of(time.monotonic_ns()))
    h = ho.Handover(saved, np.eye(4), 3, lambda t: AutopilotPose(t, np.eye(4), 50_000), lambda *_: p.hand_over(x, cov))
    assert h.on_frame(time.monotonic_ns()) is False and not h.pending
    assert h.outcome is not None and h.outcome.startswith("refused: handover:") and why in h.outcome


def test_a_carried_covariance_with_rounding_in_it_is_taken() -> None:
    """A covariance turned into another frame (R D Rᵀ, one variance 0) carries rounding: a few
    1e-17 off symmetric and an eigenvalue just below 0. The check must not refuse it."""
    cfg = load_config(None)
    p = Pipeline(cfg, RectifiedStereo(700.0, 320.0, 200.0, 0.12, 640, 400), np.random.default_rng(0))
    R = pose6_to_T(np.array([0, 0, 0, -0.72, -0.6, 0.94]))[:3, :3]
    block = R @ np.diag([0.04, 0.09, 0.0]) @ R.T
    cov = np.zeros((6, 6))
    cov[:3, :3], cov[3:, 3:] = block, np.diag([1e-4, 1e-4, 1e-3])
    assert np.linalg.eigvalsh(cov).min() < 0.0  # the rounding this test is about
    p.hand_over(np.r_[1.0, 2.0, 0.0, 0.0, 0.0, 0.5], cov)
    np.testing.assert_allclose(p.estimator.estimate().xyz_W_m[:2], [1.0, 2.0], atol=1e-9)
