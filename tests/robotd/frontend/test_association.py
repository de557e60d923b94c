"""Landmark descriptors and identification (docs/math.md §4.3)."""

from __future__ import annotations

import numpy as np
import pytest

from robotd.core.errors import ConfigError, InputError, PersistenceError
from robotd.frontend.association import (
    IDENTIFIED,
    NEW,
    REJECTED,
    AssociationParams,
    Correspondences,
    LandmarkDescriptors,
)
from robotd.frontend.stereo_match import normalise_descriptors


def _unit(rng: np.random.Generator, n: int, d: int = 64) -> np.ndarray:
    return normalise_descriptors(rng.normal(size=(n, d)), False)


def test_identify_new_then_identified(rng):
    db = LandmarkDescriptors(64, binary=False)
    desc = _unit(rng, 30)
    c = db.identify(desc)
    assert np.all(c.status == NEW)
    db.commit(c, desc)
    np.testing.assert_array_equal(c.ids, np.arange(30))
    assert db.n == 30 and db.next_id == 30
    # the same landmarks seen again with a little descriptor noise, shuffled, plus 10 unseen ones
    perm = rng.permutation(30)
    seen = normalise_descriptors(desc[perm] + 0.02 * rng.normal(size=(30, 64)), False)
    fresh = _unit(rng, 10)
    c2 = db.identify(np.r_[seen, fresh])
    assert np.all(c2.status[:30] == IDENTIFIED)
    np.testing.assert_array_equal(c2.ids[:30], perm)
    assert np.all(c2.status[30:] == NEW) and np.all(c2.ids[30:] == -1)
    db.commit(c2, np.r_[seen, fresh])
    np.testing.assert_array_equal(c2.ids[30:], np.arange(30, 40))  # global ids are never reused
    # the stored descriptor is the latest accepted observation's
    np.testing.assert_allclose(db.desc[db.rows(perm)], seen)


def test_candidate_restriction_and_ambiguity(rng):
    db = LandmarkDescriptors(64, binary=False)
    base = _unit(rng, 5)
    twin = normalise_descriptors(base[:1] + 0.01 * rng.normal(size=(1, 64)), False)
    desc = np.r_[base, twin]  # landmark 5 looks like landmark 0 (repeated texture)
    db.commit(db.identify(desc), desc)
    # a measurement halfway between landmark 0 and its twin, and one of landmark 1
    q = normalise_descriptors(np.r_[0.5 * (base[:1] + twin), base[1:2]], False)
    c = db.identify(q)
    # landmark 0 has a near-twin: the ratio test cannot decide; it is rejected, not made new
    assert c.status[0] == REJECTED and c.status[1] == IDENTIFIED and c.ids[1] == 1
    assert db.identify(q, params=AssociationParams(ambiguous_is_rejected=False)).status[0] == NEW
    # restricted to landmarks predicted in view (the twin is not), the match is unambiguous
    c = db.identify(q, candidate_ids=np.array([0, 1, 2]))
    assert np.all(c.status == IDENTIFIED) and c.ids.tolist() == [0, 1]
    # unknown candidate ids are ignored
    c = db.identify(q, candidate_ids=np.array([1, 99]))
    assert c.status[1] == IDENTIFIED and c.status[0] != IDENTIFIED


def test_binary_descriptors_and_cross_check(rng):
    db = LandmarkDescriptors(32, binary=True)
    desc = rng.integers(0, 256, (20, 32), dtype=np.uint8)
    db.commit(db.identify(desc), desc)
    # two measurements both nearest to landmark 3; the cross-check keeps the closer one only
    m = np.stack([desc[3], desc[3]])
    m[1, :2] ^= 0xFF  # 16 bits away
    c = db.identify(m)
    assert c.status[0] == IDENTIFIED and c.ids[0] == 3
    assert c.status[1] != IDENTIFIED


def test_reject_commit_a_subset_of_new_and_forget(rng):
    db = LandmarkDescriptors(64, binary=False)
    desc = _unit(rng, 6)
    c = db.identify(desc)
    db.commit(c, desc, new=np.array([4, 1]))  # only these become landmarks, in index order
    assert c.ids.tolist() == [-1, 0, -1, -1, 1, -1] and db.n == 2 and db.next_id == 2
    np.testing.assert_allclose(db.desc, desc[[1, 4]])
    c = db.identify(desc[[1, 4]])
    c.reject(np.array([True, False]))
    db.commit(c, desc[[1, 4]])
    assert c.ids.tolist() == [-1, 1] and db.n == 2  # rejected: neither updated nor initialised
    db.forget(np.array([0, 99]))  # what the filter pruned; unknown ids are ignored
    assert db.ids.tolist() == [1] and not db.contains(np.array([0]))[0]
    back = LandmarkDescriptors.from_state_dict(db.state_dict())
    np.testing.assert_array_equal(back.ids, db.ids)
    np.testing.assert_array_equal(back.desc, db.desc)
    assert back.next_id == db.next_id == 2


def test_state_of_old_maps_with_an_existence_array_still_loads(rng):
    desc = _unit(rng, 3)
    old = {"dim": 64, "binary": False, "ids": np.arange(3), "desc": desc, "existence": np.ones(3), "next_id": 3}
    db = LandmarkDescriptors.from_state_dict(old)
    assert db.ids.tolist() == [0, 1, 2] and db.next_id == 3
    with pytest.raises(PersistenceError, match=r"database.desc: expected shape \(3, 64\), got \(2, 64\)"):
        LandmarkDescriptors.from_state_dict({**old, "desc": desc[:2]})
    with pytest.raises(PersistenceError, match="database.binary: missing"):
        LandmarkDescriptors.from_state_dict({"dim": 64})


def test_bad_inputs(rng):
    db = LandmarkDescriptors(64, binary=False)
    with pytest.raises(InputError, match=r"\(N, 64\)"):
        db.identify(np.zeros((3, 32), np.float32))
    with pytest.raises(InputError, match="unknown landmark ids"):
        db.rows(np.array([5]))
    with pytest.raises(ConfigError, match="ratio"):
        AssociationParams(ratio=1.5)
    empty = db.identify(np.zeros((0, 64), np.float32))
    assert isinstance(empty, Correspondences) and empty.n == 0


# ------------------------------------------------------------------ guided matching


def _guided_store(rng: np.random.Generator, k: int) -> tuple[LandmarkDescriptors, np.ndarray, np.ndarray]:
    store = LandmarkDescriptors(32, True)
    desc = rng.integers(0, 256, (k, 32), dtype=np.uint8)
    ids = store.add(desc)
    return store, ids, desc


def test_guided_matching_finds_each_landmark_near_its_prediction_only():
    rng = np.random.default_rng(4)
    store, ids, desc = _guided_store(rng, 30)
    pred = np.c_[rng.uniform(50, 600, 30), np.zeros(30), rng.uniform(50, 350, 30)]
    pred[:, 1] = pred[:, 0] - rng.uniform(5, 40, 30)
    # the measurements: the landmarks 3 px from their predictions, then a decoy with the
    # descriptor of landmark 0 (repeated texture) 200 px away from it
    meas_px = pred + np.array([3.0, 3.0, -2.0])
    decoy = pred[0] + np.array([200.0, 200.0, 0.0])
    px = np.r_[meas_px, decoy[None]]
    d = np.r_[desc, desc[:1]]
    corr = store.identify_guided(d, px, ids, pred, AssociationParams(guided_radius_px=10.0))
    assert np.all(corr.status[:30] == IDENTIFIED)
    np.testing.assert_array_equal(corr.ids[:30], ids)
    assert corr.status[30] == NEW
    # the plain descriptor search cannot tell the decoy from the landmark
    plain = store.identify(d, ids)
    assert plain.status[0] != IDENTIFIED or plain.status[30] != NEW


def test_guided_matching_ignores_rows_on_a_planar_map_and_rejects_far_disparities():
    rng = np.random.default_rng(5)
    store, ids, desc = _guided_store(rng, 5)
    pred = np.array([[100.0, 80.0, 50.0]] * 5) + np.arange(5)[:, None] * np.array([100.0, 100.0, 0.0])
    px = pred.copy()
    px[:, 2] += 120.0  # every row off by 120 px
    p = AssociationParams(guided_radius_px=10.0)
    assert np.all(store.identify_guided(desc, px, ids, pred, p).status == NEW)
    assert np.all(store.identify_guided(desc, px, ids, pred, p, rows_known=False).status == IDENTIFIED)
    px2 = pred.copy()
    px2[:, 1] -= 30.0  # disparity 30 px larger than predicted: a different depth
    assert np.all(store.identify_guided(desc, px2, ids, pred, p).status == NEW)


def test_guided_matching_with_no_descriptor_under_the_limit_finds_nothing():
    rng = np.random.default_rng(6)
    store, ids, desc = _guided_store(rng, 4)
    pred = np.array([[100.0, 80.0, 50.0]] * 4)
    corr = store.identify_guided(~desc, pred, ids, pred, AssociationParams(guided_radius_px=10.0))
    assert np.all(corr.status == NEW) and np.all(corr.ids == -1)


def test_guided_matching_settings_are_checked():
    with pytest.raises(ConfigError, match="guided"):
        AssociationParams(guided_radius_px=0.0)
