"""``robotd replay`` and ``robotd record``: the same Pipeline.step, driven synchronously.

Replay reads every frame of a recording or dataset in order (no drops: determinism matters more
than real time here, unless ``--realtime`` paces the source), integrates the recorded odometry to
each frame's capture time, steps the pipeline and writes the trajectory in TUM format. The same
seed and input give bit-identical poses. Each frame goes through the daemon's own per-frame loop
(robotd.pipeline.feed: gate, integrate, step, a failed step skipped and counted in ``step_errors``).

KITTI and EuRoC run visual only by default (``replay.odometry = "none"``): the motion prior
comes from the images (the outlier stage's frame-to-frame transform) and ground truth never
reaches the filter. With ``replay.odometry = "dataset"`` a KITTI raw folder that keeps its drive's
OXTS GPS/INS records (``raw/*/oxts``) feeds them as the vehicle's odometry, as a rover's wheel
odometry would arrive (``drivers.kitti_oxts``); a folder without them stays visual only. The
summary's ``odometry`` says which was used ("none", "oxts", "sim", "gt-synthetic", or a recording's
source). ``gt_odometry=True`` synthesises odometry from ground truth with documented noise, for
experiments only; such runs are labelled in the summary and never reported as results.
The simulated rover runs with its own noisy odometry; ``odometry=0`` in its URL makes that rover
give none, so the same world runs on vision alone (docs/sim.md).

Which odometry a source brings, how it is paced, how many frames it has and what it says at the
end are its camera driver's declarations (:mod:`drivers.cameras`), never its scheme.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import os
import sys
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

import drivers
from drivers.cameras import CameraDriver, DatasetOdometry, camera_driver, camera_kind, cameras, schemes_text
from robotd.config import Config
from robotd.config.params import odometry_limits_from_config
from robotd.core.errors import RobotdError
from robotd.core.msgs import Odometry, StepResult
from robotd.daemon.device_urls import calibration_refusals, camera_options
from robotd.pipeline.feed import Feed
from robotd.pipeline.odometry import OdometryGate, OdometryIntegrator
from robotd.pipeline.step import Pipeline
from robotd.research.evaluate import TRAJECTORY_FORMATS, cov_path_for, write_pose_cov, write_trajectory
from robotd.tools.progress import progress_bar

logger = logging.getLogger("robotd.replay")  # its name before the layer packages: users filter by it


def _progress_bar(total: int | None, enabled: bool) -> Any:
    """The replay's progress bar (tqdm, on stderr): n/total, fps and ETA. Off with ``--quiet`` and
    when stderr is not a terminal (a log file or CI gets the one summary line instead)."""
    return progress_bar(total, "frame", "replay", enabled=enabled)


def _frame_total(camera: Any, max_frames: int, driver: CameraDriver | None = None) -> int | None:
    """Frames the replay will process, when the source can tell without reading them (the bar's
    total, from the camera's driver; None: the bar shows a count and a rate only)."""
    driver = driver or camera_driver(camera.url)
    total = driver.frame_total(camera)
    if max_frames:
        total = max_frames if total is None else min(total, max_frames)
    return total


def _opening_line(source: str) -> str:
    """What replay is doing during its silent start: opening (indexing) a recording takes seconds."""
    path = source.partition("://")[2] if "://" in source else source
    path = path.split("?", 1)[0]
    if camera_kind(source).reads == "file" and os.path.isfile(path):
        return f"opening {path} ({os.path.getsize(path) / 1e6:.0f} MB)..."
    return f"opening {source}..."


def summary_line(summary: dict[str, Any]) -> str:
    """One human line for the end of a replay: frames, wall time, fps, lost frames and, when the
    source carried ground truth, the truth figures (drift in % of path, or in m on a short path)."""
    n, wall = summary["frames"], summary["wall_s"]
    line = f"replayed {n} frames in {wall:.1f} s ({n / max(wall, 1e-9):.0f} fps): {summary['lost_frames']} lost"
    truth: list[str] = []
    if summary.get("truth_drift_pct") is not None:
        truth.append(f"drift {summary['truth_drift_pct']:.2f} %")
    elif summary.get("truth_drift_m") is not None:
        truth.append(f"drift {summary['truth_drift_m']:.3f} m (path {summary['truth_path_length_m']:.2f} m)")
    if summary.get("truth_ate_rmse_m") is not None:
        truth.append(f"ATE {summary['truth_ate_rmse_m']:.3f} m")
    if truth:
        line += "; " + ", ".join(truth)
    if summary.get("gt_odometry"):
        line += " [EXPERIMENT: odometry from ground truth]"
    elif summary.get("odometry", "none") != "none":
        line += f" [odometry: {summary['odometry']}]"
    rec = summary.get("recording") or {}
    if rec.get("stopped"):
        clean = "closed cleanly" if rec.get("finished") else "not closed cleanly (interrupted)"
        line += f"; recording {clean}, read up to the damage: {rec['stopped']}"
    return line


def _source_url(source: str, realtime: bool, driver: CameraDriver) -> str:
    """The URL replay opens: ``source``, paced at its own rate with ``realtime`` (a URL's driver
    says how)."""
    return driver.paced(source) if realtime and "://" in source else source


def check_output_file(path: str | None, what: str) -> None:
    """Refuse, before any work, an output file (``what``: "replay: the trajectory file", say)
    whose folder is missing or not writable, or that is a folder: found at the end, it would cost
    the whole run."""
    if not path:
        return
    if os.path.isdir(path):
        raise RobotdError(f"{what} {path} is a folder")
    folder = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(folder):
        raise RobotdError(f"{what} {path}: its folder {folder} does not exist")
    if not os.access(folder, os.W_OK):
        raise RobotdError(f"{what} {path}: its folder {folder} is not writable")


def replay(
    cfg: Config,
    source: str,
    realtime: bool = False,
    out_traj: str | None = None,
    max_frames: int = 0,
    progress: bool = True,
    gt_odometry: bool = False,
    on_step: Callable[[StepResult], None] | None = None,
    out_format: str = "tum",
    truth_out: str | None = None,
    truth_out_if_any: str | None = None,
) -> dict[str, Any]:
    """Run ``source`` through the pipeline; returns a summary (and writes the trajectory).

    ``on_step`` (for tools such as bench/mavlink_covariance.py) receives each step's result, as
    kept for the summary (without its observations), in order. ``out_format``: "tum" (robot frame,
    stamped) or "kitti" (the left camera's poses, one row per frame:
    :func:`robotd.research.evaluate.write_trajectory`), of ``out_traj`` and of ``truth_out``, which
    receives the ground truth the source carries for the same frames. ``truth_out_if_any``: the
    same, written only when the source carried a truth (``robotd replay-many``), where
    ``truth_out`` refuses a source without one.
    """
    if out_format not in TRAJECTORY_FORMATS:
        raise RobotdError(f"replay: trajectory format {out_format!r}: expected one of {list(TRAJECTORY_FORMATS)}")
    for what, path in (("trajectory", out_traj), ("truth", truth_out), ("truth", truth_out_if_any)):
        check_output_file(path, f"replay: the {what} file")
    driver = camera_driver(source)  # what the source declares (drivers.cameras)
    url = _source_url(source, realtime, driver)
    rng = np.random.default_rng(cfg.robot.seed)
    results: list[StepResult] = []
    truths: list[tuple[int, np.ndarray]] = []
    seqs: list[int] = []  # the source's frame numbers of the poses
    gate = OdometryGate(odometry_limits_from_config(cfg))
    t_wall = time.monotonic()
    with contextlib.ExitStack() as stack:
        if progress:
            # opening a recording is seconds of silence otherwise (the MCAP index is read first)
            print(_opening_line(source), file=sys.stderr, flush=True)
        replay_opts = driver.replay_options(url)  # e.g. a fixed clock start, so two replays agree
        cam_opts = camera_options(cfg, url)  # camera.calibration, for a source that rectifies (else refused)
        with calibration_refusals(cfg):
            camera = stack.enter_context(drivers.open_camera(url, **replay_opts, **cam_opts))
        vehicle = None
        if gt_odometry:
            logger.warning("EXPERIMENT: odometry synthesised from ground truth (never for reported figures)")
            # the truth's robot frame is the rectified rig's: the same calibration as the camera's
            vehicle = stack.enter_context(drivers.open_vehicle(_gt_odometry_url(source), **replay_opts, **cam_opts))
        elif (vehicle_url := driver.replay_vehicle(source, url, _dataset_odometry(cfg))) is not None:
            # the source's own odometry: a recording's, a simulated rover's, a dataset's when asked for
            vehicle = stack.enter_context(drivers.open_vehicle(vehicle_url, **replay_opts))
        recorded = _RecordedOdometry(vehicle.odometry(timeout_s=0.0) if vehicle is not None else None)
        rig = camera.rectified_model()
        pipeline = Pipeline(cfg, rig, rng)
        feed = Feed(pipeline, OdometryIntegrator(max_gap_s=cfg.vehicle.max_gap_s), gate, log=logger)
        prog = stack.enter_context(_progress_bar(_frame_total(camera, max_frames, driver), progress))
        if not prog.disable:
            # log lines (a skipped frame) go above the bar instead of through it
            from tqdm.contrib.logging import logging_redirect_tqdm

            stack.enter_context(logging_redirect_tqdm())
        for frame in camera.frames(timeout_s=1.0):
            # the odometry up to this frame's time, as the daemon's SLAM thread takes it (robotd.pipeline.feed)
            fed = feed.process(frame, recorded.until(frame.t_ns))
            if fed is None:
                continue
            res = fed.result
            results.append(dataclasses.replace(res, observations=None))  # the run's poses, not its features
            seqs.append(frame.seq)
            if on_step is not None:
                on_step(results[-1])
            if frame.truth_T_world_robot is not None:
                truths.append((frame.t_ns, frame.truth_T_world_robot))
            prog.set_postfix_str(f"lm {res.counts.get('landmarks', 0)}", refresh=False)
            prog.update(1)
            if max_frames and len(results) >= max_frames:
                break
        # the last step's deferred work (each earlier one ran, and was timed, in the next step)
        pipeline.after_step()
    recording = driver.status(camera)
    if not results:
        why = f": {recording['stopped']}" if recording and recording.get("stopped") else ""
        raise RobotdError(f"{source}: no frame was processed{why}")
    stamps = np.array([r.t_ns for r in results], dtype=np.int64)
    T = np.stack([r.pose.T_world_robot for r in results])
    if out_traj:
        try:
            write_trajectory(out_traj, stamps / 1e9, T, out_format, rig.baseline_m)
            write_pose_cov(cov_path_for(out_traj), stamps / 1e9, np.stack([r.pose.cov for r in results]))
        except OSError as exc:  # a full disk, a folder removed meanwhile: said in one line, exit non-zero
            raise RobotdError(f"replay: writing the trajectory {out_traj}: {exc.strerror or exc}") from exc
        logger.info(
            "trajectory written to %s (%d poses, %s; covariance in %s)",
            out_traj,
            len(results),
            out_format.upper(),
            cov_path_for(out_traj),
        )
    by_row = camera_kind(source).truth_by_row
    if out_traj and out_format == "kitti" and by_row and seqs != list(range(len(seqs))):
        logger.warning(
            "%s has one row per replayed frame, and frames of the source are missing (start/stride/drop or a skipped "
            "frame): it pairs by row with the truth --truth-out writes, not with %s",
            out_traj,
            by_row,
        )
    if truth_out:
        _write_truth(truth_out, source, truths, len(results), out_format, rig.baseline_m)
    if truth_out_if_any and truths and (out_format != "kitti" or len(truths) == len(results)):
        _write_truth(truth_out_if_any, source, truths, len(results), out_format, rig.baseline_m)
    total_ms = np.array([r.timings_ms.get("total", np.nan) for r in results])
    summary: dict[str, Any] = {
        "source": source,
        "frames": len(results),
        "seed": cfg.robot.seed,
        "filter": cfg.slam.filter,
        "dim": cfg.slam.dim,
        "detector": cfg.frontend.detector,
        "gt_odometry": gt_odometry,
        "odometry": _odometry_name(vehicle, source),
        "step_ms_p50": float(np.nanpercentile(total_ms, 50)),
        "step_ms_p95": float(np.nanpercentile(total_ms, 95)),
        "wall_s": time.monotonic() - t_wall,
        "landmarks": int(results[-1].counts.get("landmarks", 0)),
        "final_xyz_m": [float(v) for v in results[-1].pose.xyz_W_m],
        "lost_frames": int(sum(not r.tracking for r in results)),
        # runs of lost frames (a lost frame after a tracked one, or the first)
        "tracking_lost_episodes": int(
            sum(not r.tracking and (i == 0 or results[i - 1].tracking) for i, r in enumerate(results))
        ),
        "step_errors": feed.counters.step_errors,
        "visual_priors": pipeline.counters.visual_priors,
        "odometry_priors": pipeline.counters.odometry_priors,
        "odometry_rejected": sum(gate.rejected.values()),
        "gravity_fused": pipeline.counters.gravity_fused,
        "gravity_rejected": pipeline.counters.gravity_rejected,
        "gravity_reopened": pipeline.counters.gravity_reopened,
        "gravity_implausible": pipeline.counters.gravity_implausible,
        "fused_priors": pipeline.counters.fused_priors,
        "fusion_refused": pipeline.counters.fusion_refused,
        "attitude_resets": pipeline.counters.attitude_resets,
        "implausible_fixes": pipeline.counters.implausible_fixes,
        **pipeline.frontend.disparity_bias.stats(),
        "motion_blur": {**pipeline.fuse.blur_stats, **pipeline.measure.blur_health()},
    }
    stages = sorted({k for r in results for k in r.timings_ms})
    summary["stage_ms_p50"] = {k: float(np.nanmedian([r.timings_ms.get(k, np.nan) for r in results])) for k in stages}
    if recording is not None:
        # a damaged or interrupted recording replays up to the damage; the summary says so
        summary["recording"] = recording
    if truths:
        summary.update(_truth_metrics(stamps, T, truths, np.stack([r.pose.cov for r in results])))
    if out_traj:
        summary["trajectory"] = str(out_traj)
    return summary


class _RecordedOdometry:
    """A source's odometry in recorded order, handed out up to each frame's time (no clocks involved)."""

    def __init__(self, samples: Iterator[Odometry] | None) -> None:
        self._it = samples
        self._pending: Odometry | None = None

    def until(self, t_ns: int) -> list[Odometry]:
        """The samples stamped at or before ``t_ns`` not handed out yet."""
        out: list[Odometry] = []
        while self._it is not None:
            if self._pending is None:
                self._pending = next(self._it, None)
            if self._pending is None or self._pending.t_ns > t_ns:
                break
            out.append(self._pending)
            self._pending = None
        return out


def _write_truth(
    path: str, source: str, truths: list[tuple[int, np.ndarray]], n_poses: int, fmt: str, baseline_m: float
) -> None:
    """``--truth-out``: the truth the frames carried, relative to the first (as the estimate is), in
    the trajectory's format and frame, so a tool that knows nothing of robotd's frames (evo) compares
    like with like. A KITTI file pairs by row, so it needs a truth for every replayed frame."""
    if not truths:
        which = schemes_text([r.scheme for r in cameras() if r.kind.truth], "and")
        raise RobotdError(f"--truth-out {path}: {source} carries no ground truth ({which} do)")
    if fmt == "kitti" and len(truths) != n_poses:
        raise RobotdError(
            f"--truth-out {path}: {len(truths)} of the {n_poses} replayed frames carry a truth, and a KITTI file "
            "pairs poses by row: write TUM (stamped) instead"
        )
    t_gt = np.array([t for t, _ in truths], dtype=np.int64)
    G = np.stack([g for _, g in truths])
    write_trajectory(path, t_gt / 1e9, np.linalg.inv(G[0]) @ G, fmt, baseline_m)
    logger.info("ground truth written to %s (%d poses, %s)", path, len(truths), fmt.upper())


def _truth_metrics(
    stamps: np.ndarray, T: np.ndarray, truths: list[tuple[int, np.ndarray]], cov: np.ndarray | None = None
) -> dict[str, Any]:
    """ATE/drift against the ground truth the source carried (evaluation only); the keys of
    :func:`robotd.research.evaluate.evaluate_trajectories` prefixed ``truth_``. Undefined figures
    (drift % and similarity scale on a path shorter than ``MIN_PATH_FOR_RELATIVE_M``) are None,
    JSON null, rather than NaN, which is not JSON.

    Also KITTI's segment drift over 100 ... 800 m (truth_segment_drift_pct, truth_segment_rot_deg_per_m,
    truth_segment_count: ``robotd eval --segments``) and, with ``cov``, the position NEES after
    aligning by positions over the first ``ALIGN_POSITIONS_M`` metres (truth_aligned_nees_pos_mean,
    truth_aligned_nees_pos_in_band_frac, truth_aligned_nees_pos_frames, truth_alignment:
    ``robotd eval --align-positions 10``)."""
    from robotd.research.evaluate import (
        ALIGN_POSITIONS_M,
        Trajectory,
        associate_trajectories,
        evaluate_trajectories,
        positions_aligned_nees,
        segment_drift,
    )

    t_gt = np.array([t for t, _ in truths], dtype=np.int64)
    G = np.stack([g for _, g in truths])
    G = np.linalg.inv(G[0]) @ G  # truth relative to the first truth pose, as the estimate is
    est, gt = Trajectory(stamps / 1e9, T), Trajectory(t_gt / 1e9, G)
    try:
        m = evaluate_trajectories(est, gt, cov=cov)
    except RobotdError as exc:
        logger.warning("no truth metrics: %s", exc)
        return {}
    out: dict[str, Any] = {f"truth_{k}": (float(v) if math.isfinite(v) else None) for k, v in m.items()}
    ie, ig, _ = associate_trajectories(est, gt)
    seg = segment_drift(T[ie], G[ig])
    extra: dict[str, Any] = {k: seg[k] for k in ("segment_drift_pct", "segment_rot_deg_per_m", "segment_count")}
    if cov is not None:
        _, aligned = positions_aligned_nees(T[ie], G[ig], cov[ie], ALIGN_POSITIONS_M)
        extra.update(
            {k: aligned[k] for k in ("aligned_nees_pos_mean", "aligned_nees_pos_in_band_frac", "alignment")},
            aligned_nees_pos_frames=aligned["aligned_nees_pos_frames"],
        )
    for k, v in extra.items():
        out[f"truth_{k}"] = None if isinstance(v, float) and not math.isfinite(v) else v
    out.update(_tilt_errors(stamps, T, t_gt, G))
    return out


def _tilt_errors(stamps: np.ndarray, T: np.ndarray, t_gt: np.ndarray, G: np.ndarray) -> dict[str, float]:
    """Roll and pitch error without yaw: the angle between the world's z axis seen from the
    estimated and from the true robot, both worlds the robot's first pose (no alignment, so a
    tilted world cannot hide). Frames with a truth at their own stamp only."""
    common, i_est, i_gt = np.intersect1d(np.asarray(stamps, np.int64), t_gt, return_indices=True)
    if common.size == 0:
        return {}
    ze = T[i_est, 2, :3]  # R^T e_z is the third row of R
    zg = G[i_gt, 2, :3]
    ang = np.degrees(np.arccos(np.clip(np.sum(ze * zg, axis=1), -1.0, 1.0)))
    return {"truth_tilt_rmse_deg": float(np.sqrt(np.mean(ang**2))), "truth_tilt_max_deg": float(ang.max())}


def _odometry_name(vehicle: Any, source: str) -> str:
    """What the replay's odometry was: "none" (vision only), else the vehicle's source (a dataset
    vehicle says it: "oxts", "gt-synthetic", a recording's "sim" ...; else the URL scheme)."""
    if vehicle is None:
        return "none"
    return str(getattr(vehicle, "odometry_source", None) or source.partition("://")[0])


def _dataset_odometry(cfg: Config) -> DatasetOdometry | None:
    """``replay.odometry = "dataset"``: the dataset's recorded odometry (KITTI's OXTS) with its
    configured noise; None: vision only (a source whose driver always brings odometry still does)."""
    if cfg.replay.odometry != "dataset":
        return None
    return DatasetOdometry(cfg.replay.oxts_sigma_vel_mps, cfg.replay.oxts_sigma_rate_radps)


def _gt_odometry_url(source: str) -> str:
    sep = "&" if "?" in source else "?"
    return f"{source}{sep}gt_odometry=1"
