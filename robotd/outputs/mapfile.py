"""The map-file output: the pipeline's state (filter and landmark descriptors) saved to disk
periodically and at shutdown, and the resume from it at start-up (robotd.formats.persist: atomic,
versioned, checked; a bad file is moved aside, never overwritten).

The SLAM thread takes the state snapshot between steps; the file is written on this output's own
writer thread, so a save (fsync included) never delays the poses.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from robotd.config import PersistenceConfig
from robotd.core.errors import MapMismatchError, PersistenceError
from robotd.formats.persist import MapStore, default_state_dir
from robotd.formats.queues import DropOldestQueue
from robotd.outputs.base import Output, StepReport
from robotd.pipeline.step import Pipeline

logger = logging.getLogger(__name__)

HANDOVER_KEY = "handover"  # a state snapshot's entry that goes beside the state in the file


class MapFileOutput(Output):
    """Saves the map under ``persistence.state_dir`` (or $STATE_DIRECTORY, or ~/.local/state/robotd)."""

    name = "map_file"
    health_key = "map_file"  # the health state reads the last save's failure there

    def __init__(self, cfg: PersistenceConfig, robot_id: str) -> None:
        self.store = MapStore(default_state_dir(cfg.state_dir), robot_id)
        if self.store.dir.is_dir():
            self.store.remove_orphans()
        self.keep_maps = cfg.keep_maps
        self.resumed = False
        self.saved_handover: object = None  # the resumed map's ``handover`` table, unchecked (robotd.daemon.handover)
        self._first_save = True
        # failed saves, for the health document: how many, the last error and when (monotonic)
        self.failures = 0
        self.last_error: str | None = None
        self.last_failure_ns: int | None = None
        self.last_failed = False
        self.state_period_s = cfg.save_period_s if cfg.save_period_s > 0 else None
        self._queue: DropOldestQueue[tuple[int, Mapping[str, Any]]] = DropOldestQueue(1)
        self._thread = threading.Thread(target=self._writer, name="robotd-mapfile", daemon=True)
        self._thread.start()

    @property
    def path(self) -> Path:
        return self.store.path

    def resume(self, pipeline: Pipeline) -> bool:
        """Load the saved map into ``pipeline``; False (and one log line) when there is none or it
        cannot be used. The map is checked whole before the pipeline is touched: a corrupt or
        invalid map is moved aside (``map.robotd.bad-<time>``; left in place and never saved over
        when it cannot be moved), a valid map of another filter, dimension or detector stays and is
        kept under a new name at the first save (``persistence.keep_maps``)."""
        if not self.store.exists():
            logger.info("resume: no saved map in %s, starting a new map", self.store.dir)
            return False
        try:
            saved = self.store.load()
            try:
                pipeline.load_state_dict(saved["state"])
            except MapMismatchError:
                raise
            except PersistenceError as exc:
                raise PersistenceError(self.store.set_aside(f"{self.store.path}: {exc}")) from None
        except PersistenceError as exc:
            logger.error("resume failed: %s", exc)
            return False
        n = int(pipeline.estimator.landmark_ids().shape[0])
        logger.info("resumed from saved map %s: %d landmarks", self.store.path, n)
        self.saved_handover = saved.get("handover")
        self.resumed = True
        return True

    def publish(self, report: StepReport) -> None:
        if report.state is not None:
            self._queue.put((report.result.t_ns, report.state))

    def finish(self, state: Mapping[str, Any] | None, t_ns: int) -> None:
        """The final save, once the SLAM thread stopped (after any periodic save still queued)."""
        self._stop_writer()
        if state is not None:
            self.save(state, t_ns)

    def save(self, state: Mapping[str, Any], t_ns: int) -> bool:
        """Write ``state``; its ``handover`` entry, when there is one (the autopilot's pose at the
        state's frame, robotd.daemon.handover), is kept beside it in the file. The first save of a
        run that did not resume from the saved map keeps that map under a new name first
        (``persistence.keep_maps``): a map is never lost silently."""
        state = dict(state)
        handover = state.pop(HANDOVER_KEY, None)
        try:
            if self._first_save and not self.resumed:
                self.store.keep_previous(self.keep_maps)
            self._first_save = False
            path = self.store.save(state, t_ns, handover)
        except (PersistenceError, OSError) as exc:
            logger.error("map not saved: %s", exc)
            self.failures += 1
            self.last_error, self.last_failure_ns, self.last_failed = str(exc), time.monotonic_ns(), True
            return False
        self.last_failed = False
        n = len(state.get("database", {}).get("ids", ()))
        logger.info("map saved to %s (%d landmarks)", path, n)
        return True

    def stats(self) -> dict[str, Any]:
        """Saves and failed saves (the last error and how long ago); ``not_saving``: why this run
        saves no map (a map that failed to resume could not be moved aside), else None."""
        ago = None if self.last_failure_ns is None else round((time.monotonic_ns() - self.last_failure_ns) / 1e9, 1)
        return {
            "saves": self.store.saves,
            "failures": self.failures,
            "last_failed": self.last_failed,
            "last_error": self.last_error,
            "since_failure_s": ago,
            "not_saving": self.store.protected,
        }

    def close(self) -> None:
        self._stop_writer()

    def _writer(self) -> None:
        while True:
            item = self._queue.get(timeout=0.5)
            if item is None:
                if self._queue.closed:
                    return
                continue
            self.save(item[1], item[0])

    def _stop_writer(self) -> None:
        self._queue.close()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join()
