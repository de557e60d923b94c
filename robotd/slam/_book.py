"""Landmark bookkeeping shared by the filters: global id -> storage slot, existence counters.

Ids are global (shared by all particles) and may be arbitrary int64 values, so they map to dense
storage slots through a dict. Existence counter (docs/math.md §8, Thrun et al. 2005 §10.3.3):
+1 when a landmark is observed, −1 when it is predicted inside the field of view and range but not
observed; a landmark is deleted when its counter falls below 0 after the frame that created it.

"Predicted inside the field of view" alone counts as a miss every frame a landmark is in view from
where its descriptor cannot be recognised: a point made 4 m ahead and approached again from 10 m, or
from the side. On a loop that deleted every landmark of the first pass before the rover got near
enough to match it (docs/slam.md "Which landmarks the map keeps"). So the book also remembers where
each landmark was seen from, the range of its observed distances and the mean direction it was seen
from, and a landmark only counts as missed where it can be recognised: its distance within
``RECOGNISE_SCALE`` of that range and its direction within ``RECOGNISE_ANGLE_DEG`` of the mean.
"""

from __future__ import annotations

import numpy as np

from robotd.core.errors import InputError, PersistenceError
from robotd.core.statecheck import COUNTER_LIMIT, ID_LIMIT, StateTable, check_finite

# where a landmark counts as recognisable (module docstring): its observed distances widened by this
# factor either way, and within this angle of the mean direction it was seen from
RECOGNISE_SCALE = 1.5
RECOGNISE_ANGLE_DEG = 45.0
_COS_ANGLE = float(np.cos(np.radians(RECOGNISE_ANGLE_DEG)))


class LandmarkBook:
    """Slots ``0 … n_slots-1`` of the filter's landmark storage; freed slots are reused (FastSLAM)."""

    def __init__(self, capacity: int = 64) -> None:
        self.id_to_slot: dict[int, int] = {}
        self.slot_id = np.full(capacity, -1, np.int64)  # (cap,) id per slot, -1 = free
        self.counter = np.zeros(capacity, np.int64)  # (cap,) existence counter
        # where each landmark was seen from: nearest and farthest distance [m], and the sum of the
        # unit directions (world frame, landmark -> robot) it was observed along; zero = not yet
        self.near = np.zeros(capacity)
        self.far = np.zeros(capacity)
        self.view = np.zeros((capacity, 3))
        self.n_slots = 0  # high-water mark: slots >= n_slots were never used
        self.held_below = 0  # landmarks with smaller ids are never counted missed (Estimator.hold_landmarks)
        self.free: list[int] = []

    @property
    def capacity(self) -> int:
        return int(self.slot_id.shape[0])

    @property
    def n(self) -> int:
        return len(self.id_to_slot)

    def active_slots(self) -> np.ndarray:
        """(M,) slots in use, ascending."""
        s = np.flatnonzero(self.slot_id[: self.n_slots] >= 0)
        return s

    def check(self, ids: np.ndarray, is_new: np.ndarray) -> None:
        """Raise InputError (before any state change) when a new id exists or an old id is unknown."""
        if ids.size and int(ids.min()) < 0:
            raise InputError(f"Observations.ids: expected non-negative ids, got {int(ids.min())}")
        for i, new in zip(ids.tolist(), is_new.tolist()):
            known = i in self.id_to_slot
            if new and known:
                raise InputError(f"Observations: landmark id {i} is marked new but is already in the map")
            if not new and not known:
                raise InputError(f"Observations: landmark id {i} is not in the map (never initialised or pruned)")

    def slots_of(self, ids: np.ndarray) -> np.ndarray:
        """(N,) slots of known ids."""
        return np.fromiter((self.id_to_slot[int(i)] for i in ids), np.int64, count=len(ids))

    def allocate(self, ids: np.ndarray, reuse: bool = True) -> np.ndarray:
        """Slots for new ids (reusing freed slots when ``reuse``); grows ``capacity`` as needed.

        Counters start at 1: the creating observation counts. The caller grows its own arrays to
        ``capacity`` (see :meth:`grow_to`).
        """
        out = np.empty(len(ids), np.int64)
        for k, i in enumerate(ids.tolist()):
            if reuse and self.free:
                s = self.free.pop()
            else:
                s = self.n_slots
                self.n_slots += 1
                if s >= self.capacity:
                    self._grow(max(2 * self.capacity, s + 1))
            self.id_to_slot[int(i)] = s
            self.slot_id[s] = i
            self.counter[s] = 1
            self.near[s] = self.far[s] = 0.0
            self.view[s] = 0.0
            out[k] = s
        return out

    def _grow(self, cap: int) -> None:
        extra = cap - self.capacity
        self.slot_id = np.concatenate([self.slot_id, np.full(extra, -1, np.int64)])
        self.counter = np.concatenate([self.counter, np.zeros(extra, np.int64)])
        self.near = np.concatenate([self.near, np.zeros(extra)])
        self.far = np.concatenate([self.far, np.zeros(extra)])
        self.view = np.concatenate([self.view, np.zeros((extra, 3))])

    def release(self, slots: np.ndarray) -> None:
        for s in slots.tolist():
            del self.id_to_slot[int(self.slot_id[s])]
            self.slot_id[s] = -1
            self.counter[s] = 0
            self.near[s] = self.far[s] = 0.0
            self.view[s] = 0.0
            self.free.append(int(s))

    def note_views(self, slots: np.ndarray, dist: np.ndarray, dirs: np.ndarray) -> None:
        """Slots observed (or created) this frame, at distances ``dist`` (N,) [m] along unit
        directions ``dirs`` (N, 2|3) (world frame, landmark -> robot): widen their seen range, add
        to their mean direction."""
        if slots.size == 0:
            return
        seen = self.far[slots] > 0
        self.near[slots] = np.where(seen, np.minimum(self.near[slots], dist), dist)
        self.far[slots] = np.maximum(self.far[slots], dist)
        self.view[slots, : dirs.shape[1]] += dirs

    def recognisable(self, slots: np.ndarray, dist: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """(N,) True where ``slots``, at distances ``dist`` along directions ``dirs`` (as
        :meth:`note_views`), can be recognised: within ``RECOGNISE_SCALE`` of their seen range and
        ``RECOGNISE_ANGLE_DEG`` of their mean direction. A landmark with no view noted (a map saved
        before the book kept them) is recognisable wherever it is in view."""
        v = self.view[slots, : dirs.shape[1]]
        norm = np.linalg.norm(v, axis=1)
        known = (self.far[slots] > 0) & (norm > 0)
        ok = (dist >= self.near[slots] / RECOGNISE_SCALE) & (dist <= self.far[slots] * RECOGNISE_SCALE)
        ok &= np.sum(v * dirs, axis=1) >= _COS_ANGLE * np.where(known, norm, 1.0)
        return ~known | ok

    def existence_update(self, observed: np.ndarray, expected: np.ndarray, born: np.ndarray) -> np.ndarray:
        """Apply the counter rule; return the slots to delete.

        Args:
            observed: slots observed this frame (+1; new ones already start at 1).
            expected: slots predicted visible this frame (−1 when not observed).
            born: slots created this frame (never deleted in their first frame).
        """
        self.counter[observed] += 1
        missed = np.setdiff1d(expected, np.concatenate([observed, born]))
        if self.held_below:
            missed = missed[self.slot_id[missed] >= self.held_below]
        self.counter[missed] -= 1
        return missed[self.counter[missed] < 0]

    def compact(self) -> np.ndarray:
        """Renumber the active slots to 0 … n-1 (EKF storage); returns the old slots in new order."""
        keep = self.active_slots()
        ids = self.slot_id[keep].copy()
        cnt = self.counter[keep].copy()
        near, far, view = self.near[keep].copy(), self.far[keep].copy(), self.view[keep].copy()
        self.slot_id[:] = -1
        self.counter[:] = 0
        self.near[:] = self.far[:] = 0.0
        self.view[:] = 0.0
        self.slot_id[: len(keep)] = ids
        self.counter[: len(keep)] = cnt
        self.near[: len(keep)], self.far[: len(keep)], self.view[: len(keep)] = near, far, view
        self.n_slots = len(keep)
        self.free = []
        self.id_to_slot = {int(i): k for k, i in enumerate(ids.tolist())}
        return keep

    def state_dict(self) -> dict[str, np.ndarray | int]:
        return {
            "book_slot_id": self.slot_id[: self.n_slots].copy(),
            "book_counter": self.counter[: self.n_slots].copy(),
            "book_near": self.near[: self.n_slots].copy(),
            "book_far": self.far[: self.n_slots].copy(),
            "book_view": self.view[: self.n_slots].copy(),
        }

    @classmethod
    def from_state(cls, st: StateTable, compact: bool) -> LandmarkBook:
        """The book of a saved filter state (keys ``book_slot_id``, ``book_counter``), checked:
        int64 arrays of one length, ids in [0, ID_LIMIT) and unique, -1 for a free slot (none in a
        ``compact`` book: the EKF's), counters of plausible size; where each landmark was seen from
        (``book_near``, ``book_far``, ``book_view``: finite, non-negative distances), absent in maps
        saved before the book kept it (then none is known). PersistenceError otherwise."""
        slot_id = st.array("book_slot_id", "<i8", (None,))
        counter = st.array("book_counter", "<i8", slot_id.shape)
        if slot_id.size and (int(slot_id.min()) < -1 or int(slot_id.max()) >= ID_LIMIT):
            raise PersistenceError(
                f"{st.name('book_slot_id')}: expected ids in [0, {ID_LIMIT}) or -1 (free), "
                f"got {int(slot_id.min())}..{int(slot_id.max())}"
            )
        active = slot_id >= 0
        if compact and not np.all(active):
            raise PersistenceError(f"{st.name('book_slot_id')}: {int(np.sum(~active))} free slots in a compact book")
        if np.unique(slot_id[active]).size != int(np.sum(active)):
            raise PersistenceError(f"{st.name('book_slot_id')}: duplicate landmark ids")
        if counter.size and int(np.max(np.abs(counter))) > COUNTER_LIMIT:
            raise PersistenceError(f"{st.name('book_counter')}: a counter beyond ±{COUNTER_LIMIT}")
        book = cls(max(64, slot_id.size))
        book.slot_id[: slot_id.size] = slot_id
        book.counter[: slot_id.size] = counter
        if st.has("book_view"):
            near = st.array("book_near", "<f8", slot_id.shape)
            far = st.array("book_far", "<f8", slot_id.shape)
            view = st.array("book_view", "<f8", (slot_id.size, 3))
            for key, a in (("book_near", near), ("book_far", far), ("book_view", view)):
                check_finite(st.name(key), a, 1e9)
            if np.any(near < 0) or np.any(far < near):
                raise PersistenceError(f"{st.name('book_near')}: expected 0 <= near <= far")
            book.near[: slot_id.size], book.far[: slot_id.size], book.view[: slot_id.size] = near, far, view
        book.n_slots = int(slot_id.size)
        book.id_to_slot = {int(i): k for k, i in enumerate(slot_id.tolist()) if i >= 0}
        book.free = [k for k in range(book.n_slots) if slot_id[k] < 0]
        return book


def note_and_recognise(
    book: LandmarkBook,
    slots: np.ndarray,
    p_R: np.ndarray,
    R_wr: np.ndarray,
    observed: np.ndarray,
    born: np.ndarray,
    in_view: np.ndarray,
) -> np.ndarray:
    """The filters' half of the existence rule: ``slots`` (N,) ascending, at robot-frame positions
    ``p_R`` (N, dim) from a robot of orientation ``R_wr`` (dim, dim); ``in_view`` (N,) the field
    of view's verdict. Notes where the ``observed`` and ``born`` slots were seen from, and returns
    the slots in view that can be recognised (:meth:`LandmarkBook.recognisable`), the ones a miss
    counts against. Only those rows are transformed: the map grows, the view does not."""
    seen = np.concatenate([observed, born])
    pos = np.searchsorted(slots, seen)
    ok = pos < slots.size
    pos = pos[ok][slots[pos[ok]] == seen[ok]]
    book.note_views(slots[pos], *_views(p_R[pos], R_wr))
    rows = np.flatnonzero(in_view)
    return slots[rows][book.recognisable(slots[rows], *_views(p_R[rows], R_wr))]


def _views(p_R: np.ndarray, R_wr: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distances (N,) and unit directions (N, dim) landmark -> robot in the world frame of the
    robot-frame positions ``p_R`` (N, dim) seen from orientation ``R_wr``."""
    dist = np.linalg.norm(p_R, axis=1)
    return dist, -(p_R @ R_wr.T) / np.maximum(dist, 1e-9)[:, None]
