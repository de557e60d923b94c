"""One replay of ``robotd replay-many``, run in whatever process the engine gives it (a local worker
or a Ray task): :func:`robotd.tools.replay.replay` in-process, exactly as ``robotd replay SOURCE --out
T.txt`` runs it, so the trajectory is bit for bit the one a single replay writes.

A job is a plain dict (picklable, JSON-able): the source URL, the resolved configuration, the
limits. :func:`run_job` returns a row, a plain dict: the replay's summary, the trajectory and
covariance files' text (the engine writes them into the results folder, so workers need no shared
folder to write to), or the error. It never raises for a replay that fails: a failure is a row.

Limits, watched from a thread inside the job: past ``timeout_s`` or above ``memory_mb`` of
resident memory the replay is interrupted between two frames (SIGUSR1 to this process's main
thread, which raises :class:`LimitExceeded`), and the row says which limit. A replay stuck
inside native code is not interruptible; the local engine kills its worker ``KILL_GRACE_S`` later,
and on Ray the same watchdog ends the worker process itself.

The robotd version in every key is :func:`code_version`: the package version plus a digest of
robotd's and the drivers' source files and of the numeric libraries' versions, so an edited or
upgraded robotd reruns everything, whether or not it was committed or released.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib.metadata
import logging
import os
import signal
import socket
import tempfile
import threading
import time
import traceback
from collections.abc import Iterator
from pathlib import Path
from typing import Any

# statuses of a row; "ok" and "error" (the replay itself raised: it will raise again) are done and
# reused by a rerun; the others depend on the machine and are run again
OK, ERROR, TIMEOUT, MEMORY, DIED, INTERRUPTED = "ok", "error", "timeout", "memory", "died", "interrupted"
DONE_STATUSES = (OK, ERROR)
KILL_GRACE_S = 10.0  # after a limit: how long a replay may take to reach the next frame
WATCH_PERIOD_S = 0.2
LIBRARIES = ("numpy", "scipy", "numba", "opencv-python-headless", "mcap")
_version_cache: str | None = None


def code_version() -> str:
    """``0.1.0+<12 hex>``: robotd's version and a digest of its code and numeric libraries."""
    global _version_cache
    if _version_cache is None:
        import robotd

        h = hashlib.sha256()
        root = Path(robotd.__file__).resolve().parent.parent
        for pkg in ("robotd", "drivers"):
            for f in sorted((root / pkg).rglob("*.py")):
                h.update(f.relative_to(root).as_posix().encode() + b"\0" + f.read_bytes() + b"\0")
        for lib in LIBRARIES:
            try:
                h.update(f"{lib}=={importlib.metadata.version(lib)}\n".encode())
            except importlib.metadata.PackageNotFoundError:
                h.update(f"{lib} missing\n".encode())
        _version_cache = f"{robotd.__version__}+{h.hexdigest()[:12]}"
    return _version_cache


def rss_mb(pid: int | None = None) -> float | None:
    """Resident memory of a process in MB (Linux /proc; None elsewhere or when it is gone)."""
    try:
        with open(f"/proc/{pid or 'self'}/statm", encoding="ascii") as f:
            pages = int(f.read().split()[1])
    except (OSError, ValueError, IndexError):
        return None
    return pages * os.sysconf("SC_PAGE_SIZE") / 1e6


class LimitExceeded(BaseException):
    """Raised in the replaying thread when the job ran past its time or memory limit (a
    BaseException, so the replay's own ``except Exception`` handlers let it through)."""

    def __init__(self, status: str, message: str) -> None:
        super().__init__(message)
        self.status = status


class _Watchdog:
    """Watches the job's time and this process's memory; interrupts the main thread once."""

    def __init__(self, timeout_s: float, memory_mb: float) -> None:
        self.timeout_s, self.memory_mb = timeout_s, memory_mb
        self.peak_mb = rss_mb() or 0.0
        self.tripped: LimitExceeded | None = None
        self._stop = threading.Event()
        self._can_interrupt = threading.current_thread() is threading.main_thread()
        self._old_handler: Any = None
        self._thread = threading.Thread(target=self._watch, name="robotd-batch-watchdog", daemon=True)

    def __enter__(self) -> _Watchdog:
        if self._can_interrupt:
            self._old_handler = signal.signal(signal.SIGUSR1, self._on_signal)
        self._t0 = time.monotonic()
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        if self._can_interrupt:
            signal.signal(signal.SIGUSR1, self._old_handler)

    def _on_signal(self, signum: int, frame: Any) -> None:
        if self.tripped is not None:
            raise self.tripped

    def _watch(self) -> None:
        deadline: float | None = None
        while not self._stop.wait(WATCH_PERIOD_S):
            rss = rss_mb()
            if rss is not None:
                self.peak_mb = max(self.peak_mb, rss)
            if self.tripped is None:
                elapsed = time.monotonic() - self._t0
                if self.timeout_s > 0 and elapsed > self.timeout_s:
                    self.tripped = LimitExceeded(TIMEOUT, f"timeout: still running after {self.timeout_s:g} s")
                elif self.memory_mb > 0 and rss is not None and rss > self.memory_mb:
                    self.tripped = LimitExceeded(
                        MEMORY, f"memory limit: {rss:.0f} MB resident, above the limit of {self.memory_mb:g} MB"
                    )
                if self.tripped is not None:
                    deadline = time.monotonic() + KILL_GRACE_S
                    if self._can_interrupt:
                        os.kill(os.getpid(), signal.SIGUSR1)
            elif deadline is not None and time.monotonic() > deadline and os.environ.get("ROBOTD_BATCH_SELF_KILL"):
                # stuck in native code past the grace (a Ray task: nobody else would end it)
                os._exit(70)


class _LogTail(logging.Handler):
    """Keeps the replay's warnings and errors (counted, the last few kept) for the row."""

    def __init__(self, keep: int = 8) -> None:
        super().__init__(logging.WARNING)
        self.keep = keep
        self.lines: list[str] = []
        self.warnings = 0
        self.errors = 0

    def emit(self, record: logging.LogRecord) -> None:
        if record.levelno >= logging.ERROR:
            self.errors += 1
        else:
            self.warnings += 1
        try:
            line = f"{record.levelname} {record.name}: {record.getMessage()}"
        except Exception:
            line = f"{record.levelname} {record.name}: {record.msg}"
        self.lines = [*self.lines[-(self.keep - 1) :], " ".join(line.split())[:400]]


@contextlib.contextmanager
def _captured_logs() -> Iterator[_LogTail]:
    root = logging.getLogger()
    tail = _LogTail()
    old_level = root.level
    root.addHandler(tail)
    if root.level > logging.WARNING or root.level == logging.NOTSET:
        root.setLevel(logging.WARNING)
    try:
        yield tail
    finally:
        root.removeHandler(tail)
        root.setLevel(old_level)


def events_of(summary: dict[str, Any], tail: _LogTail | None = None) -> list[str]:
    """The health events of a replay, as short phrases: frames the step refused, tracking lost
    (episodes and frames), odometry refused by the plausibility gates, gravity refused, a damaged
    recording read up to the damage, and the warnings and errors it logged."""
    ev: list[str] = []
    if summary.get("step_errors"):
        ev.append(f"{summary['step_errors']} frames failed")
    if summary.get("lost_frames"):
        ep = summary.get("tracking_lost_episodes")
        ev.append(f"tracking lost {summary['lost_frames']} frames" + (f" in {ep} episodes" if ep else ""))
    if summary.get("odometry_rejected"):
        ev.append(f"{summary['odometry_rejected']} odometry samples refused")
    if summary.get("gravity_rejected"):
        ev.append(f"{summary['gravity_rejected']} gravity refused")
    rec = summary.get("recording") or {}
    if rec.get("stopped"):
        ev.append(f"recording damaged: {rec['stopped']}")
    if tail is not None and (tail.warnings or tail.errors):
        ev.append(f"{tail.warnings} warnings, {tail.errors} errors logged")
    return ev


def _thread_lock_for_tqdm() -> None:
    """tqdm's default lock is a multiprocessing lock, a semaphore that the resource tracker reports as
    leaked when a worker is killed mid-replay (a limit, Ctrl-C); a worker needs a thread lock only."""
    from tqdm import tqdm

    if getattr(tqdm, "_lock", None) is None:
        tqdm.set_lock(threading.RLock())


def run_job(job: dict[str, Any]) -> dict[str, Any]:
    """One replay (module docstring); the row, whatever happens."""
    t0 = time.monotonic()
    _thread_lock_for_tqdm()
    row: dict[str, Any] = {
        "key": job["key"],
        "source": job["source"],
        "source_name": job.get("source_name", job["source"]),
        "source_digest": job["source_digest"],
        "config": job["config_name"],
        "config_digest": job["config_digest"],
        "robotd_version": code_version(),
        "worker": f"{socket.gethostname()}:{os.getpid()}",
    }
    if job.get("robotd_version") and job["robotd_version"] != row["robotd_version"]:
        row.update(
            status=ERROR,
            error=f"this worker runs robotd {row['robotd_version']}, the run was started with "
            f"{job['robotd_version']}: install the same robotd on every node",
            wall_s=0.0,
        )
        return row
    # imported before the watchdog starts: a limit interrupts the replay, never an import half done
    # (a module left half imported would fail this worker's next replays)
    from robotd.research.evaluate import cov_path_for
    from robotd.tools.batch.configs import Configuration
    from robotd.tools.replay import replay

    watchdog = _Watchdog(float(job.get("timeout_s") or 0.0), float(job.get("memory_mb") or 0.0))
    try:
        with _captured_logs() as tail, watchdog, tempfile.TemporaryDirectory(prefix="robotd-batch-") as td:
            cfg = Configuration(job["config_name"], job["config"], job["config_digest"]).config()
            traj = Path(td) / "trajectory.txt"
            truth = Path(td) / "truth.txt"
            summary = replay(cfg, job["source"], out_traj=str(traj), progress=False, truth_out_if_any=str(truth))
            summary.pop("trajectory", None)
            row["summary"] = summary
            row["trajectory_text"] = traj.read_text(encoding="ascii")
            row["covariance_text"] = cov_path_for(traj).read_text(encoding="ascii")
            row["truth_text"] = truth.read_text(encoding="ascii") if truth.is_file() else None
            row["events"] = events_of(summary, tail)
            row["log_tail"] = tail.lines
            row["status"] = OK
    except LimitExceeded as exc:
        row.update(status=exc.status, error=str(exc))
    except MemoryError:
        row.update(status=MEMORY, error="memory: the replay ran out of memory (MemoryError)")
    except Exception as exc:  # a failed replay is a row, never the end of the run
        row.update(status=ERROR, error=f"{type(exc).__name__}: {' '.join(str(exc).split())}"[:1000])
        row["traceback"] = traceback.format_exc(limit=6)[-3000:]
    row["wall_s"] = time.monotonic() - t0
    row["peak_rss_mb"] = round(watchdog.peak_mb, 1)
    return row
