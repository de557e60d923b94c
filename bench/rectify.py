"""Rectification cost: building the remap tables once, and rectifying one stereo pair.

Rigs: the OAK-D factory calibration at 640x400 (14-coefficient rational model) and a
synthetic 1280x800 rig, both with the OpenCV and the thesis rectification (robotd.core.stereo.Rectifier,
CV_16SC2 tables, bilinear). Times are medians over --repeats runs on whatever machine runs this.
Prints a Markdown table, or one JSON object with --json.

    python bench/rectify.py [--repeats 50] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from robotd.core.stereo import Rectifier, StereoCalibration, camera_matrix

OAK_JSON = Path(os.environ.get("ROBOTD_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data")) / (
    "oakd-calibration/BW1098OBC_14442C10218CCCD200.json"
)


def _synthetic(width: int, height: int) -> StereoCalibration:
    R, _ = cv2.Rodrigues(np.array([0.004, -0.01, 0.002]))
    f = 0.67 * width
    return StereoCalibration(
        K_left=camera_matrix(f, f, width / 2 + 3, height / 2 - 2),
        D_left=np.array([-0.28, 0.08, 1e-3, -2e-4]),
        K_right=camera_matrix(f * 1.004, f * 1.003, width / 2 - 4, height / 2 + 5),
        D_right=np.array([-0.27, 0.07, -5e-4, 6e-4]),
        R=R,
        T=np.array([-0.075, 0.001, 0.0005]),
        image_size=(width, height),
    )


def _rigs() -> list[tuple[str, StereoCalibration]]:
    rigs = []
    if OAK_JSON.exists():
        from drivers.oak import load_oak_eeprom_json

        rigs.append(("oak-d 640x400 rational", load_oak_eeprom_json(OAK_JSON, 640, 400)))
    rigs.append(("synthetic 640x400 radtan", _synthetic(640, 400)))
    rigs.append(("synthetic 1280x800 radtan", _synthetic(1280, 800)))
    return rigs


def run(repeats: int) -> list[dict]:
    rows = []
    rng = np.random.default_rng(0)
    for name, calib in _rigs():
        w, h = calib.image_size
        left = rng.integers(0, 255, (h, w), dtype=np.uint8)
        right = rng.integers(0, 255, (h, w), dtype=np.uint8)
        for method in ("opencv", "thesis"):
            t0 = time.perf_counter()
            r = Rectifier(calib, method=method)  # type: ignore[arg-type]
            build_ms = (time.perf_counter() - t0) * 1e3
            times = []
            for _ in range(repeats):
                t0 = time.perf_counter()
                r.rectify(left, right)
                times.append((time.perf_counter() - t0) * 1e3)
            m = r.model
            rows.append(
                {
                    "rig": name,
                    "method": method,
                    "build_ms": build_ms,
                    "pair_ms": statistics.median(times),
                    "f_px": m.f_px,
                    "baseline_m": m.baseline_m,
                }
            )
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeats", type=int, default=50)
    p.add_argument("--json", action="store_true")
    args = p.parse_args(argv)
    rows = run(args.repeats)
    if args.json:
        sys.stdout.write(json.dumps({"cv2_threads": cv2.getNumThreads(), "results": rows}) + "\n")
        return 0
    print(f"cv2 threads: {cv2.getNumThreads()}, {os.cpu_count()} cores, median of {args.repeats}\n")
    print("| rig | method | build tables ms | rectify pair ms | f px | b m |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['rig']} | {r['method']} | {r['build_ms']:.1f} | {r['pair_ms']:.2f} | {r['f_px']:.2f} | "
            f"{r['baseline_m']:.5f} |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
