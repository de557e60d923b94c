"""The ``robotd`` command: run | replay | replay-many | record | eval | experiments | echo | fleet | router |
doctor | print-config | mcu-sim.

Logging is configured here and nowhere else. Every subcommand returns an exit code; a
:class:`robotd.core.errors.RobotdError` becomes one clear line on stderr and exit status 2.
"""

from __future__ import annotations

import os

# One BLAS thread: robotd runs its own threads on a 2-core board, and OpenBLAS's pool competing
# with them made an EKF step 15× slower. Must be set before numpy is first imported.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
# The FastSLAM kernel's OpenMP workers (numba's "omp" layer, GNU libgomp) spin-wait after each
# parallel region by default, holding a core the detection threads need when frames queue up:
# back to back, the two-image ORB detection took 11.3 ms instead of 7.0 ms. Passive workers sleep
# at once. Read when libgomp loads (at the first parallel launch), so set before that.
os.environ.setdefault("OMP_WAIT_POLICY", "passive")

import argparse
import json
import logging
import math
import sys
import typing
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from drivers.cameras import usages
from robotd import __version__
from robotd.config import CameraConfig, Config, load_config, to_toml
from robotd.core.errors import InputError, RobotdError
from robotd.tools import journal
from robotd.tools.journal import SYSLOG_PRIORITY, JournalFormatter

__all__ = ["SYSLOG_PRIORITY", "JournalFormatter", "build_parser", "configure_logging", "main"]

logger = logging.getLogger("robotd")


def configure_logging(level: str = "INFO") -> None:
    """stderr logging; under systemd (stderr the journal stream: robotd.tools.journal) with a syslog
    priority on every line and without timestamps, which journald adds."""
    handler = logging.StreamHandler()
    if journal.active():
        handler.setFormatter(JournalFormatter("%(levelname)s %(name)s: %(message)s"))
    else:
        handler.setFormatter(
            logging.Formatter("%(asctime)s.%(msecs)03d %(levelname)s %(name)s: %(message)s", "%H:%M:%S")
        )
    logging.basicConfig(level=getattr(logging, level.upper(), logging.INFO), handlers=[handler])


def _seconds(text: str) -> float:
    """A ``--duration``: seconds >= 0 (0: until stopped)."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected seconds, got {text!r}") from None
    if not (v >= 0 and v < float("inf")):
        raise argparse.ArgumentTypeError(f"expected seconds >= 0 (0: until stopped), got {text}")
    return v


def _load(args: argparse.Namespace) -> Config:
    return load_config(getattr(args, "config", None))


# --------------------------------------------------------------------------------------------
# subcommands


def _check_devices(cfg: Config, args: argparse.Namespace) -> None:
    """The device URLs' schemes and parameters, with the rest of the config and before anything
    slow (robotd.daemon.device_urls): one error line naming the key."""
    from robotd.daemon.device_urls import check_device_urls

    given = {k: f"--{k.split('.')[0]}" for k in ("camera.url", "vehicle.url") if getattr(args, k.split(".")[0], None)}
    check_device_urls(cfg, where=getattr(args, "config", None), given=given)


def cmd_print_config(args: argparse.Namespace) -> int:
    cfg = _load(args)
    _check_devices(cfg, args)
    sys.stdout.write(to_toml(cfg, with_docs=args.docs))
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    from robotd.daemon import run_daemon

    cfg = _load(args)
    overrides: dict[str, Any] = {}
    if args.camera:
        overrides.setdefault("camera", {})["url"] = args.camera
    if args.vehicle:
        overrides.setdefault("vehicle", {})["url"] = args.vehicle
    if overrides:
        cfg = load_config(getattr(args, "config", None), overrides)
    _check_devices(cfg, args)
    configure_logging(args.log_level or cfg.log.level)
    return run_daemon(cfg, duration_s=args.duration)


def cmd_replay(args: argparse.Namespace) -> int:
    from robotd.tools.replay import replay, summary_line

    cfg = _load(args)
    configure_logging(args.log_level or cfg.log.level)
    if (args.format != "tum") and not args.out:
        raise InputError(f"replay --format {args.format}: give the trajectory file with --out")
    summary = replay(
        cfg,
        args.source,
        realtime=args.realtime,
        out_traj=args.out,
        max_frames=args.max_frames,
        progress=not args.quiet,
        gt_odometry=args.gt_odometry,
        out_format=args.format,
        truth_out=args.truth_out,
    )
    # always, terminal or not, --quiet or not: the one line a person reads at the end (stdout
    # keeps only the JSON, for scripts)
    with journal.priority(journal.INFO):
        print(summary_line(summary), file=sys.stderr, flush=True)
    if args.json:
        print(json.dumps(summary, sort_keys=True))
    return 0


def cmd_replay_many(args: argparse.Namespace) -> int:
    from robotd.tools.batch.configs import build_configurations
    from robotd.tools.batch.run import Options, print_outcome, replay_many
    from robotd.tools.batch.sources import check_sources, expand_sources

    configure_logging(args.log_level or "WARNING")
    for name, value in (("--workers", args.workers), ("--max-retries", args.max_retries)):
        if value < 0:
            raise InputError(f"{name}: expected an integer >= 0, got {value}")
    for name, fv in (("--timeout", args.timeout), ("--memory-mb", args.memory_mb)):
        if not (fv >= 0 and math.isfinite(fv)):
            raise InputError(f"{name}: expected a number >= 0 (0: no limit), got {fv}")
    sources = expand_sources(args.sources, args.sources_file)
    check_sources(sources)
    configurations = build_configurations(args.config, args.set, args.variant)
    opts = Options(
        out_dir=Path(args.out),
        workers=args.workers,
        ray=args.ray,
        timeout_s=args.timeout,
        memory_mb=args.memory_mb,
        max_retries=args.max_retries,
        rerun=args.rerun,
        progress=not args.quiet,
    )
    outcome = replay_many(sources, configurations, opts)
    print_outcome(outcome, args.json)
    return outcome.exit_code


def cmd_replay_many_compare(args: argparse.Namespace) -> int:
    from robotd.tools.batch import compare

    configure_logging(args.log_level or "WARNING")
    tol = compare.Tolerance(args.tolerance, args.ate_m, args.drift_pct, args.drift_m, args.lost)
    a, b = compare.load(args.a), compare.load(args.b)
    report = compare.compare(a, b, tol)
    plots = Path(args.plots) if args.plots else b.folder / "compare"
    if args.worst > 0 and report["worse"]:
        compare.plot_pairs(report, a, b, plots, args.worst)
    if args.json:
        print(json.dumps(report, sort_keys=True, default=str))
    else:
        sys.stdout.write(compare.markdown(report))
    return 1 if report["worse"] else 0


def cmd_record(args: argparse.Namespace) -> int:
    from robotd.daemon import Daemon
    from robotd.outputs.recorder import summary_line

    cfg = _load(args)
    if args.state_dir:
        cfg = load_config(getattr(args, "config", None), {"persistence": {"state_dir": args.state_dir}})
    if not args.buffer_mb > 0:
        raise InputError(f"--buffer-mb: expected MB > 0, got {args.buffer_mb}")
    _check_devices(cfg, args)
    configure_logging(args.log_level or cfg.log.level)
    daemon = Daemon(
        cfg, duration_s=args.duration, record_path=args.out, keep_state=bool(args.state_dir), buffer_mb=args.buffer_mb
    )
    code = daemon.run()
    summary = daemon.record_summary()
    if daemon.recorder is not None:  # a start-up that failed has said so in its one line
        with journal.priority(journal.INFO):
            print(summary_line(summary), file=sys.stderr, flush=True)
    if args.json:
        print(json.dumps(summary, sort_keys=True))
    return code


def cmd_eval(args: argparse.Namespace) -> int:
    from robotd.research.evaluate import (
        KITTI_SEGMENT_LENGTHS_M,
        associate_trajectories,
        evaluate_trajectories,
        plot_nees,
        plot_trajectory,
        position_nees,
        positions_aligned_nees,
        read_trajectory,
        segment_drift,
    )
    from robotd.tools.replay import check_output_file

    configure_logging(args.log_level or "WARNING")
    for option in ("plot", "nees_plot"):
        check_output_file(getattr(args, option), f"eval --{option.replace('_', '-')}")
    if args.no_plot:
        logger.warning("eval: --no-plot is deprecated and does nothing: no plot is written unless --plot PNG is given")
    # a KITTI poses.txt is read as the replay carries it: robot frame at the baseline centre,
    # stamped from the times.txt beside it (by index when it has none and the counts match)
    # a KITTI file without a calib.txt beside it (robotd replay --format kitti --out /tmp/T.txt)
    # takes the other file's: both are the same rig's left camera
    est = read_trajectory(args.traj, calib_fallback=Path(args.gt).parent / "calib.txt")
    gt = read_trajectory(args.gt, calib_fallback=Path(args.traj).parent / "calib.txt")
    cov = _pose_covariance(args, est)
    result: dict[str, Any] = dict(evaluate_trajectories(est, gt, planar=args.planar, cov=cov))
    result["frames"] = int(result["frames"])
    ie, ig, result["association"] = associate_trajectories(est, gt)
    if args.segments or args.segment_lengths:
        lengths = args.segment_lengths or KITTI_SEGMENT_LENGTHS_M
        result.update(segment_drift(est.T[ie], gt.T[ig], lengths, planar=args.planar))
        if result["segment_note"] and not args.segment_lengths:
            result["segment_note"] += "; --segment-lengths sets shorter ones (e.g. 10,20,40)"
    if cov is not None:
        result["nees_pos_frames"] = int(result["nees_pos_frames"])
        eps = None
        if args.align_positions is not None:
            eps, aligned = positions_aligned_nees(est.T[ie], gt.T[ig], cov[ie], args.align_positions)
            result.update(aligned)
        if args.nees_plot:
            if eps is None:
                eps = position_nees(est.T[ie], gt.T[ig], cov[ie])
            plot_nees(est.t_s[ie] - est.t_s[ie][0], eps, args.nees_plot, title=Path(args.traj).name)
            result["nees_plot"] = args.nees_plot
    elif args.nees_plot or args.align_positions is not None:
        what = "--nees-plot" if args.nees_plot else "--align-positions"
        raise InputError(f"eval {what}: no pose covariance beside {args.traj} (robotd replay --out writes one)")
    if args.plot:
        plot_trajectory(est.T[ie], gt.T[ig], None, args.plot, title=f"{Path(args.traj).name} vs {Path(args.gt).name}")
        result["plot"] = args.plot
    if args.json:
        # full precision; NaN (an undefined figure, e.g. drift_pct on a stationary path) as null
        print(json.dumps(_json_number(result), sort_keys=True))
    else:
        width = max(22, *(len(k) for k in result))
        for k in sorted(result):
            if k == "segments" or (k.endswith("_note") and result[k] is None):
                continue
            print(f"{k:>{width}}: {_human_number(k, result[k])}")
        if "segments" in result:
            _print_segments(result)
    return 0


def _print_segments(result: dict[str, Any]) -> None:
    """The per-length rows of ``eval --segments`` as a small table."""
    print(f"segments (one starting every {result['segment_step_frames']} frames):")
    print(f"{'length m':>10} {'count':>6} {'drift %':>9} {'rot deg/m':>10}")
    for r in result["segments"]:
        print(
            f"{r['length_m']:>10g} {r['count']:>6d} {_human_number('drift_pct', r['drift_pct']):>9} "
            f"{_human_number('rot_deg_per_m', r['rot_deg_per_m']):>10}"
        )


def _segment_lengths(text: str) -> list[float]:
    """``--segment-lengths``: comma-separated metres > 0."""
    try:
        v = [float(p) for p in text.split(",") if p.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected metres separated by commas, e.g. 10,20,40, got {text!r}") from None
    if not v or not all(math.isfinite(x) and x > 0 for x in v):
        raise argparse.ArgumentTypeError(f"expected positive metres separated by commas, got {text!r}")
    return v


def _metres(text: str) -> float:
    """A positive length in metres."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected metres, got {text!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"expected a positive length in metres, got {text!r}")
    return v


def _pose_covariance(args: argparse.Namespace, est: Any) -> Any:
    """The estimate's pose covariance: ``--cov FILE``, else the T.cov.txt beside T.txt when there is
    one (robotd replay writes it), else None. Its stamps must be the trajectory's."""
    import numpy as np

    from robotd.research.evaluate import cov_path_for, read_pose_cov

    path = Path(args.cov) if args.cov else cov_path_for(args.traj)
    if not args.cov and not path.is_file():
        return None
    t, C = read_pose_cov(path)
    # a KITTI pose file has no stamps (est.timed False): its rows are the covariance's, in order
    by_index = not est.timed and len(t) == len(est.t_s)
    if not by_index and (len(t) != len(est.t_s) or not np.allclose(t, est.t_s, atol=1e-6)):
        raise InputError(
            f"eval: the pose covariance {path} has {len(t)} rows that do not match the {len(est.t_s)} poses of "
            f"{args.traj} (stamps differ)"
        )
    return C


def _json_number(v: Any) -> Any:
    """NaN and infinities as None (JSON null), in nested lists and dicts too."""
    if isinstance(v, dict):
        return {k: _json_number(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_json_number(x) for x in v]
    return None if isinstance(v, float) and not math.isfinite(v) else v


def _human_number(key: str, v: Any) -> str:
    """A figure as a person reads it: metres to 0.1 mm, degrees to 0.001°, percentages and ratios
    to 3 significant digits, counts as integers; an undefined figure as "n/a" (see --help)."""
    if isinstance(v, list | tuple):
        return ",".join(f"{x:g}" for x in v)
    if not isinstance(v, float):
        return str(v)
    if not math.isfinite(v):
        return "n/a"
    if key.endswith("_per_m"):
        return f"{v:.3g}"
    if key.endswith("_m"):
        return f"{v:.4f}"
    if key.endswith("_deg"):
        return f"{v:.3f}"
    return f"{v:.3g}"


def cmd_experiments(args: argparse.Namespace) -> int:
    from robotd.research.experiments import run_experiments

    configure_logging(args.log_level or "INFO")
    run_experiments(Path(args.out), quick=args.quick, seeds=args.seeds)
    print(Path(args.out) / "report.md")
    return 0


def cmd_echo(args: argparse.Namespace) -> int:
    from robotd.tools.echo import echo

    configure_logging(args.log_level or "WARNING")
    return echo(args.key, connect=args.connect, count=args.count, timeout_s=args.timeout)


def cmd_fleet(args: argparse.Namespace) -> int:
    from robotd.tools.fleet import fleet

    configure_logging(args.log_level or "WARNING")
    return fleet(args.connect, as_json=args.json, wait_s=args.wait, watch=args.watch, timeout_s=args.timeout)


def cmd_router(args: argparse.Namespace) -> int:
    from robotd.tools.fleet import run_router

    configure_logging(args.log_level or "WARNING")
    return run_router(args.listen, args.zenoh_config, args.duration)


def cmd_doctor(args: argparse.Namespace) -> int:
    from robotd.tools import doctor

    cfg = _load(args)
    configure_logging(args.log_level or "WARNING")
    results = doctor.run_checks(cfg, warm=args.warm)
    if args.json:
        print(json.dumps(doctor.to_json(results), sort_keys=True))
    else:
        for r in results:
            print(doctor.format_line(r))
        print(doctor.summary(results))
    return 1 if any(r.status == doctor.FAIL for r in results) else 0


def cmd_mcu_sim(args: argparse.Namespace) -> int:
    from drivers.mcu_sim import main as mcu_main

    return mcu_main(list(args.rest))


# --------------------------------------------------------------------------------------------


class _Parser(argparse.ArgumentParser):
    """argparse's usage and error lines are errors (journald priority 3); its subparsers too."""

    def error(self, message: str) -> typing.NoReturn:
        with journal.priority(journal.ERR):
            super().error(message)


def _truth_sources() -> str:
    """The cameras whose frames carry a truth (their registrations, drivers.cameras), for help texts."""
    from drivers.cameras import cameras, schemes_text

    return schemes_text([r.scheme for r in cameras() if r.kind.truth], "and")


def _replay_many_sources() -> str:
    """replay-many's sources, from the registered cameras (drivers.cameras), for its help."""
    import textwrap

    text = (
        f"Sources: URLs of the cameras that are not hardware ({', '.join(usages(hardware=False))}), recordings, "
        "dataset folders (those a camera's driver recognises), folders of recordings, and globs of any of these "
        "('archive/**/*.mcap', or in a URL's path); the shell's braces give one source per seed: "
        "'URL&seed='{1..8} (docs/fleet.md)."
    )
    return textwrap.fill(text, 100)


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="robotd", description="Onboard stereo-vision SLAM daemon.")
    p.add_argument("--version", action="version", version=f"robotd {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def add(name: str, fn: Callable[[argparse.Namespace], int], help_: str, config: bool = True) -> Any:
        sp = sub.add_parser(name, help=help_, description=help_)
        if config:
            sp.add_argument("--config", metavar="FILE", help="TOML file overriding the built-in defaults")
        sp.add_argument("--log-level", choices=["DEBUG", "INFO", "WARNING", "ERROR"], default=None)
        sp.set_defaults(func=fn)
        return sp

    sp = add("run", cmd_run, f"run the daemon (default: on the simulated rover, {CameraConfig().url})")
    sp.add_argument("--camera", metavar="URL", help="override camera.url")
    sp.add_argument("--vehicle", metavar="URL", help="override vehicle.url")
    sp.add_argument(
        "--duration", type=_seconds, default=0.0, help="stop after this many seconds, in every state (0: until SIGTERM)"
    )

    sp = add("replay", cmd_replay, "run a recording or dataset through the pipeline")
    sp.epilog = """\
Progress on stderr when it is a terminal; one summary line on stderr at the end. With --json,
a JSON summary on stdout; when the source carries ground truth it holds the keys of
`robotd eval` prefixed truth_ (truth_drift_m, truth_drift_pct, truth_ate_rmse_m, ...),
truth_drift_pct and truth_similarity_scale null on a path shorter than 1 m; also those of
`robotd eval --segments` (truth_segment_drift_pct, truth_segment_rot_deg_per_m,
truth_segment_count: 100-800 m segments, null on a shorter path) and of `--align-positions 10`
(truth_aligned_nees_pos_mean, truth_aligned_nees_pos_in_band_frac, truth_aligned_nees_pos_frames,
truth_alignment; null when nothing lies past the first 10 m).

--out T.txt writes the trajectory and T.cov.txt (the pose covariance, stamped). TUM (the default):
robotd's robot frame (FRD, origin at the stereo baseline centre), world = the robot at the first
frame. --format kitti: a KITTI pose file, the left rectified camera's optical frame (x right,
y down, z forward) relative to its first pose, one row per replayed frame, as a KITTI poses.txt,
so `evo_ape kitti DIR/poses.txt T.txt -a` compares like with like. --truth-out G.txt writes the
truth the source carries (TRUTH_SOURCES do) for the same frames,
in the same format and frame: `evo_ape tum G.txt T.txt -a` then gives truth_ate_umeyama_rmse_m
and `evo_rpe tum G.txt T.txt` truth_rpe_trans_m (docs/experiments.md, "Metrics").""".replace(
        "TRUTH_SOURCES", _truth_sources()
    )
    sp.formatter_class = argparse.RawDescriptionHelpFormatter
    sp.add_argument("source", help=", ".join(usages(hardware=False)))
    sp.add_argument("--realtime", action="store_true", help="pace frames at their recorded rate")
    sp.add_argument("--out", metavar="TRAJ", help="write the trajectory (TUM format; see --format)")
    sp.add_argument(
        "--format",
        choices=("tum", "kitti"),
        default="tum",
        help="of --out and --truth-out: tum (robot frame, stamped) or kitti (the left camera's poses, one row a frame)",
    )
    sp.add_argument(
        "--truth-out", metavar="FILE", help="also write the source's ground truth, in --out's format and frame"
    )
    sp.add_argument("--max-frames", type=int, default=0)
    sp.add_argument("--gt-odometry", action="store_true", help="EXPERIMENTS ONLY: odometry synthesised from truth")
    sp.add_argument("--json", action="store_true", help="print a JSON summary")
    sp.add_argument("--quiet", action="store_true", help="no progress bar (the final summary line stays)")

    sp = add("replay-many", cmd_replay_many, "replay many sources × configurations, locally or on Ray", config=False)
    sp.epilog = (
        _replay_many_sources()
        + """

Configurations: each --config FILE (none: the defaults) times each --variant ('NAME: slam.filter=ekf
frontend.detector=sift'; none: one per file), with every --set applied to all. The first is the
baseline of the comparison columns.

Each replay runs robotd.tools.replay in a worker process (or a Ray task), exactly as `robotd replay SOURCE
--out T.txt`: DIR/trajectories/KEY.txt is byte for byte that file. Rows go to DIR/rows.jsonl as they
finish, keyed by (source digest, configuration digest, robotd version): a rerun skips the rows done
(ok, or the replay raised) and runs again those that timed out, ran out of memory, lost their
worker or were interrupted. A failure is a row. The table goes to stdout (Markdown; --json: the JSON
document) and to DIR/table.md, DIR/results.json and DIR/table.csv.

Exit status: 0 every replay ok, 1 some failed, 130 interrupted (finished rows kept), 2 usage error.
`robotd replay-many compare A B` compares two results (see its --help). docs/fleet.md."""
    )
    sp.formatter_class = argparse.RawDescriptionHelpFormatter
    sp.add_argument("sources", nargs="*", metavar="SOURCE", help="URL, recording, dataset folder, folder or glob")
    sp.add_argument("--sources-file", action="append", default=[], metavar="FILE", help="sources, one a line")
    sp.add_argument("--out", required=True, metavar="DIR", help="the results folder (rows, trajectories, table)")
    sp.add_argument("--config", action="append", default=[], metavar="FILE", help="a configuration (repeatable)")
    sp.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE", help="for every configuration")
    sp.add_argument(
        "--variant", action="append", default=[], metavar="'[NAME:] K=V ...'", help="a configuration per variant"
    )
    sp.add_argument("--workers", type=int, default=0, help="local worker processes (0: one per core)")
    sp.add_argument("--ray", metavar="ADDRESS", help="run on Ray: a cluster's address, 'auto', or 'local'")
    sp.add_argument("--max-retries", type=int, default=3, help="Ray: retries of a replay whose worker died")
    sp.add_argument("--timeout", type=float, default=0.0, help="seconds a replay may take (0: no limit)")
    sp.add_argument(
        "--memory-mb", type=float, default=4000.0, help="resident memory a replay may use (Ray: its request)"
    )
    sp.add_argument("--rerun", action="store_true", help="run every replay again, done or not")
    sp.add_argument("--json", action="store_true", help="print the JSON document instead of the Markdown table")
    sp.add_argument("--quiet", action="store_true", help="no progress bar")

    sp = add(
        "replay-many compare",
        cmd_replay_many_compare,
        "which sources got worse between two replay-many results (versions or configurations)",
        config=False,
    )
    sp.epilog = """\
A and B: a replay-many --out folder (or its results.json), with #CONFIG to take one configuration
(DIR#default DIR#ekf compares two configurations of one run). Rows pair by source digest. B is
worse where it failed and A did not, lost more frames (beyond --lost), or its ATE or drift exceeds
A's x (1 + --tolerance) plus --ate-m / --drift-pct (--drift-m on paths under 1 m). The worst
--worst get a PNG each: A's and B's trajectories side by side over the truth, in --plots (default
B's folder/compare). Exit status 1 when something got worse, else 0."""
    sp.formatter_class = argparse.RawDescriptionHelpFormatter
    sp.add_argument("a", metavar="A", help="the reference: DIR[#CONFIG] or results.json[#CONFIG]")
    sp.add_argument("b", metavar="B", help="the candidate, likewise")
    sp.add_argument("--tolerance", type=float, default=0.10, help="relative slack on ATE and drift (0.10: 10 %%)")
    sp.add_argument("--ate-m", type=float, default=0.005, help="absolute slack on ATE [m]")
    sp.add_argument("--drift-pct", type=float, default=0.1, help="absolute slack on drift [points of %%]")
    sp.add_argument("--drift-m", type=float, default=0.005, help="absolute slack on drift in metres (short paths)")
    sp.add_argument("--lost", type=int, default=0, help="more lost frames than this is worse")
    sp.add_argument("--worst", type=int, default=5, help="plot this many of the worst (0: none)")
    sp.add_argument("--plots", metavar="DIR", help="where the PNGs go (default: B's folder/compare)")
    sp.add_argument("--json", action="store_true")

    sp = add("record", cmd_record, "record a session (camera, odometry, calibration, poses) as MCAP")
    sp.epilog = """\
Every frame the camera delivers and every odometry sample is recorded, whatever SLAM keeps up
with; SLAM's poses, features and map go beside them. Samples the writer could not keep up with
(a full --buffer-mb) are counted, in the health line and in the summary line at the end.
A recording keeps no map and no reset counter, and touches no state directory, unless
--state-dir names one (of its own, never a running daemon's)."""
    sp.formatter_class = argparse.RawDescriptionHelpFormatter
    sp.add_argument("out", help="OUT.mcap")
    sp.add_argument("--duration", type=_seconds, default=10.0, help="seconds to record (0: until SIGTERM)")
    sp.add_argument("--state-dir", metavar="DIR", help="keep a map and the reset counter in DIR (default: none)")
    sp.add_argument(
        "--buffer-mb", type=float, default=128.0, help="images that may wait for the writer, MB (default 128)"
    )
    sp.add_argument("--json", action="store_true", help="print the summary as JSON on stdout")

    sp = add("eval", cmd_eval, "ATE/RPE/drift of a trajectory against ground truth", config=False)
    sp.epilog = """\
keys: frames (associated poses); ate_rmse_m, ate_mean_m, ate_median_m, ate_max_m, final_error_m
(after a rigid alignment; on a straight path its rotation about the path comes from the
orientations, which positions leave open); ate_umeyama_rmse_m (after the plain least-squares fit
of positions, as evo_ape -a computes it); heading_rmse_deg; rpe_trans_m, rpe_rot_deg (frame to
frame, as evo_rpe's defaults);
drift_m (end-point error after aligning the first poses only) and drift_pct (the same in % of
path_length_m); similarity_scale (diagnostic). drift_pct and similarity_scale are undefined
(n/a, JSON null) when the ground-truth path is shorter than 1 m (a stationary sequence);
travel_offset_deg and gt_travel_offset_deg (diagnostic): the median angle between heading and
direction of travel over 2 m steps, estimate's and truth's; a vehicle's camera mount gives both
the same, and a difference is an orientation the truth or the estimate gets wrong, which
drift_pct carries as lateral error (null without 3 forward steps);
association: how the poses were paired ("time", or "index" when one side has no recorded times
and both have one pose per frame).

With the pose covariance beside the trajectory (robotd replay --out T.txt writes T.cov.txt; see
docs/slam.md "Reported covariance"): nees_pos_mean, the mean over poses of the position NEES
e^T P^-1 e (3-D position error e after aligning the first poses, P the reported 3x3 position
covariance, rotated with the alignment), nees_pos_in_band_frac, the share of poses inside the
two-sided 95 % chi2(3) interval [0.216, 9.35], and nees_pos_frames (the start, known exactly, has
none). A consistent covariance puts about 95 % inside.

--align-positions M judges the same NEES without resting on the first pose's orientation: the
estimate is aligned to the truth by the positions of the poses within the first M metres of true
path only (rigid least squares, no scale), and the NEES is taken on the poses after those M
metres: aligned_nees_pos_mean, aligned_nees_pos_in_band_frac (same band), aligned_nees_pos_frames,
aligned_fit_frames (the poses fitted), alignment and alignment_note (how, and why). alignment is
"positions"; "positions+first-pose-roll" when the first M metres are straight (collinear
positions fix every rotation but the one about the line, taken from the first pose's orientation);
or "first-pose" when they stay within 0.1 m (RMS about their mean) or hold no pose but the first
(aligned by the first pose, as nees_pos_*). A true path no longer than M leaves no pose to judge: the figures are n/a
(JSON null) and alignment_note says so (a stationary sequence). With --nees-plot the plot shows
this NEES.

--segments: KITTI-style segment drift. From every 10th pose, for each length L (default 100, 200,
..., 800 m; --segment-lengths 10,20,40 sets others and implies --segments), a segment ends at the
first pose at which the true path from its start reaches L; its error is the relative pose error
between start and end: translation in % of L, rotation in deg per metre of L. segments: per length
its count, drift_pct and rot_deg_per_m (means); segment_drift_pct, segment_rot_deg_per_m: the means
over every segment of every length; segment_count. A true path shorter than the shortest length
has no segment: the figures are n/a (JSON null) and segment_note says why.

A KITTI poses.txt is read as a replay of its folder carries its truth: moved from the left
camera's optical frame to the robot frame at the stereo baseline centre (baseline from the
calib.txt beside it, else the one beside the other file) and stamped from the times.txt beside
it, so a replay of the folder (`robotd replay URL --out T.txt`, TUM or --format kitti) then
`robotd eval T.txt DIR/poses.txt` gives the replay's own truth_* figures."""
    sp.formatter_class = argparse.RawDescriptionHelpFormatter
    sp.add_argument("traj", help="estimated trajectory (TUM, or KITTI poses)")
    sp.add_argument("gt", help="ground truth (TUM, or KITTI poses.txt)")
    sp.add_argument("--plot", metavar="PNG", help="also write a plot of both trajectories to PNG (none by default)")
    # kept so that old scripts still run: a plot is opt-in now, so there is nothing to turn off
    sp.add_argument("--no-plot", action="store_true", help=argparse.SUPPRESS)
    sp.add_argument(
        "--cov", metavar="FILE", help="the estimate's pose covariance (default: T.cov.txt beside T.txt, if any)"
    )
    sp.add_argument("--nees-plot", metavar="PNG", help="write the position NEES over time with its 95 %% band to PNG")
    sp.add_argument(
        "--align-positions",
        type=_metres,
        metavar="M",
        help="also the position NEES after aligning by positions over the first M metres of true path, on the rest",
    )
    sp.add_argument("--segments", action="store_true", help="also KITTI-style segment drift (100 ... 800 m segments)")
    sp.add_argument(
        "--segment-lengths",
        type=_segment_lengths,
        metavar="M,M,...",
        help="segment lengths in metres for --segments (implies it), e.g. 10,20,40 on a short sequence",
    )
    sp.add_argument("--planar", action="store_true", help="SE(2) alignment (2D runs)")
    sp.add_argument("--json", action="store_true")

    sp = add("experiments", cmd_experiments, "reproduce the thesis's simulation experiments", config=False)
    sp.add_argument("--out", required=True, metavar="DIR")
    sp.add_argument("--quick", action="store_true", help="a small version (seconds) for smoke tests")
    sp.add_argument("--seeds", type=int, default=None)

    sp = add("echo", cmd_echo, "print what robotd publishes on a Zenoh key", config=False)
    sp.add_argument("key", help="key expression, e.g. robotd/r1/pose or robotd/**")
    sp.add_argument("--connect", action="append", default=[], metavar="ENDPOINT", help="e.g. tcp/127.0.0.1:7447")
    sp.add_argument("--count", type=int, default=0, help="exit after N samples (0: forever)")
    sp.add_argument("--timeout", type=float, default=0.0, help="exit after this many seconds (0: never)")

    sp = add("fleet", cmd_fleet, "the live rovers on a Zenoh network and their health", config=False)
    sp.epilog = """\
Lists every robotd whose liveliness token robotd/<id>/alive is alive where --connect points (a
base station's router, or a robotd's own endpoint), with the state and problems of its health
topic, fps, tracking, quality, landmarks, position and latency. --watch then prints a line when a
rover joins or leaves, and the table again. Exit status 1 when no rover is alive. docs/fleet.md."""
    sp.formatter_class = argparse.RawDescriptionHelpFormatter
    sp.add_argument("--connect", action="append", default=[], metavar="ENDPOINT", help="e.g. tcp/base-station:7447")
    sp.add_argument("--wait", type=float, default=2.0, help="seconds to wait for each rover's health (1 Hz)")
    sp.add_argument("--watch", action="store_true", help="then report rovers joining and leaving")
    sp.add_argument("--timeout", type=float, default=0.0, help="with --watch: stop after this many seconds")
    sp.add_argument("--json", action="store_true", help="one JSON object (per table, with --watch)")

    sp = add("router", cmd_router, "a Zenoh router (a fleet's base station, or a host without zenohd)", config=False)
    sp.add_argument(
        "--listen", action="append", default=[], metavar="ENDPOINT", help="default tcp/127.0.0.1:7447 (repeatable)"
    )
    sp.add_argument("--zenoh-config", metavar="FILE", help="a JSON5 file instead (config/zenoh-base-station.json5)")
    sp.add_argument("--duration", type=_seconds, default=0.0, help="stop after this many seconds (0: until SIGTERM)")

    add("print-config", cmd_print_config, "print the resolved configuration").add_argument(
        "--docs", action="store_true", help="with each key's documentation"
    )

    sp = add("doctor", cmd_doctor, "check this machine for a rover install (devices, ports, cache, calibration)")
    sp.add_argument("--json", action="store_true", help="print one JSON object with every result")
    sp.add_argument("--warm", action="store_true", help="compile the numba kernels into their cache first")

    sp = add("mcu-sim", cmd_mcu_sim, "the reference vehicle MCU simulator (serial protocol)", config=False)
    sp.add_argument("rest", nargs=argparse.REMAINDER)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    if argv is None:  # the robotd command itself (not a caller passing arguments, e.g. a test)
        journal.install()  # under systemd: a syslog priority on every line it writes
    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:2] == ["replay-many", "compare"]:  # a command of two words (argparse knows it as one)
        argv = ["replay-many compare", *argv[2:]]
    args = parser.parse_args(argv)
    try:
        return int(args.func(args))
    except RobotdError as exc:
        with journal.priority(journal.ERR):
            print(f"robotd: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
