"""Copy-on-write landmark store: behaves exactly like dense per-particle arrays."""

from __future__ import annotations

import numpy as np
import pytest

from robotd.slam._store import LandmarkStore


@pytest.mark.parametrize("block", [1, 4, 64])
def test_store_matches_dense_reference_under_random_operations(block: int) -> None:
    rng = np.random.default_rng(0)
    P, dm = 12, 3
    st = LandmarkStore(P, dm, block)
    dense_m = np.zeros((P, 0, dm))
    dense_c = np.zeros((P, 0, dm, dm))
    n = 0
    for _ in range(60):
        op = rng.integers(3)
        if op == 0 or n == 0:  # new landmarks
            k = int(rng.integers(1, 6))
            st.ensure_capacity(n + k)
            slots = np.arange(n, n + k)
            m, c = rng.normal(size=(P, k, dm)), rng.normal(size=(P, k, dm, dm))
            st.scatter(slots, m, c)
            dense_m = np.concatenate([dense_m, m], 1)
            dense_c = np.concatenate([dense_c, c], 1)
            n += k
        elif op == 1:  # update a few existing landmarks in every particle
            slots = rng.choice(n, size=min(n, 5), replace=False)
            m, c = rng.normal(size=(P, slots.size, dm)), rng.normal(size=(P, slots.size, dm, dm))
            st.scatter(slots, m, c)
            dense_m[:, slots], dense_c[:, slots] = m, c
        else:  # resample with duplicates
            idx = np.sort(rng.integers(0, P, P))
            st.select(idx)
            dense_m, dense_c = dense_m[idx], dense_c[idx]
        gm, gc = st.dense(n)
        np.testing.assert_array_equal(gm, dense_m)
        np.testing.assert_array_equal(gc, dense_c)
    # every pool block in use is referenced by the table, and nothing else is marked in use
    used = np.zeros(st.n_pool, bool)
    used[st.table.ravel()] = True
    np.testing.assert_array_equal(used, st.in_use)


def test_resampling_shares_blocks_until_written() -> None:
    st = LandmarkStore(4, 2, block=8)
    st.ensure_capacity(32)
    st.scatter(np.arange(32), np.ones((4, 32, 2)), np.ones((4, 32, 2, 2)))
    st.select(np.array([0, 0, 0, 1]))
    assert len(np.unique(st.table)) == 2 * 4  # two distinct particles × four blocks
    before = st.n_copied_blocks
    st.scatter(np.array([3]), np.full((4, 1, 2), 5.0), np.zeros((4, 1, 2, 2)))
    # only the written block (slots 0..7) is copied, for the two extra sharers of particle 0
    assert st.n_copied_blocks - before == 2
    assert np.all(st.gather(np.array([3]))[0] == 5.0)
    assert np.all(st.gather(np.array([4]))[0] == 1.0)


def test_from_dense_round_trip() -> None:
    rng = np.random.default_rng(1)
    m, c = rng.normal(size=(3, 10, 3)), rng.normal(size=(3, 10, 3, 3))
    st = LandmarkStore.from_dense(m, c, 4)
    gm, gc = st.dense(10)
    np.testing.assert_array_equal(gm, m)
    np.testing.assert_array_equal(gc, c)
    with pytest.raises(ValueError, match="block size"):
        LandmarkStore(3, 3, 0)
