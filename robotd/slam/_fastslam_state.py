"""FastSLAM's saved state (``Persistent``): :func:`saved_state` builds it, :func:`check_state`
checks one whole before the filter takes it (:meth:`robotd.slam.fastslam.FastSlam.restore`)."""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np

from robotd.core.choices import MAX_PARTICLES
from robotd.core.errors import PersistenceError
from robotd.core.statecheck import POSITION_LIMIT_M, StateTable, check_covariances
from robotd.core.statecheck import check_finite as check_saved_finite
from robotd.slam._book import LandmarkBook
from robotd.slam._store import LandmarkStore
from robotd.slam.common import FILTER_CODE, check_header, check_saved_poses


class Particles(Protocol):
    """What :func:`saved_state` reads of the filter (a :class:`~robotd.slam.fastslam.FastSlam`)."""

    name: str
    dim: int
    dx: int
    t_ns: int
    pose: np.ndarray
    store: LandmarkStore
    book: LandmarkBook
    log_w: np.ndarray
    pending_S: np.ndarray | None
    best: int
    neff: float


def saved_state(fs: Particles) -> dict[str, np.ndarray | float | int]:
    """The filter's state as numpy arrays and Python scalars (the landmarks as dense copies)."""
    mean, cov = fs.store.dense(fs.book.n_slots)
    d: dict[str, np.ndarray | float | int] = {
        "filter_code": FILTER_CODE[fs.name],
        "dim": fs.dim,
        "t_ns": fs.t_ns,
        "pose": fs.pose.copy(),
        "lm_mean": mean,
        "lm_cov": cov,
        "log_w": fs.log_w.copy(),
        "pending_S": fs.pending_S.copy() if fs.pending_S is not None else np.zeros((0, fs.dx, fs.dx)),
        "best": fs.best,
        "neff": fs.neff,
    }
    d.update(fs.book.state_dict())
    return d


def check_state(name: str, dim: int, state: Any) -> dict[str, Any]:
    """Every key, type, shape and range of a saved state of the filter ``name`` in ``dim``
    dimensions (:func:`saved_state`): PersistenceError naming the key (MapMismatchError for another
    filter or dimension). Returns the checked values, ``ids`` (M,) the landmark ids it holds."""
    st = StateTable(state, f"{name} state")
    t_ns = check_header(st, name, dim)
    book = LandmarkBook.from_state(st, compact=False)
    n, dx, dm = book.n_slots, 3 if dim == 2 else 6, dim
    pose = st.array("pose", "<f8", (None, dx))
    P = pose.shape[0]
    if not 1 <= P <= MAX_PARTICLES:
        raise PersistenceError(f"{st.name('pose')}: expected 1 to {MAX_PARTICLES} particles, got {P}")
    mean = st.array("lm_mean", "<f8", (P, n, dm))
    cov = st.array("lm_cov", "<f8", (P, n, dm, dm))
    log_w = st.array("log_w", "<f8", (P,))
    pend = st.array("pending_S", "<f8", (None, dx, dx))
    if pend.shape[0] not in (0, P):
        raise PersistenceError(f"{st.name('pending_S')}: expected 0 or {P} matrices, got {pend.shape[0]}")
    best = st.integer("best", 0, P - 1)
    neff = st.number("neff", 0.0, P * (1 + 1e-6))
    check_saved_poses(st.name("pose"), pose, dim)
    check_saved_finite(st.name("lm_mean"), mean, POSITION_LIMIT_M)
    check_covariances(st.name("lm_cov"), cov)
    check_covariances(st.name("pending_S"), pend)
    if np.any(np.isnan(log_w)) or np.any(log_w == np.inf) or not np.isfinite(log_w.max()):
        raise PersistenceError(f"{st.name('log_w')}: expected finite log weights (-inf allowed), got NaN or inf")
    ids = book.slot_id[book.active_slots()].copy()
    return {
        "t_ns": t_ns,
        "book": book,
        "pose": pose,
        "mean": mean,
        "cov": cov,
        "log_w": log_w,
        "pending_S": pend,
        "best": best,
        "neff": neff,
        "ids": ids,
    }
