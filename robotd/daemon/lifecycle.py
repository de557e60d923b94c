"""The daemon: signals → startup → loop → graceful shutdown (docs/architecture.md "House style", docs/interfaces.md §4).

Threads:

- camera: ``camera.frames()`` → the outputs' tees (the recorder's sensor log: every frame) → frame
  queue (bounded, drop-oldest, counted)
- vehicle: ``vehicle.odometry()`` → the tees (every sample) → odometry queue (bounded, drop-oldest, counted)
- slam (slam_thread.py): frame queue → :class:`robotd.pipeline.feed.Feed`, the per-frame loop ``robotd
  replay`` runs too (odometry gated and integrated to the frame's capture time → ``Pipeline.step``,
  a failed step skipped) → publish queue; the latency budget degrades (features, particles, frame
  skipping) and recovers. It is the only thread that touches the pipeline: the map and state
  snapshots the outputs ask for are taken here, between steps.
- publisher (publisher.py): every step's :class:`~robotd.outputs.base.StepReport` (reset counter,
  quality) to the outputs
- one worker per output (robotd.outputs.runner): the output's ``record_inputs``, ``publish`` and
  ``publish_health``, which the SLAM, publisher and supervisor threads only queue; every hook of
  every output under one error policy (logged once, counted, in health, stopping nothing else)
- main: supervises (supervisor.py): sd_notify (READY=1 once camera and vehicle deliver, WATCHDOG=1 only on real
  SLAM progress, STATUS=), the once-a-second health line, the health document for the outputs,
  and the stop flag that the signal handlers set (they do nothing else).
"""

from __future__ import annotations

import contextlib
import importlib
import logging
import math
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

import drivers
from drivers.mavlink_odometry import AutopilotPose
from robotd.config import Config
from robotd.config.params import odometry_limits_from_config
from robotd.core import jit
from robotd.core.errors import ConfigError, RobotdError
from robotd.core.jit import CompileWatch
from robotd.core.msgs import Odometry, StereoFrame
from robotd.daemon.budget import LatencyBudget, StageTimer, budget_for
from robotd.daemon.device_urls import check_device_urls
from robotd.daemon.devices import open_devices
from robotd.daemon.handover import Handover, handover_from
from robotd.daemon.handover import record as handover_record
from robotd.daemon.health import STALL_MIN_S, STALL_PERIODS, DaemonStats, HealthMonitor
from robotd.daemon.inputs import pump_frames, pump_odometry
from robotd.daemon.publisher import Publisher
from robotd.daemon.sdnotify import Notifier
from robotd.daemon.signals import StopSignals
from robotd.daemon.slam_thread import Deliveries, SlamThread, Stepped
from robotd.daemon.state import open_state
from robotd.daemon.supervisor import Supervisor
from robotd.daemon.threadpools import ThreadLimits, limit_threads
from robotd.formats.autopilot import ResetCounterPolicy, ResetEvent
from robotd.formats.persist import CounterFile, StateDirLock, default_state_dir
from robotd.formats.queues import DropOldestQueue
from robotd.outputs import Output, OutputContext, OutputRunner, build_outputs
from robotd.outputs.mapfile import HANDOVER_KEY, MapFileOutput
from robotd.outputs.recorder import RecorderOutput
from robotd.pipeline.feed import Feed
from robotd.pipeline.odometry import OdometryGate, OdometryIntegrator
from robotd.pipeline.step import Pipeline
from robotd.slam.estimator import Persistent

logger = logging.getLogger("robotd.daemon")  # the name users filter the lifecycle lines by

JOIN_TIMEOUT_S = 2.0
# said when the first kernel compiles (numba found none in its cache); a warm start never says it
COMPILING = (
    "compiling the kernels: the numba cache has none for this robotd, numba and CPU (a first run or an "
    "upgrade); this takes tens of seconds, more on a busy machine, once: later starts load them from the cache"
)
COMPILING_UNCACHED = (
    "compiling the kernels: no numba cache directory is writable (NUMBA_CACHE_DIR), so every start compiles "
    "them; this takes tens of seconds, more on a busy machine"
)


class Daemon:
    """``robotd run`` and ``robotd record``: startup (devices, pipeline, budget, state, outputs),
    the threads (inputs.py, slam_thread.py, publisher.py; supervisor.py on the main thread), the
    health documents, and shutdown (module docstring)."""

    def __init__(
        self,
        cfg: Config,
        duration_s: float = 0.0,
        environ: dict[str, str] | None = None,
        record_path: str | None = None,
        keep_state: bool | None = None,
        buffer_mb: float | None = None,
    ) -> None:
        """``keep_state`` False: no map file (no resume, no save) and no reset counter file, nothing
        read or written under the state directory (``robotd record`` beside a running daemon);
        None: False when recording (``record_path``), else True. ``buffer_mb``: images that may
        wait for the recorder's writer (None: its default)."""
        if not (duration_s >= 0 and math.isfinite(duration_s)):
            raise ConfigError(f"--duration: expected seconds >= 0 (0: until stopped), got {duration_s}")
        self.cfg = cfg
        self.record_path = record_path
        self.keep_state = record_path is None if keep_state is None else keep_state
        self.buffer_mb = buffer_mb
        self.duration_s = duration_s
        self._t_created = time.monotonic()
        self.stop_event = threading.Event()
        self.signals = StopSignals(self.stop_event)
        self._stop_reason = ""
        self.notifier = Notifier(environ)
        self.health = HealthMonitor()
        self.frame_q: DropOldestQueue[StereoFrame] = DropOldestQueue(cfg.camera.queue_size)
        self.odo_q: DropOldestQueue[Odometry] = DropOldestQueue(cfg.vehicle.queue_size)
        self.pub_q: DropOldestQueue[Stepped] = DropOldestQueue(64)
        self.integrator = OdometryIntegrator(max_gap_s=cfg.vehicle.max_gap_s)
        self.odometry_gate = OdometryGate(odometry_limits_from_config(cfg))
        self.camera: drivers.StereoCamera | None = None
        self.vehicle: drivers.VehicleLink | None = None
        self.autopilot_link: drivers.VehicleLink | None = None  # a MAVLink link opened only for the pose
        self.reset_policy = ResetCounterPolicy()
        self.counter_file: CounterFile | None = None
        self._pending_event: str | None = None  # a discontinuity before the first step (map load)
        self.pipeline: Pipeline | None = None
        self.autopilot_pose_at: Callable[[int], AutopilotPose | None] | None = None
        self.handover: Handover | None = None  # a resumed pose carried by the autopilot's motion
        self._slam: SlamThread | None = None
        self.feed: Feed | None = None  # the per-frame loop the SLAM thread runs (robotd.pipeline.feed)
        self.budget: LatencyBudget | None = None
        self.maps: MapFileOutput | None = None
        self.recorder: RecorderOutput | None = None
        self.outputs: list[Output] = []
        self.output_runner = OutputRunner([])  # every output's hooks, under one error policy
        self.threads: list[threading.Thread] = []
        self._supervisor: Supervisor | None = None
        # the camera stamps frames on this host's monotonic clock (a live camera); False for a
        # dataset's clock (kitti://, euroc://, a recording, sim:// not in real time)
        self.host_clock = True
        self._deliveries = Deliveries(cfg.camera.queue_size + 16)
        self._frame_period_s = 1.0 / 30.0  # the camera's, once it is open
        self.resumed = False
        self.exit_code = 0
        self.failed: list[str] = []  # threads that stopped the daemon (see _fail)
        self._limits = ThreadLimits()

    @property
    def stop_reason(self) -> str:
        """Why the daemon stopped: the signal's name, "duration reached", "source ended", ..."""
        return self._stop_reason or self.signals.reason

    @stop_reason.setter
    def stop_reason(self, why: str) -> None:
        self._stop_reason = why

    @property
    def stats(self) -> DaemonStats:
        return self.health.stats

    @property
    def timer(self) -> StageTimer:
        return self.health.timer

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
        # the device URLs' schemes and parameters before anything slow (the CLI checked them too)
        check_device_urls(cfg)
        if self.keep_state:  # one robotd per state directory, before anything slow (robotd.formats.persist)
            stack.enter_context(StateDirLock(default_state_dir(cfg.persistence.state_dir), cfg.robot.id))
        # The kernels and the devices. With the kernels in numba's cache, loading them (0.7 s on
        # the 2-core VM) runs while the devices open (a sim world's build, an OAK-D's boot, a
        # MAVLink heartbeat): a restarted robotd's first pose comes that much sooner, and the
        # autopilot dead-reckons that much less (docs/mavlink.md §9). Without them, the kernels
        # first: compiling takes tens of seconds, and the devices are opened only then, so no
        # camera streams into a queue nobody reads (and sim:// starts its path when the daemon
        # can follow it). The compile is announced only when numba finds no cached kernel
        # (robotd.core.jit.CompileWatch), never on a warm start.
        give_up_at = self._t_created + self.duration_s if self.duration_s > 0 else math.inf
        if kernels_cached():
            with _KernelLoader(cfg):
                dev = open_devices(cfg, stack, self.stop_event, self.notifier, give_up_at)
        else:
            _load_kernels(cfg)
            dev = open_devices(cfg, stack, self.stop_event, self.notifier, give_up_at)
        self.camera, self.vehicle, self.autopilot_link = dev.camera, dev.vehicle, dev.autopilot_link
        # the autopilot's own pose, where a link carries it: recorded with each map save, and what
        # carries the pose across a restart (robotd.daemon.handover)
        for link in (dev.autopilot_link, dev.vehicle):
            if isinstance(link, drivers.AutopilotPoseSource):
                self.autopilot_pose_at = link.autopilot_pose_at
                break
        rig = dev.camera.rectified_model()
        logger.info("rig: f %.1f px, baseline %.4f m, %dx%d", rig.f_px, rig.baseline_m, rig.width, rig.height)
        self.pipeline = Pipeline(cfg, rig, np.random.default_rng(cfg.robot.seed))
        self.feed = Feed(self.pipeline, self.integrator, self.odometry_gate, self.stats, log=logger)
        self._limits = limit_threads(self.pipeline.frontend.params.parallel_detect, cfg.slam.blas_threads)
        self.host_clock = dev.camera.host_clock
        if not self.host_clock:
            self.health.latency_from = "delivery"
            logger.info("camera stamps are not on this host's clock: latency is measured from each frame's delivery")
        fps = dev.camera.fps or 30.0
        self._frame_period_s = 1.0 / fps
        self.budget = budget_for(cfg, fps, self.pipeline.kind.particles is not None)  # what the filter declared
        logger.info(
            "latency budget: deadline %.1f ms, %d degradation levels", self.budget.deadline_ms, self.budget.max_level
        )
        if self.keep_state:
            state = open_state(cfg, stack, self.pipeline, self.reset_policy)
            self.counter_file, self.maps, self.resumed = state.counter_file, state.maps, state.resumed
            if self.resumed and not state.new_segment:
                # a discontinuity for the autopilot; when the counter already starts above the last
                # run's, the first pose is a new segment without it, and a second bump one frame on
                # (the relocalisation's) is what the autopilot should see next
                self._pending_event = ResetEvent.MAP_LOAD
            if self.resumed and self.maps is not None:
                self.handover = handover_from(self.maps.saved_handover, self.pipeline, self.autopilot_pose_at)
        else:
            logger.info("state: none (no map, no reset counter file; the state directory is not touched)")
        meta = {"robot": cfg.robot.id, "camera": cfg.camera.url, "vehicle": cfg.vehicle.url, "seed": cfg.robot.seed}
        meta["inputs"] = "delivered"  # a recording holds every sample the devices delivered (not what SLAM took)
        ctx = OutputContext(cfg, rig, dev.autopilot, self.record_path, meta, dev.camera.raw_calibration, self.buffer_mb)
        self.outputs = [*([self.maps] if self.maps is not None else []), *build_outputs(ctx, stack)]
        self.output_runner = OutputRunner(self.outputs)
        self.recorder = next((o for o in self.outputs if isinstance(o, RecorderOutput)), None)
        logger.info("outputs: %s", ", ".join(o.name for o in self.outputs))

    # ------------------------------------------------------------------ health
    def record_summary(self) -> dict[str, Any]:
        """``robotd record``'s figures: what the devices delivered, what the file holds and what it
        lost (the writer fell behind), and what SLAM processed of it."""
        rec = self.recorder
        counts = rec.stats() if rec is not None else {"out": self.record_path, "frames": 0, "odometry": 0, "poses": 0}
        counts.pop("last_loss_ns", None)
        return {
            **counts,
            "frames_delivered": self.stats.frames_in,
            "odometry_delivered": self.stats.odometry_in,
            "frames_missed": self.stats.frames_missed,  # never delivered by the camera (sequence gaps)
            "slam_steps": self.stats.steps,
            "slam_dropped": self.frame_q.dropped,
            "slam_skipped": self.budget.skipped if self.budget is not None else 0,
            "camera": _plain_stats(self.camera),  # the driver's own counts ("frames": what it delivered)
        }

    def health_doc(self) -> dict[str, Any]:
        assert self.budget is not None
        devices = {"camera": self.camera, "vehicle": self.vehicle}
        ready = self._supervisor is not None and self._supervisor.ready
        doc = self.health.doc(ready, self.budget, self.frame_q, self.odo_q, devices)
        doc["odometry"] = {**self.odometry_gate.stats(), "gaps": self.integrator.gaps}
        if self.pipeline is not None:
            c = self.pipeline.counters
            doc["odometry"].update(
                gravity_fused=c.gravity_fused,
                gravity_rejected=c.gravity_rejected,
                gravity_reopened=c.gravity_reopened,
                gravity_implausible=c.gravity_implausible,
                fused_priors=c.fused_priors,
                fusion_refused=c.fusion_refused,
            )
            # the rig's estimated constant disparity error (robotd.frontend.disparity_bias)
            doc["stereo"] = self.pipeline.frontend.disparity_bias.stats()
            # the images' motion blur the reported covariance allowed for (robotd.pipeline.stages.fuse)
            doc["motion_blur"] = {**self.pipeline.fuse.blur_stats, **self.pipeline.measure.blur_health()}
            # map fixes the prediction could not explain, refused (robotd.pipeline.stages.motion)
            doc["implausible_fixes"] = c.implausible_fixes
        # the run's reset_counter bumps and why (the autopilot resets its position at each)
        doc["reset_bumps"] = [[c, why] for c, why in list(self.reset_policy.history)]
        if self.handover is not None:
            # a resume carried by the autopilot's motion (robotd.daemon.handover): what happened
            doc["handover"] = self.handover.outcome or "waiting for the autopilot's pose"
        doc.update(self.output_runner.health())  # every output's counters and stats
        return self.health.assess(doc, needs_vehicle=self._needs_vehicle)

    @property
    def _needs_vehicle(self) -> bool:
        """A vehicle link is configured: readiness waits for its odometry, health judges it."""
        return not self.cfg.vehicle.url.startswith("none:")

    # ------------------------------------------------------------------ main loop
    def run(self) -> int:
        self.signals.install()
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
            self.signals.restore()

    def _start_threads(self) -> None:
        assert self.camera is not None and self.vehicle is not None
        assert self.feed is not None and self.budget is not None
        vehicle, stop, stats = self.vehicle, self.stop_event, self.stats
        runner = self.output_runner
        runner.start()
        tees = [runner.tee_odometry] if runner.tees_odometry else []
        queues = (self.frame_q, self.odo_q, self.pub_q)
        slam = SlamThread(
            self.feed,
            self.budget,
            self.health,
            queues,
            runner,
            self.host_clock,
            self._deliveries,
            self._frame_period_s,
            self.handover,
            self.autopilot_pose_at,
        )
        self._slam = slam
        publisher = Publisher(
            self.cfg,
            self.pub_q,
            self.health,
            self.budget,
            runner,
            self.reset_policy,
            self.counter_file,
            self._pending_event,
        )
        for name, fn in (
            ("camera", self._pump_frames),
            ("vehicle", lambda: pump_odometry(vehicle, self.odo_q, stop, stats, tees)),
            ("slam", lambda: slam.run(stop)),
            ("publisher", publisher.run),
        ):
            t = threading.Thread(target=self._guarded, args=(name, fn), name=f"robotd-{name}", daemon=True)
            t.start()
            self.threads.append(t)

    def _pump_frames(self) -> None:
        assert self.camera is not None
        stall_s = max(STALL_MIN_S, STALL_PERIODS * self._frame_period_s)
        pump_frames(
            self.camera,
            self.frame_q,
            self.stop_event,
            self.stats,
            self._fail,
            self.duration_s == 0.0,
            stall_s,
            lambda gap_s: self.health.on_stall(gap_s, camera=True),
            ([self.output_runner.tee_frame] if self.output_runner.tees_frames else [])
            + ([] if self.host_clock else [self._deliveries.tee]),
        )

    def _guarded(self, name: str, loop: Callable[[], None]) -> None:
        """Run a thread's loop; an exception nobody expected stops the daemon with exit status 1
        (systemd's Restart=on-failure then restarts it), never a quiet "source ended"."""
        try:
            loop()
        except Exception as exc:
            logger.exception("%s thread crashed", name)
            self._fail(name, f"{name} thread crashed: {type(exc).__name__}: {exc}")

    def _fail(self, thread: str, why: str) -> None:
        """Stop the daemon with a non-zero exit status; a crashed SLAM thread's state is not saved."""
        logger.error("stopping: %s", why)
        self.failed.append(thread)
        self.stop_reason = why
        self.exit_code = 1
        self.stop_event.set()

    def _supervise(self) -> None:
        self._supervisor = Supervisor(
            self.cfg,
            self.duration_s,
            self.stop_event,
            self.notifier,
            self.health,
            self.output_runner,
            self.recorder,
            self.health_doc,
            self.threads[2].is_alive,  # the SLAM thread: it ends when the source does
            self._fail,
            self._needs_vehicle,
        )
        why = self._supervisor.run()
        if self.failed:
            pass  # the failure's reason (``_fail``) is why it stopped, whatever else came true then
        elif why:
            self.stop_reason = why
        elif self.stop_event.is_set() and not self.stop_reason:
            self.stop_reason = "stop requested"

    def final_state(self) -> dict[str, Any] | None:
        """The pipeline's state at shutdown, once the SLAM thread has stopped (nothing else touches
        the estimator); None when no step ran or the thread is still running."""
        if self.pipeline is None or self.stats.steps == 0 or not isinstance(self.pipeline.estimator, Persistent):
            return None
        if "slam" in self.failed:
            logger.error("map not saved at shutdown: the SLAM thread crashed mid-step (the last saved map is kept)")
            return None
        if any(t.name == "robotd-slam" and t.is_alive() for t in self.threads):
            logger.error("map not saved at shutdown: the SLAM thread is still running")
            return None
        state = self.pipeline.state_dict()
        last_t_ns = self._slam.last_t_ns if self._slam is not None else None
        handover = handover_record(self.autopilot_pose_at, last_t_ns)
        return state if handover is None else {**state, HANDOVER_KEY: handover}

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
        self._limits.restore()
        state = self.final_state()
        self.output_runner.finish(state, time.monotonic_ns())  # each output's, whatever the others' do
        lat = np.asarray(self.stats.latencies_ms) if self.stats.latencies_ms else np.zeros(1)
        logger.info(
            "stopped after %d steps: latency p50 %.1f ms p99 %.1f ms%s, %d frames dropped, shutdown %.2f s",
            self.stats.steps,
            np.percentile(lat, 50),
            np.percentile(lat, 99),
            "" if self.host_clock else " from delivery",
            self.health.frames_dropped(self.frame_q),  # the status line's `dropped`
            time.monotonic() - t0,
        )
        self.notifier.close()


def _load_kernels(cfg: Config) -> None:
    """Compile or load every numba kernel a step uses; the compile is announced only when numba
    finds no cached kernel (robotd.core.jit.CompileWatch), never on a warm start."""
    logger.info("loading the filter and matcher kernels")
    with CompileWatch(lambda: logger.info(COMPILING_UNCACHED if jit.UNCACHED else COMPILING)) as watch:
        seconds = Pipeline.warmup((cfg.slam.measurement,), (cfg.slam.dim,))
    how = "loaded from the numba cache"
    if watch.compiled:
        how = f"{watch.compiled} compiled" + ("" if jit.UNCACHED else ", now cached")
    logger.info("filter and matcher kernels ready in %.1f s (%s)", seconds, how)


KERNEL_MODULES = (
    "robotd.slam._kernels",
    "robotd.core._outlier_kernels",
    "robotd.frontend._detect_kernels",
    "robotd.frontend._pnp_kernels",
    "robotd.frontend._stereo_kernels",
)


def kernels_cached(modules: tuple[str, ...] = KERNEL_MODULES) -> bool:
    """Whether numba's disk cache holds kernels of every module of ``modules``: a start will then
    most likely load them rather than compile them. A hint, not a promise: numba indexes only the
    kernels called from Python (helpers called from other kernels are compiled into them and have
    no entry), and an index written for an older source still compiles; this only reads that index
    files are there, one at least per module. False when it cannot tell (a kernel without a disk
    cache, numba's cache internals not as expected). The daemon loads the kernels while it opens
    the devices only when this is True: a compile takes tens of seconds, and the devices would
    stream meanwhile."""
    try:
        for name in modules:
            mod = importlib.import_module(name)
            found = False
            for value in vars(mod).values():
                cache = getattr(value, "_cache", None)
                if cache is None or not hasattr(value, "py_func"):
                    continue
                index = getattr(getattr(cache, "_cache_file", None), "_index_path", None)
                if isinstance(index, str) and Path(index).is_file():
                    found = True
                    break
            if not found:
                return False
    except Exception:  # numba's internals differ: say "do not know"
        return False
    return not jit.UNCACHED


class _KernelLoader:
    """:func:`_load_kernels` in a thread while the ``with`` block runs; leaving the block waits for
    it and raises what it raised (the block's own exception wins)."""

    def __init__(self, cfg: Config) -> None:
        self._cfg = cfg
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="robotd-kernels", daemon=True)

    def _run(self) -> None:
        try:
            _load_kernels(self._cfg)
        except BaseException as exc:  # handed to the main thread on exit
            self._error = exc

    def __enter__(self) -> _KernelLoader:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._thread.join()
        if self._error is not None and exc[0] is None:
            raise self._error


def _plain_stats(dev: Any) -> dict[str, Any]:
    try:
        stats = dev.stats() if dev is not None else {}
    except Exception as exc:  # a driver's counters must not cost the summary
        return {"error": str(exc)}
    return {k: v for k, v in stats.items() if v is None or isinstance(v, int | float | str | bool)}


def run_daemon(cfg: Config, duration_s: float = 0.0) -> int:
    return Daemon(cfg, duration_s).run()
