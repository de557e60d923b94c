"""Rendering speed of the sim:// rover (drivers/sim.py): ms per stereo pair and pairs per second.

Renders ``--pairs`` consecutive frames of a world (``--world``, default the yard; seed 1) off the
clock (``SimRig.render``: both views, depth test, the moving box if the world has one, sensor
noise, StereoFrame with truth), after one warm-up frame, with OpenCV limited to ``--threads``
threads (1 = the "one core" goal of ≥ 60 pairs/s at 640×400). Also reports the world build time
(textures, first call in the process) and ORB features per left image on a few frames.

Prints a Markdown table, or exactly one JSON object with --json.

    python bench/sim_render.py [--world yard] [--pairs 300] [--width 640] [--height 400] [--threads 1]
        [--speed 1] [--fps 30] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np

# the project root first, so the checkout is benchmarked even where another robotd is installed
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from drivers.sim import SimParams, SimRig
from drivers.simworld import WORLDS, build_world


def run(
    pairs: int,
    width: int,
    height: int,
    threads: int,
    seed: int,
    world_name: str = "yard",
    speed: float = 1.0,
    fps: float = 30.0,
) -> dict:
    cv2.setNumThreads(threads)
    t = time.perf_counter()
    world = build_world(seed, world_name, speed)
    build_s = time.perf_counter() - t
    params = SimParams(width=width, height=height, seed=seed, realtime=0, world=world_name, speed=speed, fps=fps)
    rig = SimRig(world, params)
    rig.render(0, 0)  # warm-up: first touches of the textures
    ms = np.empty(pairs)
    for k in range(pairs):
        t = time.perf_counter()
        rig.render(k + 1, 0)
        ms[k] = (time.perf_counter() - t) * 1e3
    orb = cv2.ORB_create(nfeatures=2000)
    feats = [len(orb.detect(rig.render(int(k), 0)[0].left, None)) for k in np.linspace(0, 850, 8).astype(int)]
    return {
        "world": world_name,
        "speed": speed,
        "fps": fps,
        "width": width,
        "height": height,
        "pairs": pairs,
        "cv2_threads": threads,
        "cpu_count": os.cpu_count(),
        "loadavg_1min": os.getloadavg()[0],
        "world_build_s": round(build_s, 3),
        "ms_per_pair_p50": round(float(np.percentile(ms, 50)), 2),
        "ms_per_pair_p95": round(float(np.percentile(ms, 95)), 2),
        "ms_per_pair_mean": round(float(ms.mean()), 2),
        "pairs_per_s": round(float(1e3 / ms.mean()), 1),
        "orb2000_features_min": int(min(feats)),
        "orb2000_features_median": float(np.median(feats)),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=300)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=400)
    ap.add_argument("--threads", type=int, default=1, help="cv2.setNumThreads (0 = OpenCV default)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--world", choices=WORLDS, default="yard")
    ap.add_argument("--speed", type=float, default=1.0, help="the rover's speed [m/s] (sim:// speed=)")
    ap.add_argument("--fps", type=float, default=30.0, help="frame rate [Hz]: with --speed, how far the pairs reach")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    res = run(args.pairs, args.width, args.height, args.threads, args.seed, args.world, args.speed, args.fps)
    if args.json:
        print(json.dumps(res))
        return 0
    print(
        f"sim:// render, world {res['world']} (speed {res['speed']:g} m/s, {res['fps']:g} fps), "
        f"{res['width']}×{res['height']}, {res['pairs']} pairs, "
        f"cv2 threads {res['cv2_threads']}, "
        f"{res['cpu_count']} CPUs, load {res['loadavg_1min']:.2f}\n"
    )
    print("| metric | value |\n|---|---|")
    for key in ("world_build_s", "ms_per_pair_p50", "ms_per_pair_p95", "ms_per_pair_mean", "pairs_per_s",
                "orb2000_features_min", "orb2000_features_median"):  # fmt: skip
        print(f"| {key} | {res[key]} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
