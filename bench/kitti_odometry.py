"""Vision, recorded odometry and both on a KITTI raw folder (issue 13, item 5).

Runs ``robotd replay`` (in process, the same ``replay()``) with the default configuration and
``replay.odometry`` = "none" (vision only) and "dataset" (the drive's OXTS GPS/INS records as the
vehicle's odometry), for each filter, and the OXTS records alone (dead reckoning: the samples
integrated between frame times by ``robotd.pipeline.odometry.dead_reckon``). Each row: drift in % of the
path, ATE RMSE after a rigid alignment, RPE per frame, lost frames, all against the folder's
truth in the robot frame (the replay's own ``truth_*`` figures). Nothing is tuned here: the
configuration is the default, the OXTS noise is ``replay.oxts_sigma_*`` (drivers/kitti_oxts.py says
where the figures come from). Prints a Markdown table, or one JSON object with --json.

    python bench/kitti_odometry.py [--data ../shared/data/kitti-raw-0009] [--filters fastslam2,fastslam1,ekf] [--json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from robotd.config import load_config
from robotd.research.evaluate import Trajectory, evaluate_trajectories

KEYS = ("drift_pct", "ate_rmse_m", "rpe_trans_m", "rpe_rot_deg")


def run_replay(data: Path, filter_name: str, odometry: str, detector: str) -> dict[str, Any]:
    from robotd.tools.replay import replay

    cfg = load_config(
        overrides={
            "slam": {"filter": filter_name},
            "replay": {"odometry": odometry},
            "frontend": {"detector": detector},
        }
    )
    s = replay(cfg, f"kitti://{data}", progress=False)
    row: dict[str, Any] = {
        "run": f"{filter_name}, {detector}, {'vision + odometry' if odometry == 'dataset' else 'vision only'}",
        "filter": filter_name,
        "detector": detector,
        "odometry": s["odometry"],
        "lost_frames": s["lost_frames"],
        "frames": s["frames"],
        "odometry_priors": s["odometry_priors"],
        "odometry_rejected": s["odometry_rejected"],
        "ms_per_frame_p50": s["step_ms_p50"],
    }
    row.update({k: s.get(f"truth_{k}") for k in KEYS})
    return row


def run_dead_reckoning(data: Path) -> dict[str, Any]:
    """The OXTS samples alone, integrated between the frame times, against the frames' truth."""
    from drivers.dataset import KittiCamera, open_kitti_vehicle
    from robotd.pipeline.odometry import OdometryGate, dead_reckon

    cam = KittiCamera(f"kitti://{data}")
    truth = cam.truth()
    veh = open_kitti_vehicle(f"kitti://{data}?odometry=oxts")
    if veh.odometry_source != "oxts":
        raise SystemExit(f"{data}: no raw OXTS records (raw/*/oxts)")
    gate = OdometryGate()
    samples = [s for s in veh.samples if gate.accept(s)]
    t = np.array([t for t, _ in truth], dtype=np.int64)
    G = np.stack([g for _, g in truth])
    P = dead_reckon(samples, t)
    m = evaluate_trajectories(Trajectory(t / 1e9, P), Trajectory(t / 1e9, np.linalg.inv(G[0]) @ G))
    return {
        "run": "OXTS dead reckoning alone",
        "filter": "-",
        "detector": "-",
        "odometry": "oxts",
        "lost_frames": 0,
        "frames": len(t),
        "odometry_rejected": sum(gate.rejected.values()),
        **{k: m[k] for k in KEYS},
    }


def main(argv: list[str] | None = None) -> int:
    default = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "kitti-raw-0009"
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=default, help="KITTI folder with raw/<drive>/oxts")
    ap.add_argument("--filters", default="fastslam2,fastslam1,ekf")
    ap.add_argument("--detector", default="orb")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    if not (args.data / "calib.txt").exists():
        print(f"KITTI data not found at {args.data}", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    rows = []
    for f in [s.strip() for s in args.filters.split(",") if s.strip()]:
        for odo in ("none", "dataset"):
            rows.append(run_replay(args.data, f, odo, args.detector))
    rows.append(run_dead_reckoning(args.data))
    if args.json:
        json.dump({"benchmark": "kitti_odometry", "data": str(args.data), "wall_s": time.perf_counter() - t0,
                   "results": rows}, sys.stdout)  # fmt: skip
        sys.stdout.write("\n")
        return 0
    print(f"{args.data.name}: default configuration, seed 1, truth in the robot frame\n")
    print("| run | odometry | drift % | ATE m | RPE m/frame | RPE °/frame | lost frames |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['run']} | {r['odometry']} | {r['drift_pct']:.2f} | {r['ate_rmse_m']:.3f} | "
            f"{r['rpe_trans_m']:.3f} | {r['rpe_rot_deg']:.3f} | {r['lost_frames']} |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
