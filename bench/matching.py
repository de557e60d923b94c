#!/usr/bin/env python3
"""Frame-to-frame descriptor matching: the (N, M) distance-matrix path against the one-pass kernel.

Every frame the front end matches its stereo measurements' descriptors against the previous
frame's, every one against every one (the PnP motion's pairs; the disparity offset does the same
against its anchor frame every 2 m). Until session 29 that was the whole (N, M) distance matrix,
its threshold mask, the ratio and cross-check kernel on the candidates and a partition of every
row; ``robotd.frontend.stereo_match.mutual_matches`` now does it in one numba pass for binary
descriptors (``_stereo_kernels.mutual_binary_kernel``). This benchmark runs both on the stereo
measurements of consecutive frames of each source (ORB at its defaults, the daemon's detector)
and checks that they give the same pairs.

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
from robotd.frontend.frontend import Frontend, FrontendParams
from robotd.frontend.stereo_match import distance_matrix, mutual_matches, ratio_and_cross_check

SHARED = Path(os.environ.get("ROBOTD_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
SOURCES = {
    "kitti-seq1": f"kitti://{SHARED / 'kitti-seq1'}",
    "kitti-raw-0009": f"kitti://{SHARED / 'kitti-raw-0009'}",
    "euroc-v101-micro": f"euroc://{SHARED / 'euroc-v101-micro'}",
    "sim": "sim://?realtime=0&fps=30",
}


def matrix_path(
    a: np.ndarray, b: np.ndarray, binary: bool, max_d: float, ratio: float
) -> tuple[np.ndarray, np.ndarray]:
    """What ``Frontend.visual_motion`` ran before session 29 (the kernel's reference)."""
    D = distance_matrix(a, b, binary)
    ii, jj = np.nonzero(D <= max_d)
    sel, _ = ratio_and_cross_check(ii, jj, D[ii, jj], b.shape[0], ratio, max_d, True)
    ic, ip = ii[sel], jj[sel]
    if D.shape[1] > 1:
        second = np.partition(D, 1, axis=1)[:, 1]
        ok = D[ic, ip] < ratio * second[ic]
        ic, ip = ic[ok], ip[ok]
    return ic, ip


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
    max_d, ratio = p.association.max_dist_binary, p.association.ratio or 0.75
    before, after, sizes, pairs, same = [], [], [], [], True
    for a, b in zip(descs[1:], descs[:-1], strict=True):
        ref = matrix_path(a, b, True, max_d, ratio)
        got = mutual_matches(a, b, True, max_d, ratio, second_in_row=True)
        same &= bool(np.array_equal(ref[0], got[0]) and np.array_equal(ref[1], got[1]))
        before.append(_median_ms(lambda a=a, b=b: matrix_path(a, b, True, max_d, ratio), reps))
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


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sources", default=",".join(SOURCES))
    ap.add_argument("--frames", type=int, default=30, help="frames per source (consecutive pairs: one fewer)")
    ap.add_argument("--reps", type=int, default=7, help="timings per pair of frames (their median is kept)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    from robotd.frontend import stereo_match

    stereo_match.warmup()  # the kernels compiled (or loaded) before any timing
    rows = []
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
    conditions = {
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "load_avg_1min": round(os.getloadavg()[0], 2),
    }
    if args.json:
        print(json.dumps({"benchmark": "matching", "conditions": conditions, "results": rows}))
        return 0 if all(r["same_pairs"] for r in rows) else 1
    print("## Frame-to-frame descriptor matching, ORB (per pair of consecutive frames, ms)\n")
    print(
        "| source | pairs of frames | measurements per frame | matches | matrix path median / p95 "
        "| kernel median / p95 | speed-up (median) | same pairs |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        same = "yes" if r["same_pairs"] else "**no**"
        print(
            f"| {r['source']} | {r['pairs_of_frames']} | {r['measurements_per_frame']:.0f} "
            f"| {r['matches_per_frame']:.0f} | {r['matrix_ms_median']:.2f} / {r['matrix_ms_p95']:.2f} "
            f"| {r['kernel_ms_median']:.2f} / {r['kernel_ms_p95']:.2f} | {r['speedup_median']:.1f}× | {same} |"
        )
    print(f"\nConditions: {conditions}")
    return 0 if all(r["same_pairs"] for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
