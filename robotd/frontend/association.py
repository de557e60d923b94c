"""Landmark identification: match a frame's measurements to map landmarks by descriptor (docs/math.md §4.3).

The :class:`LandmarkDescriptors` store holds what is global to the map and shared by every
FastSLAM particle: landmark ids and one descriptor per landmark (the left descriptor of its most
recent accepted observation). It allocates the ids of new landmarks. Whether a landmark exists is
the filter's business alone (its existence counter, robotd.slam._book): the filter reports the ids
it deleted in ``UpdateReport.pruned_ids`` and the landmark registry (robotd.slam.landmarks) has
this store forget them, and the new ones the filter did not take; positions and covariances
are the filter's too, the caller passes them when it wants the outlier stage to check the matches.

Outcome per measurement (``Correspondences.status``): IDENTIFIED (matched, passed the outlier
stage: update landmark ``ids[i]``), NEW (no descriptor match: a landmark may be initialised, which gets a
fresh global id when it is committed), REJECTED (matched but failed the outlier stage, or ambiguous: neither update
nor initialise in this frame, which avoids duplicate landmarks).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from robotd.core.errors import ConfigError, InputError, PersistenceError
from robotd.core.statecheck import ID_LIMIT, INT64_MAX, StateTable
from robotd.core.statecheck import check_finite as check_saved_finite
from robotd.frontend.stereo_match import distance_matrix, pair_distances, ratio_and_cross_check, window_pairs

logger = logging.getLogger(__name__)

IDENTIFIED, NEW, REJECTED = 0, 1, 2


@dataclass(frozen=True, slots=True)
class AssociationParams:
    """Map-matching configuration (config key ``frontend.association``; docs/math.md §4.3, §5.5).

    ratio: τ_r (None: 0.8 float descriptors, 0.75 binary). max_dist_float / max_dist_binary:
      absolute limit on the best distance (unit-normalised Euclidean; Hamming bits); a measurement
      whose nearest landmark is farther is NEW. Above it but failing the ratio test or the
      cross-check the match is ambiguous: REJECTED when ``ambiguous_is_rejected`` (no duplicate
      landmark is made for something the map may already hold), else NEW.
    cross_check: keep mutual best matches only.
    guided_radius_px: guided matching (:meth:`LandmarkDescriptors.identify_guided`) searches this
      far from a landmark's predicted pixels (left column, row and disparity).
    guided_ratio: the ratio test inside the search window (a landmark's two nearest candidates
      there must differ by this much).
    """

    ratio: float | None = None
    max_dist_float: float = 0.45
    max_dist_binary: float = 60.0
    cross_check: bool = True
    ambiguous_is_rejected: bool = True
    guided_radius_px: float = 15.0
    guided_ratio: float = 0.9

    def __post_init__(self) -> None:
        if self.ratio is not None and not 0.0 < self.ratio <= 1.0:
            raise ConfigError(f"frontend.association.ratio: expected in (0, 1], got {self.ratio}")
        if self.guided_radius_px <= 0 or not 0.0 < self.guided_ratio <= 1.0:
            raise ConfigError(
                "frontend.association: expected guided_radius_px > 0 and guided_ratio in (0, 1], got "
                f"{self.guided_radius_px}, {self.guided_ratio}"
            )
        if self.max_dist_float <= 0 or self.max_dist_binary <= 0:
            raise ConfigError(
                "frontend.association.max_dist_float/max_dist_binary: expected > 0, got "
                f"{self.max_dist_float}, {self.max_dist_binary}"
            )

    def limits(self, binary: bool) -> tuple[float, float]:
        """(absolute distance limit, ratio) for binary or float descriptors: ``max_dist_binary`` or
        ``max_dist_float``, and ``ratio`` or its default (0.75 binary, 0.8 float)."""
        max_d = self.max_dist_binary if binary else self.max_dist_float
        return max_d, (self.ratio if self.ratio is not None else (0.75 if binary else 0.8))


@dataclass(slots=True, eq=False)
class Correspondences:
    """The correspondence vector c_t of one frame (docs/math.md §4.3).

    status: (N,) int8 IDENTIFIED / NEW / REJECTED per measurement; ids: (N,) int64 global landmark
    id (the matched landmark for IDENTIFIED and REJECTED-after-match, the new id for a NEW
    measurement once :meth:`LandmarkDescriptors.commit` initialised it, −1 otherwise); dist: (N,)
    descriptor distance to the matched landmark (inf when none).
    """

    status: np.ndarray
    ids: np.ndarray
    dist: np.ndarray
    stats: dict[str, int] = field(default_factory=dict)

    @property
    def n(self) -> int:
        return int(self.status.shape[0])

    @property
    def matched(self) -> np.ndarray:
        """(N,) True for measurements with a putative map match (input of the outlier stage)."""
        return self.ids >= 0

    def reject(self, mask: np.ndarray) -> None:
        """Mark the measurements in ``mask`` (N,) bool as REJECTED (they failed the outlier stage)."""
        self.status[mask] = REJECTED


class LandmarkDescriptors:
    """Global landmark ids and their descriptors (shared by all particles).

    Descriptors are stored normalised (:func:`robotd.frontend.stereo_match.normalise_descriptors`).
    Ids are never reused; rows are kept in creation order, so ``ids`` is sorted.
    """

    def __init__(self, dim: int, binary: bool, first_id: int = 0) -> None:
        self.dim = int(dim)
        self.binary = bool(binary)
        self.ids = np.zeros(0, np.int64)  # (M,)
        self.desc = np.zeros((0, self.dim), np.uint8 if binary else np.float32)  # (M, D)
        self.next_id = int(first_id)

    @property
    def n(self) -> int:
        return int(self.ids.shape[0])

    def rows(self, ids: np.ndarray) -> np.ndarray:
        """Row index of each id (ids must exist; ids are sorted because they are never reused)."""
        ids = np.asarray(ids, dtype=np.int64)
        r = np.searchsorted(self.ids, ids)
        r = np.minimum(r, max(self.n - 1, 0))
        if ids.size and (self.n == 0 or np.any(self.ids[r] != ids)):
            missing = ids if self.n == 0 else ids[self.ids[r] != ids]
            raise InputError(f"LandmarkDescriptors: unknown landmark ids {missing[:10].tolist()}")
        return r

    def contains(self, ids: np.ndarray) -> np.ndarray:
        """(K,) True where the id is in the store."""
        ids = np.asarray(ids, dtype=np.int64)
        if self.n == 0:
            return np.zeros(ids.shape, bool)
        r = np.minimum(np.searchsorted(self.ids, ids), self.n - 1)
        return self.ids[r] == ids

    def add(self, desc: np.ndarray) -> np.ndarray:
        """Append landmarks with descriptors (K, D); returns their new global ids (K,)."""
        desc = np.asarray(desc)
        if desc.ndim != 2 or desc.shape[1] != self.dim:
            raise InputError(f"LandmarkDescriptors.add: expected descriptors (K, {self.dim}), got {desc.shape}")
        k = desc.shape[0]
        if self.next_id + k > INT64_MAX:  # int64 ids never wrap (a saved map starts at most at ID_LIMIT)
            raise InputError(f"LandmarkDescriptors.add: ids exhausted (next id {self.next_id}, limit {INT64_MAX})")
        new_ids = np.arange(self.next_id, self.next_id + k, dtype=np.int64)
        self.next_id += k
        self.ids = np.r_[self.ids, new_ids]
        self.desc = np.concatenate([self.desc, desc.astype(self.desc.dtype)])
        return new_ids

    def update(self, ids: np.ndarray, desc: np.ndarray) -> None:
        """Replace the descriptors of identified landmarks (latest accepted observation)."""
        self.desc[self.rows(ids)] = desc

    def forget(self, ids: np.ndarray) -> None:
        """Delete landmarks the filter deleted (``UpdateReport.pruned_ids``); unknown ids are ignored."""
        if len(ids):
            keep = ~np.isin(self.ids, np.asarray(ids, dtype=np.int64))
            self.ids, self.desc = self.ids[keep], self.desc[keep]

    def identify_guided(
        self,
        desc: np.ndarray,
        pixels: np.ndarray,
        candidate_ids: np.ndarray,
        predicted: np.ndarray,
        params: AssociationParams | None = None,
        rows_known: bool = True,
    ) -> Correspondences:
        """Guided matching: each landmark is searched only near where the predicted pose projects it.

        ``desc`` (N, D), ``pixels`` (N, 3) = (x_l, x_r, y) of the frame's measurements;
        ``candidate_ids`` (K,) landmarks and ``predicted`` (K, 3) their predicted pixels. A pair
        is a candidate when the left column, the row and the disparity all lie within
        ``guided_radius_px`` of the prediction and the descriptor distance is under the absolute
        limit; the nearest descriptor wins, if it passes the ratio test against the second
        nearest inside the window and the match is mutual. Geometry, not the descriptor alone,
        decides: repeated texture elsewhere in the image cannot steal a match, and a landmark
        seen from a new scale or angle is still found where it must be. Measurements without a
        match are NEW (the outlier stage still screens the IDENTIFIED ones). ``rows_known``
        False: the predictions' rows are meaningless (a planar map has no heights) and not tested.
        """
        params = params or AssociationParams()
        n = int(np.shape(desc)[0])
        status = np.full(n, NEW, np.int8)
        ids = np.full(n, -1, np.int64)
        dist = np.full(n, np.inf, np.float32)
        cand = np.asarray(candidate_ids, dtype=np.int64)
        known = self.contains(cand)
        cand, predicted = cand[known], np.asarray(predicted, float)[known]
        stats = {"candidates": int(cand.size), "matched": 0, "ambiguous": 0, "new": n, "guided": 1}
        if n == 0 or cand.size == 0:
            return Correspondences(status, ids, dist, stats)
        rows = self.rows(cand)
        ii, jj = window_pairs(np.asarray(pixels, float), predicted, params.guided_radius_px, rows_known)
        if ii.size == 0:
            return Correspondences(status, ids, dist, stats)
        d = pair_distances(np.asarray(desc)[ii], self.desc[rows[jj]], self.binary)
        max_d = params.max_dist_binary if self.binary else params.max_dist_float
        ok = d <= max_d
        ii, jj, d = ii[ok], jj[ok], d[ok]
        if ii.size == 0:
            return Correspondences(status, ids, dist, stats)
        # the ratio test per landmark: its nearest measurement in the window against the second
        order = np.lexsort((d, jj))
        j_s, d_s = jj[order], d[order]
        first = np.r_[True, j_s[1:] != j_s[:-1]]
        start = np.flatnonzero(first)
        second = np.full(cand.size, np.inf)
        has2 = np.r_[start[1:], j_s.size] - start > 1
        second[j_s[start[has2]]] = d_s[start[has2] + 1]
        passes = np.zeros(cand.size, bool)
        passes[j_s[start]] = d_s[start] < params.guided_ratio * second[j_s[start]]
        keep = passes[jj]
        ii, jj, d = ii[keep], jj[keep], d[keep]
        sel, _ = ratio_and_cross_check(ii, jj, d, cand.size, 1.0, max_d, True)
        i_sel, j_sel = ii[sel], jj[sel]
        status[i_sel] = IDENTIFIED
        ids[i_sel] = cand[j_sel]
        dist[i_sel] = d[sel]
        stats.update(matched=int(i_sel.size), new=int(np.sum(status == NEW)))
        return Correspondences(status, ids, dist, stats)

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to resume: numpy arrays and scalars only (robotd.formats.persist)."""
        return {
            "dim": self.dim,
            "binary": self.binary,
            "ids": self.ids.copy(),
            "desc": self.desc.copy(),
            "next_id": self.next_id,
        }

    @classmethod
    def from_state_dict(cls, state: Any) -> LandmarkDescriptors:
        """Restore from :meth:`state_dict`, checked whole: ``dim`` and ``binary`` of a known
        descriptor kind, ids (M,) int64 strictly increasing in [0, next_id), descriptors (M, dim)
        uint8 (binary) or finite float32, ``next_id`` at most ID_LIMIT (room for 2**40 more ids).
        PersistenceError naming the key otherwise. Maps saved before the filter became the one
        owner of landmark existence also carry an ``existence`` array: it is ignored."""
        st = StateTable(state, "database")
        dim = st.integer("dim", 1, 4096)
        binary = st.boolean("binary")
        next_id = st.integer("next_id", 0, ID_LIMIT)
        ids = st.array("ids", "<i8", (None,))
        desc = st.array("desc", "|u1" if binary else "<f4", (ids.shape[0], dim))
        if ids.size and (int(ids[0]) < 0 or int(ids[-1]) >= next_id or np.any(np.diff(ids) <= 0)):
            raise PersistenceError(
                f"{st.name('ids')}: expected strictly increasing ids in [0, next_id = {next_id}), "
                f"got {int(ids.min())}..{int(ids.max())}"
            )
        if not binary:
            check_saved_finite(st.name("desc"), desc)
        store = cls(dim, binary, first_id=next_id)
        store.ids, store.desc = ids.copy(), desc.copy()
        return store

    def identify(
        self,
        desc: np.ndarray,
        candidate_ids: np.ndarray | None = None,
        params: AssociationParams | None = None,
    ) -> Correspondences:
        """Match measurement descriptors (N, D) (normalised) to landmarks (§4.3).

        ``candidate_ids``: restrict the search to these landmarks (e.g. those predicted inside the
        field of view, or those whose positions the caller knows); None: all landmarks. Brute force
        over candidates, ratio test and cross-check as for stereo. Returns statuses IDENTIFIED (a
        putative match the outlier stage must still confirm), NEW or REJECTED (ambiguous).
        """
        params = params or AssociationParams()
        desc = np.asarray(desc)
        n = desc.shape[0]
        if n and (desc.ndim != 2 or desc.shape[1] != self.dim):
            raise InputError(f"LandmarkDescriptors.identify: expected descriptors (N, {self.dim}), got {desc.shape}")
        status = np.full(n, NEW, np.int8)
        ids = np.full(n, -1, np.int64)
        dist = np.full(n, np.inf, np.float32)
        if candidate_ids is None:
            rows = np.arange(self.n)
        else:
            cand = np.asarray(candidate_ids, dtype=np.int64)
            known = self.contains(cand)
            if not np.all(known):
                logger.debug("identify: %d candidate ids not in the store ignored", int(np.sum(~known)))
            rows = self.rows(cand[known])
        stats = {"candidates": int(rows.size), "matched": 0, "ambiguous": 0, "new": n}
        if n == 0 or rows.size == 0:
            return Correspondences(status, ids, dist, stats)
        D = distance_matrix(desc, self.desc[rows], self.binary)  # (N, C)
        max_d, ratio = params.limits(self.binary)
        # nearest landmark per measurement decides NEW (too far) against "something similar exists"
        nearest = D.min(axis=1)
        near = nearest <= max_d
        # dense pairs under the absolute limit, then the shared ratio/cross-check selector
        ii, jj = np.nonzero(D <= max_d)
        dd = D[ii, jj]
        # the ratio test must see the true second-nearest, even when it lies above the limit
        second = np.partition(D, 1, axis=1)[:, 1] if D.shape[1] > 1 else np.full(n, np.inf)
        sel, st = ratio_and_cross_check(ii, jj, dd, rows.size, ratio, max_d, params.cross_check)
        i_sel, j_sel, d_sel = ii[sel], jj[sel], dd[sel]
        ok = d_sel < ratio * second[i_sel]
        i_sel, j_sel, d_sel = i_sel[ok], j_sel[ok], d_sel[ok]
        status[i_sel] = IDENTIFIED
        ids[i_sel] = self.ids[rows[j_sel]]
        dist[i_sel] = d_sel
        ambiguous = near & (status != IDENTIFIED)
        if params.ambiguous_is_rejected:
            status[ambiguous] = REJECTED
        stats.update(
            matched=int(i_sel.size),
            ambiguous=int(ambiguous.sum()),
            new=int(np.sum(status == NEW)),
            ratio_rejected=st["ratio_rejected"],
            cross_rejected=st["cross_rejected"],
        )
        logger.debug(
            "identify: %d measurements vs %d landmarks: %d matched, %d ambiguous, %d new",
            n,
            rows.size,
            stats["matched"],
            stats["ambiguous"],
            stats["new"],
        )
        return Correspondences(status, ids, dist, stats)

    def commit(self, corr: Correspondences, desc: np.ndarray, new: np.ndarray | None = None) -> None:
        """Apply a frame's decisions: IDENTIFIED landmarks take the new descriptor; the NEW
        measurements at indices ``new`` (all NEW ones when None) get fresh ids, written into
        ``corr.ids`` in ascending index order; REJECTED and the NEW ones not initialised keep id −1.
        """
        ident = corr.status == IDENTIFIED
        if np.any(ident):
            self.update(corr.ids[ident], desc[ident])
        idx = np.flatnonzero(corr.status == NEW) if new is None else np.sort(np.asarray(new, np.int64))
        if idx.size:
            corr.ids[idx] = self.add(desc[idx])
        corr.ids[corr.status == REJECTED] = -1
