#!/usr/bin/env python3
"""Recording size and cost: MB per second of 640×400 stereo at 30 Hz from sim://, per channel.

Two runs:

- ``writer``: the sim:// rover's frames and odometry written straight through SessionWriter
  (with the truth as the pose), so every frame of the 30 Hz stream is in the file; gives MB/s at
  30 Hz and the writer's time per frame (PNG encoding dominates);
- ``daemon``: a real ``robotd record`` for ``--seconds``: the file as the daemon writes it, with
  the SLAM channels (features, map, trajectory); MB/s is its size per recorded frame × 30 (frames
  SLAM did not take are not recorded).

    python bench/recording.py [--seconds 5] [--json] [--no-daemon]
"""

from __future__ import annotations

import argparse
import json
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
    from robotd.mcap_scan import McapScan

    sizes: dict[str, int] = defaultdict(int)
    for ch, m in McapScan(path).messages():
        sizes[ch.topic] += len(m.data)
    return dict(sizes)


def writer_run(seconds: float, image_format: str, tmp: Path) -> dict[str, Any]:
    import numpy as np

    import drivers
    from robotd.geometry import R_to_euler
    from robotd.msgs import PoseEstimate
    from robotd.record import SessionWriter

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


def daemon_run(seconds: float, tmp: Path) -> dict[str, Any]:
    from robotd.config import load_config
    from robotd.daemon import Daemon
    from robotd.record import SessionReader

    cfg_file = tmp / "c.toml"
    cfg_file.write_text(
        f'[camera]\nurl = "{SIM}"\n[vehicle]\nurl = "{SIM}"\n[zenoh]\nenabled = false\n'
        f'[persistence]\nstate_dir = "{tmp / "state"}"\nsave_period_s = 0.0\n'
    )
    path = tmp / "daemon.mcap"
    d = Daemon(load_config(str(cfg_file)), duration_s=seconds, record_path=str(path))
    if d.run() != 0:
        return {"run": "daemon", "error": "robotd record failed"}
    frames = SessionReader(path).frame_count() or 0
    size = path.stat().st_size
    return {
        "run": "daemon (robotd record)",
        "frames": frames,
        "file_MB": size / 1e6,
        "MB_per_s_at_30Hz": size / max(frames, 1) * FPS / 1e6,
        "recorded_fps": frames / seconds,
        "payload_MB_per_s_by_topic": {k: v / max(frames, 1) * FPS / 1e6 for k, v in sorted(_per_topic(path).items())},
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--no-daemon", action="store_true")
    args = ap.parse_args(argv)
    import logging

    logging.basicConfig(level=logging.WARNING)
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        rows = [writer_run(args.seconds, "png", tmp), writer_run(args.seconds, "raw", tmp)]
        if not args.no_daemon:
            rows.append(daemon_run(args.seconds, tmp))
    if args.json:
        print(json.dumps({"rows": rows}, sort_keys=True))
        return 0
    print("| run | frames | MB/s at 30 Hz | write ms/frame |\n|---|---:|---:|---:|")
    for r in rows:
        ms = r.get("write_ms_per_frame")
        print(f"| {r['run']} | {r.get('frames')} | {r.get('MB_per_s_at_30Hz', float('nan')):.2f} | "
              f"{'' if ms is None else f'{ms:.1f}'} |")  # fmt: skip
    print("\nPayload by topic, MB/s at 30 Hz (before chunk compression):\n")
    for r in rows:
        top = ", ".join(f"{k} {v:.3f}" for k, v in r.get("payload_MB_per_s_by_topic", {}).items() if v >= 0.001)
        print(f"- {r['run']}: {top}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
