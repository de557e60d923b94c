"""The local engine of ``robotd replay-many``: worker processes on this machine, one per core by default.

Each worker is a spawned process (never a fork of a process with numba or OpenCV threads) that
runs :func:`robotd.tools.batch.jobs.run_job` for one job at a time and sends back the row; it keeps its
imports and numba kernels between jobs. The parent hands out jobs, receives rows and enforces the
limits a job cannot enforce itself: a worker that dies (a crash, the kernel's OOM killer) costs
only its row ("died"), one that overruns its job's time or memory by ``KILL_GRACE_S`` (stuck in
native code, where the job's own watchdog cannot reach it) is killed and its row says so; a new
worker takes its place, as it does after any time or memory limit (an interrupted worker is not
reused). Ctrl-C (SIGINT to the process group: workers ignore it) stops handing out
jobs, kills the workers, records the unfinished jobs as "interrupted" and raises
KeyboardInterrupt: every finished row was already handed to ``on_row``.

Worker processes run numba with ``cores / workers`` threads (one when every core has a worker),
OpenBLAS with one, as ``robotd replay`` does.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import multiprocessing.connection
import os
import signal
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from robotd.tools.batch.jobs import DIED, INTERRUPTED, KILL_GRACE_S, MEMORY, TIMEOUT, WATCH_PERIOD_S, rss_mb


def cpu_count() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


def _worker_main(conn: Any, numba_threads: int) -> None:
    """A worker process: jobs in, rows out, until told to stop (None) or the pipe closes."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    os.environ["NUMBA_NUM_THREADS"] = str(numba_threads)
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    os.environ.setdefault("OMP_WAIT_POLICY", "passive")
    from robotd.tools.batch.jobs import run_job

    while True:
        try:
            job = conn.recv()
        except (EOFError, OSError):
            return
        if job is None:
            return
        conn.send(run_job(job))


@dataclass
class _Slot:
    proc: Any
    conn: Any
    job: dict[str, Any] | None = None
    t0: float = 0.0
    over_since: float | None = None
    jobs_done: int = field(default=0)


def _failed_row(job: dict[str, Any], status: str, error: str, t0: float, worker: str) -> dict[str, Any]:
    return {
        "key": job["key"],
        "source": job["source"],
        "source_name": job.get("source_name", job["source"]),
        "source_digest": job["source_digest"],
        "config": job["config_name"],
        "config_digest": job["config_digest"],
        "robotd_version": job.get("robotd_version"),
        "status": status,
        "error": error,
        "wall_s": time.monotonic() - t0,
        "worker": worker,
    }


class LocalEngine:
    """Runs jobs on ``workers`` local processes (module docstring)."""

    name = "local"

    def __init__(self, workers: int = 0) -> None:
        self.workers = workers or cpu_count()
        self._ctx = multiprocessing.get_context("spawn")
        self.replaced = 0  # workers started again after one died or was killed
        self._slots: list[_Slot] = []

    def describe(self) -> str:
        return f"local, {self.workers} worker process{'es' if self.workers != 1 else ''}"

    def running(self) -> dict[int, str]:
        """The worker processes running a job now: pid -> the job's key."""
        return {s.proc.pid: s.job["key"] for s in list(self._slots) if s.job is not None}

    def _spawn(self) -> _Slot:
        parent, child = self._ctx.Pipe()
        threads = max(1, cpu_count() // self.workers)
        proc = self._ctx.Process(target=_worker_main, args=(child, threads), name="robotd-replay-worker", daemon=True)
        proc.start()
        child.close()
        return _Slot(proc, parent)

    @staticmethod
    def _kill(slot: _Slot) -> None:
        with contextlib.suppress(OSError):
            slot.proc.kill()
        slot.proc.join(5.0)
        with contextlib.suppress(OSError):
            slot.conn.close()

    def run(self, jobs: Sequence[dict[str, Any]], on_row: Callable[[dict[str, Any]], None]) -> None:
        pending = deque(jobs)
        slots = self._slots = [self._spawn() for _ in range(min(self.workers, len(pending)))]
        try:
            while pending or any(s.job is not None for s in slots):
                for s in slots:
                    if s.job is None and pending:
                        s.job, s.t0, s.over_since = pending.popleft(), time.monotonic(), None
                        s.conn.send(s.job)
                busy = [s for s in slots if s.job is not None]
                multiprocessing.connection.wait(
                    [s.conn for s in busy] + [s.proc.sentinel for s in busy], WATCH_PERIOD_S
                )
                for i, s in enumerate(slots):
                    row = self._check(s)
                    if row is None:
                        continue
                    if row.get("status") in (MEMORY, TIMEOUT) and s.proc.is_alive():
                        # interrupted mid-replay (its heap large, who knows what half done): a fresh
                        # worker takes the next job
                        self._kill(s)
                    if not s.proc.is_alive():
                        slots[i] = self._spawn()
                        self.replaced += 1
                    on_row(row)
        except KeyboardInterrupt:
            for s in slots:
                if s.job is not None:
                    self._kill(s)
                    on_row(_failed_row(s.job, INTERRUPTED, "interrupted (Ctrl-C)", s.t0, f"pid {s.proc.pid}"))
                    s.job = None
            raise
        finally:
            for s in slots:
                if s.proc.is_alive():
                    with contextlib.suppress(OSError, BrokenPipeError):
                        s.conn.send(None)
            for s in slots:
                s.proc.join(2.0)
                if s.proc.is_alive():
                    self._kill(s)

    def _check(self, s: _Slot) -> dict[str, Any] | None:
        """The slot's row when its job ended (a reply, a death, a kill), else None."""
        job = s.job
        if job is None:
            return None
        worker = f"pid {s.proc.pid}"
        try:
            if s.conn.poll():
                row: dict[str, Any] = s.conn.recv()
                s.job = None
                s.jobs_done += 1
                return row
        except (EOFError, OSError):
            pass
        now = time.monotonic()
        if not s.proc.is_alive():
            code = s.proc.exitcode
            why = f"killed by signal {-code}" if code is not None and code < 0 else f"exited with status {code}"
            s.job = None
            return _failed_row(job, DIED, f"worker process died: {why}", s.t0, worker)
        timeout = float(job.get("timeout_s") or 0.0)
        if timeout > 0 and now - s.t0 > timeout + KILL_GRACE_S:
            self._kill(s)
            s.job = None
            return _failed_row(
                job, TIMEOUT, f"timeout: still running after {timeout:g} s (worker killed)", s.t0, worker
            )
        limit = float(job.get("memory_mb") or 0.0)
        rss = rss_mb(s.proc.pid) if limit > 0 else None
        if rss is not None and rss > limit:
            s.over_since = s.over_since or now
            if now - s.over_since > KILL_GRACE_S:
                self._kill(s)
                s.job = None
                return _failed_row(
                    job,
                    MEMORY,
                    f"memory limit: {rss:.0f} MB resident, above {limit:g} MB (worker killed)",
                    s.t0,
                    worker,
                )
        else:
            s.over_since = None
        return None
