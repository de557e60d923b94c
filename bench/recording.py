#!/usr/bin/env python3
"""Recording size and cost: MB per second of 640×400 stereo at 30 Hz from sim://, per channel.

Two runs:

- ``writer``: the sim:// rover's frames and odometry written straight through SessionWriter
  (with the truth as the pose), so every frame of the 30 Hz stream is in the file; gives MB/s at
  30 Hz and the writer's time per frame (PNG encoding dominates);
- ``daemon``: a real ``robotd record`` for ``--seconds``: the file as the daemon writes it, with
  the SLAM channels (features, map, trajectory); MB/s is its size per recorded frame × 30, and
  over the recording's span. With ``--hogs N``, N CPU-bound processes run beside it (issue 27's
  evidence: ``--hogs 2 --seconds 10`` on a 2-core host): the row gives the frames the camera
  delivered (the daemon's count and the driver's own), the frames in the file and those lost
  (the recorder's writer fell behind), what SLAM processed, the recorder queue's peak, the
  messages the ``mcap`` library reads with CRC checks on, and the frames a replay processes.

    python bench/recording.py [--seconds 5] [--hogs N] [--json] [--no-daemon]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

FPS = 30.0
SIM = "sim://?width=640&height=400&fps=30&seed=1"


def _per_topic(path: Path) -> dict[str, int]:
    from robotd.formats.mcap_scan import McapScan

    sizes: dict[str, int] = defaultdict(int)
    for ch, m in McapScan(path).messages():
        sizes[ch.topic] += len(m.data)
    return dict(sizes)


def writer_run(seconds: float, image_format: str, tmp: Path) -> dict[str, Any]:
    import numpy as np

    import drivers
    from robotd.core.geometry import R_to_euler
    from robotd.core.msgs import PoseEstimate
    from robotd.formats.record import SessionWriter

    n = int(seconds * FPS)
    fast = SIM + "&realtime=0"  # as fast as rendered: the 30 Hz stamps are the simulator's own
    with drivers.open_camera(fast) as cam:
        frames = [f for _, f in zip(range(n), cam.frames(), strict=False)]
        rig = cam.rectified_model()
    odo = []
    with drivers.open_vehicle(fast) as veh:
        for o in veh.odometry(timeout_s=0.0):
            if o.t_ns > frames[-1].t_ns:
                break
            odo.append(o)
    path = tmp / f"writer-{image_format}.mcap"
    t_write = 0.0
    with SessionWriter(path, rig, {"bench": "recording"}, image_format=image_format) as w:
        k = 0
        for f in frames:
            t0 = time.perf_counter()
            while k < len(odo) and odo[k].t_ns <= f.t_ns:
                w.write_odometry(odo[k])
                k += 1
            w.write_frame(f)
            T = f.truth_T_world_robot
            if T is not None:  # the truth stands in for the estimate (no SLAM in this run)
                w.write_pose(PoseEstimate(f.t_ns, T[:3, 3].copy(), R_to_euler(T[:3, :3]), 1e-4 * np.eye(6)))
            t_write += time.perf_counter() - t0
    size = path.stat().st_size
    return {
        "run": f"writer ({image_format})",
        "frames": len(frames),
        "file_MB": size / 1e6,
        "MB_per_s_at_30Hz": size / len(frames) * FPS / 1e6,
        "write_ms_per_frame": t_write / len(frames) * 1e3,
        "payload_MB_per_s_by_topic": {k: v / len(frames) * FPS / 1e6 for k, v in sorted(_per_topic(path).items())},
    }


@contextlib.contextmanager
def _hogs(n: int) -> Any:
    """``n`` CPU-bound processes for the duration of the block (each stopped by its own id)."""
    procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(n)]
    try:
        yield
    finally:
        for p in procs:
            p.kill()
            p.wait()


def _crc_read(path: Path) -> int:
    """Messages the ``mcap`` library reads, every chunk's CRC checked (raises on a bad one)."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        return sum(1 for _ in make_reader(f, validate_crcs=True).iter_messages(log_time_order=False))


def daemon_run(seconds: float, tmp: Path, hogs: int = 0, replay: bool = True) -> dict[str, Any]:
    from robotd.config import load_config
    from robotd.daemon import Daemon
    from robotd.formats.record import SessionReader

    cfg_file = tmp / "c.toml"
    cfg_file.write_text(f'[camera]\nurl = "{SIM}"\n[vehicle]\nurl = "{SIM}"\n[zenoh]\nenabled = false\n')
    path = tmp / "daemon.mcap"
    cfg = load_config(str(cfg_file))
    d = Daemon(cfg, duration_s=seconds, record_path=str(path))
    with _hogs(hogs):
        if d.run() != 0:
            return {"run": "daemon", "error": "robotd record failed"}
    s = d.record_summary()
    frames = SessionReader(path).frame_count() or 0
    size = path.stat().st_size
    row = {
        "run": f"daemon (robotd record{f', {hogs} CPU hogs' if hogs else ''})",
        "frames": frames,
        "frames_delivered": s["frames_delivered"],
        "camera_frames": s["camera"].get("frames"),  # the driver's own count of what it delivered
        "frames_lost": s["frames_lost"],
        "odometry": s["odometry"],
        "odometry_delivered": s["odometry_delivered"],
        "odometry_lost": s["odometry_lost"],
        "slam_steps": s["slam_steps"],
        "slam_dropped": s["slam_dropped"],
        "slam_skipped": s["slam_skipped"],
        "queue_high_water_MB": s["queue_high_water_mb"],
        "file_MB": size / 1e6,
        "span_s": s["span_s"],
        "MB_per_s": size / 1e6 / max(s["span_s"], 1e-9),
        "MB_per_s_at_30Hz": size / max(frames, 1) * FPS / 1e6,
        "recorded_fps": frames / seconds,
        "mcap_crc_messages": _crc_read(path),
        "payload_MB_per_s_by_topic": {k: v / max(frames, 1) * FPS / 1e6 for k, v in sorted(_per_topic(path).items())},
    }
    if replay:
        from robotd.tools.replay import replay as run_replay

        row["replayed_frames"] = run_replay(cfg, str(path), progress=False)["frames"]
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--no-daemon", action="store_true")
    ap.add_argument("--hogs", type=int, default=0, help="CPU-bound processes beside the daemon run")
    ap.add_argument("--no-replay", action="store_true", help="do not replay the daemon's recording")
    ap.add_argument("--no-writer", action="store_true", help="only the daemon run")
    args = ap.parse_args(argv)
    import logging

    logging.basicConfig(level=logging.WARNING)
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        rows = [] if args.no_writer else [writer_run(args.seconds, "png", tmp), writer_run(args.seconds, "raw", tmp)]
        if not args.no_daemon:
            rows.append(daemon_run(args.seconds, tmp, args.hogs, not args.no_replay))
    if args.json:
        print(json.dumps({"rows": rows}, sort_keys=True))
        return 0
    print("| run | frames | MB/s at 30 Hz | write ms/frame |\n|---|---:|---:|---:|")
    for r in rows:
        ms = r.get("write_ms_per_frame")
        print(f"| {r['run']} | {r.get('frames')} | {r.get('MB_per_s_at_30Hz', float('nan')):.2f} | "
              f"{'' if ms is None else f'{ms:.1f}'} |")  # fmt: skip
    for r in rows:
        if "frames_delivered" in r:
            print(
                f"\n{r['run']}: camera delivered {r['frames_delivered']} frames (driver: {r['camera_frames']}), "
                f"file holds {r['frames']}, lost {r['frames_lost']}; odometry {r['odometry']} of "
                f"{r['odometry_delivered']}; SLAM processed {r['slam_steps']} (dropped {r['slam_dropped']}, "
                f"skipped {r['slam_skipped']}); {r['file_MB']:.1f} MB over {r['span_s']:.1f} s = "
                f"{r['MB_per_s']:.1f} MB/s; queue peak {r['queue_high_water_MB']} MB; mcap (CRC on) read "
                f"{r['mcap_crc_messages']} messages; replay processed {r.get('replayed_frames', '-')} frames"
            )
    print("\nPayload by topic, MB/s at 30 Hz (before chunk compression):\n")
    for r in rows:
        top = ", ".join(f"{k} {v:.3f}" for k, v in r.get("payload_MB_per_s_by_topic", {}).items() if v >= 0.001)
        print(f"- {r['run']}: {top}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
