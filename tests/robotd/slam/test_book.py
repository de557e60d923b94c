"""The existence rule counts a miss only where a landmark can be recognised (robotd/slam/_book.py).

A landmark made 4 m ahead and seen again from 10 m, or from the side, is in view but not matched:
its descriptor was taken at another scale or angle. Counting those frames as misses deleted the
whole first pass of a loop before the rover came near enough to match it (docs/slam.md "Which
landmarks the map keeps").
"""

from __future__ import annotations

import numpy as np
import pytest

from robotd.core.msgs import Observations
from robotd.core.statecheck import StateTable
from robotd.slam._book import RECOGNISE_ANGLE_DEG, RECOGNISE_SCALE, LandmarkBook
from robotd.slam.factory import make_estimator
from robotd.slam.params import SlamParams

AHEAD = np.array([[1.0, 0.0, 0.0]])  # landmark -> robot, world frame


def _noted(dist: float) -> tuple[LandmarkBook, np.ndarray]:
    book = LandmarkBook()
    s = book.allocate(np.array([7]))
    book.note_views(s, np.array([dist]), AHEAD)
    return book, s


def test_recognisable_within_the_seen_range_and_angle() -> None:
    book, s = _noted(4.0)
    book.note_views(s, np.array([3.0]), AHEAD)  # seen from 3 and 4 m
    assert book.recognisable(s, np.array([3.0]), AHEAD)[0]
    assert book.recognisable(s, np.array([4.0 * RECOGNISE_SCALE * 0.99]), AHEAD)[0]
    assert not book.recognisable(s, np.array([4.0 * RECOGNISE_SCALE * 1.01]), AHEAD)[0]
    assert not book.recognisable(s, np.array([3.0 / RECOGNISE_SCALE / 1.01]), AHEAD)[0]
    for deg, ok in ((RECOGNISE_ANGLE_DEG - 1, True), (RECOGNISE_ANGLE_DEG + 1, False)):
        a = np.radians(deg)
        side = np.array([[np.cos(a), np.sin(a), 0.0]])
        assert book.recognisable(s, np.array([3.5]), side)[0] == ok, deg


def test_a_landmark_with_no_view_noted_is_recognisable_anywhere() -> None:
    book = LandmarkBook()
    s = book.allocate(np.array([3]))
    assert book.recognisable(s, np.array([100.0]), -AHEAD)[0]


def test_views_survive_the_state_and_old_states_load() -> None:
    book, s = _noted(4.0)
    book.allocate(np.array([9]))
    state = book.state_dict()
    again = LandmarkBook.from_state(StateTable(state, "book"), compact=False)
    for key in ("near", "far", "view"):
        np.testing.assert_array_equal(getattr(again, key)[: book.n_slots], getattr(book, key)[: book.n_slots])
    assert not again.recognisable(s, np.array([10.0]), AHEAD)[0]
    old = {k: v for k, v in state.items() if k in ("book_slot_id", "book_counter")}  # a map saved before
    legacy = LandmarkBook.from_state(StateTable(old, "book"), compact=False)
    assert legacy.recognisable(s, np.array([10.0]), AHEAD)[0]


def test_implausible_views_are_refused_by_name() -> None:
    from robotd.core.errors import PersistenceError

    book, _ = _noted(4.0)
    state = book.state_dict()
    state["book_near"] = state["book_near"] + 10.0  # nearer than it is far: impossible
    with pytest.raises(PersistenceError, match="book_near"):
        LandmarkBook.from_state(StateTable(state, "book"), compact=False)


@pytest.mark.parametrize("filt", ["fastslam2", "ekf"])
def test_unrecognisable_landmarks_survive_and_recognisable_misses_die(filt: str) -> None:
    # A at 4 m ahead, B at 3 m ahead and 1 m right; then the robot stands back (A at 10 m: in view,
    # in range, beyond the seen range) or steps back 0.5 m (A at 4.5 m: recognisable), sees B only
    pts = np.array([[4.0, 0.0, 0.0], [3.0, 1.0, 0.0]])
    cov = np.tile(np.eye(3) * 1e-4, (2, 1, 1))
    for back, survives in ((6.0, True), (0.5, False)):
        e = make_estimator(SlamParams(filter=filt, dim=3, n_particles=5, max_range_m=30.0), np.random.default_rng(0))
        e.update(Observations(1, pts, cov, np.array([0, 1]), np.ones(2, bool)))
        e.reset_pose(np.array([-back, 0, 0, 0, 0, 0.0]))
        for t in range(2, 8):
            e.update(Observations(t, pts[1:] + np.array([back, 0.0, 0.0]), cov[1:], np.array([1]), np.zeros(1, bool)))
        assert (0 in e.landmark_ids()) == survives, (back, e.landmark_ids())


@pytest.mark.parametrize("filt", ["fastslam2", "ekf"])
def test_held_landmarks_are_never_counted_missed(filt: str) -> None:
    # the loaded map while the pose is searched for in it (robotd/pipeline/relocalise.py): A (id 0)
    # is in view and recognisable, and missed; held, it stays; released, it goes
    pts = np.array([[4.0, 0.0, 0.0], [3.0, 1.0, 0.0]])
    cov = np.tile(np.eye(3) * 1e-4, (2, 1, 1))
    e = make_estimator(SlamParams(filter=filt, dim=3, n_particles=5, max_range_m=30.0), np.random.default_rng(0))
    e.update(Observations(1, pts, cov, np.array([0, 1]), np.ones(2, bool)))
    e.hold_landmarks(1)
    for t in range(2, 8):
        e.update(Observations(t, pts[1:], cov[1:], np.array([1]), np.zeros(1, bool)))
    assert 0 in e.landmark_ids()
    e.hold_landmarks(0)
    for t in range(8, 11):
        e.update(Observations(t, pts[1:], cov[1:], np.array([1]), np.zeros(1, bool)))
    assert 0 not in e.landmark_ids()
