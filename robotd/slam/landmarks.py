"""The landmark registry: the one set of landmark ids of a map, and every store that keeps
something per landmark held to it by construction.

Three stores key their state by landmark id: the filter's book (robotd/slam/_book.py: existence
counters, and the Gaussians beside them), the front end's descriptors
(``robotd.frontend.association.LandmarkDescriptors``, which also numbers new landmarks) and the
reported covariance's anchors (``robotd.slam.uncertainty.AnchoredCovariance``). The filter alone
decides which landmarks exist (its existence counter); every other store subscribes to the
registry once (:meth:`LandmarkRegistry.subscribe`) and is told when landmarks leave the map,
whatever the path:

- the filter pruned them (``UpdateReport.pruned_ids``), reported by :meth:`LandmarkRegistry.update`,
  the one way the step hands a frame to the filter;
- the filter did not take a frame's new landmarks: the front end committed them (``propose``) and
  something raised before the filter's update accepted them, inside :meth:`LandmarkRegistry.frame`;
- a map was loaded (:meth:`LandmarkRegistry.reset`): the old map's landmarks leave every store.

Before, the pipeline called each store's ``forget`` by hand on each path, and a path that missed
one left orphans behind: a predict that failed every frame left 233 835 descriptors for 2 675
landmarks after 12 minutes of bench/soak.py, and the saved map failed its own check.

A store may hold fewer landmarks than the map (the anchors keep none for a loaded map's
landmarks, which anchor in the map's own frame), never one the map does not hold.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from robotd.core.msgs import Observations, UpdateReport
from robotd.slam.estimator import Estimator

_NONE = np.zeros(0, np.int64)


class LandmarkStore(Protocol):
    """Something kept per landmark id, outside the filter."""

    def forget(self, ids: np.ndarray) -> None:
        """The landmarks ``ids`` (K,) int64 left the map: drop what is kept for them (ids not held
        are ignored)."""
        ...


class LandmarkRegistry:
    """The ids of the landmarks in ``estimator``'s map, and the stores that follow it.

    ``ids`` are the map's landmarks (the filter's, :meth:`Estimator.landmark_ids`, as a sorted
    array); ``pending`` the new ones the front end committed this frame that the filter has not
    taken yet.
    """

    def __init__(self, estimator: Estimator) -> None:
        self.estimator = estimator
        self._stores: list[LandmarkStore] = []
        self._live: set[int] = set()
        self._pending = _NONE

    def subscribe(self, store: LandmarkStore) -> None:
        """``store`` follows the map from now on: every landmark that leaves it leaves ``store``."""
        self._stores.append(store)

    @property
    def ids(self) -> np.ndarray:
        """(M,) int64 the map's landmark ids, ascending."""
        return np.array(sorted(self._live), np.int64)

    @property
    def n(self) -> int:
        return len(self._live)

    @property
    def pending(self) -> np.ndarray:
        """(K,) int64 the new landmarks committed this frame, not taken by the filter yet."""
        return self._pending.copy()

    def propose(self, ids: np.ndarray) -> None:
        """The front end committed the new landmarks ``ids`` (K,) (it numbered them and keeps
        their descriptors): they join the map when the filter takes them (:meth:`update`), and
        leave every store when it does not (:meth:`frame`)."""
        ids = np.asarray(ids, np.int64).reshape(-1)
        if ids.size:
            self._pending = np.concatenate([self._pending, ids])

    def update(self, obs: Observations) -> UpdateReport:
        """The filter's update with ``obs``: the new landmarks it took join the map, those it
        pruned leave it and every store. A proposed landmark ``obs`` did not give the filter
        leaves every store; when the update raises, nothing changed (:meth:`frame` rolls back)."""
        report = self.estimator.update(obs)
        taken = obs.ids[obs.is_new]
        self._live.update(taken.tolist())
        left = _NONE  # proposed, not given to the filter (usually none: the frame gives it all)
        if self._pending.size and not np.array_equal(self._pending, taken):
            left = self._pending[~np.isin(self._pending, taken)]
        self._pending = _NONE
        pruned = np.asarray(report.pruned_ids, np.int64)
        if pruned.size:
            self._live.difference_update(pruned.tolist())
        gone = np.concatenate([left, pruned]) if left.size else pruned
        if gone.size:
            self._forget(gone)
        return report

    def rollback(self) -> None:
        """The filter did not take this frame's new landmarks: they leave every store."""
        pending, self._pending = self._pending, _NONE
        if pending.size:
            self._forget(pending)

    def frame(self) -> _Frame:
        """One frame's changes to the map, as a context (``with registry.frame(): ...``): the new
        landmarks proposed inside it reach the map and every store with the filter's update, or,
        when anything raises first (or the update is never made), leave every store again."""
        return _Frame(self)

    def reset(self, ids: np.ndarray) -> None:
        """A map was loaded into the filter: its landmarks ``ids`` (M,) are the map now. The old
        map's leave every store (ids are reused across maps: both start at 0); the caller then
        gives each store what the loaded map keeps for them."""
        old = np.array(sorted(self._live), np.int64)
        if self._pending.size:
            old = np.concatenate([old, self._pending])
        self._live = {int(i) for i in np.asarray(ids, np.int64).reshape(-1)}
        self._pending = _NONE
        if old.size:
            self._forget(old)

    def _forget(self, ids: np.ndarray) -> None:
        for store in self._stores:
            store.forget(ids)


class _Frame:
    """The context of :meth:`LandmarkRegistry.frame`: whatever is still pending when it ends (an
    exception, or no update) is rolled back."""

    def __init__(self, registry: LandmarkRegistry) -> None:
        self.registry = registry

    def __enter__(self) -> None:
        return None

    def __exit__(self, *exc: object) -> None:
        self.registry.rollback()  # nothing is pending after an update
