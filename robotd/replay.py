"""``robotd replay`` and ``robotd record``: the same Pipeline.step, driven synchronously.

Replay reads every frame of a recording or dataset in order (no drops: determinism matters more
than real time here, unless ``--realtime`` paces the source), integrates the recorded odometry to
each frame's capture time, steps the pipeline and writes the trajectory in TUM format. The same
seed and input give bit-identical poses.

KITTI and EuRoC carry no wheel odometry, so they run visual only by default: the motion prior
comes from the images (the outlier stage's frame-to-frame transform) and ground truth never
reaches the filter. ``gt_odometry=True`` synthesises odometry from ground truth with documented
noise, for experiments only; such runs are labelled in the summary and never reported as results.
"""

from __future__ import annotations

import contextlib
import logging
import sys
import time
from typing import Any

import numpy as np

import drivers
from robotd.config import Config
from robotd.errors import RobotdError
from robotd.msgs import StepResult
from robotd.odometry import OdometryIntegrator
from robotd.pipeline import Pipeline
from robotd.research.evaluate import write_tum

logger = logging.getLogger(__name__)


class Progress:
    """A light progress line on stderr (only when it is a terminal, or when forced)."""

    def __init__(self, total: int | None, enabled: bool) -> None:
        self.total = total
        self.enabled = enabled and sys.stderr.isatty()
        self.n = 0
        self.t0 = time.monotonic()
        self._last = 0.0

    def update(self, extra: str = "") -> None:
        self.n += 1
        now = time.monotonic()
        if not self.enabled or now - self._last < 0.2:
            return
        self._last = now
        rate = self.n / max(now - self.t0, 1e-9)
        tot = f"/{self.total}" if self.total else ""
        sys.stderr.write(f"\r{self.n}{tot} frames, {rate:.1f} fps {extra}   ")
        sys.stderr.flush()

    def close(self) -> None:
        if self.enabled:
            sys.stderr.write("\n")


def _source_url(source: str, realtime: bool) -> str:
    if realtime and "://" in source and not source.startswith("sim://"):
        sep = "&" if "?" in source else "?"
        return f"{source}{sep}realtime=1"
    return source


def replay(
    cfg: Config,
    source: str,
    realtime: bool = False,
    out_traj: str | None = None,
    max_frames: int = 0,
    progress: bool = True,
    gt_odometry: bool = False,
) -> dict[str, Any]:
    """Run ``source`` through the pipeline; returns a summary (and writes the TUM trajectory)."""
    url = _source_url(source, realtime)
    rng = np.random.default_rng(cfg.robot.seed)
    results: list[StepResult] = []
    truths: list[tuple[int, np.ndarray]] = []
    integ = OdometryIntegrator(max_gap_s=cfg.vehicle.max_gap_s)
    t_wall = time.monotonic()
    with contextlib.ExitStack() as stack:
        camera = stack.enter_context(drivers.open_camera(url))
        vehicle = None
        if gt_odometry:
            logger.warning("EXPERIMENT: odometry synthesised from ground truth (never for reported figures)")
            vehicle = stack.enter_context(drivers.open_vehicle(_gt_odometry_url(source)))
        elif source.endswith(".mcap") or source.startswith("mcap://"):
            vehicle = stack.enter_context(drivers.open_vehicle(source if "://" in source else f"mcap://{source}"))
        elif source.startswith("sim://"):
            # the simulated rover's own noisy odometry (same world and clock as its camera)
            vehicle = stack.enter_context(drivers.open_vehicle(url))
        odo_iter = vehicle.odometry(timeout_s=0.0) if vehicle is not None else None
        pending = None
        rig = camera.rectified_model()
        pipeline = Pipeline(cfg, rig, rng)
        total = getattr(camera, "n_frames", None)
        prog = Progress(total, progress)
        last_t: int | None = None
        for frame in camera.frames(timeout_s=1.0):
            if odo_iter is not None:
                # feed odometry up to this frame's time (recorded order; no clocks involved)
                while True:
                    if pending is None:
                        pending = next(odo_iter, None)
                    if pending is None or pending.t_ns > frame.t_ns:
                        break
                    integ.add(pending)
                    pending = None
            inc = integ.integrate(last_t, frame.t_ns) if (last_t is not None and odo_iter is not None) else None
            try:
                res = pipeline.step(frame, inc)
            except RobotdError as exc:
                logger.error("frame %d skipped: %s", frame.seq, exc)
                continue
            last_t = frame.t_ns
            results.append(res)
            if frame.truth_T_world_robot is not None:
                truths.append((frame.t_ns, frame.truth_T_world_robot))
            prog.update(f"lm {res.counts.get('landmarks', 0)}")
            if max_frames and len(results) >= max_frames:
                break
        prog.close()
    if not results:
        raise RobotdError(f"{source}: no frame was processed")
    stamps = np.array([r.t_ns for r in results], dtype=np.int64)
    T = np.stack([r.pose.T_world_robot for r in results])
    if out_traj:
        write_tum(out_traj, stamps / 1e9, T)
        logger.info("trajectory written to %s (%d poses)", out_traj, len(results))
    total_ms = np.array([r.timings_ms.get("total", np.nan) for r in results])
    summary: dict[str, Any] = {
        "source": source,
        "frames": len(results),
        "seed": cfg.robot.seed,
        "filter": cfg.slam.filter,
        "dim": cfg.slam.dim,
        "detector": cfg.frontend.detector,
        "gt_odometry": gt_odometry,
        "step_ms_p50": float(np.nanpercentile(total_ms, 50)),
        "step_ms_p95": float(np.nanpercentile(total_ms, 95)),
        "wall_s": time.monotonic() - t_wall,
        "landmarks": int(results[-1].counts.get("landmarks", 0)),
        "final_xyz_m": [float(v) for v in results[-1].pose.xyz_W_m],
        "lost_frames": int(sum(not r.tracking for r in results)),
        "visual_priors": pipeline.counters.visual_priors,
        "odometry_priors": pipeline.counters.odometry_priors,
    }
    stages = sorted({k for r in results for k in r.timings_ms})
    summary["stage_ms_p50"] = {k: float(np.nanmedian([r.timings_ms.get(k, np.nan) for r in results])) for k in stages}
    if truths:
        summary.update(_truth_metrics(stamps, T, truths))
    if out_traj:
        summary["trajectory"] = str(out_traj)
    return summary


def _truth_metrics(stamps: np.ndarray, T: np.ndarray, truths: list[tuple[int, np.ndarray]]) -> dict[str, float]:
    """ATE/drift against the ground truth the source carried (evaluation only)."""
    from robotd.research.evaluate import Trajectory, evaluate_trajectories

    t_gt = np.array([t for t, _ in truths], dtype=np.int64)
    G = np.stack([g for _, g in truths])
    G = np.linalg.inv(G[0]) @ G  # truth relative to the first truth pose, as the estimate is
    try:
        m = evaluate_trajectories(Trajectory(stamps / 1e9, T), Trajectory(t_gt / 1e9, G))
    except RobotdError as exc:
        logger.warning("no truth metrics: %s", exc)
        return {}
    return {f"truth_{k}": float(v) for k, v in m.items()}


def _gt_odometry_url(source: str) -> str:
    sep = "&" if "?" in source else "?"
    return f"{source}{sep}gt_odometry=1"
