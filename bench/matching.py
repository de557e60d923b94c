#!/usr/bin/env python3
"""Frame-to-frame descriptor matching and guided identification's window: the (N, M) array paths
against the kernels that replaced them.

Every frame the front end matches its stereo measurements' descriptors against the previous
frame's, every one against every one (the PnP motion's pairs; the disparity offset does the same
against its anchor frame every 2 m). Until session 29 that was the whole (N, M) distance matrix,
its threshold mask, the ratio and cross-check kernel on the candidates and a partition of every
row; ``robotd.frontend.stereo_match.mutual_matches`` now does it in one numba pass for binary
descriptors (``_stereo_kernels.mutual_binary_kernel``). This benchmark runs both on the stereo
measurements of consecutive frames of each source (ORB at its defaults, the daemon's detector)
and checks that they give the same pairs.

Guided identification looks for each map landmark within a radius of its predicted pixel: three
(N, K) masks of column, row and disparity until session 29, now a search of the column-sorted
predictions (``stereo_match.window_pairs``). The second table replays each source through the
whole pipeline, keeps the inputs identification saw, and times both on them.

    python bench/matching.py [--sources kitti-seq1,kitti-raw-0009,euroc-v101-micro,sim] [--frames 30] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import drivers
import robotd.frontend.association as association
from robotd.config import load_config
from robotd.frontend.frontend import Frontend, FrontendParams
from robotd.frontend.stereo_match import mutual_matches, mutual_matches_matrix, window_pairs
from robotd.tools.replay import replay
from tests.support.reference_frontend import window_pairs_numpy as window_masks  # the masks it replaced

SHARED = Path(os.environ.get("ROBOTD_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
SOURCES = {
    "kitti-seq1": f"kitti://{SHARED / 'kitti-seq1'}",
    "kitti-raw-0009": f"kitti://{SHARED / 'kitti-raw-0009'}",
    "euroc-v101-micro": f"euroc://{SHARED / 'euroc-v101-micro'}",
    "sim": "sim://?realtime=0&fps=30",
}


def run_window(name: str, url: str, frames: int, reps: int) -> dict[str, Any]:
    """Guided identification's inputs from a replay of the source, then both window searches on them."""
    seen: list[tuple[np.ndarray, np.ndarray, float, bool]] = []
    real = association.window_pairs

    def keep(px: np.ndarray, pred: np.ndarray, r: float, rows_known: bool = True) -> tuple[np.ndarray, np.ndarray]:
        seen.append((px.copy(), np.array(pred, float), r, rows_known))
        return real(px, pred, r, rows_known)

    association.window_pairs = keep  # type: ignore[assignment]
    try:
        replay(load_config(None, {"frontend": {"detector": "orb"}}), url, max_frames=frames, progress=False)
    finally:
        association.window_pairs = real  # type: ignore[assignment]
    before, after, sizes, pairs, same = [], [], [], [], True
    for px, pred, r, rk in seen:
        ref, got = window_masks(px, pred, r, rk), window_pairs(px, pred, r, rk)
        same &= bool(np.array_equal(ref[0], got[0]) and np.array_equal(ref[1], got[1]))
        before.append(_median_ms(lambda px=px, pred=pred, r=r, rk=rk: window_masks(px, pred, r, rk), reps))
        after.append(_median_ms(lambda px=px, pred=pred, r=r, rk=rk: window_pairs(px, pred, r, rk), reps))
        sizes.append((px.shape[0], pred.shape[0]))
        pairs.append(got[0].size)
    bm, am = np.array(before), np.array(after)
    return {
        "source": name,
        "frames": len(seen),
        "measurements_per_frame": round(float(np.mean([s[0] for s in sizes])), 0) if sizes else 0.0,
        "landmarks_per_frame": round(float(np.mean([s[1] for s in sizes])), 0) if sizes else 0.0,
        "pairs_per_frame": round(float(np.mean(pairs)), 1) if pairs else 0.0,
        "masks_ms_median": round(float(np.median(bm)), 3) if seen else None,
        "kernel_ms_median": round(float(np.median(am)), 3) if seen else None,
        "speedup_median": round(float(np.median(bm / am)), 2) if seen else None,
        "same_pairs": same,
    }


def _median_ms(fn: Any, reps: int) -> float:
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts) * 1e3)


def run_source(name: str, url: str, frames: int, reps: int) -> dict[str, Any]:
    with drivers.open_camera(url) as cam:
        rig = cam.rectified_model()
        fe = Frontend(rig, FrontendParams(), np.random.default_rng(0))
        descs = []
        for k, fr in enumerate(cam.frames()):
            if k >= frames:
                break
            meas = fe.match_stereo(fe.detect(fr.left, fr.right), fr.left, fr.right)
            descs.append(meas.desc)
    p = fe.params
    max_d, ratio = p.association.limits(True)
    before, after, sizes, pairs, same = [], [], [], [], True
    for a, b in zip(descs[1:], descs[:-1], strict=True):
        ref = mutual_matches_matrix(a, b, True, max_d, ratio, True)
        got = mutual_matches(a, b, True, max_d, ratio, second_in_row=True)
        same &= bool(np.array_equal(ref[0], got[0]) and np.array_equal(ref[1], got[1]))
        before.append(_median_ms(lambda a=a, b=b: mutual_matches_matrix(a, b, True, max_d, ratio, True), reps))
        after.append(_median_ms(lambda a=a, b=b: mutual_matches(a, b, True, max_d, ratio, True), reps))
        sizes.append(a.shape[0] * b.shape[0])
        pairs.append(got[0].size)
    bm, am = np.array(before), np.array(after)
    return {
        "source": name,
        "pairs_of_frames": len(before),
        "measurements_per_frame": round(float(np.sqrt(np.mean(sizes))), 0),
        "matches_per_frame": round(float(np.mean(pairs)), 1),
        "matrix_ms_median": round(float(np.median(bm)), 3),
        "matrix_ms_p95": round(float(np.percentile(bm, 95)), 3),
        "kernel_ms_median": round(float(np.median(am)), 3),
        "kernel_ms_p95": round(float(np.percentile(am, 95)), 3),
        "speedup_median": round(float(np.median(bm / am)), 2),
        "same_pairs": same,
    }


def _table(title: str, header: list[str], body: list[list[Any]]) -> None:
    """A Markdown table under its title."""
    print(title + "\n")
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for row in body:
        print("| " + " | ".join(str(c) for c in row) + " |")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sources", default=",".join(SOURCES))
    ap.add_argument("--frames", type=int, default=30, help="frames per source (consecutive pairs: one fewer)")
    ap.add_argument("--reps", type=int, default=7, help="timings per pair of frames (their median is kept)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    from robotd.frontend import stereo_match

    stereo_match.warmup()  # the kernels compiled (or loaded) before any timing
    rows: list[dict[str, Any]] = []
    windows: list[dict[str, Any]] = []
    for name in args.sources.split(","):
        if name not in SOURCES:
            raise SystemExit(f"bench/matching.py: unknown source {name!r}; expected some of {', '.join(SOURCES)}")
        if not name.startswith("sim") and not Path(SOURCES[name].split("://", 1)[1]).is_dir():
            print(
                f"# {name}: skipped, {SOURCES[name]} is not there (../shared or ROBOTD_SHARED_DATA)",
                file=sys.stderr,
            )
            continue
        rows.append(run_source(name, SOURCES[name], args.frames, args.reps))
        windows.append(run_window(name, SOURCES[name], args.frames, args.reps))
    conditions = {
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "load_avg_1min": round(os.getloadavg()[0], 2),
    }
    if args.json:
        print(json.dumps({"benchmark": "matching", "conditions": conditions, "results": rows, "window": windows}))
        return 0 if all(r["same_pairs"] for r in rows + windows) else 1
    _table(
        "## Frame-to-frame descriptor matching, ORB (per pair of consecutive frames, ms)",
        ["source", "pairs of frames", "measurements per frame", "matches", "matrix path median / p95",
         "kernel median / p95", "speed-up (median)", "same pairs"],
        [
            [r["source"], r["pairs_of_frames"], f"{r['measurements_per_frame']:.0f}", f"{r['matches_per_frame']:.0f}",
             f"{r['matrix_ms_median']:.2f} / {r['matrix_ms_p95']:.2f}",
             f"{r['kernel_ms_median']:.2f} / {r['kernel_ms_p95']:.2f}", f"{r['speedup_median']:.1f}×",
             "yes" if r["same_pairs"] else "**no**"]
            for r in rows
        ],
    )  # fmt: skip
    _table(
        "\n## Guided identification's window (per frame of a replay, ms)",
        ["source", "frames", "measurements", "landmarks predicted", "pairs", "masks median", "kernel median",
         "speed-up", "same pairs"],
        [
            [w["source"], w["frames"], f"{w['measurements_per_frame']:.0f}", f"{w['landmarks_per_frame']:.0f}",
             f"{w['pairs_per_frame']:.0f}", f"{w['masks_ms_median']:.3f}", f"{w['kernel_ms_median']:.3f}",
             f"{w['speedup_median']:.1f}×", "yes" if w["same_pairs"] else "**no**"]
            for w in windows
            if w["frames"]  # a source whose replay never identified against the map has no row
        ],
    )  # fmt: skip
    print(f"\nConditions: {conditions}")
    return 0 if all(r["same_pairs"] for r in rows + windows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
