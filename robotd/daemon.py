"""The daemon: signals → startup → loop → graceful shutdown (design.md §5.10, interfaces.md §4).

Threads:
- camera: ``camera.frames()`` → frame queue (bounded, drop-oldest, counted)
- vehicle: ``vehicle.odometry()`` → odometry queue (bounded, drop-oldest, counted)
- slam: frame queue → odometry integrated to the frame's capture time → ``Pipeline.step`` →
  publish queue; the latency budget degrades (features, particles, frame skipping) and recovers
- publisher: pose every step (Zenoh, MAVLink), map periodically, health at 1 Hz
- main: supervises: sd_notify (READY=1 once camera and vehicle deliver, WATCHDOG=1 only on real
  SLAM progress, STATUS=), the once-a-second health line, periodic map saves, and the stop flag
  that the signal handlers set (they do nothing else).
"""

from __future__ import annotations

import contextlib
import logging
import os
import resource
import signal
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

import drivers
from robotd.autopilot import ResetCounterPolicy, ResetEvent, quality_from
from robotd.budget import LatencyBudget, StageTimer
from robotd.config import Config
from robotd.errors import DriverError, PersistenceError, RobotdError
from robotd.geometry import se3_inverse
from robotd.msgs import Odometry, StepResult, StereoFrame
from robotd.odometry import OdometryIntegrator
from robotd.persist import MapStore, default_state_dir
from robotd.pipeline import Pipeline
from robotd.queues import DropOldestQueue
from robotd.sdnotify import Notifier

logger = logging.getLogger(__name__)

JOIN_TIMEOUT_S = 2.0
# devices that can appear later (plugged in, powered up): opening them is retried
HARDWARE_SCHEMES = ("oak", "serial", "mavlink+udp", "mavlink+serial")


def rss_mb() -> float:
    """Resident set size now (Linux /proc), MB."""
    try:
        with open("/proc/self/statm") as f:
            pages = int(f.read().split()[1])
        return pages * os.sysconf("SC_PAGE_SIZE") / 1e6
    except (OSError, ValueError):
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3


@dataclass
class Published:
    """One SLAM result on its way to the publisher."""

    result: StepResult
    truth: np.ndarray | None
    quality: int
    frame_seq: int
    landmarks: Any = None  # LandmarkMap snapshot, taken by the SLAM thread when a map update is due
    event: str | None = None  # a pose discontinuity in this step (ResetEvent), for the autopilot


@dataclass
class DaemonStats:
    started_ns: int = field(default_factory=time.monotonic_ns)
    frames_in: int = 0
    odometry_in: int = 0
    steps: int = 0
    step_errors: int = 0
    last_step_ns: int = 0
    published: int = 0
    latencies_ms: list[float] = field(default_factory=list)  # capture → publish, last window
    seq_gaps: int = 0
    reset_counter: int = 0
    last_error_m: float = float("nan")
    max_latency_window: int = 2000

    def add_latency(self, ms: float) -> None:
        self.latencies_ms.append(ms)
        if len(self.latencies_ms) > self.max_latency_window:
            del self.latencies_ms[: len(self.latencies_ms) - self.max_latency_window]


class Daemon:
    def __init__(
        self,
        cfg: Config,
        duration_s: float = 0.0,
        environ: dict[str, str] | None = None,
        record_path: str | None = None,
    ) -> None:
        self.cfg = cfg
        self.record_path = record_path
        self.writer: Any = None
        self.recorded = {"frames": 0, "odometry": 0, "poses": 0}
        self.duration_s = duration_s
        self.stop_event = threading.Event()
        self.stop_reason = ""
        self.notifier = Notifier(environ)
        self.stats = DaemonStats()
        self.frame_q: DropOldestQueue[StereoFrame] = DropOldestQueue(cfg.camera.queue_size)
        self.odo_q: DropOldestQueue[Odometry] = DropOldestQueue(cfg.vehicle.queue_size)
        self.pub_q: DropOldestQueue[Published] = DropOldestQueue(64)
        self.integrator = OdometryIntegrator(max_gap_s=cfg.vehicle.max_gap_s)
        self.timer = StageTimer()
        self.camera: Any = None
        self.vehicle: Any = None
        self.autopilot: drivers.AutopilotLink | None = None  # where the pose goes (MAVLink, sim), if anywhere
        self.autopilot_link: drivers.VehicleLink | None = None  # a MAVLink link opened only for the pose
        self.reset_policy = ResetCounterPolicy()
        self._pending_event: str | None = None
        self.pipeline: Pipeline | None = None
        self.budget: LatencyBudget | None = None
        self.publisher: Any = None
        self.store: MapStore | None = None
        self.threads: list[threading.Thread] = []
        self._lock = threading.Lock()
        self._last_result: Published | None = None
        self._last_frame_seq: int | None = None
        self._first_truth_inv: np.ndarray | None = None
        self._ready = False
        self._save_request = threading.Event()
        self._save_q: DropOldestQueue[tuple[int, dict[str, Any]]] = DropOldestQueue(1)
        self.resumed = False
        self.exit_code = 0
        self._cv_threads: int | None = None  # OpenCV's thread count before startup changed it
        self._blas_limits: list[tuple[Any, int]] | None = None  # BLAS pools and their thread counts before startup
        self._prev_handlers: dict[int, Any] = {}  # signal handlers replaced by install_signal_handlers

    # ------------------------------------------------------------------ signals: flags only
    def _on_signal(self, signum: int, _frame: Any) -> None:
        self.stop_reason = signal.Signals(signum).name
        self.stop_event.set()

    def install_signal_handlers(self) -> None:
        if threading.current_thread() is threading.main_thread():
            self._prev_handlers = {sig: signal.signal(sig, self._on_signal) for sig in (signal.SIGTERM, signal.SIGINT)}

    def restore_signal_handlers(self) -> None:
        """Put back the handlers the daemon replaced (a program that embeds it keeps its own
        Ctrl-C after the daemon stops, and the stopped daemon is not kept alive by them)."""
        if threading.current_thread() is threading.main_thread():
            for sig, handler in self._prev_handlers.items():
                signal.signal(sig, handler if handler is not None else signal.SIG_DFL)
        self._prev_handlers = {}

    # ------------------------------------------------------------------ startup
    def startup(self, stack: contextlib.ExitStack) -> None:
        cfg = self.cfg
        logger.info(
            "robotd starting: robot %s, seed %d, camera %s, vehicle %s, filter %s %dD",
            cfg.robot.id,
            cfg.robot.seed,
            cfg.camera.url,
            cfg.vehicle.url,
            cfg.slam.filter,
            cfg.slam.dim,
        )
        self.camera = self._open_with_retry(stack, "camera", drivers.open_camera, cfg.camera.url)
        self.vehicle = self._open_with_retry(
            stack, "vehicle", drivers.open_vehicle, cfg.vehicle.url, **self._link_options(cfg.vehicle.url)
        )
        if cfg.mavlink.enabled and not cfg.vehicle.url.startswith("mavlink"):
            # odometry from one link (e.g. the MCU over serial), the pose to the autopilot on another
            self.autopilot_link = self._open_with_retry(
                stack, "autopilot", drivers.open_vehicle, cfg.mavlink.url, **self._link_options(cfg.mavlink.url)
            )
            self.autopilot = self.autopilot_link.autopilot
        else:
            self.autopilot = self.vehicle.autopilot
        rig = self.camera.rectified_model()
        logger.info("rig: f %.1f px, baseline %.4f m, %dx%d", rig.f_px, rig.baseline_m, rig.width, rig.height)
        rng = np.random.default_rng(cfg.robot.seed)
        self.pipeline = Pipeline(cfg, rig, rng)
        warm_s = self.pipeline.warmup()
        if self.pipeline.frontend.params.parallel_detect:
            # the front end detects the left and right images on two threads of its own; OpenCV's
            # worker pool on top of them only adds threads and their spin-waits (≈ 1 ms CPU per
            # frame on 2 cores); the results do not depend on it. Restored at shutdown.
            import cv2

            self._cv_threads = cv2.getNumThreads()
            cv2.setNumThreads(1)
        # One BLAS thread by default (slam.blas_threads): the daemon runs its stages on threads of
        # its own, and the matrix products on its hot path are small. A second OpenBLAS worker only
        # spin-waits between calls: with SIFT (float descriptor products) it burned half a core,
        # with ORB ≈ 0.7 ms of CPU per frame, on the cores the detection threads need. Restored at
        # shutdown.
        self._blas_limits = _limit_blas_threads(cfg.slam.blas_threads)
        logger.info("filter and matcher kernels ready in %.1f s", warm_s)
        fps = float(getattr(self.camera, "fps", 0.0) or 30.0)
        deadline = cfg.budget.deadline_ms or 1000.0 / fps
        self.budget = LatencyBudget(
            deadline,
            cfg.frontend.max_features,
            cfg.slam.n_particles if cfg.slam.filter != "ekf" else 1,
            min(cfg.budget.min_features, cfg.frontend.max_features),
            min(cfg.budget.min_particles, cfg.slam.n_particles) if cfg.slam.filter != "ekf" else 1,
            cfg.budget.recover_after_frames,
            warmup_frames=int(fps),  # the first second: caches and the first map
            frame_period_ms=1000.0 / fps,
        )
        logger.info("latency budget: deadline %.1f ms, %d degradation levels", deadline, self.budget.max_level)
        self.store = MapStore(default_state_dir(cfg.persistence.state_dir), cfg.robot.id)
        if cfg.persistence.resume:
            self._resume()
        if self.record_path:
            from robotd.record import SessionWriter

            meta = {"robot": cfg.robot.id, "camera": cfg.camera.url, "vehicle": cfg.vehicle.url, "seed": cfg.robot.seed}
            self.writer = stack.enter_context(
                SessionWriter(
                    self.record_path, rig, meta, raw_calibration=getattr(self.camera, "raw_calibration", None)
                )
            )
            logger.info("recording to %s", self.record_path)
        if cfg.zenoh.enabled:
            from robotd.publish import Publisher

            self.publisher = stack.enter_context(Publisher(cfg.zenoh, cfg.robot.id))

    def _link_options(self, url: str) -> dict[str, Any]:
        """Driver keywords from the config for a MAVLink link (others take theirs from the URL)."""
        if not url.startswith("mavlink"):
            return {}
        m = self.cfg.mavlink
        opts: dict[str, Any] = {"sysid": m.system_id, "message": m.message}
        if m.signing_key_file:
            opts["signing_key"] = m.signing_key_file
        if m.set_origin:
            opts["origin"] = (m.origin_lat_deg, m.origin_lon_deg, m.origin_alt_m)
        return opts

    def _open_with_retry(self, stack: contextlib.ExitStack, kind: str, opener: Any, url: str, **options: Any) -> Any:
        """Open a driver; a missing device is a degraded state with retries, not an exit."""
        delay = 0.5
        while True:
            try:
                return stack.enter_context(opener(url, **options))
            except DriverError as exc:
                if self.stop_event.is_set():
                    raise
                if url.split("://")[0] not in HARDWARE_SCHEMES:
                    raise  # a simulator or dataset that fails to open will not heal by waiting
                logger.error("%s %s unavailable: %s; retrying in %.1f s", kind, url, exc, delay)
                self.notifier.status(f"waiting for {kind}: {exc}")
                if self.stop_event.wait(delay):
                    raise
                delay = min(delay * 2, 10.0)

    def _resume(self) -> None:
        assert self.store is not None and self.pipeline is not None
        if not self.store.exists():
            logger.info("resume: no saved map in %s, starting a new map", self.store.dir)
            return
        try:
            saved = self.store.load()
            self.pipeline.load_state_dict(saved["state"])
        except PersistenceError as exc:
            logger.error("resume failed: %s", exc)
            return
        self.resumed = True
        self._pending_event = ResetEvent.MAP_LOAD  # a discontinuity for the autopilot
        n = int(self.pipeline.estimator.landmark_ids().shape[0])
        logger.info("resumed from saved map %s: %d landmarks", self.store.path, n)

    # ------------------------------------------------------------------ threads
    def _camera_loop(self) -> None:
        try:
            for frame in self.camera.frames(timeout_s=0.5):
                if self.stop_event.is_set():
                    break
                self.stats.frames_in += 1
                self.frame_q.put(frame)
        except RobotdError as exc:
            logger.error("camera thread stopped: %s", exc)
        except Exception:
            logger.exception("camera thread crashed")
        finally:
            if not self.stop_event.is_set() and self.duration_s == 0.0:
                logger.info("camera source ended")
            self.frame_q.close()

    def _vehicle_loop(self) -> None:
        try:
            for odo in self.vehicle.odometry(timeout_s=0.5):
                if self.stop_event.is_set():
                    break
                self.stats.odometry_in += 1
                self.odo_q.put(odo)
        except RobotdError as exc:
            logger.error("vehicle thread stopped: %s", exc)
        except Exception:
            logger.exception("vehicle thread crashed")

    def _slam_loop(self) -> None:
        assert self.pipeline is not None and self.budget is not None
        pipeline, budget = self.pipeline, self.budget
        last_t: int | None = None
        next_map = 0.0
        # Only this thread touches the pipeline and the estimator: map snapshots for the publisher
        # and state snapshots for saving are taken here, between steps.
        while not self.stop_event.is_set():
            frame = self.frame_q.get(timeout=0.2)
            if frame is None:
                if self.frame_q.closed:
                    break
                continue
            for odo in self.odo_q.drain():
                self.integrator.add(odo)
                if self.writer is not None:
                    self.writer.write_odometry(odo)
                    self.recorded["odometry"] += 1
            if self.writer is not None:
                # the writer belongs to this thread: what is recorded is exactly what SLAM consumed
                self.writer.write_frame(frame)
                self.recorded["frames"] += 1
            if self._last_frame_seq is not None and frame.seq > self._last_frame_seq + 1:
                self.stats.seq_gaps += 1
            self._last_frame_seq = frame.seq
            if not budget.should_process():
                continue
            inc = None
            if last_t is not None:
                inc = self.integrator.integrate(last_t, frame.t_ns)
            t0 = time.perf_counter()
            try:
                result = pipeline.step(frame, inc)
            except RobotdError as exc:
                self.stats.step_errors += 1
                logger.error("frame %d skipped: %s", frame.seq, exc)
                continue
            frame_ms = (time.perf_counter() - t0) * 1e3
            # the budget judges what the deadline is about: capture to result, queue wait included
            latency_ms = (time.monotonic_ns() - frame.t_ns) / 1e6
            last_t = frame.t_ns
            self.integrator.prune_before(frame.t_ns)
            for k, v in result.timings_ms.items():
                self.timer.add(k, v)
            state = budget.record(frame_ms, latency_ms)
            pipeline.set_max_features(state.max_features)
            if self.cfg.slam.filter != "ekf":
                pipeline.set_particles(state.n_particles)
            self.stats.steps += 1
            self.stats.last_step_ns = time.monotonic_ns()
            if self.writer is not None:
                self.writer.write_pose(result.pose)
                self.recorded["poses"] += 1
            lm = None
            now = time.monotonic()
            if now >= next_map:
                next_map = now + self.cfg.zenoh.map_period_s
                lm = pipeline.estimator.landmarks()
            if self._save_request.is_set():
                self._save_request.clear()
                self._save_q.put((frame.t_ns, pipeline.state_dict()))
            event = ResetEvent.RELOCALISATION if result.relocalised else None
            quality = quality_from(
                result.tracking,
                result.counts.get("identified", 0),
                result.pose.neff,
                result.pose.n_particles,
                min_inliers=self.cfg.frontend.min_inliers,
            )
            self.pub_q.put(Published(result, frame.truth_T_world_robot, quality, frame.seq, lm, event))
        self.pub_q.close()

    def _publisher_loop(self) -> None:
        from robotd.publish import pose_to_json

        seq = 0
        while True:
            item = self.pub_q.get(timeout=0.2)
            if item is None:
                if self.pub_q.closed:
                    break
                continue
            res = item.result
            latency_ms = (time.monotonic_ns() - res.t_ns) / 1e6
            self.stats.add_latency(latency_ms)
            self.stats.published += 1
            if item.truth is not None:
                if self._first_truth_inv is None:
                    self._first_truth_inv = se3_inverse(item.truth)
                T_true = self._first_truth_inv @ item.truth
                self.stats.last_error_m = float(np.linalg.norm(res.pose.T_world_robot[:3, 3] - T_true[:3, 3]))
            with self._lock:
                self._last_result = item
            seq += 1
            event, self._pending_event = self._pending_event or item.event, None
            self.stats.reset_counter = self.reset_policy.update(res.pose, event)
            if self.publisher is not None:
                self.publisher.publish_pose(
                    pose_to_json(res.pose, self.cfg.robot.id, seq, item.quality, self.stats.reset_counter, latency_ms)
                )
                if item.landmarks is not None:
                    self.publisher.update_map(res.t_ns, item.landmarks)
            if self.autopilot is not None:
                try:
                    self.autopilot.set_health(self._health_state(item))
                    self.autopilot.send_pose(res.pose, item.quality, self.stats.reset_counter)
                except RobotdError as exc:
                    logger.warning("autopilot pose not sent: %s", exc)

    # ------------------------------------------------------------------ health
    def _health_state(self, item: Published) -> str:
        if not item.result.tracking:
            return "failed"
        if self.budget is not None and self.budget.state.level > 0:
            return "degraded"
        return "tracking"

    def record_summary(self) -> dict[str, Any]:
        return {"out": self.record_path, **self.recorded, "frames_dropped": self.frame_q.dropped}

    def health(self) -> dict[str, Any]:
        assert self.budget is not None and self.pipeline is not None
        lat = np.asarray(self.stats.latencies_ms[-300:]) if self.stats.latencies_ms else np.zeros(0)
        with self._lock:
            last = self._last_result
        pose = last.result if last else None
        return {
            "t_ns": time.monotonic_ns(),
            "uptime_s": round((time.monotonic_ns() - self.stats.started_ns) / 1e9, 3),
            "ready": self._ready,
            "tracking": bool(pose.tracking) if pose else False,
            "quality": last.quality if last else 0,
            "stages_ms": self.timer.percentiles(),
            "latency_ms": {
                "p50": float(np.percentile(lat, 50)) if lat.size else None,
                "p99": float(np.percentile(lat, 99)) if lat.size else None,
            },
            "frames_in": self.stats.frames_in,
            "frames_processed": self.stats.steps,
            "frame_drops": self.frame_q.dropped,
            "odometry_drops": self.odo_q.dropped,
            "seq_gaps": self.stats.seq_gaps,
            "step_errors": self.stats.step_errors,
            "budget": self.budget.health(),
            "neff": None if not pose or not np.isfinite(pose.pose.neff) else float(pose.pose.neff),
            "particles": pose.pose.n_particles if pose else 0,
            "features": pose.counts.get("features_left", 0) if pose else 0,
            "landmarks": pose.counts.get("landmarks", 0) if pose else 0,
            "error_vs_truth_m": None if not np.isfinite(self.stats.last_error_m) else self.stats.last_error_m,
            "rss_mb": round(rss_mb(), 1),
            "camera": _safe_stats(self.camera),
            "vehicle": _safe_stats(self.vehicle),
        }

    def status_line(self, h: dict[str, Any], fps: float) -> str:
        with self._lock:
            last = self._last_result
        if last is None:
            return f"waiting for frames (in {h['frames_in']}, odometry {self.stats.odometry_in})"
        p = last.result.pose
        yaw = np.degrees(p.rpy_rad[2])
        err = h["error_vs_truth_m"]
        lat = h["latency_ms"]
        return (
            f"pose x {p.xyz_W_m[0]:+7.2f} y {p.xyz_W_m[1]:+7.2f} z {p.xyz_W_m[2]:+6.2f} m yaw {yaw:+6.1f}° | "
            f"err {'n/a' if err is None else f'{err:.3f} m'} | "
            f"latency p50 {lat['p50'] or 0:.1f} p99 {lat['p99'] or 0:.1f} ms | "
            f"{fps:.1f} fps, drops {h['frame_drops']} | lm {h['landmarks']} feat {h['features']} | "
            f"q {last.quality} budget L{h['budget']['level']}"
        )

    # ------------------------------------------------------------------ main loop
    def run(self) -> int:
        self.install_signal_handlers()
        try:
            with contextlib.ExitStack() as stack:
                try:
                    self.startup(stack)
                except RobotdError as exc:
                    if self.stop_event.is_set():
                        logger.info("stopped during startup (%s)", self.stop_reason)
                        return 0
                    logger.error("startup failed: %s", exc)
                    self.notifier.notify(f"STATUS=startup failed: {exc}", "ERRNO=1")
                    return 2
                self._start_threads()
                try:
                    self._supervise()
                finally:
                    self._shutdown()
            return self.exit_code
        finally:
            self.restore_signal_handlers()

    def _start_threads(self) -> None:
        for name, fn in (
            ("camera", self._camera_loop),
            ("vehicle", self._vehicle_loop),
            ("slam", self._slam_loop),
            ("publisher", self._publisher_loop),
        ):
            t = threading.Thread(target=fn, name=f"robotd-{name}", daemon=True)
            t.start()
            self.threads.append(t)

    def _supervise(self) -> None:
        cfg = self.cfg
        t_start = time.monotonic()
        next_status = t_start + cfg.log.status_period_s
        next_health = t_start + cfg.zenoh.health_period_s
        next_save = t_start + cfg.persistence.save_period_s if cfg.persistence.save_period_s > 0 else float("inf")
        wd = self.notifier.watchdog_interval_s
        next_wd = t_start
        last_steps = 0
        last_rate_t, last_rate_steps = t_start, 0
        fps = 0.0
        needs_vehicle = not cfg.vehicle.url.startswith("none:")
        while not self.stop_event.wait(0.05):
            now = time.monotonic()
            if self.duration_s and now - t_start >= self.duration_s:
                self.stop_reason = "duration reached"
                break
            if not self.threads[2].is_alive():
                self.stop_reason = "source ended"
                break
            if not self._ready and self.stats.steps > 0 and (self.stats.odometry_in > 0 or not needs_vehicle):
                self._ready = True
                self.notifier.ready("tracking")
                logger.info("ready: camera and vehicle link deliver (first step after %.2f s)", now - t_start)
            if wd is not None and now >= next_wd:
                # ping only on real progress: SLAM completed a step since the last ping
                if self.stats.steps > last_steps:
                    self.notifier.watchdog()
                    last_steps = self.stats.steps
                next_wd = now + wd / 2
            if now >= next_health:
                next_health = now + cfg.zenoh.health_period_s
                if self.publisher is not None:
                    self.publisher.publish_health(self.health())
            if now >= next_status:
                next_status = now + cfg.log.status_period_s
                fps = (self.stats.steps - last_rate_steps) / max(now - last_rate_t, 1e-6)
                last_rate_t, last_rate_steps = now, self.stats.steps
                h = self.health()
                line = self.status_line(h, fps)
                logger.info(line)
                self.notifier.status(line[:200])
            if now >= next_save:
                next_save = now + cfg.persistence.save_period_s
                self._save_request.set()
            snap = self._save_q.get(timeout=0)
            if snap is not None:
                self._write_map(*snap)
        if self.stop_event.is_set() and not self.stop_reason:
            self.stop_reason = "stop requested"

    def _write_map(self, t_ns: int, state: dict[str, Any]) -> bool:
        """Write a state snapshot (taken by the SLAM thread, or after it stopped) to disk."""
        if self.store is None:
            return False
        try:
            path = self.store.save(state, t_ns)
        except PersistenceError as exc:
            logger.error("%s", exc)
            return False
        n = len(state.get("database", {}).get("ids", ()))
        logger.info("map saved to %s (%d landmarks)", path, n)
        return True

    def save_final_map(self) -> bool:
        """At shutdown, once the SLAM thread has stopped: nothing else touches the estimator."""
        if self.pipeline is None or self.stats.steps == 0:
            return False
        if any(t.name == "robotd-slam" and t.is_alive() for t in self.threads):
            logger.error("map not saved at shutdown: the SLAM thread is still running")
            return False
        return self._write_map(time.monotonic_ns(), self.pipeline.state_dict())

    def _shutdown(self) -> None:
        t0 = time.monotonic()
        logger.info("shutting down (%s)", self.stop_reason or "stop")
        self.notifier.stopping(f"stopping: {self.stop_reason}")
        self.stop_event.set()
        for dev in (self.camera, self.vehicle, self.autopilot_link):
            if dev is not None:
                with contextlib.suppress(Exception):
                    dev.close()
        self.frame_q.close()
        for t in self.threads:
            t.join(JOIN_TIMEOUT_S)
            if t.is_alive():
                logger.warning("thread %s did not stop within %.1f s", t.name, JOIN_TIMEOUT_S)
        if self._cv_threads is not None:
            import cv2

            cv2.setNumThreads(self._cv_threads)
        if self._blas_limits is not None:
            _restore_blas_threads(self._blas_limits)
        self.save_final_map()
        lat = np.asarray(self.stats.latencies_ms) if self.stats.latencies_ms else np.zeros(1)
        logger.info(
            "stopped after %d steps: latency p50 %.1f ms p99 %.1f ms, %d frames dropped, shutdown %.2f s",
            self.stats.steps,
            np.percentile(lat, 50),
            np.percentile(lat, 99),
            self.frame_q.dropped,
            time.monotonic() - t0,
        )
        self.notifier.close()


def _limit_blas_threads(n: int) -> list[tuple[Any, int]]:
    """Set every loaded BLAS pool (numpy's, SciPy's and OpenCV's OpenBLAS each have one) to ``n``
    threads; returns the pools with their previous counts for :func:`_restore_blas_threads`.

    Best effort: OpenBLAS may ignore a second change in one process (seen when an earlier daemon in
    the same process had limited and restored it, the limit then being set from another thread);
    that is logged. ``robotd`` itself sets OPENBLAS_NUM_THREADS=1 before numpy loads (robotd.cli),
    which this only repeats; it matters for daemons embedded in other programs (bench/daemon.py)."""
    from threadpoolctl import ThreadpoolController

    changed: list[tuple[Any, int]] = []
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


def _restore_blas_threads(changed: list[tuple[Any, int]]) -> None:
    for lib, before in changed:
        try:
            lib.set_num_threads(before)
        except Exception as exc:
            logger.warning("BLAS %s: thread count not restored (%s)", getattr(lib, "filepath", "?"), exc)


def _safe_stats(dev: Any) -> dict[str, Any]:
    if dev is None:
        return {}
    try:
        s = dev.stats()
        return {k: v for k, v in s.items() if isinstance(v, int | float | str | bool) or v is None}
    except Exception as exc:
        return {"error": str(exc)}


def run_daemon(cfg: Config, duration_s: float = 0.0) -> int:
    return Daemon(cfg, duration_s).run()


__all__ = ["Daemon", "run_daemon"]
