"""The landmark registry (robotd.slam.landmarks): every store that keeps something per landmark
holds the filter's landmarks, whatever happened to the map.

The property test drives a real pipeline's filter and stores (the descriptors, the reported
covariance's anchors, subscribed by ``Pipeline.__init__``) through random sequences of frames
that add and re-observe landmarks (those not re-observed in view are pruned by the filter's
existence counter), frames the filter refuses or that fail before the update, relocalisations
and map loads, and checks after each that the id sets agree. The replay-level test runs
``robotd replay`` on the simulated rover and compares the descriptor store with the filter at the
end.
"""

from __future__ import annotations

import contextlib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from robotd.config import load_config
from robotd.core.errors import InputError
from robotd.core.msgs import Observations
from robotd.core.stereo import RectifiedStereo
from robotd.pipeline.step import Pipeline
from robotd.slam.landmarks import LandmarkRegistry

RIG = RectifiedStereo(700.0, 320.0, 200.0, 0.12, 640, 400)


class Store:
    """A store that keeps the ids it was given and forgets what it is told to."""

    def __init__(self) -> None:
        self.ids: set[int] = set()

    def forget(self, ids: np.ndarray) -> None:
        self.ids.difference_update(np.asarray(ids).tolist())


class Filter:
    """A filter whose update takes what it is given and prunes what the test says."""

    def __init__(self) -> None:
        self.ids: set[int] = set()
        self.prune: list[int] = []

    def update(self, obs: Observations):
        from robotd.core.msgs import UpdateReport

        self.ids.update(obs.ids[obs.is_new].tolist())
        pruned = np.array(sorted(set(self.prune) & self.ids), np.int64)
        self.ids.difference_update(pruned.tolist())
        return UpdateReport(n_new=int(obs.is_new.sum()), pruned_ids=pruned)


def _obs(t_ns: int, ids: np.ndarray, is_new: np.ndarray) -> Observations:
    n = ids.size
    xyz = np.tile([5.0, 0.0, 0.0], (n, 1))
    return Observations(t_ns, xyz, np.tile(np.eye(3) * 1e-2, (n, 1, 1)), ids.astype(np.int64), is_new)


def test_pruned_and_refused_landmarks_leave_every_store() -> None:
    f, a, b = Filter(), Store(), Store()
    reg = LandmarkRegistry(f)  # type: ignore[arg-type]
    reg.subscribe(a)
    reg.subscribe(b)

    def propose(ids: list[int]) -> np.ndarray:
        arr = np.array(ids, np.int64)
        for s in (a, b):
            s.ids.update(ids)
        reg.propose(arr)
        return arr

    with reg.frame():
        new = propose([0, 1, 2])
        reg.update(_obs(1, new, np.ones(3, bool)))
    assert reg.ids.tolist() == [0, 1, 2] and a.ids == b.ids == f.ids == {0, 1, 2}
    # the filter prunes 1 while taking 3
    f.prune = [1]
    with reg.frame():
        new = propose([3])
        reg.update(_obs(2, np.r_[0, new], np.array([False, True])))
    assert reg.ids.tolist() == [0, 2, 3] and a.ids == b.ids == f.ids == {0, 2, 3}
    # a frame that fails before the filter's update: its new landmarks leave every store
    with pytest.raises(InputError), reg.frame():
        propose([4, 5])
        raise InputError("predict refused")
    assert reg.ids.tolist() == [0, 2, 3] and a.ids == b.ids == {0, 2, 3} and reg.pending.size == 0
    # a proposed landmark the update was not given leaves every store too
    f.prune = []
    with reg.frame():
        new = propose([6, 7])
        reg.update(_obs(3, new[:1], np.ones(1, bool)))
    assert reg.ids.tolist() == [0, 2, 3, 6] and a.ids == b.ids == f.ids == {0, 2, 3, 6}
    # a loaded map: the old map leaves every store
    reg.reset(np.array([10, 11]))
    assert reg.ids.tolist() == [10, 11] and a.ids == b.ids == set()


# --- the property test, on a real pipeline's filter and stores -------------------------------

frames = st.tuples(
    st.just("frame"),
    st.integers(0, 4),  # new landmarks
    st.integers(0, 3),  # of the map's landmarks, re-observe every one, 2 in 3, 1 in 3, none
    st.sampled_from(["taken", "refused", "failed"]),  # the filter takes the frame; refuses it; predict fails
)
others = st.tuples(st.sampled_from(["save", "load", "relocalise"]), st.just(0), st.just(0), st.just(""))
ACTIONS = st.lists(st.one_of(frames, others), min_size=1, max_size=14)


def _pipeline(filt: str) -> Pipeline:
    cfg = load_config(None, {"slam": {"filter": filt, "n_particles": 8}})
    p = Pipeline(cfg, RIG, np.random.default_rng(3))
    p.frontend.detect(np.zeros((RIG.height, RIG.width), np.uint8), np.zeros((RIG.height, RIG.width), np.uint8))
    return p


def _check(p: Pipeline) -> None:
    ids = p.registry.ids
    db = p.frontend.descriptors
    assert db is not None
    np.testing.assert_array_equal(np.sort(p.estimator.landmark_ids()), ids)
    np.testing.assert_array_equal(db.ids, ids)
    assert p.registry.pending.size == 0
    anchors = p.covariance.anchors
    if anchors is not None:  # the anchors keep none for a loaded map's landmarks: a subset
        assert set(anchors.anchored_ids.tolist()) <= set(ids.tolist())


def _frame(p: Pipeline, t_ns: int, n_new: int, every: int, how: str, world: dict[int, np.ndarray]) -> None:
    """One frame as Pipeline.step makes it after identification: commit, propose, update, report."""
    db = p.frontend.descriptors
    assert db is not None
    live = p.registry.ids
    old = live[np.arange(live.size) % 3 < 3 - every]
    rng = np.random.default_rng(t_ns)
    with contextlib.suppress(InputError), p.registry.frame():
        new = db.add(rng.integers(0, 256, (n_new, db.dim), np.uint8))
        p.registry.propose(new)
        for i in new.tolist():
            world[i] = np.r_[rng.uniform(3.0, 8.0), rng.uniform(-1.0, 1.0, 2)]
        if how == "failed":
            raise InputError("predict refused for the test")
        ids = np.r_[old, new]
        is_new = np.r_[np.zeros(old.size, bool), np.ones(new.size, bool)]
        if how == "refused":  # a landmark the map does not hold: the filter refuses the frame whole
            ids, is_new = np.r_[ids, db.next_id + 100], np.r_[is_new, False]
        xyz = np.array([world.get(int(i), np.r_[5.0, 0.0, 0.0]) for i in ids]).reshape(-1, 3)
        obs = Observations(t_ns, xyz, np.tile(np.eye(3) * 1e-3, (ids.size, 1, 1)), ids.astype(np.int64), is_new)
        p.registry.update(obs)
        p.covariance.report(p.estimator.estimate(), obs)


@pytest.mark.parametrize("filt", ["fastslam2", "ekf"])
@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(actions=ACTIONS)
def test_every_store_holds_the_filters_landmarks_whatever_happens(filt: str, actions: list) -> None:
    p = _pipeline(filt)
    world: dict[int, np.ndarray] = {}
    saved = None
    t_ns = 10**9
    for kind, n_new, every, how in actions:
        t_ns += 100_000_000
        if kind == "frame":
            _frame(p, t_ns, n_new, every, how, world)
        elif kind == "save":
            saved = p.state_dict()
        elif kind == "load" and saved is not None:
            p.load_state_dict(saved)
        elif kind == "relocalise":
            p.estimator.reset_pose(np.zeros(6), None)
        _check(p)


def test_a_replay_ends_with_as_many_descriptors_as_landmarks(monkeypatch) -> None:
    """``robotd replay`` on the simulated rover: at the end the descriptor store holds exactly the
    filter's landmarks (the soak once found 233 835 descriptors for 2 675 landmarks)."""
    from robotd.tools.replay import replay

    seen: list[Pipeline] = []
    pruned = []
    real_step = Pipeline.step

    def step(self: Pipeline, frame, increment=None):
        if not seen or seen[-1] is not self:
            seen.append(self)
        r = real_step(self, frame, increment)
        pruned.append(r.report.n_pruned)
        return r

    monkeypatch.setattr(Pipeline, "step", step)
    cfg = load_config(None, {"slam": {"n_particles": 20, "max_new_per_frame": 15}})
    summary = replay(cfg, "sim://?fps=15&seed=4&duration=4&realtime=0", progress=False)
    (p,) = seen
    db = p.frontend.descriptors
    assert db is not None and summary["frames"] > 30 and sum(pruned) > 0
    assert db.n == p.estimator.landmark_ids().size == p.registry.n == summary["landmarks"] > 0
    np.testing.assert_array_equal(db.ids, p.registry.ids)
