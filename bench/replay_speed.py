"""robotd's step against OpenCV's own ORB on the same frames, in one run (issue 25).

The step's cost is judged against a floor any ORB-based pipeline pays: OpenCV's ORB (1000
features, one OpenCV thread) detecting and describing a frame's two images, one after the other.
This bench times that floor on every frame of a source, replays the source through robotd's
pipeline (`robotd replay`'s code: default configuration, vision only), then times the floor
again, and reports the step's median over the floor's (the mean of the two medians that bracket
the replay, so a machine that changes speed during the run shows as the two differing). Being a
ratio measured minutes apart on one machine, it means the same on a slow VM as on a fast one;
the absolute figures do not. The replay's stages (median milliseconds) say where the rest goes.

    python bench/replay_speed.py [--source kitti://../shared/data/kitti-seq1] [--repeat 2] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import drivers  # noqa: E402
from robotd.config import load_config  # noqa: E402
from robotd.pipeline.step import StepResult  # noqa: E402
from robotd.tools.replay import replay  # noqa: E402

DEFAULT_DATA = Path(os.environ.get("ROBOTD_SHARED_DATA", REPO.parent / "shared" / "data"))
STAGES = (
    "offset",
    "detect",
    "stereo",
    "motion",
    "identify",
    "outliers",
    "select",
    "predict",
    "consistency",
    "update",
    "gap",
    "search",
    "relocalise",
)


def load_pairs(source: str) -> list[tuple[np.ndarray, np.ndarray]]:
    """Every rectified pair of ``source`` (replayed as fast as it decodes), in memory."""
    url = source + ("&" if "?" in source else "?") + "realtime=0" if source.startswith("sim://") else source
    pairs = []
    with drivers.open_camera(url) as cam:
        for frame in cam.frames():
            pairs.append((np.ascontiguousarray(frame.left), np.ascontiguousarray(frame.right)))
    return pairs


def orb_floor_ms(pairs: list[tuple[np.ndarray, np.ndarray]], n_features: int = 1000) -> np.ndarray:
    """Milliseconds per frame for OpenCV's ORB to detect and describe both images, one thread."""
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        orb = cv2.ORB_create(nfeatures=n_features)
        out = np.empty(len(pairs))
        for k, (left, right) in enumerate(pairs):
            t0 = time.perf_counter()
            orb.detectAndCompute(left, None)
            orb.detectAndCompute(right, None)
            out[k] = (time.perf_counter() - t0) * 1e3
        return out
    finally:
        cv2.setNumThreads(threads)


def robotd_steps(source: str) -> tuple[dict[str, Any], list[dict[str, float]]]:
    """The replay's summary and each step's stage timings [ms]."""
    cfg = load_config(None, {"camera": {"url": source}, "vehicle": {"url": "none://"}})
    timings: list[dict[str, float]] = []

    def keep(r: StepResult) -> None:
        timings.append(dict(r.timings_ms))

    summary = replay(cfg, source, progress=False, on_step=keep)
    return summary, timings


def run(source: str, repeat: int) -> list[dict[str, Any]]:
    from robotd.pipeline.step import Pipeline

    Pipeline.warmup()  # kernels loaded before anything is timed
    pairs = load_pairs(source)
    rows = []
    for k in range(repeat):
        before = float(np.median(orb_floor_ms(pairs)))
        summary, timings = robotd_steps(source)
        after = float(np.median(orb_floor_ms(pairs)))
        floor = 0.5 * (before + after)
        stage_p50 = {
            s: float(np.median([t.get(s, 0.0) for t in timings])) for s in STAGES if any(s in t for t in timings)
        }
        total = np.array([t.get("total", np.nan) for t in timings])
        in_stages = np.array([sum(t.get(s, 0.0) for s in STAGES) for t in timings])
        rows.append(
            {
                "run": k + 1,
                "frames": len(pairs),
                "orb_pair_ms_p50_before": before,
                "orb_pair_ms_p50_after": after,
                "step_ms_p50": summary["step_ms_p50"],
                "step_ms_p95": summary["step_ms_p95"],
                "ratio": summary["step_ms_p50"] / floor,
                "stages_ms_p50": stage_p50,
                "outside_stages_ms_p50": float(np.nanmedian(total - in_stages)),
                "load_avg_1min": os.getloadavg()[0],
            }
        )
    return rows


def table(rows: list[dict[str, Any]]) -> str:
    stages = [s for s in STAGES if any(s in r["stages_ms_p50"] for r in rows)]
    out = [
        "| run | frames | OpenCV ORB pair p50 before / after [ms] | robotd step p50 / p95 [ms] | step / ORB | "
        + " | ".join(stages)
        + " | not in a stage | load |",
        "|---" * (7 + len(stages)) + "|",
    ]
    for r in rows:
        st = " | ".join(f"{r['stages_ms_p50'].get(s, 0.0):.1f}" for s in stages)
        out.append(
            f"| {r['run']} | {r['frames']} | {r['orb_pair_ms_p50_before']:.1f} / {r['orb_pair_ms_p50_after']:.1f} | "
            f"{r['step_ms_p50']:.1f} / {r['step_ms_p95']:.1f} | **{r['ratio']:.2f}×** | {st} | "
            f"{r['outside_stages_ms_p50']:.1f} | {r['load_avg_1min']:.1f} |"
        )
    return "\n".join(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--source", default=f"kitti://{DEFAULT_DATA / 'kitti-seq1'}", help="a camera URL robotd replays")
    ap.add_argument("--repeat", type=int, default=2, help="runs (each brackets a replay with two floor timings)")
    ap.add_argument("--json", action="store_true", help="one JSON object on stdout")
    args = ap.parse_args(argv)
    if args.source.startswith("kitti://") and not Path(args.source[len("kitti://") :].split("?")[0]).exists():
        msg = f"{args.source}: no such data: skipped"
        print(json.dumps({"skipped": msg}) if args.json else msg)
        return 0
    rows = run(args.source, max(1, args.repeat))
    print(json.dumps({"source": args.source, "runs": rows}) if args.json else table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
