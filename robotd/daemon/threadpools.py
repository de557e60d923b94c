"""Thread-pool limits the daemon sets at start-up and restores at shutdown (OpenCV, BLAS).

- OpenCV: the front end detects the left and right images on two threads of its own; OpenCV's
  worker pool on top of them only adds threads and their spin-waits (≈ 1 ms CPU per frame on two
  cores); the results do not depend on it.
- BLAS: one thread by default (``slam.blas_threads``). The daemon runs its stages on threads of
  its own, and the matrix products on its hot path are small; a second OpenBLAS worker only
  spin-waits between calls: with SIFT (float descriptor products) it burned half a core, with ORB
  ≈ 0.7 ms of CPU per frame, on the cores the detection threads need.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Protocol

logger = logging.getLogger(__name__)


class BlasPool(Protocol):
    """One loaded BLAS library as threadpoolctl controls it."""

    filepath: str

    def get_num_threads(self) -> int: ...
    def set_num_threads(self, num_threads: int) -> None: ...


@dataclass
class ThreadLimits:
    """What :func:`limit_threads` changed, for :meth:`restore`."""

    cv_threads: int | None = None  # OpenCV's thread count before, when changed
    blas: list[tuple[BlasPool, int]] = field(default_factory=list)  # BLAS pools and their counts before

    def restore(self) -> None:
        if self.cv_threads is not None:
            import cv2

            cv2.setNumThreads(self.cv_threads)
            self.cv_threads = None
        for lib, before in self.blas:
            try:
                lib.set_num_threads(before)
            except Exception as exc:
                logger.warning("BLAS %s: thread count not restored (%s)", getattr(lib, "filepath", "?"), exc)
        self.blas = []


def limit_threads(single_opencv_thread: bool, blas_threads: int) -> ThreadLimits:
    """OpenCV to one thread when ``single_opencv_thread`` (the front end detects on two threads of
    its own), every loaded BLAS pool to ``blas_threads``; returns what to restore."""
    limits = ThreadLimits()
    if single_opencv_thread:
        import cv2

        limits.cv_threads = cv2.getNumThreads()
        cv2.setNumThreads(1)
    limits.blas = limit_blas_threads(blas_threads)
    return limits


def limit_blas_threads(n: int) -> list[tuple[BlasPool, int]]:
    """Set every loaded BLAS pool (numpy's, SciPy's and OpenCV's OpenBLAS each have one) to ``n``
    threads; returns the pools with their previous counts.

    Best effort: OpenBLAS may ignore a second change in one process (seen when an earlier daemon in
    the same process had limited and restored it, the limit then being set from another thread);
    that is logged. ``robotd`` itself sets OPENBLAS_NUM_THREADS=1 before numpy loads (robotd.tools.cli),
    which this only repeats; it matters for daemons embedded in other programs (bench/daemon.py)."""
    from threadpoolctl import ThreadpoolController

    changed: list[tuple[BlasPool, int]] = []
    try:
        libs = ThreadpoolController().select(user_api="blas").lib_controllers
    except Exception as exc:  # a thread-count setting is not worth failing startup over
        logger.warning("BLAS thread pools not inspectable (%s); slam.blas_threads not applied", exc)
        return changed
    for lib in libs:
        try:
            before = int(lib.get_num_threads())
            if before == n:
                continue
            lib.set_num_threads(n)
            changed.append((lib, before))
            now = int(lib.get_num_threads())
        except Exception as exc:
            logger.warning("BLAS %s: threads not set (%s)", getattr(lib, "filepath", "?"), exc)
            continue
        if now != n:
            logger.warning("BLAS %s kept %d threads (asked for %d: slam.blas_threads)", lib.filepath, now, n)
    return changed
